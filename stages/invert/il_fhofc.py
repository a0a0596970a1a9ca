"""invert.kind=il_fhofc: iterative-learning FHOFC on the true plant, [B2] (22) (SPEC §6, §8 B2c).

Trial i = 0 applies the FHOFC feedforward of the identified model; after each trial the
target becomes R^(i+1) = Ŷ^(i) + α E^(i) and FHOFC is solved again (``invert.alpha``,
``invert.gamma``, ``invert.n_trials`` runs of the plant).  ``invert.trial_noise``: the plant's
measurement noise in every trial (a fresh seeded draw per trial) or none (v = 0).

Metrics per reference, ``step`` = trial: ``invert/<ref>/trial_rms`` (rms of the measured
error R - Y, [B2] Fig. 5), ``invert/<ref>/trial_rms_clean`` (R - y_clean) and the FHOFC
inversion error; with noise also ``invert/<ref>/ideal_rms``: the same noise realisation with
the ideal feedforward (norm-optimal ILC converged on the noise-free plant, SPEC §2.3), the
noise floor of B2c.  Returns the last trial's feedforward (the evaluate stage runs it once more).
"""
from __future__ import annotations

from typing import Literal

import numpy as np

from pipeline.errors import ConfigError
from pipeline.invert.fhofc import il_fhofc
from pipeline.invert.ilc import norm_optimal_ilc, system_trial
from pipeline.models.closed_loop import DiscreteController
from pipeline.params import COUNT_MAX, schema, spec
from pipeline.plots import pyplot
from stages.export import table_laws
from stages.invert.fhofc import Params as FhofcParams
from stages.invert.fhofc import check as check_fhofc


@schema
class Params(FhofcParams):
    kind: Literal["il_fhofc"]
    name: str = "il_fhofc"
    # γ [m/N] of Γ = γΔ ([B2] Fig. 5: 1e-8)
    gamma: float = spec(1e-8, ge=0, le=1.0, unit="m/N")
    # learning gain α in (0, 1] ([B2] Fig. 5: 1)
    alpha: float = spec(1.0, gt=0, le=1, rule="the learning gain must be in (0, 1]")
    # plant runs, trial 0 = FHOFC of the identified model (B2c: i = 0..6)
    n_trials: int = spec(7, ge=1, le=COUNT_MAX)
    # measurement noise of the plant in every trial (false: v = 0)
    trial_noise: bool = False
    # noise floor: norm-optimal ILC input weight / σ_max(G)² (SPEC §2.3: <= 1e-10)
    ideal_w_rel: float = spec(1e-10, ge=0, le=1.0)
    # ILC trials for the ideal feedforward (noise-free plant)
    ideal_trials: int = spec(12, ge=1, le=COUNT_MAX)


def check(cfg, system) -> None:
    check_fhofc(cfg, system)
    inv = cfg.invert   # alpha, n_trials: pipeline.schema
    if inv.get("horizon") is not None:
        raise ConfigError("invert.kind=il_fhofc solves the full-horizon FHOFC; set invert.horizon=null")


def ideal_feedforward(ctx, r) -> tuple[np.ndarray, float]:
    """The optimal input of r on the noise-free plant by norm-optimal ILC (pipeline.invert.ilc)
    and the rms error of its last trial [m] (how ideal it is)."""
    inv = ctx.cfg.invert
    res = norm_optimal_ilc(system_trial(ctx.system, r), ctx.system.learning_model(), r.size,
                           w_delta=0.0, w_rel=float(inv.ideal_w_rel), n_trials=int(inv.ideal_trials),
                           backend="lifted")
    return res.f, float(res.rms[-1])


def feedforward(ctx, name, r):
    inv = ctx.cfg.invert
    system = ctx.system
    model = ctx.inputs["train"]["arx"]
    ctrl = DiscreteController.from_tf(system.controller())
    n_trials = int(inv.n_trials)
    rng = ctx.rng(f"il_fhofc/{name}")
    noises = [system.noise(r.size, rng) if inv.trial_noise else np.zeros(r.size) for _ in range(n_trials)]
    clean = []

    def plant(u_ff, _it=iter(range(n_trials))):
        sim = system.simulate(r, u_ff=u_ff, v=noises[next(_it)])
        clean.append(sim.y_clean)
        return sim.y

    bar = ctx.progress(None, desc=f"IL-FHOFC trials on '{name}'", total=n_trials)   # a manual bar

    def advance(i, e_rms):
        bar.set_postfix(rms=f"{e_rms:.3e}", refresh=False)
        bar.update(1)
    out = il_fhofc(model, ctrl, r, plant, n_trials=n_trials, alpha=float(inv.alpha), gamma=float(inv.gamma),
                   max_iter=int(inv.max_iter), ftol=float(inv.ftol), check_range=bool(inv.check_range),
                   range_margin=float(inv.range_margin), callback=advance)
    bar.close()
    for i in range(n_trials):
        ctx.metric(f"{name}/trial_rms", out.e_rms[i], step=i)
        ctx.metric(f"{name}/trial_rms_clean", float(np.sqrt(np.mean((r - clean[i]) ** 2))), step=i)
        ctx.metric(f"{name}/inversion_error", out.inversion_error[i], step=i)
        if not out.solver[i].converged:
            ctx.tag(f"fhofc_fallback_{name}_trial{i}", out.solver[i].message)
    if inv.trial_noise:
        f_opt, rms_opt = ideal_feedforward(ctx, r)
        ctx.metric(f"{name}/ideal_noise_free_rms", rms_opt)
        for i in range(n_trials):
            y = system.simulate(r, u_ff=f_opt, v=noises[i]).y
            ctx.metric(f"{name}/ideal_rms", float(np.sqrt(np.mean((r - y) ** 2))), step=i)
    ctx.figure(_figure(out.e_rms, name), f"il_fhofc_{name}.png")
    return out.u_ff[-1]


def _figure(e_rms, name):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.semilogy(np.arange(e_rms.size), e_rms, "o-")
    ax.set_xlabel("trial i")
    ax.set_ylabel("rms(R - Y^(i)) [m]")
    ax.set_title(f"IL-FHOFC on '{name}' ([B2] (22))", fontsize=9)
    ax.grid(True, which="both", lw=0.3)
    return fig


# ---- export (stages/export.py asks this module): one table per reference, optimised offline for it
def export_laws(ctx) -> dict:
    return table_laws(ctx, "il_fhofc")
