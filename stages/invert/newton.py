"""invert.kind=newton: Newton inversion of the forward PGNN, [B1] Algorithm 1 (SPEC §6).

``invert.k`` Newton updates per sample from the physics feedforward, optional input bounds
``invert.u_min``/``u_max`` [N] (on the model input w).  Every sample Newton could not solve
cleanly is counted (``invert/<ref>/newton_bounds|singular|diverged``), never silent.
"""
from __future__ import annotations

import math
from typing import Literal, Optional

from pipeline.errors import ConfigError
from pipeline.invert.newton import newton_feedforward, newton_step
from pipeline.params import FORCE_MAX, schema, spec
from stages.export import pgnn_check, pgnn_laws
from stages.invert._pgnn import applied, check_structure, log_common, log_diagnostics, trained


@schema
class Params:
    kind: Literal["newton"]
    name: str = "newton"
    # the model this inversion needs (fills model.structure)
    model_structure: Literal["forward", "inverse", "invertible"] = "forward"
    # Newton updates per sample ([B1] §VI: 5)
    k: int = spec(5, ge=0, le=1000)
    # [N] lower bound of the search (null = none); leaving it is reported
    u_min: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-100.0)
    # [N] upper bound of the search (null = none)
    u_max: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=100.0)


VERSION = 3   # 2: averaged model input: w(N) is the law's next sample on the held reference (pipeline.export)
              # 3: a measured rigid body (PhysicsModelFeatures of RigidBodyPhysics) inverts on the numba fast path
              # (the torch reference summed in another order: last bits)


def _bounds(cfg):
    lo = cfg.invert.get("u_min")
    hi = cfg.invert.get("u_max")
    lo = -math.inf if lo is None else float(lo)
    hi = math.inf if hi is None else float(hi)
    return lo, hi


def check(cfg, system) -> None:
    check_structure(cfg, "newton", ("forward", "invertible"))   # invert.k, u_min, u_max: pipeline.schema
    lo, hi = _bounds(cfg)
    if not lo < hi:
        raise ConfigError(f"invert.u_min={lo} must be below invert.u_max={hi}")


def feedforward(ctx, name, r):
    model = trained(ctx)
    k = int(ctx.cfg.invert.k)
    lo, hi = _bounds(ctx.cfg)
    out = []

    def law(rr):   # the model input w; the diagnostics below are of this run
        out.append(newton_feedforward(model, rr, k=k, u_bounds=None if math.isinf(lo) and math.isinf(hi)
                                      else (lo, hi)))
        return out[-1].u_ff
    u = applied(ctx, law, r)
    res = out[-1]
    ctx.metric(f"{name}/newton_bounds", res.n_bounds)
    ctx.metric(f"{name}/newton_singular", res.n_singular)
    ctx.metric(f"{name}/newton_diverged", res.n_diverged)
    ctx.metric(f"{name}/newton_max_residual", float(res.residual.max()))
    if res.n_fallback:
        ctx.tag(f"newton_fallback_{name}", res.n_fallback)
    log_common(ctx, name, model, r, u, newton_step, k, lo, hi)
    log_diagnostics(ctx, name, model, r)
    return u


# ---- export (stages/export.py asks this module)
EXPORTS_MEASURED = True   # a measured axis ships the PGNN's inversion minus the controller's force on y = r


def export_check(cfg, system) -> None:
    pgnn_check(cfg, "newton")


def export_laws(ctx) -> dict:
    return pgnn_laws(ctx, "newton", k=int(ctx.cfg.invert.k), u_bounds=_bounds(ctx.cfg))
