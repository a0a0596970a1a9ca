"""PGNN with shared linear AR dynamics ([K] (6), SPEC §3 item 6).

    B(q) f(k) = A(r(k)) + g_φ(r(k)),   A(r) = Σ a_i ψ_{i-1}(r),   B = ψ_0 + Σ b_i ψ_i,

i.e. the rational model of :mod:`pipeline.models.rational` with an approximator ``g_φ`` in the
exogenous part.  ``g_φ`` is any torch module mapping a window of references to one value per
sample; its input transform is a :class:`ReferenceWindow`: the window [r(k), …, r(k-q)]
(``shift``) or its δ-basis (r, δr, …, δ^q r) (``delta``, the default: at Ts = 1 ms the raw
window differs in its 4th digit from sample to sample), normalised by training statistics
that are stored in the model.  Defaults follow [K] VI-B: MLP 5-10-10-1, tanh, Glorot.
"""
from __future__ import annotations

import math
from typing import Literal, Sequence

import numba
import numpy as np
import torch
from torch import nn

from pipeline.models.activations import Tanh, tanh
from pipeline.models.pgnn import blas_syrk_lower
from pipeline.models.rational import BASES, RationalFeedforward, Segments, basis_columns
from pipeline.params import schema, spec

KIND = "pgnn_shared_ar"   # the model option (model.kind, or model=physics) this module's Params checks


_WIDTHS = "widths must be positive integers"


@schema
class Params:
    kind: Literal["pgnn_shared_ar"]
    name: str = "pgnn_shared_ar"
    # coefficients of A = Σ a_i ψ_{i-1} r ([K] VI-B: 5, contains the plant's A(δ))
    n_a: int = spec(5, ge=1, le=1000)
    # AR coefficients of B ([K] VI-B: 2, contains the plant's B(δ))
    n_b: int = spec(2, ge=0, le=1000)
    # ψ_i = δ^i (delta, as the plant (31)) | q^-i (shift)
    basis: Literal["delta", "shift"] = "delta"
    # g_φ: mlp ([K] (4)) | residual (ResNet blocks h + tanh(W h + c): the slot is generic)
    approximator: Literal["mlp", "residual"] = "mlp"
    # hidden widths of the mlp ([K] VI-B: 5-10-10-1)
    hidden: list[int] = spec([10, 10], ge=1, le=100_000, rule=_WIDTHS)
    # residual only: block width
    width: int = spec(10, ge=1, le=100_000)
    # residual only: number of blocks
    n_blocks: int = spec(2, ge=1, le=1000)
    # hidden activation ([K] VI-B: tanh)
    activation: Literal["tanh", "relu", "sigmoid", "softplus"] = "tanh"
    # bias in the output layer ([K] (4): none)
    out_bias: bool = False
    # output weights = Glorot × this ([K] Alg. 5: φ^0 by Glorot)
    out_init_scale: float = spec(1.0, ge=0, le=1e6)
    # q: g_φ sees r(k) … r(k-q) ([K] VI-B: the last 5 samples)
    window: int = spec(4, ge=0, le=10_000)
    # input transform (r, δr, …, δ^q r), normalised by training statistics (SPEC §3 item 6) | shift (raw window)
    window_basis: Literal["delta", "shift"] = "delta"


__all__ = ["ReferenceWindow", "MLP", "ResidualMLP", "SharedARPGNN", "make_approximator",
           "per_sample_jacobian"]

_ACTIVATIONS = {"tanh": Tanh, "relu": nn.ReLU, "sigmoid": nn.Sigmoid, "softplus": nn.Softplus}


def _activation(name: str) -> nn.Module:
    if name not in _ACTIVATIONS:
        raise ValueError(f"unknown activation '{name}'; choose one of {sorted(_ACTIVATIONS)}")
    return _ACTIVATIONS[name]()


def _glorot_(layer: nn.Linear, generator: torch.Generator, gain: float = 1.0) -> None:
    """Glorot-uniform weights ([K] ref. 23), zero biases, from a seeded generator."""
    nn.init.xavier_uniform_(layer.weight, gain=gain, generator=generator)
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)


class ReferenceWindow(nn.Module):
    """Input transform of g_φ: a window of q+1 reference samples, normalised.

    Parameters
    ----------
    q : int
        Window length minus one ([K] (4): [r(k), …, r(k-q)]; [K] VI-B uses q = 4).
    basis : {'delta', 'shift'}
        ``delta``: features (r, δr, …, δ^q r) (units m/s^i); ``shift``: the raw window.
    Ts : float
        Sample time [s].
    normalisation : {'std', 'maxabs'}
        Per feature: subtract the training mean and divide by the training standard deviation
        (``std``), or divide by the largest training magnitude (``maxabs``, no centring).  The
        high δ-powers of a jerk-limited reference are sparse (δ⁴r is zero except for spikes at
        the jerk switches), so ``std`` maps their spikes to ~20 standard deviations where
        ``maxabs`` keeps every feature in [-1, 1].

    Notes
    -----
    The normalisation (offset and scale per feature, buffers of the module) is set from the
    training references with :meth:`fit` and is part of the saved model (SPEC §3).
    """

    NORMALISATIONS = ("std", "maxabs")

    def __init__(self, q: int = 4, basis: str = "delta", Ts: float = 1e-3, normalisation: str = "std"):
        super().__init__()
        if int(q) < 0:
            raise ValueError(f"window length q must be >= 0, got {q}")
        if basis not in BASES:
            raise ValueError(f"unknown window basis '{basis}'; choose one of {BASES}")
        if normalisation not in self.NORMALISATIONS:
            raise ValueError(f"unknown normalisation '{normalisation}'; choose one of {self.NORMALISATIONS}")
        self.q, self.basis, self.Ts = int(q), basis, float(Ts)
        self.normalisation = normalisation
        self.register_buffer("mean", torch.zeros(self.q + 1, dtype=torch.float64))
        self.register_buffer("std", torch.ones(self.q + 1, dtype=torch.float64))

    @property
    def n_features(self) -> int:
        return self.q + 1

    def features(self, r: np.ndarray, segments: Segments) -> np.ndarray:
        """Unnormalised window features [N, q+1] of a concatenated reference (rest before)."""
        return basis_columns(r, segments, self.basis, self.q, self.Ts)

    def fit(self, r, segments: Segments | None = None) -> "ReferenceWindow":
        """Set the normalisation from training references (a feature with zero spread keeps
        scale 1)."""
        if segments is None:
            r, segments = Segments.concat(r, "reference")
        X = self.features(r, segments)
        if self.normalisation == "std":
            offset, scale = X.mean(axis=0), X.std(axis=0)
        else:
            offset, scale = np.zeros(X.shape[1]), np.abs(X).max(axis=0)
        with torch.no_grad():
            self.mean.copy_(torch.from_numpy(offset))
            self.std.copy_(torch.from_numpy(np.where(scale > 0, scale, 1.0)))
        return self

    def forward(self, X: torch.Tensor) -> torch.Tensor:
        return (X - self.mean) / self.std


class MLP(nn.Module):
    """Fully connected network ([K] (4)): tanh hidden layers, linear output layer.

    Parameters
    ----------
    n_in : int
        Number of inputs (window features).
    hidden : sequence of int
        Neurons per hidden layer ([K] VI-B: (10, 10)).
    activation : str
        Hidden activation ('tanh' default).
    out_bias : bool
        Bias in the output layer ([K] (4) has none; its text allows one).
    out_scale : float
        Multiplies the Glorot output weights (1.0 = plain Glorot as [K]; small values make
        the initial PGNN equal the physics model, SPEC §3).
    seed : int
        Seed of the torch generator used for the initialisation.
    """

    def __init__(self, n_in: int = 5, hidden: Sequence[int] = (10, 10), activation: str = "tanh",
                 out_bias: bool = False, out_scale: float = 1.0, seed: int = 0):
        super().__init__()
        gen = torch.Generator().manual_seed(int(seed))
        layers: list[nn.Module] = []
        width = int(n_in)
        for h in hidden:
            lin = nn.Linear(width, int(h), dtype=torch.float64)
            _glorot_(lin, gen)
            layers += [lin, _activation(activation)]
            width = int(h)
        out = nn.Linear(width, 1, bias=out_bias, dtype=torch.float64)
        _glorot_(out, gen, gain=out_scale)
        layers.append(out)
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x).squeeze(-1)


class ResidualMLP(nn.Module):
    """Residual network ([K] mentions ResNets, ref. 21): h ← h + tanh(W h + c) blocks.

    An input layer lifts the features to ``width``; each of ``n_blocks`` blocks adds a tanh
    layer to its input (identity skip); a linear layer gives the output.  Same init rules as
    :class:`MLP`.
    """

    def __init__(self, n_in: int = 5, width: int = 10, n_blocks: int = 2, activation: str = "tanh",
                 out_bias: bool = False, out_scale: float = 1.0, seed: int = 0):
        super().__init__()
        gen = torch.Generator().manual_seed(int(seed))
        self.inp = nn.Linear(int(n_in), int(width), dtype=torch.float64)
        _glorot_(self.inp, gen)
        self.blocks = nn.ModuleList()
        for _ in range(int(n_blocks)):
            lin = nn.Linear(int(width), int(width), dtype=torch.float64)
            _glorot_(lin, gen)
            self.blocks.append(lin)
        self.act = _activation(activation)
        self.out = nn.Linear(int(width), 1, bias=out_bias, dtype=torch.float64)
        _glorot_(self.out, gen, gain=out_scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.act(self.inp(x))
        for lin in self.blocks:
            h = h + self.act(lin(h))
        return self.out(h).squeeze(-1)


def make_approximator(kind: str = "mlp", n_in: int = 5, seed: int = 0, **kw) -> nn.Module:
    """Build the g_φ module: ``mlp`` (:class:`MLP`) or ``residual`` (:class:`ResidualMLP`)."""
    kinds = {"mlp": MLP, "residual": ResidualMLP}
    if kind not in kinds:
        raise ValueError(f"unknown approximator '{kind}'; choose one of {sorted(kinds)}")
    return kinds[kind](n_in=n_in, seed=seed, **kw)


def per_sample_jacobian(module: nn.Module, X: torch.Tensor, phi: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Output y [N] of ``module`` on samples X and the per-sample Jacobian ∂y_k/∂φ [N, n_φ].

    φ is the flat vector of ``module.parameters()`` (``parameters_to_vector`` order); the
    module's parameters are restored afterwards.  The samples must be independent (no
    batch statistics).  When every parameter belongs to an ``nn.Linear`` applied to [N, ·]
    inputs (one row per sample) the Jacobian is
    assembled from one forward and one backward pass (for a Linear layer with input h and
    output gradient δ, ∂y_k/∂W = δ_k h_kᵀ and ∂y_k/∂c = δ_k); otherwise by forward mode, one
    ``torch.func.jvp`` per parameter (n_φ batched passes: slower, but for any module).
    """
    params = list(module.parameters())
    saved = nn.utils.parameters_to_vector(params).detach().clone()
    if phi is not None:
        with torch.no_grad():
            nn.utils.vector_to_parameters(torch.as_tensor(phi, dtype=torch.float64), params)
    try:
        linear = [m for m in module.modules() if isinstance(m, nn.Linear)]
        owned = {id(p) for m in linear for p in m.parameters(recurse=False)}
        if all(id(p) in owned for p in params):
            return _linear_jacobian(module, X, linear, params)
        return _func_jacobian(module, X, params)
    finally:
        with torch.no_grad():
            nn.utils.vector_to_parameters(saved, params)


def _linear_jacobian(module, X, linear, params):
    calls: list[tuple[nn.Linear, torch.Tensor, torch.Tensor]] = []

    def hook(mod, inp, out):
        calls.append((mod, inp[0].detach(), out))
    handles = [m.register_forward_hook(hook) for m in linear]
    try:
        with torch.enable_grad():
            y = module(X.detach()).reshape(-1)
            # samples are independent: the gradient of Σ_k y_k w.r.t. a layer output holds
            # the per-sample δ_k = ∂y_k/∂(layer output)_k
            deltas = torch.autograd.grad(y.sum(), [c[2] for c in calls], allow_unused=True)
    finally:
        for h in handles:
            h.remove()
    n = X.shape[0]
    if any(h.dim() != 2 or h.shape[0] != n for _, h, _ in calls):
        return _func_jacobian(module, X, params)    # a Linear not applied sample by sample
    # built transposed, [n_φ, N] contiguous (time along rows: cheap filtering), returned as
    # its [N, n_φ] view
    offsets, k = {}, 0
    for p in params:
        offsets[id(p)] = (k, p.numel())
        k += p.numel()
    JT = torch.empty(k, n, dtype=torch.float64)
    filled: set[int] = set()

    def write(p, factors):
        """Rows of p in JT ← product of the broadcast factors (+= if p was written before,
        i.e. a layer called twice with shared weights)."""
        k0, size = offsets[id(p)]
        rows = JT[k0:k0 + size].view(torch.broadcast_shapes(*(f.shape for f in factors)))
        if id(p) in filled:
            rows += factors[0] * factors[1] if len(factors) == 2 else factors[0]
        elif len(factors) == 2:
            torch.mul(*factors, out=rows)   # written in place: no [N, n_φ] temporary
        else:
            rows.copy_(factors[0])
        filled.add(id(p))

    for (mod, h, _), d in zip(calls, deltas):
        if d is None:
            continue
        dT, hT = d.T, h.T                                  # [out, N], [in, N]
        write(mod.weight, (dT[:, None, :], hT[None, :, :]))   # ∂y_k/∂W = δ_k h_kᵀ
        if mod.bias is not None:
            write(mod.bias, (dT,))                             # ∂y_k/∂c = δ_k
    for p in params:                                       # parameters the output ignores
        if id(p) not in filled:
            k0, size = offsets[id(p)]
            JT[k0:k0 + size] = 0.0
    return y.detach(), JT.T


def _func_jacobian(module, X, params):
    """Forward-mode fallback: one Jacobian-vector product (torch.func.jvp) per parameter."""
    names = [n for n, _ in module.named_parameters()]
    shapes = [p.shape for _, p in module.named_parameters()]
    sizes = [math.prod(s) for s in shapes]
    phi = nn.utils.parameters_to_vector(params).detach()

    def f(p):
        d = {k: c.view(s) for k, c, s in zip(names, torch.split(p, sizes), shapes)}
        return torch.func.functional_call(module, d, (X,)).reshape(-1)
    with torch.no_grad():
        y = f(phi)
        JT = torch.empty(phi.numel(), X.shape[0], dtype=torch.float64)
        e = torch.zeros_like(phi)
        for i in range(phi.numel()):
            e[i] = 1.0
            JT[i] = torch.func.jvp(f, (phi,), (e,))[1]
            e[i] = 0.0
    return y, JT.T


# ----------------------------------------------------------------------------- filtered Jacobian (numba)
# W ∂g/∂φ of a tanh MLP (:class:`MLP`) in one pass over time: per sample the row of ∂g/∂φ in closed
# form from the forward activations (backpropagation of one output), then every column filtered by
# num/den exactly as scipy.signal.lfilter does it (direct form II transposed, coefficients divided by
# den[0], state at rest at every segment start), so W ∂g/∂φ needs no [N, n_φ] temporary and no pass
# per column.
def _lfilter_coefficients(num, den) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) as scipy's lfilter uses them: padded to one length, divided by a[0] (in that order)."""
    num = np.atleast_1d(np.asarray(num, dtype=np.float64))
    den = np.atleast_1d(np.asarray(den, dtype=np.float64))
    L = max(num.size, den.size)
    b = np.zeros(L)
    a = np.zeros(L)
    b[:num.size] = num
    a[:den.size] = den
    a0 = a[0]
    for n in range(L):           # scipy: b[n] /= a0 then a[n] /= a0, n = 0 … L-1
        b[n] = b[n] / a0
        a[n] = a[n] / a0
    return b, a


@numba.njit(cache=True)
def _mlp_jacobian_row(acts, Ws, w_out, out_bias, k, gain, jr, d, t):
    """Row k of ∂g/∂φ of g = w_outᵀ h_L (+ b_out), h_l = tanh(W_l h_{l-1} + b_l), h_0 = x, into ``jr``
    (φ order: W_1, b_1, …, W_L, b_L, w_out[, b_out]) times ``gain``; ``acts`` = (x, h_1, …, h_L) [N, ·],
    ``d``, ``t``: scratch of the widest layer.  The offsets into ``jr`` are unsigned, so numba adds no
    negative-index fix-up and the inner loops are vectorised."""
    u = np.uint64
    L = len(Ws)
    hL = acts[L][k]
    wL = hL.shape[0]
    o = u(jr.shape[0] - wL - (1 if out_bias else 0))
    for i in range(wL):
        jr[o + u(i)] = hL[i]                           # ∂g/∂w_out = h_L
    if out_bias:
        jr[o + u(wL)] = 1.0
    for i in range(wL):
        d[i] = w_out[i] * (1.0 - hL[i] * hL[i])        # ∂g/∂(pre-activation of layer L)
    end = o
    for l in range(L - 1, -1, -1):
        W = Ws[l]
        n_out, n_in = W.shape
        a_in = acts[l][k]
        start = end - u(n_out * n_in + n_out)
        bias = start + u(n_out * n_in)
        for i in range(n_out):
            di = d[i]
            q = start + u(i * n_in)
            for j in range(n_in):
                jr[q + u(j)] = di * a_in[j]            # ∂g/∂W_l[i, j]
            jr[bias + u(i)] = di                       # ∂g/∂b_l[i]
        if l > 0:                                      # back through W_l and the tanh of layer l-1
            for j in range(n_in):
                t[j] = 0.0
            for i in range(n_out):
                di = d[i]
                for j in range(n_in):
                    t[j] += di * W[i, j]
            for j in range(n_in):
                d[j] = t[j] * (1.0 - a_in[j] * a_in[j])
        end = start
    if gain != 1.0:
        for c in range(jr.shape[0]):
            jr[c] *= gain


@numba.njit(cache=True)
def _lfilter_step(x, y, Z, b, a):
    """One sample of scipy's lfilter (DOUBLE_filt) for every column at once, the same operations in
    the same order: y = Z_0 + b_0 x, Z_n = (Z_{n+1} + x b_{n+1}) - y a_{n+1}, Z_last = x b_last - y a_last."""
    L = b.shape[0]
    m = x.shape[0]
    b0 = b[0]
    if L == 1:
        for c in range(m):
            y[c] = x[c] * b0
    elif L == 3:                                       # second order (n_b = 2): one pass
        b1, a1, b2, a2 = b[1], a[1], b[2], a[2]
        Z0, Z1 = Z[0], Z[1]
        for c in range(m):
            xc = x[c]
            yc = Z0[c] + b0 * xc
            Z0[c] = Z1[c] + xc * b1 - yc * a1
            Z1[c] = xc * b2 - yc * a2
            y[c] = yc
    else:
        for c in range(m):
            y[c] = Z[0, c] + b0 * x[c]
        for n in range(L - 2):
            bn, an = b[n + 1], a[n + 1]
            Zn, Zn1 = Z[n], Z[n + 1]
            for c in range(m):
                Zn[c] = Zn1[c] + x[c] * bn - y[c] * an
        bl, al = b[L - 1], a[L - 1]
        Zl = Z[L - 2]
        for c in range(m):
            Zl[c] = x[c] * bl - y[c] * al


@numba.njit(cache=True, inline="always")
def _row_buffers(acts, n_phi, nb):
    """Work arrays of one Jacobian row: the row, two layer-width vectors, the filter state."""
    width = 1
    for l in range(len(acts)):
        width = max(width, acts[l].shape[1])
    return np.empty(n_phi), np.empty(width), np.empty(width), np.zeros((max(nb - 1, 1), n_phi))


@numba.njit(cache=True)
def _mlp_filtered_jacobian(acts, Ws, w_out, out_bias, gain, b, a, bounds, WJ):
    """WJ [N, n_φ] (C order) = (num/den) ∂g/∂φ filtered along time, per segment from rest."""
    n_phi = WJ.shape[1]
    jr, d, t, Z = _row_buffers(acts, n_phi, b.shape[0])
    for s in range(bounds.shape[0]):
        Z[:] = 0.0
        for k in range(bounds[s, 0], bounds[s, 1]):
            _mlp_jacobian_row(acts, Ws, w_out, out_bias, k, gain, jr, d, t)
            _lfilter_step(jr, WJ[k], Z, b, a)


@numba.njit(cache=True)
def _mlp_filtered_gram(acts, Ws, w_out, out_bias, gain, b, a, bounds, U1, r, block, G):
    """The reductions of WJ = (num/den) ∂g/∂φ without storing it: ``block`` rows at a time in one
    buffer (in cache), each row [WJ_k, U1_k, r_k], reduced by one BLAS syrk per block into G (lower
    triangle, Fortran order, n_φ + p + 1 square): WJᵀWJ, and below it U1ᵀWJ = C, rᵀWJ, U1ᵀU1, rᵀU1, rᵀr
    (the p + 1 extra columns cost less than a gemm and a gemv of the block)."""
    n_phi = G.shape[0] - U1.shape[1] - 1
    p = U1.shape[1]
    jr, d, t, Z = _row_buffers(acts, n_phi, b.shape[0])
    N = bounds[bounds.shape[0] - 1, 1]
    w = G.shape[0]
    Jb = np.empty((min(block, N), w))
    i = 0
    for s in range(bounds.shape[0]):
        Z[:] = 0.0
        for k in range(bounds[s, 0], bounds[s, 1]):
            _mlp_jacobian_row(acts, Ws, w_out, out_bias, k, gain, jr, d, t)
            row = Jb[i]
            _lfilter_step(jr, row[:n_phi], Z, b, a)
            for q in range(p):
                row[n_phi + q] = U1[k, q]
            row[n_phi + p] = r[k]
            i += 1
            if i == Jb.shape[0] or k == N - 1:
                blas_syrk_lower(w, i, Jb, G)
                i = 0


class SharedARPGNN(RationalFeedforward):
    """Feedforward F_θ,φ of [K] (6): model M_θ and approximator C_φ sharing B(q).

    Parameters
    ----------
    n_a, n_b, basis, Ts, a, b
        As :class:`~pipeline.models.rational.RationalFeedforward` ([K] VI-B: n_a = 5,
        n_b = 2).
    g : torch.nn.Module
        Approximator g_φ: maps normalised window features [N, q+1] to [N] (or [N, 1]).
    window : ReferenceWindow
        Input transform of g_φ (its normalisation must be fitted on the training data).

    Notes
    -----
    The buffer ``g_gain`` (1 unless a root of B was reflected, SPEC §5) multiplies g_φ.
    """

    def __init__(self, n_a: int, n_b: int, g: nn.Module, window: ReferenceWindow,
                 basis: str = "delta", Ts: float = 1e-3, a=None, b=None):
        super().__init__(n_a, n_b, basis=basis, Ts=Ts, a=a, b=b)
        if not isinstance(g, nn.Module):
            raise TypeError(f"g must be a torch.nn.Module, got {type(g).__name__}")
        self.g = g.double()
        self.window = window
        self.register_buffer("g_gain", torch.ones((), dtype=torch.float64))

    # -- data ----------------------------------------------------------------------------
    def inputs(self, r, segments: Segments | None = None) -> dict:
        inp = super().inputs(r, segments)
        inp["X"] = torch.from_numpy(self.window.features(inp["r"], inp["segments"]))
        return inp

    # -- approximator ----------------------------------------------------------------------
    def exogenous_extra(self, inputs: dict) -> torch.Tensor:
        out = self.g(self.window(inputs["X"]))
        return self.g_gain * out.reshape(-1)

    def scale_extra(self, gain: float) -> None:
        with torch.no_grad():
            self.g_gain.mul_(gain)

    @property
    def phi(self) -> torch.Tensor:
        """φ: the approximator's parameters as one flat float64 vector."""
        return nn.utils.parameters_to_vector(self.g.parameters()).detach().clone()

    def set_phi(self, phi: torch.Tensor) -> None:
        phi = torch.as_tensor(phi, dtype=torch.float64)
        if phi.numel() != self.n_phi:
            raise ValueError(f"φ has {phi.numel()} entries, the approximator {self.n_phi}")
        with torch.no_grad():
            nn.utils.vector_to_parameters(phi.detach().clone(), self.g.parameters())

    @property
    def n_phi(self) -> int:
        return int(sum(p.numel() for p in self.g.parameters()))

    def _functional_g(self, Xn: torch.Tensor):
        """g as a function of a flat φ vector (torch.func), on normalised features."""
        names = [n for n, _ in self.g.named_parameters()]
        shapes = [p.shape for _, p in self.g.named_parameters()]
        sizes = [math.prod(s) for s in shapes]

        def g_of(phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            chunks = torch.split(phi, sizes)
            params = {n: c.view(s) for n, c, s in zip(names, chunks, shapes)}
            return torch.func.functional_call(self.g, params, (x,)).reshape(-1)
        return g_of

    def g_and_jacobian(self, inputs: dict, phi: torch.Tensor | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """g(r) [N] and its exact Jacobian ∂g/∂φ [N, n_φ] (columns in the order of φ).

        ``phi`` defaults to the current parameters; the model is not modified.  Uses
        :func:`per_sample_jacobian` (one forward and one backward pass).
        """
        Xn = self.window(inputs["X"]).detach()
        g, J = per_sample_jacobian(self.g, Xn, phi)
        if float(self.g_gain) == 1.0:      # the usual case: skip two [N, n_φ] passes (same bits)
            return g, J
        return self.g_gain * g, self.g_gain * J

    def g_value(self, inputs: dict, phi: torch.Tensor) -> torch.Tensor:
        """g(r) at parameters φ without changing the model [N]."""
        Xn = self.window(inputs["X"]).detach()
        with torch.no_grad():
            return self.g_gain * self._functional_g(Xn)(torch.as_tensor(phi, dtype=torch.float64), Xn)

    def _g_of_phi(self, inputs: dict):
        """g on these inputs as a function of the flat φ alone (for torch.func), without the gain."""
        Xn = self.window(inputs["X"]).detach()
        g_of = self._functional_g(Xn)
        return lambda p: g_of(p, Xn)

    def g_jvp(self, inputs: dict, phi: torch.Tensor, v: torch.Tensor, acts=None) -> torch.Tensor:
        """∂g/∂φ · v [N] at φ, without forming ∂g/∂φ; the model is not modified.  A tanh MLP in closed
        form (forward-mode chain rule through the layers, from the activations ``acts`` of
        :meth:`g_forward` at φ when given), any other approximator by ``torch.func.jvp``.  Equal to
        ``g_and_jacobian(inputs, φ)[1] @ v`` to rounding."""
        lin = self._mlp_layers()
        if lin is None:
            _, out = torch.func.jvp(self._g_of_phi(inputs), (torch.as_tensor(phi, dtype=torch.float64),),
                                    (torch.as_tensor(v, dtype=torch.float64),))
            return float(self.g_gain) * out
        acts = self.g_forward(inputs, phi)[1] if acts is None else acts
        P, D = self._mlp_parameters(phi, lin), self._mlp_parameters(v, lin)
        t = None                                   # the tangent of the layer's input (x does not move)
        for a, h, (W, _), (dW, db) in zip(acts[:-1], acts[1:], P[:-1], D[:-1]):
            dz = a @ dW.numpy().T + db.numpy()    # z = W a + b  ->  dz = dW a + db + W da
            if t is not None:
                dz += t @ W.numpy().T
            t = (1.0 - h * h) * dz                 # tanh' = 1 - tanh²
        (W, _), (dW, db) = P[-1], D[-1]
        dg = acts[-1] @ dW.numpy()[0] + t @ W.numpy()[0] + (float(db[0]) if db is not None else 0.0)
        return torch.from_numpy(float(self.g_gain) * dg)

    def g_vjp(self, inputs: dict, phi: torch.Tensor, w: torch.Tensor, acts=None) -> torch.Tensor:
        """(∂g/∂φ)ᵀ w [n_φ] at φ, without forming ∂g/∂φ; the model is not modified.  A tanh MLP in
        closed form (backpropagation of w through the layers, from ``acts`` of :meth:`g_forward` at φ
        when given), any other approximator by ``torch.func.vjp``.  Equal to
        ``g_and_jacobian(inputs, φ)[1].T @ w`` to rounding."""
        lin = self._mlp_layers()
        if lin is None:
            _, pull = torch.func.vjp(self._g_of_phi(inputs), torch.as_tensor(phi, dtype=torch.float64))
            return float(self.g_gain) * pull(torch.as_tensor(w, dtype=torch.float64))[0]
        acts = self.g_forward(inputs, phi)[1] if acts is None else acts
        P = self._mlp_parameters(phi, lin)
        w = float(self.g_gain) * np.asarray(w, dtype=np.float64)
        grads = [[w @ acts[-1]] + ([np.array([w.sum()])] if P[-1][1] is not None else [])]
        delta = np.outer(w, P[-1][0].numpy()[0])          # ∂/∂h_L
        for a, h, (W, _) in zip(acts[-2::-1], acts[:0:-1], P[-2::-1]):
            delta = delta * (1.0 - h * h)                   # ∂/∂z of this layer
            grads.append([(delta.T @ a).ravel(), delta.sum(axis=0)])
            delta = delta @ W.numpy()                       # ∂/∂ its input
        return torch.from_numpy(np.concatenate([c for layer in grads[::-1] for c in layer]))

    # -- closed-form filtered Jacobian (tanh MLP) ------------------------------------------
    def _mlp_layers(self) -> list[nn.Linear] | None:
        """The Linear layers of a tanh :class:`MLP` approximator with at least one hidden layer
        (biases in every hidden layer), or None for any other approximator."""
        if type(self.g) is not MLP:
            return None
        mods = list(self.g.net)
        lin, act = mods[0::2], mods[1::2]
        if len(lin) != len(act) + 1 or len(act) < 1 or not all(type(m) is nn.Linear for m in lin) \
                or not all(type(m) is Tanh for m in act) or lin[-1].out_features != 1 \
                or any(m.bias is None for m in lin[:-1]):
            return None
        return lin

    @property
    def closed_form_jacobian(self) -> bool:
        """g_φ has the closed-form (filtered) Jacobian of :meth:`g_forward` / :meth:`filtered_jacobian`."""
        return self._mlp_layers() is not None

    def _mlp_parameters(self, phi, lin) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
        """(W, b) of every Linear layer as views of the flat φ (the split of :meth:`_functional_g`)."""
        phi = torch.as_tensor(phi, dtype=torch.float64)
        shapes = [p.shape for p in self.g.parameters()]
        chunks = iter(c.view(sh) for c, sh in zip(torch.split(phi, [math.prod(sh) for sh in shapes]), shapes))
        return [(next(chunks), next(chunks) if m.bias is not None else None) for m in lin]

    def g_forward(self, inputs: dict, phi: torch.Tensor):
        """(g(r) at φ [N], the activations (x, h_1, …, h_L) as numpy arrays [N, ·]) of a tanh MLP
        (None for another approximator): the operations of :meth:`g_value` (the same bits), with the
        layer outputs kept for :meth:`filtered_jacobian` at the same φ."""
        lin = self._mlp_layers()
        if lin is None:
            return None
        x = self.window(inputs["X"]).detach()
        params = self._mlp_parameters(phi, lin)
        acts = [x]
        with torch.no_grad():
            for W, b in params[:-1]:
                x = tanh(nn.functional.linear(x, W, b))
                acts.append(x)
            W, b = params[-1]
            g = self.g_gain * nn.functional.linear(x, W, b).squeeze(-1).reshape(-1)
        return g, tuple(a.numpy() for a in acts)

    def _filtered_jacobian_args(self, inputs, phi, num, den, segments, acts):
        lin = self._mlp_layers()
        if acts is None:
            acts = self.g_forward(inputs, phi)[1]
        params = self._mlp_parameters(phi, lin)
        Ws = tuple(np.ascontiguousarray(W.numpy()) for W, _ in params[:-1])
        w_out = np.ascontiguousarray(params[-1][0].numpy()[0])
        b, a = _lfilter_coefficients(num, den)
        bounds = np.array(segments.bounds, dtype=np.int64)
        return (tuple(np.ascontiguousarray(x) for x in acts), Ws, w_out, params[-1][1] is not None,
                float(self.g_gain), b, a, bounds)

    def filtered_jacobian(self, inputs: dict, phi: torch.Tensor, num, den, segments: Segments,
                          acts=None) -> np.ndarray | None:
        """(num/den)(q) ∂g/∂φ [N, n_φ] (C order), each column filtered per segment from rest as
        :func:`~pipeline.models.rational.filter_segments` does (scipy's lfilter arithmetic), in one
        numba pass over time (:func:`_mlp_filtered_jacobian`); ``acts``: the activations of
        :meth:`g_forward` at this φ.  None when g_φ has no closed form (:attr:`closed_form_jacobian`).

        ∂g/∂φ is the exact Jacobian of :meth:`g_and_jacobian` (backpropagation in closed form, in
        another order of the sums: equal to rounding, not to the bit)."""
        if not self.closed_form_jacobian:
            return None
        args = self._filtered_jacobian_args(inputs, phi, num, den, segments, acts)
        WJ = np.empty((segments.n, self.n_phi))
        _mlp_filtered_jacobian(*args, WJ)
        return WJ

    def filtered_jacobian_gram(self, inputs: dict, phi: torch.Tensor, num, den, segments: Segments,
                               U1: np.ndarray, r: np.ndarray, acts=None, block: int = 240):
        """(G, C, WJᵀr) of WJ = :meth:`filtered_jacobian` without storing WJ: G = WJᵀWJ [n_φ, n_φ]
        (symmetric), C = U1ᵀ WJ [p, n_φ], WJᵀr [n_φ], reduced ``block`` rows at a time while they are
        in cache (:func:`_mlp_filtered_gram`: one BLAS syrk per block of the rows [WJ, U1, r]).  None
        when g_φ has no closed form.

        ``block``: 240, not a power of two. On the AVX-512 EPYC (OpenBLAS SkylakeX kernels, 21167 × 188)
        blocks of 256 and 512 rows took 27.3–27.8 ms and every other size from 96 to 1536 22.5–23.9 ms
        (``benchmarks/bench_iterations.py --case k`` prints the kernel by block size; issue 19)."""
        if not self.closed_form_jacobian:
            return None
        args = self._filtered_jacobian_args(inputs, phi, num, den, segments, acts)
        n, p = self.n_phi, U1.shape[1]
        Ga = np.zeros((n + p + 1, n + p + 1), order="F")
        _mlp_filtered_gram(*args, np.ascontiguousarray(U1), np.ascontiguousarray(r, dtype=np.float64),
                           int(block), Ga)
        G = np.tril(Ga[:n, :n]) + np.tril(Ga[:n, :n], -1).T
        return G, Ga[n:n + p, :n].copy(), Ga[n + p, :n].copy()
