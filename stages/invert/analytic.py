"""invert.kind=analytic: analytic inversion of the invertible PGNN, [B1] (26)-(27) (SPEC §6)."""
from __future__ import annotations

from typing import Literal

from pipeline.invert.analytic import analytic_feedforward, analytic_step
from pipeline.params import schema
from stages.export import pgnn_check, pgnn_laws
from stages.invert._pgnn import applied, check_structure, log_common, log_diagnostics, trained


@schema
class Params:
    kind: Literal["analytic"]
    name: str = "analytic"
    # the model this inversion needs (fills model.structure)
    model_structure: Literal["forward", "inverse", "invertible"] = "invertible"


VERSION = 3   # 2: averaged model input: w(N) is the law's next sample on the held reference (pipeline.export)
              # 3: a measured rigid body (PhysicsModelFeatures of RigidBodyPhysics) inverts on the numba fast path
              # (the torch reference summed in another order: last bits)


def check(cfg, system) -> None:
    check_structure(cfg, "analytic", ("invertible",))


def feedforward(ctx, name, r):
    model = trained(ctx)
    u = applied(ctx, lambda rr: analytic_feedforward(model, rr), r)
    log_common(ctx, name, model, r, u, analytic_step)
    log_diagnostics(ctx, name, model, r)
    return u


# ---- export (stages/export.py asks this module)
EXPORTS_MEASURED = True   # a measured axis ships the PGNN's inversion minus the controller's force on y = r


def export_check(cfg, system) -> None:
    pgnn_check(cfg, "analytic")


def export_laws(ctx) -> dict:
    return pgnn_laws(ctx, "analytic")
