"""An identified one-step model inside the known controller of a measured system (SPEC §2.5).

The model is a forward PGNN with rigid-body physics (:class:`pipeline.systems.measured.
RigidBodyPhysics`, direct input on w) and at most one tanh hidden layer ([B1] (10), [B2] (9))::

    ŷ(k) = 2y(k-1) - y(k-2) + Ts² (θ0 w(k-1) - θ1 δy(k-1) - θ2 sign δy(k-1) - θ3)
           + s_out (W2 tanh(W1 x(k) + b1) + b2),       x(k) = P φ(k) + c,
    φ(k) = [y(k-1) … y(k-n_a), w(k-1) … w(k-n_b)],   w = ū = (u(k) + u(k-1))/2 or u,

(with an actuator lag, ``pipeline.systems.actuator_lag``, w is its exact sampling with the mass,
w = B(q⁻¹)/(1 - a q⁻¹) u, in place of ū), closed around the known controller
(:class:`pipeline.systems.controller.LTIController`, any discrete LTI C_r, C_y with a common denominator A;
the EMPS cascade is one instance)::

    A v(k) = B_r r(k) - B_y ŷ(k),     c(k) = sat(v(k) + u_ff(k) / gtau)
    u(k) = gtau (c(k - D) + d(k))                   applied force [N]
    τ̂(k) = gtau (c(k - D_c) + d(k))                the recorded force's model [N]

with d the measured disturbance [V] (EMPS test file: ``pulses_N``, after the saturation), u_ff [N]
a force feedforward added to the command before the drive's limit (after it, a saturated
feedback could not be cancelled, see ``LTIController.reference_force``) and D_c the controller's
configured delay. Two timing conventions (EMPS README, issue 9):

- ``data`` (default): D = D_c, as recorded (EMPS: vir[k] is the law on qm[k] of the same sample);
- ``published``: the benchmark authors' simulation script: D = D_c + 1 (one more sample of delay
  on the controller output, not on the pulses) and the reference and disturbance read at the
  script's time base k·h, h = t(10) - t(9), by linear interpolation in the data's time column.

One numba kernel simulates the loop and, on request, the exact forward sensitivities of ŷ
and τ̂ to every parameter (the Jacobian of the closed-loop simulation error, [B2] (16)).
Parameter order = the PGNN module's: [θ_phy, W1 (row-major), b1, W2, b2].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numba
import numpy as np

from pipeline.models.closed_loop import nn_export, nn_split
from pipeline.systems.controller import LTIController
from pipeline.systems.force_terms import ForceTerms, term

CONVENTIONS = ("data", "published")


@dataclass
class LoopModel:
    """A rigid-body PGNN as float64 arrays (see the module docstring)."""

    Ts: float
    n_a: int
    n_b: int
    averaged: bool
    theta_phy: np.ndarray
    W1: np.ndarray = None
    b1: np.ndarray = None
    W2: np.ndarray = None
    b2: float = 0.0
    nn_P: np.ndarray = None
    nn_c: np.ndarray = None
    out_scale: float = 1.0
    term_codes: np.ndarray = None     # the physics' force terms (ForceTerms.kernel()); None: viscous, Coulomb
    term_p: np.ndarray = None         # (sign) and, for a 4-entry θ, the offset (the EMPS model)
    lag_b: np.ndarray = None          # an actuator lag: w = lag_b/lag_a u replaces ū (pipeline.systems.actuator_lag);
    lag_a: np.ndarray = None          # None: no lag

    def __post_init__(self):
        if self.n_a < 2 or self.n_b < 1:
            raise ValueError(f"the rigid-body loop model needs n_a >= 2 and n_b >= 1, got n_a={self.n_a}, "
                             f"n_b={self.n_b}")
        self.theta_phy = np.ascontiguousarray(self.theta_phy, dtype=np.float64).reshape(-1)
        if self.term_codes is None:
            names = ("viscous", "coulomb") + (("offset",) if self.theta_phy.size == 4 else ())
            self.term_codes, self.term_p = ForceTerms(names).kernel()
        self.term_codes = np.ascontiguousarray(self.term_codes, dtype=np.int64)
        self.term_p = np.ascontiguousarray(self.term_p, dtype=np.float64)
        if self.lag_b is None:
            self.lag_b, self.lag_a = np.zeros(0), np.ones(1)
        self.lag_b = np.ascontiguousarray(self.lag_b, dtype=np.float64)
        self.lag_a = np.ascontiguousarray(self.lag_a, dtype=np.float64)
        if self.lag_b.size and not (self.averaged and self.lag_a.size >= 1 and self.lag_a[0] == 1.0):
            raise ValueError("an actuator lag replaces the averaged input: give averaged=True and lag_a[0] = 1")
        if self.theta_phy.shape != (1 + self.term_codes.size,):
            raise ValueError(f"theta_phy must be [1/M, p_1/M, …] with one entry per force term "
                             f"({1 + self.term_codes.size}), got shape {self.theta_phy.shape}")
        nphi = self.n_a + self.n_b
        self.nn_P = np.eye(nphi) if self.nn_P is None else np.ascontiguousarray(self.nn_P, dtype=np.float64)
        nx = self.nn_P.shape[0]
        self.nn_c = np.zeros(nx) if self.nn_c is None else np.ascontiguousarray(self.nn_c, dtype=np.float64)
        self.W1 = np.zeros((0, nx)) if self.W1 is None else np.ascontiguousarray(self.W1, np.float64).reshape(-1, nx)
        n1 = self.W1.shape[0]
        self.b1 = np.zeros(n1) if self.b1 is None else np.ascontiguousarray(self.b1, np.float64).reshape(-1)
        self.W2 = np.zeros(n1) if self.W2 is None else np.ascontiguousarray(self.W2, np.float64).reshape(-1)
        self.b2 = float(self.b2)

    @classmethod
    def from_pgnn(cls, model, averaged: bool) -> "LoopModel":
        """Export a forward PGNN with rigid-body physics (``RigidBodyPhysics`` on w) and zero or
        one tanh hidden layer; ``averaged``: the model input w is ū (the data's u is averaged)."""
        if model.structure not in ("forward", "invertible") or not model.use_physics:
            raise ValueError(f"closed-loop simulation needs a forward PGNN with physics, got structure="
                             f"{model.structure!r}, use_physics={model.use_physics}")
        if model.use_nn and not (len(model.hidden) == 1 and model.activation == "tanh"):
            raise ValueError(f"the loop model has one tanh hidden layer, got hidden={model.hidden}, "
                             f"activation={model.activation!r}")
        pm = getattr(model.physics, "pm", model.physics)
        codes, tp = pm.kernel_terms() if hasattr(pm, "kernel_terms") else (None, None)
        return cls(float(pm.Ts), model.n_a, model.n_b, bool(averaged), model.theta_phy.detach().numpy().copy(),
                   **nn_export(model), term_codes=codes, term_p=tp, **_lag(pm, averaged))

    @classmethod
    def physics_only(cls, physics, theta) -> "LoopModel":
        """The physics model alone (``RigidBodyPhysics``; w = ū if it averages its input)."""
        codes, tp = physics.kernel_terms() if hasattr(physics, "kernel_terms") else (None, None)
        return cls(physics.Ts, 2, 1, bool(physics.averaged_input), np.asarray(theta, dtype=np.float64),
                   term_codes=codes, term_p=tp, **_lag(physics, physics.averaged_input))

    @property
    def n1(self) -> int:
        return self.W1.shape[0]

    @property
    def n_params(self) -> int:
        return self.theta_phy.size + (self.n1 * (self.nn_P.shape[0] + 2) + 1 if self.n1 else 0)

    def theta(self) -> np.ndarray:
        if not self.n1:
            return self.theta_phy.copy()
        return np.concatenate([self.theta_phy, self.W1.ravel(), self.b1, self.W2, [self.b2]])

    def with_theta(self, theta) -> "LoopModel":
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta must have {self.n_params} entries, got {theta.shape}")
        return replace(self, **nn_split(theta, self.theta_phy.size, self.n1, self.nn_P.shape[0]))


def _lag(physics, averaged: bool) -> dict:
    """{lag_b, lag_a} of the physics' actuator lag where its input is the model input (else {})."""
    lag = getattr(physics, "lag", None) or getattr(physics, "input_lag", None)   # input_lag: a PGNN's map on w
    if lag is None or not averaged:
        return {}
    b, a = lag.coefficients()
    return {"lag_b": b, "lag_a": a}


@numba.njit(cache=True)
def _filtered(x, k, y, b, a):
    """y(k) of A y = B x (a[0] = 1), zero before k = 0: the actuator lag's model input."""
    acc = 0.0
    for i in range(b.size):
        if k - i >= 0:
            acc += b[i] * x[k - i]
    for i in range(1, a.size):
        if k - i >= 0:
            acc -= a[i] * y[k - i]
    return acc


@numba.njit(cache=True)
def ctrl_law(k, r, y, y0, vv, br, by, ca):
    """v(k) of the controller A v = B_r r - B_y y (pipeline.systems.controller; r, y held at their
    first values before k = 0, v zero)."""
    vk = 0.0
    for i in range(br.size):
        vk += br[i] * r[k - i if k - i >= 0 else 0]
    for i in range(by.size):
        vk -= by[i] * (y[k - i] if k - i >= 0 else y0)
    for i in range(1, ca.size):
        if k - i >= 0:
            vk -= ca[i] * vv[k - i]
    return vk


@numba.njit(cache=True)
def _loop(r, d, uff, y0, yrec, urec, n0, n_a, n_b, averaged, th, codes, tp, W1, b1, W2, b2, P, c, so, Ts, br, by, ca,
          gtau, vsat, D, Dt, sens, lb, la):
    N = r.size
    n1, nx = W1.shape[0], P.shape[0]
    nphi = n_a + n_b
    nth = th.size
    NP = nth + (n1 * (nx + 2) + 1 if n1 > 0 else 0)
    y = np.empty(N)
    u = np.zeros(N)        # applied force
    w = np.zeros(N)        # model input
    cc = np.zeros(N)       # controller output before the disturbance [V]
    vv = np.zeros(N)       # the controller's filter output v (before u_ff and the limit)
    tau = np.empty(N)      # controller force compared with the record
    M = N if sens else 1
    Sy = np.zeros((M, NP))
    Sc = np.zeros((M, NP))
    Sv = np.zeros((M, NP))
    Sw = np.zeros((M, NP))
    Su = np.zeros((M if lb.size else 1, NP))    # ∂u/∂θ, the lag's input
    W1P = np.zeros((n1, nphi))   # W1 P: ∂(pre-activation)/∂φ, constant over the run
    for m in range(n1):
        for i in range(nphi):
            col = 0.0
            for a in range(nx):
                col += W1[m, a] * P[a, i]
            W1P[m, i] = col
    phi = np.zeros(nphi)
    tt = np.zeros(codes.size)
    dfdphi = np.zeros(nphi)
    x = np.zeros(nx)
    h = np.zeros(n1)
    for k in range(N):
        if k < n0:
            # the recorded state: output and applied force from the record; the controller's output
            # c(k - D) = u(k)/gtau - d(k) as recorded (the record ran without u_ff) and, once the
            # record ends, its last D commands (applied after n0) from its law on the recorded y, r
            y[k] = yrec[k]
            u[k] = urec[k]
            tau[k] = urec[k]
            if lb.size:
                w[k] = _filtered(u, k, w, lb, la)
            else:
                w[k] = 0.5 * (u[k] + (u[k - 1] if k >= 1 else 0.0)) if averaged else u[k]
            if k - D >= 0:
                cc[k - D] = urec[k] / gtau - d[k]
                vv[k - D] = cc[k - D]
            if k == n0 - 1:
                for j in range(max(n0 - D, 0), n0):
                    vv[j] = ctrl_law(j, r, y, y0, vv, br, by, ca)
                    cc[j] = min(max(vv[j] + uff[j] / gtau, -vsat), vsat)
            continue
        if k == 0:
            y[0] = y0
        else:
            for i in range(n_a):
                phi[i] = y[k - 1 - i] if k - 1 - i >= 0 else y0
            for j in range(n_b):
                phi[n_a + j] = w[k - 1 - j] if k - 1 - j >= 0 else 0.0
            y1, y2, w1 = phi[0], phi[1], phi[n_a]
            v = (y1 - y2) / Ts
            for i in range(nphi):
                dfdphi[i] = 0.0
            # M q̈ = w - Σ p_j T_j(q, q̇) (pipeline.systems.force_terms), one step at (y1, δy)
            f = 2.0 * y1 - y2 + Ts * Ts * th[0] * w1
            dfdphi[0] = 2.0
            dfdphi[1] = -1.0
            dfdphi[n_a] += Ts * Ts * th[0]
            for j in range(codes.size):
                T, dq, dv = term(codes[j], tp[j], y1, v)
                tt[j] = T
                f -= Ts * Ts * th[1 + j] * T
                dfdphi[0] -= Ts * Ts * th[1 + j] * (dq + dv / Ts)
                dfdphi[1] += Ts * Ts * th[1 + j] * dv / Ts
            if n1 > 0:
                for a in range(nx):
                    acc = c[a]
                    for i in range(nphi):
                        acc += P[a, i] * phi[i]
                    x[a] = acc
                o = b2
                for m in range(n1):
                    z = b1[m]
                    for a in range(nx):
                        z += W1[m, a] * x[a]
                    h[m] = math.tanh(z)
                    o += W2[m] * h[m]
                    g = so * W2[m] * (1.0 - h[m] * h[m])
                    for i in range(nphi):
                        dfdphi[i] += g * W1P[m, i]
                f += so * o
            y[k] = f
            if sens:
                # ∂f/∂θ (direct) then the chain through the past outputs and inputs
                Sy[k, 0] = Ts * Ts * w1
                for j in range(codes.size):
                    Sy[k, 1 + j] = -Ts * Ts * tt[j]
                if n1 > 0:
                    p0 = nth
                    for m in range(n1):
                        g = so * W2[m] * (1.0 - h[m] * h[m])
                        for a in range(nx):
                            Sy[k, p0 + m * nx + a] = g * x[a]
                        Sy[k, p0 + n1 * nx + m] = g
                        Sy[k, p0 + n1 * nx + n1 + m] = so * h[m]
                    Sy[k, NP - 1] = so
                for i in range(n_a):
                    if k - 1 - i >= 1 and dfdphi[i] != 0.0:
                        for p in range(NP):
                            Sy[k, p] += dfdphi[i] * Sy[k - 1 - i, p]
                for j in range(n_b):
                    if k - 1 - j >= 0 and dfdphi[n_a + j] != 0.0:
                        for p in range(NP):
                            Sy[k, p] += dfdphi[n_a + j] * Sw[k - 1 - j, p]
        vk = ctrl_law(k, r, y, y0, vv, br, by, ca)
        vv[k] = vk
        raw = vk + uff[k] / gtau
        sat = 1.0
        if raw > vsat:
            raw, sat = vsat, 0.0
        elif raw < -vsat:
            raw, sat = -vsat, 0.0
        cc[k] = raw
        tau[k] = gtau * ((cc[k - Dt] if k - Dt >= 0 else 0.0) + d[k])
        cd = cc[k - D] if k - D >= 0 else 0.0
        u[k] = gtau * (cd + d[k])
        if lb.size:
            w[k] = _filtered(u, k, w, lb, la)
        elif averaged:
            w[k] = 0.5 * (u[k] + (u[k - 1] if k >= 1 else 0.0))
        else:
            w[k] = u[k]
        if sens:
            for p in range(NP):
                sv = 0.0
                for i in range(by.size):
                    if k - i >= 1:
                        sv -= by[i] * Sy[k - i, p]
                for i in range(1, ca.size):
                    if k - i >= 0:
                        sv -= ca[i] * Sv[k - i, p]
                Sv[k, p] = sv
                Sc[k, p] = sv if sat != 0.0 else 0.0
            for p in range(NP):
                su = gtau * Sc[k - D, p] if k - D >= 0 else 0.0
                if lb.size:
                    Su[k, p] = su
                    sw = 0.0
                    for i in range(lb.size):
                        if k - i >= 0:
                            sw += lb[i] * Su[k - i, p]
                    for i in range(1, la.size):
                        if k - i >= 0:
                            sw -= la[i] * Sw[k - i, p]
                    Sw[k, p] = sw
                elif averaged:
                    sp = 0.0
                    if k >= 1:
                        sp = gtau * Sc[k - 1 - D, p] if k - 1 - D >= 0 else 0.0
                    Sw[k, p] = 0.5 * (su + sp)
                else:
                    Sw[k, p] = su
    return y, tau, u, Sy, Sc


@dataclass
class LoopSignals:
    """Inputs of one closed-loop run: reference r [m], disturbance d [V], feedforward u_ff [N],
    the initial position y0 [m] and, for the published convention, the data's time column t [s].

    Started from the recorded state (``n_init`` > 0): samples k < n_init of the output, the applied
    force and the controller output (u/gtau - d) are the record's, so the first simulated sample
    n_init sees the machine's recorded position, velocity and force history instead of rest;
    scores then start at n_init (:func:`loop_errors` ``start``)."""

    r: np.ndarray
    d: np.ndarray
    y0: float
    t: np.ndarray | None = None
    u_ff: np.ndarray | None = None
    y_rec: np.ndarray | None = None     # the record, for a start from the recorded state:
    u_rec: np.ndarray | None = None     # its position [m] and applied force [N]
    n_init: int = 0                     # samples taken from the record (0: start at rest at y0)

    def __post_init__(self):
        if self.n_init and (self.y_rec is None or self.u_rec is None):
            raise ValueError("a start from the recorded state (n_init > 0) needs y_rec and u_rec")
        if self.n_init < 0 or (self.n_init and self.n_init >= np.size(self.r)):
            raise ValueError(f"n_init={self.n_init} must be in [0, {np.size(self.r)})")

    @classmethod
    def recorded(cls, r, d, y, u, t=None, n_init: int = 0, u_ff=None) -> "LoopSignals":
        """A replay of a record (position y, applied force u) started from its first ``n_init`` samples."""
        return cls(r, d, float(y[0]), t, u_ff, y, u, int(n_init))


def _convention(sig: LoopSignals, convention: str, delay: int = 0):
    """(r, d, u_ff, D) of the convention: as recorded (D = the controller's delay), or read at the
    script's time base with one sample more (the EMPS authors' script)."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention={convention!r}; choose one of {CONVENTIONS}")
    uff = np.zeros_like(sig.r) if sig.u_ff is None else sig.u_ff
    if convention == "data":
        return sig.r, sig.d, uff, delay
    if sig.n_init:
        raise ValueError("the published convention is the authors' script, which starts at rest: give n_init=0")
    if sig.t is None or sig.t.size < 10:
        raise ValueError("the published convention needs the data's time column t (>= 10 samples)")
    h = float(sig.t[9] - sig.t[8])                       # the script's step t(10) - t(9)
    ts = sig.t[0] + np.arange(sig.r.size) * h
    return tuple(np.interp(ts, sig.t, x) for x in (sig.r, sig.d, uff)) + (delay + 1,)


def simulate_loop(model: LoopModel, ctrl, sig: LoopSignals, convention: str = "data", sens: bool = False):
    """Closed-loop simulation of ``model`` inside ``ctrl`` (module docstring).

    Returns (ŷ [m], τ̂ [N], u [N] applied force) and, with ``sens``, the sensitivities
    (∂ŷ/∂θ [N, P], ∂τ̂/∂θ [N, P])."""
    r, d, uff, D = _convention(sig, convention, ctrl.delay)
    Dt = int(ctrl.delay)                          # the recorded force is the applied one, u(k) = gtau (c(k-D) + d(k))
    r, d, uff = (np.ascontiguousarray(x, dtype=np.float64) for x in (r, d, uff))
    if not (d.shape == r.shape == uff.shape):
        raise ValueError(f"r, d and u_ff must have one length, got {r.shape}, {d.shape}, {uff.shape}")
    n0 = int(sig.n_init)
    need = max(model.n_a, model.n_b + int(model.averaged), ctrl.b_y.size, ctrl.b_r.size, ctrl.a.size,
               int(ctrl.delay) + 1)
    if 0 < n0 < need:
        raise ValueError(f"a recorded start needs the model's and the controller's whole history: n_init={n0} < {need}")
    yrec = np.ascontiguousarray(sig.y_rec if n0 else np.zeros(1), dtype=np.float64)
    urec = np.ascontiguousarray(sig.u_rec if n0 else np.zeros(1), dtype=np.float64)
    if n0 and not (yrec.shape == urec.shape == r.shape):
        raise ValueError(f"y_rec and u_rec must have the reference's length {r.shape}, got {yrec.shape}, {urec.shape}")
    y, tau, u, Sy, Sc = _loop(r, d, uff, float(sig.y0), yrec, urec, n0, model.n_a, model.n_b, model.averaged,
                              model.theta_phy,
                              model.term_codes, model.term_p,
                              model.W1, model.b1, model.W2, model.b2, model.nn_P, model.nn_c, model.out_scale,
                              model.Ts, ctrl.b_r, ctrl.b_y, ctrl.a, ctrl.gtau, ctrl.v_sat, D, Dt, sens,
                              model.lag_b, model.lag_a)
    if sens:
        St = Sc * ctrl.gtau
        if Dt:
            St = np.concatenate([np.zeros((Dt, St.shape[1])), St[:-Dt]])
        return y, tau, u, Sy, St
    return y, tau, u


def loop_errors(y_meas, tau_meas, y_hat, tau_hat, start: int = 0) -> dict[str, float]:
    """Scores of a closed-loop simulation against the record (EMPS README), on samples k >= start:

    - ``force_rel_error`` [%] = 100 ‖τ - τ̂‖ / ‖τ‖;
    - ``position_rel_error`` [%] = 100 ‖q - q̂‖ / ‖q‖;
    - ``loop_rmse_mm`` [mm]: rms(q - q̂) of the closed-loop replay.
    """
    y_meas, tau_meas = np.asarray(y_meas)[start:], np.asarray(tau_meas)[start:]
    y_hat, tau_hat = np.asarray(y_hat)[start:], np.asarray(tau_hat)[start:]
    return {"force_rel_error": float(100 * np.linalg.norm(tau_meas - tau_hat) / np.linalg.norm(tau_meas)),
            "position_rel_error": float(100 * np.linalg.norm(y_meas - y_hat) / np.linalg.norm(y_meas)),
            "loop_rmse_mm": float(1e3 * np.sqrt(np.mean((y_meas - y_hat) ** 2)))}


#: no controller: the open-loop convention (u enters as the disturbance)
_NO_FEEDBACK = LTIController(np.zeros(1), np.zeros(1), np.ones(1), 1.0, math.inf, 0, "none")

#: samples that initialise an open-loop simulation (nonlinear_benchmarks' EMPS convention)
N_INIT = 20


def simulate_open_loop(model: LoopModel, u, y0: float, y_rec=None, n_init: int = 0) -> np.ndarray:
    """ŷ [m] of the model driven by a recorded force u [N], no controller (the EMPS benchmark's
    simulation convention: input vir, output qm): the loop kernel with zero gains and u as the
    disturbance, so the same model code runs.  With ``y_rec``, the first ``n_init`` samples are
    the record's (the benchmark's initialisation), else the model starts at rest at y0."""
    u = np.asarray(u, dtype=np.float64)
    sig = LoopSignals(np.zeros_like(u), u, float(y0), None, None, y_rec, u if y_rec is not None else None,
                      int(n_init) if y_rec is not None else 0)
    y, _, _ = simulate_loop(model, _NO_FEEDBACK, sig, "data")
    return y


def benchmark_scores(y_meas, y_hat, n_init: int = N_INIT) -> dict[str, float]:
    """The open-loop simulation's scores on the samples after the first ``n_init`` (which only
    initialise): ``benchmark_rmse_mm`` = rms(q - q̂) [mm] and ``benchmark_r2`` = 1 - Σe² / Σ(q - q̄)²."""
    y = np.asarray(y_meas)[n_init:]
    e = y - np.asarray(y_hat)[n_init:]
    return {"benchmark_rmse_mm": float(1e3 * np.sqrt(np.mean(e ** 2))),
            "benchmark_r2": float(1.0 - np.sum(e ** 2) / np.sum((y - y.mean()) ** 2))}


def benchmark_rmse_mm(y_meas, y_hat, n_init: int = N_INIT) -> float:
    """rms(q - q̂) [mm] over the samples after the first ``n_init`` (which only initialise)."""
    return benchmark_scores(y_meas, y_hat, n_init)["benchmark_rmse_mm"]


# --------------------------------------------------------------------------------------
# closed-loop simulation-error identification ([B2] (16) on the measured loop)
# --------------------------------------------------------------------------------------
@dataclass
class LoopFit:
    """Result of :func:`identify_loop_sim_error` (the PGNN module holds the kept parameters)."""

    loop: LoopModel                # the identified model as arrays
    theta_phy_star: np.ndarray     # regulariser centre θ*_phy
    sigma: float                   # std of the measured force on the training samples [N]
    n_train: int
    val_force_rel_error: float | None   # on the samples after n_train [%] (None without validation)
    tau_hat: np.ndarray                 # the identified loop's force over the whole record [N]
    restarts: list = field(default_factory=list)   # pipeline.identify.narx.RestartResult per start
    best: int = 0

    @property
    def cost(self) -> float:
        return self.restarts[self.best].cost


def identify_loop_sim_error(model, averaged: bool, ctrl, sig, tau_meas, *, lam: float = 0.0,
                            n_train=None, n_restarts: int = 3, seed: int = 0,
                            progress=None, **lm_options) -> LoopFit:
    """Closed-loop simulation-error identification of a rigid-body PGNN on a measured loop,

        V(θ) = ‖(τ - τ̂(θ)) / (σ_τ sqrt(N_t))‖² + ‖R (θ_phy - θ*_phy)/|θ*_phy|‖²,   RᵀR = Λ,

    [B2] (16) with the loop's measured force τ as the output (τ̂ follows ŷ through the known
    controller, so this is the simulation error the EMPS benchmark scores) and the SPEC §5
    normalisation; θ*_phy is where ``model`` holds θ_phy (the physics baseline).  ``sig``,
    ``tau_meas`` and ``n_train`` are one record's or lists, one per recording (``data.files``):
    each record is simulated on its own from ``sig``'s start (the recorded state of its first
    ``n_init`` samples, or rest); its samples n_init … n_train - 1 enter V, the rest is its
    validation block (the force error over all blocks is logged, never used to stop).  LM
    (:func:`pipeline.identify.lm.levenberg_marquardt`, ``lm_options``) with the exact Jacobian
    from the loop's forward sensitivities, best of ``n_restarts`` NN initialisations
    (:func:`pipeline.identify.narx.best_of_restarts`).  ``model`` (a forward PGNN whose NN
    normalisation and output scale are set) is modified in place.
    """
    import torch  # lazy: saves 1.7 s of start-up (torch: evaluate replays the loop without it)

    from pipeline.identify.narx import best_of_restarts, regularizer_sqrt  # lazy: saves 2.2 s of start-up (torch)
    one = isinstance(sig, LoopSignals)
    sigs = [sig] if one else list(sig)
    taus = [np.asarray(t, dtype=np.float64) for t in ([tau_meas] if one else tau_meas)]
    nts = [n_train] * len(sigs) if (n_train is None or np.ndim(n_train) == 0) else list(n_train)
    if not len(sigs) == len(taus) == len(nts):
        raise ValueError(f"give one force record and one n_train per loop signal: {len(sigs)}, {len(taus)}, {len(nts)}")
    nts = [t.size if n is None else int(n) for n, t in zip(nts, taus)]
    n0s = [int(s_.n_init) for s_ in sigs]
    for n0, nt in zip(n0s, nts):
        if not 0 <= n0 < nt:
            raise ValueError(f"the recorded start n_init={n0} leaves no training sample before n_train={nt}")
    train = np.concatenate([t[n0:nt] for t, n0, nt in zip(taus, n0s, nts)])
    sigma = float(np.std(train))
    if not sigma > 0:
        raise ValueError("the measured force is constant on the training samples; nothing to identify")
    cn = 1.0 / (sigma * math.sqrt(train.size))
    loop0 = LoopModel.from_pgnn(model, averaged)
    ts = loop0.theta_phy.copy()
    npy = ts.size
    scale = np.where(np.abs(ts) > 0, np.abs(ts), 1.0)
    Rs = regularizer_sqrt(lam, npy) / scale[None, :]
    reg = bool(np.any(Rs != 0))
    cache: dict = {}

    def run(theta, sens: bool):
        """The loop simulated at θ, with the sensitivities only where the Jacobian needs them: a trial
        step, a rejected step or the geodesic acceleration's extra point needs the residual alone
        (about 20× cheaper; ŷ and τ̂ are the same to the bit with or without them)."""
        key = theta.tobytes()
        if key not in cache or (sens and not cache[key][0]):
            cache.clear()
            m = loop0.with_theta(theta)
            cache[key] = (sens, [simulate_loop(m, ctrl, s_, "data", sens=sens) for s_ in sigs])
        return cache[key][1]

    def residual(th):
        theta = th.numpy()
        e = np.concatenate([(t[n0:nt] - out[1][n0:nt]) * cn
                            for t, out, n0, nt in zip(taus, run(theta, False), n0s, nts)])
        if not np.all(np.isfinite(e)):
            e = np.full_like(e, 1e150)        # a diverged simulation: LM rejects the step
        return torch.from_numpy(np.concatenate([e, Rs @ (theta[:npy] - ts)]) if reg else e)

    def jacobian(th):
        J = np.concatenate([-out[4][n0:nt] * cn for out, n0, nt in zip(run(th.numpy(), True), n0s, nts)])
        if reg:
            Jr = np.zeros((npy, J.shape[1]))
            Jr[:, :npy] = Rs
            J = np.concatenate([J, Jr])
        return torch.from_numpy(np.where(np.isfinite(J), J, 0.0))

    restarts, best = best_of_restarts(model, residual, jacobian, n_restarts if model.use_nn else 1, seed,
                                      progress=progress, **lm_options)
    loop = LoopModel.from_pgnn(model, averaged)
    hats = [simulate_loop(loop, ctrl, s_, "data")[1] for s_ in sigs]
    val = None
    if any(nt < t.size for t, nt in zip(taus, nts)):
        vm = np.concatenate([t[nt:] for t, nt in zip(taus, nts)])
        vh = np.concatenate([h[nt:] for h, nt in zip(hats, nts)])
        val = float(100 * np.linalg.norm(vm - vh) / np.linalg.norm(vm))
    return LoopFit(loop, ts, sigma, sum(nts), val, np.concatenate(hats), restarts, best)
