"""Rational feedforward ``B(q) f = A(q) r`` with linear AR dynamics ([K] (2), SPEC §3 item 2).

The feedforward filter of [K] (6) is

    B(q) f(k) = A(r(k)) + g(r(k)),     B(q) = ψ_0 + Σ_{i=1..N_b} b_i ψ_i(q),
                                        A(r) = Σ_{i=1..N_a} a_i ψ_{i-1}(q) r,

with the basis either ``shift`` (ψ_i = q^{-i}, [K] VI-B: ψ_i(r) = q^{-i+1} r for A) or
``delta`` (ψ_i = δ^i, δ = (1 - q^{-1})/Ts, SPEC §0), which is far better conditioned at high
sample rates (the q^{-i} columns of a slowly varying reference agree in their 4th digit at
Ts = 1 ms).  Normalisation: the coefficient of ψ_0 in B is 1 (monic in q^{-1} for ``shift``,
unit DC gain B(q=1) = 1 for ``delta``).  ``g`` is the exogenous approximator slot of the PGNN
(:mod:`pipeline.models.shared_ar`); it is absent (zero) for the rational transfer function.

Signals made of several references are handled as one concatenated 1-D array plus the
lengths of its :class:`Segments`; every filter restarts at rest at a segment boundary
(SPEC §0), so results equal filtering each reference on its own.

Filtering by ``1/B(q)`` is a recursive filter (:func:`filter_segments`, scipy's ``lfilter``)
that torch differentiates through with :class:`RecursiveFilter`, whose backward pass is the
time-reversed filter (the adjoint of a causal LTI operator); no N×N matrix is ever formed.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import comb
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.signal
import torch
from torch import nn

from pipeline.params import schema, spec


@schema
class Params:
    kind: Literal["rational"]
    name: str = "rational"
    # coefficients a_i of A = Σ a_i ψ_{i-1} r ([K] VI-B: 10, "10th-order rational TF")
    n_a: int = spec(10, ge=1, le=1000)
    # AR coefficients b_i of B = ψ_0 + Σ b_i ψ_i ([K] VI-B: 9)
    n_b: int = spec(9, ge=0, le=1000)
    # ψ_i = δ^i (delta) | q^-i (shift, the paper's). Same model class; at Ts = 1 ms the shift basis makes W M
    # numerically singular after weighting by 1/B (σ_min/σ_max ~ 4e-16)
    basis: Literal["delta", "shift"] = "delta"


__all__ = ["BASES", "Segments", "basis_matrix", "basis_columns", "ar_polynomial",
           "basis_coefficients", "reflect_unstable_roots", "filter_segments", "RecursiveFilter",
           "recursive_filter", "UnstableFilterError", "RationalFeedforward"]

#: the bases ψ_i of the polynomials A and B
BASES = ("shift", "delta")


# ----------------------------------------------------------------------------- segments
@dataclass(frozen=True)
class Segments:
    """Lengths of the references concatenated into one signal (each filtered from rest).

    Parameters
    ----------
    lengths : tuple of int
        Number of samples of each reference, in order.
    """

    lengths: tuple[int, ...]

    def __post_init__(self):
        if len(self.lengths) == 0 or any(int(n) < 1 for n in self.lengths):
            raise ValueError(f"segment lengths must be positive integers, got {self.lengths}; "
                             "drop empty references")
        object.__setattr__(self, "lengths", tuple(int(n) for n in self.lengths))

    @property
    def n(self) -> int:
        """Total number of samples."""
        return int(sum(self.lengths))

    @property
    def bounds(self) -> list[tuple[int, int]]:
        """(start, stop) index of every segment in the concatenated signal."""
        edges = np.concatenate([[0], np.cumsum(self.lengths)])
        return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]

    @classmethod
    def concat(cls, signals, name: str = "signal") -> tuple[np.ndarray, "Segments"]:
        """Concatenate one 1-D signal or a list of 1-D signals; return (array, segments)."""
        if isinstance(signals, np.ndarray) and signals.ndim == 1:
            signals = [signals]
        arrays = []
        for i, s in enumerate(signals):
            a = np.asarray(s, dtype=np.float64)
            if a.ndim != 1 or a.size == 0:
                raise ValueError(f"{name} #{i} must be a non-empty 1-D array, got shape {a.shape}; "
                                 "pass one array per reference")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} #{i} contains NaN/inf (first at sample "
                                 f"{int(np.flatnonzero(~np.isfinite(a))[0])}); clean the data")
            arrays.append(a)
        if not arrays:
            raise ValueError(f"no {name} given; pass at least one reference")
        return np.concatenate(arrays), cls(tuple(a.size for a in arrays))

    def split(self, x) -> list:
        """Split a concatenated signal (first axis) into its segments."""
        if len(x) != self.n:
            raise ValueError(f"signal has {len(x)} samples, the segments {self.n}")
        return [x[a:b] for a, b in self.bounds]

    def check(self, x, name: str = "signal") -> None:
        if x.shape[0] != self.n:
            raise ValueError(f"{name} has {x.shape[0]} samples but the segments hold {self.n}; "
                             "build every signal from the same references")


# ----------------------------------------------------------------------------- bases
def _check_basis(basis: str) -> str:
    if basis not in BASES:
        raise ValueError(f"unknown basis '{basis}'; choose one of {BASES}")
    return basis


def basis_matrix(basis: str, n: int, Ts: float) -> np.ndarray:
    """Matrix T [n+1, n+1] mapping basis coefficients β to q^{-1} coefficients c = T β.

    ``shift``: ψ_i = q^{-i}, T = I.  ``delta``: ψ_i = δ^i = Ts^{-i} (1 - q^{-1})^i, so
    column i holds Ts^{-i} (-1)^k C(i, k) at row k (upper triangular, invertible).
    """
    _check_basis(basis)
    if basis == "shift":
        return np.eye(n + 1)
    if not Ts > 0:
        raise ValueError(f"sample time Ts must be > 0 s for the delta basis, got {Ts}")
    T = np.zeros((n + 1, n + 1))
    for i in range(n + 1):
        for k in range(i + 1):
            T[k, i] = (-1.0) ** k * comb(i, k) / Ts ** i
    return T


def basis_columns(x: np.ndarray, segments: Segments, basis: str, n: int, Ts: float,
                  first: int = 0) -> np.ndarray:
    """Columns ψ_i(x), i = first..n, of a concatenated signal, at rest before each segment.

    ``delta`` columns are computed by repeated backward differences, not by the FIR filter
    Ts^{-i}(1 - q^{-1})^i whose 1e12-sized taps (i = 4, Ts = 1 ms) would cancel catastrophically.

    Returns
    -------
    np.ndarray
        [N, n + 1 - first] (units of x per s^i for ``delta``).
    """
    _check_basis(basis)
    x = np.asarray(x, dtype=np.float64)
    segments.check(x)
    out = np.empty((x.size, n + 1 - first))
    for a, b in segments.bounds:
        col = x[a:b].copy()
        for i in range(n + 1):
            if i >= first:
                out[a:b, i - first] = col
            if i == n:
                break
            if basis == "shift":  # q^{-1}
                col = np.concatenate([[0.0], col[:-1]])
            else:                 # δ = (1 - q^{-1})/Ts, at rest before the segment
                col = np.diff(col, prepend=0.0) / Ts
    return out


def ar_polynomial(b, basis: str, Ts: float) -> np.ndarray:
    """q^{-1} coefficients ``c`` of B(q) = ψ_0 + Σ b_i ψ_i (``lfilter`` denominator of 1/B)."""
    b = np.asarray(b, dtype=np.float64).ravel()
    beta = np.concatenate([[1.0], b])
    return basis_matrix(basis, b.size, Ts) @ beta


def basis_coefficients(c, basis: str, Ts: float) -> np.ndarray:
    """Inverse of :func:`ar_polynomial` without normalisation: β with T β = c (β_0 free)."""
    c = np.asarray(c, dtype=np.float64).ravel()
    T = basis_matrix(basis, c.size - 1, Ts)
    return scipy.linalg.solve_triangular(T, c, lower=False)


def reflect_unstable_roots(b, basis: str, Ts: float) -> tuple[np.ndarray, float, int]:
    """Reflect the roots of B outside the unit circle inside, keeping |B(e^{jω})| (SPEC §5).

    A root p with |p| > 1 becomes 1/p̄ (as vector fitting does); the factor (1 - p q^{-1}) is
    replaced by |p| (1 - q^{-1}/p̄), which has the same magnitude on the unit circle.  The
    result is renormalised to ψ_0-coefficient 1, so the exogenous part must be multiplied by
    the returned ``gain`` to keep the magnitude response of the filter (A + g)/B.

    Returns
    -------
    b_new : np.ndarray
        AR coefficients of the stable B (same basis).
    gain : float
        Factor for the exogenous coefficients (1.0 if nothing was reflected).
    n_reflected : int
        Number of roots that were outside the unit circle.
    """
    b = np.asarray(b, dtype=np.float64).ravel()
    c = ar_polynomial(b, basis, Ts)
    if b.size == 0:
        return b.copy(), 1.0, 0
    p = np.roots(c)
    out = np.abs(p) > 1.0
    if not np.any(out):
        return b.copy(), 1.0, 0
    p_new = np.where(out, 1.0 / np.conj(p), p)
    c_new = np.real(np.poly(p_new)) * c[0] * float(np.prod(np.abs(p[out])))
    beta = basis_coefficients(c_new, basis, Ts)
    return beta[1:] / beta[0], 1.0 / float(beta[0]), int(np.sum(out))


# ----------------------------------------------------------------------------- filters
def filter_segments(x: np.ndarray, num, den, segments: Segments, reverse: bool = False
                    ) -> np.ndarray:
    """Apply num(q)/den(q) along the first axis of x, restarting at rest in every segment.

    ``reverse=True`` applies the adjoint (time-reversed filter): for the lower-triangular
    Toeplitz matrix W of one segment, Wᵀ y = flip(W flip(y)).  A 2-D result is the
    transpose of a C-contiguous [m, N] array (columns contiguous in time).
    """
    x = np.asarray(x, dtype=np.float64)
    segments.check(x)
    num = np.atleast_1d(np.asarray(num, dtype=np.float64))
    den = np.atleast_1d(np.asarray(den, dtype=np.float64))
    if den[0] == 0:
        raise ValueError(f"filter denominator has a zero leading coefficient ({den}); "
                         "B(q) must have a nonzero q^0 coefficient to be causal")
    xt = np.ascontiguousarray(x.T)      # filter along the last, contiguous axis (no copy when
    y = np.empty_like(xt)               # x is the transpose of a C-contiguous [m, N] array)
    for a, b in segments.bounds:
        seg = xt[..., a:b]
        if reverse:
            y[..., a:b] = scipy.signal.lfilter(num, den, seg[..., ::-1], axis=-1)[..., ::-1]
        else:
            y[..., a:b] = scipy.signal.lfilter(num, den, seg, axis=-1)
    return y.T                          # same shape as x (a transposed view for 2-D x)


class RecursiveFilter(torch.autograd.Function):
    """``y = (num/den)(q) x`` per segment, differentiable in x (not in the coefficients).

    Forward and backward are ``scipy.signal.lfilter`` calls; the backward is the same
    filter run backwards in time (the adjoint), itself differentiable, so higher derivatives
    work too.  Use through :func:`recursive_filter`.
    """

    @staticmethod
    def forward(ctx, x, num, den, segments, reverse):
        ctx.filt = (num, den, segments, reverse)
        y = filter_segments(x.detach().cpu().numpy(), num, den, segments, reverse=reverse)
        return torch.from_numpy(y)

    @staticmethod
    def backward(ctx, grad_y):
        num, den, segments, reverse = ctx.filt
        return RecursiveFilter.apply(grad_y, num, den, segments, not reverse), None, None, None, None


def recursive_filter(x: torch.Tensor, num, den, segments: Segments,
                     reverse: bool = False) -> torch.Tensor:
    """Differentiable ``num(q)/den(q)`` filtering along the first axis of a float64 tensor."""
    if not isinstance(x, torch.Tensor) or x.dtype != torch.float64:
        raise TypeError(f"recursive_filter needs a float64 torch tensor, got {type(x).__name__} "
                        f"{getattr(x, 'dtype', '')}; convert with torch.as_tensor(x, dtype=torch.float64)")
    return RecursiveFilter.apply(x, np.atleast_1d(np.asarray(num, dtype=np.float64)),
                                 np.atleast_1d(np.asarray(den, dtype=np.float64)), segments, reverse)


class UnstableFilterError(ValueError):
    """B(q) has a root on or outside the unit circle: 1/B would diverge."""


# ----------------------------------------------------------------------------- the model
class RationalFeedforward(nn.Module):
    """Feedforward filter ``B(q) f = A(q) r`` ([K] (2) with g_i = Id; SPEC §3 item 2).

    Parameters
    ----------
    n_a : int
        Number of exogenous coefficients a_i (A = Σ_{i=1..n_a} a_i ψ_{i-1}).
    n_b : int
        Number of AR coefficients b_i (B = ψ_0 + Σ_{i=1..n_b} b_i ψ_i).
    basis : {'shift', 'delta'}
        Polynomial basis ψ_i = q^{-i} ([K] VI-B) or δ^i (better conditioned at small Ts).
    Ts : float
        Sample time [s].
    a, b : array_like, optional
        Initial coefficients (zeros if omitted); units N·s^{i-1}/m-like for ``delta``.

    Notes
    -----
    Subclasses add an exogenous approximator by overriding :meth:`exogenous_extra`.
    """

    def __init__(self, n_a: int, n_b: int, basis: str = "shift", Ts: float = 1e-3,
                 a=None, b=None):
        super().__init__()
        if int(n_a) < 1 or int(n_b) < 0:
            raise ValueError(f"need n_a >= 1 and n_b >= 0, got n_a={n_a}, n_b={n_b}")
        if not Ts > 0:
            raise ValueError(f"sample time Ts must be > 0 s, got {Ts}")
        self.n_a, self.n_b = int(n_a), int(n_b)
        self.basis = _check_basis(basis)
        self.Ts = float(Ts)
        self.a = nn.Parameter(self._coef(a, self.n_a, "a"))
        self.b = nn.Parameter(self._coef(b, self.n_b, "b"))

    @staticmethod
    def _coef(x, n, name):
        if x is None:
            return torch.zeros(n, dtype=torch.float64)
        t = torch.as_tensor(np.asarray(x, dtype=np.float64).ravel().copy())
        if t.numel() != n:
            raise ValueError(f"coefficient vector {name} has {t.numel()} entries, expected {n}")
        return t

    # -- parameters ---------------------------------------------------------------
    @property
    def theta(self) -> np.ndarray:
        """θ = col(a, b) ([K] Lemma 8)."""
        return np.concatenate([self.a.detach().numpy(), self.b.detach().numpy()])

    def set_theta(self, theta) -> None:
        theta = np.asarray(theta, dtype=np.float64).ravel()
        if theta.size != self.n_a + self.n_b:
            raise ValueError(f"θ has {theta.size} entries, expected n_a + n_b = {self.n_a + self.n_b}")
        with torch.no_grad():
            self.a.copy_(torch.from_numpy(theta[:self.n_a].copy()))
            self.b.copy_(torch.from_numpy(theta[self.n_a:].copy()))

    def denominator(self) -> np.ndarray:
        """q^{-1} coefficients of B(q), the denominator of the filter 1/B."""
        return ar_polynomial(self.b.detach().numpy(), self.basis, self.Ts)

    def poles(self) -> np.ndarray:
        """Roots of B in z (the poles of the feedforward filter)."""
        c = self.denominator()
        return np.roots(c) if c.size > 1 else np.zeros(0, dtype=complex)

    def is_stable(self) -> bool:
        p = self.poles()
        return bool(p.size == 0 or np.max(np.abs(p)) < 1.0)

    def check_stable(self) -> None:
        """Raise :class:`UnstableFilterError` if a root of B is on or outside the unit circle."""
        p = self.poles()
        if p.size and np.max(np.abs(p)) >= 1.0:
            bad = p[np.abs(p) >= 1.0]
            raise UnstableFilterError(
                f"the feedforward filter 1/B(q) is unstable: root(s) {np.round(bad, 6).tolist()} "
                f"(|z| = {np.round(np.abs(bad), 6).tolist()}) are on/outside the unit circle; "
                "refit with reflection of unstable roots (SK does this), lower n_b, or use the "
                "delta basis")

    def reflect_unstable(self) -> int:
        """Reflect unstable roots of B inside (SPEC §5); returns how many were reflected."""
        b_new, gain, n = reflect_unstable_roots(self.b.detach().numpy(), self.basis, self.Ts)
        if n:
            with torch.no_grad():
                self.b.copy_(torch.from_numpy(b_new))
                self.a.mul_(gain)
            self.scale_extra(gain)
        return n

    # -- regressors (parameter independent, computed once per data set) -------------
    def regressors(self, r: np.ndarray, segments: Segments) -> np.ndarray:
        """R = [ψ_0(r) … ψ_{n_a-1}(r)] [N, n_a] ([K] (14))."""
        return basis_columns(r, segments, self.basis, self.n_a - 1, self.Ts)

    def ar_regressors(self, f: np.ndarray, segments: Segments) -> np.ndarray:
        """F = [ψ_1(f) … ψ_{n_b}(f)] [N, n_b] ([K] (14), F̂ for f = f̂)."""
        if self.n_b == 0:
            return np.zeros((segments.n, 0))
        return basis_columns(f, segments, self.basis, self.n_b, self.Ts, first=1)

    def inputs(self, r, segments: Segments | None = None) -> dict:
        """Everything the model needs from a reference (concatenated), computed once."""
        if segments is None:
            r, segments = Segments.concat(r, "reference")
        r = np.asarray(r, dtype=np.float64)
        return {"r": r, "segments": segments, "R": self.regressors(r, segments)}

    # -- evaluation ---------------------------------------------------------------------
    def exogenous_extra(self, inputs: dict) -> torch.Tensor | None:
        """The approximator output g(r) [N] (none for the rational model)."""
        return None

    def scale_extra(self, gain: float) -> None:
        """Multiply the approximator output by ``gain`` (after a root reflection)."""

    def exogenous(self, inputs: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(A(r), g(r)) — the two exogenous terms of [K] (6); g is None without approximator."""
        A = torch.from_numpy(inputs["R"]) @ self.a
        return A, self.exogenous_extra(inputs)

    def parts(self, inputs: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(f_M, f_C) = (A(r)/B, g(r)/B) ([K] Def. 1, 2); f = f_M + f_C."""
        den = self.denominator()
        A, g = self.exogenous(inputs)
        seg = inputs["segments"]
        f_M = recursive_filter(A, [1.0], den, seg)
        f_C = None if g is None else recursive_filter(g, [1.0], den, seg)
        return f_M, f_C

    def simulate(self, inputs: dict) -> torch.Tensor:
        """f = (A(r) + g(r))/B(q), the feedforward of [K] (6) [N]."""
        A, g = self.exogenous(inputs)
        u = A if g is None else A + g
        return recursive_filter(u, [1.0], self.denominator(), inputs["segments"])

    def forward(self, r) -> torch.Tensor:
        """Feedforward for one reference (1-D) or a list of references (concatenated)."""
        return self.simulate(self.inputs(r))

    def feedforward(self, r) -> np.ndarray | list[np.ndarray]:
        """The trained filter run on reference(s) (SPEC §6); refuses an unstable B."""
        self.check_stable()
        single = isinstance(r, np.ndarray) and r.ndim == 1
        inp = self.inputs(r)
        with torch.no_grad():
            f = self.simulate(inp).numpy()
        return f if single else inp["segments"].split(f)
