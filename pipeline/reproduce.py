"""``make reproduce``'s driver: every job of the paper experiments in one queue, timed.

    python -m pipeline.reproduce [--results DIR] [--jobs N] [--override KEY=VALUE ...] EXPERIMENT [EXPERIMENT ...]

One ``python -m pipeline -m hydra/sweeper=queue hydra.sweeper.experiments=[...] hydra/launcher=local
hydra.launcher.n_jobs=N`` in a subprocess: every experiment's sweep (one job where it has none) in
one job list, longest first by the previous run's job times (``hydra_plugins/pgnn_queue``,
:mod:`pipeline.job_queue`), run N at once through Hydra's joblib launcher (N = the machine's cores by
default; ``--jobs 1`` runs them one after another), each job single-threaded, so results are
bit-identical to a serial run in any order.  Its output streams through.  ``results/timings.csv``
holds each job's wall time without its waits for another job's identical entry (experiment,
job = its overrides, wall_seconds, git_sha; the next run's order) and a ``total`` row: the whole
queue's wall time, its job time, and the cores it kept busy.
A subset run replaces its experiments' rows and keeps the others.
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

from pipeline import job_queue
from pipeline.atomic import replace_file

_STAGE_LINE = re.compile(r"^\[(?P<run>.+)\] (?:generate|baseline|train|invert|evaluate|report): ")  # names may hold [ ]


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
        jobs: int | None = None, overrides: list[str] | None = None) -> pd.DataFrame:
    from pipeline.runner import ROOT  # lazy: saves 1.9 s of start-up (mlflow via pipeline.runner)
    from pipeline.tracking import git_sha  # lazy: saves 2.2 s of start-up (mlflow via pipeline.tracking)
    path = results / "timings.csv"
    # a check's rerun (its own results folder): ordered by the reference run's job times
    if not path.exists() and (ROOT / "results" / "timings.csv").exists():
        results.mkdir(parents=True, exist_ok=True)
        replace_file(path, (ROOT / "results" / "timings.csv").read_bytes())   # never through a planted link
    cores = cores_available()
    jobs = jobs or cores
    threads = int(os.environ.get("OMP_NUM_THREADS", "1") or 1)      # BLAS threads per job
    env = dict(os.environ)
    if sys.stderr.isatty():                       # keep the progress bars through the pipe
        env.setdefault("PIPELINE_PROGRESS", "1")
    print(f"== {len(experiments)} experiments in one queue, {jobs} jobs at once: {' '.join(experiments)}",
          flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen([python, "-m", "pipeline", "-m", "hydra/sweeper=queue",
                             f"hydra.sweeper.experiments=[{','.join(experiments)}]",
                             f"hydra.sweeper.timings='{path}'", "hydra/launcher=local",
                             f"hydra.launcher.n_jobs={jobs}", *(overrides or [])], stderr=subprocess.PIPE, env=env)
    _stream(proc.stderr.fileno())
    if proc.wait() != 0:
        raise SystemExit(f"make reproduce failed (exit code {proc.returncode}); see the job's error above")
    wall = time.perf_counter() - t0
    table = job_queue.read_timings(path)
    if table is None:
        raise SystemExit(f"{path}: the queue did not write its job times")
    mine = table[table["experiment"].isin(experiments)]
    busy = float(mine["wall_seconds"].sum())
    total = {"experiment": job_queue.TOTAL,
             "job": f"{len(mine)} jobs of {len(experiments)} experiments, {jobs} at once ({threads} thread(s) each) "
                    f"on {cores} cores; job time {busy:.0f} s, {busy / (wall * jobs):.0%} of the cores busy",
             "wall_seconds": round(wall, 1), "git_sha": git_sha()[:12]}
    table = pd.concat([table, pd.DataFrame([total])], ignore_index=True)[job_queue.COLUMNS]
    job_queue.write_csv(path, table)
    print(f"== done: {_fmt(wall)} wall; {total['job']}", flush=True)
    return table


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("experiments", nargs="+", help="conf/experiment/<name>.yaml names, in order")
    ap.add_argument("--results", default=None, help="results folder (default <repo>/results)")
    ap.add_argument("--jobs", type=int, default=None,
                    help="jobs of a sweep run at once (default: the machine's cores)")
    ap.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for every job, e.g. init_seed=1 (make reproduce-spread)")
    a = ap.parse_args(argv)
    if a.jobs is not None and a.jobs < 1:
        ap.error(f"--jobs {a.jobs}: give a positive number of parallel jobs, e.g. --jobs 2")
    from pipeline.runner import ROOT  # lazy: saves 1.9 s of start-up (mlflow via pipeline.runner)
    run(a.experiments, Path(a.results) if a.results else ROOT / "results", jobs=a.jobs, overrides=a.override)


if __name__ == "__main__":
    main()
