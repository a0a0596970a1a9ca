"""A campaign's model from a finished pipeline run of a measured system (issue 50, ``learn init --run``).

The run's config is composed again as ``pgnn-ff export RUN_ID`` does (pipeline.export.cli: the current
``conf/`` and the run's tag ``overrides``; a stored module name or path is never used), its stages
``generate`` and ``baseline`` are loaded from the cache (or recomputed, bit-identical for the config), and
the campaign's sections are what that run identified and would ship:

- ``Ts``, ``controller``: ``system.Ts`` and ``system.controller`` (gtau, v_sat, delay included);
- ``model``: the baseline's physics θ as physical parameters (M, F_v, F_c, K; the rigid-body model
  M q̈ = τ - F_v q̇ - F_c tanh(q̇/w) - K q of pipeline.learn.update.LoopModel) and the Coulomb width w
  (``system.force_terms.coulomb_width``, or the baseline's choice for ``auto``; none: 0, sign(q̇)), and the
  drive's lag τ (``system.actuator.lag_tau``, or the baseline's for ``auto``; none: 0);
- ``safety.u_max``, ``safety.rate``: the export's guard limits (stages.export.guard_of, rest start).

Terms the campaign's loop model has no place for (offset OF, cogging, gravity, …) are kept in the
campaign's state (``source_run.physical``) and named in :func:`model_of`'s ``dropped``: trial-to-trial
learning absorbs a force that repeats with the reference.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

from omegaconf import OmegaConf

from pipeline import runner, tracking
from pipeline.errors import ConfigError
from pipeline.export.cli import run_config, stored_run
from stages.baseline import adopt
from stages.export import guard_of

__all__ = ["model_of", "MODEL_KEYS"]

#: the physical parameters the campaign's model takes (pipeline.learn.campaign.LearnModel)
MODEL_KEYS = ("M", "F_v", "F_c", "K")


def model_of(run_id: str) -> dict:
    """{"config": the campaign config's Ts, controller, model and safety limits; "physical": every identified
    parameter; "dropped": the ones the campaign's model does not take}, or a one-line ConfigError for an
    unknown run, one not finished, or one not of a measured system (before any work)."""
    run = stored_run(run_id)
    if run.info.status != "FINISHED":
        raise ConfigError(f"run {run_id} is {run.info.status}, not FINISHED: its model may be incomplete; give a "
                          "finished run (make ui lists them) or wait for this one")
    stages = [s for s in run.data.tags.get("stages", "").split(",") if s]
    if "baseline" not in stages:
        raise ConfigError(f"run {run_id} identified no physics (stages={stages}): give a run with the baseline stage")
    cfg = run_config(run)
    target = str(OmegaConf.select(cfg, "system._target_", default=""))
    if not target.endswith("measured.Recording"):
        raise ConfigError(f"run {run_id} is of system {OmegaConf.select(cfg, 'system.name', default='?')!r}, not a "
                          "measured system (system=measured): a campaign learns on a machine's recordings; give a run "
                          "made with your machine's data (README \"Your own machine's data\")")
    cfg.stages = ["generate", "baseline"]
    results = runner.run_job(cfg, run=tracking.JobRun.resume(run_id))   # cached: loads
    base = results["baseline"]
    physical = {k: float(v) for k, v in base["physical"].items()}
    _, system, _ = runner.validate(cfg)
    adopt(system, base)                 # the baseline's chosen Coulomb width, as run_job hands it on
    width = system.physics.terms.coulomb_width       # None: sign(q̇), the campaign's width 0
    model = {k: physical[k] for k in MODEL_KEYS if k in physical}
    model["coulomb_width"] = float(width or 0.0) if "F_c" in physical else 0.0
    if base.get("lag"):                 # the drive's lag the physics has (system.actuator.lag_tau, or auto's τ)
        model["lag_tau"] = float(base["lag"]["tau"])
    ctx = SimpleNamespace(cfg=cfg, system=system, inputs={"generate": results["generate"], "baseline": base})
    guard, _ = guard_of(ctx, "rest")    # the export's limits; the campaign's loop starts from rest at r(0)
    u_max = min(-guard["u_min"], guard["u_max"])
    safety = {k: v for k, v in (("u_max", u_max), ("rate", guard["rate"])) if math.isfinite(v) and v > 0}
    controller = {k: v for k, v in OmegaConf.to_container(cfg.system.controller, resolve=True).items()
                  if v is not None}
    config = {"Ts": float(cfg.system.Ts), "controller": controller, "model": model, "safety": safety}
    dropped = sorted(k for k in physical if k not in MODEL_KEYS and k != "M")
    return {"config": config, "physical": physical, "dropped": dropped}
