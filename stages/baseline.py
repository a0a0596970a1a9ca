"""baseline: least-squares identification of the plant's nominal physics model (SPEC §3, §5).

Simulated plants: column-scaled LS of the one-step model.  Measured systems
(:class:`pipeline.systems.measured.Recording`): the filtered inverse-model LS of the EMPS
benchmark (``system.idim``), with the relative deviation from the published parameters where
the system config gives them.  Physical parameters that must be positive (masses, stiffnesses,
friction, damping) and come out negative are a warning: run tag ``physics_warning`` (the report
shows it) and a Python warning, because the physics model does not fit the data.  On a measured
system the least-squares residual is also searched for a force term the config lacks (velocity,
velocity sign, offset, a position-periodic cogging force at any period): one that would explain
≥ 20 % of the residual's energy is named, with its config key (tag ``physics_missing_term``).
"""
from __future__ import annotations

import warnings

import numpy as np

from pipeline.errors import ConfigError
from pipeline.identify.least_squares import fit_physics

UPSTREAM = ("generate",)
DEPENDS = ("system",)
VERSION = 2   # 2: residual diagnostics of measured systems
#: physical parameters that cannot be negative (masses, stiffnesses, friction and damping)
POSITIVE = ("m", "M", "m1", "m2", "k", "k1", "k2", "c", "d2", "f_v", "F_v", "f_c", "F_c")


def nonphysical(physical: dict) -> list[str]:
    """Names (with values) of parameters that must be positive but are not."""
    return [f"{k}={v:.4g}" for k, v in physical.items() if k in POSITIVE and not v > 0]


#: share of the recorded force a measured system's physics fit may leave unexplained before it is
#: flagged as no model of the machine (EMPS: 4 %)
UNUSABLE_RESIDUAL = 0.5


def run(ctx) -> dict:
    ds = ctx.inputs["generate"]["dataset"]
    if getattr(ctx.system, "lag_tau", None) == "auto":
        ctx.system.use_lag(None)       # identified afresh from these data (fit_physics)
    system = ctx.system
    physics = system.physics
    try:
        if system.measured:   # each recording filtered on its own (data.files)
            ys, us = zip(*[(g["y"].to_numpy(np.float64), g["u"].to_numpy(np.float64)) for g in ds.segments()])
            theta = system.fit_physics(list(ys), list(us))
        else:
            theta = fit_physics(physics, ({c: seg[c].to_numpy() for c in ("y", "u", "r")}
                                          for seg in ds.segments()))
    except ValueError as exc:
        raise ConfigError(f"physics baseline of '{system.name}': {exc}") from exc
    physical = physics.physical(theta)
    for k, v in physical.items():
        ctx.metric(k, v)
    bad = nonphysical(physical)
    if bad:
        msg = (f"the physics model of '{system.name}' does not fit these data: {', '.join(bad)} "
               "(must be positive); check the system choice, signs and units")
        ctx.tag("physics_warning", msg)
        warnings.warn(msg, stacklevel=1)
    if system.measured:      # a term the config lacks that the residual still holds
        diag, found = system.missing_terms(list(ys), list(us))
        for k, v in diag.items():
            ctx.metric(f"residual/{k}", v)
        if found:
            msg = (f"the physics of '{system.name}' leaves {100 * diag['residual_rel']:.1f} % of the force "
                   "unexplained and it is structured: " + "; ".join(found))
            ctx.tag("physics_missing_term", msg)
            warnings.warn(msg, stacklevel=1)
        if diag["residual_rel"] > UNUSABLE_RESIDUAL:   # e.g. a prefilter cutoff below the motion's bandwidth
            msg = (f"the physics fit of '{system.name}' leaves {100 * diag['residual_rel']:.0f} % of the force "
                   f"unexplained (M = {physical.get('M', float('nan')):.4g}): it is not a model of this machine. "
                   f"Check system.idim (cutoff_hz={system.idim.get('cutoff_hz')} Hz must pass the motion), "
                   "the force terms, and the signs and units of u and y")
            ctx.tag("physics_warning", msg)
            warnings.warn(msg, stacklevel=1)
    truth = getattr(system, "true_physical", None)
    if callable(truth):  # where the simulator knows its parameters, report the estimation error
        for k, v in truth().items():
            if k in physical and v != 0:
                ctx.metric(f"rel_error/{k}", abs(physical[k] - v) / abs(v))
    published = getattr(system, "published", None)
    if published:       # measured systems: deviation from the published reference model
        for k, v in published.items():
            if k in physical and v != 0:
                ctx.metric(f"rel_error_published/{k}", (physical[k] - v) / abs(v))
    out = {"theta": theta, "physical": physical}
    if system.measured and system.physics.lag is not None:    # the actuator lag (system.actuator.lag_tau)
        lag = dict(getattr(system, "lag_fit", None) or {"tau": system.physics.lag.tau})
        ctx.metric("lag_tau", lag["tau"])
        if "tau_std" in lag:
            ctx.metric("lag_tau_std", lag["tau_std"])
            ctx.metric("lag_residual_share", lag["rss"] / lag["rss_no_lag"])   # of the residual without a lag
            if lag["at_bound"]:
                msg = (f"the actuator lag of '{system.name}' is not identifiable from these data (τ = "
                       f"{lag['tau']:.3g} s at the end of the searched range): set system.actuator.lag_tau "
                       "to the drive's datasheet value, or null")
                ctx.tag("lag_warning", msg)
                warnings.warn(msg, stacklevel=1)
        out["lag"] = lag
    return out
