"""invert.kind=physics: the analytic inverse of the identified physics model (SPEC §6)."""
from typing import Literal

from pipeline.errors import ConfigError
from pipeline.export import law as laws
from pipeline.params import schema
from stages.export import every_reference


@schema
class Params:   # nothing to set
    kind: Literal["physics"]
    name: str = ""


VERSION = 2   # 2: averaged model input: w(N) is the law's next sample on the held reference (pipeline.export)


def feedforward(ctx, name, r):
    return ctx.system.physics.feedforward(ctx.inputs["baseline"]["theta"], r)


# ---- export (stages/export.py asks this module)
EXPORTS_MEASURED = True   # a measured axis ships its physics feedforward minus the controller's force on y = r


def export_check(cfg, system) -> None:
    if system is not None and not system.measured and \
            getattr(getattr(system, "physics", None), "physics_law", None) != "linear_motor":
        raise ConfigError(f"export: the physics feedforward (8) is exported for the linear motor only, not "
                          f"for system '{system.name}'; drop 'export' from stages")


def export_laws(ctx) -> dict:
    theta = ctx.inputs["baseline"]["theta"]
    if ctx.system.measured:
        law = laws.from_measured_physics(ctx.system.physics, theta, ctx.system.ctrl)
    else:
        law = laws.from_linear_motor_physics(ctx.system.physics, theta)
    return {"ff_physics": (law, every_reference(ctx))}
