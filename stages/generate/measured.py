"""data.kind=measured: load a measured record (Parquet/CSV with t, r, u, y(, d), or EMPS .mat).

``data.path`` is a file, or a folder holding ``data.file`` (the training record; EMPS:
``DATA_EMPS``).  Before any work (:func:`check`): the file exists and parses, every value is a
finite, plausible number, the sample time (t column and/or sidecar ``Ts``) is positive,
uniform, increasing and equal to ``system.Ts``; for a measured system (:class:`pipeline.systems.
measured.Recording`) the file's controller constants match the config and the recorded force
is the configured controller's output on the recorded position (signs, units, gains).
Evaluation references of kind ``measured`` (:func:`reference`) load the test file the same way.
"""
from __future__ import annotations

from pathlib import Path

from pipeline import data
from pipeline.runner import ROOT, ConfigError
from pipeline.systems.measured import Recording

FORMATS = ("table", "emps")
#: relative rms of (recorded force - controller law on the recorded position) above which the
#: record is not this loop (EMPS: 0.2 % in the training file; a sign or unit error gives > 100 %)
CONTROLLER_RTOL = 0.05
#: shortest record an evaluation reference may be (the published convention reads t(10) - t(9))
MIN_REFERENCE = 20


def _folder_and_file(cfg, file: str | None) -> tuple[Path, str | None]:
    p = Path(str(cfg.data.path))
    p = p if p.is_absolute() else ROOT / p
    return p, (str(file) if file not in (None, "") else None)


def load_file(cfg, file: str | None = None) -> data.Dataset:
    """Load ``file`` (default ``data.file``) from ``data.path`` in ``data.format``; ValueError /
    FileNotFoundError with the file named on any problem."""
    fmt = str(cfg.data.get("format", "table"))
    if fmt not in FORMATS:
        raise ConfigError(f"data.format={fmt!r}; choose one of {FORMATS}")
    folder, name = _folder_and_file(cfg, file if file is not None else cfg.data.get("file"))
    if fmt == "emps":
        return data.load_emps(folder, name or "DATA_EMPS")
    target = folder
    if name is not None and folder.is_dir():
        target = folder / name
        if target.suffix not in (".parquet", ".csv"):
            target = next((target.with_suffix(s) for s in (".parquet", ".csv")
                           if target.with_suffix(s).exists()), target.with_suffix(".parquet"))
    ds = data.load(target)
    dist = cfg.system.get("disturbance") if "system" in cfg else None
    if dist and dist in ds.frame and "d" not in ds.frame:   # the system's disturbance column is d
        ds.frame = ds.frame.rename(columns={dist: "d"})
    return ds


def check_record(ds: data.Dataset, system, source: str, min_len: int = 0) -> None:
    """A loaded record against the system it is meant for (length, sample time, controller, units)."""
    if len(ds) < min_len:
        raise ValueError(f"{source}: {len(ds)} samples; at least {min_len} are needed here (a short record cannot "
                         "identify or score the loop): give the whole recording")
    Ts = float(ds.Ts)
    sys_Ts = float(getattr(system, "Ts", Ts))
    if abs(Ts - sys_Ts) > data.TS_RTOL * sys_Ts:
        raise ValueError(f"{source}: the data are sampled at Ts = {Ts:.6g} s but system "
                         f"'{getattr(system, 'name', '?')}' has Ts = {sys_Ts:g} s; set system.Ts={Ts:.6g} "
                         "(a wrong Ts scales an identified mass by its square)")
    if not isinstance(system, Recording):
        return
    ctrl = system.ctrl
    for k in data.EMPS_CONSTANTS:
        if k in ds.meta and ds.meta[k] is not None and abs(float(ds.meta[k]) - getattr(ctrl, k)) > \
                1e-6 * abs(float(ds.meta[k])):
            raise ValueError(f"{source}: the file's {k} = {ds.meta[k]} differs from system.controller.{k} = "
                             f"{getattr(ctrl, k)}; make the config match the machine the data came from")
    d = ds["d"] if "d" in ds.frame else 0.0 * ds["y"]
    rel = ctrl.residual(ds["r"], ds["y"], ds["u"], d, sys_Ts)
    if not rel < CONTROLLER_RTOL:
        raise ValueError(f"{source}: the recorded force u is not the configured controller's output on the "
                         f"recorded position (relative rms residual {100 * rel:.1f} % > "
                         f"{100 * CONTROLLER_RTOL:.0f} %): check the signs and units of u [N] and y [m], "
                         "system.controller (kp, kv, gtau, v_sat), system.Ts, and the disturbance column d")


def check(cfg, system) -> None:
    try:
        ds = load_file(cfg)
        need = system.min_samples() if isinstance(system, Recording) else 0   # filtered LS trims, decimates
        check_record(ds, system, ds.meta.get("source", str(cfg.data.path)), min_len=need)
    except (ValueError, FileNotFoundError) as exc:
        raise ConfigError(str(exc)) from exc


def make(cfg, system, ctx) -> data.Dataset:
    return load_file(cfg)


def reference(cfg, spec: dict, system) -> data.Dataset:
    """The record an evaluation reference of kind ``measured`` names (``spec['file']``), checked."""
    if not spec.get("file"):
        raise ConfigError(f"reference '{spec.get('name')}' of kind 'measured' names no file; give the recorded "
                          "file inside data.path, e.g. {name: test, kind: measured, file: DATA_EMPS_PULSES}")
    try:
        ds = load_file(cfg, spec["file"])
        check_record(ds, system, ds.meta.get("source", str(spec["file"])), min_len=MIN_REFERENCE)
    except FileNotFoundError as exc:
        raise ConfigError(f"reference '{spec.get('name')}': {str(exc).split(';')[0]}; check data.path and the "
                          "reference's file") from exc
    except ValueError as exc:
        raise ConfigError(f"reference '{spec.get('name')}': {exc}") from exc
    return ds
