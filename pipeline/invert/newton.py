"""Newton inversion of a forward PGNN, [B1] Algorithm 1 (SPEC §6).

Per sample t, solve V_R(u) := r(t+n_k+1) - ŷ(θ̂, φ_ff(t+n_k+1)) = 0 ([B1] (23)) for
u = u_ff(t), with φ_ff(t+n_k+1) = [r(t+n_k), …, r(t+n_k+1-n_a), u, u_ff(t-1), …]:

- start from the physics feedforward u⁽⁰⁾ = f_phy⁻¹(θ*_phy, φ'_ff(t)) ([B1] (8)), computed with
  the Newton history u_ff(t-1), …;
- k Newton–Raphson updates u⁽ⁱ⁾ = u⁽ⁱ⁻¹⁾ - V_R/V_R' (the paper prints V_R'/V_R, a misprint),
  V_R' = -∂f_phy/∂u - ∂f_NN/∂u ([B1] (24), (25));
- return the iterate with the smallest |V_R| (the best one, not the last).

Never silent: ``flags`` marks per sample (bit mask) ``BOUNDS`` (the start or an update
left [u_min, u_max]: the search stopped there; the start is clipped into the bounds),
``SINGULAR`` (zero or non-finite derivative or prediction: stopped), ``DIVERGED`` (the last
evaluated |V_R| exceeds the first one).  In every case the best iterate so far is returned.

Two implementations: numba (one-hidden-layer tanh, built-in physics maps; per-sample
:func:`newton_step` for real-time use and timing) and the torch reference with autograd
derivatives (any PGNN), held equal to 1e-10 by the tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from pipeline.invert.analytic import analytic_solve
from pipeline.invert.direct import initial_state, reference_regressor, resolve_fast
from pipeline.models.fast_pgnn import (
    fast_build_phi,
    fast_nn_affine,
    fast_physics_affine,
    fast_push_input,
    fast_push_reference,
    padded_reference,
)
from pipeline.models.pgnn import PGNN

__all__ = ["NewtonResult", "newton_feedforward", "newton_step", "newton_solve",
           "BOUNDS", "SINGULAR", "DIVERGED"]

BOUNDS, SINGULAR, DIVERGED = 1, 2, 4


@dataclass
class NewtonResult:
    """Feedforward of [B1] Alg. 1 and its diagnostics.

    u_ff [N] feedforward [N]; residual [N] |V_R| at the returned u_ff ([B1] (23)), units of
    y; flags [N] bit mask (BOUNDS=1, SINGULAR=2, DIVERGED=4); best_iter [N] index of the
    returned iterate (0 = physics start); k Newton updates allowed.
    """

    u_ff: np.ndarray
    residual: np.ndarray
    flags: np.ndarray
    best_iter: np.ndarray
    k: int

    @property
    def n_bounds(self) -> int:
        return int(np.count_nonzero(self.flags & BOUNDS))

    @property
    def n_singular(self) -> int:
        return int(np.count_nonzero(self.flags & SINGULAR))

    @property
    def n_diverged(self) -> int:
        return int(np.count_nonzero(self.flags & DIVERGED))

    @property
    def n_fallback(self) -> int:
        """Samples where Newton did not run cleanly (any flag set)."""
        return int(np.count_nonzero(self.flags))

    def summary(self) -> dict[str, float]:
        return {"n_bounds": self.n_bounds, "n_singular": self.n_singular,
                "n_diverged": self.n_diverged, "max_residual": float(np.max(self.residual)),
                "median_residual": float(np.median(self.residual))}


@numba.njit(cache=True)
def newton_solve(blob, meta, phi, r_next, k, lo, hi):
    """[B1] Alg. 1 for one sample; φ has the u_ff(t) slot free.  Returns
    (u_best, |V_R|(u_best), flags, best_iter)."""
    iu = meta[4]
    flags = 0
    u = analytic_solve(blob, meta, phi, r_next, True, False)  # physics start, θ*_phy
    if not math.isfinite(u):
        u = 0.0
        flags |= SINGULAR
    if u < lo:
        u, flags = lo, flags | BOUNDS
    elif u > hi:
        u, flags = hi, flags | BOUNDS
    phi[iu] = 0.0
    a, psi = fast_physics_affine(blob, meta, phi, False)  # θ̂_phy: ŷ = a + ψ u + f_NN
    best_u, best_v, best_i = u, np.inf, 0
    first_v, last_v = np.nan, np.nan
    for i in range(k + 1):
        phi[iu] = u
        nn, dnn = fast_nn_affine(blob, meta, phi)
        V = r_next - (a + psi * u + nn)  # [B1] (23)
        if not math.isfinite(V):
            flags |= SINGULAR
            break
        av = abs(V)
        if i == 0:
            first_v = av
        last_v = av
        if av < best_v:
            best_u, best_v, best_i = u, av, i
        if i == k or V == 0.0:
            break
        dV = -(psi + dnn)  # [B1] (24), (25)
        if dV == 0.0 or not math.isfinite(dV):
            flags |= SINGULAR
            break
        u_new = u - V / dV
        if not (lo <= u_new <= hi):
            flags |= BOUNDS
            break
        u = u_new
    if last_v > first_v:
        flags |= DIVERGED
    if best_v == np.inf:  # not even the start could be evaluated
        best_u = u
    phi[iu] = 0.0
    return best_u, best_v, flags, best_i


@numba.njit(cache=True)
def newton_step(blob, meta, state, r_new, k, lo, hi):
    """One sample of [B1] Alg. 1: push r(t+n_k+1), return u_ff(t) (see :func:`newton_solve`)."""
    fast_push_reference(state, meta, r_new)
    phi = fast_build_phi(state, meta, False)
    u, v, f, i = newton_solve(blob, meta, phi, r_new, k, lo, hi)
    fast_push_input(state, meta, u)
    return u


@numba.njit(cache=True)
def _newton_run(blob, meta, state, r_ext, N, k, lo, hi):
    n_a, n_k = meta[7], meta[9]
    u = np.empty(N)
    res = np.empty(N)
    flags = np.zeros(N, dtype=np.int64)
    best = np.zeros(N, dtype=np.int64)
    for t in range(N):
        rn = r_ext[t + n_k + 1 + n_a]
        fast_push_reference(state, meta, rn)
        phi = fast_build_phi(state, meta, False)
        u[t], res[t], flags[t], best[t] = newton_solve(blob, meta, phi, rn, k, lo, hi)
        fast_push_input(state, meta, u[t])
    return u, res, flags, best


def _reference_solve(model: PGNN, phi: torch.Tensor, r_next: float, k: int, lo: float, hi: float,
                     theta_start: torch.Tensor):
    """Torch reference of :func:`newton_solve` (autograd derivative, any PGNN)."""
    iu = model.u_index
    flags = 0
    with torch.no_grad():
        a0, psi0 = model.physics_affine(phi, theta_start)
        a0, psi0 = float(a0[0]), float(psi0[0])
    u = (r_next - a0) / psi0 if psi0 != 0.0 else math.nan  # physics start [B1] (8)
    if not math.isfinite(u):
        u, flags = 0.0, flags | SINGULAR
    if u < lo:
        u, flags = lo, flags | BOUNDS
    elif u > hi:
        u, flags = hi, flags | BOUNDS
    best_u, best_v, best_i = u, math.inf, 0
    first_v = last_v = math.nan
    for i in range(k + 1):
        x = phi.clone()
        uu = torch.tensor(u, dtype=torch.float64, requires_grad=True)
        x[0, iu] = uu
        yhat = model(x)[0]
        V = r_next - float(yhat.detach())  # [B1] (23)
        if not math.isfinite(V):
            flags |= SINGULAR
            break
        av = abs(V)
        if i == 0:
            first_v = av
        last_v = av
        if av < best_v:
            best_u, best_v, best_i = u, av, i
        if i == k or V == 0.0:
            break
        dV = -float(torch.autograd.grad(yhat, uu)[0])  # [B1] (24), (25) by backprop
        if dV == 0.0 or not math.isfinite(dV):
            flags |= SINGULAR
            break
        u_new = u - V / dV
        if not (lo <= u_new <= hi):
            flags |= BOUNDS
            break
        u = u_new
    if last_v > first_v:
        flags |= DIVERGED
    if best_v == math.inf:
        best_u = u
    return best_u, best_v, flags, best_i


def newton_feedforward(model: PGNN, r, *, k: int = 5, u_bounds=None, theta_start=None,
                       fast: bool | None = None) -> NewtonResult:
    """Feedforward of a forward-layout PGNN by [B1] Algorithm 1.

    Parameters
    ----------
    model : PGNN
        Forward (or invertible) PGNN with a physics part affine in u(t-n_k-1) (the start
        is the physics feedforward).
    r : array [N]
        Reference [m].
    k : int
        Newton updates per sample ([B1] §VI: 5).
    u_bounds : (float, float), optional
        Input bounds [N] of the search; None for unbounded.
    theta_start : array, optional
        θ_phy of the physics start (default θ*_phy of [B1] (7), else the model's θ_phy).
    fast : bool or None
        Numba path (True), torch reference (False), or numba when available (None).
    """
    if model.structure == "inverse":
        raise ValueError("Newton inversion needs a forward-layout PGNN (structure='forward' or "
                         "'invertible'); a direct-inverse PGNN is evaluated by direct_feedforward")
    if not model.use_physics or not model.physics.affine_in_latest_input:
        raise ValueError("Newton inversion starts from the physics feedforward [B1] (8): the model "
                         "needs a physics part affine in u(t-n_k-1)")
    if int(k) != k or k < 0:
        raise ValueError(f"k must be a non-negative integer number of Newton updates, got {k}")
    lo, hi = (-math.inf, math.inf) if u_bounds is None else (float(u_bounds[0]), float(u_bounds[1]))
    if not lo < hi:
        raise ValueError(f"u_bounds must satisfy u_min < u_max, got {u_bounds}")
    if theta_start is None:
        star = model.theta_phy_star.detach().numpy()
        theta_start = star if np.all(np.isfinite(star)) else model.theta_phy.detach().numpy()
    theta_start = np.asarray(theta_start, dtype=float)
    r_ext = padded_reference(r, model.n_a, model.n_k)
    N = r_ext.shape[0] - model.n_a - model.n_k - 1
    fm = resolve_fast(model, fast, theta_start=theta_start)
    if fm is not None:
        u, res, flags, best = _newton_run(fm.blob, fm.meta, initial_state(fm, r_ext), r_ext, N,
                                          int(k), lo, hi)
        return NewtonResult(u, res, flags, best, int(k))
    u = np.zeros(N)
    res = np.zeros(N)
    flags = np.zeros(N, dtype=np.int64)
    best = np.zeros(N, dtype=np.int64)
    ts = torch.as_tensor(theta_start)
    for t in range(N):
        phi = reference_regressor(model, r_ext, u, t)
        rn = r_ext[t + model.n_k + 1 + model.n_a]
        u[t], res[t], flags[t], best[t] = _reference_solve(model, phi, rn, int(k), lo, hi, ts)
    return NewtonResult(u, res, flags, best, int(k))
