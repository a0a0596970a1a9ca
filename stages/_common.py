"""Helpers shared by the stages (config -> library objects)."""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline import references
from pipeline.errors import ConfigError


def baseline_lag(ctx) -> None:
    """A measured system with ``actuator.lag_tau: auto`` models the lag the baseline identified (its output
    may come from the cache, where fit_physics did not run in this process)."""
    lag = ctx.inputs.get("baseline", {}).get("lag")
    if lag is not None and getattr(ctx.system, "lag_tau", None) == "auto":
        ctx.system.use_lag(lag["tau"])


def reference_specs(node) -> list[dict]:
    """A list of reference specs from the config (each a dict with ``name`` and ``kind``)."""
    if node is None:
        return []
    specs = OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig,)) or \
        OmegaConf.is_list(node) else list(node)
    if isinstance(specs, dict):
        specs = [dict(v, name=v.get("name", k)) for k, v in specs.items()]
    for i, s in enumerate(specs):
        if "kind" not in s:
            raise ConfigError(f"reference #{i} {s} has no 'kind'; use one of {references.KINDS}")
        s.setdefault("name", f"ref{i}")
    return specs


def build_reference(spec: dict, Ts: float) -> np.ndarray:
    """Sample the reference described by ``spec`` at ``Ts`` (see :func:`pipeline.references.from_spec`)."""
    try:
        return references.from_spec(spec, Ts)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"reference '{spec.get('name')}': {exc}") from exc


def check_references(specs: list[dict], system, cfg=None) -> dict[str, np.ndarray]:
    """Build every reference and check it against the plant's limits, before any work.

    A reference of kind ``measured`` is the reference column r of a recorded file
    (``file``, read from ``data.path`` like the training data, checked like it; needs ``cfg``)."""
    out = {}
    for s in specs:
        if s.get("kind") == "measured":
            if cfg is None or str(cfg.data.get("kind")) != "measured":
                raise ConfigError(f"reference '{s['name']}' is of kind 'measured' (a recorded file): it needs "
                                  "data=measured with data.path pointing at the records")
            from stages.generate.measured import (  # lazy: saves 2.3 s of start-up (mlflow, via pipeline.runner)
                reference,
            )
            r = reference(cfg, s, system)["r"]
        else:
            r = build_reference(s, system.Ts)
        try:
            system.check_reference(r)
        except ValueError as exc:
            raise ConfigError(f"reference '{s['name']}' is outside the limits of system "
                              f"'{system.name}': {exc}") from exc
        out[s["name"]] = r
    return out
