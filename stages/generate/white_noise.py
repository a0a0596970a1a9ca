"""data.kind=white_noise: open-loop identification experiment with white input (SPEC §2.4).

u ~ N(0, ``data.u_std``²) for ``data.n_samples`` samples, r = 0; the plant's noise model adds v.
"""
from __future__ import annotations

from typing import Literal

import numpy as np

from pipeline.data import Dataset
from pipeline.params import FORCE_MAX, schema, spec


@schema
class Params:
    kind: Literal["white_noise"]
    name: str = "white_noise"
    # N, number of samples
    n_samples: int = spec(10000, ge=10, le=10**7, rule="give an integer >= 10 and <= 10^7 (shorter is too short to "
                          "identify from; longer takes more than 80 MB per signal)")
    # [input unit] standard deviation of u
    u_std: float = spec(1.0, ge=0, le=FORCE_MAX, unit="input units")


def make(cfg, system, ctx) -> Dataset:
    n = int(cfg.data.n_samples)
    rng = ctx.rng("data/white_noise")
    u = float(cfg.data.u_std) * rng.standard_normal(n)
    v = system.noise(n, rng)
    sim = system.simulate(np.zeros(n), u_ff=np.zeros(n), du=u, v=v).as_dict()
    sim["t"] = np.arange(n) * system.Ts
    return Dataset.from_segments([sim], {"Ts": system.Ts})
