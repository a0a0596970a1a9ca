"""Sanathanan–Koerner iterations for output-error identification ([K] Alg. 5 and 19, SPEC §5).

The output-error criterion ([K] (7))

    J_OE = Σ_k ( f̂(k) − (A(r(k)) + g_φ(r(k))) / B(q) )²

is minimised by iterating, with the weighting 1/B^{j-1}(q) fixed ([K] (10), (27), (30)),

    θ^j, φ^j = argmin ‖W^{j-1} (f̂ − M θ − g_φ(r))‖² + λ R^{j-1}(φ),   M = [R, −F̂] ([K] (14)).

W^{j-1} is a recursive filter (never an N×N matrix).  Within an iteration θ enters linearly:
for the rational model the step is closed-form least squares on the column-scaled W M; for
the PGNN θ is eliminated in closed form (variable projection, Golub–Pereyra)

    θ(φ) = (W M)^+ W (f̂ − g_φ),   cost(φ) = ‖(I − U1 U1ᵀ) W (f̂ − g_φ)‖² + λ R(φ),

which has exactly the minimisers of [K] (30) (the θ-block of [K] (23) is zeroed), and φ is
found by Levenberg–Marquardt with the exact Jacobian −W ∂g/∂φ (per-sample gradients filtered
column by column).  Initialisation per [K]: a, b from the best linear approximation (equation
error, B^0 = 1), φ as constructed (Glorot).  After every step roots of B outside the unit circle
are reflected inside (SPEC §5, reported in :attr:`SKResult.reflected`), the true J_OE is
logged, and the best iterate by J_OE is returned.

:func:`output_error_lm` minimises (7) directly by LM from a given model (SPEC §8 K3 check).
"""
from __future__ import annotations

import copy
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from pipeline.identify.lm import LMResult, levenberg_marquardt
from pipeline.identify.orthogonal import ModelSubspace, model_subspace, orthogonal_regularizer
from pipeline.models.rational import RationalFeedforward, Segments, filter_segments

__all__ = ["REGULARIZERS", "SKIterate", "SKResult", "SKNotConvergedWarning", "sk_iterations", "sk_restarts",
           "oe_cost", "output_error_lm", "output_error_problem", "OEResult", "prepare_data"]

#: relative size below which a projected Jacobian column is rounding noise (see _varpro_step)
_FLAT_RTOL = 1e-11
#: regularisers of the SK step ([K] Alg. 5 = 'none', Alg. 19 = 'orthogonal')
REGULARIZERS = ("none", "orthogonal")


class SKNotConvergedWarning(UserWarning):
    """SK stopped at max_iter before the parameter change fell below the tolerance."""


@dataclass
class SKIterate:
    """One SK iterate (j = 0 is the initialisation).

    Attributes
    ----------
    j : int
    theta : np.ndarray
        col(a, b) after the step (and after a root reflection, if any).
    phi : np.ndarray or None
        Approximator parameters (None for the rational model).
    g_gain : float
        Approximator output gain (changes only when a root reflection happened).
    J_OE : float
        True output-error cost [K] (7) of this iterate [N²].
    J_weighted : float
        Weighted cost J^j ([K] (10)) at the step's optimum, plus λR for 'orthogonal' [N²].
    regularizer : float
        R^{j-1}(φ^j) ([K] (29)) [N²] (0 without approximator).
    change : float
        Relative parameter change from the previous iterate (column-scaled θ, and φ).
    n_reflected : int
        Roots of B reflected into the unit circle after this step.
    condition : float
        Condition number of the column-scaled W^{j-1} M (over the kept directions).
    n_truncated : int
        Numerically singular directions of W^{j-1} M dropped (``weighted_rank='truncate'``).
    lm_iter : int
        LM iterations of the step (0 for closed form).
    lm_message : str
    seconds : float
        Wall time of the step [s].
    """

    j: int
    theta: np.ndarray
    phi: np.ndarray | None
    g_gain: float
    J_OE: float
    J_weighted: float = math.nan
    regularizer: float = 0.0
    change: float = math.inf
    n_reflected: int = 0
    condition: float = math.nan
    n_truncated: int = 0
    lm_iter: int = 0
    lm_message: str = ""
    seconds: float = 0.0


@dataclass
class SKResult:
    """Outcome of :func:`sk_iterations`.

    Attributes
    ----------
    model : RationalFeedforward
        The model at the best iterate (lowest J_OE); the input model is not modified.
    best : int
        Index j of that iterate.
    iterates : list of SKIterate
        Every iterate, j = 0 (initialisation) … last.
    converged : bool
        True when the parameter change fell below ``tol``.
    message : str
        'tol' or 'max_iter'.
    reflected : list of int
        Iterations after which roots of B were reflected (SPEC §5: tag the run).
    """

    model: RationalFeedforward
    best: int
    iterates: list[SKIterate]
    converged: bool
    message: str
    reflected: list[int] = field(default_factory=list)

    @property
    def J_OE(self) -> list[float]:
        """J_OE per iterate ([K] (7)), j = 0 … last."""
        return [it.J_OE for it in self.iterates]

    @property
    def seconds_per_iter(self) -> float:
        """Mean wall time of the SK steps j ≥ 1 [s]."""
        t = [it.seconds for it in self.iterates[1:]]
        return float(np.mean(t)) if t else 0.0


# ----------------------------------------------------------------------------- helpers
def prepare_data(model: RationalFeedforward, r, f_hat) -> dict:
    """Concatenate the references and optimal inputs and build everything SK needs once:
    the model inputs, f̂ and M = [R, −F̂] ([K] (14))."""
    r_cat, seg = Segments.concat(r, "reference")
    f_cat, seg_f = Segments.concat(f_hat, "optimal input f̂")
    if seg_f != seg:
        raise ValueError(f"references and optimal inputs have different lengths {seg.lengths} vs "
                         f"{seg_f.lengths}; pair every reference with its own f̂")
    inp = model.inputs(r_cat, seg)
    M = np.hstack([inp["R"], -model.ar_regressors(f_cat, seg)])
    names = [f"a{i + 1}" for i in range(model.n_a)] + [f"b{i + 1}" for i in range(model.n_b)]
    return {"inputs": inp, "segments": seg, "f": f_cat, "M": M, "names": names}


def _has_approximator(model) -> bool:
    return hasattr(model, "g_and_jacobian")


def oe_cost(model: RationalFeedforward, data: dict) -> float:
    """J_OE = ‖f̂ − F_θ,φ(r)‖² ([K] (7)) [N²]; inf when B is unstable."""
    if not model.is_stable():
        return math.inf
    with torch.no_grad():
        f = model.simulate(data["inputs"]).numpy()
    e = data["f"] - f
    c = float(e @ e)
    return c if math.isfinite(c) else math.inf


def _snapshot(model) -> tuple:
    phi = model.phi.numpy().copy() if _has_approximator(model) else None
    gain = float(model.g_gain) if _has_approximator(model) else 1.0
    return model.theta.copy(), phi, gain


def _restore(model, theta, phi, gain) -> None:
    model.set_theta(theta)
    if phi is not None:
        model.set_phi(torch.from_numpy(phi.copy()))
        with torch.no_grad():
            model.g_gain.fill_(gain)


# ----------------------------------------------------------------------------- SK step
def _varpro_step(model, data: dict, sub: ModelSubspace, Wf: np.ndarray, den: np.ndarray,
                 lam: float, lm_kw: dict) -> tuple[torch.Tensor, LMResult]:
    """φ^j of [K] (30) with θ eliminated (variable projection), by LM with exact Jacobian."""
    seg, inp = data["segments"], data["inputs"]
    U1 = sub.U1
    Wf_perp = sub.project_out(Wf)
    sq = math.sqrt(lam)

    def residual(phi: torch.Tensor) -> torch.Tensor:
        Wg = filter_segments(model.g_value(inp, phi).numpy(), [1.0], den, seg)
        res = Wf_perp - sub.project_out(Wg)                    # (I − U1U1ᵀ) W (f̂ − g)
        if lam > 0:   # [K] (23): extra rows √λ (ΣVᵀ)^{-1} U1ᵀ W g_φ
            res = np.concatenate([res, sq * sub.coordinates(Wg)])
        return torch.from_numpy(res)

    def jacobian(phi: torch.Tensor) -> torch.Tensor:
        _, Jg = model.g_and_jacobian(inp, phi)
        WJ = filter_segments(Jg.numpy(), [1.0], den, seg)     # W ∂g/∂φ, column by column
        C = U1.T @ WJ                                         # U1ᵀ W ∂g/∂φ  [p, n_φ]
        J = U1 @ C - WJ                                       # −(I − U1U1ᵀ) W ∂g/∂φ
        # a φ_i that moves g only inside im(W M) is flat in the reduced cost (θ absorbs it,
        # [K] Corollary 14); its projected column is rounding noise, which LM's scale-
        # invariant damping would turn into a huge step: make it exactly zero
        flat = np.linalg.norm(J, axis=0) <= _FLAT_RTOL * np.linalg.norm(WJ, axis=0)
        if np.any(flat):
            J[:, flat] = 0.0
        if lam > 0:
            J = np.vstack([J, sq * sub.coordinates(C, projected=True)])
        return torch.from_numpy(J)

    res = levenberg_marquardt(residual, model.phi, jacobian=jacobian, **lm_kw)
    return res.theta, res


def sk_iterations(model: RationalFeedforward, r, f_hat, *, max_iter: int = 20, tol: float = 1e-8,
                  regularizer: str = "orthogonal", lam: float = 1.0, column_scale: bool = True,
                  init: str = "equation_error", lm_max_iter: int = 100, lm_ftol: float = 1e-10,
                  lm_gtol: float = 1e-10, rank_rtol: float | None = None,
                  weighted_rank: str = "truncate",
                  callback: Callable[[SKIterate], None] | None = None) -> SKResult:
    """Identify a [K] feedforward by SK iterations ([K] Alg. 5; Alg. 19 with the regulariser).

    Parameters
    ----------
    model : RationalFeedforward or SharedARPGNN
        Model structure and initial φ (copied; the input is not modified).
    r, f_hat : array or list of arrays
        Training references [m] and their optimal inputs f̂ [N] (one array per reference).
    max_iter : int
        Maximum number of SK iterations (the run stops there with a warning).
    tol : float
        Stop when the relative parameter change (column-scaled θ and φ) is below ``tol``.
    regularizer : {'orthogonal', 'none'}
        Orthogonal projection-based regulariser [K] (29) or none ([K] Alg. 5).  Ignored for
        the rational model (no approximator).
    lam : float
        λ of [K] (30) (dimensionless: R is in column-scaled coefficients, units N²).
    column_scale : bool
        Scale the columns of W M to unit norm before least squares / SVD (SPEC §5).
    init : {'equation_error', 'model'}
        θ^0 from the equation-error linear fit (B^0 = 1, [K]) or the model's current θ.
    lm_max_iter, lm_ftol, lm_gtol : int, float, float
        LM settings of each PGNN step (:func:`pipeline.identify.lm.levenberg_marquardt`).
    rank_rtol : float, optional
        Rank tolerance of [K] Assumption 10 (see :func:`model_subspace`).
    weighted_rank : {'truncate', 'raise'}
        Policy when the *weighted* W^{j-1} M (j ≥ 1) is numerically rank deficient although
        M itself is not (overparametrised rational models: weighting by 1/B smooths the
        columns): minimum-norm solution over the kept directions (reported per iterate in
        ``n_truncated``) or raise.  M itself (j = 0) must always have full rank.
    callback : callable, optional
        Called with every :class:`SKIterate` (e.g. to log J_OE per iteration).

    Returns
    -------
    SKResult

    Raises
    ------
    RankDeficientModelError
        If W M is rank deficient at some iteration.
    """
    if regularizer not in REGULARIZERS:
        raise ValueError(f"unknown regularizer '{regularizer}'; choose one of {REGULARIZERS}")
    if init not in ("equation_error", "model"):
        raise ValueError(f"unknown init '{init}'; choose 'equation_error' or 'model'")
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if lam < 0:
        raise ValueError(f"λ must be >= 0, got {lam}")
    model = copy.deepcopy(model)
    has_g = _has_approximator(model)
    lam_eff = lam if (has_g and regularizer == "orthogonal") else 0.0
    data = prepare_data(model, r, f_hat)
    seg, M, f = data["segments"], data["M"], data["f"]
    lm_kw = dict(max_iter=lm_max_iter, ftol=lm_ftol, gtol=lm_gtol)

    # j = 0: best linear approximation by equation error, B^0 = 1 ([K] Alg. 5, Remark 7)
    t0 = time.perf_counter()
    sub0 = model_subspace(M, column_scale=column_scale, rtol=rank_rtol, names=data["names"])
    if init == "equation_error":                                   # [K] Assumption 10 on M
        model.set_theta(sub0.solve(f))
    n_ref = model.reflect_unstable()
    snap = _snapshot(model)
    iterates = [SKIterate(j=0, theta=snap[0], phi=snap[1], g_gain=snap[2], J_OE=oe_cost(model, data),
                          n_reflected=n_ref, seconds=time.perf_counter() - t0)]
    reflected = [0] if n_ref else []
    if callback is not None:
        callback(iterates[0])

    converged, message = False, "max_iter"
    for j in range(1, int(max_iter) + 1):
        t0 = time.perf_counter()
        den = model.denominator()                                  # B^{j-1}(q)
        WM = filter_segments(M, [1.0], den, seg)                   # [K] (27), as a filter
        Wf = filter_segments(f, [1.0], den, seg)
        sub = model_subspace(WM, column_scale=column_scale, rtol=rank_rtol, names=data["names"],
                             rank_deficient=weighted_rank)
        lm_iter, lm_msg, reg = 0, "closed form", 0.0
        if has_g:
            phi, lmres = _varpro_step(model, data, sub, Wf, den, lam_eff, lm_kw)
            model.set_phi(phi)
            with torch.no_grad():
                g = model.exogenous_extra(data["inputs"]).numpy()
            Wg = filter_segments(g, [1.0], den, seg)
            theta = sub.solve(Wf - Wg)                             # θ(φ) = (WM)^+ W (f̂ − g)
            reg = float(orthogonal_regularizer(sub, Wg))
            lm_iter, lm_msg = lmres.n_iter, lmres.message
        else:
            Wg = 0.0
            theta = sub.solve(Wf)                                  # closed-form LS
        model.set_theta(theta)
        e_w = Wf - WM @ theta - Wg
        J_w = float(e_w @ e_w) + lam_eff * reg
        n_ref = model.reflect_unstable()                           # SPEC §5
        if n_ref:
            reflected.append(j)
        snap = _snapshot(model)
        prev = iterates[-1]
        d_theta = (snap[0] - prev.theta) / sub.scale
        change = float(np.linalg.norm(d_theta) / max(np.linalg.norm(snap[0] / sub.scale), 1e-300))
        if has_g:
            change = max(change, float(np.linalg.norm(snap[1] - prev.phi)
                                       / max(np.linalg.norm(snap[1]), 1e-300)))
        it = SKIterate(j=j, theta=snap[0], phi=snap[1], g_gain=snap[2], J_OE=oe_cost(model, data),
                       J_weighted=J_w, regularizer=reg, change=change, n_reflected=n_ref,
                       condition=sub.condition, n_truncated=sub.n_truncated, lm_iter=lm_iter,
                       lm_message=lm_msg,
                       seconds=time.perf_counter() - t0)
        iterates.append(it)
        if callback is not None:
            callback(it)
        if change < tol:
            converged, message = True, "tol"
            break

    if not converged:
        warnings.warn(f"SK iterations did not converge in {max_iter} iterations (last relative "
                      f"parameter change {iterates[-1].change:.2e} > tol {tol:.1e}); returning the "
                      "best iterate by J_OE. Raise max_iter or tol if this is expected.",
                      SKNotConvergedWarning, stacklevel=2)
    J = np.array([it.J_OE for it in iterates])
    best = int(np.argmin(J)) if np.any(np.isfinite(J)) else len(iterates) - 1
    b = iterates[best]
    _restore(model, b.theta, b.phi, b.g_gain)
    return SKResult(model=model, best=best, iterates=iterates, converged=converged,
                    message=message, reflected=reflected)


def _sk_restart(job: tuple) -> tuple[SKResult, float, bool]:
    """One SK run for :func:`sk_restarts` (module level: picklable for a process pool)."""
    model, r, f_hat, kw = job
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SKNotConvergedWarning)
        res = sk_iterations(model, r, f_hat, **kw)
    warned = any(issubclass(w.category, SKNotConvergedWarning) for w in caught)
    return res, time.perf_counter() - t0, warned


def sk_restarts(models, r, f_hat, *, n_jobs: int = 1, **kw) -> list[tuple[SKResult, float, bool]]:
    """:func:`sk_iterations` from several initial models (random restarts, SPEC §5).

    Parameters
    ----------
    models : sequence of RationalFeedforward
        One initial model per restart (e.g. g_φ initialised from different seeds).
    r, f_hat
        Training data, as :func:`sk_iterations`.
    n_jobs : int
        Worker processes (``spawn`` context: each imports only this module's dependencies);
        1 runs the restarts in this process.
    **kw
        Passed to :func:`sk_iterations`.

    Returns
    -------
    list of (SKResult, seconds, not_converged)
        In the order of ``models``; ``not_converged`` is True when the run stopped at
        ``max_iter`` (its :class:`SKNotConvergedWarning` is captured, not re-raised).
    """
    jobs = [(m, r, f_hat, kw) for m in models]
    if int(n_jobs) <= 1 or len(jobs) == 1:
        return [_sk_restart(j) for j in jobs]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    ctx = multiprocessing.get_context("spawn")    # never fork a process that holds torch threads
    with ProcessPoolExecutor(max_workers=min(int(n_jobs), len(jobs)), mp_context=ctx) as pool:
        return list(pool.map(_sk_restart, jobs))


# ----------------------------------------------------------------------------- direct OE
@dataclass
class OEResult:
    """Outcome of :func:`output_error_lm`: the refined model and J_OE before/after [N²]."""

    model: RationalFeedforward
    J_before: float
    J_after: float
    lm: LMResult

    @property
    def improvement(self) -> float:
        """Relative decrease of J_OE, (J_before − J_after)/J_before."""
        return (self.J_before - self.J_after) / self.J_before if self.J_before > 0 else 0.0


def output_error_problem(model: RationalFeedforward, data: dict):
    """Residual and exact Jacobian of J_OE ([K] (7)) over x = col(a, b, φ).

    With f = (R a + g)/B and e = f̂ − f: ∂e/∂a = −R/B, ∂e/∂b_i = ψ_i(f)/B,
    ∂e/∂φ = −(∂g/∂φ)/B, all computed by filtering.  The residual is +inf when B is
    unstable (LM then rejects the step).

    Returns
    -------
    residual, jacobian : callable
        ``residual(x) -> e`` [N], ``jacobian(x) -> ∂e/∂x`` [N, n_x] (torch float64).
    x0 : torch.Tensor
        The model's current x.
    """
    seg, inp, f_hat_c = data["segments"], data["inputs"], data["f"]
    R = inp["R"]
    has_g = _has_approximator(model)
    n_th = model.n_a + model.n_b

    def split(x: torch.Tensor):
        xn = x.detach().numpy()
        trial = RationalFeedforward(model.n_a, model.n_b, model.basis, model.Ts, b=xn[model.n_a:n_th])
        u = R @ xn[:model.n_a]
        if has_g:
            u = u + model.g_value(inp, x[n_th:]).numpy()
        return trial, u

    def residual(x: torch.Tensor) -> torch.Tensor:
        trial, u = split(x)
        if not trial.is_stable():
            return torch.full((seg.n,), math.inf, dtype=torch.float64)
        return torch.from_numpy(f_hat_c - filter_segments(u, [1.0], trial.denominator(), seg))

    def jacobian(x: torch.Tensor) -> torch.Tensor:
        trial, u = split(x)
        den = trial.denominator()
        fsim = filter_segments(u, [1.0], den, seg)
        cols = [-R, trial.ar_regressors(fsim, seg)]
        if has_g:
            cols.append(-model.g_and_jacobian(inp, x[n_th:])[1].numpy())
        return torch.from_numpy(np.ascontiguousarray(filter_segments(np.hstack(cols), [1.0], den, seg)))

    x0 = [torch.from_numpy(model.theta)]
    if has_g:
        x0.append(model.phi)
    return residual, jacobian, torch.cat(x0)


def output_error_lm(model: RationalFeedforward, r, f_hat, *, max_iter: int = 50,
                    ftol: float = 1e-12, gtol: float = 1e-12) -> OEResult:
    """Minimise J_OE ([K] (7)) directly by LM over (a, b, φ), starting from ``model``.

    Exact Jacobian by filtering (:func:`output_error_problem`); steps that make B unstable
    are rejected, so the result stays stable.  Used to check that SK reached the
    output-error optimum (SPEC §8 K3).  The input model is not modified.
    """
    model = copy.deepcopy(model)
    model.check_stable()
    data = prepare_data(model, r, f_hat)
    residual, jacobian, x0 = output_error_problem(model, data)
    J_before = oe_cost(model, data)
    res = levenberg_marquardt(residual, x0, jacobian=jacobian, max_iter=max_iter, ftol=ftol, gtol=gtol)
    n_th = model.n_a + model.n_b
    model.set_theta(res.theta[:n_th].numpy())
    if _has_approximator(model):
        model.set_phi(res.theta[n_th:])
    return OEResult(model=model, J_before=J_before, J_after=oe_cost(model, data), lm=res)
