"""invert: turn the identified model into a feedforward for each evaluation reference (SPEC §6).

Implementations: ``stages/invert/<kind>.py`` exposing ``feedforward(ctx, name, r) -> u_ff`` (one
reference) and optionally ``check(cfg, system)``.  The references are ``evaluate.references``.
"""
from __future__ import annotations

import time

import numpy as np

from pipeline.runner import ConfigError, implementation
from stages._common import check_references, reference_specs

UPSTREAM = ("generate", "baseline", "train")
DEPENDS = ("invert", "evaluate.references", "evaluate.noise")  # fhofc scores the bound terms on the measured Y
VERSION = 1
KIND_KEY = "invert.kind"


def validate(cfg, system) -> None:
    if not reference_specs(cfg.evaluate.references):
        raise ConfigError("evaluate.references is empty; give at least one reference to design a "
                          "feedforward for (see conf/evaluate/*.yaml)")
    check_references(reference_specs(cfg.evaluate.references), system)
    impl = implementation("invert", str(cfg.invert.kind))
    if hasattr(impl, "check"):
        impl.check(cfg, system)


def run(ctx) -> dict:
    impl = implementation("invert", str(ctx.cfg.invert.kind))
    refs = check_references(reference_specs(ctx.cfg.evaluate.references), ctx.system)
    u_ff = {}
    for name, r in ctx.progress(refs.items(), desc="feedforward", total=len(refs)):
        t0 = time.perf_counter()
        f = np.asarray(impl.feedforward(ctx, name, r), dtype=np.float64)
        ctx.metric(f"{name}/seconds_per_sample", (time.perf_counter() - t0) / r.size)
        if f.shape != r.shape or not np.all(np.isfinite(f)):
            raise ValueError(f"invert.kind={ctx.cfg.invert.kind} returned a feedforward of shape "
                             f"{f.shape} with {int((~np.isfinite(f)).sum())} non-finite values for "
                             f"reference '{name}' (expected {r.shape}, all finite)")
        u_ff[name] = f
    return {"u_ff": u_ff, "r": refs}
