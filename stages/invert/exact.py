"""invert.kind=exact: the simulator's exact optimal input (only where the plant knows it)."""
from typing import Literal

import numpy as np

from pipeline.errors import ConfigError
from pipeline.params import schema


@schema
class Params:   # nothing to set
    kind: Literal["exact"]
    name: str = ""


def check(cfg, system) -> None:
    try:
        system.exact_inverse(np.zeros(8))
    except NotImplementedError as exc:
        raise ConfigError(f"invert.kind=exact: {exc}") from exc


def feedforward(ctx, name, r):
    return ctx.system.exact_inverse(r)
