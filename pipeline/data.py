"""The dataset type and its I/O: Parquet + JSON sidecar (DESIGN, output contracts; SPEC §4).

A :class:`Dataset` is a table of samples with columns ``t, r, u, y`` plus, where known,
``u_ff, u_fb, f_opt, y_clean, v`` and ``segment`` (the index of the experiment a sample
belongs to: identification never builds a regressor across a segment boundary), and a dict of
metadata (system, Ts, seed, config hash, ...).  Simulated and measured data share it.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

REQUIRED = ("t", "r", "u", "y")
OPTIONAL = ("u_ff", "u_fb", "f_opt", "y_clean", "v", "segment")


@dataclass
class Dataset:
    frame: pd.DataFrame
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate_frame(self.frame, self.meta.get("source", "dataset"))

    @property
    def Ts(self) -> float:
        return float(self.meta["Ts"])

    def __len__(self) -> int:
        return len(self.frame)

    def __getitem__(self, col: str) -> np.ndarray:
        return self.frame[col].to_numpy(dtype=np.float64)

    def segments(self) -> Iterator[pd.DataFrame]:
        """The contiguous experiments of the set (one if there is no ``segment`` column)."""
        if "segment" not in self.frame:
            yield self.frame
            return
        for _, seg in self.frame.groupby("segment", sort=True):
            yield seg

    @classmethod
    def from_segments(cls, parts: list[dict[str, np.ndarray]], meta: dict) -> "Dataset":
        """Concatenate per-segment column dicts (t restarts at 0 in each segment)."""
        frames = []
        for i, cols in enumerate(parts):
            df = pd.DataFrame({k: np.asarray(v, dtype=np.float64) for k, v in cols.items()})
            df["segment"] = i
            frames.append(df)
        return cls(pd.concat(frames, ignore_index=True), dict(meta))


def validate_frame(df: pd.DataFrame, source: str) -> None:
    """Raise a clear error on missing columns or NaN/inf values."""
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise ValueError(f"{source}: missing column(s) {missing}; a dataset needs {list(REQUIRED)} "
                         f"(optional {list(OPTIONAL)})")
    for c in df.columns:
        if c == "segment":
            continue
        a = df[c].to_numpy(dtype=np.float64)
        bad = ~np.isfinite(a)
        if bad.any():
            raise ValueError(f"{source}: column '{c}' has {int(bad.sum())} NaN/inf value(s), first at "
                             f"row {int(np.flatnonzero(bad)[0])}; clean or cut those samples first")


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def save(ds: Dataset, path: str | Path) -> Path:
    """Write ``<path>.parquet`` and its JSON sidecar ``<path>.json`` atomically."""
    path = Path(path).with_suffix(".parquet")
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, lambda p: ds.frame.to_parquet(p, index=False))
    _atomic_write(path.with_suffix(".json"),
                  lambda p: p.write_text(json.dumps(ds.meta, indent=1, sort_keys=True, default=str)))
    return path


def load(path: str | Path) -> Dataset:
    """Read a Parquet dataset (+ sidecar); clear errors for a missing file or bad data."""
    path = Path(path)
    if path.suffix not in (".parquet", ".csv"):
        path = path.with_suffix(".parquet")
    if not path.exists():
        raise FileNotFoundError(f"data file {path} does not exist; check data.path (absolute, or "
                                "relative to the repo root) or generate it with stages=[generate]")
    frame = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    side = path.with_suffix(".json")
    meta = json.loads(side.read_text()) if side.exists() else {}
    meta.setdefault("source", str(path))
    if "Ts" not in meta:
        t = frame["t"].to_numpy() if "t" in frame else None
        if t is None or len(t) < 2:
            raise ValueError(f"{path}: no sidecar with 'Ts' and no usable 't' column; add {side.name} "
                             "with {\"Ts\": <sample time in s>}")
        meta["Ts"] = float(np.median(np.diff(t)))
    return Dataset(frame, meta)


def load_emps(folder: str | Path, which: str = "DATA_EMPS") -> Dataset:
    """The EMPS benchmark (SPEC §2.5): force τ = gtau·vir as u, position qm as y, qg as r."""
    from scipy.io import loadmat
    path = Path(folder) / f"{which}.mat"
    if not path.exists():
        raise FileNotFoundError(f"EMPS file {path} not found; point data.path to the folder holding "
                                "DATA_EMPS.mat and DATA_EMPS_PULSES.mat (e.g. ../shared/data/emps)")
    m = loadmat(path)
    col = {k: np.asarray(m[k], dtype=np.float64).ravel() for k in ("t", "qm", "qg", "vir")}
    gtau = float(np.asarray(m["gtau"]).ravel()[0])
    frame = pd.DataFrame({"t": col["t"] - col["t"][0], "r": col["qg"], "u": gtau * col["vir"],
                          "y": col["qm"]})
    return Dataset(frame, {"system": "emps", "Ts": float(np.median(np.diff(col["t"]))),
                           "source": str(path), "gtau": gtau})
