"""baseline: least-squares identification of the plant's nominal physics model (SPEC §3, §5).

Simulated plants: column-scaled LS of the one-step model.  Measured systems
(:class:`pipeline.systems.measured.Recording`): the filtered inverse-model LS of the EMPS
benchmark (``system.idim``), with the relative deviation from the published parameters where
the system config gives them.  Physical parameters that must be positive (masses, stiffnesses,
friction, damping) and come out negative are a warning: run tag ``physics_warning`` (the report
shows it) and a Python warning, because the physics model does not fit the data.  On a measured
system the least-squares residual is also searched for a force term the config lacks (velocity,
velocity sign, offset, a force linear or polynomial in position, a quadratic drag, a position-periodic
cogging force at any period): one that would explain ≥ 20 % of the residual's energy is named, with its
config key (tag ``physics_missing_term``).  ``coulomb_width: auto`` is chosen here, on the training
records' tails, and handed to the later stages (:func:`adopt`); a ``sign`` Coulomb term that a smooth
one would beat is hinted at (tag ``physics_coulomb_hint``).
"""
from __future__ import annotations

import warnings

import numpy as np

from omegaconf import OmegaConf

from pipeline.errors import ConfigError
from pipeline.identify.least_squares import fit_physics
from pipeline.systems.coulomb_width import HOLD_OUT, SMOOTH_SHARE

UPSTREAM = ("generate",)
DEPENDS = ("system", "identify.val_fraction")
VERSION = 3   # 2: residual diagnostics of measured systems; 3: spring, position_poly, drag in the scan, the
              # Coulomb width chosen from data (auto) or hinted (issue 49)
#: physical parameters that cannot be negative (masses, stiffnesses, friction and damping)
POSITIVE = ("m", "M", "m1", "m2", "k", "k1", "k2", "c", "d2", "f_v", "F_v", "f_c", "F_c", "F_d")


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
    result = {}
    try:
        if system.measured:   # each recording filtered on its own (data.files)
            ys, us = zip(*[(g["y"].to_numpy(np.float64), g["u"].to_numpy(np.float64)) for g in ds.segments()])
            result = _auto_width(ctx, list(ys), list(us))
            physics = system.physics
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
        hinted = _smooth_hint(ctx, list(ys), list(us))
        diag, found = system.missing_terms(list(ys), list(us))
        for k, v in diag.items():
            ctx.metric(f"residual/{k}", v)
        if found:
            msg = (f"the physics of '{system.name}' leaves {100 * diag['residual_rel']:.1f} % of the force "
                   "unexplained and it is structured: " + "; ".join(found)
                   + ("; but first smooth the Coulomb term (tag physics_coulomb_hint): a sign term's error leaks "
                      "into the others" if hinted else ""))
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
    out = {"theta": theta, "physical": physical, **result}
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


def _auto_width(ctx, ys, us) -> dict:
    """``coulomb_width: auto``: the width of least held-out force error on the training records' tails
    (``identify.val_fraction``, or 0.2; pipeline.systems.coulomb_width), given to the system for every later
    stage (:func:`adopt`), metric and tag ``coulomb_width_chosen``."""
    system = ctx.system
    if not system.physics.terms.auto_width:
        return {}
    c = system.choose_coulomb_width(ys, us, _val_fraction(ctx))
    system.use_coulomb_width(c["width"])
    ctx.metric("coulomb_width_chosen", c["width"])
    ctx.metric("coulomb_width_val_force_rel_error", 100 * c["error"])
    ctx.tag("coulomb_width_chosen", f"{c['width']:.4g} m/s (held-out force error {100 * c['error']:.2f} %, "
                                    f"sign {100 * c['error_sign']:.2f} %)")
    return {"coulomb_width": c["width"]}


def _smooth_hint(ctx, ys, us) -> bool:
    """A ``sign`` Coulomb term: the same search; a hint (warning, tag ``physics_coulomb_hint``) when a smooth
    width would explain ≥ 20 % of its held-out residual (a diagnosis: data it cannot use give no hint).
    Returns whether it hinted."""
    system = ctx.system
    terms = system.physics.terms
    if "coulomb" not in terms.names or terms.coulomb_width is not None:
        return False
    try:
        c = system.choose_coulomb_width(ys, us, _val_fraction(ctx))
    except ValueError:
        return False
    ctx.metric("residual/smooth_coulomb", c["share"])
    ctx.metric("residual/smooth_coulomb_width", c["width"])
    if c["share"] >= SMOOTH_SHARE:
        msg = (f"the sign Coulomb term of '{system.name}' fits poorly: a smooth one, coulomb_width ≈ "
               f"{c['width']:.3g} m/s, would explain {100 * c['share']:.0f} % of its held-out residual force "
               f"(error {100 * c['error_sign']:.2f} % → {100 * c['error']:.2f} %): set "
               f"system.force_terms.coulomb_width={c['width']:.3g} (or auto)")
        ctx.tag("physics_coulomb_hint", msg)
        warnings.warn(msg, stacklevel=1)
        return True
    return False


def _val_fraction(ctx) -> float:
    """The held-out tail of each training record: ``identify.val_fraction`` when the identification has one
    (> 0), else :data:`~pipeline.systems.coulomb_width.HOLD_OUT`."""
    return float(OmegaConf.select(ctx.cfg, "identify.val_fraction") or 0.0) or HOLD_OUT


def adopt(system, result: dict) -> None:
    """After the baseline (computed or cached): the chosen Coulomb width goes to the system, so train,
    invert, evaluate and export use it (``coulomb_width: auto``)."""
    w = result.get("coulomb_width")
    if w is not None and getattr(system, "measured", False) and system.physics.terms.auto_width:
        system.use_coulomb_width(w)
