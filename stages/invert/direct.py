"""invert.kind=direct: the direct-inverse PGNN [B1] (13) evaluated on the reference (SPEC §6)."""
from __future__ import annotations

from pipeline.invert.direct import direct_feedforward, direct_step
from stages.invert._pgnn import applied, check_structure, log_common, log_diagnostics, trained


def check(cfg, system) -> None:
    check_structure(cfg, "direct", ("inverse",))


def feedforward(ctx, name, r):
    model = trained(ctx)
    w = direct_feedforward(model, r)
    u = applied(ctx, w)
    log_common(ctx, name, model, r, u, direct_step)
    log_diagnostics(ctx, name, model, r)
    return u
