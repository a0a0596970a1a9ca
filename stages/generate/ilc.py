"""data.kind=ilc: learn each reference's optimal input by norm-optimal ILC on the true plant
(SPEC §4), then record the closed-loop experiment with that input as ``u_ff`` and ``f_opt``.

The learning model is the plant's linear part seen by the feedforward
(:meth:`System.learning_model`); the error per trial is logged (``ilc/<ref>/rms``, step =
trial) and drawn.
"""
from __future__ import annotations

from dataclasses import field
from typing import Literal

import numpy as np

from pipeline import plots
from pipeline.data import Dataset
from pipeline.errors import ConfigError
from pipeline.invert.ilc import make_update, norm_optimal_ilc, system_trial
from pipeline.params import COUNT_MAX, NOISE_MAX, schema, spec
from stages._common import check_references, reference_specs
from stages.generate.closed_loop import Params as ClosedLoopParams
from stages.generate.closed_loop import check as check_closed_loop


@schema
class Ilc:
    # maximum number of trials (runs of the true plant)
    trials: int = spec(30, ge=1, le=COUNT_MAX)
    # learning gain L in (0, 2): f_{j+1} = f_j + L Δf
    gain: float = spec(1.0, gt=0, lt=2, rule="the learning gain must be in (0, 2)")
    # weight of ‖f‖², relative to σ_max(G)² (SPEC §2.3)
    w_rel: float = spec(0.0, ge=0, le=1e6)
    # weight of ‖f_{j+1} − f_j‖², relative to σ_max(G)² (SPEC §2.3: ≤ 1e-10)
    w_delta_rel: float = spec(0.0, ge=0, le=1e6)
    # [m] stop at this rms tracking error
    tol: float = spec(0.0, ge=0, lt=NOISE_MAX, unit="m")
    # lifted (dense, short references) | matrix_free (CG on filters) | auto
    backend: Literal["auto", "lifted", "matrix_free"] = "auto"
    # trials see the plant's noise model (seeded)
    noise: bool = True


@schema
class Params(ClosedLoopParams):
    kind: Literal["ilc"]
    name: str = "ilc"
    ilc: Ilc = field(default_factory=Ilc)


def check(cfg, system) -> None:
    check_closed_loop(cfg, system)
    try:
        system.learning_model()
    except NotImplementedError as exc:
        raise ConfigError(f"data=ilc: {exc}") from exc


def make(cfg, system, ctx) -> Dataset:
    p = cfg.data.ilc
    refs = check_references(reference_specs(cfg.data.references), system)
    model = system.learning_model()
    parts, curves = [], {}
    for name, r in ctx.progress(refs.items(), desc="ILC", total=len(refs)):
        rng = ctx.rng(f"data/{name}")
        update = make_update(model, r.size, backend=str(p.backend))
        s2 = update.sigma_max ** 2  # weights relative to σ_max(G)² (SPEC §2.3)
        update.set_weights(float(p.w_rel) * s2, float(p.w_delta_rel) * s2)
        res = norm_optimal_ilc(system_trial(system, r, rng if p.noise else None), None, r.size,
                               gain=float(p.gain), n_trials=int(p.trials), tol=float(p.tol),
                               update=update, progress=True)
        for i, e in enumerate(res.rms):
            ctx.metric(f"ilc/{name}/rms", e, step=i)
        ctx.metric(f"ilc/{name}/final_rms", res.rms[-1])
        curves[name] = np.asarray(res.rms)
        f = res.f
        v = system.noise(r.size, rng)
        sim = system.simulate(r, u_ff=f, v=v).as_dict()
        sim.update(f_opt=f, t=np.arange(r.size) * system.Ts)
        parts.append(sim)
    ctx.figure(plots.trials(curves, title=f"{system.name}: ILC error per trial"), "ilc_trials.png")
    return Dataset.from_segments(parts, {"Ts": system.Ts, "references": list(refs)})
