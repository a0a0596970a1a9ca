"""Resource errors: a full disk, a read-only or forbidden directory, an unreachable tracking server,
memory exhausted.

:func:`describe` turns such an error into one line ``error: <what> at <path>: <reason>; <fix>`` for
the entry point (``python -m pipeline``), instead of a traceback.  Only these errors: an ``OSError``
whose errno is ENOSPC, EDQUOT, EROFS or EACCES, an SQLite store that is read-only, full or cannot
be opened, and an MLflow request that could not connect.  Anything else (a programming error) is
not described and keeps its traceback.

:func:`job_cores`: the cores one job may use (the machine's, shared among the jobs the Hydra
launcher runs at once), so a job's own pool (SK restarts) never outnumbers the free cores.
"""
from __future__ import annotations

import errno
import os
import re
from pathlib import Path


def job_cores() -> int:
    """Cores available to this process divided by the jobs the Hydra launcher runs at once
    (``hydra.launcher.n_jobs`` of a multirun; 1 outside Hydra or for a single run), at least 1."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jobs = 1
    try:
        from hydra.core.hydra_config import HydraConfig  # lazy: saves 0.2 s of start-up (hydra)
        if HydraConfig.initialized():
            hc = HydraConfig.get()
            if str(hc.mode) in ("RunMode.MULTIRUN", "MULTIRUN"):
                jobs = int(hc.launcher.get("n_jobs", 1) or 1)
                jobs = cores if jobs < 0 else jobs         # joblib: -1 = every core
    except (ImportError, ValueError, AttributeError):
        pass
    return max(1, cores // max(1, jobs))


#: errno -> (reason, what to do)
ERRNOS = {
    errno.ENOSPC: ("no space left on the device", "free space there, or"),
    errno.EDQUOT: ("disk quota exceeded", "free space there, or"),
    errno.EROFS: ("read-only file system", ""),
    errno.EACCES: ("permission denied", "make it writable for this user, or"),
}
#: SQLite's messages for a store it cannot write (sqlite3 / SQLAlchemy OperationalError)
SQLITE = {
    "attempt to write a readonly database": ("read-only database", "make it writable for this user, or"),
    "database or disk is full": ("no space left on the device", "free space there, or"),
    "unable to open database file": ("cannot open the database (missing, read-only or forbidden folder)",
                                     "make the folder writable for this user, or"),
    "file is not a database": ("the file there is not an SQLite database", "move it away, or"),
}


def _places(cfg=None) -> list[tuple[str, Path, str]]:
    """(what, folder, how to choose another) of every place a job writes."""
    from pipeline import runner, tracking  # lazy: saves 2.0 s of start-up (mlflow)
    out = []
    try:
        out.append(("stage cache", runner.cache_dir(cfg) if cfg is not None else
                    Path(os.environ.get("PIPELINE_CACHE") or runner.ROOT / ".cache"),
                    "point PIPELINE_CACHE (or paths.cache=DIR) at a writable folder"))
    except Exception:  # noqa: BLE001 — a broken cfg: the other places still apply
        pass
    out.append(("cache key", runner.cache_key_file().parent,
                "point PIPELINE_CACHE_KEY_FILE at a writable location"))
    uri = os.environ.get("MLFLOW_TRACKING_URI") or tracking.default_uri()
    if uri.startswith("sqlite:///"):   # its folder, and the file itself (deeper: it wins over a neighbour)
        for place in (Path(uri[len("sqlite:///"):]).parent, Path(uri[len("sqlite:///"):])):
            out.append(("MLflow store", place, "point MLFLOW_TRACKING_URI at a writable store"))
    elif uri.startswith("file:") or "://" not in uri:
        out.append(("MLflow store", Path(re.sub(r"^file://", "", uri)),
                    "point MLFLOW_TRACKING_URI at a writable store"))
    results = (cfg.get("paths", {}) or {}).get("results") if cfg is not None else None
    out.append(("report folder", Path(results) if results else runner.ROOT / "results",
                "set paths.results=DIR to a writable folder"))
    return out


def _where(path: str | None, cfg) -> tuple[str, str]:
    """(what, how to choose another place) for ``path``: the deepest known place containing it."""
    if not path:
        return "file", ""
    p = Path(os.path.abspath(path))
    best = ("file", "", -1)
    for what, folder, fix in _places(cfg):
        folder = Path(os.path.abspath(folder))
        if (p == folder or folder in p.parents) and len(folder.parts) > best[2]:
            best = (what, fix, len(folder.parts))
    return best[0], best[1]


def _chain(exc: BaseException):
    """``exc`` and its causes (``raise ... from``, and the exception being handled when it was raised)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


#: errno -> (reason, what to do) where the path is a place a job writes (elsewhere: a program error)
PLACE_ERRNOS = {
    errno.ENOENT: ("a folder on its path is missing and cannot be made", ""),
    errno.ENOTDIR: ("a part of its path is a file, not a folder", ""),
    errno.EEXIST: ("a part of its path is a file, not a folder", ""),
    errno.EISDIR: ("it is a folder, not a file", ""),
}


def _os_line(exc: OSError, cfg) -> str | None:
    path = exc.filename2 or exc.filename   # rename / copy: the destination
    what, fix = _where(str(path) if path else None, cfg)
    if exc.errno not in ERRNOS and not (exc.errno in PLACE_ERRNOS and what != "file"):
        return None
    reason, first = ERRNOS.get(exc.errno) or PLACE_ERRNOS[exc.errno]
    fix = " ".join(x for x in (first, fix) if x).removesuffix(", or").removesuffix(" or") or \
        "choose a writable location"
    return f"error: {what} at {path or 'an unnamed file'}: {reason}; {fix}"


def describe(exc: BaseException, cfg=None) -> str | None:
    """One line for a resource error, or None for any other error."""
    from pipeline import tracking  # lazy: saves 2.0 s of start-up (mlflow via pipeline.tracking)
    if isinstance(exc, MemoryError):   # numpy's "Unable to allocate", torch's "Allocation failed"
        detail = str(exc).splitlines()[0][:160] if str(exc) else "an allocation failed"
        return (f"error: out of memory ({detail}): the model or the data is too large for this machine; make "
                "model.hidden, identify.n_restarts or the record smaller, or run it on a machine with more memory")
    if isinstance(exc, OSError):
        return _os_line(exc, cfg)
    try:
        import mlflow  # lazy: saves 2.7 s of start-up (mlflow)
        mlflow_error = isinstance(exc, mlflow.exceptions.MlflowException)
    except ImportError:  # pragma: no cover
        mlflow_error = False
    sql_error = type(exc).__name__ in ("OperationalError", "DatabaseError")   # sqlite3 / SQLAlchemy
    if not (mlflow_error or sql_error):
        return None
    uri = os.environ.get("MLFLOW_TRACKING_URI") or tracking.default_uri()
    for e in _chain(exc):
        if isinstance(e, OSError) and (line := _os_line(e, cfg)):
            return line
        if _is_connection_error(e):
            reason = re.search(r"\[Errno -?\d+\] ([^\"')]+)|(timed out|Read timed out)", str(e))
            why = (reason.group(1) or reason.group(2)).strip() if reason else type(e).__name__
            return (f"error: MLflow tracking server at {uri}: unreachable ({why}); start it or fix "
                    "MLFLOW_TRACKING_URI (unset: the local store under mlruns/)")
        msg = str(e)
        status = re.search(r"too many (\d{3}) error responses|error code (\d{3}) != 200", msg)
        if status and (status.group(1) or status.group(2)).startswith("5"):   # 503 (busy), 502, 500 (issue 51)
            code = status.group(1) or status.group(2)
            return (f"error: MLflow tracking server at {uri}: answered HTTP {code} (a server error: overloaded, "
                    "restarting or broken); retry later, check the server's log, or point MLFLOW_TRACKING_URI "
                    "at another store")
        for key, (reason, first) in SQLITE.items():
            if key in msg:
                db = uri[len("sqlite:///"):] if uri.startswith("sqlite:///") else uri
                return (f"error: MLflow store at {db}: {reason}; {first} point MLFLOW_TRACKING_URI "
                        "at a writable store")
    return None


def _is_connection_error(e: BaseException) -> bool:
    try:
        import requests  # lazy: saves 0.2 s of start-up (requests)
    except ImportError:  # pragma: no cover
        return False
    return isinstance(e, (requests.exceptions.ConnectionError, requests.exceptions.Timeout))
