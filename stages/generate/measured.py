"""data.kind=measured: load a measured record (Parquet/CSV with t, r, u, y(, d), or EMPS .mat).

``data.path`` is a file, or a folder holding ``data.file`` (the training record; EMPS:
``DATA_EMPS``) or ``data.files`` (several training records, each a segment of the dataset).
Before any work (:func:`check`): the file exists and parses, every value is a
finite, plausible number, the sample time (t column and/or sidecar ``Ts``) is positive,
uniform, increasing and equal to ``system.Ts``; for a measured system (:class:`pipeline.systems.
measured.Recording`) the file's controller constants match the config and the recorded force
is the configured controller's output on the recorded position (signs, units, gains).
Evaluation references of kind ``measured`` (:func:`reference`) load the test file the same way.
"""
from __future__ import annotations

import hashlib
import warnings
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from omegaconf import OmegaConf

from pipeline import data
from pipeline.params import schema, spec
from pipeline.runner import ROOT, ConfigError


@schema
class Params:
    kind: Literal["measured"]
    name: str = "measured"
    # a file (Parquet/CSV) or a folder holding `file`; absolute or relative to the repo
    path: str = spec(example="../shared/data/emps")
    # table: Parquet/CSV with t [s], r [m], u [N], y [m] (+ optional d, sidecar Ts) | emps: .mat
    format: Literal["table", "emps"] = "table"     # = stages.generate.measured.FORMATS
    # the training record inside `path` (emps: DATA_EMPS); null = `path` is the file
    file: Optional[str] = None
    # several training records inside `path` instead of `file`, e.g. [run1.csv, run2.csv]: each is its own segment
    # (filtered, regressed and simulated on its own, no seam)
    files: Optional[list[str]] = spec(None, min_len=1, example=["run1.csv", "run2.csv"])   # several records


FORMATS = ("table", "emps")
#: relative rms of (recorded force - controller law on the recorded position) above which the
#: record is not this loop (EMPS: 0.2 % in the training file; a sign or unit error gives > 100 %)
CONTROLLER_RTOL = 0.05
#: above this (and below CONTROLLER_RTOL) a variant of the controller that fits twice as well is named
CONTROLLER_NOTE = 0.01
#: shortest record an evaluation reference may be (the published convention reads t(10) - t(9))
MIN_REFERENCE = 20
#: an evaluation record shorter than this is scored but flagged (a 25-row test file passed without a word)
SHORT_REFERENCE = 500


def _folder_and_file(cfg, file: str | None) -> tuple[Path, str | None]:
    p = Path(str(cfg.data.path))
    p = p if p.is_absolute() else ROOT / p
    return p, (str(file) if file not in (None, "") else None)


_HASHES: dict[tuple, str] = {}      # (path, size, mtime_ns) -> SHA-256, per process


def _sha256(path: Path) -> str:
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _HASHES:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _HASHES[key] = h.hexdigest()
    return _HASHES[key]


def data_files(cfg) -> list:
    """The files (``data.file`` names, None = ``data.path`` itself) a job reads: the training file(s) and
    every evaluation reference's recording (:func:`load_file` reads each; the queue's pre-flight too)."""
    files = list(training_files(cfg))
    refs = OmegaConf.to_container(cfg.evaluate.references, resolve=True) \
        if cfg.get("evaluate") is not None and cfg.evaluate.get("references") is not None else []
    specs = list(refs.values()) if isinstance(refs, dict) else refs   # a list, or a mapping by name
    return files + [s["file"] for s in specs if isinstance(s, dict) and s.get("kind") == "measured" and s.get("file")]


def content_key(cfg) -> dict[str, str]:
    """SHA-256 of every file this job reads measured data from: the training file(s) and every
    evaluation reference's recording, wherever they are (beside data.path, in a sub-folder, or by
    an absolute path): part of the stage's cache key (runner.stage_key), so a recording replaced under
    the same name is reread, never served from the cache of the old one (issue 24). A missing file
    adds nothing here: :func:`check` names it before any work."""
    out = {}
    for f in data_files(cfg):
        try:
            target = _target(cfg, f)
        except ConfigError:
            continue
        if target.is_file():
            out[str(f) if f is not None else "data.path"] = _sha256(target)
    return out


def _target(cfg, file: str | None) -> Path:
    """The file :func:`load_file` reads for ``file`` (default ``data.file``)."""
    fmt = str(cfg.data.format)
    folder, name = _folder_and_file(cfg, file if file is not None else cfg.data.get("file"))
    if folder.is_file() and name is not None and name not in (folder.name, folder.stem):
        folder = folder.parent       # data.path is the training file: another file is read beside it
    elif folder.is_file() and fmt == "emps":
        folder, name = folder.parent, folder.stem
    if fmt == "emps":
        return folder / f"{name or 'DATA_EMPS'}.mat"
    target = folder
    if name is not None and folder.is_dir():
        target = folder / name
        if target.suffix not in (".parquet", ".csv"):
            target = next((target.with_suffix(s) for s in (".parquet", ".csv")
                           if target.with_suffix(s).exists()), target.with_suffix(".parquet"))
    return target


def load_file(cfg, file: str | None = None) -> data.Dataset:
    """Load ``file`` (default ``data.file``) from ``data.path`` in ``data.format``; ValueError /
    FileNotFoundError with the file named on any problem."""
    fmt = str(cfg.data.format)
    if fmt not in FORMATS:
        raise ConfigError(f"data.format={fmt!r}; choose one of {FORMATS}")
    target = _target(cfg, file)
    if fmt == "emps":
        return data.load_emps(target.parent, target.stem)
    ds = data.load(target)
    if "segment" in ds.frame:   # issue 51: read as labels, it split EMPS-like data into 1-row "experiments"
        warnings.warn(f"{target}: its column 'segment' is ignored (several experiments are several files: "
                      "data.files=[run1.csv, run2.csv]); rename or drop it to silence this", stacklevel=2)
        ds.frame = ds.frame.drop(columns="segment")
    dist = cfg.system.get("disturbance") if "system" in cfg else None
    if dist and dist in ds.frame and "d" not in ds.frame:   # the system's disturbance column is d
        ds.frame = ds.frame.rename(columns={dist: "d"})
    return ds


def check_record(ds: data.Dataset, system, source: str, min_len: int = 0,
                 uses_controller: bool = True, reference: bool = False) -> None:
    """A loaded record against the system it is meant for (length, sample time, controller, units).
    A controller that does not fit the record is an error where the run uses the controller
    (``uses_controller``: replay, feedforward), else a warning."""
    if len(ds) < min_len:
        raise ValueError(f"{source}: {len(ds)} samples; at least {min_len} are needed here (a short record cannot "
                         "identify or score the loop): give the whole recording")
    Ts = float(ds.Ts)
    sys_Ts = float(getattr(system, "Ts", Ts))
    if abs(Ts - sys_Ts) > data.TS_RTOL * sys_Ts:
        if reference:     # the training data fix system.Ts: an evaluation file must match them
            raise ValueError(f"{source}: this evaluation recording is sampled at Ts = {Ts:.6g} s but the system (and "
                             f"its training data) at Ts = {sys_Ts:g} s; record or resample the evaluation run at "
                             f"{sys_Ts:g} s (system.Ts would no longer fit the training data)")
        raise ValueError(f"{source}: the data are sampled at Ts = {Ts:.6g} s but system "
                         f"'{getattr(system, 'name', '?')}' has Ts = {sys_Ts:g} s; set system.Ts={Ts:.6g} "
                         "(a wrong Ts scales an identified mass by its square)")
    if system is None or not system.measured:
        return
    msg = units_warning(ds, Ts)
    if msg:
        warnings.warn(f"{source}: {msg}", stacklevel=2)
    ctrl, params = system.ctrl, dict(system.ctrl.params)
    for k in data.EMPS_CONSTANTS:
        if k in ds.meta and ds.meta[k] is not None and (k not in params or abs(float(ds.meta[k]) - params[k]) >
                                                         1e-6 * abs(float(ds.meta[k]))):
            raise ValueError(f"{source}: the file's {k} = {ds.meta[k]} differs from system.controller.{k} = "
                             f"{params.get(k)}; make the config match the machine the data came from")
    d = ds["d"] if "d" in ds.frame else 0.0 * ds["y"]
    rel = ctrl.check(ds["r"], ds["y"], ds["u"], d)
    if not rel < CONTROLLER_RTOL:
        hints = ctrl.diagnose(ds["r"], ds["y"], ds["u"], d, CONTROLLER_RTOL)
        msg = (f"{source}: the recorded force u is not the output of the configured controller, "
               f"{ctrl.describe()}, on the recorded r and y (relative equation error {100 * rel:.1f} % > "
               f"{100 * CONTROLLER_RTOL:.0f} %). " + ("What fits: " + "; ".join(hints) + ". " if hints else
               "No gain, sign, delay or error-feedback variant of it fits: the structure is different. ") +
               "Give the machine's controller as system.controller (kind: lti with num, den in powers of z⁻¹, "
               "num_r for a 2-DOF reference path, delay, gtau, v_sat; README \"Your own machine's data\"); "
               "check the signs and units of u [N] and y [m] and the disturbance column d")
        if uses_controller:
            raise ValueError(msg + ". Only the physics least squares runs without it "
                             "(stages=[generate,baseline])")
        warnings.warn(msg, stacklevel=2)
    else:
        msg = delay_warning(ctrl, ds["r"], ds["y"], ds["u"], d, rel)
        hints = ctrl.diagnose(ds["r"], ds["y"], ds["u"], d, rel / 2) if not msg and rel > CONTROLLER_NOTE else []
        if msg:
            warnings.warn(f"{source}: {msg}", stacklevel=2)
        elif hints:   # within CONTROLLER_RTOL, but a variant fits twice as well (a gain ×1.04 passed silently)
            warnings.warn(f"{source}: the recorded force u is the configured controller's output to {100 * rel:.1f} % "
                          f"(EMPS: 0.2 %), and a variant fits better: {'; '.join(hints)}", stacklevel=2)
    _check_disturbance(ds, ctrl, source)


#: a recorded speed above this [m/s] is not a motion stage's: y (and r) are likely not in metres
PLAUSIBLE_SPEED = 20.0


def units_warning(ds, Ts: float) -> str | None:
    """A warning when the recorded motion is implausible in metres (a recording in mm moves 1000x faster):
    the controller check cannot see it when the gains were scaled to match, and a mass comes out 1000x off."""
    y = np.asarray(ds["y"], dtype=np.float64)
    v = float(np.max(np.abs(np.diff(y)))) / Ts if y.size > 1 else 0.0
    if v <= PLAUSIBLE_SPEED:
        return None
    return (f"the recorded position moves at up to {v:.4g} m/s, above the {PLAUSIBLE_SPEED:g} m/s of any motion stage: "
            "are y and r in metres (not mm or µm), and u in newtons? The pipeline's units are SI (README \"Your own "
            "machine's data\")")


def delay_warning(ctrl, r, y, u, d, rel: float) -> str | None:
    """A warning when another controller delay fits the record 10x better than the configured one."""
    better = ctrl.better_delay(r, y, u, d, rel)
    if better is None:
        return None
    D, res = better
    return (f"the configured controller fits the recording (equation error {100 * rel:.2g} %), but with a delay of "
            f"{D} samples instead of {ctrl.delay} it fits {rel / max(res, 1e-300):.0f}x better ({100 * res:.2g} %): "
            f"check system.controller.delay (set +system.controller.delay={D} if the machine's output is delayed so)")


#: a measured disturbance is suspect when it carries this share of the recorded force's rms ...
DISTURBANCE_SHARE = 0.5
#: ... and changes value at more than this fraction of the samples
DISTURBANCE_ACTIVE = 0.5


def disturbance_diagnostics(ds, ctrl) -> tuple[float, float]:
    """(share, active): rms(gtau d)/rms(u), and the fraction of samples at which d changes value.

    Whether d was injected or is a controller mismatch put into d (u minus a wrong law) cannot be
    told from its size or its correlation with the motion (any force is a linear function of the
    motion through M q̈; the EMPS test pulses are 98 % "explained" by lags of r and y).  What
    differs is its texture: an injected test signal is a step or pulse sequence (EMPS: d changes at
    0.2 % of the samples), a law on the measured position changes at every sample (sensor noise
    through the feedback)."""
    d = np.asarray(ds["d"], dtype=np.float64)
    share = float(np.linalg.norm(ctrl.gtau * d) / max(np.linalg.norm(ds["u"]), 1e-300))
    active = float(np.mean(np.diff(d) != 0)) if d.size > 1 else 0.0
    return share, active


def _check_disturbance(ds, ctrl, source: str) -> None:
    """Warn when the disturbance column d carries most of the recorded force *and* follows the
    motion: a controller that does not match the recording can be hidden in d (u minus the
    configured law put into d passes the controller check)."""
    if "d" not in ds.frame:
        return
    share, active = disturbance_diagnostics(ds, ctrl)
    if share > DISTURBANCE_SHARE and active > DISTURBANCE_ACTIVE:
        warnings.warn(f"{source}: the disturbance column d carries {100 * share:.0f} % of the recorded force's "
                      f"rms and changes at {100 * active:.0f} % of the samples: it looks like a controller output, "
                      "not an injected disturbance (a step or pulse sequence). If d was computed as u minus a "
                      "controller law, the configured controller does not match the machine and every replay "
                      "and feedforward built on it is wrong: give the real controller as system.controller",
                      DisturbanceShareWarning, stacklevel=2)


class DisturbanceShareWarning(UserWarning):
    """The measured disturbance carries most of the recorded force (issue 20)."""


def uses_controller(cfg) -> bool:
    """Whether a stage of this run replays the recorded loop or designs a feedforward for it: the
    closed-loop simulation-error training, invert, evaluate, export (the physics LS does not)."""
    stages = set(cfg.get("stages") or [])
    return bool(stages & {"invert", "evaluate", "export"}) or \
        ("train" in stages and str(OmegaConf.select(cfg, "identify.kind")) == "sim_error")


def training_files(cfg) -> list:
    """The training records: ``data.files`` (several, each its own segment) or ``data.file`` (one;
    None = ``data.path`` itself is the file)."""
    files, file = cfg.data.get("files"), cfg.data.get("file")
    path = _folder_and_file(cfg, None)[0]
    named = [str(f) for f in (files or [])] + ([str(file)] if file not in (None, "") else [])
    if path.is_file() and any(n not in (path.name, path.stem) for n in named):
        raise ConfigError(f"data.path={cfg.data.path} is a file and data.file(s)={named} name another: give the "
                          "folder as data.path with data.file, or the training file as data.path alone")
    if files:
        if file not in (None, ""):
            raise ConfigError(f"data.file={file!r} and data.files={list(files)} are both set; give one training "
                              "file as data.file or several as data.files")
        seen = {}
        for f in files:   # one record twice weighs it double and glues it to itself (issue 51)
            seen.setdefault(_target(cfg, str(f)).resolve(), []).append(str(f))
        twice = [v for v in seen.values() if len(v) > 1]
        if twice:
            raise ConfigError(f"data.files={list(files)} names the same file more than once ({twice[0]}); list "
                              "each training record once")
        return [str(f) for f in files]
    return [file]


def check(cfg, system) -> None:
    try:
        need = system.min_samples() if system is not None and system.measured else 0   # filtered LS trims, decimates
        for f in training_files(cfg):
            ds = load_file(cfg, f)
            if len(ds) < need:   # the physics baseline's settings, not the record, are what to change
                idim = {k: v for k, v in system.idim.items() if k in ("decimation", "trim")}
                raise ConfigError(f"{ds.meta.get('source', f)}: {len(ds)} samples, fewer than the {need} the "
                                  f"filtered least squares needs with system.idim {idim or '(defaults)'} (trim "
                                  "at each end, then 20 decimated rows): lower system.idim.trim or "
                                  "system.idim.decimation, or give a longer recording")
            check_record(ds, system, ds.meta.get("source", str(cfg.data.path)), min_len=need,
                         uses_controller=uses_controller(cfg))
    except (ValueError, FileNotFoundError) as exc:
        raise ConfigError(str(exc)) from exc


def load_training(cfg) -> data.Dataset:
    """The training records as one dataset: one file as it is; several as segments (column
    ``segment``; t restarts in each), so no regressor, filter or simulation crosses a boundary
    (a jump between two recordings is not a motion of the machine)."""
    files = training_files(cfg)
    sets = [load_file(cfg, f) for f in files]
    if len(sets) == 1:
        return sets[0]
    cols = ["t", "r", "u", "y"] + (["d"] if any("d" in ds.frame for ds in sets) else [])
    parts = [{c: (ds[c] if c in ds.frame else np.zeros(len(ds))) for c in cols} for ds in sets]
    meta = dict(sets[0].meta)
    meta["source"] = ", ".join(str(ds.meta.get("source", f)) for ds, f in zip(sets, files))
    return data.Dataset.from_segments(parts, meta)


def make(cfg, system, ctx) -> data.Dataset:
    ds = load_training(cfg)
    if system is not None and system.measured:   # the checks' numbers on the run (check() warned or refused already)
        segs = list(ds.segments())
        sig = [(g["r"].to_numpy(), g["y"].to_numpy(), g["u"].to_numpy(),
                g["d"].to_numpy() if "d" in g else 0.0 * g["y"].to_numpy()) for g in segs]
        rels = [system.ctrl.check(*s) for s in sig]
        rel = max(rels)
        ctx.metric("controller_equation_error", rel)
        ctx.metric("segments", len(segs))
        ctx.tag("controller", system.ctrl.describe())
        if not rel < CONTROLLER_RTOL:
            ctx.tag("controller_warning", f"the recorded u is not the configured controller's output "
                                          f"(equation error {100 * rel:.1f} %)")
        else:
            msg = delay_warning(system.ctrl, *sig[0], rels[0])     # the first segment, as check_record's warning
            if msg:
                ctx.tag("controller_warning", msg)
        if "d" in ds.frame:
            share, active = disturbance_diagnostics(ds, system.ctrl)
            ctx.metric("disturbance_share", share)
            ctx.metric("disturbance_active", active)
            if share > DISTURBANCE_SHARE and active > DISTURBANCE_ACTIVE:
                ctx.tag("disturbance_warning", f"d carries {100 * share:.0f} % of the recorded force and changes "
                                               f"at {100 * active:.0f} % of the samples: a controller mismatch "
                                               "hidden in d?")
    return ds


def reference(cfg, spec: dict, system) -> data.Dataset:
    """The record an evaluation reference of kind ``measured`` names (``spec['file']``), checked."""
    unknown = sorted(set(spec) - {"name", "kind", "file"})
    if unknown:
        raise ConfigError(f"reference '{spec.get('name')}' of kind 'measured': unknown key(s) {unknown}; it takes "
                          "name, kind and file, e.g. {name: test, kind: measured, file: DATA_EMPS_PULSES}")
    if not spec.get("file"):
        raise ConfigError(f"reference '{spec.get('name')}' of kind 'measured' names no file; give the recorded "
                          "file inside data.path, e.g. {name: test, kind: measured, file: DATA_EMPS_PULSES}")
    try:
        ds = load_file(cfg, spec["file"])
        check_record(ds, system, ds.meta.get("source", str(spec["file"])), min_len=MIN_REFERENCE, reference=True)
        if len(ds) < SHORT_REFERENCE:
            warnings.warn(f"reference '{spec.get('name')}': {ds.meta.get('source', spec['file'])} holds {len(ds)} "
                          f"samples, fewer than {SHORT_REFERENCE}: its errors are a glimpse, not a test of the "
                          "feedforward (the EMPS test file holds 24 841); give the whole test recording", stacklevel=2)
    except FileNotFoundError as exc:
        raise ConfigError(f"reference '{spec.get('name')}': {str(exc).split(';')[0]}; check data.path and the "
                          "reference's file") from exc
    except ValueError as exc:
        raise ConfigError(f"reference '{spec.get('name')}': {exc}") from exc
    return ds
