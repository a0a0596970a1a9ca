"""The order of ``make reproduce``'s one job queue (``hydra/sweeper=queue``,
``hydra_plugins/pgnn_queue/queue_sweeper.py``) and its job times (``results/timings.csv``).

Longest processing time first (Graham's LPT rule: on m cores its makespan is at most 4/3 − 1/(3m) of
the best, and a long job never starts last to leave the other cores idle), from the previous run's
time of the same job (same experiment and overrides), else the mean job time of its experiment; jobs
with no estimate go first, in the order given.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pipeline.atomic import replace_file

COLUMNS = ["experiment", "job", "wall_seconds", "git_sha"]
#: the row of the whole run (written by pipeline/reproduce.py), not a job
TOTAL = "total"


@dataclass(frozen=True)
class Job:
    experiment: str
    overrides: tuple[str, ...]

    @property
    def key(self) -> str:
        return " ".join(o for o in self.overrides if not o.startswith("experiment="))


def read_timings(path: Path) -> pd.DataFrame | None:
    """The job rows of a timings.csv (None when absent or of another format)."""
    if not path.exists():
        return None
    t = pd.read_csv(path, dtype={"job": str}, keep_default_na=False)
    if not set(COLUMNS) <= set(t.columns):
        return None
    t = t[t["experiment"] != TOTAL].copy()
    t["wall_seconds"] = pd.to_numeric(t["wall_seconds"], errors="coerce")
    return t


def estimates(jobs: list[Job], previous: pd.DataFrame | None) -> list[float | None]:
    """Per job, the previous run's seconds of that job, else its experiment's mean, else None."""
    if previous is None or previous.empty:
        return [None] * len(jobs)
    by_job = {(e, j): s for e, j, s in zip(previous["experiment"], previous["job"], previous["wall_seconds"])}
    by_exp = previous.groupby("experiment")["wall_seconds"].mean().to_dict()
    out = []
    for job in jobs:
        s = by_job.get((job.experiment, job.key), by_exp.get(job.experiment))
        out.append(None if s is None or pd.isna(s) else float(s))
    return out


def longest_first(jobs: list[Job], previous: pd.DataFrame | None) -> list[Job]:
    """LPT order; jobs without an estimate first (a new job may be long), ties in the given order."""
    est = estimates(jobs, previous)
    order = sorted(range(len(jobs)), key=lambda i: (est[i] is not None, -(est[i] or 0.0), i))
    return [jobs[i] for i in order]


def plan_line(ordered: list[Job], est: list[float | None], n_jobs: int) -> str:
    """One line on the plan: jobs, experiments, and the previous times (``est``, per ordered job)."""
    n_exp = len({j.experiment for j in ordered})
    known = [s for s in est if s is not None]
    line = f"queue: {len(ordered)} jobs of {n_exp} experiments, longest first, {n_jobs} at once"
    if known:
        line += (f"; the previous run's times of {len(known)} of them sum to {sum(known):.0f} s "
                 f"(≥ {sum(known) / max(n_jobs, 1):.0f} s of wall, {n_jobs} at once)")
    return line


def write_timings(path: Path, ordered: list[Job], seconds: list[float | None],
                  previous: pd.DataFrame | None) -> pd.DataFrame:
    """This run's job times, then the previous rows of experiments it did not run (a subset run);
    written atomically."""
    from pipeline.tracking import git_sha  # lazy: saves 3.3 s of start-up (mlflow via pipeline.tracking)
    sha = git_sha()[:12]
    rows = pd.DataFrame([{"experiment": j.experiment, "job": j.key,
                          "wall_seconds": None if s is None else round(float(s), 2), "git_sha": sha}
                         for j, s in zip(ordered, seconds)], columns=COLUMNS)
    if previous is not None and not previous.empty:
        kept = previous[~previous["experiment"].isin(set(rows["experiment"]))]
        rows = pd.concat([rows, kept[COLUMNS]], ignore_index=True)
    write_csv(path, rows)
    return rows


def write_csv(path: Path, table: pd.DataFrame) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_file(path, table.to_csv(index=False))
