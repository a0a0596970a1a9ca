"""The integrator check of a measured system's replay (issue 20, SPEC §8 X1).

Every model is replayed by one discrete integrator, the rigid body's exact-ZOH step on the averaged
input ([B1] (10) with w = ū, :mod:`pipeline.identify.measured_loop`).  A physics model is also a
continuous-time model,

    M q̈ = u(t) - Σ_j p_j T_j(q, q̇),       u(t) = u(k) on [k Ts, (k+1) Ts)  (zero-order hold),

(with an actuator lag τ, ``pipeline.systems.actuator_lag``, the force is F with τ Ḟ + F = u(t), a third
state integrated alongside), so how far the one-step integrator is from it can be *measured*:
:func:`replay_rk4` runs the same closed loop (controller at the samples, as in the kernel) with
``n_sub`` classical Runge-Kutta sub-steps per sample. As n_sub doubles the scores settle (a sign()
Coulomb term limits the order near velocity reversals); the settled value minus the one-step replay's is
the integrator's own error. Started from the recorded state like the kernel: the first ``n_init``
samples are the record's, the state at n_init - 1 the one the one-step replay implies (exact for a
mass).
"""
from __future__ import annotations

import numba
import numpy as np

from pipeline.identify.measured_loop import ctrl_law
from pipeline.systems.force_terms import term


@numba.njit(cache=True)
def _accel(q, v, u, th, codes, tp):
    a = th[0] * u
    for j in range(codes.size):
        T, _, _ = term(codes[j], tp[j], q, v)
        a -= th[1 + j] * T
    return a


@numba.njit(cache=True)
def _rk4_loop(r, d, yrec, urec, n0, th, codes, tp, Ts, n_sub, br, by, ca, gtau, vsat, D, lag):
    N = r.size
    y = np.empty(N)
    tau = np.empty(N)
    cc = np.zeros(N)
    vv = np.zeros(N)
    h = Ts / n_sub
    # the state at n0 - 1 the one-step replay implies (exact for a mass under ZOH): q = y(n0-1),
    # q̇ = (y(n0-1) - y(n0-2))/Ts + Ts/2 q̈(n0-2), so both start from the same motion
    q = yrec[n0 - 1]
    v2 = (yrec[n0 - 2] - yrec[n0 - 3]) / Ts
    v = (yrec[n0 - 1] - yrec[n0 - 2]) / Ts + 0.5 * Ts * _accel(yrec[n0 - 2], v2, urec[n0 - 2], th, codes, tp)
    F = 0.0               # the lagged force at n0 - 1: the exact sampled lag of the recorded u from rest
    if lag > 0.0:
        a = np.exp(-Ts / lag)
        for j in range(n0 - 1):
            F = a * F + (1.0 - a) * urec[j]
    for k in range(N):
        if k < n0:   # the record, as in the one-step kernel (pipeline.identify.measured_loop._loop)
            y[k] = yrec[k]
            tau[k] = urec[k]
            uk = urec[k]
            if k - D >= 0:
                cc[k - D] = urec[k] / gtau - d[k]
                vv[k - D] = cc[k - D]
            if k == n0 - 1:
                for j in range(max(n0 - D, 0), n0):
                    vv[j] = ctrl_law(j, r, y, yrec[0], vv, br, by, ca)
                    cc[j] = min(max(vv[j], -vsat), vsat)
        else:
            y[k] = q
            vv[k] = ctrl_law(k, r, y, yrec[0], vv, br, by, ca)
            cc[k] = min(max(vv[k], -vsat), vsat)
            uk = gtau * (cc[k - D] + d[k])
            tau[k] = uk
        if k >= n0 - 1 and lag > 0.0:   # [k, k+1] with u(k) held: q, q̇ and the lagged force F
            for _ in range(n_sub):
                k1q, k1v, k1f = v, _accel(q, v, F, th, codes, tp), (uk - F) / lag
                q2, v2, f2 = q + 0.5 * h * k1q, v + 0.5 * h * k1v, F + 0.5 * h * k1f
                k2q, k2v, k2f = v2, _accel(q2, v2, f2, th, codes, tp), (uk - f2) / lag
                q3, v3, f3 = q + 0.5 * h * k2q, v + 0.5 * h * k2v, F + 0.5 * h * k2f
                k3q, k3v, k3f = v3, _accel(q3, v3, f3, th, codes, tp), (uk - f3) / lag
                q4, v4, f4 = q + h * k3q, v + h * k3v, F + h * k3f
                k4q, k4v, k4f = v4, _accel(q4, v4, f4, th, codes, tp), (uk - f4) / lag
                q += h / 6.0 * (k1q + 2 * k2q + 2 * k3q + k4q)
                v += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
                F += h / 6.0 * (k1f + 2 * k2f + 2 * k3f + k4f)
        elif k >= n0 - 1:   # integrate [k, k+1] with u(k) held
            for _ in range(n_sub):
                k1q, k1v = v, _accel(q, v, uk, th, codes, tp)
                k2q, k2v = v + 0.5 * h * k1v, _accel(q + 0.5 * h * k1q, v + 0.5 * h * k1v, uk, th, codes, tp)
                k3q, k3v = v + 0.5 * h * k2v, _accel(q + 0.5 * h * k2q, v + 0.5 * h * k2v, uk, th, codes, tp)
                k4q, k4v = v + h * k3v, _accel(q + h * k3q, v + h * k3v, uk, th, codes, tp)
                q += h / 6.0 * (k1q + 2 * k2q + 2 * k3q + k4q)
                v += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return y, tau


def replay_rk4(physics, theta, ctrl, sig, n_sub: int):
    """(ŷ [m], τ̂ [N]) of the continuous-time physics (θ = [1/M, p_j/M] of ``physics``, a
    ``RigidBodyPhysics``) in the recorded loop, data timing, ``n_sub`` RK4 sub-steps per sample;
    ``sig`` a :class:`~pipeline.identify.measured_loop.LoopSignals` started from the record."""
    n0 = int(sig.n_init)
    need = max(4, ctrl.b_y.size, ctrl.b_r.size, ctrl.a.size, int(ctrl.delay) + 1)
    if n0 < need:
        raise ValueError(f"replay_rk4 starts from the recorded state: n_init={n0} must be >= {need}")
    if int(n_sub) < 1:
        raise ValueError(f"n_sub={n_sub} must be >= 1")
    codes, tp = physics.kernel_terms()
    lag = getattr(physics, "lag", None)
    f = lambda x: np.ascontiguousarray(x, dtype=np.float64)  # noqa: E731
    return _rk4_loop(f(sig.r), f(sig.d), f(sig.y_rec), f(sig.u_rec), n0, f(theta), codes, tp, float(physics.Ts),
                     int(n_sub), f(ctrl.b_r), f(ctrl.b_y), f(ctrl.a), float(ctrl.gtau), float(ctrl.v_sat),
                     int(ctrl.delay), 0.0 if lag is None else float(lag.tau))


#: sub-step counts of the integrator check
SUBSTEPS = (1, 4, 16, 64)
