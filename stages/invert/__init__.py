"""invert: turn the identified model into a feedforward for each evaluation reference (SPEC §6).

Implementations: ``stages/invert/<kind>.py`` exposing ``feedforward(ctx, name, r) -> u_ff`` (one
reference) and optionally ``check(cfg, system)``.  The references are ``evaluate.references``.
On a measured system the applied feedforward is the model inverse minus the force the controller
outputs when the axis follows the reference exactly, (C_r - C_y) r (``LTIController.
reference_force``): zero for error feedback, the velocity feedback on r for the EMPS cascade.
Every law starts as the ``start`` node says (``pipeline.invert.start``): at rest at r(0) on a measured
system (every state steady there, the controller term from its rest value; with ``start.static=exclude``
the force at rest taken off), the papers' conventions on the simulators.

Every reference's feedforward is written where a user looks (issue 49): the artifact
``invert/feedforward/<ref>.csv`` with columns t [s], r, u_ff (the study's, the one evaluate replays) and flags:
where the exported law's guard (``export.limits``, its defaults from the identification data; the training
envelope) would act on the sample, e.g. ``SATURATED|RATE_LIMITED`` or ``OUT_OF_RANGE``, empty otherwise. When a
reference leaves the training data's velocity or acceleration range the stage warns, tags ``envelope_warning``
with the factor ("reference 'test' reaches 1.66× the training velocity") and the remedy, and logs
``envelope_velocity_factor`` and ``envelope_acceleration_factor`` (the largest over the references; per
reference ``<ref>/envelope_…``): max |δr| / max |δy| of the training data, likewise δ².
"""
from __future__ import annotations

import re
import time
import warnings

import numpy as np

from pipeline.errors import NonPhysical
from pipeline.export.guard import Guard, envelope_of, run_guard
from pipeline.export.package import write_feedforward_csv
from pipeline.invert.start import resolve, settle_count, started
from pipeline.runner import ConfigError, implementation
from pipeline.systems.controller import advanced_reference
from stages._common import baseline_lag, check_references, reference_specs
from stages.export import guard_of

UPSTREAM = ("generate", "baseline", "train")
DEPENDS = ("invert", "evaluate.references", "evaluate.noise", "start",  # fhofc scores the bound terms on the measured Y
           "export.limits")                                           # the flags of the u_ff CSV
VERSION = 5   # 2: reference_warning when the feedforward spikes at an end of the reference; 3: start (issue 48);
              # 4: invert/feedforward/<ref>.csv, envelope factors (issue 49); 5: the model's force advanced by the
              # controller's delay D (u_ff(k) acts at k + D)
KIND_KEY = "invert.kind"


def validate(cfg, system) -> None:
    if not reference_specs(cfg.evaluate.references):
        raise ConfigError("evaluate.references is empty; give at least one reference to design a "
                          "feedforward for (see conf/evaluate/*.yaml)")
    check_references(reference_specs(cfg.evaluate.references), system, cfg)
    impl = implementation("invert", str(cfg.invert.kind))
    if hasattr(impl, "check"):
        impl.check(cfg, system)
    try:
        st = start_of(cfg, system)
        if st.rest and system is not None and system.measured:
            system.ctrl.rest_gain()       # a controller with no rest away from 0 is named before any work
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    if st.rest and str(cfg.invert.kind) in TABLES:
        raise ConfigError(f"start.at=rest: invert.kind={cfg.invert.kind} is a signal optimised offline for one "
                          "reference and starts where that reference starts; use start.at=zero")


#: laws that are signals optimised for one reference (no state to start)
TABLES = ("fhofc", "il_fhofc")


def start_of(cfg, system):
    """The job's :class:`~pipeline.invert.start.Start` (``auto`` decided for its system)."""
    return resolve(cfg.get("start"), system)


def run(ctx) -> dict:
    try:
        return _run(ctx)
    except NonPhysical as exc:   # e.g. a record whose physics fit gives 1/M <= 0 (issue 51: was a traceback)
        raise ConfigError(f"invert.kind={ctx.cfg.invert.kind} on '{ctx.system.name}': {exc}") from None


def _run(ctx) -> dict:
    impl = implementation("invert", str(ctx.cfg.invert.kind))
    baseline_lag(ctx)
    refs = check_references(reference_specs(ctx.cfg.evaluate.references), ctx.system, ctx.cfg)
    st = start_of(ctx.cfg, ctx.system)
    ctrl = ctx.system.ctrl if ctx.system.measured else None
    u_ff, edge, u_start = {}, [], {}
    delay = int(ctrl.delay) if ctrl is not None else 0
    for name, r in ctx.progress(refs.items(), desc="feedforward", total=len(refs)):
        t0 = time.perf_counter()
        law = lambda rr: np.asarray(impl.feedforward(ctx, name, rr), dtype=np.float64)   # noqa: E731
        r0 = float(r[0])
        # the controller delays u_ff by D samples: the model's force is that of r(k + D), its own term of r(k)
        r_law = advanced_reference(r, delay)
        if st.rest:               # every state at rest at r(0) (pipeline.invert.start)
            n_metrics = len(ctx.metrics)
            settle = settle_count(law, [r0])
            del ctx.metrics[n_metrics:]     # the law's own metrics of the rest probe are not the reference's
            f, u_rest = started(law, r_law, r0, settle)
            last = {m[0]: m for m in ctx.metrics[n_metrics:]}   # the rest run's and the reference's: the latter's,
            ctx.metrics[n_metrics:] = list(last.values())       # once (a key twice at one time breaks MLflow's log)
            ctx.metric(f"{name}/start_settle_samples", settle)
        else:
            f = law(r_law)
        ctx.metric(f"{name}/seconds_per_sample", (time.perf_counter() - t0) / r.size)
        if f.shape != r.shape or not np.all(np.isfinite(f)):
            raise ValueError(f"invert.kind={ctx.cfg.invert.kind} returned a feedforward of shape "
                             f"{f.shape} with {int((~np.isfinite(f)).sum())} non-finite values for "
                             f"reference '{name}' (expected {r.shape}, all finite)")
        if ctrl is not None:      # a 2-DOF controller: cancel its output on y = r
            f = f - ctrl.reference_force(r, r0 if st.rest else 0.0)
            if st.rest:
                u_rest -= ctrl.gtau * ctrl.rest_gain() * r0
        if st.rest:
            if st.static == "exclude":
                f = f - u_rest
            ctx.metric(f"{name}/static_force_at_start", u_rest)
            u_start[name] = 0.0 if st.static == "exclude" else u_rest   # the guard's output before t = 0
        if ctrl is not None or st.rest:   # the law's own max|u_ff| was of the model inverse alone: the applied one
            key = f"{ctx.name}/{name}/max_abs_u_ff"
            ctx.metrics[:] = [m for m in ctx.metrics if m[0] != key]
            ctx.metric(f"{name}/max_abs_u_ff", float(np.max(np.abs(f))))
        u_ff[name] = f
        msg = edge_warning(name, r, f, float(ctx.system.Ts), st.at)
        if msg:
            edge.append(msg)
            warnings.warn(msg, stacklevel=1)
    if edge:
        ctx.tag("reference_warning", " ".join(edge))
    env = envelope_warning(ctx, refs)
    if env:
        warnings.warn(env, stacklevel=1)
        ctx.tag("envelope_warning", env)
    write_feedforward(ctx, refs, u_ff, st, u_start)
    ctx.tag("start", f"{st.at}, static {st.static}")
    out = {"u_ff": u_ff, "r": refs, "start": {"at": st.at, "static": st.static}}
    if ctx.system.measured:   # evaluate replays the identified model in the recorded loop
        out["loop"] = loop_model(ctx)
    return out


#: samples at each end of a reference that are compared with the rest of its feedforward
EDGE_SAMPLES = 3
#: an end's largest |u_ff| above this many times the interior's is a spike worth a warning
EDGE_RATIO = 2.0


def edge_warning(name: str, r: np.ndarray, u_ff: np.ndarray, Ts: float, at: str = "rest") -> str | None:
    """A warning when the feedforward spikes at an end of the reference: a law takes the reference at rest before
    its first sample (at r(0) with ``start.at=rest``, at 0 with ``zero``) and held after its last, so a reference
    that starts moving, or starts away from 0 under ``zero``, or ends while moving asks for an instant start or
    stop there (a recording cut mid-motion: 390 N at the end where the motion needs 5 N). None when both ends
    are calm. A reference at rest away from 0 is normal under ``rest``: no spike, no warning."""
    k = EDGE_SAMPLES
    if r.size <= 4 * k:
        return None
    inner = float(np.max(np.abs(u_ff[k:-k])))
    v = np.abs(np.diff(r)) / Ts
    v_peak = float(np.max(v)) if v.size else 0.0
    parts, why = [], []
    for end, u_end, v_end in (("starts", u_ff[:k], v[0]), ("ends", u_ff[-k:], v[-1])):
        peak = float(np.max(np.abs(u_end)))
        if peak > EDGE_RATIO * inner:
            r_end = float(r[0] if end == "starts" else r[-1])
            parts.append(f"{end} with |u_ff| = {peak:.4g} against {inner:.4g} inside (r {end} at {r_end:.4g}, "
                         f"moving at {v_end:.3g} per s, its peak {v_peak:.3g} per s)")
            if end == "starts" and at == "zero" and r_end != 0.0 and v_end <= 1e-3 * v_peak:
                why.append("the reference starts at rest away from 0 while start.at=zero takes it at 0 before its "
                           "first sample: set start.at=rest (the default on a measured system)")
            elif v_end > 1e-3 * v_peak:
                why.append(f"the reference {end} while moving: the law takes it at rest before its first sample "
                           "and held after its last, so those samples ask for an instant start or stop; start and "
                           "end the reference at rest, or leave those samples out of the comparison")
    if not parts:
        return None
    if not why:
        why.append("the law takes the reference at rest before its first sample and held after its last")
    return f"reference '{name}' " + " and ".join(parts) + ": " + "; ".join(why) + "."


def envelope_warning(ctx, refs: dict) -> str | None:
    """A warning naming every reference that leaves the identification data's range of position, velocity or
    acceleration (the law's regressors, r standing in for y; ``pipeline.export.guard.envelope_of`` without margin):
    there the model is extrapolated ([B1] Definition 6), and the exported guard flags it OUT_OF_RANGE. The factor
    max |δr| / max |δy| of the training data (likewise δ²) is logged per reference and its largest over them
    (``envelope_velocity_factor``, ``envelope_acceleration_factor``); the warning names it and the remedy."""
    ds = ctx.inputs["generate"].get("dataset")
    if ds is None:
        return None
    Ts = float(ctx.system.Ts)
    lo, hi = envelope_of((seg["y"].to_numpy(dtype=float) for seg in ds.segments()), Ts, 0.0)
    names, units, parts = ("position", "velocity", "acceleration"), ("", "/s", "/s²"), []
    worst = [0.0, 0.0, 0.0]
    for name, r in refs.items():
        rlo, rhi = envelope_of([r], Ts, 0.0)
        out = []
        for i in (1, 2, 0):   # the velocity and acceleration first: the regressors the NN is most sensitive to
            q = names[i]
            span = max(abs(lo[i]), abs(hi[i]))
            factor = max(abs(rlo[i]), abs(rhi[i])) / span if span > 0 else (np.inf if rhi[i] > rlo[i] else 0.0)
            if i:          # the regressors' factors: velocity, acceleration
                ctx.metric(f"{name}/envelope_{q}_factor", factor)
                worst[i] = max(worst[i], factor)
            if rlo[i] < lo[i] or rhi[i] > hi[i]:
                out.append(f"{factor:.3g}× the training {q} ({rlo[i]:.4g} .. {rhi[i]:.4g} against {lo[i]:.4g} .. "
                           f"{hi[i]:.4g} {'m' if i == 0 else 'm' + units[i]})")
        if out:
            parts.append(f"reference '{name}' reaches " + ", ".join(out))
    if refs:
        ctx.metric("envelope_velocity_factor", worst[1])
        ctx.metric("envelope_acceleration_factor", worst[2])
    if not parts:
        return None
    return ("; ".join(parts) + ": there the feedforward extrapolates the model beyond its training data. Record a "
            "training run that covers it (moves as fast, accelerations as high and positions as far as the "
            "reference's) and train again; an exported law flags OUT_OF_RANGE beyond export.limits.envelope_margin "
            "(0.1 of each range by default) outside them.")


def guard_preview(ctx) -> int:
    """P of the exported law of ``invert.kind`` (pipeline.export.law): the PGNN inversions read r(t) .. r(t+n_k+1),
    the physics laws r(t) .. r(t+1), one more on an averaged model input, and on a measured axis D more (its
    controller's delay: the model's force of r(t + D)); the [K] filters and tables r(t) only."""
    kind = str(ctx.cfg.invert.kind)
    averaged = bool(getattr(getattr(ctx.system, "physics", None), "averaged_input", False))
    delay = int(ctx.system.ctrl.delay) if getattr(ctx.system, "measured", False) else 0
    if kind in ("direct", "analytic", "newton"):
        train = ctx.inputs["train"]
        return int(train["model"].n_k) + 1 + int(averaged and bool(train.get("model_input"))) + delay
    return 1 + int(averaged) + delay if kind == "physics" else 0


def feedforward_flags(ctx, refs: dict, u_ff: dict, st, u_start: dict) -> dict:
    """{ref: flags} of the exported law's guard (stages.export.guard_of: export.limits, defaults from the data, the
    training envelope) run on the study's u_ff: where it would saturate, rate-limit, flag OUT_OF_RANGE or fall
    back. Zeros without an export node."""
    if ctx.cfg.get("export") is None or ctx.inputs["generate"].get("dataset") is None:
        return {name: np.zeros(r.size, dtype=np.int64) for name, r in refs.items()}
    g = Guard(**guard_of(ctx, st.at)[0])
    P, Ts = guard_preview(ctx), float(ctx.system.Ts)
    out = {}
    for name, r in refs.items():
        # the law's r0 (pipeline.export.law.start_position): the physics law and the [K] filters of the papers' start
        # from r = 0, every other law from r(0)
        r0 = 0.0 if not st.rest and str(ctx.cfg.invert.kind) in ("physics", "rational_filter") else float(r[0])
        u0 = min(max(u_start.get(name, 0.0), g.u_min), g.u_max)     # inside the limits, as the C's init clamps it
        u = u_ff[name]
        out[name] = run_guard(g, Ts, P, r, r0, lambda _r, u=u: (u, np.zeros(u.size, dtype=np.int64)), u_start=u0)[1]
    return out


def write_feedforward(ctx, refs: dict, u_ff: dict, st, u_start: dict) -> None:
    """``invert/feedforward/<ref>.csv`` per reference: t [s], r, u_ff (the study's) and the guard's flags by name
    (``|``-joined, empty where it would not act); the count of flagged samples as ``<ref>/guard_flagged_samples``."""
    flags = feedforward_flags(ctx, refs, u_ff, st, u_start)
    for name, r in refs.items():
        path = ctx.artifact(f"feedforward/{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}.csv")
        write_feedforward_csv(path, float(ctx.system.Ts), r, u_ff[name], flags[name])
        ctx.metric(f"{name}/guard_flagged_samples", int(np.count_nonzero(flags[name])))


def loop_model(ctx):
    """The identified model of a measured system as a loop model: the trained PGNN (simulation
    error or a forward/invertible NARX PGNN) or, without one, the physics baseline."""
    from pipeline.identify.measured_loop import (  # lazy: saves 0.9 s of start-up (numba kernels, measured systems)
        LoopModel,
    )
    train = ctx.inputs["train"]
    if train.get("loop") is not None:
        return train["loop"]
    model = train.get("model")
    if model is not None:
        try:
            return LoopModel.from_pgnn(model, bool(train.get("model_input")))
        except ValueError as exc:
            raise ConfigError(f"the trained model cannot be replayed in the recorded loop: {exc}") from exc
    return LoopModel.physics_only(ctx.system.physics, ctx.inputs["baseline"]["theta"])
