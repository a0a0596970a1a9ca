"""identify.kind=none: no training; downstream stages use the physics baseline."""


def fit(ctx) -> dict:
    return {"model": None}
