"""invert.kind=rational_filter: the trained [K] filter F_θ,φ run on the reference (SPEC §6).

f = (A(r) + g_φ(r))/B(q); an unstable B is refused with a clear error.  Logged per reference:
the largest |root| of B, the split into f_M and f_C (‖f_C‖/‖f_M‖), and, when the train stage
kept several restarts, the spread of f_M over them (SPEC §8 K2) relative to rms f̂ (the
plant's exact optimal input where known, else the feedforward itself).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from pipeline.errors import ConfigError
from pipeline.export import law as laws
from pipeline.identify.orthogonal import spread_over_inits
from pipeline.invert.rational_filter import rational_feedforward
from pipeline.params import schema
from stages.export import every_reference


@schema
class Params:   # nothing to set
    kind: Literal["rational_filter"]
    name: str = ""


def check(cfg, system) -> None:
    if str(cfg.identify.kind) != "sk_oe":
        raise ConfigError(f"invert.kind=rational_filter runs a filter identified by identify.kind=sk_oe, "
                          f"got identify.kind={cfg.identify.kind}")


def feedforward(ctx, name, r):
    train = ctx.inputs["train"]
    model = train["model"]
    out = rational_feedforward(model, r)
    ctx.metric(f"{name}/max_pole_abs", out.max_pole_abs)
    if out.f_C is not None:
        ctx.metric(f"{name}/ratio_C_M", float(np.linalg.norm(out.f_C) / np.linalg.norm(out.f_M)))
        restarts = train.get("restart_models") or []
        if len(restarts) > 1:
            try:
                f_hat = ctx.system.exact_inverse(r)
            except NotImplementedError:
                f_hat = out.f
            parts = []
            for m in restarts:
                with torch.no_grad():
                    parts.append(m.parts(m.inputs(r))[0].numpy())
            ctx.metric(f"{name}/spread_f_M", spread_over_inits(parts, f_hat))
    return out.f


# ---- export (stages/export.py asks this module)
def export_check(cfg, system) -> None:
    m = cfg.model
    if str(m.get("kind")) == "pgnn_shared_ar" and str(m.get("approximator")) != "mlp":
        raise ConfigError(f"export: the [K] PGNN is exported with the MLP approximator (model.approximator=mlp), "
                          f"got {m.get('approximator')!r}")


def export_laws(ctx) -> dict:
    model = ctx.inputs["train"]["model"]
    name = "pgnn_shared_ar" if hasattr(model, "g") else "rational"
    return {f"ff_{name}": (laws.from_k_filter(model), every_reference(ctx))}
