"""train: identify a (PGNN) model, chosen by ``identify.kind`` (SPEC §3, §5).

Implementations: ``stages/train/<kind>.py`` exposing ``fit(ctx) -> dict`` (at least ``model``)
and optionally ``check(cfg, system)``.  ``identify.kind=none`` trains nothing: the physics
baseline is the model.
"""
from __future__ import annotations

from pipeline.runner import implementation

UPSTREAM = ("generate", "baseline")
DEPENDS = ("model", "identify", "regularizer", "seed")
VERSION = 1
KIND_KEY = "identify.kind"


def validate(cfg, system) -> None:
    impl = implementation("train", str(cfg.identify.kind))
    if hasattr(impl, "check"):
        impl.check(cfg, system)


def run(ctx) -> dict:
    return implementation("train", str(ctx.cfg.identify.kind)).fit(ctx)
