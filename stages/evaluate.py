"""evaluate: run the true plant with each feedforward and score the tracking (SPEC §7).

``evaluate.noise``: false = noise-free evaluation runs (B1b); true = the plant's noise model,
seeded by the config.  Metrics ``evaluate/<reference>/<metric>`` (mae, max_abs, norm2,
sq_norm2, rms, ff_error where the optimal input is known; the peak per motion phase
max_abs_accel|constvel|standstill, and with a known optimal input the feedforward's force error
per phase ff_rms_<phase>); a figure of the tracking errors, and artifact
``evaluate/errors.npz`` (t, and r and e per reference) for figures across runs.
"""
from __future__ import annotations

import numpy as np

from pipeline import plots
from pipeline.metrics import phase_ff_errors, phase_peaks, tracking_metrics

UPSTREAM = ("invert",)
DEPENDS = ("system", "evaluate", "seed")
VERSION = 3   # 2: per-phase peaks, errors.npz artifact; 3: per-phase feedforward force error


def optimal_input(system, r):
    """The exact optimal input where the simulator knows it, else None."""
    try:
        return system.exact_inverse(r)
    except NotImplementedError:
        return None


def run(ctx) -> dict:
    inv = ctx.inputs["invert"]
    system = ctx.system
    out, errors = {}, {}
    for name, r in inv["r"].items():
        u_ff = inv["u_ff"][name]
        v = system.noise(r.size, ctx.rng(f"evaluate/{name}")) if ctx.cfg.evaluate.noise else None
        sim = system.simulate(r, u_ff=u_ff, v=v)
        f_opt = optimal_input(system, r)
        m = tracking_metrics(r, sim.y_clean, f_opt, u_ff if f_opt is not None else None)
        m |= phase_peaks(r, sim.y_clean)
        if f_opt is not None:
            m |= phase_ff_errors(r, f_opt, u_ff)
        for k, val in m.items():
            ctx.metric(f"{name}/{k}", val)
        t = np.arange(r.size) * system.Ts
        errors[name] = (t, r - sim.y_clean)
        out[name] = {"y": sim.y_clean, "u": sim.u, "u_ff": u_ff, "e": r - sim.y_clean, **m}
    ctx.figure(plots.tracking_errors(errors, f"{system.name}: {ctx.cfg.invert.name} feedforward"),
               "tracking_error.png")
    np.savez_compressed(ctx.artifact("errors.npz"), Ts=system.Ts,
                        **{f"{k}/{x}": v for k, (t, e) in errors.items()
                           for x, v in (("r", inv["r"][k]), ("e", e))})
    first = next(iter(inv["r"]))
    t = np.arange(inv["r"][first].size) * system.Ts
    ctx.figure(plots.signals(t, {"u_ff": inv["u_ff"][first], "u": out[first]["u"]}, "input [N]",
                             f"{first}: feedforward and total input"), "feedforward.png")
    return {"per_reference": out}
