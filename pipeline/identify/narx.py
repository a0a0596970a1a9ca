"""NARX (forward) and direct-inverse identification of PGNNs, [B1] §II-B and §V-B.

Criteria (SPEC §5, squared 2-norms, normalised units):

- [B1] (7): physics-only MSE, solved in closed form (column-scaled linear least squares);
- [B1] (12): forward PGNN, one-step-ahead output residuals plus the regulariser
  (θ_phy - θ*_phy)ᵀ Λ (θ_phy - θ*_phy) toward the physics-only estimate θ*_phy;
- [B1] (14): direct-inverse PGNN, the same on the input residuals;
- [B1] (29): invertible PGNN, the regulariser without the input gains ψ.

Normalisation (SPEC §5): residuals are divided by the standard deviation σ of the predicted
signal over the training rows (y for forward models, u for inverse ones) and by sqrt(M), and
θ_phy enters the regulariser as the relative deviation (θ_phy - θ*_phy)/|θ*_phy|, so the cost

    V(θ) = (1/M) Σ ((target - ŷ)/σ)² + dᵀ Λ d,      d = (θ_phy - θ*_phy) / |θ*_phy|

makes Λ = 0.01 I mean "a 10% change of a physical parameter costs 1e-4 of normalised MSE".
It is minimised by Levenberg–Marquardt (:mod:`pipeline.identify.lm`) with the exact closed-form
Jacobian, from ``n_restarts`` random NN initialisations (θ_phy starts at θ*_phy), keeping the
lowest training cost; early stopping watches a contiguous validation block at the end of the
record (never a random split of time samples).
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from scipy.linalg import solve_discrete_lyapunov

from pipeline.identify.lm import CAP_FACTOR, LMResult, levenberg_marquardt, normal_equations_from_blocks
from pipeline.models.pgnn import PGNN, Prepared

__all__ = ["Regression", "forward_regressor", "inverse_regressor", "build_regression",
           "physics_least_squares", "regularizer_sqrt", "RestartResult", "NarxFit",
           "identify_pgnn", "criterion", "arx_inverse_asymptotics"]


# --------------------------------------------------------------------------------------------
# regressors
# --------------------------------------------------------------------------------------------
@dataclass
class Regression:
    """Rows of a NARX regression: regressors ``phi`` [M, n_a + n_b], ``target`` [M] and the
    time index ``t`` [M] of each row (the sample of the target y(t) or u(t))."""

    phi: np.ndarray
    target: np.ndarray
    t: np.ndarray

    def __len__(self):
        return self.target.shape[0]


def _check_orders(n_a, n_b, n_k):
    if int(n_a) != n_a or int(n_b) != n_b or int(n_k) != n_k or n_a < 0 or n_b < 1 or n_k < 0:
        raise ValueError(f"NARX orders need integers n_a >= 0, n_b >= 1, n_k >= 0; got "
                         f"n_a={n_a}, n_b={n_b}, n_k={n_k}")


def _check_pair(y, u):
    y = np.asarray(y, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if y.ndim != 1 or u.ndim != 1 or y.shape != u.shape:
        raise ValueError(f"y and u must be 1-D signals of one length, got shapes {y.shape} and "
                         f"{u.shape}")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        raise ValueError("y or u contains NaN/inf; clean or drop those samples first")
    return y, u


def forward_regressor(y, u, n_a: int, n_b: int, n_k: int = 0) -> Regression:
    """Forward NARX rows ([B1] (1)): φ(t) = [y(t-1..t-n_a), u(t-n_k-1..t-n_k-n_b)], target y(t).

    Only complete rows are kept: t = max(n_a, n_k + n_b), …, N-1 (no padding).

    Raises
    ------
    ValueError
        If the orders leave no complete row in the data.
    """
    _check_orders(n_a, n_b, n_k)
    y, u = _check_pair(y, u)
    N = y.shape[0]
    t0 = max(n_a, n_k + n_b)
    if N - t0 < 1:
        raise ValueError(f"regressor orders n_a={n_a}, n_b={n_b}, n_k={n_k} need more than "
                         f"{t0} samples per record, the data have N={N}; use longer records "
                         "or lower orders")
    t = np.arange(t0, N)
    cols = [y[t - i] for i in range(1, n_a + 1)] + [u[t - n_k - i] for i in range(1, n_b + 1)]
    return Regression(np.stack(cols, axis=1), y[t].copy(), t)


def inverse_regressor(y, u, n_a: int, n_b: int, n_k: int = 0) -> Regression:
    """Direct-inverse rows ([B1] (13)): φ'(t) = [y(t+n_k+1..t+n_k-n_a+1), u(t-1..t-n_b+1)],
    target u(t).

    Complete rows only: t = max(n_a - n_k - 1, n_b - 1, 0), …, N - n_k - 2.

    Raises
    ------
    ValueError
        If the orders leave no complete row in the data.
    """
    _check_orders(n_a, n_b, n_k)
    y, u = _check_pair(y, u)
    N = y.shape[0]
    t0 = max(n_a - n_k - 1, n_b - 1, 0)
    t1 = N - n_k - 2
    if t1 < t0:
        raise ValueError(f"inverse regressor orders n_a={n_a}, n_b={n_b}, n_k={n_k} need at "
                         f"least {t0 + n_k + 2} samples per record, the data have N={N}; use "
                         "longer records or lower orders")
    t = np.arange(t0, t1 + 1)
    cols = [y[t + n_k + 1 - i] for i in range(0, n_a + 1)] + [u[t - i] for i in range(1, n_b)]
    return Regression(np.stack(cols, axis=1), u[t].copy(), t)


def build_regression(model: PGNN, y, u) -> Regression:
    """Rows for ``model``'s structure; ``y``/``u`` may be lists of records (concatenated)."""
    if isinstance(y, (list, tuple)):
        if not isinstance(u, (list, tuple)) or len(u) != len(y) or len(y) == 0:
            raise ValueError("give y and u as two lists of records of one length")
        parts = [build_regression(model, a, b) for a, b in zip(y, u)]
        return Regression(np.concatenate([p.phi for p in parts]),
                          np.concatenate([p.target for p in parts]),
                          np.concatenate([p.t for p in parts]))
    make = inverse_regressor if model.structure == "inverse" else forward_regressor
    return make(y, u, model.n_a, model.n_b, model.n_k)


# --------------------------------------------------------------------------------------------
# criteria
# --------------------------------------------------------------------------------------------
_BLOCK = 1024  # rows per block of the residual and the Jacobian: a [_BLOCK, ~100] block stays in L2


def physics_least_squares(model: PGNN, phi, target) -> np.ndarray:
    """θ*_phy of [B1] (7): closed-form least squares of the physics part alone,
    ``target - T₀(φ) ≈ T(φ) θ``, with column scaling (SVD-based ``numpy.linalg.lstsq``).

    Raises
    ------
    ValueError
        If the model has no physics part or the features are rank deficient on the data.
    """
    if not model.use_physics:
        raise ValueError("physics_least_squares needs a model with a physics part")
    phi = torch.as_tensor(np.asarray(phi, dtype=float))
    with torch.no_grad():
        off, T = model.physics.features(phi)
    T = T.numpy()
    z = np.asarray(target, dtype=float) - off.numpy()
    scale = np.linalg.norm(T, axis=0)
    if np.any(scale == 0):
        bad = [model.physics.param_names[i] for i in np.flatnonzero(scale == 0)]
        raise ValueError(f"physics features {bad} are zero on all data: the data do not excite "
                         "them; use richer data or remove those parameters")
    theta_s, _, rank, sv = np.linalg.lstsq(T / scale, z, rcond=None)
    if rank < T.shape[1]:
        raise ValueError(f"physics features are rank deficient on the data (rank {rank} < "
                         f"{T.shape[1]}, singular values {sv}); the data do not excite every "
                         "physical parameter")
    return theta_s / scale


def regularizer_sqrt(lam, p: int, keep: np.ndarray | None = None) -> np.ndarray:
    """R with RᵀR = Λ (symmetric square root), Λ given as a scalar (λ I), a vector (diagonal)
    or a p×p matrix; rows/columns where ``keep`` is False are zeroed ([B1] (29) omits ψ)."""
    L = np.asarray(lam, dtype=float)
    if L.ndim == 0:
        L = float(L) * np.eye(p)
    elif L.ndim == 1:
        if L.shape[0] != p:
            raise ValueError(f"Λ diagonal has {L.shape[0]} entries, θ_phy has {p}")
        L = np.diag(L)
    if L.shape != (p, p):
        raise ValueError(f"Λ must be a scalar, a length-{p} diagonal or a {p}×{p} matrix, got "
                         f"shape {L.shape}")
    if not np.allclose(L, L.T):
        raise ValueError("Λ must be symmetric")
    if keep is not None:
        L = L * keep[:, None] * keep[None, :]
    w, V = np.linalg.eigh(L)
    if w.min() < -1e-12 * max(1.0, abs(w).max()):
        raise ValueError(f"Λ must be positive semidefinite, smallest eigenvalue {w.min():.3g}")
    return (V * np.sqrt(np.clip(w, 0, None))) @ V.T


def criterion(model: PGNN, prep: Prepared, target: torch.Tensor, sigma: float,
              theta_star: torch.Tensor | None, R: torch.Tensor | None
              ) -> tuple[Callable, Callable]:
    """Residual and exact Jacobian of the normalised criterion ([B1] (12), (14), (29)).

    ``residual(θ) = [(target - ŷ(θ))/(σ sqrt M); R d(θ)]`` with d the relative deviation of
    θ_phy from θ*_phy; ``||residual||²`` is V(θ) of the module docstring.  ``jacobian`` returns
    the same buffer at every call (overwritten): use each J before asking for the next.  The LM
    uses ``jacobian.normal_equations(θ, r) -> (JᵀJ, Jᵀr)`` instead, summed over row blocks of J
    in cache (:func:`pipeline.identify.lm.normal_equations_from_blocks`), so J is never stored.
    """
    M = target.shape[0]
    c = 1.0 / (sigma * np.sqrt(M))
    reg = R is not None and theta_star is not None and model.use_physics and bool(torch.any(R != 0))
    sl = model.phy_slice
    n_reg = 0
    if reg:
        scale = theta_star.abs()
        scale = torch.where(scale > 1e-12 * scale.max(), scale, torch.ones_like(scale))
        Rs = R / scale[None, :]  # ∂(R d)/∂θ_phy
        n_reg = Rs.shape[0]
        J_reg = torch.zeros(n_reg, model.n_params, dtype=torch.float64)  # constant rows of J
        J_reg[:, sl] = Rs

    # the hidden activations of the last residual evaluation and its θ: the LM asks for the
    # normal equations at the θ of the residual it just accepted, so they need not be recomputed
    one_hidden = model.use_nn and len(model.hidden) == 1
    hidden = torch.empty(M, model.hidden[0], dtype=torch.float64) if one_hidden else None
    hidden_at = [None]

    def residual(theta):
        hidden_at[0] = None
        e = (target - model.predict(theta, prep, block=_BLOCK, hidden=hidden)) * c
        hidden_at[0] = theta.detach().clone() if one_hidden else None
        if reg:
            e = torch.cat([e, Rs @ (theta[sl] - theta_star)])
        return e

    buf = None  # one buffer for every full Jacobian, allocated on first use

    def jacobian(theta):
        nonlocal buf
        if buf is None:
            buf = torch.empty(M + n_reg, model.n_params, dtype=torch.float64)
            if reg:
                buf[M:] = J_reg
        model.jacobian(theta, prep, out=buf[:M], scale=-c, block=_BLOCK)
        return buf

    def normal_equations(theta, r):
        h = hidden if hidden_at[0] is not None and torch.equal(hidden_at[0], theta) else None
        # one hidden layer: the blocks formed and reduced in one numba kernel, the same sums to the bit
        fused = model.normal_equations(theta, prep, r, scale=-c, block=_BLOCK, hidden=h,
                                       extra=[(M, J_reg)] if reg else ())
        if fused is not None:
            return fused
        blocks = model.jacobian_blocks(theta, prep, scale=-c, block=_BLOCK, hidden=h)
        if reg:
            blocks = itertools.chain(blocks, [(M, J_reg)])
        return normal_equations_from_blocks(blocks, r, model.n_params)

    def jvp(theta, v):            # J v, block by block (geodesic acceleration, lm.py)
        out = torch.empty(M + n_reg, dtype=torch.float64)
        for a, J in model.jacobian_blocks(theta, prep, scale=-c, block=_BLOCK):
            out[a:a + J.shape[0]] = J @ v
        if reg:
            out[M:] = J_reg @ v
        return out

    def vjp(theta, w):            # Jᵀ w, block by block
        out = torch.zeros(model.n_params, dtype=torch.float64)
        for a, J in model.jacobian_blocks(theta, prep, scale=-c, block=_BLOCK):
            out += J.T @ w[a:a + J.shape[0]]
        if reg:
            out += J_reg.T @ w[M:]
        return out

    jacobian.normal_equations = normal_equations
    jacobian.jvp, jacobian.vjp = jvp, vjp
    return residual, jacobian


# --------------------------------------------------------------------------------------------
# identification
# --------------------------------------------------------------------------------------------
@dataclass
class RestartResult:
    """One LM run from one random initialisation."""

    seed: int
    cost: float                 # training criterion V(θ) at the returned θ
    val_cost: float | None      # validation normalised MSE at θ (None without validation)
    history: list[float]        # training V per accepted LM step (the loss curve)
    val_history: list[float]
    n_iter: int
    message: str
    seconds: float
    theta: torch.Tensor


@dataclass
class NarxFit:
    """Result of :func:`identify_pgnn`: ``model`` holds the best restart's parameters."""

    model: PGNN
    theta_phy_star: np.ndarray | None     # [B1] (7) estimate (None for a black box)
    sigma: float                          # std of the predicted signal on the training rows
    n_train: int
    n_val: int
    restarts: list[RestartResult] = field(default_factory=list)
    best: int = 0

    @property
    def cost(self) -> float:
        return self.restarts[self.best].cost

    @property
    def histories(self) -> list[list[float]]:
        return [r.history for r in self.restarts]


def _split_tail(y, u, val_fraction):
    """Split records into training and a contiguous validation block at the end."""
    ys = list(y) if isinstance(y, (list, tuple)) else [y]
    us = list(u) if isinstance(u, (list, tuple)) else [u]
    ys = [np.asarray(a, dtype=float) for a in ys]
    us = [np.asarray(a, dtype=float) for a in us]
    if len(ys) != len(us):
        raise ValueError("give y and u as two lists of records of one length")
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    if val_fraction == 0.0:
        return ys, us, [], []
    n_tot = sum(a.shape[0] for a in ys)
    n_val = int(round(val_fraction * n_tot))
    ty, tu, vy, vu = [], [], [], []
    remaining = n_tot - n_val  # samples left for training, taken from the start
    for a, b in zip(ys, us):
        k = min(max(remaining, 0), a.shape[0])
        if k > 0:
            ty.append(a[:k]); tu.append(b[:k])
        if k < a.shape[0]:
            vy.append(a[k:]); vu.append(b[k:])
        remaining -= a.shape[0]
    return ty, tu, vy, vu


def identify_pgnn(model: PGNN, y, u, *, lam=0.01, n_restarts: int = 10, seed: int = 0,
                  val_fraction: float = 0.2, max_iter: int = 100, ftol: float = 1e-10,
                  gtol: float = 1e-10, mu0: float = 1e-3, patience: int = 5,
                  geodesic: bool = False, stat_window: int = 0, stat_tol: float = 0.1,
                  stat_frac: float = 0.0, screen_iter: int = 0, stat_promise: str = "gauss_newton",
                  progress: Callable | None = None,
                  on_iteration: Callable[[int, int, float], None] | None = None,
                  theta_star=None, memo: Callable | None = None) -> NarxFit:
    """Identify ``model`` from data with the criterion its structure implies.

    ``structure='forward'`` → [B1] (12); ``'inverse'`` → [B1] (14); ``'invertible'`` → [B1]
    (29) (ψ free).  A physics-only model (``use_nn=False``) is the closed form [B1] (7).

    Parameters
    ----------
    model : PGNN
        Modified in place (normalisation, θ*_phy, best parameters) and returned in the fit.
    y, u : array or list of arrays
        Measured output [m] and input [N] (one record or a list of records).
    lam : float, array
        Λ in normalised units (scalar → λ I, vector → diagonal, or a matrix).
    n_restarts : int
        Random NN initialisations; the lowest training cost wins ([B1] §VI: 10).
    seed : int
        Seed of the initialisations (restart i uses ``SeedSequence([seed, i])``).
    val_fraction : float
        Length of the validation block at the end of the record(s) (0 disables early
        stopping).
    max_iter, ftol, gtol, mu0, patience, geodesic, stat_window, stat_tol, stat_frac, stat_promise
        Passed to :func:`pipeline.identify.lm.levenberg_marquardt` (the statistical stop's N is
        the number of training rows).
    screen_iter : int
        > 0: every restart runs this many LM steps, only the best continues (:func:`best_of_restarts`).
    progress : callable, optional
        Wraps the restart iterable (e.g. ``ctx.progress``).
    on_iteration : callable, optional
        ``on_iteration(restart, it, cost)`` after every accepted LM step.
    theta_star : array, optional
        θ*_phy, the regulariser centre and start of θ_phy; default the physics-only least
        squares [B1] (7) on the same rows (a measured system passes its filtered baseline).
    memo : callable, optional
        ``memo(i, budget, compute)`` caches restart i (see :func:`best_of_restarts`).

    Returns
    -------
    NarxFit
    """
    if n_restarts < 1:
        raise ValueError(f"n_restarts must be >= 1, got {n_restarts}")
    ty, tu, vy, vu = _split_tail(y, u, val_fraction)
    train = build_regression(model, ty, tu)
    val = build_regression(model, vy, vu) if vy else None
    M = len(train)
    if M < model.n_params:
        raise ValueError(f"{M} training rows cannot identify {model.n_params} parameters; "
                         "use more data or a smaller network")
    phi = torch.as_tensor(train.phi)
    target = torch.as_tensor(train.target)
    sigma = float(target.std())
    if not sigma > 0:
        raise ValueError("the predicted signal is constant on the training rows; nothing to fit")

    if model.use_physics:
        if theta_star is None:
            theta_star = physics_least_squares(model, train.phi, train.target)  # [B1] (7)
        theta_star = np.asarray(theta_star, dtype=np.float64).reshape(-1)
        model.set_physics_estimate(theta_star)
    else:
        theta_star = None
    if model.use_nn:
        model.fit_normalisation(phi)
        with torch.no_grad():
            base = model.physics_part(phi) if model.use_physics else torch.zeros_like(target)
            s = float((target - base).std())
            model.out_scale.fill_(s if s > 0 else sigma)

    prep = model.prepare(phi)
    R = None
    if model.use_physics:
        keep = ~model.psi_mask().numpy() if model.structure == "invertible" else None
        R = torch.as_tensor(regularizer_sqrt(lam, model.physics.n_params, keep))
    th_star_t = None if theta_star is None else torch.as_tensor(theta_star)
    residual, jacobian = criterion(model, prep, target, sigma, th_star_t, R)

    val_fn = None
    if val is not None:
        vprep = model.prepare(torch.as_tensor(val.phi))
        vtarget = torch.as_tensor(val.target)

        def val_fn(theta):
            with torch.no_grad():
                e = (vtarget - model.predict(theta, vprep)) / sigma
            return float(e @ e) / e.numel()

    fit = NarxFit(model=model, theta_phy_star=theta_star, sigma=sigma, n_train=M,
                  n_val=0 if val is None else len(val))
    if not model.use_nn:  # [B1] (7): closed form, nothing to iterate
        th = model.parameter_vector()
        r = residual(th)
        c = float(r @ r)
        fit.restarts.append(RestartResult(seed, c, None if val_fn is None else val_fn(th), [c], [],
                                          0, "closed_form", 0.0, th))
        return fit

    restarts, fit.best = best_of_restarts(model, residual, jacobian, n_restarts, seed, val_fn=val_fn,
                                          max_iter=max_iter, ftol=ftol, gtol=gtol, mu0=mu0,
                                          patience=patience, progress=progress, on_iteration=on_iteration,
                                          memo=memo, geodesic=geodesic, stat_window=stat_window,
                                          stat_tol=stat_tol, stat_frac=stat_frac, n_data=M,
                                          screen_iter=screen_iter, stat_promise=stat_promise)
    fit.restarts.extend(restarts)
    return fit


def _best_validation_index(val_history: list[float]) -> int:
    """Index of the iterate :func:`levenberg_marquardt` keeps under early stopping: the first strict
    minimum of the validation costs (NaN never improves)."""
    k, best = 0, val_history[0]
    for i, v in enumerate(val_history[1:], 1):
        if v < best:
            k, best = i, v
    return k


def best_of_restarts(model: PGNN, residual, jacobian, n_restarts: int, seed: int, *, val_fn=None,
                     progress=None, on_iteration=None, memo=None, screen_iter: int = 0,
                     **lm_options) -> tuple[list[RestartResult], int]:
    """LM from ``n_restarts`` random NN initialisations ([B1] §VI: best of 10): restart i is
    seeded by SeedSequence([seed, i]), θ_phy starts where the model holds it; the lowest training
    cost is loaded into ``model``. Returns every restart and the index of the best.

    ``screen_iter`` (0 < screen_iter < max_iter): every restart runs ``screen_iter`` LM
    iterations, and only the best of them continues (LM again from its θ) up to ``max_iter`` in
    all; the others stay at the screening budget (their stop reason says so).

    Restart i on a budget depends on ``(seed, i)`` only, not on ``n_restarts``:
    ``memo(i, budget, compute)`` (e.g. the stage cache, :meth:`pipeline.runner.StageContext.memo`)
    may return a stored result of it."""
    theta0 = model.parameter_vector()
    max_iter = int(round(int(lm_options.pop("max_iter", 100)) * CAP_FACTOR))   # the tightening check's cap
    screen = 0 < int(screen_iter) < max_iter and n_restarts > 1
    budget = int(screen_iter) if screen else max_iter

    def restart(i: int) -> RestartResult:
        s_i = int(np.random.SeedSequence([seed, i]).generate_state(1)[0])
        model.load_parameter_vector(theta0)
        model.reset_parameters(s_i)
        t0 = time.perf_counter()
        cb = None if on_iteration is None else (lambda it, th, c: on_iteration(i, it, c))
        res: LMResult = levenberg_marquardt(residual, model.parameter_vector(), jacobian=jacobian,
                                            val_cost=val_fn, callback=cb, max_iter=budget, **lm_options)
        return RestartResult(s_i, res.cost, res.val_cost, res.history, res.val_history, res.n_iter,
                             res.message, time.perf_counter() - t0, res.theta)

    out = []
    restarts = range(n_restarts)
    if progress is not None:
        restarts = progress(restarts)
    for i in restarts:
        out.append(restart(i) if memo is None else memo(i, budget, lambda i=i: restart(i)))
    best = int(np.argmin([r.cost for r in out]))
    first = out[best]
    if screen and first.message == "max_iter":     # the kept restart continues to the full budget
        t0 = time.perf_counter()
        # it continues from first.theta: with early stopping the best-validation iterate, not the last one.
        # Its costs up to there are the continued run's past (the statistical window), those after it are dropped
        k = _best_validation_index(first.val_history) if first.val_history else len(first.history) - 1
        cb = None if on_iteration is None else (lambda it, th, c: on_iteration(best, first.n_iter + it, c))
        res = levenberg_marquardt(residual, first.theta, jacobian=jacobian, val_cost=val_fn, callback=cb,
                                  max_iter=max_iter - first.n_iter, stat_history=first.history[:k],
                                  **lm_options)
        out[best] = RestartResult(first.seed, res.cost, res.val_cost, first.history[:k + 1] + res.history[1:],
                                  first.val_history[:k + 1] + res.val_history[1:], first.n_iter + res.n_iter,
                                  res.message, first.seconds + time.perf_counter() - t0, res.theta)
    model.load_parameter_vector(out[best].theta)
    return out, best


# --------------------------------------------------------------------------------------------
# [B1] §II-C: asymptotic bias of the direct inverse of a linear ARX system
# --------------------------------------------------------------------------------------------
def arx_inverse_asymptotics(a, b, sigma_u: float, sigma_v: float):
    """Exact inverse parameters θ0', regressor covariance M and the asymptotic bias (18) of
    the direct-inverse least squares ([B1] (15)-(18)) for the ARX system

        y(t) = Σ a_i y(t-i) + Σ b_i u(t-i) + v(t)      (n_k = 0, white u, white v)

    identified as u(t) ≈ θ'ᵀ φ'(t), φ'(t) = [y(t+1), …, y(t+1-n_a), u(t-1), …, u(t-n_b+1)].

    With s(t) = [y(t), …, y(t-n_a+1), u(t-1), …, u(t-n_b+1)], φ'(t) = [y(t+1); s(t)],
    y(t+1) = c s(t) + b_1 u(t) + v(t+1); the stationary covariance P of s solves a discrete
    Lyapunov equation (scipy), so M = E[φ'φ'ᵀ] is exact, and (18) gives

        lim θ̂' - θ0' = -M⁻¹ E[φ'(t) v(t+1)] / ψ0 = -M⁻¹ [σ_v², 0, …, 0]ᵀ / b_1.

    (the paper prints the sign as +; the minus follows from (15): u = θ0'ᵀφ' - v(t+1)/ψ0.)

    Returns
    -------
    theta_inv : ndarray [n_a + n_b]
        θ0' = [1, -a_1, …, -a_{n_a}, -b_2, …, -b_{n_b}] / b_1.
    bias : ndarray [n_a + n_b]
        Asymptotic bias of the direct-inverse estimate.
    M : ndarray [n_a + n_b, n_a + n_b]
        E[φ'φ'ᵀ].
    """
    a = np.atleast_1d(np.asarray(a, dtype=float))
    b = np.atleast_1d(np.asarray(b, dtype=float))
    n_a, n_b = a.size, b.size
    if n_a < 1 or n_b < 1 or b[0] == 0.0:
        raise ValueError(f"need n_a >= 1, n_b >= 1 and b_1 != 0; got a={a}, b={b}")
    ns = n_a + n_b - 1
    c = np.concatenate([a, b[1:]])
    A = np.zeros((ns, ns))
    B = np.zeros((ns, 2))
    A[0] = c
    B[0] = [b[0], 1.0]  # y(t+1) = c s(t) + b_1 u(t) + v(t+1)
    for i in range(1, n_a):
        A[i, i - 1] = 1.0  # y(t+1-i) shifts down
    if n_b > 1:
        B[n_a, 0] = 1.0  # u(t) enters as the newest input lag
        for i in range(n_a + 1, ns):
            A[i, i - 1] = 1.0
    if np.any(np.abs(np.linalg.eigvals(A)) >= 1.0):
        raise ValueError(f"the ARX system a={a}, b={b} is not stable: no stationary covariance")
    Q = np.diag([sigma_u ** 2, sigma_v ** 2])
    P = solve_discrete_lyapunov(A, B @ Q @ B.T)
    M = np.empty((ns + 1, ns + 1))
    M[0, 0] = c @ P @ c + b[0] ** 2 * sigma_u ** 2 + sigma_v ** 2
    M[0, 1:] = M[1:, 0] = c @ P
    M[1:, 1:] = P
    theta_inv = np.concatenate([[1.0], -a, -b[1:]]) / b[0]
    e = np.zeros(ns + 1)
    e[0] = sigma_v ** 2 / b[0]
    bias = -np.linalg.solve(M, e)
    return theta_inv, bias, M
