"""`rot_trans_nmp`: translating-rotating mass of [B2] §VI (SPEC §2.3), nonminimum phase.

Actuation and sensing sit on opposite sides of the centre of mass.  [B2] (27) is realised in
its physical coordinates: translation x and rotation ϑ of a mass m (inertia J) driven by
ξ = u - c sin(2π y/l_m) ([B2] (28), cogging "unknown" to the user)::

    m ẍ = ξ - f_v ẋ
    J ϑ̈ = l_y ξ - 2 l_x k ϑ - 2 l_x d ϑ̇
    y   = x - l_y ϑ

whose transfer ξ -> y is ``1/(m s² + f_v s) - l_y²/(J s² + 2 l_x d s + 2 l_x k)``, i.e. (27)
exactly (the test checks the coefficients), with a zero at s ≈ +80.9 rad/s.  State
[x, ẋ, ϑ, ϑ̇], integrated by RK4 with ``substeps`` (≥ 20) steps per sample, ξ recomputed from y
inside each stage, ZOH on u, in a numba loop.

Feedback C(s) = 5e3 (s + 4π)/(s + 20π), ZOH-discretised at Ts = 0.01 s; no computational
delay: ``u(k) = C(q)(r(k) - y(k) - v(k)) + u_ff(k) + du(k)``.  Measurement noise
v ~ N(0, (1e-6)²) m on the data and the controller.

Physics model: the ZOH-discretised linear part as an ARX (n_a = n_b = 4, n_k = 0,
:class:`RotTransPhysics`); its B has a zero at z ≈ 2.25, so its inverse is unstable and
:meth:`RotTransPhysics.feedforward` raises (use FHOFC or ILC); :func:`zpetc_feedforward` is a
documented stable approximate inverse for comparison.
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

from pipeline.params import (
    DAMP_MAX,
    FORCE_MAX,
    FREQ_MAX,
    LENGTH_MAX,
    MASS_MAX,
    NOISE_MAX,
    SPEED_MAX,
    STIFF_MAX,
    TS_MAX,
    schema,
    spec,
)
from pipeline.systems._statespace import ss_step
from pipeline.systems.arx_bias import ARXPhysics, _noise_options
from pipeline.systems.base import SimResult, System, check_limits, check_signal, lfilter, loop_signals


@schema
class Noise:
    # measurement noise on y (data and controller), [B2] §VI
    structure: Literal["output"] = "output"
    # noise std [m]; 0 switches it off
    std: float = spec(1e-6, ge=0, lt=NOISE_MAX, unit="m")


@schema
class Params:
    _target_: str
    name: str = "rot_trans_nmp"
    # sample time [s] (100 Hz)
    Ts: float = spec(0.01, gt=0, le=TS_MAX, unit="s")
    # mass [kg], [B2] Table I
    m: float = spec(20.0, gt=0, le=MASS_MAX, unit="kg")
    # half width [m]
    l_x: float = spec(1.0, gt=0, le=LENGTH_MAX, unit="m")
    # half height [m] (actuator/sensor offset from the centre of mass)
    l_y: float = spec(1.0, ge=-LENGTH_MAX, le=LENGTH_MAX, unit="m")
    # inertia [kg m^2] = 40/3
    J: float = spec(40.0 / 3.0, gt=0, le=MASS_MAX * LENGTH_MAX**2, unit="kg m^2")
    f_v: float = spec(50.0, ge=0, le=DAMP_MAX, unit="kg/s")
    # rotational spring [kg/s^2] = 25e3/3
    k: float = spec(25e3 / 3.0, ge=0, le=STIFF_MAX, unit="kg/s^2")
    # rotational damper [kg/s] = 575/3
    d: float = spec(575.0 / 3.0, ge=0, le=DAMP_MAX, unit="kg/s")
    # magnet pole pitch [m], [B2] (28)
    l_m: float = spec(0.05, gt=0, le=LENGTH_MAX, unit="m")
    # cogging magnitude [N], [B2] (28); 0 = linear plant
    c: float = spec(1.0, ge=-FORCE_MAX, le=FORCE_MAX, unit="N")
    # C(s) = gain (s + zero)/(s + pole) [N/m], [B2] (29), ZOH at Ts
    controller_gain: float = spec(5000.0, gt=0, le=STIFF_MAX, unit="N/m")
    # [rad/s] = 4 pi
    controller_zero: float = spec(4.0 * math.pi, gt=0, le=FREQ_MAX, unit="rad/s")
    # [rad/s] = 20 pi
    controller_pole: float = spec(20.0 * math.pi, gt=0, le=FREQ_MAX, unit="rad/s")
    noise: Noise = field(default_factory=Noise)
    # RK4 steps per sample (SPEC: >= 20)
    substeps: int = spec(20, ge=1, le=10_000)
    # reference limit |r| <= r_limit [m]
    r_limit: float = spec(0.5, gt=0, le=LENGTH_MAX, unit="m")
    # reference limit |dr/dt| <= v_limit [m/s]
    v_limit: float = spec(1.0, gt=0, le=SPEED_MAX, unit="m/s")


# --------------------------------------------------------------------------- numba kernel
@njit(cache=True)
def _rhs(x, u, par):
    """d/dt [x, ẋ, ϑ, ϑ̇]; par = [m, l_x, l_y, J, f_v, k, d, l_m, c]."""
    m, l_x, l_y, J, f_v, k, d, l_m, c = (par[0], par[1], par[2], par[3], par[4], par[5],
                                         par[6], par[7], par[8])
    y = x[0] - l_y * x[2]
    xi = u - c * math.sin(2.0 * math.pi * y / l_m)            # [B2] (28)
    return (x[1], (xi - f_v * x[1]) / m, x[3],
            (l_y * xi - 2.0 * l_x * k * x[2] - 2.0 * l_x * d * x[3]) / J)


@njit(cache=True)
def _closed_loop(r, u_ff, du, v, Ac, Bc, Cc, Dc, Ts, par, substeps):
    N = r.shape[0]
    nc = Ac.shape[0]
    y = np.empty(N)
    y_clean = np.empty(N)
    u = np.empty(N)
    u_fb = np.empty(N)
    xc = np.zeros(nc)
    xn = np.zeros(nc)
    x = np.zeros(4)
    xs = np.zeros(4)
    h = Ts / substeps
    l_y = par[2]
    for kk in range(N):
        yk = x[0] - l_y * x[2]
        y_clean[kk] = yk
        y[kk] = yk + v[kk]
        acc = ss_step(Ac, Bc, Cc, Dc, xc, xn, r[kk] - y[kk])     # no computational delay
        u_fb[kk] = acc
        uk = acc + u_ff[kk] + du[kk]
        u[kk] = uk
        for _ in range(substeps):                             # RK4, u held (ZOH)
            k1 = _rhs(x, uk, par)
            for i in range(4):
                xs[i] = x[i] + 0.5 * h * k1[i]
            k2 = _rhs(xs, uk, par)
            for i in range(4):
                xs[i] = x[i] + 0.5 * h * k2[i]
            k3 = _rhs(xs, uk, par)
            for i in range(4):
                xs[i] = x[i] + h * k3[i]
            k4 = _rhs(xs, uk, par)
            for i in range(4):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    return y, y_clean, u, u_fb


# --------------------------------------------------------------------------- physics model
class RotTransPhysics(ARXPhysics):
    """Linear physics model of [B2] (30): ARX with n_a = n_b = 4, n_k = 0 (θ = [a1..a4, b1..b4],
    ``y(k) = Σ a_i y(k-i) + Σ b_i u(k-i)``), identified by forward least squares.

    Its B(z) has a zero at z ≈ 2.25 (the sampled NMP zero), so :meth:`feedforward` (the
    causal exact inverse) raises a ValueError naming it: compute the feedforward with FHOFC
    ([B2] (17)) or ILC, or use :func:`zpetc_feedforward` for a stable approximate inverse."""

    def __init__(self, Ts: float = 0.01):
        super().__init__(4, 4, 0, Ts)


def zpetc_feedforward(physics: ARXPhysics, theta, r) -> np.ndarray:
    """Zero-phase-error tracking feedforward (Tomizuka 1987): a stable, non-causal
    *approximate* inverse of an ARX model with zeros outside the unit circle.

    With ``B(z) = B_s(z) B_u(z)`` (B_u: zeros on/outside the unit circle), the feedforward is
    ``u = A(q) B_u*(q) / (B_s(q) B_u(1)²) q^{n_k+1} r`` where ``B_u*`` is B_u with reversed
    coefficients: the phase error is zero and the gain error is |B_u(e^{jω})|²/B_u(1)² - 1
    (exact at DC, large near Nyquist).  The preview is n_k + 1 + deg B_u samples; r is held
    at r(N-1) beyond the record, and the past is at rest.

    Parameters
    ----------
    physics : ARXPhysics
        The model structure (orders).
    theta : array
        θ = [a_1..a_{n_a}, b_1..b_{n_b}].
    r : array
        Reference [m], length N.

    Returns
    -------
    u_ff : ndarray, length N
    """
    theta = physics._check_theta(theta)
    r = check_signal("r", r)
    a, b = theta[:physics.n_a], theta[physics.n_a:]
    zeros = physics.input_zeros(theta)
    unstable = zeros[np.abs(zeros) >= 1.0]
    stable = zeros[np.abs(zeros) < 1.0]
    bu = np.real(np.poly(unstable)) if unstable.size else np.array([1.0])   # monic B_u
    bs = b[0] * np.real(np.poly(stable)) if stable.size else np.array([b[0]])
    nu = bu.size - 1
    h = physics.n_k + 1 + nu
    r_ext = np.concatenate([r, np.full(h, r[-1])])
    w = lfilter(np.concatenate([[1.0], -a]), [1.0], r_ext)          # A(q) r
    w = lfilter(bu[::-1], [1.0], w) / np.sum(bu) ** 2               # B_u*(q) / B_u(1)²
    return lfilter([1.0], bs, w[h:])                                # 1/B_s, advanced by h


# --------------------------------------------------------------------------- the plant
class RotTransNMP(System):
    """Translating-rotating mass in closed loop (SPEC §2.3, [B2] §VI).

    Parameters
    ----------
    Ts : float
        Sample time [s] (100 Hz).
    m, l_x, l_y, J, f_v, k, d : float
        Mass [kg], half width / height [m], inertia [kg m²], viscous friction [kg/s],
        rotational spring [kg/s²] and damper [kg/s] ([B2] Table I).
    l_m, c : float
        Magnet pole pitch [m] and cogging magnitude [N] ([B2] (28)); c = 0 gives the linear
        plant.
    controller_gain, controller_zero, controller_pole : float
        C(s) = gain (s + zero)/(s + pole) [N/m, rad/s, rad/s] ([B2] (29)); ZOH at Ts.
    noise : mapping
        ``{structure: output, std: σ [m]}`` measurement noise.
    substeps : int
        RK4 steps per sample (≥ 20).
    r_limit, v_limit : float
        Reference limits |r| ≤ r_limit [m], |δr| ≤ v_limit [m/s].
    """

    name = "rot_trans_nmp"

    def __init__(self, Ts: float = Params.Ts, m: float = Params.m, l_x: float = Params.l_x, l_y: float = Params.l_y,
                 J: float = 40.0 / 3.0, f_v: float = Params.f_v, k: float = 25e3 / 3.0,
                 d: float = 575.0 / 3.0, l_m: float = Params.l_m, c: float = Params.c,
                 controller_gain: float = Params.controller_gain, controller_zero: float = 4.0 * math.pi,
                 controller_pole: float = 20.0 * math.pi, noise=None, substeps: int = Params.substeps,
                 r_limit: float = Params.r_limit, v_limit: float = Params.v_limit, name: str = Params.name):
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        for key, x in dict(Ts=Ts, m=m, l_x=l_x, J=J, l_m=l_m, r_limit=r_limit,
                           v_limit=v_limit).items():
            if not (np.isfinite(float(x)) and float(x) > 0):
                raise ValueError(f"{key} must be positive and finite, got {x!r}")
        for key, x in dict(l_y=l_y, f_v=f_v, k=k, d=d, c=c, controller_gain=controller_gain,
                           controller_zero=controller_zero,
                           controller_pole=controller_pole).items():
            if not np.isfinite(float(x)):
                raise ValueError(f"{key} must be finite, got {x!r}")
        if int(substeps) < 1:
            raise ValueError(f"substeps must be >= 1 (SPEC: >= 20), got {substeps!r}")
        self.Ts, self.m, self.l_x, self.l_y, self.J = float(Ts), float(m), float(l_x), \
            float(l_y), float(J)
        self.f_v, self.k, self.d, self.l_m, self.c = float(f_v), float(k), float(d), \
            float(l_m), float(c)
        self.substeps = int(substeps)
        self.r_limit, self.v_limit = float(r_limit), float(v_limit)
        self.structure, self.std = _noise_options(noise, ("output",),
                                                  {"structure": "output", "std": 1e-6})
        self.name = name
        s = ct.tf("s")
        self._Cs = ct.ss(float(controller_gain) * (s + float(controller_zero)) /
                         (s + float(controller_pole)))
        self._Cz = ct.sample_system(self._Cs, self.Ts, method="zoh")   # [B2] (29), ZOH
        A, B, C, D = (np.asarray(x, dtype=np.float64) for x in
                      (self._Cz.A, self._Cz.B, self._Cz.C, self._Cz.D))
        self._ctrl = (np.ascontiguousarray(A), np.ascontiguousarray(B[:, 0]),
                      np.ascontiguousarray(C[0, :]), float(D[0, 0]))
        self._physics = RotTransPhysics(self.Ts)

    # ----- linear part
    def continuous_tf(self) -> ct.TransferFunction:
        """ξ -> y of [B2] (27) as a continuous transfer function [m/N]."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        m, lx, ly, J, fv, k, d = self.m, self.l_x, self.l_y, self.J, self.f_v, self.k, self.d
        num = [J - ly ** 2 * m, 2 * lx * d - ly ** 2 * fv, 2 * lx * k]
        den = [J * m, fv * J + 2 * lx * d * m, 2 * (lx * d * fv + lx * k * m), 2 * lx * k * fv, 0.0]
        return ct.tf(num, den)

    def continuous_ss(self) -> ct.StateSpace:
        """The physical-coordinate realisation ([x, ẋ, ϑ, ϑ̇], input ξ, output y) integrated by
        the simulator."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        m, lx, ly, J, fv, k, d = self.m, self.l_x, self.l_y, self.J, self.f_v, self.k, self.d
        A = [[0, 1, 0, 0], [0, -fv / m, 0, 0], [0, 0, 0, 1], [0, 0, -2 * lx * k / J, -2 * lx * d / J]]
        B = [[0], [1 / m], [0], [ly / J]]
        return ct.ss(A, B, [[1, 0, -ly, 0]], [[0]])

    def linear_plant(self) -> ct.TransferFunction:
        """ZOH discretisation of the linear part (c = 0) at Ts: n_a = n_b = 4, n_k = 0, zeros
        at z ≈ 2.25, -0.77, 0.73 ([B2] §VI)."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        return ct.tf(ct.sample_system(self.continuous_ss(), self.Ts, "zoh"))

    def linear_theta(self) -> np.ndarray:
        """θ of :class:`RotTransPhysics` equal to :meth:`linear_plant` (the true linear part)."""
        G = self.linear_plant()
        num, den = np.asarray(G.num[0][0], float), np.asarray(G.den[0][0], float)
        num, den = num / den[0], den / den[0]
        num = np.concatenate([np.zeros(4 - num.size), num])         # z^3 .. z^0
        return np.concatenate([-den[1:], num])

    def controller(self) -> ct.TransferFunction:
        """C(z): ZOH discretisation of 5e3 (s + 4π)/(s + 20π) [N/m], dt = Ts."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        return ct.tf(self._Cz)

    def sensitivity(self) -> ct.StateSpace:
        """S = 1/(1 + P C) of the linear loop (discrete, dt = Ts)."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        P = ct.sample_system(self.continuous_ss(), self.Ts, "zoh")
        return ct.feedback(ct.ss([], [], [], [[1.0]], dt=self.Ts), P * self._Cz)

    def learning_model(self):
        """The ILC model: the process sensitivity P S from u_ff to y (SPEC §2.3)."""
        return self.process_sensitivity()

    def process_sensitivity(self) -> ct.StateSpace:
        """PS = P/(1 + P C) of the linear loop [m/N] (u_ff -> y; the ILC/FHOFC model)."""
        import control as ct  # lazy: saves 1.9 s of start-up (python-control)
        P = ct.sample_system(self.continuous_ss(), self.Ts, "zoh")
        return ct.feedback(P, self._Cz)

    # ----- interface
    @property
    def physics(self) -> RotTransPhysics:
        return self._physics

    def noise(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Measurement noise v ~ N(0, std²) [m], length n."""
        return self.std * rng.standard_normal(int(n))

    def check_reference(self, r) -> None:
        """Raise ValueError if |r| > r_limit or |δr| > v_limit (or NaN / not 1-D)."""
        check_limits(r, self.Ts, self.r_limit, self.v_limit)

    def simulate(self, r, u_ff=None, du=None, v=None) -> SimResult:
        """Closed loop ``u(k) = C(q)(r(k) - y(k) - v(k)) + u_ff(k) + du(k)``, ZOH on u, no
        computational delay (SPEC §0, §2.3); starts at rest at 0."""
        r, u_ff, du, v = loop_signals(r, u_ff, du, v)
        self.check_reference(r)
        n = r.shape[0]
        par = np.array([self.m, self.l_x, self.l_y, self.J, self.f_v, self.k, self.d, self.l_m,
                        self.c])
        Ac, Bc, Cc, Dc = self._ctrl
        y, y_clean, u, u_fb = _closed_loop(r, u_ff, du, v, Ac, Bc, Cc, Dc, self.Ts, par,
                                           self.substeps)
        if not np.all(np.isfinite(y)):
            raise FloatingPointError("rot_trans_nmp simulation diverged (non-finite y); check "
                                     "the feedforward/excitation magnitudes")
        return SimResult(t=np.arange(n) * self.Ts, r=r, u=u, y=y, u_ff=u_ff, u_fb=u_fb,
                         y_clean=y_clean, v=v)
