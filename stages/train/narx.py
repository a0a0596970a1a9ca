"""identify.kind=narx: PGNN identification from one-step (NARX) residuals, [B1] §II-B, §V-B.

The criterion follows from ``model.structure``: forward → [B1] (12), inverse (direct-inverse
PGNN) → [B1] (14), invertible → [B1] (29) (ψ not regularised), physics-only → [B1] (7).
The physics part is the plant's nominal physics model (``pipeline.models.pgnn.
physics_features_for``).  If the plant's physics model takes a transformed input w =
``physics.model_input(u)`` (the averaged ū of the continuous linear motor, SPEC §2.2), the
PGNN is identified on (y, w) and the inversions turn w back into u with
``physics.applied_input``.

On a measured system (:class:`pipeline.systems.measured.Recording`) θ*_phy is the physics
baseline (the filtered inverse-model least squares): the one-step LS on a quantised position
record is dominated by the encoder step.

Logged: the loss curve of every restart (``train/loss/restart<i>`` per accepted LM step, and
``train/val_loss/restart<i>``), the best restart's cost and seconds, θ*_phy and θ̂_phy as
physical parameters.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from omegaconf import OmegaConf

from pipeline.errors import ConfigError
from pipeline.identify.narx import identify_pgnn
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import physics_features_for
from pipeline.params import COUNT_MAX, ITER_MAX, schema, spec
from pipeline.plots import pyplot
from stages.train import check_rows, init_seed, l2_lam, lm_progress, log_restarts, restart_memo, restart_options


@schema
class Params:
    kind: Literal["narx"]
    name: str = "narx"
    # random NN initialisations, lowest training cost kept ([B1] §VI: 10)
    n_restarts: int = spec(10, ge=1, le=COUNT_MAX)
    # safety cap on LM damped solves of the kept restart: fits stop on ftol/gtol/stat
    max_iter: int = spec(2000, ge=0, le=ITER_MAX)
    # every restart runs 50 LM steps, only the best continues to its stop (0: all run to their stop)
    screen_iter: int = spec(50, ge=0, le=ITER_MAX)
    # stop on relative cost change below this
    ftol: float = spec(1e-10, ge=0, lt=1)
    # stop on scaled gradient (cosine) below this
    gtol: float = spec(1e-10, ge=0, lt=1)
    # initial LM damping, relative to the scaled JᵀJ diagonal
    mu0: float = spec(1e-3, gt=0, le=1e12)
    # contiguous validation block at the end of the record (early stopping); 0 = off
    val_fraction: float = spec(0.2, ge=0, lt=1)
    # accepted LM steps without validation improvement before stopping (the validation MSE moves in its 4th digit per
    # step on noisy data: a short patience stops on noise)
    patience: int = spec(20, ge=1, le=ITER_MAX)
    # geodesic acceleration (Transtrum & Sethna) in the LM: off here, measured (issue 19) on the b1 noise sweep at
    # sigma=1e-7 it cost 1.4x the CPU of plain LM (42.7 vs 30.0 s) to the same stop
    geodesic: bool = False
    # statistical stop: the cost fell by <= stat_tol·sqrt(2/N)·C over the last stat_window accepted
    stat_window: int = spec(10, ge=0, le=ITER_MAX)
    # steps (below the cost's sampling fluctuation: converged on noisy data); 0 = off
    stat_tol: float = spec(0.1, ge=0, le=100)
    # window of the statistical stop grows with the run (0: fixed; see conf/identify/sim_error.yaml)
    stat_frac: float = spec(0.0, ge=0, lt=1)
    # the statistical stop's promise: gauss_newton | damped | auto (as identify=sim_error: stages/train/sim_error.py)
    stat_promise: Literal["auto", "gauss_newton", "damped"] = "auto"


VERSION = 4   # 2: the statistical window spans a continued restart's screening steps (issue 19); 3: stat_promise;
              # 4: a screened restart continues from its best-validation iterate with the costs before it as its past

STRUCTURES = ("forward", "inverse", "invertible")


def _model_cfg(cfg) -> dict:
    m = OmegaConf.to_container(cfg.model, resolve=True)
    m.pop("name", None)
    return m


def check(cfg, system) -> None:
    """The model against the plant (types and ranges of model.* and identify.*: pipeline.schema)."""
    m = _model_cfg(cfg)
    if "structure" not in m:
        raise ConfigError(f"identify.kind=narx trains a PGNN; model={m.get('name')!r} is not one (use model=pgnn)")
    if system is not None and m["use_physics"]:
        try:
            build_model(cfg, system)
        except ValueError as exc:
            raise ConfigError(f"model: {exc}") from exc


def uses_model_input(system) -> bool:
    """True when the physics model's input w differs from u (averaged input)."""
    return bool(getattr(system.physics, "averaged_input", False))


def build_model(cfg, system) -> PGNN:
    m = _model_cfg(cfg)
    structure = m.pop("structure")
    phys = None
    if m["use_physics"]:
        phys = physics_features_for(system.physics, structure, m["n_a"], m["n_b"], m["n_k"],
                                    input_is_model_input=uses_model_input(system))
    m["hidden"] = tuple(m["hidden"])
    return PGNN(structure=structure, physics=phys, seed=init_seed(cfg), **m)


def fit(ctx) -> dict:
    cfg, system = ctx.cfg, ctx.system
    model = build_model(cfg, system)
    ds = ctx.inputs["generate"]["dataset"]
    ys, us = [], []
    for seg in ds.segments():
        y, u = seg["y"].to_numpy(np.float64), seg["u"].to_numpy(np.float64)
        if uses_model_input(system):
            u = system.physics.model_input(u)  # w = ū (SPEC §2.2 sampling pitfall)
        ys.append(y)
        us.append(u)
    ident = cfg.identify
    check_rows(model, sum(len(y) for y in ys), float(ident.val_fraction))
    lam = l2_lam(cfg)
    fit_ = identify_pgnn(model, ys, us, lam=lam, seed=init_seed(cfg), val_fraction=float(ident.val_fraction),
                         patience=int(ident.patience), **restart_options(ident, system.measured),
                         **lm_progress(ctx), theta_star=ctx.inputs["baseline"]["theta"] if system.measured else None,
                         memo=restart_memo(ctx))
    log_restarts(ctx, fit_.restarts, fit_.best)
    best = fit_.restarts[fit_.best]
    ctx.metric("cost", best.cost)
    if best.val_cost is not None:
        ctx.metric("val_cost", best.val_cost)
    ctx.metric("best_restart", fit_.best)
    ctx.metric("seconds_per_restart", float(np.mean([r.seconds for r in fit_.restarts])))
    ctx.metric("n_params", model.n_params)
    ctx.tag("lm_stop", best.message)
    physical = {}
    if model.use_physics:
        th = model.theta_phy.detach().numpy()
        physical = model.physics.physical(th)
        for k, v in physical.items():
            ctx.metric(f"theta_phy/{k}", v)
        for k, v in model.physics.physical(fit_.theta_phy_star).items():
            ctx.metric(f"theta_phy_star/{k}", v)
    ctx.figure(_loss_figure(fit_), "loss.png")
    model.eval()
    return {"model": model, "model_input": uses_model_input(system),
            "theta_phy_star": fit_.theta_phy_star, "physical": physical,
            "costs": [r.cost for r in fit_.restarts], "best": fit_.best, "sigma": fit_.sigma}


def _loss_figure(fit_):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for i, rr in enumerate(fit_.restarts):
        lw = 2.0 if i == fit_.best else 0.8
        ax.semilogy(rr.history, lw=lw, label=f"restart {i}" if i == fit_.best else None)
        if rr.val_history:
            ax.semilogy(rr.val_history, lw=lw, ls=":", color=ax.lines[-1].get_color())
    ax.set_xlabel("accepted LM step")
    ax.set_ylabel("normalised cost")
    ax.set_title("LM loss per restart (solid: training criterion, dotted: validation MSE)",
                 fontsize=8)
    ax.legend(fontsize=7)
    return fig
