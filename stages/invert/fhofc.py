"""invert.kind=fhofc: finite-horizon optimal feedforward control of the identified model, [B2] (17).

``invert.gamma`` is γ of Γ = γΔ ([B2] (31)); ``invert.horizon`` null = the whole reference
(Gauss–Newton on the exact N_k × N_k Jacobian), an integer h = the receding-horizon form
[B2] (18); optional box bounds on U_ff and on the model input Û.

Besides the feedforward, every reference logs the [B2] (15) bound terms (SPEC §7):
identification error (from the train stage), inversion error ‖R - Ŷ‖/sqrt(N_k), tracking
error, ε ([B2] (14)) and whether (15) holds, with Y the *measured* output (SPEC §8 B2a) of the
plant run with this feedforward and the evaluation noise realisation the evaluate stage
draws (same seeded stream ``evaluate/<reference>``; noise-free when ``evaluate.noise`` is
false).  Metrics: ``invert/<ref>/bound/<term>``, ``invert/<ref>/fhofc_seconds`` (solve wall
time, B2d), ``invert/<ref>/fhofc_iterations``; tag ``fhofc_fallback_<ref>`` when the solver
stopped without converging.
"""
from __future__ import annotations

from dataclasses import field
from typing import Literal, Optional

import numpy as np

from pipeline.errors import ConfigError
from pipeline.invert.fhofc import fhofc, fhofc_receding
from pipeline.metrics_bound import bound_terms
from pipeline.models.closed_loop import DiscreteController
from pipeline.params import FORCE_MAX, ITER_MAX, schema, spec
from stages.export import table_laws


@schema
class Bounds:
    lower: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-100.0)
    upper: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=100.0)


@schema
class Params:
    kind: Literal["fhofc"]
    name: str = "fhofc"
    # the closed-loop model simulation needs the forward PGNN
    model_structure: Literal["forward", "inverse", "invertible"] = "forward"
    # γ [m/N] of Γ = γΔ ([B2] §VI: 1e-6 and 5e-5)
    gamma: float = spec(1e-6, ge=0, le=1.0, unit="m/N")
    # (invert/fhofc.yaml) null: whole reference (N_k x N_k Gauss-Newton); h: receding horizon [B2] (18)
    # (invert/il_fhofc.yaml) IL-FHOFC uses the full-horizon FHOFC
    horizon: Optional[int] = spec(None, ge=1, le=10**6, example=50)
    # box bounds on U_ff [N] (null = unbounded side)
    uff_bounds: Bounds = field(default_factory=Bounds)
    # box bounds on the model input Û = C(R - Ŷ) + U_ff [N]
    u_bounds: Bounds = field(default_factory=Bounds)
    # (invert/fhofc.yaml) Gauss-Newton/LM iterations (per window for the receding horizon)
    # (invert/il_fhofc.yaml) Gauss-Newton/LM iterations per FHOFC solve
    max_iter: int = spec(50, ge=1, le=ITER_MAX)
    # stop when a step lowers the cost by less than ftol x cost
    ftol: float = spec(1e-10, ge=0, lt=1)
    # refuse references outside the identification data's output range
    check_range: bool = True
    # margin of that range, relative to its width
    range_margin: float = spec(0.1, ge=0, le=100.0)


VERSION = 3   # 2: the FHOFC solve is timed warm (the first solve of a process compiles numba kernels); 3: the
              # receding-horizon window halves an overshooting Gauss–Newton step instead of calling it a minimum


def _bounds(node):
    if node is None:
        return None
    lo, hi = node.get("lower"), node.get("upper")
    if lo is None and hi is None:
        return None
    return (-np.inf if lo is None else float(lo), np.inf if hi is None else float(hi))


def check(cfg, system) -> None:
    if str(cfg.identify.kind) != "sim_error":
        raise ConfigError(f"invert.kind={cfg.invert.kind} needs a closed-loop model identified by "
                          f"identify.kind=sim_error, got identify.kind={cfg.identify.kind}")
    inv = cfg.invert   # gamma, horizon, max_iter, the bounds' types: pipeline.schema
    for key in ("uff_bounds", "u_bounds"):
        b = _bounds(inv.get(key))
        if b is not None and not b[0] < b[1]:
            raise ConfigError(f"invert.{key}: lower {b[0]} must be below upper {b[1]}")


def solve(ctx, r, target=None, u_ff0=None, gamma=None):
    """FHOFC of the trained model for reference r (the config's solver settings)."""
    inv = ctx.cfg.invert
    model = ctx.inputs["train"]["arx"]
    ctrl = DiscreteController.from_tf(ctx.system.controller())
    gamma = float(inv.gamma) if gamma is None else gamma
    kw = dict(gamma=gamma, target=target, check_range=bool(inv.check_range),
              range_margin=float(inv.range_margin))
    if inv.get("horizon") is None:
        return fhofc(model, ctrl, r, u_ff0=u_ff0, uff_bounds=_bounds(inv.get("uff_bounds")),
                     u_bounds=_bounds(inv.get("u_bounds")), max_iter=int(inv.max_iter),
                     ftol=float(inv.ftol), **kw)
    return fhofc_receding(model, ctrl, r, h=int(inv.horizon), max_iter=int(inv.max_iter), **kw)


def evaluation_noise(ctx, name, n):
    """The evaluate stage's noise realisation for reference ``name`` (zeros when it is off)."""
    if not ctx.cfg.evaluate.noise:
        return np.zeros(n)
    return ctx.system.noise(n, ctx.rng(f"evaluate/{name}"))


def log_bound(ctx, prefix, r, y, y_hat) -> dict:
    """[B2] (15) terms with the identification signals of the train stage."""
    tr = ctx.inputs["train"]
    terms = bound_terms(r, y, y_hat, tr["y_d"], tr["y_hat_d"])
    for k, v in terms.items():
        ctx.metric(f"{prefix}/{k}", float(v))
    return terms


def feedforward(ctx, name, r):
    solve(ctx, r)           # a first solve compiles the numba kernels in this process: B2d times the solver
    res = solve(ctx, r)     # (deterministic: the same result)
    ctx.metric(f"{name}/fhofc_seconds", res.time_s)
    ctx.metric(f"{name}/fhofc_iterations", res.n_iter)
    ctx.metric(f"{name}/fhofc_cost", res.cost)
    ctx.metric(f"{name}/max_abs_u_ff", float(np.max(np.abs(res.u_ff))))
    if not res.converged:
        ctx.tag(f"fhofc_fallback_{name}", res.message)
    sim = ctx.system.simulate(r, u_ff=res.u_ff, v=evaluation_noise(ctx, name, r.size))
    log_bound(ctx, f"{name}/bound", r, sim.y, res.y_hat)
    return res.u_ff


# ---- export (stages/export.py asks this module): one table per reference, optimised offline for it
def export_laws(ctx) -> dict:
    return table_laws(ctx, "fhofc")
