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
from typing import Sequence

import numpy as np
import torch
from torch import nn

from pipeline.models.rational import BASES, RationalFeedforward, Segments, basis_columns

__all__ = ["ReferenceWindow", "MLP", "ResidualMLP", "SharedARPGNN", "make_approximator",
           "per_sample_jacobian"]

_ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "sigmoid": nn.Sigmoid, "softplus": nn.Softplus}


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
