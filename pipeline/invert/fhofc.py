"""Finite-horizon optimal feedforward control (FHOFC), IL-FHOFC and linear ILC of [B2].

FHOFC ([B2] (17), squared norms per SPEC §0):

    U_ff = argmin ‖R* - Φ̂(θ̂, x0, R, U_ff)‖² + ‖γ Δ U_ff‖²,   Δ = 1 on the diagonal, -1 below,
    subject to U_ff ∈ [lo, hi] and Û ∈ [lo_u, hi_u] (optional),

where Φ̂ is the closed-loop model simulation (:mod:`pipeline.models.closed_loop`) driven by
the reference R, and R* is the target (R itself, or R^(i+1) in IL-FHOFC).  Unconstrained
problems are solved by Gauss–Newton with Levenberg damping on the exact N_k × N_k Jacobian
(forward sensitivities, lower triangular); the step is a rank-revealing QR least-squares
solve of the stacked ``[J; γΔ]`` system, not the normal equations, because the lifted
matrix of the NMP loop has condition ~1e19 (SPEC §2.3).  With γ = 0 the attainable block
``J[d:, :N-d]`` (d = n_k + 1) is square lower triangular and the step is one triangular
solve.  Box bounds on U_ff use scipy's trust-region-reflective least squares, bounds on Û
scipy's SLSQP, both with the same exact Jacobians.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.linalg as sla

from pipeline.models.closed_loop import (
    ArxPGNN,
    DiscreteController,
    LoopState,
    as_arx,
    jacobian_uff,
    simulate_closed_loop,
)

__all__ = ["FHOFCResult", "ILResult", "difference_matrix", "fhofc", "fhofc_receding", "fhofc_windows", "il_fhofc",
           "il_fhofc_step", "linear_ilc", "check_validity", "inverse_model_feedforward", "lemma_5_1_gap",
           "lemma_5_2_gap"]


@dataclass
class FHOFCResult:
    """Outcome of :func:`fhofc` / :func:`fhofc_receding`.

    Attributes
    ----------
    u_ff : ndarray [N]
        Feedforward U_ff.
    y_hat : ndarray [m]
        Model output Ŷ = Φ̂(θ̂, x0, R, U_ff).
    u_hat : ndarray [N]
        Model input Û = C(q)(R - Ŷ) + U_ff.
    cost : float
        ‖R* - Ŷ‖² + ‖γΔU_ff‖² [m²].
    inversion_error : float
        ‖R* - Ŷ‖/sqrt(N_k) [m] ([B2] (15) term).
    history : list of float
        Cost after each accepted iteration (history[0]: initial cost).
    n_iter : int
    converged : bool
        False flags a fallback: the best iterate is returned but the solver stopped on
        ``max_iter``, a failed line of steps or an infeasible constraint.
    feasible : bool
        All requested bounds hold at u_ff (within 1e-9 relative).
    message : str
    time_s : float
        Wall time [s].
    """

    u_ff: np.ndarray
    y_hat: np.ndarray
    u_hat: np.ndarray
    cost: float
    inversion_error: float
    history: list = field(default_factory=list)
    n_iter: int = 0
    converged: bool = False
    feasible: bool = True
    message: str = ""
    time_s: float = 0.0


def difference_matrix(n: int) -> np.ndarray:
    """Δ of [B2] (31): 1 on the diagonal, -1 on the sub-diagonal (n × n)."""
    return np.eye(n) - np.eye(n, k=-1)


def _diff(u: np.ndarray, u_prev: float = 0.0) -> np.ndarray:
    """Δ u with u(-1) = u_prev."""
    return np.diff(u, prepend=u_prev)


def check_validity(model: ArxPGNN, signals: dict, margin: float = 0.1) -> None:
    """Raise ValueError if a reference leaves the model's validity range.

    The range is the output range seen in the identification data (``model.y_range``),
    widened by ``margin`` times its width on both sides.
    """
    if model.y_range is None:
        return
    lo, hi = model.y_range
    w = (hi - lo) * margin
    for name, s in signals.items():
        s = np.asarray(s)
        if s.size and (s.min() < lo - w or s.max() > hi + w):
            raise ValueError(
                f"{name} spans [{s.min():.4g}, {s.max():.4g}] m but the model was identified on outputs in "
                f"[{lo:.4g}, {hi:.4g}] m (validity range with margin {margin:g}: [{lo - w:.4g}, {hi + w:.4g}]); "
                "identify on data covering this reference or pass check_range=False to extrapolate")


def _check_bounds(name: str, bounds, n: int):
    if bounds is None:
        return None
    lo, hi = bounds
    lo = np.broadcast_to(np.asarray(-np.inf if lo is None else lo, float), (n,)).copy()
    hi = np.broadcast_to(np.asarray(np.inf if hi is None else hi, float), (n,)).copy()
    if np.any(lo > hi):
        k = int(np.flatnonzero(lo > hi)[0])
        raise ValueError(f"{name} are infeasible: lower bound {lo[k]:.4g} > upper bound {hi[k]:.4g} at sample "
                         f"{k}; give lower <= upper")
    return lo, hi


def fhofc(model: ArxPGNN, ctrl: DiscreteController, r, *, gamma: float = 0.0, target=None, u_ff0=None,
          state: LoopState | None = None, u_prev: float = 0.0, uff_bounds: tuple | None = None,
          u_bounds: tuple | None = None, max_iter: int = 50, ftol: float = 1e-10, check_range: bool = True,
          range_margin: float = 0.1, max_horizon: int = 5000) -> FHOFCResult:
    """FHOFC [B2] (17): the feedforward minimising ‖R* - Φ̂(θ̂, x0, R, U_ff)‖² + ‖γΔU_ff‖².

    Parameters
    ----------
    model : ArxPGNN or pipeline.models.pgnn.PGNN
        Identified model θ̂ ([B2] (30); n1 = 0 is the linear model); a PGNN module is exported
        with :meth:`ArxPGNN.from_pgnn` (no validity range then).
    ctrl : DiscreteController
        Feedback controller C(q) of the loop.
    r : array_like [m], shape (N_k,)
        Reference R driving the loop's feedback.
    gamma : float
        γ of Γ = γΔ ([B2] (31)) [m/N]; 0 = no regularisation.
    target : array_like [m], optional
        Output target R* (default R); IL-FHOFC passes R^(i+1) ([B2] (22)).
    u_ff0 : array_like [N], optional
        Initial guess (default zeros, or clipped into the bounds).
    state : LoopState, optional
        Initial state x0 (default at rest).
    u_prev : float
        u_ff(-1) [N] for the first row of Δ (0 at rest).
    uff_bounds, u_bounds : (lower, upper), optional
        Box bounds [N] on U_ff and on Û (scalars or arrays; None = unbounded side).
    max_iter : int
        Maximum solver iterations.
    ftol : float
        Stop when a step lowers (or is predicted to lower) the cost by less than ftol times the
        cost.
    check_range : bool
        Refuse references outside the model's validity range (:func:`check_validity`).
    range_margin : float
        Relative margin of that range.
    max_horizon : int
        Largest N_k for the dense N_k × N_k Jacobian; use :func:`fhofc_receding` beyond.

    Returns
    -------
    FHOFCResult
    """
    t0 = time.perf_counter()
    model = as_arx(model)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    N = r.shape[0]
    if N > max_horizon:
        raise ValueError(f"reference has N_k = {N} samples, above max_horizon = {max_horizon} for the dense "
                         f"{N}x{N} Jacobian; use fhofc_receding (receding horizon, [B2] (18)) or split the reference")
    tgt = r if target is None else np.asarray(target, dtype=np.float64).reshape(-1)
    if tgt.shape != r.shape:
        raise ValueError(f"target has {tgt.shape[0]} samples but r has {N}; give both one length")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(tgt))):
        raise ValueError("reference/target contain NaN or inf; clean them first")
    if gamma < 0 or not np.isfinite(gamma):
        raise ValueError(f"gamma must be a finite number >= 0, got {gamma}")
    if check_range:
        check_validity(model, {"reference": r, "target": tgt}, range_margin)
    ub = _check_bounds("uff_bounds", uff_bounds, N)
    uub = _check_bounds("u_bounds", u_bounds, N)
    u = np.zeros(N) if u_ff0 is None else np.array(u_ff0, dtype=np.float64).reshape(-1)
    if u.shape != (N,):
        raise ValueError(f"u_ff0 has {u.shape[0]} samples but r has {N}")
    if ub is not None:
        u = np.clip(u, ub[0], ub[1])
    yh0, _ = simulate_closed_loop(model, ctrl, r, u, state)
    if not np.all(np.isfinite(yh0)):
        raise ValueError("the closed-loop model simulation diverges at the initial feedforward (non-finite "
                         "output); check the model's stability in closed loop or give a better u_ff0")
    if uub is not None:
        out = _solve_slsqp(model, ctrl, r, tgt, gamma, u, state, u_prev, ub, uub, max_iter, ftol)
    elif ub is not None:
        out = _solve_trf(model, ctrl, r, tgt, gamma, u, state, u_prev, ub, max_iter, ftol)
    else:
        out = _solve_gn(model, ctrl, r, tgt, gamma, u, state, u_prev, max_iter, ftol)
    u, history, n_iter, converged, message = out
    y_hat, u_hat = simulate_closed_loop(model, ctrl, r, u, state)
    e = tgt - y_hat
    cost = float(e @ e + gamma ** 2 * np.sum(_diff(u, u_prev) ** 2))
    feasible = True
    for b, x in ((ub, u), (uub, u_hat)):
        if b is not None:
            tol = 1e-9 * max(1.0, float(np.max(np.abs(x))))
            feasible &= bool(np.all(x >= b[0] - tol) and np.all(x <= b[1] + tol))
    if not feasible:
        converged = False
        message += "; bounds violated at the returned iterate (infeasible problem?)"
    return FHOFCResult(u, y_hat, u_hat, cost, float(np.linalg.norm(e) / math.sqrt(N)), history, n_iter,
                       bool(converged), feasible, message, time.perf_counter() - t0)


def _residual_jac(model, ctrl, r, tgt, gamma, u, state, u_prev, need_jac=True):
    """Stacked residual [R* - Ŷ; γΔU] and Jacobian [-J; γΔ] (plus Û and ∂Û/∂U)."""
    if need_jac:
        y, uh, J, Ju = jacobian_uff(model, ctrl, r, u, state)
    else:
        y, uh = simulate_closed_loop(model, ctrl, r, u, state)
        J = Ju = None
    res = np.concatenate([tgt - y, gamma * _diff(u, u_prev)])
    return res, y, uh, J, Ju


def _solve_gn(model, ctrl, r, tgt, gamma, u, state, u_prev, max_iter, ftol):
    """Gauss–Newton with Levenberg damping (μ = 0 first) on the stacked least squares.

    Stops ('ftol') when an accepted step, or the Gauss–Newton model's predicted decrease of an
    undamped step, is below ftol times the cost: near the minimum of a nearly linear problem
    further steps only move rounding noise.
    """
    N = r.shape[0]
    d = model.delay
    D = difference_matrix(N)
    res, _, _, J, _ = _residual_jac(model, ctrl, r, tgt, gamma, u, state, u_prev)
    cost = float(res @ res)
    history = [cost]
    mu = 0.0
    n_iter = 0
    message, converged = "max_iter", False
    need = False
    while n_iter < max_iter:
        if cost == 0.0:
            message, converged = "zero_cost", True
            break
        if need:
            res, _, _, J, _ = _residual_jac(model, ctrl, r, tgt, gamma, u, state, u_prev)
        need = False
        n_iter += 1
        colnorm = np.sqrt(np.sum(J ** 2, axis=0) + 2.0 * gamma ** 2)
        step = _gn_step(J, res, gamma, D, d, mu, colnorm)
        # decrease predicted by the Gauss–Newton model ‖[e - Jδ; γΔ(u + δ)]‖²
        pred_res = np.concatenate([res[:N] - J @ step, res[N:] + gamma * _diff(step)])
        pred = cost - float(pred_res @ pred_res)
        if mu == 0.0 and pred <= ftol * cost:
            message, converged = "ftol", True
            break
        u_new = u + step
        res_new, *_ = _residual_jac(model, ctrl, r, tgt, gamma, u_new, state, u_prev, need_jac=False)
        finite = bool(np.all(np.isfinite(res_new)))
        decrease = float((res - res_new) @ (res + res_new)) if finite else -np.inf
        scale2 = float(colnorm.max()) ** 2
        if decrease > 0:
            u, cost_old = u_new, cost
            res = res_new
            cost = float(res @ res)
            history.append(cost)
            rho = decrease / pred if pred > 0 else 0.0
            if rho > 0.75 or mu < 1e-14 * scale2:
                mu = mu / 10.0 if mu > 1e-14 * scale2 else 0.0
            elif rho < 0.25:
                mu = 1e-6 * scale2 if mu == 0.0 else mu * 4.0
            need = True
            if decrease <= ftol * cost_old:
                message, converged = "ftol", True
                break
        else:
            # reject: raise the damping (relative to the largest column norm²)
            mu = 1e-6 * scale2 if mu == 0.0 else mu * 10.0
            if mu > 1e20 * scale2:
                message, converged = "mu_max", True
                break
    return u, history, n_iter, converged, message


def _gn_step(J, res, gamma, D, d, mu, colnorm):
    """Gauss–Newton/Levenberg step: least-squares solution of [J; γΔ; √μ diag(c)] δ = [e; -γΔu; 0].

    e = R* - Ŷ; the predicted residual is e - Jδ (Ŷ moves by Jδ).  With γ = μ = 0 the
    attainable block is square lower triangular and solved by substitution.
    """
    N = J.shape[0]
    e = res[:N]
    if gamma == 0.0 and mu == 0.0:
        # attainable block J[d:, :N-d] is square lower triangular: one triangular solve
        B = J[d:, :N - d]
        diag = np.abs(np.diag(B))
        if B.shape[0] and diag.min() > 1e-300 and diag.min() > 1e-14 * diag.max():
            step = np.zeros(N)
            step[:N - d] = sla.solve_triangular(B, e[d:], lower=True, check_finite=False)
            return step
    rows = [J, gamma * D] if gamma > 0 else [J]
    rhs = [e, -res[N:]] if gamma > 0 else [e]
    if mu > 0:
        rows.append(np.sqrt(mu) * np.diag(colnorm))
        rhs.append(np.zeros(N))
    A = np.vstack(rows)
    b = np.concatenate(rhs)
    step, *_ = sla.lstsq(A, b, lapack_driver="gelsy", check_finite=False)
    return step


def _solve_trf(model, ctrl, r, tgt, gamma, u, state, u_prev, ub, max_iter, ftol):
    """Box bounds on U_ff: scipy trust-region reflective least squares with the exact Jacobian."""
    from scipy.optimize import least_squares  # lazy: saves 0.5 s of start-up (scipy.optimize: the TRF solver only)
    N = r.shape[0]
    D = difference_matrix(N)
    cache = {}

    def ev(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            res, _, _, J, _ = _residual_jac(model, ctrl, r, tgt, gamma, x, state, u_prev)
            cache[key] = (res, J)
        return cache[key]

    def fun(x):
        return ev(x)[0]

    def jac(x):
        J = ev(x)[1]
        return np.vstack([-J, gamma * D]) if gamma > 0 else -J

    def fun_s(x):
        res = fun(x)
        return res if gamma > 0 else res[:N]

    lo, hi = ub
    x0 = np.clip(u, lo, hi)
    # strictly inside for trf
    inside = np.where(np.isfinite(lo) & np.isfinite(hi), 1e-10 * (hi - lo), 0.0)
    x0 = np.clip(x0, lo + inside, hi - inside)
    c0 = float(np.sum(fun_s(x0) ** 2))
    sol = least_squares(fun_s, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                        ftol=max(ftol, 1e-15), xtol=1e-15, gtol=1e-15, max_nfev=max(max_iter, 1))
    c1 = float(np.sum(fun_s(sol.x) ** 2))
    return sol.x, [c0, c1], int(sol.nfev), bool(sol.status > 0), f"trf: {sol.message}"


def _solve_slsqp(model, ctrl, r, tgt, gamma, u, state, u_prev, ub, uub, max_iter, ftol):
    """Bounds on Û (and U_ff): SLSQP with exact objective and constraint gradients."""
    from scipy.optimize import minimize  # lazy: saves 0.3 s of start-up (scipy.optimize: the SLSQP solver only)
    N = r.shape[0]
    D = difference_matrix(N)
    cache = {}

    def ev(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = _residual_jac(model, ctrl, r, tgt, gamma, x, state, u_prev)
        return cache[key]

    res0 = ev(u)[0]
    scale = 1.0 / max(float(res0 @ res0), 1e-300)

    def f(x):
        res = ev(x)[0]
        return scale * float(res @ res)

    def g(x):
        res, _, _, J, _ = ev(x)
        Ja = np.vstack([-J, gamma * D])
        return scale * 2.0 * (Ja.T @ res)

    lo_u, hi_u = uub
    fin_lo, fin_hi = np.isfinite(lo_u), np.isfinite(hi_u)
    uscale = 1.0 / max(float(np.max(np.abs(np.concatenate([lo_u[fin_lo], hi_u[fin_hi]])), initial=1.0)), 1.0)

    def cons(x):
        uh = ev(x)[2]
        return uscale * np.concatenate([uh[fin_lo] - lo_u[fin_lo], hi_u[fin_hi] - uh[fin_hi]])

    def cons_jac(x):
        Ju = ev(x)[4]
        return uscale * np.vstack([Ju[fin_lo], -Ju[fin_hi]])

    bounds = None if ub is None else list(zip(np.where(np.isfinite(ub[0]), ub[0], None),
                                              np.where(np.isfinite(ub[1]), ub[1], None)))
    c0 = float(np.sum(res0 ** 2))
    sol = minimize(f, u, jac=g, method="SLSQP", bounds=bounds,
                   constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}],
                   options={"maxiter": max_iter, "ftol": max(ftol, 1e-14)})
    c1 = float(np.sum(ev(sol.x)[0] ** 2))
    return sol.x, [c0, c1], int(sol.nit), bool(sol.success), f"slsqp: {sol.message}"


def _window_solve(model, ctrl, rs, ts, w, st, u_prev, gamma, d, max_iter, ftol):
    """Gauss–Newton on one receding-horizon window; returns (w, cost, iterations, converged)."""
    n_in, L = w.shape[0], rs.shape[0]
    n_out = ts.shape[0]

    def sim(wv, jac):
        useg = np.full(L, wv[-1])
        useg[:n_in] = wv
        if jac:
            y, _, J, _ = jacobian_uff(model, ctrl, rs, useg, st)
            J = J[d:, :n_in]
        else:
            y, _ = simulate_closed_loop(model, ctrl, rs, useg, st)
            J = None
        res = np.concatenate([ts - y[d:], gamma * np.diff(wv, prepend=u_prev)])
        return res, J

    res, J = sim(w, True)
    cost = float(res @ res)
    Dw = difference_matrix(n_in)
    for it in range(1, max_iter + 1):
        if cost == 0.0:
            return w, cost, it, True
        A = np.vstack([J, gamma * Dw]) if gamma > 0 else J
        b = np.concatenate([res[:n_out], -res[n_out:]]) if gamma > 0 else res[:n_out]
        step, *_ = sla.lstsq(A, b, lapack_driver="gelsy", check_finite=False)
        # the Gauss–Newton step is a descent direction: where the full step overshoots (a nonlinear model) or leaves
        # the finite range, halve it; only when 2^-30 of it gains nothing is w a minimum to working precision
        for _ in range(31):
            res_new, _ = sim(w + step, False)
            c_new = float(res_new @ res_new)
            if c_new < cost:
                break
            step = 0.5 * step
        else:
            return w, cost, it, True
        w, cost_old, cost = w + step, cost, c_new
        if cost_old - cost <= ftol * cost_old:
            return w, cost, it, True
        res, J = sim(w, True)
    return w, cost, max_iter, False


def fhofc_receding(model: ArxPGNN, ctrl: DiscreteController, r, *, h: int, gamma: float = 0.0, target=None,
                   state: LoopState | None = None, max_iter: int = 20, ftol: float = 1e-14,
                   check_range: bool = True, range_margin: float = 0.1) -> FHOFCResult:
    """Receding-horizon FHOFC [B2] (18).

    At every k the window ū(k) = [u_ff(k), …, u_ff(k+h-1)] minimises
    ‖r̄(k) - ŷ̄(k)‖² + ‖γ Δ ū(k)‖² over the outputs it moves, ŷ(k+d), …, ŷ(k+d+h-1)
    (d = n_k + 1, clipped at N_k), from the model state reached with the inputs already
    applied; Δ's first row uses the applied u_ff(k-1).  Only u_ff(k) is applied.  Inputs
    whose window holds no output (k ≥ N_k - d) keep u_ff(k-1).  With h = n_k + 1 and γ = 0
    this is the inverse-model feedforward [B2] (20) (Lemma 5.1).

    Parameters
    ----------
    h : int
        Prediction horizon (window length) ≥ 1.
    Other parameters as :func:`fhofc`.

    Returns
    -------
    FHOFCResult (history holds the final window cost per k; converged is False if any
    window stopped on max_iter).
    """
    t0 = time.perf_counter()
    model = as_arx(model)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    N = r.shape[0]
    if h < 1:
        raise ValueError(f"horizon h must be >= 1, got {h}")
    tgt = r if target is None else np.asarray(target, dtype=np.float64).reshape(-1)
    if tgt.shape != r.shape:
        raise ValueError(f"target has {tgt.shape[0]} samples but r has {N}")
    if check_range:
        check_validity(model, {"reference": r, "target": tgt}, range_margin)
    d = model.delay
    st = LoopState.rest(model, ctrl) if state is None else state.copy()
    u_ff = np.zeros(N)
    window = np.zeros(h)                   # warm start of ū(k)
    u_prev = 0.0
    costs, all_conv, iters = [], True, 0
    for k in range(N):
        L = min(N, k + d + h) - k          # samples simulated from k
        n_in = min(h, L - d)               # inputs u_ff(k..k+n_in-1) moving ŷ(k+d..k+L-1)
        if n_in <= 0:
            u_ff[k] = u_prev
        else:
            w, c, n, conv = _window_solve(model, ctrl, r[k:k + L], tgt[k + d:k + L], window[:n_in].copy(),
                                          st, u_prev, gamma, d, max_iter, ftol)
            iters += n
            all_conv &= conv
            costs.append(c)
            u_ff[k] = w[0]
            window = np.concatenate([w[1:], np.full(h - n_in + 1, w[-1])])
        # apply u_ff(k): advance the model state one sample
        _, _, st = simulate_closed_loop(model, ctrl, r[k:k + 1], u_ff[k:k + 1], st, return_state=True)
        u_prev = u_ff[k]
    y_hat, u_hat = simulate_closed_loop(model, ctrl, r, u_ff, state)
    e = tgt - y_hat
    cost = float(e @ e + gamma ** 2 * np.sum(_diff(u_ff) ** 2))
    return FHOFCResult(u_ff, y_hat, u_hat, cost, float(np.linalg.norm(e) / math.sqrt(N)), costs, iters,
                       bool(all_conv), True, "receding horizon" + ("" if all_conv else ": some window hit max_iter"),
                       time.perf_counter() - t0)


def inverse_model_feedforward(model: ArxPGNN, r, *, max_iter: int = 50, tol: float = 1e-15) -> np.ndarray:
    """Inverse-model feedforward [B2] (20): per sample, u_ff(k) solving r(k+n_k+1) = ŷ(k+n_k+1)
    with the regressor filled by the reference and past u_ff (scalar Newton, exact derivative).

    Assumes the inverse relation (19) is unique (ŷ monotone in u(k-n_k-1)) and r(i) = ŷ(i) = 0
    at rest before k = 0; the last n_k + 1 inputs move no output inside the horizon and keep
    the previous value.  For a nonminimum-phase model the result grows without bound (the
    inverse is unstable): it is the reference of Lemma 5.1, not a practical feedforward there.

    Parameters
    ----------
    model : ArxPGNN
    r : array_like [m], shape (N,)
    max_iter : int
        Newton iterations per sample.
    tol : float
        Relative step size at which Newton stops.

    Returns
    -------
    u_ff : ndarray [N]
    """
    model = as_arx(model)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    N, d = r.shape[0], model.delay
    n_a, n_b, n_k = model.n_a, model.n_b, model.n_k
    u = np.zeros(N)
    for k in range(N - d):
        t = k + d                                   # output sample moved first by u_ff(k)
        phi = np.zeros(model.n_phi)
        for i in range(1, n_a + 1):
            phi[i - 1] = r[t - i] if t - i >= 0 else 0.0
        for i in range(1, n_b + 1):
            j = t - n_k - i
            phi[n_a + i - 1] = u[j] if j >= 0 else 0.0
        x = -0.0
        for _ in range(max_iter):
            phi[n_a] = x
            f = float(model.one_step(phi[None, :])[0]) - r[t]
            g = float(model.input_gain(phi[None, :])[0])
            if g == 0.0:
                raise ValueError(f"the model is not invertible at sample {k}: ∂ŷ/∂u = 0")
            step = f / g
            x -= step
            if abs(step) <= tol * max(abs(x), 1e-300):
                break
        u[k] = x
    u[N - d:] = u[N - d - 1] if N > d else 0.0
    return u


# --------------------------------------------------------------------------------------
# iterative learning: IL-FHOFC [B2] (22) and linear ILC [B2] (23)
# --------------------------------------------------------------------------------------

@dataclass
class ILResult:
    """Per-trial log of :func:`il_fhofc` / :func:`linear_ilc`.

    Attributes
    ----------
    e_rms : ndarray
        rms(R - Y^(i)) [m] per trial i = 0..n_trials-1 ([B2] Fig. 5).
    u_ff : list of ndarray
        U_ff^(i) applied at trial i [N].
    y : list of ndarray
        Output Y^(i) returned by the plant [m].
    y_hat : list of ndarray
        Model prediction Ŷ^(i) = Φ̂(θ̂, x0, R, U_ff^(i)) [m] (IL-FHOFC only).
    inversion_error : list of float
        ‖R^(i) - Ŷ^(i)‖/sqrt(N) of each FHOFC solve [m] (IL-FHOFC only).
    solver : list of FHOFCResult
        Each FHOFC solve (IL-FHOFC only).
    """

    e_rms: np.ndarray
    u_ff: list
    y: list
    y_hat: list = field(default_factory=list)
    inversion_error: list = field(default_factory=list)
    solver: list = field(default_factory=list)


def _run_plant(plant, u_ff, N, i):
    y = np.asarray(plant(u_ff), dtype=np.float64).reshape(-1)
    if y.shape != (N,) or not np.all(np.isfinite(y)):
        raise ValueError(f"the plant callable returned {y.shape} (finite={np.all(np.isfinite(y))}) at trial {i}; "
                         f"it must return a finite output of {N} samples for a feedforward of {N} samples")
    return y


def il_fhofc(model: ArxPGNN, ctrl: DiscreteController, r, plant: Callable[[np.ndarray], np.ndarray], *,
             n_trials: int, alpha: float = 1.0, gamma: float = 0.0, u_ff0=None, callback: Callable | None = None,
             **fhofc_kwargs) -> ILResult:
    """IL-FHOFC [B2] (22): R^(i+1) = Ŷ^(i) + α E^(i), re-solve FHOFC, run the plant, repeat.

    Trial 0 applies the FHOFC feedforward of the model for R (target R^(0) = R).

    Parameters
    ----------
    model, ctrl : the identified model and the known controller.
    r : array_like [m]
        Reference R (also drives the model loop's feedback in every solve).
    plant : callable
        ``plant(u_ff) -> y``: runs the true system in its loop with feedforward u_ff and
        returns the measured output Y [m].
    n_trials : int
        Number of plant runs (trials 0..n_trials-1).
    alpha : float
        Learning gain α ∈ (0, 1].
    gamma : float
        γ of Γ = γΔ.
    u_ff0 : array_like, optional
        Initial guess of the first FHOFC solve.
    callback : callable, optional
        ``callback(i, e_rms)`` after every trial.
    fhofc_kwargs
        Passed to :func:`fhofc` (bounds, max_iter, ...).

    Returns
    -------
    ILResult
    """
    model = as_arx(model)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    N = r.shape[0]
    if not 0 < alpha <= 1:
        raise ValueError(f"learning gain alpha must be in (0, 1], got {alpha}")
    if n_trials < 1:
        raise ValueError(f"n_trials must be >= 1, got {n_trials}")
    target = r
    u = u_ff0
    out = ILResult(np.zeros(n_trials), [], [])
    for i in range(n_trials):
        sol = fhofc(model, ctrl, r, gamma=gamma, target=target, u_ff0=u, **fhofc_kwargs)
        u = sol.u_ff
        y = _run_plant(plant, u, N, i)
        e = r - y
        out.e_rms[i] = float(np.linalg.norm(e) / math.sqrt(N))
        out.u_ff.append(u.copy())
        out.y.append(y)
        out.y_hat.append(sol.y_hat)
        out.inversion_error.append(sol.inversion_error)
        out.solver.append(sol)
        if callback is not None:
            callback(i, out.e_rms[i])
        target = sol.y_hat + alpha * e          # [B2] (22)
    return out


def fhofc_windows(model: ArxPGNN, ctrl: DiscreteController, r, *, window: int, overlap: int, gamma: float = 0.0,
                  target=None, u_ff0=None, state: LoopState | None = None, u_prev: float = 0.0,
                  **fhofc_kwargs) -> FHOFCResult:
    """FHOFC [B2] (17) on a reference too long for one dense N_k × N_k Jacobian: :func:`fhofc` on consecutive
    windows of ``window`` + ``overlap`` samples, each from the model's state (and Δ's u_ff(-1)) that the inputs
    already kept reached; a window keeps its first ``window`` inputs, the ``overlap`` only looks ahead (the
    receding horizon of [B2] (18) with a step of ``window`` samples). With γ = 0 the solution is causal (the
    triangular solve of :func:`_gn_step`: u_ff(k) follows from the target up to k + n_k + 1), so any
    ``overlap`` ≥ n_k + 1 gives the whole-horizon solution; with γ > 0 the overlap must cover the decay of the
    regularised inverse. ``N_k`` ≤ ``window`` + ``overlap``: :func:`fhofc` itself (the same result to the
    bit). Bounds must be scalars (they apply to every window). Other parameters as :func:`fhofc`."""
    t0 = time.perf_counter()
    model = as_arx(model)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    N = r.shape[0]
    window, overlap = int(window), int(overlap)
    if window < 1 or overlap < model.delay:
        raise ValueError(f"fhofc_windows needs window >= 1 and overlap >= n_k + 1 = {model.delay} (the inputs a "
                         f"window cannot move an output with); got window={window}, overlap={overlap}")
    if N <= window + overlap:
        return fhofc(model, ctrl, r, gamma=gamma, target=target, u_ff0=u_ff0, state=state, u_prev=u_prev,
                     **fhofc_kwargs)
    tgt = r if target is None else np.asarray(target, dtype=np.float64).reshape(-1)
    if tgt.shape != r.shape:
        raise ValueError(f"target has {tgt.shape[0]} samples but r has {N}; give both one length")
    u = np.zeros(N) if u_ff0 is None else np.array(u_ff0, dtype=np.float64).reshape(-1)
    if u.shape != (N,):
        raise ValueError(f"u_ff0 has {u.shape[0]} samples but r has {N}")
    st = LoopState.rest(model, ctrl) if state is None else state.copy()
    prev, n_iter, converged, messages, history = u_prev, 0, True, set(), []
    for s in range(0, N, window):
        e, keep = min(N, s + window + overlap), min(window, N - s)
        sol = fhofc(model, ctrl, r[s:e], gamma=gamma, target=tgt[s:e], u_ff0=u[s:e], state=st, u_prev=prev,
                    **fhofc_kwargs)
        u[s:s + keep] = sol.u_ff[:keep]
        _, _, st = simulate_closed_loop(model, ctrl, r[s:s + keep], u[s:s + keep], st, return_state=True)
        prev = u[s + keep - 1]
        n_iter += sol.n_iter
        converged &= sol.converged
        messages.add(sol.message)
        history.append(sol.cost)
    y_hat, u_hat = simulate_closed_loop(model, ctrl, r, u, state)
    err = tgt - y_hat
    cost = float(err @ err + gamma ** 2 * np.sum(_diff(u, u_prev) ** 2))
    return FHOFCResult(u, y_hat, u_hat, cost, float(np.linalg.norm(err) / math.sqrt(N)), history, n_iter,
                       bool(converged), True, f"{len(history)} windows: " + ", ".join(sorted(messages)),
                       time.perf_counter() - t0)


def il_fhofc_step(model: ArxPGNN, ctrl: DiscreteController, r, u_ff, y, *, alpha: float = 1.0, gamma: float = 0.0,
                  window: int | None = None, overlap: int = 0, **fhofc_kwargs) -> FHOFCResult:
    """One trial of IL-FHOFC [B2] (22) from a *measured* trial: the plant ran U_ff^(i) and returned Y^(i) (a
    recording, not :func:`il_fhofc`'s plant callable). Ŷ^(i) = Φ̂(θ̂, x0, R, U_ff^(i)), R^(i+1) = Ŷ^(i) + α (R -
    Y^(i)), and FHOFC for R^(i+1) from U_ff^(i). With ``window`` None the whole-horizon :func:`fhofc`: the
    U_ff^(i+1) of :func:`il_fhofc` to the bit (the same Ŷ^(i), target and start); else :func:`fhofc_windows`."""
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    if not alpha > 0:
        raise ValueError(f"learning gain alpha must be > 0, got {alpha}")
    if y.shape != r.shape or not np.all(np.isfinite(y)):
        raise ValueError(f"the measured output must be {r.shape[0]} finite samples (one per reference sample)")
    y_hat, _ = simulate_closed_loop(model, ctrl, r, u_ff)
    target = y_hat + alpha * (r - y)          # [B2] (22)
    if window is None:
        return fhofc(model, ctrl, r, gamma=gamma, target=target, u_ff0=u_ff, **fhofc_kwargs)
    return fhofc_windows(model, ctrl, r, window=window, overlap=overlap, gamma=gamma, target=target, u_ff0=u_ff,
                         **fhofc_kwargs)


def linear_ilc(model: ArxPGNN, ctrl: DiscreteController, r, plant: Callable[[np.ndarray], np.ndarray], *,
               n_trials: int, alpha: float = 1.0, u_ff0=None, callback: Callable | None = None) -> ILResult:
    """Linear ILC [B2] (23): u_ff^(i+1) = u_ff^(i) + α Ĝ^-1 (1 + ĜC) e^(i), on a finite horizon.

    Ĝ^-1(1 + ĜC) is the inverse of the process sensitivity (1 + ĜC)^-1 Ĝ, whose lifted matrix
    is the Jacobian ∂Ŷ/∂U_ff of the linear closed-loop model.  It is strictly lower
    triangular with d = n_k + 1 samples of delay, so the update inverts its square block
    ``J[d:, :N-d]`` (forward substitution, i.e. running the non-causal inverse filter);
    e(0..d-1) cannot be influenced and u_ff(N-d..N-1) are kept.  For a nonminimum-phase Ĝ the
    inverse filter is unstable and the update grows like the unstable zero to the power N
    (use IL-FHOFC with γ > 0 instead, which is this update regularised, Lemma 5.2).

    Parameters
    ----------
    model : ArxPGNN
        Linear model Ĝ (n1 = 0 required).
    Other parameters as :func:`il_fhofc`.
    """
    model = as_arx(model)
    if model.n1:
        raise ValueError(f"linear_ilc needs a linear model (n1 = 0), got n1 = {model.n1}; use model.linear_part()")
    if not 0 < alpha <= 1:
        raise ValueError(f"learning gain alpha must be in (0, 1], got {alpha}")
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    N = r.shape[0]
    d = model.delay
    u = np.zeros(N) if u_ff0 is None else np.array(u_ff0, dtype=np.float64).reshape(-1)
    _, _, J, _ = jacobian_uff(model, ctrl, r, u)
    B = J[d:, :N - d]
    out = ILResult(np.zeros(n_trials), [], [])
    for i in range(n_trials):
        y = _run_plant(plant, u, N, i)
        e = r - y
        out.e_rms[i] = float(np.linalg.norm(e) / math.sqrt(N))
        out.u_ff.append(u.copy())
        out.y.append(y)
        if callback is not None:
            callback(i, out.e_rms[i])
        du = np.zeros(N)
        du[:N - d] = sla.solve_triangular(B, e[d:], lower=True)   # [B2] (23)
        u = u + alpha * du
    return out


# --------------------------------------------------------------------------------------
# the recovery results of [B2] §V as checks
# --------------------------------------------------------------------------------------

def _rel(a, b) -> float:
    nb = float(np.linalg.norm(b))
    return float(np.linalg.norm(a - b)) / nb if nb > 0 else float(np.linalg.norm(a - b))


def lemma_5_1_gap(model: ArxPGNN, ctrl: DiscreteController, r) -> float:
    """Lemma 5.1: relative difference between the receding-horizon FHOFC (18) with h = n_k + 1,
    Γ = 0 and the inverse-model feedforward (20) (inputs that move an output in the horizon)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    d = model.delay
    rh = fhofc_receding(model, ctrl, r, h=d, gamma=0.0, check_range=False)
    return _rel(rh.u_ff[:r.size - d], inverse_model_feedforward(model, r)[:r.size - d])


def lemma_5_2_gap(model: ArxPGNN, ctrl: DiscreteController, r, plant: Callable[[np.ndarray], np.ndarray],
                  n_trials: int = 4, alpha: float = 1.0) -> float:
    """Lemma 5.2: largest relative difference over trials between the feedforwards of IL-FHOFC
    (22) with a linear model and Γ = 0 and of the ILC update (23) from the same first input."""
    a = il_fhofc(model, ctrl, r, plant, n_trials=n_trials, alpha=alpha, gamma=0.0, check_range=False)
    b = linear_ilc(model, ctrl, r, plant, n_trials=n_trials, alpha=alpha, u_ff0=a.u_ff[0])
    return max(_rel(x, y) for x, y in zip(a.u_ff, b.u_ff))
