"""identify.kind=none: no training; downstream stages use the physics baseline."""
from typing import Literal

from pipeline.params import schema


@schema
class Params:
    kind: Literal["none"]
    name: str = "none"


def fit(ctx) -> dict:
    return {"model": None}
