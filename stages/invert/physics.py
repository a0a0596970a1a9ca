"""invert.kind=physics: the analytic inverse of the identified physics model (SPEC §6)."""
from typing import Literal

from pipeline.params import schema


@schema
class Params:   # nothing to set
    kind: Literal["physics"]
    name: str = ""


VERSION = 2   # 2: averaged model input: w(N) is the law's next sample on the held reference (pipeline.export)


def feedforward(ctx, name, r):
    return ctx.system.physics.feedforward(ctx.inputs["baseline"]["theta"], r)
