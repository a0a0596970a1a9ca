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
in both timing conventions (``evaluate.convention`` picks the one of the figures and of the
feedforward tracking; both are always logged):

- ``data`` (as recorded): every model — published, physics, PGNN — replayed by one integrator (the
  exact-ZOH step on ū), started from the recorded state (the first ``N_INIT`` = 20 samples are the
  record's) and scored from sample 20 on;
- ``published``: the benchmark authors' script (one more sample of delay, their time base, from
  rest, every sample scored; the published model with their semi-implicit Euler step).

Metrics ``<ref>/<convention>/force_rel_error | position_rel_error | loop_rmse_mm``;
``<ref>/benchmark_rmse_mm | benchmark_r2`` (the nonlinear_benchmarks open-loop simulation: the
model driven by the recorded force, the first 20 samples initialise); the published reference
model, where the system gives it, as ``<ref>/published_model/…``; the integrator check
``<ref>/[published_model/]integrator/rk4_n<n>/force_rel_error`` (physics models: the same
continuous-time model with n RK4 sub-steps per sample, :mod:`pipeline.identify.continuous_replay`);
the feedforward's *model-predicted* tracking (the identified model in the loop with u_ff added, tag
``feedforward_scoring``) as ``<ref>/model_based/mae|max_abs|rms`` beside the recorded tracking
without feedforward ``<ref>/recorded/…``; ``<ref>/data/force_rel_error_tail`` scores the last
``evaluate.validation_tail`` of the record (on the training file: the validation block the
trainings held out, where hyper-parameters are chosen); where the record has a stepped disturbance
(EMPS test pulses), ``data/force_error_share_after_steps`` is the share of the squared force error
within 60 ms after its steps and ``data/force_rel_error_outside_steps`` the error elsewhere.  A
replay far from the record (force error > 50 %, or model-based tracking > 10x the recorded) warns
and tags ``replay_warning/<ref>``.
A measured-data model scored on a simulator is refused unless ``evaluate.allow_simulator=true``,
which tags the run ``evaluated_on``.
"""
from __future__ import annotations

import warnings

import numpy as np

from pipeline import plots
from pipeline.errors import ConfigError
from pipeline.metrics import phase_ff_errors, phase_peaks, tracking_metrics
from stages._common import reference_specs

UPSTREAM = ("invert",)
DEPENDS = ("system", "evaluate", "seed")
VERSION = 7   # 2: per-phase peaks, errors.npz artifact; 3: per-phase feedforward force error; 4: measured systems;
              # 5: u_ff in the measured systems' errors.npz; 6: benchmark (open-loop) RMSE; 7: recorded-state
              # start, one integrator, R², integrator check


def optimal_input(system, r):
    """The exact optimal input where the simulator knows it, else None."""
    try:
        return system.exact_inverse(r)
    except NotImplementedError:
        return None


def validate(cfg, system) -> None:
    measured_data = str(cfg.data.get("kind")) == "measured"
    if system is not None and system.measured:   # evaluate.convention's choices: pipeline.schema
        bad = [s["name"] for s in reference_specs(cfg.evaluate.references) if s.get("kind") != "measured"]
        if bad:
            raise ConfigError(f"system '{system.name}' is a recording: it has no plant to run reference(s) {bad}; "
                              "give evaluate references of kind 'measured' naming a recorded file "
                              "(e.g. evaluate=emps)")
    elif measured_data and not cfg.evaluate.allow_simulator:
        raise ConfigError(f"the model is identified on measured data ({cfg.data.get('path')}) but system "
                          f"'{system.name}' is a simulator: scoring it there says nothing about the machine the "
                          "data came from. Use the measured system (e.g. system=emps evaluate=emps), or set "
                          "evaluate.allow_simulator=true to do it on purpose (the run is tagged)")


def run(ctx) -> dict:
    inv = ctx.inputs["invert"]
    system = ctx.system
    if system.measured:
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
    from pipeline.identify.measured_loop import (  # lazy: saves 1.0 s of start-up (numba kernels, measured systems)
        CONVENTIONS,
        N_INIT,
        LoopModel,
        LoopSignals,
        benchmark_scores,
        loop_errors,
        simulate_loop,
        simulate_open_loop,
    )
    from stages.generate.measured import reference  # lazy: saves 3.7 s of start-up (mlflow, via pipeline.runner)
    inv, system, cfg = ctx.inputs["invert"], ctx.system, ctx.cfg
    loop, ctrl = inv["loop"], system.ctrl
    tail = float(cfg.evaluate.validation_tail)
    main = str(cfg.evaluate.convention)   # of the figures and the feedforward tracking
    published = {}
    if system.published_theta() is not None:
        # data timing: the one integrator of every model (exact-ZOH step on ū); published timing: the
        # authors' script (semi-implicit Euler on u), which reproduces their figures
        published = {"data": LoopModel.physics_only(system.physics, system.published_theta()),
                     "published": LoopModel.physics_only(system.physics.with_direct_input(),
                                                         system.published_theta())}
    ctx.tag("feedforward_scoring", "model-based: the identified model in the recorded loop, not the machine")
    ctx.tag("replay", f"data timing: started from the recorded state, scored from sample {N_INIT}; "
                      "published timing: the authors' script (from rest, every sample)")
    out, errors, force = {}, {}, {}
    for spec in reference_specs(cfg.evaluate.references):
        name = spec["name"]
        ds = reference(cfg, spec, system)
        y, tau, r = ds["y"], ds["u"], ds["r"]
        d = ds["d"] if "d" in ds.frame else np.zeros_like(y)
        sigs = {"data": LoopSignals.recorded(r, d, y, tau, ds["t"], N_INIT),
                "published": LoopSignals(r, d, float(y[0]), ds["t"])}
        start = {"data": N_INIT, "published": 0}
        m = {}
        for conv in CONVENTIONS:
            y_hat, tau_hat, _ = simulate_loop(loop, ctrl, sigs[conv], conv)
            m |= {f"{conv}/{k}": v for k, v in loop_errors(y, tau, y_hat, tau_hat, start[conv]).items()}
            if conv == main:
                force[name] = (ds["t"], tau - tau_hat)
            if conv == "data":
                k0 = int(round((1.0 - tail) * y.size))   # the validation tail of a training record
                m["data/force_rel_error_tail"] = float(100 * np.linalg.norm(tau[k0:] - tau_hat[k0:])
                                                       / np.linalg.norm(tau[k0:]))
                m |= _after_disturbance_edges(d, tau, tau_hat, int(round(EDGE_WINDOW / system.Ts)), N_INIT)
            if published:
                yp, tp, _ = simulate_loop(published[conv], ctrl, sigs[conv], conv)
                m |= {f"published_model/{conv}/{k}": v for k, v in loop_errors(y, tau, yp, tp, start[conv]).items()}
        # the benchmark's open-loop simulation: recorded force in, position out, first N_INIT samples initialise
        m |= benchmark_scores(y, simulate_open_loop(loop, tau, float(y[0]), y, N_INIT))
        if published:
            m |= {f"published_model/{k}": v for k, v in
                  benchmark_scores(y, simulate_open_loop(published["data"], tau, float(y[0]), y, N_INIT)).items()}
        m |= _integrator_check(inv, system, sigs["data"], y, tau)
        u_ff = inv["u_ff"][name]
        sig_ff = LoopSignals.recorded(r, d, y, tau, ds["t"], N_INIT, u_ff) if main == "data" else \
            LoopSignals(r, d, float(y[0]), ds["t"], u_ff)
        y_ff, _, _ = simulate_loop(loop, ctrl, sig_ff, main)
        m |= {f"model_based/{k}": v for k, v in _tracking(r[start[main]:], y_ff[start[main]:]).items()}
        m |= {f"recorded/{k}": v for k, v in _tracking(r[start[main]:], y[start[main]:]).items()}
        for k, val in m.items():
            ctx.metric(f"{name}/{k}", val)
        _warn_far_from_record(ctx, name, m)
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


def _integrator_check(inv, system, sig, y, tau) -> dict[str, float]:
    """The one integrator against the continuous-time model it discretises (physics models only:
    the PGNN is a discrete-time model): the data-timing force error of the physics model (and of
    the published one) replayed with RK4 sub-steps (pipeline.identify.continuous_replay)."""
    from pipeline.identify.continuous_replay import (  # lazy: saves 0.8 s of start-up (numba kernels, measured systems)
        SUBSTEPS,
        replay_rk4,
    )
    from pipeline.identify.measured_loop import (  # lazy: saves 1.0 s of start-up (numba kernels, measured systems)
        N_INIT,
        loop_errors,
    )
    models = {"published_model/": system.published_theta()}
    if inv["loop"].n1 == 0:
        models[""] = inv["loop"].theta_phy
    out = {}
    for pre, theta in models.items():
        if theta is None:
            continue
        for n in SUBSTEPS:
            y_c, tau_c = replay_rk4(system.physics, theta, system.ctrl, sig, n)
            e = loop_errors(y, tau, y_c, tau_c, N_INIT)["force_rel_error"]
            out[f"{pre}integrator/rk4_n{n}/force_rel_error"] = e
    return out


#: a replay whose force error exceeds this [%] of the recorded force, or whose model-based tracking
#: is this many times the recorded tracking error, is not a model of the machine: warn and tag
FAR_FORCE_ERROR = 50.0
FAR_TRACKING = 10.0


def _warn_far_from_record(ctx, name: str, m: dict) -> None:
    fe = m.get("data/force_rel_error")
    mb, rec = m.get("model_based/mae"), m.get("recorded/mae")
    msgs = []
    if fe is not None and not fe <= FAR_FORCE_ERROR:
        msgs.append(f"the model's closed-loop replay errs by {fe:.3g} % of the recorded force (limit "
                    f"{FAR_FORCE_ERROR:.0f} %)")
    if mb is not None and rec and not mb <= FAR_TRACKING * rec:
        msgs.append(f"its model-based tracking MAE {mb:.3g} m is {mb / rec:.0f}x the recorded {rec:.3g} m "
                    f"(limit {FAR_TRACKING:.0f}x)")
    if msgs:
        msg = (f"{name}: " + "; ".join(msgs) + ": the model does not describe this machine; check the controller, "
               "the physics terms and the units before trusting its feedforward")
        ctx.tag(f"replay_warning/{name}", msg)
        warnings.warn(msg, stacklevel=2)


#: window after each step of the measured disturbance [s] whose force error is split off (diagnostic)
EDGE_WINDOW = 0.06


def _after_disturbance_edges(d, tau, tau_hat, n: int, start: int = 0) -> dict[str, float]:
    """Where the force error sits relative to the disturbance steps (EMPS test pulses): the share of
    ‖τ - τ̂‖² within ``n`` samples after a step of d, and the relative force error outside them."""
    edges = np.flatnonzero(np.diff(np.asarray(d)) != 0) + 1     # on the whole record: a step at `start` counts
    edges = edges[edges >= start] - start
    d, tau, tau_hat = (np.asarray(x)[start:] for x in (d, tau, tau_hat))
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
