"""Closed-loop simulation-error identification of the [B2] PGNN, [B2] (16).

The PGNN (30) is simulated in closed loop with the known controller
(:mod:`pipeline.models.closed_loop`: the model as arrays, the simulation and its exact
sensitivities); the normalised simulation error plus the relative physics deviation dᵀΛd is
minimised by Levenberg–Marquardt (:mod:`pipeline.identify.lm`) from several NN
initialisations, θ*_phy (the linear model) identified first.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

# the loop's record kernels (the trajectory kept for the Jacobian at the same θ)
from pipeline.models.closed_loop import (
    ArxPGNN,
    DiscreteController,
    LoopState,
    _cl_sens_theta,
    _cl_simulate_record,
    _prep,
    simulate_closed_loop,
)

__all__ = ["SimErrorFit", "sim_error_criterion", "closed_loop_exogenous", "identify_sim_error"]


# --------------------------------------------------------------------------------------
# closed-loop simulation-error identification, [B2] (16)
# --------------------------------------------------------------------------------------


@dataclass
class SimErrorFit:
    """Result of :func:`identify_sim_error`.

    Attributes
    ----------
    model : PGNN
        The identified module (best restart loaded).
    arx : ArxPGNN
        The same model as arrays (with its validity range), for FHOFC.
    theta_phy_star : ndarray
        θ*_phy, the regulariser centre (linear model identified first).
    sigma : float
        std of Y^d on the training samples [m] (residual normalisation).
    identification_error : float
        ‖Y^d - Ŷ^d‖/sqrt(N_d) over the whole record [m] ([B2] (15) term).
    y_hat : ndarray
        Ŷ^d = Φ̂(θ̂, x0, R^d, U_ff^d) [m].
    restarts : list of RestartResult
        One LM run per initialisation (``pipeline.identify.narx.RestartResult``).
    best : int
        Index of the kept restart (lowest training cost).
    n_train, n_val : int
        Samples in the training residual and in the validation block.
    """

    model: object
    arx: ArxPGNN
    theta_phy_star: np.ndarray
    sigma: float
    identification_error: float
    y_hat: np.ndarray
    restarts: list = field(default_factory=list)
    best: int = 0
    n_train: int = 0
    n_val: int = 0
    linear_stop: str = ""       # stop reason of θ*_phy's fit (closed_form, given, or the LM's)

    @property
    def cost(self) -> float:
        return self.restarts[self.best].cost


def sim_error_criterion(arx0: ArxPGNN, ctrl: DiscreteController, r, u_ex, y, theta_star_phy, lam=1.0,
                        train_slice: slice | None = None, sigma: float | None = None):
    """Residual and exact Jacobian of the normalised closed-loop simulation error [B2] (16).

    ``res(θ) = [(Y^d - Ŷ^d(θ))/(σ sqrt(N_t)) ; R d(θ)]``, d = (θ_phy - θ*_phy)/|θ*_phy|
    (SPEC §5 normalisation), RᵀR = ``lam`` (as in [B1]: [B2]'s ‖Λd‖² with Λ = [I, 0] is lam = 1).
    Ŷ^d is simulated over the whole record from rest; only ``train_slice`` enters the residual.

    Parameters
    ----------
    arx0 : ArxPGNN
        Layout (orders, input map, output scale); its parameters are not used.
    ctrl : DiscreteController
    r, u_ex, y : ndarray
        R^d [m], exogenous input U_ff^d (feedforward plus excitation) [N], Y^d [m].
    theta_star_phy : ndarray
    lam : float, ndarray
        Λ of the quadratic form dᵀΛd (scalar, diagonal or matrix).
    train_slice : slice, optional
    sigma : float, optional
        Residual normalisation (default: std of y on the training slice).

    Returns
    -------
    residual, jacobian : callables θ (ndarray) -> ndarray
    """
    from pipeline.identify.narx import regularizer_sqrt  # lazy: saves 2.8 s of start-up (torch)
    r = np.ascontiguousarray(r, float)
    u_ex = np.ascontiguousarray(u_ex, float)
    y = np.asarray(y, float)
    sl = train_slice or slice(None)
    yt = y[sl]
    if sigma is None:
        sigma = float(np.std(yt))
    if not sigma > 0:
        raise ValueError("the measured output is constant on the training samples; nothing to identify")
    c = 1.0 / (sigma * math.sqrt(yt.shape[0]))
    nphi = arx0.n_phi
    ts = np.asarray(theta_star_phy, float)
    scale = np.abs(ts)
    scale = np.where(scale > 1e-12 * scale.max(), scale, 1.0)
    Rs = regularizer_sqrt(lam, nphi) / scale[None, :]
    reg = bool(np.any(Rs != 0))
    P = arx0.n_params
    # The trajectory (ŷ, û, hidden tanh) of the last simulated θ: LM evaluates the Jacobian at the
    # θ whose residual it has just accepted, so the sensitivities reuse that simulation (ŷ and H
    # are equal to the bit to a fresh one; any other θ is simulated anew).
    N = r.shape[0]
    rows = range(N)[sl]
    traj = {"theta": None, "args": None, "yhat": np.empty(N), "uhat": np.empty(N),
            "H": np.empty((N, arx0.n1))}

    def simulate(theta):
        rr, uu, st, args = _prep(arx0.with_theta(theta), ctrl, r, u_ex, None)
        traj["theta"] = None
        _cl_simulate_record(rr, uu, st.yh, st.uh, st.xc, *args, traj["yhat"], traj["uhat"], traj["H"])
        traj["theta"], traj["args"] = np.array(theta, dtype=np.float64, copy=True), args
        return traj["yhat"]

    def residual(theta):
        yh = simulate(theta)
        e = (yt - yh[sl]) * c
        return np.concatenate([e, Rs @ (theta[:nphi] - ts)]) if reg else e

    def jacobian(theta):
        if traj["theta"] is None or not np.array_equal(traj["theta"], theta):
            simulate(theta)
        st = LoopState.rest(arx0, ctrl)
        M = len(rows)
        if rows.step == 1:
            # rows of the training slice written as -c ∂ŷ/∂θ straight into the result, the
            # regulariser rows below them: no N×p temporaries, no copies
            J = np.empty((M + nphi if reg else M, P))
            _cl_sens_theta(traj["H"], traj["yhat"], traj["uhat"], st.yh, st.uh, *traj["args"], J,
                           rows.start, rows.stop, -c)
        else:
            Jf = np.empty((N, P))
            _cl_sens_theta(traj["H"], traj["yhat"], traj["uhat"], st.yh, st.uh, *traj["args"], Jf, 0, N, 1.0)
            J = np.empty((M + nphi if reg else M, P))
            np.multiply(Jf[sl], -c, out=J[:M])
        if reg:
            J[M:] = 0.0
            J[M:, :nphi] = Rs
        return J

    return residual, jacobian


def closed_loop_exogenous(u, u_fb) -> np.ndarray:
    """Exogenous input of the loop, u - u_fb = u_ff + excitation [N] (data columns)."""
    return np.asarray(u, float) - np.asarray(u_fb, float)


def identify_sim_error(model, ctrl: DiscreteController, r, u_ex, y, u=None, *, lam=1.0, theta_star="arx",
                       n_restarts: int = 1, seed: int = 0, val_fraction: float = 0.0, max_iter: int = 100,
                       ftol: float = 1e-10, gtol: float = 1e-10, mu0: float = 1e-3, patience: int = 5,
                       linear_max_iter: int = 50, geodesic: bool = False, stat_window: int = 0,
                       stat_tol: float = 0.1, stat_frac: float = 0.0, progress: Callable | None = None,
                       on_iteration: Callable | None = None, memo: Callable | None = None,
                       screen_iter: int = 0, stat_promise: str = "gauss_newton") -> SimErrorFit:
    """Closed-loop simulation-error identification of a PGNN, [B2] (16), by Levenberg–Marquardt.

    Steps: θ*_phy (the linear model identified first), NN input normalisation and output
    scale from the measured regressors, then LM on the normalised criterion
    (:func:`sim_error_criterion`) with the exact Jacobian of the recurrent closed-loop
    simulation (numba forward sensitivities), from ``n_restarts`` NN initialisations
    (θ_phy starts at θ*_phy), keeping the lowest training cost.

    Parameters
    ----------
    model : pipeline.models.pgnn.PGNN
        Forward PGNN with ``LinearFeatures`` physics and one tanh hidden layer (or none: the
        linear model). Modified in place (θ*_phy, normalisation, best parameters).
    ctrl : DiscreteController
        The known feedback controller C(q) (no computational delay).
    r, u_ex, y : ndarray, shape (N_d,)
        R^d [m], exogenous input U_ff^d (feedforward plus excitation, e.g.
        :func:`closed_loop_exogenous`) [N], measured output Y^d [m].
    u : ndarray
        Measured plant input [N] (u = u_fb + u_ff + excitation): the ARX regressors of
        θ*_phy and of the NN input normalisation use the measured y and u.
    lam : float or ndarray
        Λ of the relative physics deviation (quadratic form dᵀΛd; [B2] Λ = [I, 0] → 1).
    theta_star : {'arx', 'sim_error'} or ndarray
        θ*_phy: ``'arx'`` = one-step least squares of the physics model on the measured
        data ([B1] (7)); ``'sim_error'`` = that, refined by closed-loop simulation-error LM of
        the linear model alone (output-error consistent under measurement noise); or given
        (e.g. the plant's true linear part: an oracle).  Without NN (n1 = 0) the model is θ*_phy
        itself, and its one "restart" carries the stop reason of θ*_phy's fit.
    n_restarts, seed : int
        NN initialisations; restart i uses ``SeedSequence([seed, i])`` (as [B1]'s NARX).
    val_fraction : float
        Contiguous tail of the record for early stopping (0 = none); the simulation still
        runs through it.
    max_iter, ftol, gtol, mu0, patience, geodesic, stat_window, stat_tol, stat_frac, stat_promise
        Passed to :func:`pipeline.identify.lm.levenberg_marquardt` (the statistical stop's N is
        the number of training samples; the θ*_phy refinement uses them too).
    linear_max_iter : int
        LM iterations of the ``'sim_error'`` θ*_phy refinement.
    progress : callable, optional
        Wraps the restart iterable.
    on_iteration : callable, optional
        ``on_iteration(restart, it, cost)`` after every accepted LM step.

    Returns
    -------
    SimErrorFit
    """
    import torch  # lazy: saves 2.0 s of start-up (torch)

    from pipeline.identify.lm import levenberg_marquardt  # lazy: saves 2.2 s of start-up (torch)
    from pipeline.identify.narx import (  # lazy: saves 2.5 s of start-up (torch)
        best_of_restarts,
        forward_regressor,
        physics_least_squares,
    )

    y = np.asarray(y, float)
    r = np.asarray(r, float)
    u_ex = np.asarray(u_ex, float)
    N = y.shape[0]
    if r.shape != (N,) or u_ex.shape != (N,):
        raise ValueError(f"r, u_ex and y must be 1-D of one length, got {r.shape}, {u_ex.shape}, {y.shape}")
    if n_restarts < 1:
        raise ValueError(f"n_restarts must be >= 1, got {n_restarts}")
    if not 0.0 <= val_fraction < 0.5:
        raise ValueError(f"val_fraction must be in [0, 0.5), got {val_fraction}")
    n_val = int(round(val_fraction * N))
    train = slice(0, N - n_val)
    if u is None:
        raise ValueError("give the measured plant input u: θ*_phy and the NN normalisation use the "
                         "measured regressors")
    reg = forward_regressor(y[train], np.asarray(u, float)[train], model.n_a, model.n_b, model.n_k)
    if model.n_params > N - n_val:
        raise ValueError(f"{N - n_val} training samples cannot identify {model.n_params} parameters; "
                         "use more data or fewer neurons")
    y_range = (float(y.min()), float(y.max()))
    sigma = float(np.std(y[train]))

    # θ*_phy: the linear model identified first (its fit's stop reason is kept: linear_stop)
    t0 = time.perf_counter()
    linear_stop, linear_history, linear_iter = "given", [], 0
    if isinstance(theta_star, str):
        if theta_star not in ("arx", "sim_error"):
            raise ValueError(f"theta_star must be 'arx', 'sim_error' or an array, got {theta_star!r}")
        ts = physics_least_squares(model, reg.phi, reg.target)  # [B1] (7)
        linear_stop = "closed_form"
        if theta_star == "sim_error":
            lin = ArxPGNN(model.n_a, model.n_b, model.n_k, ts)
            res_l, jac_l = sim_error_criterion(lin, ctrl, r, u_ex, y, ts, 0.0, train, sigma)
            out = levenberg_marquardt(lambda th: torch.from_numpy(res_l(th.numpy())), torch.from_numpy(ts),
                                      jacobian=lambda th: torch.from_numpy(jac_l(th.numpy())),
                                      max_iter=linear_max_iter, ftol=ftol, gtol=gtol, mu0=mu0,
                                      geodesic=geodesic, stat_window=stat_window, stat_tol=stat_tol,
                                      stat_frac=stat_frac, n_data=N - n_val, stat_promise=stat_promise)
            ts = out.theta.numpy().copy()
            linear_stop, linear_history, linear_iter = out.message, out.history, out.n_iter
    else:
        ts = np.asarray(theta_star, float).reshape(-1)
        if ts.shape != (model.n_phi,):
            raise ValueError(f"theta_star must have n_a + n_b = {model.n_phi} entries, got {ts.shape}")
    model.set_physics_estimate(ts)
    if model.use_nn:
        phi_t = torch.as_tensor(reg.phi)
        model.fit_normalisation(phi_t)
        s = float(np.std(reg.target - reg.phi @ ts))
        model.out_scale.fill_(s if s > 0 else sigma)

    arx0 = ArxPGNN.from_pgnn(model, y_range)
    residual, jacobian = sim_error_criterion(arx0, ctrl, r, u_ex, y, ts, lam, train, sigma)
    val_fn = None
    if n_val:
        yv = y[N - n_val:]
        cv = 1.0 / (sigma * math.sqrt(n_val))

        def val_fn(theta):
            yh, _ = simulate_closed_loop(arx0.with_theta(theta.numpy()), ctrl, r, u_ex)
            e = (yv - yh[N - n_val:]) * cv
            return float(e @ e) if np.all(np.isfinite(e)) else math.inf

    res_t = lambda th: torch.from_numpy(residual(th.numpy()))     # noqa: E731
    jac_t = lambda th: torch.from_numpy(jacobian(th.numpy()))     # noqa: E731
    if model.use_nn:
        restarts_out, best = best_of_restarts(model, res_t, jac_t, n_restarts, seed,
                                              val_fn=val_fn, max_iter=max_iter, ftol=ftol, gtol=gtol, mu0=mu0,
                                              patience=patience, progress=progress, on_iteration=on_iteration,
                                              memo=memo, screen_iter=screen_iter, geodesic=geodesic,
                                              stat_window=stat_window, stat_tol=stat_tol, stat_frac=stat_frac,
                                              n_data=N - n_val, stat_promise=stat_promise)
    else:   # the linear model (n1 = 0) is θ*_phy: fitting (16) toward itself would only trade it off
        from pipeline.identify.narx import RestartResult  # lazy: saves 2.7 s of start-up (torch)
        th = model.parameter_vector()
        rr = res_t(th)
        c = float(rr @ rr)
        restarts_out = [RestartResult(seed, c, None if val_fn is None else val_fn(th), linear_history or [c], [],
                                      linear_iter, linear_stop, time.perf_counter() - t0, th)]
        best = 0
    arx = ArxPGNN.from_pgnn(model, y_range)
    y_hat, _ = simulate_closed_loop(arx, ctrl, r, u_ex)
    ident = float(np.linalg.norm(y - y_hat) / math.sqrt(N))
    return SimErrorFit(model, arx, ts, sigma, ident, y_hat, restarts_out, best, N - n_val, n_val, linear_stop)
