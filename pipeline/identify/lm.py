"""Levenberg–Marquardt for nonlinear least squares, shared by every identification criterion.

Minimises ``C(θ) = ||r(θ)||²`` (squared 2-norm, SPEC §0) for a residual ``r: R^p -> R^n``
given as a torch function.  The LM step solves the damped normal equations

    (JᵀJ + μ D) δ = -Jᵀ r,      D = diag(max over iterations of diag(JᵀJ))      (Marquardt/Moré)

in the scaled variables ``θ̃ = D^{1/2} θ`` (unit-diagonal p×p system, Cholesky), which is much
cheaper than a QR of the tall Jacobian when n >> p (120,000 × 100 in [B1] §VI) and, thanks
to the scaling, well behaved for columns of very different magnitude.  μ follows Nielsen's
gain-ratio rule (H. B. Nielsen, "Damping parameter in Marquardt's method", IMM-REP-1999-05).

Geodesic acceleration (``geodesic=True``; Transtrum & Sethna, "Improvements to the
Levenberg-Marquardt algorithm for nonlinear least-squares minimization", arXiv:1201.5885, §3):
the damped step δv is the first-order term of a geodesic on the model manifold; the second-order
term ``a = -(JᵀJ + μD)⁻¹ Jᵀ r_vv`` with the directional second derivative

    r_vv ≈ (2/h) [ (r(θ + h δv) - r(θ)) / h - J δv ]                    (Transtrum (20))

(one extra residual evaluation, the Cholesky factor reused) gives the step ``δ = δv + a/2``,
taken only when ``2‖a‖/‖δv‖ ≤ α`` (scaled norms, Transtrum (23)); otherwise the step is
rejected and μ raised.  Where steps are limited by curvature rather than by damping (μ small,
few rejections: the closed-loop simulation error of [B2]) this cuts the number of Jacobians
several-fold.  It needs ``J δv`` and ``Jᵀ w``: from the dense J, or from ``jacobian.jvp(θ, v)``
and ``jacobian.vjp(θ, w)`` where the Jacobian is given as normal equations only.

Stopping (``LMResult.message``):

- ``'ftol'``: an accepted step changed the cost by at most ``ftol · C`` (relative change);
- ``'stat'``: the statistical stop (``stat_window`` W > 0): the cost fell by at most
  ``stat_tol · sqrt(2/N) · C`` over the last W accepted steps.  For a residual of N independent
  noise samples C ≈ Nσ², whose sampling standard deviation is sqrt(2N)σ² = sqrt(2/N)·C: a decrease
  below a fraction of it is not resolved by the data (N = ``n_data``, default the residual length).
  A slow crawl can meet that for W steps and still have far to go (issue 19: the [B1] direct
  inverse stopped 3 % above its minimum, 6x the sampling fluctuation), so the rule also asks the
  local model: the Gauss–Newton decrement ``gᵀ(JᵀJ + εD)⁻¹g`` (the decrease a full Gauss–Newton
  step promises, ε = ``DECREMENT_EPS`` of the largest scaled curvature: directions the data do
  not determine to that level are left out) must be below the same threshold.  Both together:
  the cost has stopped falling *and* no step along a direction determined to that level would lower
  it further.  Along a direction of scaled curvature λ < ε the remaining decrease g²/λ is counted as
  g²/ε, i.e. underestimated by λ/ε (a linear problem with a 1e-12 direction offset from its minimum
  stops 14 % above it: ``tests/test_lm.py``); so ``make reproduce-check CHECK=tighten`` divides ε by
  its factor too, and a fit whose values move then is named there.
  With ``stat_frac`` > 0 the window is the last ``stat_frac`` of the accepted steps (at least W):
  a crawl whose decrease per step shrinks like a power of k (the [B2] closed-loop fits: n1 = 32
  goes from 6x to 1.0x the noise floor between steps 250 and 1500) then stops only when the last
  30 % of the run together gained less than that, within ~1 % of its final cost (measured on
  n1 = 8, 16, 20, 32; a fixed W = 10 stopped n1 = 32 at 10x its final cost, 6.4e-9 after 302 solves).
  The full Gauss–Newton promise holds where the crawl is curvature-limited (μ stays near 1e-8 to
  1e-7 of the largest curvature: the [B1], [B2] studies). Where the gain ratio keeps μ near the
  largest curvature the quadratic model holds only inside that damped region, and its full promise
  does not come true (measured on the EMPS recorded loop, n1 = 16, λ = 0.1: μ ≈ 0.05-4, the full
  decrement promises 6-7x the threshold for 2600 steps, which gain 0.7 % of C, below the
  threshold). ``stat_promise='damped'`` then regularises the decrement by μ as well, gᵀ(JᵀJ + μD)⁻¹g:
  a lower bound (between 1/2 and 1) of the decrease the damped step itself promises, where the gain
  ratio trusts the model (the measured fits' default, ``identify.stat_promise``);
- ``'gtol'``: the scaled gradient ``max_i |J_iᵀ r| / (||J_i|| ||r||)`` (cosine between each
  Jacobian column and the residual, as in MINPACK/scipy) is at most ``gtol``;
- ``'zero_cost'``: the cost is exactly zero;
- ``'mu_max'``: no decrease possible even with a very large damping (the step is at the
  rounding level, θ is a minimiser to working precision);
- ``'max_iter'``: ``max_iter`` damped systems were solved (accepted or not);
- ``'nonfinite_jacobian'``: the Jacobian (JᵀJ or Jᵀr) at the current θ holds NaN/inf (e.g. ∂√|θ|/∂θ at 0);
  not converged, θ is the last finite iterate;
- ``'early_stop'``: the validation cost did not improve for ``patience`` accepted steps;
  θ is the best-validation iterate;
- ``'callback'``: the callback returned ``True``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from scipy.linalg.blas import dsyrk as _dsyrk

__all__ = ["CONVERGED", "LMResult", "levenberg_marquardt", "autodiff_jacobian", "normal_equations_from_blocks"]

_MU_MAX = 1e20
#: ε of the Gauss–Newton decrement in the statistical stop, relative to the largest diagonal entry
#: of the scaled JᵀJ (which is 1): curvatures below 1e-8 of it are treated as undetermined (float64
#: solves of a system conditioned at 1e8 keep ~8 digits; measured on [B1]: 1e-12 stops the
#: sigma=0 direct inverse at 800 instead of 500 accepted steps for a cost lower by 0.13 %)
DECREMENT_EPS = 1e-8
#: relative size of the rounding-level perturbation of every JᵀJ and Jᵀr (0: off); set from the
#: environment variable PIPELINE_PERTURB by ``make reproduce-check`` to emulate a second machine
#: (another BLAS summation order perturbs the normal equations at the last bits, at every step)
_PERTURB = float(os.environ.get("PIPELINE_PERTURB", "0") or 0)


#: factor by which every LM tolerance (ftol, gtol, stat_tol, DECREMENT_EPS; SK's tol too) is divided (1: off);
#: set from PIPELINE_TIGHTEN by ``make reproduce-check CHECK=tighten``: a converged fit's reported
#: values must not move when its tolerances are tightened (issue 19)
TIGHTEN = float(os.environ.get("PIPELINE_TIGHTEN", "1") or 1)
#: factor on the safety caps of the fits' restarts (``best_of_restarts``' ``max_iter``, not a screening
#: budget; 1: off); set from PIPELINE_CAP_FACTOR by ``make reproduce-check CHECK=tighten``: a fit that
#: stopped on its cap runs that much longer, so the check shows how far its values still had to go
CAP_FACTOR = float(os.environ.get("PIPELINE_CAP_FACTOR", "1") or 1)


def _perturb_normal_equations(A: torch.Tensor, g: torch.Tensor, k: int):
    """A and g times (1 + _PERTURB·u), u uniform in [-1, 1], symmetric, seeded by the step k."""
    gen = np.random.default_rng([k, A.shape[0]])
    U = gen.uniform(-1.0, 1.0, A.shape)
    U = torch.from_numpy((U + U.T) / 2.0)
    return A * (1.0 + _PERTURB * U), g * (1.0 + _PERTURB * torch.from_numpy(gen.uniform(-1.0, 1.0, g.shape)))


@dataclass
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes
    ----------
    theta : torch.Tensor
        Best parameters found (float64, 1-D): the last accepted iterate, or the
        best-validation iterate when early stopping was enabled.
    cost : float
        ``||r(theta)||²`` at ``theta`` (units of the residual, squared).
    history : list of float
        Training cost after every accepted iteration; ``history[0]`` is the initial cost.
    n_iter : int
        Number of damped linear systems solved (accepted plus rejected steps).
    converged : bool
        True when stopped by ``ftol``, ``stat``, ``gtol``, ``zero_cost``, ``mu_max`` or
        ``early_stop``.
    message : str
        Why it stopped (see the module docstring).
    val_history : list of float
        Validation cost at ``history``'s iterates (empty without ``val_cost``).
    val_cost : float or None
        Validation cost at ``theta`` (None without ``val_cost``).
    """

    theta: torch.Tensor
    cost: float
    history: list[float]
    n_iter: int
    converged: bool
    message: str
    val_history: list[float] = field(default_factory=list)
    val_cost: float | None = None
    n_jac: int = 0              # Jacobians (or normal equations) evaluated
    n_accel: int = 0            # accepted steps that carried a geodesic acceleration


CONVERGED = ("ftol", "stat", "gtol", "zero_cost", "mu_max", "early_stop")


def autodiff_jacobian(residual: Callable[[torch.Tensor], torch.Tensor], theta: torch.Tensor,
                      n_res: int | None = None) -> torch.Tensor:
    """Exact Jacobian ``∂r/∂θ`` [n_res, n_par] by torch.func, forward mode for tall shapes.

    Forward mode costs one JVP per parameter, reverse mode one VJP per residual, so
    ``jacfwd`` is used when ``n_res >= n_par`` and ``jacrev`` otherwise.
    """
    if n_res is None:
        n_res = residual(theta).numel()
    if n_res >= theta.numel():
        return torch.func.jacfwd(residual)(theta)
    return torch.func.jacrev(residual)(theta)


def _gram(J: torch.Tensor) -> torch.Tensor:
    """JᵀJ; numpy's ``a.T @ a`` uses the symmetric rank-k BLAS kernel (half the flops)."""
    if J.device.type == "cpu" and not J.requires_grad:
        Jn = J.contiguous().numpy()
        return torch.from_numpy(Jn.T @ Jn)
    return J.T @ J


def normal_equations_from_blocks(blocks, r: torch.Tensor, n_par: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(JᵀJ, Jᵀr) summed over row blocks ``(a, J[a:a+k])`` of J (contiguous float64 tensors,
    covering the rows of ``r`` once): BLAS syrk (half the flops of a gemm) and gemv on each block
    while it is in cache, so J is never stored whole.  The sums run block by block, so they differ
    from an unblocked JᵀJ in the last bits only."""
    A = np.zeros((n_par, n_par), order="F")
    g = np.zeros(n_par)
    rn = r.numpy()
    for a, J in blocks:
        Jt = J.numpy().T  # [n_par, k] Fortran-ordered: syrk 'N' computes Jt Jtᵀ = JᵀJ
        A = _dsyrk(1.0, Jt, beta=1.0, c=A, trans=0, lower=1, overwrite_c=1)
        g += Jt @ rn[a:a + Jt.shape[1]]
    A = np.tril(A) + np.tril(A, -1).T
    return torch.from_numpy(A), torch.from_numpy(g)


def _check_vector(name: str, x) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x, dtype=torch.float64)
    if x.dtype != torch.float64:
        raise TypeError(f"{name} must be float64 (SPEC §0), got {x.dtype}; convert with .double()")
    if x.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {tuple(x.shape)}; flatten it")
    if not torch.all(torch.isfinite(x)):
        raise ValueError(f"{name} contains NaN/inf; check the model or the initial parameters")
    return x


def levenberg_marquardt(residual: Callable[[torch.Tensor], torch.Tensor], theta0: torch.Tensor, *,
                        jacobian: Callable[[torch.Tensor], torch.Tensor] | None = None,
                        max_iter: int = 100, ftol: float = 1e-12, gtol: float = 1e-12,
                        mu0: float = 1e-3, val_cost: Callable[[torch.Tensor], float] | None = None,
                        patience: int = 5,
                        callback: Callable[[int, torch.Tensor, float], bool | None] | None = None,
                        geodesic: bool = False, geodesic_h: float = 0.1, geodesic_alpha: float = 0.75,
                        stat_window: int = 0, stat_tol: float = 0.1, stat_frac: float = 0.0,
                        n_data: int | None = None, stat_history: list[float] | None = None,
                        stat_promise: str = "gauss_newton") -> LMResult:
    """Minimise ``||residual(θ)||²`` by Levenberg–Marquardt.

    Parameters
    ----------
    residual : callable
        ``residual(θ) -> r`` (1-D float64 tensor, n_res entries).
    theta0 : torch.Tensor
        Initial parameters (1-D float64, n_par entries); not modified.
    jacobian : callable, optional
        ``jacobian(θ) -> J`` [n_res, n_par], exact ``∂r/∂θ``.  If None, computed with
        ``torch.func.jacfwd`` (tall J) or ``jacrev`` (wide J).  If it has an attribute
        ``normal_equations(θ, r) -> (JᵀJ, Jᵀr)``, that is used instead of forming J (e.g.
        :func:`normal_equations_from_blocks` over row blocks of a tall J).
    max_iter : int
        Maximum number of damped systems solved (accepted plus rejected steps).
    ftol : float
        Stop when an accepted step lowers the cost by at most ``ftol`` times the cost.
    gtol : float
        Stop when ``max_i |J_iᵀ r| / (||J_i|| ||r||) <= gtol``.
    mu0 : float
        Initial damping relative to the (unit) diagonal of the scaled ``JᵀJ``.
    val_cost : callable, optional
        ``val_cost(θ) -> float``; enables early stopping: the best-validation iterate is
        kept and the run stops after ``patience`` accepted steps without improvement.
    patience : int
        See ``val_cost``.
    callback : callable, optional
        ``callback(it, θ, cost)`` after every accepted step; returning True stops the run.
    geodesic : bool
        Add the geodesic acceleration (module docstring) to every damped step.
    geodesic_h : float
        Finite-difference step of r_vv, relative to δv (Transtrum: 0.1).
    geodesic_alpha : float
        Largest accepted ``2‖a‖/‖δv‖`` (Transtrum: 0.75).
    stat_window : int
        Accepted steps W of the statistical stop (0: off).
    stat_tol : float
        Fraction of the cost's sampling standard deviation sqrt(2/N)·C below which a decrease
        over W accepted steps counts as converged.
    stat_frac : float
        The window grows with the run: W_k = max(stat_window, ⌈stat_frac·k⌉) after k accepted
        steps (0: a fixed window).  On a slow crawl the decrease over a fixed W steps says little
        about the decrease still to come; over the last fraction of the run it does (module
        docstring).
    stat_history : list of float, optional
        Costs of the accepted steps of an earlier run that ended at ``theta0`` (a restart continued
        after screening): the statistical window counts them as this run's first steps.
    n_data : int, optional
        N of the statistical stop: the number of noisy samples in the residual (default: its
        length).
    stat_promise : {'gauss_newton', 'damped'}
        The local model's promise the statistical stop also asks for: ``gauss_newton``, the full
        Gauss–Newton decrement (curvatures above ``DECREMENT_EPS`` count); ``damped``, the decrement
        regularised by the current damping μ as well, i.e. what the model promises inside the region
        where the gain ratio has found it to hold (module docstring).

    Returns
    -------
    LMResult
    """
    theta = _check_vector("theta0", theta0).detach().clone()
    ftol, gtol, stat_tol = ftol / TIGHTEN, gtol / TIGHTEN, stat_tol / TIGHTEN
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
    if patience < 1:
        raise ValueError(f"patience must be >= 1, got {patience}")
    if stat_promise not in ("gauss_newton", "damped"):
        raise ValueError(f"stat_promise must be 'gauss_newton' or 'damped', got {stat_promise!r}")
    if stat_window < 0 or not stat_tol >= 0 or not 0.0 <= stat_frac < 1.0:
        raise ValueError(f"stat_window must be >= 0, stat_tol >= 0 and 0 <= stat_frac < 1, got {stat_window}, "
                         f"{stat_tol}, {stat_frac}")
    if geodesic and not (geodesic_h > 0 and geodesic_alpha > 0):
        raise ValueError(f"geodesic_h and geodesic_alpha must be > 0, got {geodesic_h}, {geodesic_alpha}")

    def eval_res(th: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            r = residual(th)
        if r.dtype != torch.float64 or r.ndim != 1:
            raise TypeError(f"residual must return a 1-D float64 tensor, got {r.dtype} "
                            f"with shape {tuple(r.shape)}")
        return r.detach()

    def eval_jac(th: torch.Tensor, n_res: int) -> torch.Tensor:
        if jacobian is None:
            J = autodiff_jacobian(residual, th, n_res)
        else:
            with torch.no_grad():
                J = jacobian(th)
        J = J.detach()
        if J.shape != (n_res, th.numel()):
            raise ValueError(f"jacobian returned shape {tuple(J.shape)}, expected "
                             f"({n_res}, {th.numel()}) = (n_residuals, n_parameters)")
        return J

    r = eval_res(theta)
    if not torch.all(torch.isfinite(r)):
        raise ValueError("residual(theta0) contains NaN/inf; choose a different initial point")
    cost = float(r @ r)
    history = [cost]
    val_history: list[float] = []
    best_val, best_val_theta, best_val_cost, since_best = math.inf, theta, cost, 0
    if val_cost is not None:
        best_val = float(val_cost(theta))
        val_history.append(best_val)

    n_par = theta.numel()
    d_max = torch.zeros(n_par, dtype=torch.float64)
    mu, nu = None, 2.0
    message, n_iter = "max_iter", 0
    need_jac = True
    eye = torch.eye(n_par, dtype=torch.float64)
    normal = getattr(jacobian, "normal_equations", None)
    if geodesic and normal is not None and not (hasattr(jacobian, "jvp") and hasattr(jacobian, "vjp")):
        raise ValueError("geodesic acceleration needs J δv and Jᵀw: give jacobian.jvp(θ, v) and "
                         "jacobian.vjp(θ, w) beside jacobian.normal_equations, or set geodesic=False")
    n_stat = int(n_data) if n_data is not None else r.numel()
    past = [float(c) for c in (stat_history or [])]
    stat_scale = stat_tol * math.sqrt(2.0 / max(n_stat, 1))
    n_jac = n_accel = 0
    J = None
    stat_pending, decrement = False, math.nan

    while True:
        if cost == 0.0:
            message = "zero_cost"
            break
        if need_jac:
            n_jac += 1
            if normal is not None:
                A, g = normal(theta, r)
                if A.shape != (n_par, n_par) or g.shape != (n_par,):
                    raise ValueError(f"jacobian.normal_equations returned shapes {tuple(A.shape)}, "
                                     f"{tuple(g.shape)}; expected ({n_par}, {n_par}) and ({n_par},)")
            else:
                J = eval_jac(theta, r.numel())
                A = _gram(J)
                g = J.T @ r
            if not (bool(torch.all(torch.isfinite(A))) and bool(torch.all(torch.isfinite(g)))):
                message = "nonfinite_jacobian"    # not a stationary point: NaN columns would pass the gtol test
                break
            if _PERTURB:            # emulate another machine's rounding (pipeline/perturbation.py)
                A, g = _perturb_normal_equations(A, g, n_jac)
            diag = torch.diagonal(A).clone()
            # gradient test, scale-free (cosine of each column with the residual)
            col = torch.sqrt(diag)
            cosine = torch.where(col > 0, g.abs() / (col * math.sqrt(cost)), torch.zeros_like(g))
            if float(cosine.max()) <= gtol:
                message = "gtol"
                break
            d_max = torch.maximum(d_max, diag)  # Moré's scaling: running max of diag(JᵀJ)
            d = torch.where(d_max > 0, d_max, torch.ones_like(d_max))
            s = 1.0 / torch.sqrt(d)
            A_s = A * s[:, None] * s[None, :]
            g_s = g * s
            if mu is None:
                mu = mu0 * float(torch.diagonal(A_s).max())
                if mu <= 0:
                    mu = mu0
            need_jac = False
            if stat_pending:   # the window test held at the last step: does the local model agree?
                decrement = _gauss_newton_decrement(A_s, g_s, eye, mu if stat_promise == "damped" else 0.0)
                if decrement <= stat_scale * cost:
                    message = "stat"
                    break
                stat_pending = False
        if n_iter >= max_iter:
            message = "max_iter"
            break
        n_iter += 1
        # damped scaled normal equations (A_s + μ I) δ̃ = -g_s, Cholesky; raise μ if not PD
        while True:
            L, info = torch.linalg.cholesky_ex(A_s + mu * eye)
            if int(info) == 0:
                break
            mu *= 10.0
            if mu > _MU_MAX:
                break
        if mu > _MU_MAX:
            message = "mu_max"
            break
        step_s = -torch.cholesky_solve(g_s[:, None], L)[:, 0]
        accel, v_s = False, step_s
        if geodesic:
            step_s, accel = _geodesic_step(eval_res, jacobian, J, normal is not None, theta, r, step_s, s, L,
                                           geodesic_h, geodesic_alpha)
            if step_s is None:          # acceleration too large or not finite: reject, raise μ
                mu *= nu
                nu *= 2.0
                if mu > _MU_MAX:
                    message = "mu_max"
                    break
                continue
        step = step_s * s
        theta_new = theta + step
        r_new = eval_res(theta_new)
        finite = bool(torch.all(torch.isfinite(r_new)))
        cost_new = float(r_new @ r_new) if finite else math.inf
        # actual decrease as (r - r_new)ᵀ(r + r_new): free of the cancellation in
        # cost - cost_new, so steps below the cost's rounding level are still judged right
        decrease = float((r - r_new) @ (r + r_new)) if finite else -math.inf
        # predicted decrease of the Gauss–Newton model ||r + J δ||² at the velocity δv (with an
        # acceleration the full step leaves that quadratic model: its gain is judged on δv)
        pred = float(-(2.0 * (v_s @ g_s) + v_s @ (A_s @ v_s)))
        rho = decrease / pred if pred > 0 else -1.0
        if rho > 0 and decrease > 0:
            theta, r, cost_old, cost = theta_new, r_new, cost, cost_new
            history.append(cost)
            n_accel += accel
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)  # Nielsen
            nu = 2.0
            need_jac = True
            stop = False
            if val_cost is not None:
                v = float(val_cost(theta))
                val_history.append(v)
                if v < best_val:
                    best_val, best_val_theta, best_val_cost, since_best = v, theta, cost, 0
                else:
                    since_best += 1
                    if since_best >= patience:
                        message, stop = "early_stop", True
            if callback is not None and callback(len(history) - 1, theta, cost) is True:
                message, stop = "callback", True
            if stop:
                break
            if decrease <= ftol * cost_old:
                message = "ftol"
                break
            # statistical stop: the decrease over W accepted steps is below stat_tol of the
            # cost's sampling standard deviation sqrt(2/N)·C (module docstring)
            # (confirmed by the Gauss–Newton decrement at the new iterate, at the loop's top)
            n_seen = len(past) + len(history)       # the earlier run's costs count as this run's first
            window = max(stat_window, math.ceil(stat_frac * (n_seen - 1)))
            i = n_seen - 1 - window
            stat_pending = bool(stat_window and i >= 0 and
                                (past[i] if i < len(past) else history[i - len(past)]) - cost <= stat_scale * cost)
        else:
            mu *= nu
            nu *= 2.0
            if mu > _MU_MAX:
                message = "mu_max"
                break

    if val_cost is not None:
        theta, cost = best_val_theta, best_val_cost  # the best-validation iterate
        val_best = best_val
    else:
        val_best = None
    return LMResult(theta=theta.clone(), cost=cost, history=history, n_iter=n_iter,
                    converged=message in CONVERGED, message=message, val_history=val_history,
                    val_cost=val_best, n_jac=n_jac, n_accel=n_accel)


def _gauss_newton_decrement(A_s: torch.Tensor, g_s: torch.Tensor, eye: torch.Tensor, floor: float = 0.0) -> float:
    """``g̃ᵀ(Ã + εI)⁻¹g̃`` in the scaled variables, ε = max(DECREMENT_EPS·max diag Ã, ``floor``): with
    ``floor`` 0 the cost decrease a full (barely damped) Gauss–Newton step from here promises; with
    ``floor`` = the current μ (the damped promise) a lower bound, between 1/2 and 1, of what the damped
    step promises."""
    eps = max(DECREMENT_EPS / TIGHTEN * float(torch.diagonal(A_s).max()), float(floor))
    while True:
        L, info = torch.linalg.cholesky_ex(A_s + eps * eye)
        if int(info) == 0:
            return float(g_s @ torch.cholesky_solve(g_s[:, None], L)[:, 0])
        eps *= 10.0


def _geodesic_step(eval_res, jacobian, J, normal: bool, theta, r, v_s, s, L, h: float, alpha: float):
    """δv + a/2 in scaled variables (Transtrum & Sethna (20), (23)), or (None, False) when the
    acceleration is not finite or ``2‖a‖/‖δv‖ > alpha``.  ``L`` is the Cholesky factor of the
    damped scaled system, reused for the acceleration."""
    v = v_s * s
    r_h = eval_res(theta + h * v)
    if not bool(torch.all(torch.isfinite(r_h))):
        return None, False
    Jv = jacobian.jvp(theta, v) if normal else J @ v
    r_vv = (2.0 / h) * ((r_h - r) / h - Jv)                     # Transtrum (20)
    Jt_rvv = jacobian.vjp(theta, r_vv) if normal else J.T @ r_vv
    a_s = -torch.cholesky_solve((Jt_rvv * s)[:, None], L)[:, 0]
    nv = float(v_s.norm())
    if not nv > 0 or not bool(torch.all(torch.isfinite(a_s))) or 2.0 * float(a_s.norm()) > alpha * nv:
        return None, False                                    # Transtrum (23)
    return v_s + 0.5 * a_s, True
