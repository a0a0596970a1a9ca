"""invert: turn the identified model into a feedforward for each evaluation reference (SPEC §6).

Implementations: ``stages/invert/<kind>.py`` exposing ``feedforward(ctx, name, r) -> u_ff`` (one
reference) and optionally ``check(cfg, system)``.  The references are ``evaluate.references``.
On a measured system the applied feedforward is the model inverse minus the force the controller
outputs when the axis follows the reference exactly, (C_r - C_y) r (``LTIController.
reference_force``): zero for error feedback, the velocity feedback on r for the EMPS cascade.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from pipeline.runner import ConfigError, implementation
from stages._common import check_references, reference_specs

UPSTREAM = ("generate", "baseline", "train")
DEPENDS = ("invert", "evaluate.references", "evaluate.noise")  # fhofc scores the bound terms on the measured Y
VERSION = 2   # 2: reference_warning when the feedforward spikes at an end of the reference
KIND_KEY = "invert.kind"


def validate(cfg, system) -> None:
    if not reference_specs(cfg.evaluate.references):
        raise ConfigError("evaluate.references is empty; give at least one reference to design a "
                          "feedforward for (see conf/evaluate/*.yaml)")
    check_references(reference_specs(cfg.evaluate.references), system, cfg)
    impl = implementation("invert", str(cfg.invert.kind))
    if hasattr(impl, "check"):
        impl.check(cfg, system)


def run(ctx) -> dict:
    impl = implementation("invert", str(ctx.cfg.invert.kind))
    refs = check_references(reference_specs(ctx.cfg.evaluate.references), ctx.system, ctx.cfg)
    u_ff, edge = {}, []
    for name, r in ctx.progress(refs.items(), desc="feedforward", total=len(refs)):
        t0 = time.perf_counter()
        f = np.asarray(impl.feedforward(ctx, name, r), dtype=np.float64)
        ctx.metric(f"{name}/seconds_per_sample", (time.perf_counter() - t0) / r.size)
        if f.shape != r.shape or not np.all(np.isfinite(f)):
            raise ValueError(f"invert.kind={ctx.cfg.invert.kind} returned a feedforward of shape "
                             f"{f.shape} with {int((~np.isfinite(f)).sum())} non-finite values for "
                             f"reference '{name}' (expected {r.shape}, all finite)")
        if ctx.system.measured:   # a 2-DOF controller: cancel its output on y = r
            f = f - ctx.system.ctrl.reference_force(r)
        u_ff[name] = f
        msg = edge_warning(name, r, f, float(ctx.system.Ts))
        if msg:
            edge.append(msg)
            warnings.warn(msg, stacklevel=1)
    if edge:
        ctx.tag("reference_warning", " ".join(edge))
    out = {"u_ff": u_ff, "r": refs}
    if ctx.system.measured:   # evaluate replays the identified model in the recorded loop
        out["loop"] = loop_model(ctx)
    return out


#: samples at each end of a reference that are compared with the rest of its feedforward
EDGE_SAMPLES = 3
#: an end's largest |u_ff| above this many times the interior's is a spike worth a warning
EDGE_RATIO = 2.0


def edge_warning(name: str, r: np.ndarray, u_ff: np.ndarray, Ts: float) -> str | None:
    """A warning when the feedforward spikes at an end of the reference: every law starts from a reference at
    rest (r(-1) = 0 or r(0)) and holds r after its last sample, so a recording that starts away from that or
    ends while moving asks for an instant start or stop, and its first or last samples carry the force of it
    (a recording cut mid-motion: 390 N at the end where the motion needs 5 N). None when both ends are calm."""
    k = EDGE_SAMPLES
    if r.size <= 4 * k:
        return None
    inner = float(np.max(np.abs(u_ff[k:-k])))
    v = np.abs(np.diff(r)) / Ts
    v_peak = float(np.max(v)) if v.size else 0.0
    parts = []
    for end, u_end, v_end in (("starts", u_ff[:k], v[0]), ("ends", u_ff[-k:], v[-1])):
        peak = float(np.max(np.abs(u_end)))
        if peak > EDGE_RATIO * inner:
            parts.append(f"{end} with |u_ff| = {peak:.4g} against {inner:.4g} inside (r {end} at "
                         f"{float(r[0] if end == 'starts' else r[-1]):.4g}, moving at {v_end:.3g} per s, its peak "
                         f"{v_peak:.3g} per s)")
    if not parts:
        return None
    return (f"reference '{name}' " + " and ".join(parts) + ": the feedforward assumes the reference at rest "
            "before its first sample and held after its last, so those samples ask for an instant start or stop. "
            "Start and end the recording at rest, or leave its first and last samples out of the comparison.")


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
