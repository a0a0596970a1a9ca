"""`linear_motor`: simulated stand-in for [B1] §VI's coreless linear motor (SPEC §2.2).

True plant (hidden from identification), continuous time, ZOH input::

    m ÿ = u - f_v ẏ - F_fric(ẏ) - F_cog(y)
    F_fric(v) = (f_c + (f_s - f_c) exp(-(v/v_s)²)) tanh(v/ε_v)     (friction='stribeck')
              = f_c sign(v)                                        (friction='sign')
    F_cog(y)  = A1 sin(2π y/p + φ1) + A2 sin(4π y/p + φ2)          (cogging=True)

integrated by fixed-step RK4 with ``substeps`` (≥ 20) steps per sample, in a numba loop.
Noise (``noise.structure``):

- ``output``: the continuous plant, white measurement noise v ~ N(0, std²) on y seen by the
  controller and the data (``y = y_clean + v``).
- ``equation``: the exactly-NARX discrete plant of SPEC §2.2 ([B1] (1))::

      y(t) = 2y(t-1) - y(t-2) + (Ts²/m)(u(t-1) - f_v δy(t-1) - F_fric(δy(t-1)) - F_cog(y(t-1))) + v(t)

  from y(-1) = y(0) - v(0) = 0 (rest); here ``y_clean = y - v`` is the noise-free one-step
  part (earlier noise has entered the dynamics).

Feedback (SPEC §2.2): ``C(s) = K (s/ωz+1)/(s/ωp+1) (s+ωi)/s / ((s/ωl)² + 1.4 s/ωl + 1)``,
ωc = 2π·20, ωz = ωc/3, ωp = 3ωc, ωi = ωc/5, ωl = 10ωc, K with |C P|(jωc) = 1 for
P = 1/(m s² + f_v s), Tustin at Ts.  No computational delay: ``u(k) = C(q)(r(k) - y(k)) +
u_ff(k) + du(k)`` uses the output of the same sample, which depends on u up to k-1 only.

Physics model: [B1] (32), :class:`LinearMotorPhysics`.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:   # annotations only; imported where used (start-up, issue 19)
    import control as ct

import math
from dataclasses import field
from typing import Literal

import numpy as np
from numba import njit

from pipeline.identify.least_squares import solve_scaled as least_squares
from pipeline.params import (
    DAMP_MAX,
    FORCE_MAX,
    FREQ_MAX,
    LENGTH_MAX,
    MASS_MAX,
    NOISE_MAX,
    SPEED_MAX,
    TS_MAX,
    schema,
    spec,
)
from pipeline.systems._statespace import ss_step
from pipeline.systems.arx_bias import _noise_options
from pipeline.systems.base import PhysicsModel, SimResult, System, check_limits, check_signal, loop_signals


@schema
class Noise:
    # equation: exact NARX discrete plant, [B1] (1) | output: continuous plant + measurement noise
    structure: Literal["equation", "output"] = "equation"
    # noise std sigma_v (equation) or sigma_y (output) [m]
    std: float = spec(1e-6, ge=0, lt=NOISE_MAX, unit="m")


@schema
class Params:
    _target_: str
    name: str = "linear_motor"
    # sample time [s] (1 kHz)
    Ts: float = spec(1e-3, gt=0, le=TS_MAX, unit="s")
    m: float = spec(20.0, gt=0, le=MASS_MAX, unit="kg")
    f_v: float = spec(50.0, ge=0, le=DAMP_MAX, unit="N s/m")
    # Coulomb friction [N]
    f_c: float = spec(10.0, ge=0, le=FORCE_MAX, unit="N")
    # static (Stribeck peak) friction [N]; only used with friction=stribeck
    f_s: float = spec(15.0, ge=0, le=FORCE_MAX, unit="N")
    v_s: float = spec(0.01, gt=0, le=SPEED_MAX, unit="m/s")
    # smooth-sign width of tanh(v/eps_v) [m/s]; smaller destabilises RK4 near v = 0
    eps_v: float = spec(1e-3, gt=0, le=SPEED_MAX, unit="m/s")
    # cogging period (magnet pitch) [m]
    p: float = spec(0.025, gt=0, le=LENGTH_MAX, unit="m")
    # cogging amplitude, first harmonic [N]
    A1: float = spec(5.0, ge=-FORCE_MAX, le=FORCE_MAX, unit="N")
    # cogging amplitude, second harmonic [N]
    A2: float = spec(2.0, ge=-FORCE_MAX, le=FORCE_MAX, unit="N")
    # cogging phase, first harmonic [rad]
    phi1: float = spec(0.3, ge=-2 * math.pi, le=2 * math.pi, unit="rad")
    # cogging phase, second harmonic [rad]
    phi2: float = spec(1.1, ge=-2 * math.pi, le=2 * math.pi, unit="rad")
    # include F_cog(y) (position-dependent parasitic, unmodelled by [B1] (32))
    cogging: bool = True
    # stribeck (smooth Stribeck curve) | sign (f_c sign(v): the [B1] (32) form)
    friction: Literal["stribeck", "sign"] = "stribeck"
    noise: Noise = field(default_factory=Noise)
    # RK4 steps per sample for the continuous plant (SPEC: >= 20)
    substeps: int = spec(20, ge=1, le=10_000)
    # feedback crossover [Hz]; C(s) lead-lag+integrator+low-pass, Tustin (SPEC §2.2)
    crossover_hz: float = spec(20.0, gt=0, le=FREQ_MAX, unit="Hz")
    # physics-model input: direct u(t-1) | averaged (u(t-1)+u(t-2))/2 | auto (direct for equation, averaged for
    # output)
    physics_input: Literal["auto", "direct", "averaged"] = "auto"
    # reference limit |r| <= stroke [m]
    stroke: float = spec(0.2, gt=0, le=LENGTH_MAX, unit="m")
    # reference limit |dr/dt| <= v_limit [m/s]
    v_limit: float = spec(0.5, gt=0, le=SPEED_MAX, unit="m/s")


# --------------------------------------------------------------------------- controller
def lead_lag_controller(m: float, f_v: float, Ts: float, crossover_hz: float = 20.0
                        ) -> tuple[ct.StateSpace, ct.StateSpace]:
    """The SPEC §2.2 feedback controller, continuous and Tustin-discretised.

    Parameters
    ----------
    m : float
        Nominal mass [kg] of the rigid-body model P = 1/(m s² + f_v s).
    f_v : float
        Nominal viscous friction [N s/m].
    Ts : float
        Sample time [s].
    crossover_hz : float
        Crossover frequency fc [Hz]; ωc = 2π fc.

    Returns
    -------
    (C_s, C_z) : StateSpace
        C(s) [N/m] and its Tustin discretisation (dt = Ts).
    """
    import control as ct  # lazy: saves 1.9 s of start-up (python-control)
    wc = 2.0 * math.pi * float(crossover_hz)
    wz, wp, wi, wl = wc / 3.0, 3.0 * wc, wc / 5.0, 10.0 * wc
    s = ct.tf("s")
    C0 = (s / wz + 1) / (s / wp + 1) * (s + wi) / s / ((s / wl) ** 2 + 1.4 * s / wl + 1)
    P = 1 / (m * s ** 2 + f_v * s)
    K = 1.0 / abs(complex((C0 * P)(1j * wc)))                    # |C P|(jωc) = 1
    Cs = ct.ss(K * C0)
    return Cs, ct.sample_system(Cs, Ts, method="tustin")


# --------------------------------------------------------------------------- numba kernel
@njit(cache=True)
def _friction(vel, f_c, f_s, v_s, eps_v, mode):
    if mode == 0:                                             # Stribeck, smooth sign
        return (f_c + (f_s - f_c) * math.exp(-(vel / v_s) ** 2)) * math.tanh(vel / eps_v)
    if vel > 0.0:                                             # Coulomb sign
        return f_c
    if vel < 0.0:
        return -f_c
    return 0.0


@njit(cache=True)
def _cogging(pos, p, A1, A2, phi1, phi2, on):
    if not on:
        return 0.0
    w = 2.0 * math.pi * pos / p
    return A1 * math.sin(w + phi1) + A2 * math.sin(2.0 * w + phi2)


@njit(cache=True)
def _closed_loop(r, u_ff, du, v, Ac, Bc, Cc, Dc, Ts, par, fric_mode, cog_on, equation, substeps):
    """Per-sample loop: measure y(k), controller (no delay), u(k), then advance the plant.

    par = [m, f_v, f_c, f_s, v_s, eps_v, p, A1, A2, phi1, phi2]."""
    m, f_v, f_c, f_s, v_s, eps_v, p, A1, A2, phi1, phi2 = (
        par[0], par[1], par[2], par[3], par[4], par[5], par[6], par[7], par[8], par[9], par[10])
    N = r.shape[0]
    nc = Ac.shape[0]
    y = np.empty(N)
    y_clean = np.empty(N)
    u = np.empty(N)
    u_fb = np.empty(N)
    xc = np.zeros(nc)
    xn = np.zeros(nc)
    pos = 0.0
    vel = 0.0
    h = Ts / substeps
    y1 = 0.0                       # equation plant: y(k-1), y(k-2)
    y2 = 0.0
    for k in range(N):
        if equation:
            if k == 0:
                yc = 0.0                                          # at rest at t = 0
            else:
                dy = (y1 - y2) / Ts                               # δy(k-1)
                yc = 2.0 * y1 - y2 + Ts * Ts / m * (
                    u[k - 1] - f_v * dy - _friction(dy, f_c, f_s, v_s, eps_v, fric_mode)
                    - _cogging(y1, p, A1, A2, phi1, phi2, cog_on))
            y_clean[k] = yc
            y[k] = yc + v[k]
            y2 = y1
            y1 = y[k]
        else:
            y_clean[k] = pos
            y[k] = pos + v[k]
        # controller, no computational delay: u_fb(k) = Cc xc(k) + Dc e(k)
        acc = ss_step(Ac, Bc, Cc, Dc, xc, xn, r[k] - y[k])
        u_fb[k] = acc
        uk = acc + u_ff[k] + du[k]
        u[k] = uk
        if not equation:
            # RK4 over [k Ts, (k+1) Ts) with u(k) held (ZOH)
            for _ in range(substeps):
                k1p = vel
                k1v = (uk - f_v * vel - _friction(vel, f_c, f_s, v_s, eps_v, fric_mode)
                       - _cogging(pos, p, A1, A2, phi1, phi2, cog_on)) / m
                p2 = pos + 0.5 * h * k1p
                v2 = vel + 0.5 * h * k1v
                k2p = v2
                k2v = (uk - f_v * v2 - _friction(v2, f_c, f_s, v_s, eps_v, fric_mode)
                       - _cogging(p2, p, A1, A2, phi1, phi2, cog_on)) / m
                p3 = pos + 0.5 * h * k2p
                v3 = vel + 0.5 * h * k2v
                k3p = v3
                k3v = (uk - f_v * v3 - _friction(v3, f_c, f_s, v_s, eps_v, fric_mode)
                       - _cogging(p3, p, A1, A2, phi1, phi2, cog_on)) / m
                p4 = pos + h * k3p
                v4 = vel + h * k3v
                k4p = v4
                k4v = (uk - f_v * v4 - _friction(v4, f_c, f_s, v_s, eps_v, fric_mode)
                       - _cogging(p4, p, A1, A2, phi1, phi2, cog_on)) / m
                pos += h / 6.0 * (k1p + 2.0 * k2p + 2.0 * k3p + k4p)
                vel += h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return y, y_clean, u, u_fb


def _sign(x):
    """sign for numpy arrays and torch tensors alike."""
    return x.sign() if hasattr(x, "sign") else np.sign(x)


# --------------------------------------------------------------------------- physics model
class LinearMotorPhysics(PhysicsModel):
    """[B1] (32): ``m δ²y(t) = -f_v δy(t-1) - f_c sign(δy(t-1)) + w(t-1)`` (SPEC §2.2).

    δ is the backward difference, ``δ²y(t) = (y(t) - 2y(t-1) + y(t-2))/Ts²``,
    ``δy(t-1) = (y(t-1) - y(t-2))/Ts``.  The model input w is

    - ``u(t-1)`` (``averaged_input=False``; n_b = 1): exact for the ``equation`` plant;
    - ``ū(t-1) = (u(t-1) + u(t-2))/2`` (``averaged_input=True``; n_b = 2): for the continuous
      ZOH plant, whose sampled mass has a zero at z = -1 (SPEC §2.2 pitfall: u(t-1) alone
      biases the forward mass estimate ~2×).

    **Forward form (θ, consistent LS).**  θ = [1/m, f_v/m, f_c/m] ("inv_m", "fv_over_m",
    "fc_over_m"), linear in the one-step prediction of y::

        ŷ(t) = offset(φ) + features(φ) θ,   offset = 2y(t-1) - y(t-2),
        features = Ts² [w(t-1), -δy(t-1), -sign(δy(t-1))]

    with φ(t) = [y(t-1), y(t-2), u(t-1)(, u(t-2))] ([B1] (10), SPEC §3 item 3).  The forward
    LS target is ``z = y(t) - offset`` [m] (:meth:`regressor`).  θ[0] = 1/m is the input gain ψ
    of [B1] (26)/(29).

    **Inverse form (θ', direct inverse identification, biased under noise).**
    θ' = [m, f_v, f_c] = :meth:`inverse_theta` (θ)::

        w(k) = θ'ᵀ [δ²y(k+1), δy(k), sign(δy(k))]

    with φ'(k) = [y(k+1), y(k), y(k-1)] (rows k = 0..N-2); the target is the model input
    w(k) = u(k) or ū(k) (:meth:`model_input`), *not* u(k) in averaged mode: a model that
    predicts u(k) = 2ū(k) - u(k-1) has a pole at z = -1.  Turn a predicted w into an applied
    input with :meth:`applied_input` (identity, or ``u_ff(t) = (w(t) + w(t+1))/2``).

    For the analytically invertible PGNN ([B1] (26)-(27)) in averaged mode, keep *both*
    u(t-1) and u(t-2) out of the NN input (they enter only through ū), solve for ū(t-1) and
    apply :meth:`applied_input`; an NN that sees u(t-2) brings the z = -1 pole back.

    **Feedforward** (:meth:`feedforward`): w(k) = m δ²r(k+1) + f_v δr(k) + f_c sign(δr(k)),
    then :meth:`applied_input` (bounded, no Nyquist oscillation).
    """

    physics_law = "linear_motor"   # exported by pipeline.export.law.from_linear_motor_physics

    param_names = ("inv_m", "fv_over_m", "fc_over_m")
    #: index in θ of the input gain ψ = 1/m ([B1] (26), omitted from the (29) regulariser)
    input_gain_index = 0
    n_a = 2
    n_k = 0

    def __init__(self, Ts: float = 1e-3, averaged_input: bool = False):
        if not (np.isfinite(Ts) and Ts > 0):
            raise ValueError(f"Ts must be positive, got {Ts!r}")
        self.Ts = float(Ts)
        self.averaged_input = bool(averaged_input)
        self.n_b = 2 if self.averaged_input else 1

    # ----- conversions
    @staticmethod
    def theta_from_physical(m: float, f_v: float, f_c: float) -> np.ndarray:
        """θ = [1/m, f_v/m, f_c/m] from m [kg], f_v [N s/m], f_c [N]."""
        if not m > 0:
            raise ValueError(f"mass must be positive, got m={m!r}")
        return np.array([1.0 / m, f_v / m, f_c / m])

    def _check_theta(self, theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape != (3,) or not np.all(np.isfinite(theta)):
            raise ValueError(f"θ must be 3 finite numbers {self.param_names}, got {theta}")
        return theta

    def physical(self, theta) -> dict[str, float]:
        """{m [kg], f_v [N s/m], f_c [N]} from θ (m = inf, f's = nan if θ[0] = 0)."""
        t = self._check_theta(theta)
        if t[0] == 0.0:
            return {"m": math.inf, "f_v": math.nan, "f_c": math.nan}
        return {"m": 1.0 / t[0], "f_v": t[1] / t[0], "f_c": t[2] / t[0]}

    def inverse_theta(self, theta) -> np.ndarray:
        """θ' = [m, f_v, f_c] of the inverse form, from forward θ."""
        t = self._check_theta(theta)
        if not t[0] > 0.0:
            raise ValueError(f"θ[0] = 1/m = {t[0]} is not positive: no physical mass, the "
                             "model cannot be inverted; check the identification")
        return np.array([1.0, t[1], t[2]]) / t[0]

    # ----- input convention
    def model_input(self, u) -> np.ndarray:
        """w(k) = u(k), or ū(k) = (u(k) + u(k-1))/2 with u(-1) = 0 (averaged_input)."""
        u = check_signal("u", u)
        if not self.averaged_input:
            return u
        return 0.5 * (u + np.concatenate([[0.0], u[:-1]]))

    def applied_input(self, w, w_end: float | None = None) -> np.ndarray:
        """Input to apply for a model input w (SPEC §2.2): identity, or in averaged mode
        ``u_ff(t) = (w(t) + w(t+1))/2`` (one sample of preview; the recursion u(t) = 2w(t) - u(t-1)
        would put a pole at z = -1).  w(N) = ``w_end``: the law's next sample on the reference held
        after its end, as a real-time loop computes it (``pipeline.export``); default w(N-1)."""
        w = check_signal("w", w)
        if not self.averaged_input:
            return w
        end = w[-1:] if w_end is None else np.array([float(w_end)])
        return 0.5 * (w + np.concatenate([w[1:], end]))

    # ----- forward model
    def phi(self, y, u) -> np.ndarray:
        """φ(t) = [y(t-1), y(t-2), u(t-1)(, u(t-2))], [N, 2+n_b], zero past."""
        y = check_signal("y", y)
        u = check_signal("u", u, y.shape[0])
        N = y.shape[0]
        cols = [np.concatenate([np.zeros(l), y[:N - l]])[:N] for l in (1, 2)]
        cols += [np.concatenate([np.zeros(l), u[:N - l]])[:N] for l in range(1, self.n_b + 1)]
        return np.stack(cols, axis=1)

    def features(self, phi):
        """Ts² [w(t-1), -δy(t-1), -sign(δy(t-1))] from φ (numpy or torch, [..., 2+n_b])."""
        Ts = self.Ts
        w = 0.5 * (phi[..., 2] + phi[..., 3]) if self.averaged_input else phi[..., 2]
        dy = (phi[..., 0] - phi[..., 1]) / Ts
        cols = [Ts * Ts * w, -Ts * Ts * dy, -Ts * Ts * _sign(dy)]
        if hasattr(phi, "sign") and not isinstance(phi, np.ndarray):   # torch tensor
            import torch  # lazy: saves 2.0 s of start-up (torch)
            return torch.stack(cols, dim=-1)
        return np.stack(cols, axis=-1)

    def offset(self, phi):
        """2y(t-1) - y(t-2) [m]: the part of ŷ(t) that does not depend on θ."""
        return 2.0 * phi[..., 0] - phi[..., 1]

    def predict(self, theta, phi):
        """One-step prediction ŷ(t) [m] = offset(φ) + features(φ) θ (numpy or torch)."""
        return self.offset(phi) + self.features(phi) @ theta

    def regressor(self, y, u, r=None):
        """(Φ [N, 3], z [N]): forward LS ``z ≈ Φ θ`` with z = y(t) - 2y(t-1) + y(t-2) [m]
        (rows from t = 0, zero past)."""
        phi = self.phi(y, u)
        return self.features(phi), check_signal("y", y) - self.offset(phi)

    def fit(self, y, u) -> np.ndarray:
        """Forward least-squares θ* ([B1] (7) for this LIP model)."""
        return least_squares(*self.regressor(y, u))

    # ----- inverse model
    def inverse_phi(self, y, u=None) -> np.ndarray:
        """φ'(k) = [y(k+1), y(k), y(k-1)], rows k = 0..N-2 (y(-1) = 0)."""
        y = check_signal("y", y)
        return np.stack([y[1:], y[:-1], np.concatenate([[0.0], y[:-2]])], axis=1)

    def inverse_features(self, phi_inv):
        """[δ²y(k+1), δy(k), sign(δy(k))] (numpy or torch): w(k) = inverse_features θ'."""
        Ts = self.Ts
        d2 = (phi_inv[..., 0] - 2.0 * phi_inv[..., 1] + phi_inv[..., 2]) / Ts ** 2
        dy = (phi_inv[..., 1] - phi_inv[..., 2]) / Ts
        cols = [d2, dy, _sign(dy)]
        if hasattr(phi_inv, "sign") and not isinstance(phi_inv, np.ndarray):
            import torch  # lazy: saves 2.0 s of start-up (torch)
            return torch.stack(cols, dim=-1)
        return np.stack(cols, axis=-1)

    def inverse_regressor(self, y, u):
        """(Φ' [N-1, 3], z' = w(k) [N-1]) for the direct inverse LS; its θ' = [m, f_v, f_c]."""
        y = check_signal("y", y)
        w = self.model_input(check_signal("u", u, y.shape[0]))
        return self.inverse_features(self.inverse_phi(y)), w[:-1]

    def feedforward(self, theta, r) -> np.ndarray:
        """Physics feedforward [N]: the analytic inverse of [B1] (32) (SPEC §6).

        w(k) = m δ²r(k+1) + f_v δr(k) + f_c sign(δr(k)) with r(-1) = 0 and r held after the
        end, then :meth:`applied_input` (with w(N) on the held reference)."""
        m, f_v, f_c = self.inverse_theta(theta)
        r = check_signal("r", r)
        rp = np.concatenate([[0.0], r, r[-1:], r[-1:]])            # r(-1) .. r(N+1)
        d2 = (rp[2:] - 2.0 * rp[1:-1] + rp[:-2]) / self.Ts ** 2    # δ²r(k+1), k = 0..N
        dr = (rp[1:-1] - rp[:-2]) / self.Ts                         # δr(k)
        w = m * d2 + f_v * dr + f_c * np.sign(dr)                   # w(0) .. w(N)
        return self.applied_input(w[:-1], w_end=w[-1])


# --------------------------------------------------------------------------- the plant
class LinearMotor(System):
    """Simulated coreless linear motor in closed loop (SPEC §2.2, [B1] §VI).

    Parameters
    ----------
    Ts : float
        Sample time [s].
    m, f_v : float
        Mass [kg], viscous friction [N s/m].
    f_c, f_s, v_s, eps_v : float
        Coulomb [N] and static [N] friction, Stribeck velocity [m/s], smooth-sign width [m/s].
    p, A1, A2, phi1, phi2 : float
        Cogging period [m], amplitudes [N], phases [rad].
    cogging : bool
        Include F_cog.
    friction : {'stribeck', 'sign'}
        Friction law (``sign``: f_c sign(v), the [B1] (32) form).
    noise : mapping
        ``{structure: 'equation'|'output', std: σ [m]}``.
    substeps : int
        RK4 steps per sample for the continuous plant (≥ 20, SPEC §2.2).
    crossover_hz : float
        Feedback bandwidth [Hz].
    physics_input : {'auto', 'direct', 'averaged'}
        Input of the physics model: u(t-1) ('direct') or ū(t-1) ('averaged'); 'auto' =
        direct for the equation plant, averaged for the continuous one.
    stroke, v_limit : float
        Reference limits |r| ≤ stroke [m], |δr| ≤ v_limit [m/s] (:meth:`check_reference`).
    """

    name = "linear_motor"

    def __init__(self, Ts: float = Params.Ts, m: float = Params.m, f_v: float = Params.f_v, f_c: float = Params.f_c,
                 f_s: float = Params.f_s, v_s: float = Params.v_s, eps_v: float = Params.eps_v, p: float = Params.p,
                 A1: float = Params.A1, A2: float = Params.A2, phi1: float = Params.phi1, phi2: float = Params.phi2,
                 cogging: bool = Params.cogging, friction: str = Params.friction, noise=None,
                 substeps: int = Params.substeps, crossover_hz: float = Params.crossover_hz,
                 physics_input: str = Params.physics_input,
                 stroke: float = Params.stroke, v_limit: float = Params.v_limit, name: str = Params.name):
        vals = dict(Ts=Ts, m=m, v_s=v_s, eps_v=eps_v, p=p, crossover_hz=crossover_hz,
                    stroke=stroke, v_limit=v_limit)
        for k, x in vals.items():
            if not (np.isfinite(float(x)) and float(x) > 0):
                raise ValueError(f"{k} must be positive and finite, got {x!r}")
        for k, x in dict(f_v=f_v, f_c=f_c, f_s=f_s, A1=A1, A2=A2, phi1=phi1, phi2=phi2).items():
            if not np.isfinite(float(x)):
                raise ValueError(f"{k} must be finite, got {x!r}")
        if friction not in ("stribeck", "sign"):
            raise ValueError(f"friction={friction!r}; use 'stribeck' or 'sign'")
        if int(substeps) < 1:
            raise ValueError(f"substeps must be >= 1 (SPEC: >= 20), got {substeps!r}")
        if physics_input not in ("auto", "direct", "averaged"):
            raise ValueError(f"physics_input={physics_input!r}; use 'auto', 'direct' or 'averaged'")
        self.Ts, self.m, self.f_v, self.f_c, self.f_s = float(Ts), float(m), float(f_v), \
            float(f_c), float(f_s)
        self.v_s, self.eps_v, self.p = float(v_s), float(eps_v), float(p)
        self.A1, self.A2, self.phi1, self.phi2 = float(A1), float(A2), float(phi1), float(phi2)
        self.cogging, self.friction = bool(cogging), friction
        self.structure, self.std = _noise_options(noise, ("equation", "output"),
                                                  {"structure": "equation", "std": 1e-6})
        self.substeps, self.crossover_hz = int(substeps), float(crossover_hz)
        self.stroke, self.v_limit = float(stroke), float(v_limit)
        self.name = name
        averaged = physics_input == "averaged" or (physics_input == "auto"
                                                   and self.structure == "output")
        self._physics = LinearMotorPhysics(self.Ts, averaged_input=averaged)
        self._Cs, self._Cz = lead_lag_controller(self.m, self.f_v, self.Ts, self.crossover_hz)
        A, B, C, D = (np.asarray(x, dtype=np.float64) for x in
                      (self._Cz.A, self._Cz.B, self._Cz.C, self._Cz.D))
        self._ctrl = (np.ascontiguousarray(A), np.ascontiguousarray(B[:, 0]),
                      np.ascontiguousarray(C[0, :]), float(D[0, 0]))

    # ----- interface
    @property
    def physics(self) -> LinearMotorPhysics:
        return self._physics

    def nominal_theta(self) -> np.ndarray:
        """θ of :class:`LinearMotorPhysics` at the simulator's m, f_v, f_c (a datasheet guess;
        exact for the equation plant with friction='sign' and cogging off)."""
        return LinearMotorPhysics.theta_from_physical(self.m, self.f_v, self.f_c)

    def controller(self) -> ct.TransferFunction:
        """C(z): the Tustin-discretised lead-lag + integrator + low-pass [N/m], dt = Ts."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        return ct.tf(self._Cz)

    def linear_plant(self) -> ct.StateSpace:
        """ZOH discretisation of the nominal rigid body P = 1/(m s² + f_v s) [m/N]."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        return ct.sample_system(ct.ss(ct.tf([1.0], [self.m, self.f_v, 0.0])), self.Ts, "zoh")

    def sensitivity(self) -> ct.StateSpace:
        """S = 1/(1 + P C) of the nominal discrete loop."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        return ct.feedback(ct.ss([], [], [], [[1.0]], dt=self.Ts), self.linear_plant() * self._Cz)

    def learning_model(self):
        """The ILC model: the process sensitivity P S of the rigid-mass part from u_ff to y."""
        return self.process_sensitivity()

    def process_sensitivity(self) -> ct.StateSpace:
        """PS = P/(1 + P C) of the nominal discrete loop [m/N] (from u_ff to y)."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        return ct.feedback(self.linear_plant(), self._Cz)

    def noise(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """v ~ N(0, std²) [m], length n: measurement noise ('output') or the NARX equation
        noise ('equation')."""
        return self.std * rng.standard_normal(int(n))

    def check_reference(self, r) -> None:
        """Raise ValueError if |r| > stroke or |δr| > v_limit (or NaN / not 1-D)."""
        check_limits(r, self.Ts, self.stroke, self.v_limit, "stroke")

    def simulate(self, r, u_ff=None, du=None, v=None) -> SimResult:
        """Closed loop ``u(k) = C(q)(r(k) - y(k)) + u_ff(k) + du(k)``, y(k) = y_clean(k) + v(k),
        no computational delay, ZOH on u (SPEC §0, §2.2); starts at rest at 0."""
        r, u_ff, du, v = loop_signals(r, u_ff, du, v)
        self.check_reference(r)
        n = r.shape[0]
        par = np.array([self.m, self.f_v, self.f_c, self.f_s, self.v_s, self.eps_v, self.p,
                        self.A1, self.A2, self.phi1, self.phi2])
        Ac, Bc, Cc, Dc = self._ctrl
        y, y_clean, u, u_fb = _closed_loop(
            r, u_ff, du, v, Ac, Bc, Cc, Dc, self.Ts, par,
            0 if self.friction == "stribeck" else 1, self.cogging,
            self.structure == "equation", self.substeps)
        if not np.all(np.isfinite(y)):
            raise FloatingPointError("linear_motor simulation diverged (non-finite y); check the "
                                     "feedforward/excitation magnitudes and the parameters")
        return SimResult(t=np.arange(n) * self.Ts, r=r, u=u, y=y, u_ff=u_ff, u_fb=u_fb,
                         y_clean=y_clean, v=v)

    def friction_force(self, vel) -> np.ndarray:
        """F_fric(v) [N] of the true plant (numpy, vectorised)."""
        vel = np.asarray(vel, dtype=np.float64)
        if self.friction == "stribeck":
            return (self.f_c + (self.f_s - self.f_c) * np.exp(-(vel / self.v_s) ** 2)) * \
                np.tanh(vel / self.eps_v)
        return self.f_c * np.sign(vel)

    def cogging_force(self, pos) -> np.ndarray:
        """F_cog(y) [N] of the true plant (zero if cogging is off)."""
        pos = np.asarray(pos, dtype=np.float64)
        if not self.cogging:
            return np.zeros_like(pos)
        w = 2.0 * np.pi * pos / self.p
        return self.A1 * np.sin(w + self.phi1) + self.A2 * np.sin(2.0 * w + self.phi2)

    def exact_inverse(self, r) -> np.ndarray:
        """The input that makes the equation plant track r exactly (v = 0, r(0) = 0):
        u(k) = m δ²r(k+1) + f_v δr(k) + F_fric(δr(k)) + F_cog(r(k)), r(N) = r(N-1).
        The continuous plant has none: use data.source=ilc."""
        if self.structure != "equation":
            raise NotImplementedError(
                "the continuous linear motor (noise.structure=output) has no exact inverse; "
                "use the ILC data source, or noise.structure=equation")
        r = check_signal("r", r)
        self.check_reference(r)
        rp = np.concatenate([[0.0], r, r[-1:]])
        d2 = (rp[2:] - 2.0 * rp[1:-1] + rp[:-2]) / self.Ts ** 2
        dr = (rp[1:-1] - rp[:-2]) / self.Ts
        return self.m * d2 + self.f_v * dr + self.friction_force(dr) + self.cogging_force(r)
