"""``make reproduce``'s driver: run the paper experiments one after another and time them.

    python -m pipeline.reproduce [--results DIR] [--jobs N] EXPERIMENT [EXPERIMENT ...]

Each experiment is ``python -m pipeline experiment=<name> hydra/launcher=local
hydra.launcher.n_jobs=N`` in a subprocess: a sweep runs N jobs at once through Hydra's joblib
launcher (N = the machine's cores by default; ``--jobs 1`` runs them one after another), each job
single-threaded, so results are bit-identical to a serial run.  Its output streams through.  After each, one line:
its wall time, its number of jobs, and an ETA for the rest from the previous run's
``results/timings.csv``.  At the end ``results/timings.csv`` is written atomically (experiment,
jobs, wall_seconds, cores_used, cores_available, git_sha); a subset run updates its own rows and
keeps the others, like ``report.update``.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

COLUMNS = ["experiment", "jobs", "wall_seconds", "cores_used", "cores_available", "git_sha"]
_STAGE_LINE = re.compile(r"^\[(?P<run>.+)\] (?:generate|baseline|train|invert|evaluate|report): ")  # names may hold [ ]


def eta_seconds(previous: pd.DataFrame | None, remaining: list[str]) -> float | None:
    """Sum of the previous wall times of the ``remaining`` experiments (None if any is unknown)."""
    if previous is None or previous.empty:
        return None
    known = dict(zip(previous["experiment"], previous["wall_seconds"]))
    if any(e not in known for e in remaining):
        return None
    return float(sum(known[e] for e in remaining))


def merge(previous: pd.DataFrame | None, rows: list[dict]) -> pd.DataFrame:
    """The new rows replace the previous rows of their experiments; the order of the new run
    first, then the experiments it did not run."""
    new = pd.DataFrame(rows, columns=COLUMNS)
    if previous is None or previous.empty:
        return new
    kept = previous[~previous["experiment"].isin(new["experiment"])]
    return pd.concat([new, kept[COLUMNS]], ignore_index=True)


def _stream(fd: int) -> set[str]:
    """Copy a child's stderr through as it comes (bars included); return the run names of its
    per-stage lines (one per job)."""
    runs, pending = set(), ""
    while True:
        chunk = os.read(fd, 4096)
        if not chunk:
            break
        sys.stderr.buffer.write(chunk)
        sys.stderr.flush()
        pending += chunk.decode(errors="replace")
        *lines, pending = pending.split("\n")
        for line in lines:
            m = _STAGE_LINE.match(line.rsplit("\r", 1)[-1])
            if m:
                runs.add(m.group("run"))
    return runs


def _fmt(seconds: float) -> str:
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s:02d} s" if m else f"{s} s"


def cores_available() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def run(experiments: list[str], results: Path, python: str = sys.executable,
        jobs: int | None = None) -> pd.DataFrame:
    from pipeline.tracking import git_sha
    path = results / "timings.csv"
    previous = pd.read_csv(path) if path.exists() else None
    cores = cores_available()
    jobs = jobs or cores
    threads = int(os.environ.get("OMP_NUM_THREADS", "1") or 1)      # BLAS threads per job
    rows, t_all = [], time.perf_counter()
    for i, exp in enumerate(experiments):
        print(f"== experiment={exp} ({i + 1}/{len(experiments)})", flush=True)
        t0 = time.perf_counter()
        env = dict(os.environ)
        if sys.stderr.isatty():                       # keep the progress bars through the pipe
            env.setdefault("PIPELINE_PROGRESS", "1")
        proc = subprocess.Popen([python, "-m", "pipeline", f"experiment={exp}", "hydra/launcher=local",
                                 f"hydra.launcher.n_jobs={jobs}"], stderr=subprocess.PIPE, env=env)
        runs = _stream(proc.stderr.fileno())
        if proc.wait() != 0:
            raise SystemExit(f"experiment {exp} failed (exit code {proc.returncode}); timings not written")
        wall = time.perf_counter() - t0
        rows.append({"experiment": exp, "jobs": len(runs), "wall_seconds": round(wall, 1),
                     "cores_used": min(jobs, max(len(runs), 1)) * threads, "cores_available": cores,
                     "git_sha": git_sha()[:12]})
        eta = eta_seconds(previous, experiments[i + 1:])
        rest = "done" if i + 1 == len(experiments) else \
            (f"ETA {_fmt(eta)} for the {len(experiments) - i - 1} left" if eta is not None
             else "ETA unknown (no earlier timings for the rest)")
        print(f"== {exp}: {_fmt(wall)}, {len(runs)} job(s); total {_fmt(time.perf_counter() - t_all)}; {rest}",
              flush=True)
    table = merge(previous, rows)
    results.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    table.to_csv(tmp, index=False)
    os.replace(tmp, path)
    return table


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("experiments", nargs="+", help="conf/experiment/<name>.yaml names, in order")
    ap.add_argument("--results", default=None, help="results folder (default <repo>/results)")
    ap.add_argument("--jobs", type=int, default=None,
                    help="jobs of a sweep run at once (default: the machine's cores)")
    a = ap.parse_args(argv)
    if a.jobs is not None and a.jobs < 1:
        ap.error(f"--jobs {a.jobs}: give a positive number of parallel jobs, e.g. --jobs 2")
    from pipeline.runner import ROOT
    run(a.experiments, Path(a.results) if a.results else ROOT / "results", jobs=a.jobs)


if __name__ == "__main__":
    main()
