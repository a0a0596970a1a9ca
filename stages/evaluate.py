"""evaluate: run the true plant with each feedforward and score the tracking (SPEC §7).

``evaluate.noise``: false = noise-free evaluation runs (B1b); true = the plant's noise model,
seeded by the config.  Metrics ``evaluate/<reference>/<metric>`` (mae, max_abs, norm2,
sq_norm2, rms, ff_error where the optimal input is known; the peak per motion phase
max_abs_accel|constvel|standstill, and with a known optimal input the feedforward's force error
per phase ff_rms_<phase>); a figure of the tracking errors, and artifact
``evaluate/errors.npz`` (t, and r and e per reference) for figures across runs.

Measured systems (:class:`pipeline.systems.measured.Recording`) have no plant to run: every
reference is a recorded file (kind ``measured``), and the identified model is replayed inside the
known controller with the recorded reference and disturbance (``pipeline.identify.measured_loop``)
in both timing conventions, ``data`` and ``published`` (``evaluate.convention`` picks the one of the
figures and of the feedforward tracking; both are always logged): metrics ``<ref>/<convention>/
force_rel_error | position_rel_error | loop_rmse_mm``, and ``<ref>/benchmark_rmse_mm`` (the
benchmark's open-loop simulation: the model driven by the recorded force, first 20 samples only
initialise); the published reference model, where the system
gives it, as ``<ref>/published_model/<convention>/…``; and the feedforward's *model-predicted*
tracking (the identified model in the loop with u_ff added, tag ``feedforward_scoring``) as
``<ref>/model_based/mae|max_abs|rms`` beside the recorded tracking without feedforward
``<ref>/recorded/…``; ``<ref>/data/force_rel_error_tail`` scores the last
``evaluate.validation_tail`` of the record (on the training file: the validation block the
trainings held out, where hyper-parameters are chosen); where the record has a stepped disturbance
(EMPS test pulses), ``data/force_error_share_after_steps`` is the share of the squared force error
within 60 ms after its steps and ``data/force_rel_error_outside_steps`` the error elsewhere.
A measured-data model scored on a simulator is refused unless ``evaluate.allow_simulator=true``,
which tags the run ``evaluated_on``.
"""
from __future__ import annotations

import numpy as np

from pipeline import plots
from pipeline.metrics import phase_ff_errors, phase_peaks, tracking_metrics
from pipeline.errors import ConfigError
from pipeline.systems.measured import Recording

UPSTREAM = ("invert",)
DEPENDS = ("system", "evaluate", "seed")
VERSION = 6   # 2: per-phase peaks, errors.npz artifact; 3: per-phase feedforward force error; 4: measured systems;
              # 5: u_ff in the measured systems' errors.npz; 6: benchmark (open-loop) RMSE


def optimal_input(system, r):
    """The exact optimal input where the simulator knows it, else None."""
    try:
        return system.exact_inverse(r)
    except NotImplementedError:
        return None


def validate(cfg, system) -> None:
    from stages._common import reference_specs
    measured_data = str(cfg.data.get("kind")) == "measured"
    if isinstance(system, Recording):   # evaluate.convention's choices: pipeline.schema
        bad = [s["name"] for s in reference_specs(cfg.evaluate.references) if s.get("kind") != "measured"]
        if bad:
            raise ConfigError(f"system '{system.name}' is a recording: it has no plant to run reference(s) {bad}; "
                              "give evaluate references of kind 'measured' naming a recorded file "
                              "(e.g. evaluate=emps)")
    elif measured_data and not cfg.evaluate.get("allow_simulator", False):
        raise ConfigError(f"the model is identified on measured data ({cfg.data.get('path')}) but system "
                          f"'{system.name}' is a simulator: scoring it there says nothing about the machine the "
                          "data came from. Use the measured system (e.g. system=emps evaluate=emps), or set "
                          "evaluate.allow_simulator=true to do it on purpose (the run is tagged)")


def run(ctx) -> dict:
    inv = ctx.inputs["invert"]
    system = ctx.system
    if isinstance(system, Recording):
        return _run_measured(ctx)
    if str(ctx.cfg.data.get("kind")) == "measured":
        ctx.tag("evaluated_on", f"simulator '{system.name}', not the plant the data came from")
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


# ------------------------------------------------------------------------------------------
# measured systems: replay in the recorded loop
# ------------------------------------------------------------------------------------------
def _run_measured(ctx) -> dict:
    from pipeline.identify.measured_loop import (CONVENTIONS, LoopModel, LoopSignals, benchmark_rmse_mm,
                                                 loop_errors, simulate_loop, simulate_open_loop)
    from stages._common import reference_specs
    from stages.generate.measured import reference
    inv, system, cfg = ctx.inputs["invert"], ctx.system, ctx.cfg
    loop, ctrl = inv["loop"], system.ctrl
    tail = float(cfg.evaluate.get("validation_tail", 0.2))
    main = str(cfg.evaluate.get("convention", "data"))   # of the figures and the feedforward tracking
    published = None
    if system.published_theta() is not None:   # the authors' model in their discretisation (direct input)
        published = LoopModel.physics_only(system.physics.with_direct_input(), system.published_theta())
    ctx.tag("feedforward_scoring", "model-based: the identified model in the recorded loop, not the machine")
    out, errors, force = {}, {}, {}
    for spec in reference_specs(cfg.evaluate.references):
        name = spec["name"]
        ds = reference(cfg, spec, system)
        y, tau, r = ds["y"], ds["u"], ds["r"]
        d = ds["d"] if "d" in ds.frame else np.zeros_like(y)
        sig = LoopSignals(r, d, float(y[0]), ds["t"])
        m = {}
        for conv in CONVENTIONS:
            y_hat, tau_hat, _ = simulate_loop(loop, ctrl, sig, conv)
            m |= {f"{conv}/{k}": v for k, v in loop_errors(y, tau, y_hat, tau_hat).items()}
            if conv == main:
                force[name] = (ds["t"], tau - tau_hat)
            if conv == "data":
                k0 = int(round((1.0 - tail) * y.size))   # the validation tail of a training record
                m["data/force_rel_error_tail"] = float(100 * np.linalg.norm(tau[k0:] - tau_hat[k0:])
                                                       / np.linalg.norm(tau[k0:]))
                m |= _after_disturbance_edges(d, tau, tau_hat, int(round(EDGE_WINDOW / system.Ts)))
            if published is not None:
                yp, tp, _ = simulate_loop(published, ctrl, sig, conv)
                m |= {f"published_model/{conv}/{k}": v for k, v in loop_errors(y, tau, yp, tp).items()}
        y_ol = simulate_open_loop(loop, tau, float(y[0]))       # benchmark convention: vir in, qm out
        m["benchmark_rmse_mm"] = benchmark_rmse_mm(y, y_ol)
        u_ff = inv["u_ff"][name]
        sig_ff = LoopSignals(r, d, float(y[0]), ds["t"], u_ff)
        y_ff, _, _ = simulate_loop(loop, ctrl, sig_ff, main)
        m |= {f"model_based/{k}": v for k, v in _tracking(r, y_ff).items()}
        m |= {f"recorded/{k}": v for k, v in _tracking(r, y).items()}
        for k, val in m.items():
            ctx.metric(f"{name}/{k}", val)
        errors[name] = (ds["t"], r - y_ff)
        out[name] = {"y_hat": y_ff, "u_ff": u_ff, **m}
    ctx.figure(plots.tracking_errors(force, f"{system.name}: recorded force - model force in the loop "
                                            f"({main} convention)", "τ - τ̂ [N]"), "force_error.png")
    ctx.figure(plots.tracking_errors(errors, f"{system.name}: {cfg.invert.name} feedforward, "
                                             "model-predicted tracking error"), "tracking_error.png")
    np.savez_compressed(ctx.artifact("errors.npz"), Ts=system.Ts,
                        **{f"{k}/{x}": v for k, (t, e) in errors.items()
                           for x, v in (("r", inv["r"][k]), ("e", e), ("force_error", force[k][1]),
                                        ("u_ff", inv["u_ff"][k]))})
    return {"per_reference": out}


#: window after each step of the measured disturbance [s] whose force error is split off (diagnostic)
EDGE_WINDOW = 0.06


def _after_disturbance_edges(d, tau, tau_hat, n: int) -> dict[str, float]:
    """Where the force error sits relative to the disturbance steps (EMPS test pulses): the share of
    ‖τ - τ̂‖² within ``n`` samples after a step of d, and the relative force error outside them."""
    edges = np.flatnonzero(np.diff(np.asarray(d)) != 0) + 1
    if edges.size == 0:
        return {}
    near = np.zeros(len(tau), bool)
    for k in edges:
        near[k:k + n] = True
    e2 = (np.asarray(tau) - tau_hat) ** 2
    return {"data/force_error_share_after_steps": float(e2[near].sum() / e2.sum()),
            "data/force_rel_error_outside_steps": float(100 * np.sqrt(e2[~near].sum() / np.sum(tau[~near] ** 2)))}


def _tracking(r, y) -> dict[str, float]:
    e = np.asarray(r) - np.asarray(y)
    return {"mae": float(np.mean(np.abs(e))), "max_abs": float(np.max(np.abs(e))),
            "rms": float(np.sqrt(np.mean(e ** 2)))}
