"""The dataset type and its I/O: Parquet + JSON sidecar (DESIGN, output contracts; SPEC §4).

A :class:`Dataset` is a table of samples with columns ``t, r, u, y`` plus, where known,
``u_ff, u_fb, f_opt, y_clean, v`` and ``segment`` (the index of the experiment a sample
belongs to: identification never builds a regressor across a segment boundary), and a dict of
metadata (system, Ts, seed, config hash, ...).  Simulated and measured data share it.
"""
from __future__ import annotations

import json
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from pipeline.atomic import replace_file

REQUIRED = ("t", "r", "u", "y")
OPTIONAL = ("u_ff", "u_fb", "f_opt", "y_clean", "v", "segment", "d")
#: measured data: |value| above this is not a plausible SI signal (a corrupted or mis-scaled file)
MAX_ABS = 1e12
#: relative tolerance on the uniformity of a time column and on sample-time agreement
TS_RTOL = 1e-3


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
    """Raise a clear error on missing or non-numeric columns, NaN/inf or implausible values."""
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        found = [str(c) for c in df.columns]
        hint = (" (one column holding them all: is the file separated by ';' or tabs? A dataset's CSV is "
                "comma-separated)" if len(found) == 1 and any(ch in found[0] for ch in ";\t") else "")
        raise ValueError(f"{source}: missing column(s) {missing}; found {found[:12]}{' …' if len(found) > 12 else ''}"
                         f"{hint}; a dataset needs {list(REQUIRED)} (optional {list(OPTIONAL)}), lower case, no "
                         "units in the header (those go in the sidecar JSON)")
    if len(df) < 2:
        raise ValueError(f"{source}: {len(df)} row(s); a dataset needs at least 2 samples")
    for c in df.columns:
        if c == "segment":
            continue
        if not pd.api.types.is_numeric_dtype(df[c]) or pd.api.types.is_bool_dtype(df[c]):
            bad = pd.to_numeric(df[c], errors="coerce").isna() & df[c].notna()
            first = df[c][bad].iloc[0] if bad.any() else df[c].iloc[0]
            raise ValueError(f"{source}: column '{c}' is not numeric (e.g. {first!r} at row "
                             f"{int(np.flatnonzero(bad.to_numpy())[0]) if bad.any() else 0}); give numbers in SI "
                             "units (no text, units or thousands separators in the cells)")
        a = df[c].to_numpy(dtype=np.float64)
        bad = ~np.isfinite(a)
        if bad.any():
            raise ValueError(f"{source}: column '{c}' has {int(bad.sum())} NaN/inf value(s), first at "
                             f"row {int(np.flatnonzero(bad)[0])}; clean or cut those samples first")
        big = np.abs(a) > MAX_ABS
        if big.any():
            k = int(np.flatnonzero(big)[0])
            raise ValueError(f"{source}: column '{c}' has |value| = {abs(a[k]):.3g} at row {k} (> {MAX_ABS:g}); "
                             "not a plausible SI signal: check the file's units and scaling")


def sample_time(t, Ts_sidecar, source: str, rtol: float = TS_RTOL, given_by: str = "the sidecar") -> float:
    """The sample time of a record [s] from its time column ``t`` (required) and optional sidecar ``Ts``.

    ``t`` must be increasing and uniform to ``rtol`` (relative spread of its steps), the sidecar
    positive and equal to t's step (to ``rtol``).  Raises ValueError naming the problem and the fix.
    """
    if Ts_sidecar is not None:
        try:
            Ts_sidecar = float(Ts_sidecar)
        except (TypeError, ValueError):
            raise ValueError(f"{source}: sidecar 'Ts' = {Ts_sidecar!r} is not a number; give the sample "
                             "time in s") from None
        if not (np.isfinite(Ts_sidecar) and Ts_sidecar > 0):
            raise ValueError(f"{source}: sidecar 'Ts' = {Ts_sidecar!r} is not a positive sample time; give "
                             "the sample time in s")
    t = np.asarray(t, dtype=np.float64)
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.flatnonzero(dt <= 0)[0])
        raise ValueError(f"{source}: column 't' is not increasing (t[{k + 1}] = {float(t[k + 1])!r} <= t[{k}] = "
                         f"{float(t[k])!r}); sort the samples by time and drop repeated ones")
    med = float(np.median(dt))
    spread = float(np.max(np.abs(dt - med)) / med)
    if spread > rtol:
        raise ValueError(f"{source}: column 't' is not uniformly sampled (steps {dt.min():.6g} to {dt.max():.6g} "
                         f"s, spread {spread:.2g} > {rtol:g}); resample the record to a uniform grid first")
    if Ts_sidecar is not None and abs(Ts_sidecar - med) > rtol * med:
        raise ValueError(f"{source}: {given_by} says Ts = {Ts_sidecar:g} s but column 't' steps {med:.6g} s; "
                         "make them agree")
    return med if Ts_sidecar is None else Ts_sidecar   # the sidecar's exact value when it agrees


def save(ds: Dataset, path: str | Path) -> Path:
    """Write ``<path>.parquet`` and its JSON sidecar ``<path>.json`` atomically."""
    path = Path(path).with_suffix(".parquet")
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    ds.frame.to_parquet(buf, index=False)
    replace_file(path, buf.getvalue())
    replace_file(path.with_suffix(".json"), json.dumps(ds.meta, indent=1, sort_keys=True, default=str))
    return path


def load(path: str | Path) -> Dataset:
    """Read a Parquet or CSV dataset (+ JSON sidecar); clear errors for a missing file or bad data.
    The sample time comes from the sidecar's ``Ts`` and/or the ``t`` column, checked by
    :func:`sample_time`."""
    path = Path(path)
    if path.suffix not in (".parquet", ".csv"):
        path = path.with_suffix(".parquet")
    if not path.exists():
        where = (f"the folder {path.parent} does not exist either" if not path.parent.exists()
                 else f"files there: {sorted(p.name for p in path.parent.iterdir())[:8]}")
        raise FileNotFoundError(f"data file {path} does not exist ({where}); check data.path (absolute, or "
                                "relative to the repo root) and data.file, or, for a simulated plant, generate it "
                                "with stages=[generate]")
    try:
        frame = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise ValueError(f"{path}: the file is empty; a dataset needs columns {list(REQUIRED)}") from None
    side = path.with_suffix(".json")
    try:
        meta = json.loads(side.read_text()) if side.exists() else {}
    except json.JSONDecodeError as exc:
        raise ValueError(f"{side}: the sidecar is not valid JSON ({exc}); it holds e.g. {{\"Ts\": 0.001}}") from None
    meta["source"] = str(path)
    validate_frame(frame, str(path))
    meta["Ts"] = sample_time(frame["t"].to_numpy(np.float64), meta.get("Ts"), str(path))
    return Dataset(frame, meta)


#: the EMPS controller constants stored in its .mat files (checked against the system config)
EMPS_CONSTANTS = ("gtau", "kp", "kv")


def load_emps(folder: str | Path, which: str = "DATA_EMPS") -> Dataset:
    """The EMPS benchmark (SPEC §2.5; Janot, Gautier, Brunot 2019): force τ = gtau·vir [N] as u,
    position qm [m] as y, reference qg [m] as r, and the test file's force pulses ``pulses_N``
    [V, added to vir after the saturation] as the measured disturbance d (zero in the training
    file).  The file's gtau, kp, kv go to the metadata (the system config is checked against them)."""
    from scipy.io import loadmat  # lazy: saves 0.2 s of start-up (scipy.io: only the EMPS .mat loader reads it)
    path = Path(folder) / f"{which}.mat"
    if not path.exists():
        here = Path(folder)
        tables = [p.name for p in (here.iterdir() if here.is_dir() else []) if p.suffix in (".csv", ".parquet")]
        own = (f" (data.path holds {sorted(tables)[:6]}: a table of your own machine is read with data.format=table)"
               if tables else "")
        raise FileNotFoundError(f"EMPS file {path} not found{own}; point data.path to the folder holding "
                                "DATA_EMPS.mat and DATA_EMPS_PULSES.mat (e.g. ../shared/data/emps)")
    m = loadmat(path)
    need = ("t", "qm", "qg", "vir") + EMPS_CONSTANTS
    missing = [k for k in need if k not in m]
    if missing:
        raise ValueError(f"{path}: variable(s) {missing} missing; an EMPS file holds {list(need)}")
    col = {k: np.asarray(m[k], dtype=np.float64).ravel() for k in ("t", "qm", "qg", "vir")}
    if "pulses_N" in m:
        col["pulses_N"] = np.asarray(m["pulses_N"], dtype=np.float64).ravel()
    lengths = {k: v.size for k, v in col.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"{path}: variables of different lengths {lengths}; every signal needs one sample per "
                         "time step: cut them to a common length")
    const = {k: float(np.asarray(m[k]).ravel()[0]) for k in EMPS_CONSTANTS}
    d = col.get("pulses_N", np.zeros_like(col["t"]))
    frame = pd.DataFrame({"t": col["t"] - col["t"][0], "r": col["qg"], "u": const["gtau"] * col["vir"],
                          "y": col["qm"], "d": d})
    validate_frame(frame, str(path))
    Ts = sample_time(col["t"], None, str(path))
    return Dataset(frame, {"system": "emps", "Ts": Ts, "source": str(path), **const,
                           "script_step": float(col["t"][9] - col["t"][8])})
