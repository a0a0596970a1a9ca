"""Helpers of the [B1] PGNN inversions (invert.kind = direct | newton | analytic)."""
from __future__ import annotations

import numpy as np
import torch

from pipeline.errors import ConfigError
from pipeline.identify.narx import build_regression
from pipeline.invert.direct import nyquist_fraction, per_sample_seconds
from pipeline.models.fast_pgnn import fast_pgnn


def check_structure(cfg, kind: str, allowed: tuple[str, ...]) -> None:
    """The identified model must have a layout the inversion can use."""
    measured = str(cfg.data.get("kind")) == "measured" and str(cfg.identify.kind) == "sim_error"
    if str(cfg.identify.kind) != "narx" and not measured:
        raise ConfigError(f"invert.kind={kind} inverts a PGNN identified by identify.kind=narx (or, on "
                          f"measured data, sim_error), got identify.kind={cfg.identify.kind}")
    s = cfg.model.get("structure")
    if s not in allowed:
        raise ConfigError(f"invert.kind={kind} needs model.structure in {allowed}, got {s!r}; "
                          "leave model.structure to invert.model_structure")


def trained(ctx):
    model = ctx.inputs["train"]["model"]
    if model is None:
        raise ConfigError("no trained model: set identify=narx")
    return model


def applied(ctx, law, r: np.ndarray) -> np.ndarray:
    """The input to apply for the feedforward ``law(r)`` of the model input w: w itself unless
    the physics model averages its input (SPEC §2.2), then u_ff(t) = (w(t) + w(t+1))/2 with
    w(N) the law's next sample on the reference held after its end (what a real-time loop
    computes, ``pipeline.export``)."""
    if ctx.inputs["train"].get("model_input") and getattr(ctx.system.physics, "averaged_input", False):
        w = law(np.append(r, r[-1]))
        return ctx.system.physics.applied_input(w[:-1], w_end=w[-1])
    return law(r)


def log_common(ctx, name: str, model, r: np.ndarray, u_ff: np.ndarray, step, *args) -> None:
    """Per-sample cost of the sample-by-sample kernel ``step`` (median over the samples of
    this reference after warm-up, SPEC §7) and the feedforward's Nyquist energy share and
    peak (SPEC §2.2: bounded, no z = -1 oscillation)."""
    fm = fast_pgnn(model)
    if fm is not None and r.size > 400:
        ts = per_sample_seconds(step, fm, r, *args)
        ctx.metric(f"{name}/sample_seconds_median", float(np.median(ts)))
        ctx.metric(f"{name}/sample_seconds_p99", float(np.percentile(ts, 99)))
    ctx.metric(f"{name}/nyquist_fraction", nyquist_fraction(u_ff))
    ctx.metric(f"{name}/max_abs_u_ff", float(np.max(np.abs(u_ff))))


def log_diagnostics(ctx, name: str, model, r: np.ndarray) -> None:
    """Why a PGNN feedforward does (not) help, beyond the tracking error:

    - ``<ref>/velocity_over_training``: max |δr| of the reference over max |δy| of the
      training data; above 1 the feedforward evaluates the NN outside the operating
      conditions it was trained on ([B1] Definition 6);
    - ``nn_r2_unmodelled`` (once per run; forward layouts on an equation-noise plant, where
      ``y_clean`` is the noise-free one-step output h(φ)): the share of the variance of the
      true unmodelled dynamics g = h - f_phy(θ̂_phy) on the training rows that f_NN explains.
    """
    if r.size < 2:
        return   # a rest probe of the start (pipeline.invert.start): no motion to compare
    ds = ctx.inputs["generate"]["dataset"]
    Ts = float(ctx.system.Ts)
    v_train = max(float(np.max(np.abs(np.diff(seg["y"].to_numpy(np.float64))))) for seg in ds.segments()) / Ts
    ctx.metric(f"{name}/velocity_over_training", float(np.max(np.abs(np.diff(r)))) / Ts / v_train)
    if any(m[0] == f"{ctx.name}/nn_r2_unmodelled" for m in ctx.metrics):
        return  # once per run
    if (model.structure == "inverse" or not model.use_nn or "y_clean" not in ds.frame
            or getattr(ctx.system, "structure", None) != "equation"):
        return
    g, nn = [], []
    for seg in ds.segments():
        u = seg["u"].to_numpy(np.float64)
        if ctx.inputs["train"].get("model_input"):
            u = ctx.system.physics.model_input(u)
        reg = build_regression(model, seg["y"].to_numpy(np.float64), u)
        phi = torch.as_tensor(reg.phi)
        with torch.no_grad():
            g.append(seg["y_clean"].to_numpy(np.float64)[reg.t] - model.physics_part(phi).numpy())
            nn.append(model.nn_part(phi).numpy())
    g, nn = np.concatenate(g), np.concatenate(nn)
    if np.var(g) > 0:
        ctx.metric("nn_r2_unmodelled", float(1.0 - np.var(g - nn) / np.var(g)))
