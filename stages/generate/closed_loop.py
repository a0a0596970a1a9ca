"""data.kind=closed_loop: the plant in its loop on each reference, with excitation Δu (SPEC §4).

``data.references``: reference specs (one segment each); ``data.excitation``: white Δu of std
``std`` [N] inside the time window [``t_start``, ``t_stop``] s (null = whole record);
``data.feedforward``: ``none`` or ``exact`` (the simulator's exact inverse as u_ff).
"""
from __future__ import annotations

from dataclasses import field
from typing import Any, Literal, Optional

import numpy as np

from pipeline.data import Dataset
from pipeline.errors import ConfigError
from pipeline.params import FORCE_MAX, references_rule, schema, spec
from stages._common import check_references, reference_specs


@schema
class Excitation:
    # [N] standard deviation
    std: float = spec(0.0, ge=0, le=FORCE_MAX, unit="N")
    # [s] excitation window start (null = from 0)
    t_start: Optional[float] = spec(None, ge=0, le=1e7, unit="s", example=10.0)
    # [s] excitation window end (null = to the end)
    t_stop: Optional[float] = spec(None, ge=0, le=1e7, unit="s", example=40.0)


@schema
class Params:
    kind: Literal["closed_loop"]
    name: str = "closed_loop"
    # reference specs (pipeline.references.from_spec), one data segment each
    references: Any = spec([], check=references_rule, example="[{name:move,kind:b2_R}]")
    # u_ff during the experiment: none | exact (the simulator's exact inverse)
    feedforward: Literal["none", "exact"] = "none"
    # white input excitation Δu added to the control input
    excitation: Excitation = field(default_factory=Excitation)


def check(cfg, system) -> None:
    specs = reference_specs(cfg.data.references)
    if not specs:
        raise ConfigError("data.references is empty; give at least one reference spec "
                          "(see conf/data/closed_loop.yaml)")
    check_references(specs, system)   # data.feedforward, excitation: pipeline.schema


def excitation(cfg, n: int, Ts: float, rng: np.random.Generator) -> np.ndarray:
    ex = cfg.data.excitation
    du = float(ex.std) * rng.standard_normal(n)
    t = np.arange(n) * Ts
    lo = -np.inf if ex.get("t_start") is None else float(ex.t_start)
    hi = np.inf if ex.get("t_stop") is None else float(ex.t_stop)
    du[(t < lo) | (t >= hi)] = 0.0
    return du


def make(cfg, system, ctx) -> Dataset:
    refs = check_references(reference_specs(cfg.data.references), system)
    parts = []
    for name, r in ctx.progress(refs.items(), desc="closed-loop simulation", total=len(refs)):
        n = r.size
        rng = ctx.rng(f"data/{name}")
        du = excitation(cfg, n, system.Ts, rng)
        v = system.noise(n, rng)
        u_ff = system.exact_inverse(r) if cfg.data.feedforward == "exact" else np.zeros(n)
        sim = system.simulate(r, u_ff=u_ff, du=du, v=v).as_dict()
        if cfg.data.feedforward == "exact":
            sim["f_opt"] = u_ff
        sim["t"] = np.arange(n) * system.Ts
        parts.append(sim)
    return Dataset.from_segments(parts, {"Ts": system.Ts, "references": list(refs)})
