"""generate: make (or load) the identification data set (SPEC §4), chosen by ``data.kind``.

Implementations: ``stages/generate/<kind>.py`` exposing ``make(cfg, system, ctx) -> Dataset`` and
optionally ``check(cfg, system)``.  Every set is saved as Parquet + JSON sidecar and logged to
MLflow as a dataset input.
"""
from __future__ import annotations

from omegaconf import OmegaConf

from pipeline.runner import implementation

UPSTREAM = ()
DEPENDS = ("system", "data", "seed")
VERSION = 1
KIND_KEY = "data.kind"


def validate(cfg, system) -> None:
    impl = implementation("generate", str(cfg.data.kind))
    if hasattr(impl, "check"):
        impl.check(cfg, system)


def run(ctx) -> dict:
    cfg = ctx.cfg
    impl = implementation("generate", str(cfg.data.kind))
    ds = impl.make(cfg, ctx.system, ctx)
    ds.meta.update({"system": getattr(ctx.system, "name", ""), "seed": int(cfg.seed),
                    "config_hash": ctx.key,
                    "data": OmegaConf.to_container(cfg.data, resolve=True)})
    ds.meta.setdefault("Ts", getattr(ctx.system, "Ts", None))
    ctx.dataset(ds, "train")
    ctx.metric("n_samples", len(ds))
    return {"dataset": ds}
