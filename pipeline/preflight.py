"""Pre-flight of ``make reproduce``'s queue (issue 51 item 7): before any job starts (and before any
MLflow run exists), every recorded data file each queued experiment reads must exist and parse.
Before, a clone without the EMPS recordings beside it ran 18 minutes of jobs, then stopped on
"EMPS file … not found".  A missing or unreadable file is one line: which files, where they were
looked for, how to get them (the EMPS data are public) and how to run without those experiments.
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline.errors import ConfigError

#: where the EMPS recordings come from (conf/system/emps.yaml; Janot, Gautier, Brunot 2019)
EMPS_SOURCE = ("they are the public EMPS benchmark (A. Janot, M. Gautier, M. Brunot, \"Data Set and Reference "
               "Models of EMPS\", 2019): download DATA_EMPS.mat and DATA_EMPS_PULSES.mat from the nonlinear "
               "system identification benchmarks (nonlinearbenchmark.org, or the nonlinear_benchmarks Python "
               "package's EMPS loader) into that folder, or point data.path at the folder holding them")


def unreadable(cfg: DictConfig, read: dict[Path, str | None] | None = None) -> dict[Path, str]:
    """The data files the job of ``cfg`` reads that are missing or do not parse: path -> why (empty for a
    job that reads no recorded file); ``read``: the files already read (path -> why, None if good), kept."""
    read = {} if read is None else read
    if str(OmegaConf.select(cfg, "data.kind", default="")) != "measured":
        return {}
    from stages.generate import measured  # lazy: saves 0.4 s of start-up (the measured-data stage, its loaders)
    out = {}
    try:
        files = measured.data_files(cfg)
    except ConfigError as exc:
        return {Path(str(cfg.data.path)): str(exc)}
    for f in files:
        target = measured._target(cfg, f)
        if target not in read:
            try:
                measured.load_file(cfg, f)
                read[target] = None
            except Exception as exc:  # noqa: BLE001 — the parsers raise several types (scipy's MatReadError)
                read[target] = str(exc).split(";")[0] or type(exc).__name__
        if read[target] is not None:
            out[target] = read[target]
    return out


def check(jobs: list[tuple[str, DictConfig]]) -> None:
    """Raise :class:`ConfigError` (one line) if an experiment of ``jobs`` ((name, composed config) in
    queue order) reads a data file that is missing or does not parse; each file is read once."""
    seen: dict[Path, str | None] = {}
    bad: dict[str, list[Path]] = {}
    for name, cfg in jobs:
        for path in unreadable(cfg, seen):
            bad.setdefault(name, []).append(path)
    if not bad:
        return
    paths = sorted({p for ps in bad.values() for p in ps})
    folders = sorted({str(p.parent.resolve()) for p in paths})
    emps = any(p.name.startswith("DATA_EMPS") for p in paths)
    others = [n for n, _ in jobs if n not in bad]
    run_without = (f"run without them: make reproduce EXPERIMENTS=\"{' '.join(dict.fromkeys(others))}\""
                   if others else "no experiment of this queue runs without them")
    raise ConfigError(f"experiment(s) {', '.join(bad)} read data file(s) that are missing or unreadable: "
                      f"{', '.join(p.name for p in paths)}, looked for in {', '.join(folders)} "
                      f"({seen[paths[0]]}); " + (EMPS_SOURCE if emps else "give the recordings there or set "
                                                 "data.path to their folder") + f"; or {run_without}")
