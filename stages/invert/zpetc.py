"""invert.kind=zpetc: zero-phase-error tracking feedforward of the identified linear physics model,
a stable approximate inverse for nonminimum-phase models (rot_trans_nmp, SPEC §2.3)."""
from typing import Literal

from pipeline.errors import ConfigError
from pipeline.params import schema
from pipeline.systems.arx_bias import ARXPhysics
from pipeline.systems.rot_trans_nmp import zpetc_feedforward


@schema
class Params:   # nothing to set
    kind: Literal["zpetc"]
    name: str = ""


def check(cfg, system) -> None:
    if not isinstance(system.physics, ARXPhysics):
        raise ConfigError(f"invert.kind=zpetc needs a linear ARX physics model; system "
                          f"'{system.name}' has {type(system.physics).__name__}")


def feedforward(ctx, name, r):
    return zpetc_feedforward(ctx.system.physics, ctx.inputs["baseline"]["theta"], r)
