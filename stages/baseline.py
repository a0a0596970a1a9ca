"""baseline: least-squares identification of the plant's nominal physics model (SPEC §3, §5)."""
from __future__ import annotations

from pipeline.identify.least_squares import fit_physics
from pipeline.runner import ConfigError

UPSTREAM = ("generate",)
DEPENDS = ("system",)
VERSION = 1


def run(ctx) -> dict:
    ds = ctx.inputs["generate"]["dataset"]
    physics = ctx.system.physics
    try:
        theta = fit_physics(physics, ({c: seg[c].to_numpy() for c in ("y", "u", "r")}
                                      for seg in ds.segments()))
    except ValueError as exc:
        raise ConfigError(f"physics baseline of '{ctx.system.name}': {exc}") from exc
    physical = physics.physical(theta)
    for k, v in physical.items():
        ctx.metric(k, v)
    truth = getattr(ctx.system, "true_physical", None)
    if callable(truth):  # where the simulator knows its parameters, report the estimation error
        for k, v in truth().items():
            if k in physical and v != 0:
                ctx.metric(f"rel_error/{k}", abs(physical[k] - v) / abs(v))
    return {"theta": theta, "physical": physical}
