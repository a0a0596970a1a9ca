"""The [B2] PGNN in closed loop: the model and the controller as arrays, and the simulation.

The model is the PGNN (30) of [B2]: a linear ARX physics model plus one tanh hidden layer
(the forward :class:`pipeline.models.pgnn.PGNN` of [B1] with ``LinearFeatures``, exported to
arrays by :class:`ArxPGNN`),

    ŷ(k) = θ_phyᵀ φ(k) + s_out (W2 tanh(W1 x(k) + b1) + b2),          [B2] (9), (30)
    φ(k) = [ŷ(k-1), …, ŷ(k-n_a), û(k-n_k-1), …, û(k-n_k-n_b)],
    x(k) = P φ(k) + c        (fixed NN input map: δ-basis and normalisation, SPEC §3),

simulated in closed loop with the known discrete controller, no computational delay
(SPEC §0), [B2] (8):

    û(k) = C(q)(r(k) - ŷ(k)) + u_ff(k).

Because φ(k) holds only past û (n_k ≥ 0), the loop has no algebraic loop.  The simulation
and its exact forward sensitivities (w.r.t. the parameters θ for identification,
:mod:`pipeline.identify.sim_error`; w.r.t. the feedforward U_ff for FHOFC,
:mod:`pipeline.invert.fhofc`) run in numba kernels: a per-sample torch loop is two orders of
magnitude slower.  The kernels are checked against finite differences, against a torch
autograd reference (:func:`simulate_closed_loop_torch`) and against python-control.

Parameter vector (order of :meth:`ArxPGNN.theta`, equal to the PGNN module's):
``[θ_phy (n_a + n_b), W1 (n1×n_x, row-major), b1 (n1), W2 (n1), b2]``; θ_phy is the physics
part of [B2] (16)'s Λ = [I, 0].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np
from llvmlite import binding, ir
from numba.core import cgutils
from numba.core.extending import intrinsic

from pipeline.systems._statespace import ss_step, ss_step_columns

__all__ = ["ArxPGNN", "DiscreteController", "LoopState", "as_arx", "arx_from_tf", "nn_export", "nn_split",
           "simulate_closed_loop", "jacobian_uff", "jacobian_theta", "simulate_closed_loop_torch"]

# --------------------------------------------------------------------------------------
# model and controller as plain arrays
# --------------------------------------------------------------------------------------


@dataclass
class ArxPGNN:
    """The PGNN (30) of [B2] as plain float64 arrays (fast closed-loop simulation).

    Mirrors a forward :class:`pipeline.models.pgnn.PGNN` with ARX physics
    (``LinearFeatures``) and at most one tanh hidden layer: :meth:`from_pgnn` exports one,
    :meth:`load_into` writes parameters back; the parameter vector has the module's order.

    Parameters
    ----------
    n_a, n_b, n_k : int
        Orders of φ(k) ([B2] (9)); n_b ≥ 1, n_k ≥ 0.
    theta_phy : ndarray, shape (n_a + n_b,)
        Linear physics model ŷ = θ_phyᵀ φ: coefficients of ŷ(k-1..k-n_a) [-] then of
        û(k-n_k-1..k-n_k-n_b) [m/N].
    W1 : ndarray, shape (n1, n_x)
        Hidden-layer weights acting on the NN input x = P φ + c [-].
    b1 : ndarray, shape (n1,)
        Hidden-layer biases [-].
    W2 : ndarray, shape (n1,)
        Output weights [-] (the NN output is multiplied by ``out_scale``).
    b2 : float
        Output bias [-].
    nn_P, nn_c : ndarray, shapes (n_x, n_a + n_b), (n_x,)
        Fixed affine NN input map (selection, δ-basis, normalisation from training data).
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
    nn_P: np.ndarray = None
    nn_c: np.ndarray = None
    out_scale: float = 1.0
    y_range: tuple[float, float] | None = None

    def __post_init__(self):
        if self.n_a < 0 or self.n_b < 1 or self.n_k < 0:
            raise ValueError(f"orders must satisfy n_a >= 0, n_b >= 1, n_k >= 0; got n_a={self.n_a}, "
                             f"n_b={self.n_b}, n_k={self.n_k}")
        nphi = self.n_a + self.n_b
        self.theta_phy = np.ascontiguousarray(self.theta_phy, dtype=np.float64).reshape(-1)
        if self.theta_phy.shape != (nphi,):
            raise ValueError(f"theta_phy must have n_a + n_b = {nphi} entries, got {self.theta_phy.shape}")
        self.nn_P = np.eye(nphi) if self.nn_P is None else np.ascontiguousarray(self.nn_P, dtype=np.float64)
        if self.nn_P.ndim != 2 or self.nn_P.shape[1] != nphi:
            raise ValueError(f"nn_P must be (n_x, {nphi}), got {self.nn_P.shape}")
        nx = self.nn_P.shape[0]
        self.nn_c = np.zeros(nx) if self.nn_c is None else np.ascontiguousarray(self.nn_c, dtype=np.float64)
        if self.nn_c.shape != (nx,):
            raise ValueError(f"nn_c must have n_x = {nx} entries, got {self.nn_c.shape}")
        if self.W1 is None:
            self.W1 = np.zeros((0, nx))
        self.W1 = np.ascontiguousarray(np.asarray(self.W1, dtype=np.float64).reshape(-1, nx))
        n1 = self.W1.shape[0]
        self.b1 = np.zeros(n1) if self.b1 is None else np.ascontiguousarray(self.b1, np.float64).reshape(-1)
        self.W2 = np.zeros(n1) if self.W2 is None else np.ascontiguousarray(self.W2, np.float64).reshape(-1)
        if self.b1.shape != (n1,) or self.W2.shape != (n1,):
            raise ValueError(f"b1 and W2 must have n1 = {n1} entries (rows of W1), got {self.b1.shape}, "
                             f"{self.W2.shape}")
        self.b2 = float(self.b2)
        self.out_scale = float(self.out_scale)

    # -- conversion from/to the [B1] PGNN module --------------------------------------
    @classmethod
    def from_pgnn(cls, model, y_range: tuple[float, float] | None = None) -> "ArxPGNN":
        """Export a forward ``pipeline.models.pgnn.PGNN`` with ``LinearFeatures`` physics and
        zero or one tanh hidden layer (the PGNN (30) of [B2])."""
        from pipeline.models.physics_maps import LinearFeatures  # lazy: saves 2.7 s of start-up (torch)
        if model.structure not in ("forward", "invertible"):
            raise ValueError(f"closed-loop simulation needs a forward PGNN, got structure={model.structure!r}")
        if not (model.use_physics and isinstance(model.physics, LinearFeatures)
                and model.physics.n_phi == model.n_phi):
            raise ValueError("the [B2] PGNN (30) needs ARX physics: physics=LinearFeatures(n_a + n_b)")
        if model.use_nn and not (len(model.hidden) == 1 and model.activation == "tanh"):
            raise ValueError(f"the [B2] PGNN (30) has one tanh hidden layer, got hidden={model.hidden}, "
                             f"activation={model.activation!r}")
        th = model.theta_phy.detach().numpy().copy()
        return cls(model.n_a, model.n_b, model.n_k, th, y_range=y_range, **nn_export(model))

    def load_into(self, model) -> None:
        """Write this model's parameters into a PGNN module of the same layout."""
        import torch  # lazy: saves 2.2 s of start-up (torch: the closed loop runs on numpy arrays)
        if model.n_params != self.n_params:
            raise ValueError(f"the PGNN has {model.n_params} parameters, this model {self.n_params}")
        model.load_parameter_vector(torch.from_numpy(self.theta()))

    # -- sizes and parameter vector -------------------------------------------------
    @property
    def n_phi(self) -> int:
        return self.n_a + self.n_b

    @property
    def n1(self) -> int:
        return self.W1.shape[0]

    @property
    def n_x(self) -> int:
        return self.nn_P.shape[0]

    @property
    def n_params(self) -> int:
        return self.n_phi + (self.n1 * (self.n_x + 2) + 1 if self.n1 else 0)

    @property
    def delay(self) -> int:
        """Samples from u_ff(j) to the first ŷ it moves: n_k + 1."""
        return self.n_k + 1

    def theta(self) -> np.ndarray:
        """All parameters as one vector (the PGNN module's order; no NN entries if n1 = 0)."""
        if not self.n1:
            return self.theta_phy.copy()
        return np.concatenate([self.theta_phy, self.W1.reshape(-1), self.b1, self.W2, [self.b2]])

    def with_theta(self, theta: np.ndarray) -> "ArxPGNN":
        """A copy with parameters ``theta`` (same orders, input map, scale)."""
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta must have {self.n_params} entries, got {theta.shape}")
        return replace(self, **nn_split(theta, self.n_phi, self.n1, self.n_x))

    def linear_part(self) -> "ArxPGNN":
        """The physics model alone (n1 = 0)."""
        return replace(self, W1=np.zeros((0, self.n_x)), b1=np.zeros(0), W2=np.zeros(0), b2=0.0)

    # -- evaluation -----------------------------------------------------------------
    def one_step(self, phi: np.ndarray) -> np.ndarray:
        """ŷ for regressors ``phi`` [..., n_a + n_b] (vectorised, [B2] (30))."""
        phi = np.asarray(phi, dtype=np.float64)
        y = phi @ self.theta_phy
        if self.n1:
            h = np.tanh((phi @ self.nn_P.T + self.nn_c) @ self.W1.T + self.b1)
            y = y + self.out_scale * (h @ self.W2 + self.b2)
        return y

    def input_gain(self, phi: np.ndarray) -> np.ndarray:
        """∂ŷ/∂u(k-n_k-1) at regressors ``phi`` [..., n_a + n_b] [m/N] (inverse relation (19))."""
        phi = np.asarray(phi, dtype=np.float64)
        g = np.full(phi.shape[:-1], self.theta_phy[self.n_a])
        if self.n1:
            h = np.tanh((phi @ self.nn_P.T + self.nn_c) @ self.W1.T + self.b1)
            col = self.W1 @ self.nn_P[:, self.n_a]          # ∂z/∂u(k-n_k-1)
            g = g + self.out_scale * ((1.0 - h * h) * self.W2) @ col
        return g


def nn_export(model) -> dict:
    """The one tanh hidden layer of a PGNN module as arrays (W1, b1, W2, b2, nn_P, nn_c,
    out_scale); empty without an NN.  Shared by the array models of the closed-loop kernels."""
    if not model.use_nn:
        return {}
    l1, l2 = model.layers
    return dict(W1=l1.weight.detach().numpy().copy(), b1=l1.bias.detach().numpy().copy(),
                W2=l2.weight.detach().numpy()[0].copy(), b2=float(l2.bias.detach()[0]),
                nn_P=model.nn_P.numpy().copy(), nn_c=model.nn_c.numpy().copy(), out_scale=float(model.out_scale))


def nn_split(theta: np.ndarray, p: int, n1: int, nx: int) -> dict:
    """θ in the PGNN module's order [θ_phy (p), W1 (n1×nx), b1, W2, b2] as the array models'
    fields (θ_phy alone without an NN)."""
    if not n1:
        return {"theta_phy": theta.copy()}
    i = p + n1 * nx
    return {"theta_phy": theta[:p].copy(), "W1": theta[p:i].reshape(n1, nx).copy(), "b1": theta[i:i + n1].copy(),
            "W2": theta[i + n1:i + 2 * n1].copy(), "b2": float(theta[i + 2 * n1])}


def as_arx(model) -> ArxPGNN:
    """``model`` as :class:`ArxPGNN` (exports a PGNN module, passes an ArxPGNN through)."""
    return model if isinstance(model, ArxPGNN) else ArxPGNN.from_pgnn(model)


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
    import control  # lazy: saves 1.9 s of start-up (python-control)
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
        import control  # lazy: saves 1.9 s of start-up (python-control)
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
def _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, phi, x, hbuf, g, need_g):
    """One step of [B2] (30): returns ŷ; fills phi, x = Pφ + c (NN input), hbuf = tanh and,
    if ``need_g``, g = ∂ŷ/∂φ."""
    nphi = n_a + n_b
    nx = P.shape[0]
    n1 = W1.shape[0]
    for i in range(n_a):
        phi[i] = yh[i]
    for i in range(n_b):
        phi[n_a + i] = uh[n_k + i]
    y = 0.0
    for j in range(nphi):
        y += th[j] * phi[j]
    if need_g:
        for j in range(nphi):
            g[j] = th[j]
    if n1 == 0:
        return y
    for i in range(nx):
        s = c[i]
        for j in range(nphi):
            s += P[i, j] * phi[j]
        x[i] = s
    for i in range(n1):
        z = b1[i]
        for j in range(nx):
            z += W1[i, j] * x[j]
        h = math.tanh(z)
        hbuf[i] = h
        y += so * W2[i] * h
    y += so * b2
    if need_g:
        # ∂ŷ/∂φ = θ_phy + Pᵀ W1ᵀ (s_out W2 ⊙ sech²(z)); sech² = 1 - tanh², no overflow (SPEC §0)
        for m in range(nx):
            v = 0.0
            for i in range(n1):
                h = hbuf[i]
                v += so * W2[i] * (1.0 - h * h) * W1[i, m]
            for j in range(nphi):
                g[j] += v * P[m, j]
    return y


@numba.njit(cache=True, inline="always")
def _loop_buffers(N, n_a, n_b, P, W1, nc):
    """Outputs ŷ, û (length N) and the per-sample scratch of :func:`_model_eval` (φ, NN input,
    tanh, ∂ŷ/∂φ) and of the controller step (next state): (yhat, uhat, phi, x, hbuf, g, xn)."""
    nphi = n_a + n_b
    return (np.empty(N), np.empty(N), np.empty(nphi), np.empty(P.shape[0]), np.empty(max(W1.shape[0], 1)),
            np.empty(nphi), np.empty(nc))


@numba.njit(cache=True, inline="always")
def _loop_advance(y, r_k, uff_k, yh, uh, xc, xn, Ac, Bc, Cc, Dc):
    """Close the loop at sample k given ŷ(k) = ``y``: returns û(k) = C x_c + D (r(k) - ŷ(k)) +
    u_ff(k) ([B2] (8), no computational delay), advances x_c and shifts ŷ, û into the
    histories yh, uh (all in place)."""
    u = ss_step(Ac, Bc, Cc, Dc, xc, xn, r_k - y, uff_k)
    for i in range(yh.shape[0] - 1, 0, -1):
        yh[i] = yh[i - 1]
    if yh.shape[0] > 0:
        yh[0] = y
    for i in range(uh.shape[0] - 1, 0, -1):
        uh[i] = uh[i - 1]
    uh[0] = u
    return u


@numba.njit(cache=True, inline="always")
def _chain_past(acc, g, J, Ju, k, n_a, n_b, n_k, causal):
    """Chain rule through the recurrent regressor φ(k) = [ŷ(k-1..k-n_a), û(k-n_k-1..)]:
    ``acc += Σ_i g_i J[k-i] + Σ_i g_{n_a+i} Ju[k-n_k-i]`` (g = ∂ŷ/∂φ, J/Ju rows = ∂ŷ/∂·, ∂û/∂·).
    With ``causal`` the columns are inputs u_ff(j) and only those that can reach the lagged
    sample are summed (j < k-i for ŷ(k-i), j ≤ k-n_k-i for û(k-n_k-i)); the rest are zero."""
    n = acc.shape[0]
    for i in range(1, n_a + 1):
        if k - i >= 0:
            gi = g[i - 1]
            for j in range(k - i if causal else n):
                acc[j] += gi * J[k - i, j]
    for i in range(1, n_b + 1):
        lag = n_k + i
        if k - lag >= 0:
            gi = g[n_a + i - 1]
            for j in range(k - lag + 1 if causal else n):
                acc[j] += gi * Ju[k - lag, j]


@numba.njit(cache=True)
def _cl_simulate(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc):
    """Closed-loop model simulation [B2] (8)+(30); yh, uh, xc are updated in place."""
    N = r.shape[0]
    yhat, uhat, phi, x, hbuf, g, xn = _loop_buffers(N, n_a, n_b, P, W1, xc.shape[0])
    for k in range(N):
        y = _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, phi, x, hbuf, g, False)
        u = _loop_advance(y, r[k], uff[k], yh, uh, xc, xn, Ac, Bc, Cc, Dc)
        yhat[k] = y
        uhat[k] = u
    return yhat, uhat


@numba.njit(cache=True)
def _cl_jac_uff(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc):
    """Simulation plus J[k, j] = ∂ŷ(k)/∂u_ff(j) (lower triangular, forward sensitivities)
    and Ju[k, j] = ∂û(k)/∂u_ff(j)."""
    N = r.shape[0]
    nc = xc.shape[0]
    yhat, uhat, phi, x, hbuf, g, xn = _loop_buffers(N, n_a, n_b, P, W1, nc)
    J = np.zeros((N, N))
    Ju = np.zeros((N, N))
    Sx = np.zeros((nc, N))     # Sx[:, j] = ∂x_c(k)/∂u_ff(j)
    Sxn = np.zeros((nc, N))
    nBc = -Bc                  # ∂e = -∂ŷ: the controller seen from ŷ is (A, -B, C, -D)
    for k in range(N):
        y = _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, phi, x, hbuf, g, True)
        # ∂ŷ(k)/∂u_ff(j), j < k: chain through past ŷ and û
        _chain_past(J[k], g, J, Ju, k, n_a, n_b, n_k, True)
        # û(k) = C x_c + D e + u_ff(k), x_c(k+1) = A x_c + B e, differentiated (∂e = -∂ŷ)
        ss_step_columns(Ac, nBc, Cc, -Dc, Sx, Sxn, J[k], Ju[k], k + 1)
        Ju[k, k] = 1.0                                    # ∂u_ff(k)/∂u_ff(k); J[k, k] = Sx[:, k] = 0
        u = _loop_advance(y, r[k], uff[k], yh, uh, xc, xn, Ac, Bc, Cc, Dc)
        yhat[k] = y
        uhat[k] = u
    return yhat, uhat, J, Ju


_SENS_CHUNK = 64   # samples whose per-sample NN quantities (x, sech² terms, ∂ŷ/∂φ) are formed at once
_SENS_BATCH = 8    # rows of J kept in the ring and written out together (one streaming copy)
_SENS_PREFETCH = 16  # rows of the output whose cache lines are requested ahead of their write
_SENS_PREFETCH_H = 32  # samples of H (hidden tanh) requested ahead of their write


@intrinsic
def _prefetch_w(typingctx, a, i):
    """Hint: fetch the cache line of ``a[i]`` (1-D contiguous array) for writing (x86 prefetchw;
    ``llvm.prefetch``).  No effect on any value.  Issued some rows ahead of the streaming writes
    of J and of the recorded tanh H, whose cache lines would otherwise be fetched one at a time
    when the rows are written (measured: ~0.4 ms of the 4,500 × 329 B2 Jacobian's ~3 ms)."""
    sig = numba.types.void(a, i)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        name = "llvm.prefetch.p0" if binding.llvm_version_info >= (15,) else "llvm.prefetch.p0i8"
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            name)
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), i8p)
        builder.call(fn, [ptr, ir.Constant(i32, 1), ir.Constant(i32, 3), ir.Constant(i32, 1)])  # write, keep, data
        return context.get_dummy_value()
    return sig, codegen


@numba.njit(cache=True)
def _cl_simulate_record(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc,
                        yhat, uhat, H):
    """:func:`_cl_simulate` into the given outputs ŷ, û (length N), also recording the hidden
    layer's tanh, H[k] = tanh(W1 x(k) + b1) (N × n1), for :func:`_cl_sens_theta`.  Same
    floating-point operations as :func:`_cl_simulate` (ŷ, û equal to the bit); yh, uh, xc are
    updated in place."""
    N = r.shape[0]
    n1 = W1.shape[0]
    nphi = n_a + n_b
    phi = np.empty(nphi)
    x = np.empty(P.shape[0])
    hbuf = np.empty(max(n1, 1))
    g = np.empty(nphi)
    xn = np.empty(xc.shape[0])
    for k in range(N):
        if n1 > 0 and k + _SENS_PREFETCH_H < N:     # H's row _SENS_PREFETCH_H samples ahead
            hrow = H[k + _SENS_PREFETCH_H]
            for i in range(0, n1, 8):
                _prefetch_w(hrow, i)
            _prefetch_w(hrow, n1 - 1)
        y = _model_eval(yh, uh, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, phi, x, hbuf, g, False)
        for i in range(n1):
            H[k, i] = hbuf[i]
        u = _loop_advance(y, r[k], uff[k], yh, uh, xc, xn, Ac, Bc, Cc, Dc)
        yhat[k] = y
        uhat[k] = u


@numba.njit(cache=True, inline="always")
def _add_terms(s, R, rows, a, q0, m, n):
    """``s[p] += a[q0] R[rows[q0], p]; s[p] += a[q0+1] R[rows[q0+1], p]; …`` for m ∈ {1, 2, 4, 8}
    terms in that order (the floating-point operations of :func:`_chain_past`), p < n: one
    contiguous, vectorised sweep over p per group, the partial sum held in registers."""
    if m == 8:
        c0, c1, c2, c3 = a[q0], a[q0 + 1], a[q0 + 2], a[q0 + 3]
        c4, c5, c6, c7 = a[q0 + 4], a[q0 + 5], a[q0 + 6], a[q0 + 7]
        r0, r1, r2, r3 = rows[q0], rows[q0 + 1], rows[q0 + 2], rows[q0 + 3]
        r4, r5, r6, r7 = rows[q0 + 4], rows[q0 + 5], rows[q0 + 6], rows[q0 + 7]
        for p in range(n):
            t = s[p]
            t += c0 * R[r0, p]
            t += c1 * R[r1, p]
            t += c2 * R[r2, p]
            t += c3 * R[r3, p]
            t += c4 * R[r4, p]
            t += c5 * R[r5, p]
            t += c6 * R[r6, p]
            t += c7 * R[r7, p]
            s[p] = t
    elif m == 4:
        c0, c1, c2, c3 = a[q0], a[q0 + 1], a[q0 + 2], a[q0 + 3]
        r0, r1, r2, r3 = rows[q0], rows[q0 + 1], rows[q0 + 2], rows[q0 + 3]
        for p in range(n):
            t = s[p]
            t += c0 * R[r0, p]
            t += c1 * R[r1, p]
            t += c2 * R[r2, p]
            t += c3 * R[r3, p]
            s[p] = t
    elif m == 2:
        c0, c1 = a[q0], a[q0 + 1]
        r0, r1 = rows[q0], rows[q0 + 1]
        for p in range(n):
            t = s[p]
            t += c0 * R[r0, p]
            t += c1 * R[r1, p]
            s[p] = t
    else:
        c0 = a[q0]
        r0 = rows[q0]
        for p in range(n):
            s[p] += c0 * R[r0, p]


@numba.njit(cache=True, inline="always")
def _fill_direct(s, q, Ph, X, CT, SHT, xq, nphi, n1, nx, so):
    """The explicit ∂f/∂θ at fixed φ of block sample q into s (the parameter order of
    :meth:`ArxPGNN.theta`): φ, the outer product c_i x_j (W1), c_i (b1), s_out h_i (W2), s_out (b2).
    Indices are unsigned where it matters: numba then emits no negative-index test and the short
    inner loops vectorise."""
    for j in range(nphi):
        s[j] = Ph[j, q]
    if n1 > 0:
        for m in range(nx):
            xq[m] = X[m, q]
        ob1 = np.uint64(nphi + n1 * nx)
        oW2 = ob1 + np.uint64(n1)
        for i in range(n1):
            ci = CT[q, i]
            b = np.uint64(nphi + i * nx)
            for m in range(nx):
                s[b + np.uint64(m)] = ci * xq[m]
        for i in range(n1):
            s[ob1 + np.uint64(i)] = CT[q, i]
        for i in range(n1):
            s[oW2 + np.uint64(i)] = SHT[q, i]
        s[oW2 + np.uint64(n1)] = so


@numba.njit(cache=True)
def _cl_sens_theta(H, yhat, uhat, yh0, uh0, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc,
                   out, k0, k1, scale):
    """Forward sensitivities J[k, p] = ∂ŷ(k)/∂θ_p of the recurrent loop along a simulated
    trajectory (ŷ, û and the hidden tanh H (N × n1) from :func:`_cl_simulate_record`, started from
    the histories yh0, uh0 and a controller state independent of θ): rows k0 ≤ k < k1 are written
    as ``out[k - k0] = J[k] * scale`` (e.g. the criterion's -1/(σ sqrt(N_t)), in place); rows k < k0
    are computed (the recursion needs them) but not written, rows k ≥ k1 not computed.

    Per sample, with φ(k) = [ŷ(k-1..k-n_a), û(k-n_k-1..k-n_k-n_b)] and g = ∂ŷ/∂φ:

        J(k) = ∂f/∂θ|_φ + Σ_i g_i J(k-i) + Σ_i g_{n_a+i} J_u(k-n_k-i),
        J_u(k) = C S(k) - D J(k),  S(k+1) = A S(k) - B J(k)       (controller, ∂e = -∂ŷ)

    - the per-sample quantities that do not depend on J (φ, x = Pφ + c, c_i = s_out W2_i sech²z_i,
      g) are formed for blocks of _SENS_CHUNK samples, the sample index innermost (vectorised);
    - the explicit gradient ∂f/∂θ|_φ = [φ, c_i x_j (outer product, W1), c_i, s_out h_i, s_out]
      is written one sample ahead, into its row of the ring;
    - the past rows of J (max(n_a + 1, _SENS_BATCH)) and J_u (n_k + n_b + 1) live in one ring
      buffer, so the working set stays in cache and nothing of size N × p is allocated here: a
      row of J costs one contiguous sweep for its lagged terms (up to 8 at once, the partial sum
      in registers) and one for J_u and the controller sensitivities S;
    - rows of J leave the ring _SENS_BATCH at a time (one streaming copy, scaled), their cache
      lines requested _SENS_PREFETCH rows ahead.

    The floating-point operations and their order are those of the per-sample reference
    (:func:`_model_eval` for g, :func:`_chain_past`, :func:`ss_step_columns`), without fastmath:
    the result is equal to the bit to the unfused kernel's."""
    nphi = n_a + n_b
    n1 = W1.shape[0]
    nx = P.shape[0]
    NP = nphi + n1 * (nx + 2) + 1 if n1 > 0 else nphi
    nc = Ac.shape[0]
    K = _SENS_CHUNK
    WA = max(n_a + 1, _SENS_BATCH)   # ring rows of J: J(k') at k' % WA (never a lag of k)
    WU = n_k + n_b + 1               # ring rows of J_u: J_u(k') at WA + k' % WU
    HR = np.empty((WA + WU, NP))     # J(k) is formed in place in its ring row
    Sx = np.zeros((nc, NP))    # ∂x_c(k)/∂θ
    Xn = np.empty((nc, NP))
    coef = np.empty(max(nphi, 1))
    rows = np.empty(max(nphi, 1), dtype=np.int64)
    Ph = np.empty((nphi, K))   # blocks, sample index innermost
    X = np.empty((nx, K))
    V = np.empty((nx, K))
    C = np.empty((n1, K))
    CT = np.empty((K, n1))     # c_i and s_out h_i, sample-major (rows of the explicit gradient)
    SHT = np.empty((K, n1))
    aW = so * W2
    G = np.empty((nphi, K))
    xq = np.empty(nx)
    nBc = -Bc                  # the controller seen from ŷ is (A, -B, C, -D)
    nDc = -Dc
    for c0 in range(0, k1, K):
        kk = min(K, k1 - c0)
        # φ(k) from the trajectory (ŷ(m), û(m) of m < 0 from the initial histories)
        for i in range(n_a):
            for q in range(kk):
                m = c0 + q - 1 - i
                Ph[i, q] = yhat[m] if m >= 0 else yh0[-1 - m]
        for i in range(n_b):
            for q in range(kk):
                m = c0 + q - n_k - 1 - i
                Ph[n_a + i, q] = uhat[m] if m >= 0 else uh0[-1 - m]
        # g = ∂ŷ/∂φ = θ_phy + Pᵀ W1ᵀ (s_out W2 ⊙ sech²(z)) in _model_eval's order
        for j in range(nphi):
            t = th[j]
            for q in range(kk):
                G[j, q] = t
        if n1 > 0:
            for i in range(nx):
                t = c[i]
                for q in range(kk):
                    X[i, q] = t
                    V[i, q] = 0.0
                for j in range(nphi):
                    pij = P[i, j]
                    for q in range(kk):
                        X[i, q] += pij * Ph[j, q]
            Hc = H[c0:c0 + kk]
            for q in range(kk):
                for i in range(n1):
                    h = Hc[q, i]
                    CT[q, i] = aW[i] * (1.0 - h * h)     # = s_out W2_i sech²(z_i), _model_eval's order
                    SHT[q, i] = so * h
            for i in range(n1):
                for q in range(kk):
                    C[i, q] = CT[q, i]
                for m in range(nx):
                    w = W1[i, m]
                    for q in range(kk):
                        V[m, q] += C[i, q] * w
            for m in range(nx):
                for j in range(nphi):
                    pmj = P[m, j]
                    for q in range(kk):
                        G[j, q] += V[m, q] * pmj
        # the explicit gradient of a sample is written one sample ahead (here, then after the
        # lagged terms of the previous one): its narrow stores have reached the cache when the
        # wide loads of the lagged-terms sweep read them (no store-forwarding stalls)
        _fill_direct(HR[c0 % WA], 0, Ph, X, CT, SHT, xq, nphi, n1, nx, so)
        for q in range(kk):
            k = c0 + q
            ku = WA + k % WU
            s = HR[k % WA]
            # chain through φ(k): lags of ŷ available for k - i ≥ 0, of û for k - n_k - i ≥ 0
            nJ = min(n_a, k)
            nU = max(min(n_b, k - n_k), 0)
            for i in range(nJ):
                coef[i] = G[i, q]
                rows[i] = (k - 1 - i) % WA
            for i in range(nU):
                coef[nJ + i] = G[n_a + i, q]
                rows[nJ + i] = WA + (k - n_k - 1 - i) % WU
            T = nJ + nU
            i = 0
            while i < T:
                m = 8 if T - i >= 8 else (4 if T - i >= 4 else (2 if T - i >= 2 else 1))
                _add_terms(s, HR, rows, coef, i, m, NP)
                i += m
            # J(k) is final: a full batch of rows (ring positions 0..WA-1, in order) goes out;
            # the lines of a row _SENS_PREFETCH rows further are requested now
            o2 = k - k0 + _SENS_PREFETCH
            if 0 <= o2 < out.shape[0]:
                orow = out[o2]
                for p in range(0, NP, 8):
                    _prefetch_w(orow, p)
                _prefetch_w(orow, NP - 1)
            if (k + 1) % WA == 0 or k == k1 - 1:
                kb = max(k - k % WA, k0)
                if kb <= k:
                    src = HR[kb % WA:k % WA + 1].reshape(-1)
                    dst = out[kb - k0:k - k0 + 1].reshape(-1)
                    for p in range(src.shape[0]):
                        dst[p] = src[p] * scale
            if q + 1 < kk:          # J(k + 1 - WA)'s row is free now
                _fill_direct(HR[(k + 1) % WA], q + 1, Ph, X, CT, SHT, xq, nphi, n1, nx, so)
            # J_u(k) = -D J(k) + C S(k), S(k+1) = A S(k) - B J(k) (ss_step_columns' order)
            if nc == 1:
                c00 = Cc[0]
                b00 = nBc[0]
                a00 = Ac[0, 0]
                for p in range(NP):
                    t = s[p]
                    z = Sx[0, p]
                    y = nDc * t
                    y += c00 * z
                    zn = b00 * t
                    zn += a00 * z
                    HR[ku, p] = y
                    Sx[0, p] = zn
                continue
            for p in range(NP):
                HR[ku, p] = nDc * s[p]
            for i in range(nc):
                cci = Cc[i]
                bi = nBc[i]
                for p in range(NP):
                    HR[ku, p] += cci * Sx[i, p]
                    Xn[i, p] = bi * s[p]
                for j in range(nc):
                    a = Ac[i, j]
                    for p in range(NP):
                        Xn[i, p] += a * Sx[j, p]
            Sx, Xn = Xn, Sx


@numba.njit(cache=True)
def _cl_jac_theta(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc):
    """Simulation plus J[k, p] = ∂ŷ(k)/∂θ_p (forward sensitivities of the recurrent loop):
    :func:`_cl_simulate_record` then :func:`_cl_sens_theta`; yh, uh, xc are updated in place."""
    N = r.shape[0]
    nphi = n_a + n_b
    n1 = W1.shape[0]
    NP = nphi + n1 * (P.shape[0] + 2) + 1 if n1 > 0 else nphi
    yh0 = yh.copy()
    uh0 = uh.copy()
    yhat = np.empty(N)
    uhat = np.empty(N)
    H = np.empty((N, n1))
    _cl_simulate_record(r, uff, yh, uh, xc, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc,
                        yhat, uhat, H)
    J = np.empty((N, NP))
    # k0 = 0 as an int64, not the literal 0: the same specialisation of the kernel that the fits call from
    # Python (a literal compiles a second one, ~8 s; the same operations, the same bits)
    _cl_sens_theta(H, yhat, uhat, yh0, uh0, n_a, n_b, n_k, th, W1, b1, W2, b2, P, c, so, Ac, Bc, Cc, Dc,
                   J, np.int64(0), N, 1.0)
    return yhat, uhat, J


# --------------------------------------------------------------------------------------
# public simulation API
# --------------------------------------------------------------------------------------

def _prep(model, ctrl: DiscreteController, r, u_ff, state: LoopState | None):
    model = as_arx(model)
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
            model.nn_P, model.nn_c, model.out_scale, Ac, Bc, Cc, Dc)
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
    import torch  # lazy: saves 2.2 s of start-up (torch: the closed loop runs on numpy arrays)
    model = as_arx(model)
    p, n1, nx = model.n_phi, model.n1, model.n_x
    theta = torch.as_tensor(theta, dtype=torch.float64)
    u_ff = torch.as_tensor(u_ff, dtype=torch.float64)
    r = torch.as_tensor(np.asarray(r, dtype=np.float64))
    th = theta[:p]
    W1 = theta[p:p + n1 * nx].reshape(n1, nx)
    b1 = theta[p + n1 * nx:p + n1 * nx + n1]
    W2 = theta[p + n1 * nx + n1:p + n1 * nx + 2 * n1]
    b2 = theta[-1]
    Pm = torch.as_tensor(model.nn_P)
    cv = torch.as_tensor(model.nn_c)
    Ac, Bc, Cc, Dc = (torch.as_tensor(a) for a in ctrl.arrays())
    yh = [torch.zeros((), dtype=torch.float64)] * model.n_a
    uh = [torch.zeros((), dtype=torch.float64)] * (model.n_k + model.n_b)
    xc = torch.zeros(ctrl.n_c, dtype=torch.float64)
    ys, us = [], []
    for k in range(r.shape[0]):
        phi = torch.stack(yh + uh[model.n_k:model.n_k + model.n_b]) if p else torch.zeros(0)
        y = th @ phi
        if n1:
            y = y + model.out_scale * (W2 @ torch.tanh(W1 @ (Pm @ phi + cv) + b1) + b2)
        e = r[k] - y
        u = Dc * e + u_ff[k] + (Cc @ xc if ctrl.n_c else 0.0)
        xc = Ac @ xc + Bc * e if ctrl.n_c else xc
        yh = [y] + yh[:-1] if model.n_a else yh
        uh = [u] + uh[:-1]
        ys.append(y)
        us.append(u)
    return torch.stack(ys), torch.stack(us)
