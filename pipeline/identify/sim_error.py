"""Closed-loop simulation of the [B2] PGNN and closed-loop simulation-error identification.

The model is the PGNN (30) of [B2]: a linear ARX physics model plus one tanh hidden layer,

    ŷ(k) = θ_phyᵀ φ(k) + s_out (W2 tanh(W1 φn(k) + b1) + b2),          [B2] (9), (30)
    φ(k) = [ŷ(k-1), …, ŷ(k-n_a), û(k-n_k-1), …, û(k-n_k-n_b)],
    φn(k) = (φ(k) - φ_mean) / φ_std                                  (SPEC §3 NN defaults),

simulated in closed loop with the known discrete controller, no computational delay
(SPEC §0), [B2] (8):

    û(k) = C(q)(r(k) - ŷ(k)) + u_ff(k).

Because φ(k) holds only past û (n_k ≥ 0), the loop has no algebraic loop.  The simulation
and its exact forward sensitivities (w.r.t. the parameters θ for identification, w.r.t. the
feedforward U_ff for FHOFC) run in numba kernels: a per-sample torch loop is two orders of
magnitude slower.  The kernels are checked against finite differences, against a torch
autograd reference (:func:`simulate_closed_loop_torch`) and against python-control.

Parameter vector (order of :meth:`ArxPGNN.theta`): ``[θ_phy (n_φ), W1 (n1×n_φ, row-major),
b1 (n1), W2 (n1), b2]`` with n_φ = n_a + n_b; θ_phy is the physics part of [B2] (16)'s
Λ = [I, 0].
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numba
import numpy as np

# --------------------------------------------------------------------------------------
# model and controller as plain arrays
# --------------------------------------------------------------------------------------


@dataclass
class ArxPGNN:
    """The PGNN (30) of [B2] as plain float64 arrays (fast closed-loop simulation).

    Parameters
    ----------
    n_a, n_b, n_k : int
        Orders of φ(k) ([B2] (9)); n_b ≥ 1, n_k ≥ 0.
    theta_phy : ndarray, shape (n_a + n_b,)
        Linear physics model ŷ = θ_phyᵀ φ: coefficients of ŷ(k-1..k-n_a) [-] then of
        û(k-n_k-1..k-n_k-n_b) [m/N].
    W1 : ndarray, shape (n1, n_a + n_b)
        Hidden-layer weights acting on the normalised regressor φn [-].
    b1 : ndarray, shape (n1,)
        Hidden-layer biases [-].
    W2 : ndarray, shape (n1,)
        Output weights [-] (the NN output is multiplied by ``out_scale``).
    b2 : float
        Output bias [-].
    phi_mean, phi_std : ndarray, shape (n_a + n_b,)
        Input normalisation of the NN (from training data; part of the model).
    out_scale : float
        Fixed output scale of the NN [m]; makes W2, b2 O(1) numbers for the solver.
    y_range : tuple of float or None
        Output range [m] seen in the identification data (the model's validity range);
        FHOFC refuses references outside it (with a margin).
    """

    n_a: int
    n_b: int
    n_k: int
    theta_phy: np.ndarray
    W1: np.ndarray = None
    b1: np.ndarray = None
    W2: np.ndarray = None
    b2: float = 0.0
    phi_mean: np.ndarray = None
    phi_std: np.ndarray = None
    out_scale: float = 1.0
    y_range: tuple[float, float] | None = None

    def __post_init__(self):
        if self.n_a < 0 or self.n_b < 1 or self.n_k < 0:
            raise ValueError(f"orders must satisfy n_a >= 0, n_b >= 1, n_k >= 0; got n_a={self.n_a}, "
                             f"n_b={self.n_b}, n_k={self.n_k}")
        nphi = self.n_a + self.n_b
        self.theta_phy = np.asarray(self.theta_phy, dtype=np.float64).reshape(-1)
        if self.theta_phy.shape != (nphi,):
            raise ValueError(f"theta_phy must have n_a + n_b = {nphi} entries, got {self.theta_phy.shape}")
        if self.W1 is None:
            self.W1 = np.zeros((0, nphi))
        self.W1 = np.ascontiguousarray(np.asarray(self.W1, dtype=np.float64).reshape(-1, nphi))
        n1 = self.W1.shape[0]
        self.b1 = np.zeros(n1) if self.b1 is None else np.asarray(self.b1, dtype=np.float64).reshape(-1)
        self.W2 = np.zeros(n1) if self.W2 is None else np.asarray(self.W2, dtype=np.float64).reshape(-1)
        if self.b1.shape != (n1,) or self.W2.shape != (n1,):
            raise ValueError(f"b1 and W2 must have n1 = {n1} entries (rows of W1), got {self.b1.shape}, "
                             f"{self.W2.shape}")
        self.b2 = float(self.b2)
        self.phi_mean = np.zeros(nphi) if self.phi_mean is None else np.asarray(self.phi_mean, np.float64)
        self.phi_std = np.ones(nphi) if self.phi_std is None else np.asarray(self.phi_std, np.float64)
        if self.phi_mean.shape != (nphi,) or self.phi_std.shape != (nphi,) or np.any(self.phi_std <= 0):
            raise ValueError("phi_mean/phi_std must have n_a + n_b entries and phi_std > 0; got "
                             f"{self.phi_mean}, {self.phi_std}")
        self.out_scale = float(self.out_scale)

    # -- sizes and parameter vector -------------------------------------------------
    @property
    def n_phi(self) -> int:
        return self.n_a + self.n_b

    @property
    def n1(self) -> int:
        return self.W1.shape[0]

    @property
    def n_params(self) -> int:
        return self.n_phi + self.n1 * (self.n_phi + 2) + 1

    @property
    def delay(self) -> int:
        """Samples from u_ff(j) to the first ŷ it moves: n_k + 1."""
        return self.n_k + 1

    def theta(self) -> np.ndarray:
        """All parameters as one vector (order in the module docstring)."""
        return np.concatenate([self.theta_phy, self.W1.reshape(-1), self.b1, self.W2, [self.b2]])

    def with_theta(self, theta: np.ndarray) -> "ArxPGNN":
        """A copy with parameters ``theta`` (same orders, normalisation, scale)."""
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta must have {self.n_params} entries, got {theta.shape}")
        p, n1 = self.n_phi, self.n1
        i = p
        W1 = theta[i:i + n1 * p].reshape(n1, p); i += n1 * p
        b1 = theta[i:i + n1]; i += n1
        W2 = theta[i:i + n1]; i += n1
        return replace(self, theta_phy=theta[:p].copy(), W1=W1.copy(), b1=b1.copy(), W2=W2.copy(),
                       b2=float(theta[i]))

    def linear_part(self) -> "ArxPGNN":
        """The physics model alone (n1 = 0)."""
        return replace(self, W1=np.zeros((0, self.n_phi)), b1=np.zeros(0), W2=np.zeros(0), b2=0.0)

    # -- evaluation -----------------------------------------------------------------
    def one_step(self, phi: np.ndarray) -> np.ndarray:
        """ŷ for regressors ``phi`` [..., n_a + n_b] (vectorised, [B2] (30))."""
        phi = np.asarray(phi, dtype=np.float64)
        y = phi @ self.theta_phy
        if self.n1:
            h = np.tanh(((phi - self.phi_mean) / self.phi_std) @ self.W1.T + self.b1)
            y = y + self.out_scale * (h @ self.W2 + self.b2)
        return y

    def regressor(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """φ(k) [N, n_a + n_b] from measured y, u (past values before k = 0 are zero)."""
        y = np.asarray(y, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        n = y.shape[0]
        phi = np.zeros((n, self.n_phi))
        for i in range(1, self.n_a + 1):
            phi[i:, i - 1] = y[:n - i]
        for i in range(1, self.n_b + 1):
            lag = self.n_k + i
            phi[lag:, self.n_a + i - 1] = u[:n - lag]
        return phi


def arx_from_tf(G) -> np.ndarray:
    """θ_phy (in the φ order of :class:`ArxPGNN`) and (n_a, n_b, n_k) of a discrete SISO TF.

    ``G(z) = (b_1 z^-(n_k+1) + … + b_nb z^-(n_k+n_b)) / (1 + a_1 z^-1 + … + a_na z^-n_a)`` gives
    ŷ(k) = -Σ a_i ŷ(k-i) + Σ b_i û(k-n_k-i).

    Parameters
    ----------
    G : control.TransferFunction
        Strictly proper discrete-time SISO transfer function (dt > 0).

    Returns
    -------
    theta_phy : ndarray
    orders : tuple (n_a, n_b, n_k)
    """
    import control
    G = control.tf(G)
    if not G.isdtime(strict=True):
        raise ValueError(f"arx_from_tf needs a discrete-time TF (dt > 0), got dt={G.dt}")
    num = np.trim_zeros(np.atleast_1d(np.squeeze(G.num[0][0])).astype(float), "f")
    den = np.trim_zeros(np.atleast_1d(np.squeeze(G.den[0][0])).astype(float), "f")
    n_a = len(den) - 1
    rel_deg = len(den) - len(num)
    if rel_deg < 1:
        raise ValueError(f"G must be strictly proper (no direct feedthrough), relative degree is {rel_deg}")
    a = den[1:] / den[0]
    b = np.trim_zeros(num / den[0], "b")
    # in z^-1: numerator coefficients start at z^-rel_deg
    n_k = rel_deg - 1
    n_b = len(b)
    # trailing zeros in b were trimmed; trailing zeros in numerator polynomial in z (b at
    # highest z^-power zero) keep n_b minimal.
    return np.concatenate([-a, b]), (n_a, n_b, n_k)


@dataclass
class DiscreteController:
    """Discrete feedback controller C(q) as a state-space realisation (no computational delay).

    ``x_c(k+1) = A x_c(k) + B e(k)``, ``u_fb(k) = C x_c(k) + D e(k)``, e = r - ŷ [m], u_fb [N].
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: float
    dt: float | None = None

    @classmethod
    def from_tf(cls, C) -> "DiscreteController":
        """Realise a discrete ``control.TransferFunction``/``StateSpace`` (``None`` = no feedback)."""
        import control
        if C is None:
            return cls(np.zeros((0, 0)), np.zeros(0), np.zeros(0), 0.0, None)
        if not C.isdtime(strict=True):
            raise ValueError(f"the controller must be discrete (dt > 0), got dt={C.dt}; discretise it "
                             "with control.c2d first")
        ss = control.ss(C)
        if ss.ninputs != 1 or ss.noutputs != 1:
            raise ValueError(f"only SISO controllers are supported, got {ss.ninputs}x{ss.noutputs}")
        return cls(np.asarray(ss.A, float), np.asarray(ss.B, float).reshape(-1),
                   np.asarray(ss.C, float).reshape(-1), float(np.asarray(ss.D).squeeze()), float(ss.dt))

    @property
    def n_c(self) -> int:
        return self.A.shape[0]

    def arrays(self):
        A = np.ascontiguousarray(np.asarray(self.A, float).reshape(self.n_c, self.n_c))
        return A, np.ascontiguousarray(self.B, dtype=float).reshape(-1), \
            np.ascontiguousarray(self.C, dtype=float).reshape(-1), float(self.D)


@dataclass
class LoopState:
    """State of the closed-loop model between samples (for receding-horizon use).

    yh[i] = ŷ(k-1-i), uh[i] = û(k-1-i) (length n_k + n_b), xc: controller state.
    """

    yh: np.ndarray
    uh: np.ndarray
    xc: np.ndarray

    @classmethod
    def rest(cls, model: ArxPGNN, ctrl: DiscreteController) -> "LoopState":
        return cls(np.zeros(model.n_a), np.zeros(model.n_k + model.n_b), np.zeros(ctrl.n_c))

    def copy(self) -> "LoopState":
        return LoopState(self.yh.copy(), self.uh.copy(), self.xc.copy())


# --------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------

@numba.njit(cache=True)
def _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, phi, phin, hbuf, g):
    """One step of [B2] (30): returns ŷ; fills phi, phin, hbuf (tanh), g = ∂ŷ/∂φ."""
    nphi = n_a + n_b
    for i in range(n_a):
        phi[i] = yh[i]
    for i in range(n_b):
        phi[n_a + i] = uh[n_k + i]
    y = 0.0
    for j in range(nphi):
        y += th[j] * phi[j]
        phin[j] = (phi[j] - mu[j]) / sd[j]
        g[j] = th[j]
    n1 = W1.shape[0]
    for i in range(n1):
        z = b1[i]
        for j in range(nphi):
            z += W1[i, j] * phin[j]
        h = math.tanh(z)
        hbuf[i] = h
        y += so * W2[i] * h
        c = so * W2[i] * (1.0 - h * h)  # sech² = 1 - tanh², no overflow (SPEC §0)
        for j in range(nphi):
            g[j] += c * W1[i, j] / sd[j]
    y += so * b2
    return y


@numba.njit(cache=True)
def _cl_simulate(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, Ac, Bc, Cc, Dc):
    """Closed-loop model simulation [B2] (8)+(30); yh, uh, xc are updated in place."""
    N = r.shape[0]
    nphi = n_a + n_b
    nh = uh.shape[0]
    nc = xc.shape[0]
    yhat = np.empty(N)
    uhat = np.empty(N)
    phi = np.empty(nphi)
    phin = np.empty(nphi)
    hbuf = np.empty(W1.shape[0])
    g = np.empty(nphi)
    xn = np.empty(nc)
    for k in range(N):
        y = _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, phi, phin, hbuf, g)
        e = r[k] - y
        u = Dc * e + uff[k]
        for i in range(nc):
            u += Cc[i] * xc[i]
        for i in range(nc):
            s = Bc[i] * e
            for j in range(nc):
                s += Ac[i, j] * xc[j]
            xn[i] = s
        for i in range(nc):
            xc[i] = xn[i]
        for i in range(n_a - 1, 0, -1):
            yh[i] = yh[i - 1]
        if n_a > 0:
            yh[0] = y
        for i in range(nh - 1, 0, -1):
            uh[i] = uh[i - 1]
        uh[0] = u
        yhat[k] = y
        uhat[k] = u
    return yhat, uhat


@numba.njit(cache=True)
def _cl_jac_uff(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, Ac, Bc, Cc, Dc):
    """Simulation plus J[k, j] = ∂ŷ(k)/∂u_ff(j) (lower triangular, forward sensitivities)
    and Ju[k, j] = ∂û(k)/∂u_ff(j)."""
    N = r.shape[0]
    nphi = n_a + n_b
    nh = uh.shape[0]
    nc = xc.shape[0]
    yhat = np.empty(N)
    uhat = np.empty(N)
    J = np.zeros((N, N))
    Ju = np.zeros((N, N))
    Sx = np.zeros((nc, N))
    Sxn = np.zeros(nc)
    phi = np.empty(nphi)
    phin = np.empty(nphi)
    hbuf = np.empty(W1.shape[0])
    g = np.empty(nphi)
    xn = np.empty(nc)
    for k in range(N):
        y = _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, phi, phin, hbuf, g)
        # ∂ŷ(k)/∂u_ff(j), j < k: chain through past ŷ and û
        for i in range(1, n_a + 1):
            if k - i >= 0:
                gi = g[i - 1]
                for j in range(k - i):
                    J[k, j] += gi * J[k - i, j]
        for i in range(1, n_b + 1):
            lag = n_k + i
            if k - lag >= 0:
                gi = g[n_a + i - 1]
                for j in range(k - lag + 1):
                    J[k, j] += gi * Ju[k - lag, j]
        # û(k) = C x_c + D e + u_ff(k)
        for j in range(k):
            s = -Dc * J[k, j]
            for i in range(nc):
                s += Cc[i] * Sx[i, j]
            Ju[k, j] = s
        Ju[k, k] = 1.0
        # x_c(k+1) = A x_c + B e
        for j in range(k + 1):
            for i in range(nc):
                s = -Bc[i] * J[k, j]
                for m in range(nc):
                    s += Ac[i, m] * Sx[m, j]
                Sxn[i] = s
            for i in range(nc):
                Sx[i, j] = Sxn[i]
        e = r[k] - y
        u = Dc * e + uff[k]
        for i in range(nc):
            u += Cc[i] * xc[i]
        for i in range(nc):
            s = Bc[i] * e
            for j in range(nc):
                s += Ac[i, j] * xc[j]
            xn[i] = s
        for i in range(nc):
            xc[i] = xn[i]
        for i in range(n_a - 1, 0, -1):
            yh[i] = yh[i - 1]
        if n_a > 0:
            yh[0] = y
        for i in range(nh - 1, 0, -1):
            uh[i] = uh[i - 1]
        uh[0] = u
        yhat[k] = y
        uhat[k] = u
    return yhat, uhat, J, Ju


@numba.njit(cache=True)
def _cl_jac_theta(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, Ac, Bc, Cc, Dc):
    """Simulation plus J[k, p] = ∂ŷ(k)/∂θ_p (forward sensitivities of the recurrent loop)."""
    N = r.shape[0]
    nphi = n_a + n_b
    n1 = W1.shape[0]
    P = nphi + n1 * (nphi + 2) + 1
    nh = uh.shape[0]
    nc = xc.shape[0]
    yhat = np.empty(N)
    uhat = np.empty(N)
    J = np.zeros((N, P))
    Ju = np.zeros((N, P))
    Sx = np.zeros((nc, P))
    Sxn = np.zeros(nc)
    phi = np.empty(nphi)
    phin = np.empty(nphi)
    hbuf = np.empty(max(n1, 1))
    g = np.empty(nphi)
    xn = np.empty(nc)
    oW1 = nphi
    ob1 = oW1 + n1 * nphi
    oW2 = ob1 + n1
    ob2 = oW2 + n1
    for k in range(N):
        y = _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, mu, sd, so, phi, phin, hbuf, g)
        Jk = J[k]
        # explicit ∂f/∂θ at fixed φ
        for j in range(nphi):
            Jk[j] = phi[j]
        for i in range(n1):
            h = hbuf[i]
            c = so * W2[i] * (1.0 - h * h)
            for j in range(nphi):
                Jk[oW1 + i * nphi + j] = c * phin[j]
            Jk[ob1 + i] = c
            Jk[oW2 + i] = so * h
        Jk[ob2] = so
        # chain through the recurrent regressor
        for i in range(1, n_a + 1):
            if k - i >= 0:
                gi = g[i - 1]
                Jp = J[k - i]
                for p in range(P):
                    Jk[p] += gi * Jp[p]
        for i in range(1, n_b + 1):
            lag = n_k + i
            if k - lag >= 0:
                gi = g[n_a + i - 1]
                Jp = Ju[k - lag]
                for p in range(P):
                    Jk[p] += gi * Jp[p]
        Juk = Ju[k]
        for p in range(P):
            s = -Dc * Jk[p]
            for i in range(nc):
                s += Cc[i] * Sx[i, p]
            Juk[p] = s
        for p in range(P):
            for i in range(nc):
                s = -Bc[i] * Jk[p]
                for m in range(nc):
                    s += Ac[i, m] * Sx[m, p]
                Sxn[i] = s
            for i in range(nc):
                Sx[i, p] = Sxn[i]
        e = r[k] - y
        u = Dc * e + uff[k]
        for i in range(nc):
            u += Cc[i] * xc[i]
        for i in range(nc):
            s = Bc[i] * e
            for j in range(nc):
                s += Ac[i, j] * xc[j]
            xn[i] = s
        for i in range(nc):
            xc[i] = xn[i]
        for i in range(n_a - 1, 0, -1):
            yh[i] = yh[i - 1]
        if n_a > 0:
            yh[0] = y
        for i in range(nh - 1, 0, -1):
            uh[i] = uh[i - 1]
        uh[0] = u
        yhat[k] = y
        uhat[k] = u
    return yhat, uhat, J


# --------------------------------------------------------------------------------------
# public simulation API
# --------------------------------------------------------------------------------------

def _prep(model: ArxPGNN, ctrl: DiscreteController, r, u_ff, state: LoopState | None):
    r = np.ascontiguousarray(r, dtype=np.float64).reshape(-1)
    u_ff = np.ascontiguousarray(u_ff, dtype=np.float64).reshape(-1)
    if u_ff.shape != r.shape:
        raise ValueError(f"u_ff has {u_ff.shape[0]} samples but r has {r.shape[0]}; give both one length")
    st = LoopState.rest(model, ctrl) if state is None else state.copy()
    if st.yh.shape != (model.n_a,) or st.uh.shape != (model.n_k + model.n_b,) or st.xc.shape != (ctrl.n_c,):
        raise ValueError("the loop state does not match the model/controller orders: "
                         f"yh {st.yh.shape} (want {model.n_a}), uh {st.uh.shape} (want "
                         f"{model.n_k + model.n_b}), xc {st.xc.shape} (want {ctrl.n_c})")
    Ac, Bc, Cc, Dc = ctrl.arrays()
    args = (model.n_a, model.n_b, model.n_k, model.theta_phy, model.W1, model.b1, model.W2, model.b2,
            model.phi_mean, model.phi_std, model.out_scale, Ac, Bc, Cc, Dc)
    return r, u_ff, st, args


def simulate_closed_loop(model: ArxPGNN, ctrl: DiscreteController, r, u_ff, state: LoopState | None = None,
                         return_state: bool = False):
    """Closed-loop model simulation Ŷ = Φ̂(θ, x0, R, U_ff) ([B2] (5), (8), (30)).

    Parameters
    ----------
    model : ArxPGNN
    ctrl : DiscreteController
    r : array_like, shape (N,)
        Reference [m].
    u_ff : array_like, shape (N,)
        Feedforward (plus any excitation) [N].
    state : LoopState, optional
        Initial state x0 (default: at rest).
    return_state : bool
        Also return the state after the last sample.

    Returns
    -------
    y_hat : ndarray [m], u_hat : ndarray [N] (û = C(q)(r - ŷ) + u_ff) [, state]
    """
    r, u_ff, st, args = _prep(model, ctrl, r, u_ff, state)
    y, u = _cl_simulate(r, u_ff, st.yh, st.uh, st.xc, *args)
    return (y, u, st) if return_state else (y, u)


def jacobian_uff(model: ArxPGNN, ctrl: DiscreteController, r, u_ff, state: LoopState | None = None):
    """Simulation and the exact Jacobians ∂Ŷ/∂U_ff, ∂Û/∂U_ff (N × N, lower triangular).

    Returns
    -------
    y_hat, u_hat : ndarray
    J_y : ndarray (N, N)
        ∂ŷ(k)/∂u_ff(j) [m/N], zero for j > k - n_k - 1.
    J_u : ndarray (N, N)
        ∂û(k)/∂u_ff(j) [-], unit diagonal.
    """
    r, u_ff, st, args = _prep(model, ctrl, r, u_ff, state)
    return _cl_jac_uff(r, u_ff, st.yh, st.uh, st.xc, *args)


def jacobian_theta(model: ArxPGNN, ctrl: DiscreteController, r, u_ff, state: LoopState | None = None):
    """Simulation and the exact Jacobian ∂Ŷ/∂θ (N × n_params) of the recurrent closed loop.

    Returns
    -------
    y_hat, u_hat : ndarray
    J : ndarray (N, n_params)
        Column order of :meth:`ArxPGNN.theta`.
    """
    r, u_ff, st, args = _prep(model, ctrl, r, u_ff, state)
    return _cl_jac_theta(r, u_ff, st.yh, st.uh, st.xc, *args)


def simulate_closed_loop_torch(theta, model: ArxPGNN, ctrl: DiscreteController, r, u_ff):
    """Reference implementation in torch (per-sample loop; differentiable, slow).

    ``theta`` and ``u_ff`` may be torch tensors requiring grad; used to cross-check the
    numba kernels by autograd.
    """
    import torch
    p, n1 = model.n_phi, model.n1
    theta = torch.as_tensor(theta, dtype=torch.float64)
    u_ff = torch.as_tensor(u_ff, dtype=torch.float64)
    r = torch.as_tensor(np.asarray(r, dtype=np.float64))
    th = theta[:p]
    W1 = theta[p:p + n1 * p].reshape(n1, p)
    b1 = theta[p + n1 * p:p + n1 * p + n1]
    W2 = theta[p + n1 * p + n1:p + n1 * p + 2 * n1]
    b2 = theta[-1]
    mu = torch.as_tensor(model.phi_mean)
    sd = torch.as_tensor(model.phi_std)
    Ac, Bc, Cc, Dc = (torch.as_tensor(a) for a in ctrl.arrays())
    yh = [torch.zeros((), dtype=torch.float64)] * model.n_a
    uh = [torch.zeros((), dtype=torch.float64)] * (model.n_k + model.n_b)
    xc = torch.zeros(ctrl.n_c, dtype=torch.float64)
    ys, us = [], []
    for k in range(r.shape[0]):
        phi = torch.stack(yh + uh[model.n_k:model.n_k + model.n_b]) if p else torch.zeros(0)
        y = th @ phi
        if n1:
            y = y + model.out_scale * (W2 @ torch.tanh(W1 @ ((phi - mu) / sd) + b1) + b2)
        e = r[k] - y
        u = Dc * e + u_ff[k] + (Cc @ xc if ctrl.n_c else 0.0)
        xc = Ac @ xc + Bc * e if ctrl.n_c else xc
        yh = [y] + yh[:-1] if model.n_a else yh
        uh = [u] + uh[:-1]
        ys.append(y)
        us.append(u)
    return torch.stack(ys), torch.stack(us)


# --------------------------------------------------------------------------------------
# closed-loop simulation-error identification, [B2] (16)
# --------------------------------------------------------------------------------------

def init_pgnn(theta_phy: np.ndarray, orders: tuple[int, int, int], n1: int, y: np.ndarray, u: np.ndarray,
              rng: np.random.Generator, out_scale: float | None = None, w2_scale: float = 1e-2) -> ArxPGNN:
    """PGNN (30) initialised at the physics model: Glorot W1, zero b1, small W2 (SPEC §3).

    Parameters
    ----------
    theta_phy : ndarray
        Physics parameters θ*_phy (the linear model identified first).
    orders : (n_a, n_b, n_k)
    n1 : int
        Hidden neurons (0 = linear model only).
    y, u : ndarray
        Identification data [m], [N]: sets the NN input normalisation (mean/std of φ), the
        default output scale and the model's validity range.
    rng : numpy.random.Generator
    out_scale : float, optional
        NN output scale [m]; default: rms of the one-step residual of the physics model on
        the data (the size of what the physics misses per sample).
    w2_scale : float
        W2 is Glorot-uniform times this factor (initial PGNN ≈ physics model).
    """
    n_a, n_b, n_k = orders
    lin = ArxPGNN(n_a, n_b, n_k, theta_phy)
    phi = lin.regressor(y, u)
    mu = phi.mean(axis=0)
    sd = phi.std(axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    if out_scale is None:
        res = y - phi @ np.asarray(theta_phy, float)
        out_scale = float(np.sqrt(np.mean(res[max(n_a, n_k + n_b):] ** 2)))
        out_scale = out_scale if out_scale > 0 else 1.0
    nphi = n_a + n_b
    lim1 = math.sqrt(6.0 / (nphi + n1)) if n1 else 0.0
    lim2 = math.sqrt(6.0 / (n1 + 1)) if n1 else 0.0
    W1 = rng.uniform(-lim1, lim1, size=(n1, nphi))
    W2 = w2_scale * rng.uniform(-lim2, lim2, size=n1)
    return ArxPGNN(n_a, n_b, n_k, theta_phy, W1, np.zeros(n1), W2, 0.0, mu, sd, out_scale,
                   (float(np.min(y)), float(np.max(y))))


@dataclass
class SimErrorResult:
    """Result of :func:`identify_sim_error`.

    model : identified PGNN; cost : final normalised cost (16); identification_error :
    ‖Y^d - Ŷ^d‖/sqrt(N_d) [m] over the whole record; history : cost per LM iteration;
    val_history : validation cost per iteration (if a validation block was used); n_iter,
    converged, message : from the solver; restart_costs : final cost of every restart;
    time_s : wall time [s].
    """

    model: ArxPGNN
    cost: float
    identification_error: float
    y_hat: np.ndarray
    history: list = field(default_factory=list)
    val_history: list = field(default_factory=list)
    n_iter: int = 0
    converged: bool = False
    message: str = ""
    restart_costs: list = field(default_factory=list)
    time_s: float = 0.0


def _phys_scale(theta_star: np.ndarray) -> np.ndarray:
    """|θ*| elementwise, floored so an (exactly) zero entry does not divide by zero."""
    a = np.abs(np.asarray(theta_star, float))
    floor = 1e-12 * max(float(a.max(initial=0.0)), 1e-300)
    return np.maximum(a, floor)


def sim_error_problem(model0: ArxPGNN, ctrl: DiscreteController, r, u_ff, y, theta_star_phy, lam: float = 1.0,
                      train_slice: slice | None = None):
    """Residual and exact Jacobian of the normalised closed-loop simulation error (16).

    ``res(θ) = [(Y^d - Ŷ^d(θ))/(σ_y sqrt(N_t)) ; λ (θ_phy - θ*_phy)/|θ*_phy|]`` (SPEC §5: residuals
    over the std of y, relative physics deviation, Λ = λ[I, 0]); ‖res‖² is the cost.
    Ŷ^d is simulated over the whole record; only ``train_slice`` samples enter the residual.

    Returns
    -------
    residual : callable θ (ndarray) -> ndarray
    jacobian : callable θ -> ndarray
    """
    r = np.asarray(r, float)
    u_ff = np.asarray(u_ff, float)
    y = np.asarray(y, float)
    sl = train_slice or slice(None)
    yt = y[sl]
    scale = 1.0 / (float(np.std(y)) * math.sqrt(yt.shape[0]))
    nphi = model0.n_phi
    pscale = lam / _phys_scale(theta_star_phy)
    ts = np.asarray(theta_star_phy, float)
    P = model0.n_params

    def residual(theta):
        m = model0.with_theta(theta)
        yh, _ = simulate_closed_loop(m, ctrl, r, u_ff)
        return np.concatenate([(yt - yh[sl]) * scale, pscale * (theta[:nphi] - ts)])

    def jacobian(theta):
        m = model0.with_theta(theta)
        _, _, J = jacobian_theta(m, ctrl, r, u_ff)
        out = np.zeros((yt.shape[0] + nphi, P))
        out[:yt.shape[0]] = -scale * J[sl]
        out[yt.shape[0] + np.arange(nphi), np.arange(nphi)] = pscale
        return out

    return residual, jacobian


def identify_sim_error(model0: ArxPGNN | list, ctrl: DiscreteController, r, u_ff, y, theta_star_phy,
                       lam: float = 1.0, max_iter: int = 200, ftol: float = 1e-10, gtol: float = 1e-12,
                       val_fraction: float = 0.0, patience: int = 10,
                       callback: Callable | None = None) -> SimErrorResult:
    """Closed-loop simulation-error identification [B2] (16) by Levenberg–Marquardt.

    Parameters
    ----------
    model0 : ArxPGNN or list of ArxPGNN
        Initial model(s) (e.g. from :func:`init_pgnn` with different seeds); with several,
        the one with the lowest final training cost wins (SPEC §5 restarts).
    ctrl : DiscreteController
        The known feedback controller C(q).
    r, u_ff, y : ndarray, shape (N_d,)
        Reference R^d [m], feedforward/excitation U_ff^d [N], measured output Y^d [m].
    theta_star_phy : ndarray
        θ*_phy, the linear model identified first (regulariser centre).
    lam : float
        Λ = lam·[I, 0] on the relative physics deviation ([B2] Λ = [I, 0] → lam = 1).
    max_iter, ftol, gtol : solver settings (see ``pipeline.identify.lm``).
    val_fraction : float
        Contiguous tail of the record used for early stopping (0 = none).
    patience : int
        Non-improving validation iterations before stopping.

    Returns
    -------
    SimErrorResult
    """
    import torch

    from pipeline.identify.lm import levenberg_marquardt

    t0 = time.perf_counter()
    y = np.asarray(y, float)
    starts = model0 if isinstance(model0, (list, tuple)) else [model0]
    if not 0.0 <= val_fraction < 0.5:
        raise ValueError(f"val_fraction must be in [0, 0.5), got {val_fraction}")
    N = y.shape[0]
    n_val = int(round(val_fraction * N))
    train = slice(0, N - n_val)
    best = None
    costs = []
    for m0 in starts:
        res_np, jac_np = sim_error_problem(m0, ctrl, r, u_ff, y, theta_star_phy, lam, train)
        val_cost = None
        if n_val:
            res_val, _ = sim_error_problem(m0, ctrl, r, u_ff, y, theta_star_phy, lam, slice(N - n_val, N))

            def val_cost(th, _f=res_val, _n=m0.n_phi):
                v = _f(th.detach().numpy())[:-_n]
                return float(v @ v)

        def residual(th, _f=res_np):
            return torch.from_numpy(_f(th.detach().numpy()))

        def jacobian(th, _f=jac_np):
            return torch.from_numpy(_f(th.detach().numpy()))

        out = levenberg_marquardt(residual, torch.from_numpy(m0.theta()), jacobian=jacobian, max_iter=max_iter,
                                  ftol=ftol, gtol=gtol, val_cost=val_cost, patience=patience, callback=callback)
        costs.append(float(out.cost))
        if best is None or out.cost < best[0].cost:
            best = (out, m0)
    out, m0 = best
    model = m0.with_theta(out.theta.detach().numpy())
    yh, _ = simulate_closed_loop(model, ctrl, r, u_ff)
    ident = float(np.linalg.norm(y - yh) / math.sqrt(N))
    return SimErrorResult(model, float(out.cost), ident, yh, list(out.history), [], out.n_iter, bool(out.converged),
                          str(out.message), costs, time.perf_counter() - t0)
