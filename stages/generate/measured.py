"""data.kind=measured: load a measured data set (Parquet/CSV with t, r, u, y, or EMPS .mat)."""
from __future__ import annotations

from pathlib import Path

from pipeline import data
from pipeline.runner import ROOT, ConfigError


def _path(cfg) -> Path:
    p = Path(str(cfg.data.path))
    p = p if p.is_absolute() else ROOT / p
    if cfg.data.get("format") != "emps" and p.suffix not in (".parquet", ".csv"):
        p = p.with_suffix(".parquet")  # as pipeline.data.load reads it
    return p


def check(cfg, system) -> None:
    p = _path(cfg)
    target = p / f"{cfg.data.get('file', 'DATA_EMPS')}.mat" if cfg.data.get("format") == "emps" else p
    if not target.exists():
        raise ConfigError(f"data file {target} does not exist; set data.path to the measured data "
                          "(absolute, or relative to the repo root)")
    try:  # loading is cheap: NaN/inf or missing columns fail here, before any work
        _load(cfg)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc


def _load(cfg) -> data.Dataset:
    if cfg.data.get("format") == "emps":
        return data.load_emps(_path(cfg), str(cfg.data.get("file", "DATA_EMPS")))
    return data.load(_path(cfg))


def make(cfg, system, ctx) -> data.Dataset:
    return _load(cfg)
