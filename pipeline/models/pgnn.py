"""Physics-guided neural networks of [B1] (SPEC §3, models 1, 3, 4, 5).

A PGNN predicts one sample of a NARX model from a regressor vector φ ([B1] (10), (13), (26)):

    ŷ(θ, φ) = f_phy(θ_phy, φ) + f_NN(θ_NN, φ),      f_phy(θ_phy, φ) = T₀(φ) + T(φ) θ_phy

The physics part is linear in its parameters (SPEC §3 item 1): a :class:`PhysicsFeatures`
map returns the parameter-free offset T₀(φ) and the feature rows T(φ); any plant plugs in
its own map.  The NN part is an MLP ([B1] (11)) on a fixed affine map of φ (selection,
optional δ-basis of the output window, normalisation by training statistics, all stored as
buffers), times a fixed output scale.

Regressor layouts (``structure``):

- ``'forward'`` ([B1] (1), (10)): φ(t) = [y(t-1), …, y(t-n_a), u(t-n_k-1), …, u(t-n_k-n_b)],
  target y(t).  The most recent input u(t-n_k-1) sits at ``phi[:, n_a]``.
- ``'invertible'`` ([B1] (26)): as ``'forward'`` but the NN does not see u(t-n_k-1).
- ``'inverse'`` ([B1] (13)): φ'(t) = [y(t+n_k+1), …, y(t+n_k-n_a+1), u(t-1), …, u(t-n_b+1)],
  target u(t).

Physics-only (``use_nn=False``) and black-box (``use_physics=False``, [B1] Remark 2.2) models
are the same class with one part switched off.  In simulation (NOE) mode a caller builds φ
from the model's own past outputs and calls :meth:`PGNN.forward` (batched, one step).

The physics maps live in :mod:`pipeline.models.physics_maps`; the numba fast path of a
one-hidden-layer tanh PGNN (flat arrays for the per-sample inversions of ``pipeline.invert``)
in :mod:`pipeline.models.fast_pgnn`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import llvmlite.binding as _llvm
import numba
import numpy as np
import torch
from numba import types as _nbt
from numba.extending import get_cython_function_address as _cython_address
from scipy.linalg.blas import dsyrk as _dsyrk
from torch import nn

from pipeline.models import activations
from pipeline.models.physics_maps import PhysicsFeatures
from pipeline.params import schema, spec

_WIDTHS = "widths must be positive integers"


@schema
class Params:
    name: str = "pgnn-forward"
    structure: Literal["forward", "inverse", "invertible"] = "forward"
    # output lags in φ (SPEC §2.2: n_a = 2 for [B1] (32))
    n_a: int = spec(2, ge=0, le=1000)
    # input lags in φ (u(t-n_k-1) .. u(t-n_k-n_b))
    n_b: int = spec(1, ge=1, le=1000)
    n_k: int = spec(0, ge=0, le=1000)
    # hidden-layer widths; [B1] §VI: one layer of 16 tanh neurons
    hidden: list[int] = spec([16], ge=1, le=100_000, rule=_WIDTHS)
    # tanh | sigmoid | relu | softplus | elu | gelu | identity
    activation: Literal["tanh", "sigmoid", "relu", "softplus", "elu", "gelu", "identity"] = "tanh"
    # false: black-box NN ([B1] Remark 2.2)
    use_physics: bool = True
    # false: physics-only model, closed-form LS [B1] (7)
    use_nn: bool = True
    # NN input basis: raw φ ([B1] (11): f_NN(θ_NN, φ)) | delta (y, Δy, Δ²y, …: the same model class, but on the linear
    # motor the NN then leans on velocity, fits the position ripple worse and extrapolates badly above the 0.05 m/s
    # training speed: Newton MAE 1.1e-5 vs 3.4e-6 m with raw at 0.05 m/s, physics 1.3e-5)
    input_transform: Literal["raw", "delta"] = "raw"
    # mirrored: paired hidden units with opposite output weights, initial PGNN = physics model (SPEC §3) with live
    # hidden units | scaled: output weights = Glorot × out_init_scale (1e-3 leaves LM stuck on the linear motor: R² of
    # the NN vs the true unmodelled part 0.10, mirrored 0.29)
    out_init: Literal["mirrored", "scaled"] = "mirrored"
    # output-layer weight scale at initialisation (× Glorot)
    out_init_scale: float = spec(1.0, ge=0, le=1e6)
    # mirrored: each twin's input weights + this × a Glorot draw (0: exact twins, which start on the overlap
    # singularity and part only by rounding; pipeline/models/pgnn.py)
    mirror_jitter: float = spec(0.0, ge=0, le=10)
    # all: the NN sees φ (as selected by the structure) | outputs: the output window only (a position-dependent
    # nonlinearity; no input-to-output path of its own)
    nn_inputs: Literal["all", "outputs"] = "all"


__all__ = ["PGNN", "Prepared", "blas_syrk_lower", "blas_gemv_n"]

_ACTIVATIONS = {
    "tanh": activations.tanh,
    "sigmoid": torch.sigmoid,
    "relu": torch.relu,
    "softplus": nn.functional.softplus,
    "elu": nn.functional.elu,
    "gelu": nn.functional.gelu,
    "identity": lambda x: x,
}
#: in-place forms of the activations that have one (the same elementwise function)
_ACTIVATIONS_INPLACE = {"tanh": activations.tanh_, "sigmoid": torch.sigmoid_, "relu": torch.relu_}
_STRUCTURES = ("forward", "inverse", "invertible")


# --------------------------------------------------------------------------------------------
# closed-form Jacobian of one hidden layer (numba)
# --------------------------------------------------------------------------------------------
# activations whose derivative is a function of their value: h' = 1 - h² (tanh), h (1 - h) (sigmoid), 1
_DERIVATIVE_FROM_VALUE = {"tanh": 0, "sigmoid": 1, "identity": 2}


@numba.njit(cache=True)
def _one_hidden_jacobian_rows(J, T, x, h, w2s, s, act, scale):
    """Rows of scale · ∂ŷ/∂θ for ŷ = T₀ + T θ_phy + s (W2 h(W1 x + b1) + b2) ([B1] (10), (11)),
    parameter order [θ_phy, W1 (H × n), b1, W2, b2]: T, G ⊗ x, G, s h, s with G = h' · (s W2)
    (∂ŷ/∂ pre-activation, ``w2s`` = s W2).  Each entry is the same IEEE product, times scale,
    as the vectorised formula (no fused multiply-add), in one pass over the rows of J."""
    M, n = x.shape
    H = h.shape[1]
    p = T.shape[1]
    c = p + H * n
    G = np.empty(H)
    for m in range(M):
        for i in range(p):
            J[m, i] = T[m, i] * scale
        for j in range(H):
            hj = h[m, j]
            if act == 0:
                G[j] = (1.0 - hj * hj) * w2s[j]
            elif act == 1:
                G[j] = (hj * (1.0 - hj)) * w2s[j]
            else:
                G[j] = w2s[j]
        q = p
        for j in range(H):
            for k in range(n):
                J[m, q] = (G[j] * x[m, k]) * scale
                q += 1
        for j in range(H):
            J[m, c + j] = G[j] * scale
            J[m, c + H + j] = (h[m, j] * s) * scale
        J[m, c + 2 * H] = s * scale


# --------------------------------------------------------------------------------------------
# BLAS from numba kernels: scipy's own BLAS (the library behind scipy.linalg.blas), so a kernel
# that reduces row blocks of J calls the very routine a Python loop over the blocks would call
# --------------------------------------------------------------------------------------------
def _blas_function(name: str, n_args: int):
    """scipy.linalg.cython_blas ``name`` (Fortran convention: every argument a pointer) as a numba
    external function; the symbol is registered with LLVM at import, so cached kernels resolve it."""
    symbol = f"pipeline_scipy_blas_{name}"
    _llvm.add_symbol(symbol, _cython_address("scipy.linalg.cython_blas", name))
    return _nbt.ExternalFunction(symbol, _nbt.void(*([_nbt.voidptr] * n_args)))


_blas_dsyrk = _blas_function("dsyrk", 10)
_blas_dgemv = _blas_function("dgemv", 11)


@numba.njit(cache=True)
def blas_syrk_lower(n, k, a, c):
    """c += a aᵀ on the lower triangle of the Fortran-ordered n×n ``c``; ``a`` holds an n×k
    Fortran-ordered matrix (i.e. k C-ordered rows of length n: c += JᵀJ for a row block J)."""
    ch = np.empty(2, np.uint8)
    ch[0], ch[1] = 76, 78                              # 'L', 'N'
    iv = np.empty(3, np.int32)
    iv[0], iv[1], iv[2] = n, k, n
    dv = np.ones(2)
    _blas_dsyrk(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, iv[1:].ctypes, dv[0:].ctypes, a.ctypes,
                iv[2:].ctypes, dv[1:].ctypes, c.ctypes, iv[2:].ctypes)


@numba.njit(cache=True)
def blas_gemv_n(m, n, a, x, beta, y):
    """y = a x + beta y for the Fortran-ordered m×n ``a`` (n C-ordered rows of length m: y = Jᵀx for a
    row block J); ``x`` holds n entries, ``y`` m."""
    ch = np.empty(1, np.uint8)
    ch[0] = 78                                         # 'N'
    iv = np.empty(3, np.int32)
    iv[0], iv[1], iv[2] = m, n, 1
    dv = np.empty(2)
    dv[0], dv[1] = 1.0, beta
    _blas_dgemv(ch.ctypes, iv[0:].ctypes, iv[1:].ctypes, dv[0:].ctypes, a.ctypes, iv[0:].ctypes,
                x.ctypes, iv[2:].ctypes, dv[1:].ctypes, y.ctypes, iv[2:].ctypes)


@numba.njit(cache=True)
def _one_hidden_rows_input_major(J, T, x, h, a, w2s, s, act, scale, G):
    """Rows a, a+1, … (as many as ``J`` has) of :func:`_one_hidden_jacobian_rows`, the same
    products, with the W1 columns input-major (column p + k H + j holds ∂ŷ/∂W1[j, k], not
    p + j n + k): every inner loop runs over the H hidden units, contiguous in J, h and G, with
    unsigned offsets (no negative-index fix-up), so it is vectorised."""
    u = np.uint64
    n = x.shape[1]
    H = h.shape[1]
    p = T.shape[1]
    c = u(p + H * n)
    for i in range(J.shape[0]):
        m = a + i
        row = J[i]
        for q in range(p):
            row[q] = T[m, q] * scale
        hm = h[m]
        if act == 0:
            for j in range(H):
                G[j] = (1.0 - hm[j] * hm[j]) * w2s[j]
        elif act == 1:
            for j in range(H):
                G[j] = (hm[j] * (1.0 - hm[j])) * w2s[j]
        else:
            for j in range(H):
                G[j] = w2s[j]
        for k in range(n):
            xk = x[m, k]
            q = u(p + k * H)
            for j in range(H):
                row[q + u(j)] = (G[j] * xk) * scale
        for j in range(H):
            row[c + u(j)] = G[j] * scale
        for j in range(H):
            row[c + u(H + j)] = (hm[j] * s) * scale
        row[c + u(2 * H)] = s * scale


@numba.njit(cache=True)
def _one_hidden_normal_equations(T, x, h, w2s, s, act, scale, r, block, A, g):
    """A += JᵀJ (lower triangle, Fortran order) and g += Jᵀr for the rows of
    :func:`_one_hidden_jacobian_rows`, ``block`` rows at a time in one reused buffer: per block
    one BLAS syrk and one gemv (Jᵀr of the block, then added to g), the calls and the order of
    :func:`pipeline.identify.lm.normal_equations_from_blocks` over :meth:`PGNN.jacobian_blocks`;
    no Python between the blocks.

    The blocks hold the columns of J permuted (:func:`_one_hidden_rows_input_major`), and the
    sums are permuted back at the end.  Entry (i, j) of syrk and entry i of gemv are the same
    sequence of operations on the same numbers wherever the columns i and j sit (BLAS vectorises
    over them), and the product J_li J_lj is commutative, so the result is the unpermuted one to
    the bit."""
    M, n = x.shape
    H = h.shape[1]
    p = T.shape[1]
    P = A.shape[0]
    J = np.empty((min(block, M), P))
    G = np.empty(H)
    Ap = np.zeros((P, P)).T                            # Fortran order
    gp = np.zeros(P)
    gb = np.empty(P)
    for a in range(0, M, block):
        k = min(block, M - a)
        _one_hidden_rows_input_major(J[:k], T, x, h, a, w2s, s, act, scale, G)
        blas_syrk_lower(P, k, J, Ap)
        blas_gemv_n(P, k, J, r[a:a + k], 0.0, gb)
        for i in range(P):
            gp[i] += gb[i]
    perm = np.arange(P)                                # perm[original column] = column in the blocks
    for j in range(H):
        for kk in range(n):
            perm[p + j * n + kk] = p + kk * H + j
    for j in range(P):
        pj = perm[j]
        g[j] += gp[pj]
        for i in range(j, P):
            pi = perm[i]
            A[i, j] += Ap[pi, pj] if pi >= pj else Ap[pj, pi]


# --------------------------------------------------------------------------------------------
# the PGNN
# --------------------------------------------------------------------------------------------
@dataclass
class Prepared:
    """θ-independent quantities of a data set, computed once for identification.

    offset [M], T [M, p]: physics features (None without physics); x [M, n_in]: normalised
    NN inputs (None without NN).
    """

    offset: torch.Tensor | None
    T: torch.Tensor | None
    x: torch.Tensor | None

    def __len__(self):
        for a in (self.offset, self.x):
            if a is not None:
                return a.shape[0]
        return 0

    def rows(self, sl: slice) -> "Prepared":
        return Prepared(*(None if a is None else a[sl] for a in (self.offset, self.T, self.x)))


def _difference_rows(n: int) -> np.ndarray:
    """Rows k = 0..n-1: the k-th backward difference of a window w[0], w[1], … (w[0] newest)."""
    D = np.zeros((n, n))
    for k in range(n):
        for j in range(k + 1):
            D[k, j] = (-1) ** j * math.comb(k, j)
    return D


class PGNN(nn.Module):
    """Physics-guided neural network on a NARX regressor ([B1] (10), (13), (26)).

    Parameters
    ----------
    n_a, n_b, n_k : int
        NARX orders ([B1] (1)): output lags, input lags, pure input delay [samples].
    structure : {'forward', 'inverse', 'invertible'}
        Regressor layout and NN inputs (module docstring).
    physics : PhysicsFeatures or None
        Linear-in-parameters physics map on φ; None for a black-box NN.
    hidden : sequence of int
        Hidden-layer widths (``()`` with ``use_nn=True`` is a linear NN).
    activation : str
        Hidden activation: tanh, sigmoid, relu, softplus, elu, gelu, identity.
    use_physics, use_nn : bool
        Switch a part off (physics-only model: ``use_nn=False``; black box:
        ``use_physics=False``).
    input_transform : {'delta', 'raw'}
        NN input basis: ``'delta'`` replaces the output window by its backward differences
        (y, Δy, Δ²y, …; an invertible linear map, so the model class is unchanged, but the
        NN sees velocity-like inputs instead of nearly identical positions); ``'raw'`` is φ.
    out_init_scale : float
        Output-layer weights at initialisation = Glorot draw × this (small: the initial PGNN
        equals the physics model up to this factor, SPEC §3).
    out_init : {'scaled', 'mirrored'}
        ``'scaled'``: output weights = Glorot × ``out_init_scale``.  ``'mirrored'``: the units
        of the last hidden layer come in identical pairs with opposite output weights (Glorot
        × ``out_init_scale``), so the initial NN output is zero up to rounding (the initial PGNN
        is the physics model) while every hidden unit has a full-size gradient; a tiny scaled
        output layer instead leaves the hidden layer's Jacobian columns ~``out_init_scale``
        small, which slows LM markedly.
    mirror_jitter : float
        ``'mirrored'`` only: the twin of each pair gets its input weights and bias plus this
        fraction of a fresh Glorot draw (0: exact twins).  Exact twins start the fit on the
        overlapping-units singularity (Amari's plateau: JᵀJ singular, the pair's columns
        opposite); they separate only through rounding, so on a slow fit a last-bit difference
        (another BLAS) decides whether a pair leaves the plateau.  A jitter separates them by
        construction; the initial NN output is then O(jitter) instead of 0.
    nn_inputs : {'all', 'outputs'}
        ``'outputs'``: the NN sees the output window only (a position-dependent nonlinearity
        such as cogging; it cannot add an input-to-output response of its own, e.g. one that
        amplifies measurement noise through an inverse).
    seed : int
        Seed of the initial NN weights (torch generator).
    """

    def __init__(self, n_a: int, n_b: int, n_k: int = 0, *, structure: str = "forward",
                 physics: PhysicsFeatures | None = None, hidden=(16,), activation: str = "tanh",
                 use_physics: bool = True, use_nn: bool = True, input_transform: str = "delta",
                 out_init_scale: float = 1e-3, out_init: str = "scaled", nn_inputs: str = "all", seed: int = 0,
                 mirror_jitter: float = 0.0):
        super().__init__()
        if nn_inputs not in ("all", "outputs"):
            raise ValueError(f"nn_inputs must be 'all' or 'outputs', got {nn_inputs!r}")
        self.nn_inputs = nn_inputs
        if structure not in _STRUCTURES:
            raise ValueError(f"structure must be one of {_STRUCTURES}, got {structure!r}")
        if n_a < 0 or n_b < 1 or n_k < 0:
            raise ValueError(f"NARX orders need n_a >= 0, n_b >= 1, n_k >= 0; got n_a={n_a}, "
                             f"n_b={n_b}, n_k={n_k}")
        if activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        if out_init not in ("scaled", "mirrored"):
            raise ValueError(f"out_init must be 'scaled' or 'mirrored', got {out_init!r}")
        if input_transform not in ("delta", "raw"):
            raise ValueError(f"input_transform must be 'delta' or 'raw', got {input_transform!r}")
        if use_physics and physics is None:
            raise ValueError("use_physics=True needs a PhysicsFeatures map (physics=...); "
                             "pass use_physics=False for a black-box NN")
        if not (use_physics or use_nn):
            raise ValueError("a PGNN needs at least one part: use_physics or use_nn must be True")
        self.n_a, self.n_b, self.n_k = int(n_a), int(n_b), int(n_k)
        self.structure = structure
        self.use_physics, self.use_nn = bool(use_physics), bool(use_nn)
        self.activation = activation
        self.hidden = tuple(int(h) for h in hidden)
        self.input_transform = input_transform
        self.out_init_scale = float(out_init_scale)
        self.out_init = out_init
        if not (math.isfinite(mirror_jitter) and mirror_jitter >= 0):
            raise ValueError(f"mirror_jitter must be finite and >= 0, got {mirror_jitter}")
        self.mirror_jitter = float(mirror_jitter)
        self.physics = physics if use_physics else None
        n_phi = self.n_phi

        # θ_phy first (parameter order = flat vector order)
        if self.use_physics:
            p = physics.n_params
            self.theta_phy = nn.Parameter(torch.zeros(p, dtype=torch.float64))
            self.register_buffer("theta_phy_star", torch.full((p,), float("nan"), dtype=torch.float64))
        # NN input map x = P φ + c (selection, δ-basis, normalisation)
        sel, n_y = self._nn_selection()
        D = np.zeros((len(sel), n_phi))
        D[np.arange(len(sel)), sel] = 1.0
        if input_transform == "delta" and n_y > 1:
            D[:n_y] = _difference_rows(n_y) @ D[:n_y]
        self.register_buffer("nn_select", torch.as_tensor(D, dtype=torch.float64))
        self.register_buffer("nn_P", torch.as_tensor(D, dtype=torch.float64).clone())
        self.register_buffer("nn_c", torch.zeros(len(sel), dtype=torch.float64))
        self.register_buffer("out_scale", torch.ones((), dtype=torch.float64))
        self.layers = nn.ModuleList()
        if self.use_nn:
            widths = (len(sel),) + self.hidden + (1,)
            for a, b in zip(widths[:-1], widths[1:]):
                self.layers.append(nn.Linear(a, b, dtype=torch.float64))
        self.reset_parameters(seed)

    # ---- layout ---------------------------------------------------------------------------
    @property
    def n_phi(self) -> int:
        return self.n_a + self.n_b

    @property
    def u_index(self) -> int:
        """Index of the most recent input u(t-n_k-1) in φ (forward / invertible layouts)."""
        return self.n_a

    def _nn_selection(self) -> tuple[list[int], int]:
        """Indices of φ the NN sees and how many of them (first) form the output window."""
        if self.structure == "inverse":
            n_y = self.n_a + 1
        else:
            n_y = self.n_a
        sel = list(range(self.n_phi))
        if self.nn_inputs == "outputs":   # the NN is a function of the output window only
            sel = sel[:n_y]
        elif self.structure == "invertible":
            sel.remove(self.u_index)  # [B1] (26): the NN does not see u(t-n_k-1)
        return sel, n_y

    @property
    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def param_slices(self) -> dict[str, slice]:
        """Slices of the flat parameter vector: ``theta_phy``, ``layers.0.weight``, …"""
        out, i = {}, 0
        for name, p in self.named_parameters():
            out[name] = slice(i, i + p.numel())
            i += p.numel()
        return out

    @property
    def phy_slice(self) -> slice:
        return slice(0, self.physics.n_params if self.use_physics else 0)

    def parameter_vector(self) -> torch.Tensor:
        """All trainable parameters as one flat float64 vector (θ_phy first)."""
        return torch.nn.utils.parameters_to_vector(self.parameters()).detach().clone()

    def load_parameter_vector(self, theta: torch.Tensor) -> None:
        if theta.numel() != self.n_params:
            raise ValueError(f"parameter vector has {theta.numel()} entries, the model {self.n_params}")
        torch.nn.utils.vector_to_parameters(theta.detach().clone(), self.parameters())

    # ---- initialisation and normalisation ------------------------------------------------
    def reset_parameters(self, seed: int | torch.Generator = 0) -> None:
        """Glorot-uniform hidden layers, zero biases, output layer scaled by ``out_init_scale``;
        θ_phy set to θ*_phy when it is known."""
        g = seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(int(seed))
        with torch.no_grad():
            for i, lin in enumerate(self.layers):
                fan_out, fan_in = lin.weight.shape
                a = math.sqrt(6.0 / (fan_in + fan_out))
                w = (2.0 * torch.rand(lin.weight.shape, generator=g, dtype=torch.float64) - 1.0) * a
                if i == len(self.layers) - 1:
                    w = w * self.out_init_scale
                lin.weight.copy_(w)
                lin.bias.zero_()
            if self.out_init == "mirrored" and len(self.layers) >= 2:
                # pairs (j, j + h) of identical units with opposite output weights: f_NN = 0
                last, out = self.layers[-2], self.layers[-1]
                h = last.weight.shape[0] // 2
                last.weight[h:2 * h] = last.weight[:h]
                last.bias[h:2 * h] = last.bias[:h]
                out.weight[0, h:2 * h] = -out.weight[0, :h]
                out.weight[0, 2 * h:] = 0.0  # an odd unit out: no output at initialisation
                if self.mirror_jitter > 0:      # twins apart by construction, not by rounding
                    fan_out, fan_in = last.weight.shape
                    a = math.sqrt(6.0 / (fan_in + fan_out))
                    dw = (2.0 * torch.rand((h, fan_in + 1), generator=g, dtype=torch.float64) - 1.0) * a
                    last.weight[h:2 * h] += self.mirror_jitter * dw[:, :fan_in]
                    last.bias[h:2 * h] += self.mirror_jitter * dw[:, fan_in]
            if self.use_physics and bool(torch.all(torch.isfinite(self.theta_phy_star))):
                self.theta_phy.copy_(self.theta_phy_star)

    def fit_normalisation(self, phi: torch.Tensor) -> None:
        """Set the NN input normalisation from training regressors φ [M, n_phi] (buffers)."""
        phi = torch.as_tensor(phi, dtype=torch.float64)
        z = phi @ self.nn_select.T
        mean = z.mean(0)
        std = z.std(0)
        tiny = 1e-12 * (z.abs().max(0).values + 1e-300)
        std = torch.where(std > tiny, std, torch.ones_like(std))  # constant inputs: no scaling
        self.nn_P.copy_(self.nn_select / std[:, None])
        self.nn_c.copy_(-mean / std)

    def set_physics_estimate(self, theta_star) -> None:
        """Store θ*_phy (the physics-only least-squares estimate, [B1] (7)) and start from it."""
        t = torch.as_tensor(np.asarray(theta_star, dtype=float), dtype=torch.float64)
        with torch.no_grad():
            self.theta_phy_star.copy_(t)
            self.theta_phy.copy_(t)

    # ---- evaluation ----------------------------------------------------------------------
    def prepare(self, phi: torch.Tensor) -> Prepared:
        """θ-independent parts of the prediction for regressors φ [M, n_phi]."""
        phi = self._check_phi(phi)
        off = T = x = None
        if self.use_physics:
            off, T = self.physics.features(phi)
        if self.use_nn:
            x = phi @ self.nn_P.T + self.nn_c
        return Prepared(off, T, x)

    def _unflatten(self, theta: torch.Tensor):
        sl = self.param_slices()
        th_phy = theta[sl["theta_phy"]] if self.use_physics else None
        layers = []
        for i, lin in enumerate(self.layers):
            W = theta[sl[f"layers.{i}.weight"]].view(lin.weight.shape)
            b = theta[sl[f"layers.{i}.bias"]]
            layers.append((W, b))
        return th_phy, layers

    def _mlp(self, x, layers, hidden: torch.Tensor | None = None):
        act = _ACTIVATIONS[self.activation]
        for W, b in layers[:-1]:
            x = act(torch.addmm(b, x, W.T))
        if hidden is not None:  # keep the (single) hidden layer's activations
            hidden.copy_(x)
        W, b = layers[-1]
        return torch.addmm(b, x, W.T)[:, 0] * self.out_scale

    def predict(self, theta: torch.Tensor, prep: Prepared, block: int | None = None,
                hidden: torch.Tensor | None = None) -> torch.Tensor:
        """ŷ [M] for a flat parameter vector θ on prepared data; with ``block``, computed in row
        blocks of that size (temporaries stay in cache; the same arithmetic per row).

        ``hidden``: a [M, H] buffer that receives the activations of a single hidden layer, for
        :meth:`jacobian_blocks` at the same θ and ``block``."""
        th_phy, layers = self._unflatten(theta)
        if hidden is not None and self.use_nn and len(layers) == 2:
            return self._predict_one_hidden(th_phy, layers, prep, block, hidden)
        if block is None:
            return self._predict_rows(th_phy, layers, prep, hidden)
        M = len(prep)
        out = torch.empty(M, dtype=torch.float64)
        for a in range(0, M, block):
            out[a:a + block] = self._predict_rows(th_phy, layers, prep.rows(slice(a, a + block)),
                                                  None if hidden is None else hidden[a:a + block])
        return out

    def _predict_one_hidden(self, th_phy, layers, prep: Prepared, block: int | None,
                            hidden: torch.Tensor) -> torch.Tensor:
        """:meth:`predict` of one hidden layer into the activation buffer ``hidden``: the same torch
        operations as :meth:`_predict_rows` (each row's arithmetic does not depend on the rows
        beside it), the pre-activation written into ``hidden`` and activated in place (no
        temporaries, no copy), the physics part in one pass, the NN in blocks of at least
        :attr:`_PREDICT_BLOCK` rows (fewer Python calls)."""
        M = len(prep)
        (W1, b1), (W2, b2) = layers
        inplace = _ACTIVATIONS_INPLACE.get(self.activation)
        act = _ACTIVATIONS[self.activation]
        nn_out = torch.empty(M, 1, dtype=torch.float64)
        step = M if block is None else max(int(block), self._PREDICT_BLOCK)
        for a in range(0, M, step):
            z = hidden[a:a + step]
            torch.addmm(b1, prep.x[a:a + step], W1.T, out=z)
            if inplace is not None:
                inplace(z)
            else:
                z.copy_(act(z))
            torch.addmm(b2, z, W2.T, out=nn_out[a:a + step])
        out = nn_out[:, 0] * self.out_scale
        return (prep.offset + prep.T @ th_phy) + out if self.use_physics else 0.0 + out

    #: smallest row block of :meth:`_predict_one_hidden`
    _PREDICT_BLOCK = 8192

    def _predict_rows(self, th_phy, layers, prep: Prepared, hidden=None) -> torch.Tensor:
        out = 0.0
        if self.use_physics:
            out = prep.offset + prep.T @ th_phy
        if self.use_nn:
            out = out + self._mlp(prep.x, layers, hidden)
        return out

    def _closed_form(self) -> bool:
        """True when :meth:`jacobian` has a closed form (one hidden tanh/sigmoid/identity layer, or none)."""
        return not self.use_nn or len(self.layers) == 1 or (
            len(self.layers) == 2 and self.activation in ("tanh", "sigmoid", "identity"))

    def jacobian(self, theta: torch.Tensor, prep: Prepared, chunk: int = 20000,
                 out: torch.Tensor | None = None, scale: float | None = None,
                 block: int = 2048) -> torch.Tensor:
        """Exact ∂ŷ/∂θ [M, n_params] (times ``scale`` if given): closed form for one hidden layer
        (tanh, sigmoid, identity) or no hidden layer, torch.func.jacfwd in row chunks otherwise.

        ``out``: a preallocated contiguous [M, n_params] float64 buffer to write into.  The rows
        are those of :meth:`jacobian_blocks` (``block`` rows, or ``chunk`` for jacfwd)."""
        M = len(prep)
        if out is not None and (out.shape != (M, self.n_params) or not out.is_contiguous()):
            raise ValueError(f"out must be a contiguous [{M}, {self.n_params}] buffer, got {tuple(out.shape)}")
        J = torch.empty(M, self.n_params, dtype=torch.float64) if out is None else out
        for _ in self.jacobian_blocks(theta, prep, scale, block if self._closed_form() else chunk, out=J):
            pass
        return J

    def jacobian_blocks(self, theta: torch.Tensor, prep: Prepared, scale: float | None = None,
                        block: int = 2048, out: torch.Tensor | None = None,
                        hidden: torch.Tensor | None = None):
        """Yield ``(a, J_a)``: the rows a, a+1, … of the exact ∂ŷ/∂θ (times ``scale``), ``block``
        rows at a time, written into the rows of ``out`` if given, else into one reused
        [block, n_params] buffer (overwritten by the next block: use J_a before asking for it).
        ``hidden``: the hidden activations at this θ, from :meth:`predict` with the same ``block``
        (one hidden layer only), instead of computing them again.

        Each block is complete (and scaled) while it is in cache, so a consumer can reduce it
        (e.g. JᵀJ by syrk) without J ever being stored whole.  Every entry is the same product
        as a one-block computation."""
        M, P = len(prep), self.n_params
        _, layers = self._unflatten(theta)
        closed = self._closed_form()
        buf = None if out is not None else torch.empty(min(block, M), P, dtype=torch.float64)
        for a in range(0, M, block):
            rows = prep.rows(slice(a, a + block))
            J = out[a:a + block] if out is not None else buf[:len(rows)]
            if closed:
                self._jacobian_rows(layers, rows, J, scale, None if hidden is None else hidden[a:a + block])
            else:
                J.copy_(torch.func.jacfwd(lambda th: self.predict(th, rows))(theta))
                if scale is not None:
                    J.mul_(scale)
            yield a, J

    def normal_equations(self, theta: torch.Tensor, prep: Prepared, r: torch.Tensor,
                         scale: float | None = None, block: int = 2048,
                         hidden: torch.Tensor | None = None, extra=()) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(JᵀJ, Jᵀr) of J = ∂ŷ/∂θ (times ``scale``) over the rows of ``prep``, followed by the
        ``extra`` row blocks ``(a, J_extra)`` (e.g. constant regulariser rows; ``r`` covers them
        all), for one hidden layer with a closed-form Jacobian (None otherwise): equal to the bit to
        :func:`pipeline.identify.lm.normal_equations_from_blocks` over :meth:`jacobian_blocks` (same
        ``block``) and ``extra``.

        The rows of each block are formed and reduced by syrk and gemv while in cache by one numba
        kernel (:func:`_one_hidden_normal_equations`); ``hidden``: the activations at this θ from
        :meth:`predict` (computed here otherwise)."""
        if not (self.use_nn and len(self.layers) == 2 and self._closed_form()):
            return None
        P = self.n_params
        A = np.zeros((P, P), order="F")
        g = np.zeros(P)
        rn = r.numpy()
        _, ((W1, b1), (W2, b2)) = self._unflatten(theta)
        if hidden is None:
            hidden = _ACTIVATIONS[self.activation](torch.addmm(b1, prep.x, W1.T))
        s = self.out_scale
        T = prep.T if self.use_physics else prep.x[:, :0]
        _one_hidden_normal_equations(np.ascontiguousarray(T.numpy()), prep.x.numpy(), hidden.numpy(),
                                     (s * W2[0]).numpy(), float(s), _DERIVATIVE_FROM_VALUE[self.activation],
                                     1.0 if scale is None else float(scale), rn, int(block), A, g)
        for a, J in extra:               # the steps of normal_equations_from_blocks
            Jt = J.numpy().T
            A = _dsyrk(1.0, Jt, beta=1.0, c=A, trans=0, lower=1, overwrite_c=1)
            g += Jt @ rn[a:a + Jt.shape[1]]
        A = np.tril(A) + np.tril(A, -1).T
        return torch.from_numpy(A), torch.from_numpy(g)

    def _jacobian_rows(self, layers, prep: Prepared, J: torch.Tensor, scale: float | None,
                       h: torch.Tensor | None = None) -> None:
        """The closed-form Jacobian (times ``scale``) of the rows of ``prep`` into the row block ``J``;
        ``h``: the hidden activations of these rows if known."""
        s = self.out_scale
        if self.use_nn and len(layers) == 2:
            (W1, b1), (W2, b2) = layers
            if h is None:
                h = _ACTIVATIONS[self.activation](torch.addmm(b1, prep.x, W1.T))
            T = prep.T if self.use_physics else prep.x[:, :0]
            _one_hidden_jacobian_rows(J.numpy(), T.numpy(), prep.x.numpy(), h.numpy(), (s * W2[0]).numpy(),
                                      float(s), _DERIVATIVE_FROM_VALUE[self.activation],
                                      1.0 if scale is None else float(scale))
            return
        i = 0
        if self.use_physics:
            p = prep.T.shape[1]
            J[:, :p] = prep.T
            i = p
        if self.use_nn:  # no hidden layer: ŷ = s (W x + b)
            n = prep.x.shape[1]
            torch.mul(prep.x, s, out=J[:, i:i + n])
            J[:, i + n] = s
        if scale is not None:
            J.mul_(scale)

    def forward(self, phi: torch.Tensor) -> torch.Tensor:
        """One-step prediction ŷ(θ, φ) [B] for a batch of regressors φ [B, n_phi] ([B1] (10)).

        In simulation (NOE) mode φ holds the model's own past outputs (SPEC §3 item 3)."""
        return self.physics_part(phi) + self.nn_part(phi)

    def physics_part(self, phi: torch.Tensor, theta_phy: torch.Tensor | None = None) -> torch.Tensor:
        """f_phy(θ_phy, φ) [B] (zero without physics); ``theta_phy`` defaults to the model's."""
        phi = self._check_phi(phi)
        if not self.use_physics:
            return torch.zeros(phi.shape[0], dtype=torch.float64)
        return self.physics(phi, self.theta_phy if theta_phy is None else theta_phy)

    def nn_part(self, phi: torch.Tensor) -> torch.Tensor:
        """f_NN(θ_NN, φ) [B] (zero without NN)."""
        phi = self._check_phi(phi)
        if not self.use_nn:
            return torch.zeros(phi.shape[0], dtype=torch.float64)
        return self._mlp(phi @ self.nn_P.T + self.nn_c, [(l.weight, l.bias) for l in self.layers])

    def _check_phi(self, phi):
        if not isinstance(phi, torch.Tensor):
            phi = torch.as_tensor(np.asarray(phi, dtype=float))
        if phi.dtype != torch.float64:
            raise TypeError(f"regressors must be float64 (SPEC §0), got {phi.dtype}")
        if phi.ndim != 2 or phi.shape[1] != self.n_phi:
            raise ValueError(f"regressor batch must have shape [B, {self.n_phi}] (n_a + n_b), "
                             f"got {tuple(phi.shape)}")
        return phi

    # ---- structure for inversion ---------------------------------------------------------
    def psi_mask(self) -> torch.Tensor:
        """Boolean mask of the θ_phy entries ψ multiplying u(t-n_k-1) ([B1] (29)); found by
        perturbing that entry of a fixed probe regressor."""
        if not self.use_physics or self.structure == "inverse":
            return torch.zeros(self.physics.n_params if self.use_physics else 0, dtype=torch.bool)
        phi0 = torch.linspace(0.3, 0.9, self.n_phi, dtype=torch.float64)[None, :].repeat(2, 1)
        phi0[0, self.u_index], phi0[1, self.u_index] = 0.0, 1.0
        _, T = self.physics.features(phi0)
        return (T[1] - T[0]).abs() > 0

    def physics_affine(self, phi: torch.Tensor, theta_phy: torch.Tensor | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """(a, ψ) with f_phy(φ) = a + ψ u(t-n_k-1) (forward layouts, affine physics): a at
        u(t-n_k-1) = 0 and the input gain ψ from feature differences (exact for a feature
        linear in u; a difference of outputs would cancel ~10 digits when ψ u << f)."""
        phi = self._check_phi(phi)
        th = self.theta_phy if theta_phy is None else theta_phy
        p0, p1 = phi.clone(), phi.clone()
        p0[:, self.u_index] = 0.0
        p1[:, self.u_index] = 1.0
        o0, T0 = self.physics.features(p0)
        o1, T1 = self.physics.features(p1)
        return o0 + T0 @ th, (o1 - o0) + (T1 - T0) @ th

    @property
    def analytically_invertible(self) -> bool:
        """True when ŷ is affine in u(t-n_k-1) with a coefficient ψ known from the physics:
        the invertible PGNN [B1] (26) or a physics-only forward model."""
        return (self.structure == "invertible" or (self.structure == "forward" and not self.use_nn)) \
            and self.use_physics and self.physics.affine_in_latest_input

    def extra_repr(self) -> str:
        return (f"structure={self.structure}, n_a={self.n_a}, n_b={self.n_b}, n_k={self.n_k}, "
                f"use_physics={self.use_physics}, use_nn={self.use_nn}, hidden={self.hidden}, "
                f"activation={self.activation}, input_transform={self.input_transform}, "
                f"out_init={self.out_init}")
