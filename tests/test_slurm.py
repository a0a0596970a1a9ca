"""Sweeps on a real SLURM (issue 24 item 3): `hydra/launcher=slurm` (conf/hydra/launcher/slurm.yaml,
hydra-submitit-launcher) submits one SLURM job per Hydra job; the jobs share one stage cache and one
MLflow store.

Slow tests, and they need a running SLURM: they skip, saying why, where `sbatch`/`sinfo`/`sacct` are
missing or no partition has a usable node. They do not start one: `make slurm-local` as root
(scripts/slurm-local.sh) brings up a one-node SLURM on this machine in seconds once its packages are
installed, then

    .venv/bin/python -m pytest -m slow tests/test_slurm.py

Every job runs the code under test: the jobs get PYTHONPATH=<this checkout> and the virtualenv of
the Python running the tests (`hydra.launcher.setup`), and the same PIPELINE_CACHE,
PIPELINE_CACHE_KEY_FILE and MLFLOW_TRACKING_URI (a SQLite file: one node shares its file system).
"""
from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT

pytestmark = pytest.mark.slow

#: generous: jobs start Python, torch and MLflow on a shared, loaded 2-core machine
TIMEOUT = 1200
STAGES = ("generate", "baseline", "train", "invert", "evaluate")


def _run(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(list(argv), capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def partition() -> str:
    """The partition to submit to: the default one (sinfo's `*`) if one of its nodes can take jobs."""
    for tool in ("sbatch", "sinfo", "sacct", "scancel"):
        if shutil.which(tool) is None:
            pytest.skip(f"no `{tool}`: SLURM's client tools are not installed "
                        "(`make slurm-local` as root installs and starts a one-node SLURM)")
    try:
        out = _run("sinfo", "-h", "-o", "%P %t")
    except subprocess.TimeoutExpired:
        pytest.skip("SLURM does not answer: sinfo took over 120 s")
    if out.returncode != 0:
        pytest.skip(f"SLURM is not up (sinfo: {out.stderr.strip()[:200]}); start it: `make slurm-local` as root")
    usable = [p for p, state in (line.split() for line in out.stdout.splitlines() if line.strip())
              if state.rstrip("*~#!%$@^-") in ("idle", "mix", "alloc", "comp")]
    if not usable:
        pytest.skip(f"no SLURM partition has a node that takes jobs (sinfo: {out.stdout.strip()!r}); "
                    "`make slurm-local` as root resumes the local node")
    acct = _run("sacct", "-n", "-X", "-j", "1")
    if acct.returncode != 0:     # submitit learns a job's end from sacct
        pytest.skip(f"sacct does not answer ({acct.stderr.strip()[:200]}): submitit needs job accounting")
    default = [p for p in usable if p.endswith("*")]
    return (default or usable)[0].rstrip("*")


def _env(tmp: Path) -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT),
            "PIPELINE_CACHE": str(tmp / "cache"), "PIPELINE_CACHE_KEY_FILE": str(tmp / "cache.key"),
            "MLFLOW_TRACKING_URI": f"sqlite:///{tmp / 'mlflow.db'}"}


def _launcher(partition: str, env: dict[str, str]) -> list[str]:
    """hydra/launcher=slurm with the lines that give each job this test's environment."""
    setup = ["export OMP_NUM_THREADS=1"]
    if sys.prefix != sys.base_prefix:            # the virtualenv running the tests
        setup.append(f". {shlex.quote(str(Path(sys.prefix) / 'bin' / 'activate'))}")
    setup += [f"export {k}={shlex.quote(env[k])}"
              for k in ("PYTHONPATH", "PIPELINE_CACHE", "PIPELINE_CACHE_KEY_FILE", "MLFLOW_TRACKING_URI")]
    return ["hydra/launcher=slurm", f"hydra.launcher.partition={partition}",
            "hydra.launcher.mem_gb=1",           # a job's peak is < 1 GB; fits a small node too
            "hydra.launcher.setup=[" + ",".join(json.dumps(line) for line in setup) + "]"]


def _sweep_cmd(tmp: Path, partition: str, sweep: str, *overrides: str) -> tuple[list[str], dict[str, str]]:
    env = _env(tmp)
    return ([sys.executable, "-m", "pipeline", "-m", *overrides, *_launcher(partition, env),
             f"hydra.sweep.dir={tmp / sweep}"], env)


def _sweep(tmp: Path, partition: str, sweep: str, *overrides: str) -> dict[str, str]:
    cmd, env = _sweep_cmd(tmp, partition, sweep, *overrides)
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT)
    assert out.returncode == 0, out.stderr[-4000:]
    return env


def _runs(env: dict[str, str], experiment: str):
    import mlflow
    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    return mlflow.search_runs(experiment_names=[experiment])


def _wait(what: str, ready, launcher: subprocess.Popen | None = None, timeout: float = TIMEOUT):
    """Poll ready() until it returns something true; fail if the launcher ends first or at timeout."""
    deadline = time.monotonic() + timeout
    while True:
        got = ready()
        if got:
            return got
        if launcher is not None and launcher.poll() is not None:
            pytest.fail(f"the sweep ended (exit {launcher.returncode}) before {what}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} within {timeout} s")
        time.sleep(1)


def _sacct(job: str) -> dict[str, tuple[str, str]]:
    """{JobID (an array task: <array>_<task>): (JobIDRaw, State)} of a job or a job array."""
    out = _run("sacct", "-n", "-X", "-P", "-o", "JobID,JobIDRaw,State", "-j", job)
    assert out.returncode == 0, out.stderr
    return {jid: (raw, state) for jid, raw, state in (line.split("|") for line in out.stdout.splitlines() if line)}


def _sacct_ended(job: str) -> dict[str, tuple[str, str]]:
    """_sacct(job) once every job has ended: submitit returns as soon as a job wrote its result, while
    SLURM may still show the job RUNNING or COMPLETING for a moment."""
    ended = ("COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "OUT_OF_MEMORY", "NODE_FAIL", "PREEMPTED")
    return _wait(f"end of SLURM job {job} in sacct",
                 lambda: (jobs := _sacct(job)) and all(s.startswith(ended) for _, s in jobs.values()) and jobs,
                 timeout=300)


def _slurm_ids(runs) -> dict[str, str]:
    """{sacct's JobID: SLURM job id} from the runs' slurm.* tags; the JobID of an array task is
    <array job>_<task> (submitit submits a sweep of one job as a plain job, not an array)."""
    def job_id(r) -> str:
        array, task = r.get("tags.slurm.array_job_id"), r.get("tags.slurm.array_task_id")
        return f"{array}_{task}" if isinstance(array, str) else r["tags.slurm.job_id"]
    return {job_id(r): r["tags.slurm.job_id"] for _, r in runs.iterrows()}


def _submitit_jobs(sweep_dir: Path) -> set[str]:
    """The SLURM jobs submitit ran: its folders with a job's log (<array>_<task> for an array task;
    the folder <array> holds only the sbatch script)."""
    return {p.parent.name for p in (sweep_dir / ".submitit").glob("*/*_log.out")}


def test_a_sweep_on_slurm_finishes_tracks_every_job_and_computes_each_stage_once(partition, tmp_path):
    """physics_arx, seed=0,1 x invert=physics,none: four SLURM jobs (an array), two at a time on a
    2-CPU node. The MLflow parent and its four children end FINISHED; each child names its SLURM job
    (slurm.* tags, as sacct has them, every one COMPLETED); jobs of one seed share generate, baseline
    and train: each computed once (one `miss`, one `hit`, one cache entry), invert and evaluate per job."""
    env = _sweep(tmp_path, partition, "sweep", "experiment=physics_arx", "seed=0,1", "invert=physics,none")
    runs = _runs(env, "physics_baseline")
    parents = runs[runs["tags.sweep"] == "parent"]
    assert len(parents) == 1 and parents["status"].iloc[0] == "FINISHED"
    kids = runs[runs["tags.mlflow.parentRunId"] == parents["run_id"].iloc[0]]
    assert len(kids) == 4 and set(kids["status"]) == {"FINISHED"} and len(runs) == 5

    ids = _slurm_ids(kids)
    [array] = set(kids["tags.slurm.array_job_id"])
    assert _sacct_ended(array) == {jid: (raw, "COMPLETED") for jid, raw in ids.items()}
    assert _submitit_jobs(tmp_path / "sweep") == set(ids)

    for seed, jobs in kids.groupby("params.seed"):
        assert sorted(jobs["params.invert.kind"]) == ["none", "physics"], seed
        for stage in STAGES[:3]:
            assert sorted(jobs[f"tags.cache.{stage}"]) == ["hit", "miss"], (seed, stage)
        for stage in STAGES[3:]:
            assert list(jobs[f"tags.cache.{stage}"]) == ["miss", "miss"], (seed, stage)
    entries = {s: [d for d in (tmp_path / "cache" / s).iterdir() if not d.name.startswith(".")] for s in STAGES}
    assert {s: len(e) for s, e in entries.items()} == \
        {"generate": 2, "baseline": 2, "train": 2, "invert": 4, "evaluate": 4}
    assert not list((tmp_path / "cache").glob("*/.tmp-*"))       # no torn temporary left


def test_a_cancelled_job_resumes_from_the_cache_when_rerun(partition, tmp_path, cfg_of, monkeypatch):
    """A one-job sweep is held at its invert stage (this test holds that cache entry's lock, as a job
    computing it would), after generate, baseline and train are done, and cancelled with scancel. The
    launcher ends with an error, the parent FAILED; the rerun loads the three finished stages from the
    cache (`hit`), computes the rest, and marks the cancelled job's run KILLED."""
    from pipeline import runner
    from pipeline.cache import _locked
    over = ["experiment=physics_arx", "seed=7"]
    env = _env(tmp_path)
    for k in ("PIPELINE_CACHE", "PIPELINE_CACHE_KEY_FILE"):
        monkeypatch.setenv(k, env[k])
    cfg = cfg_of(*over)
    names, _, modules = runner.validate(cfg)
    keys = runner.plan(cfg, names, modules)
    lock = _locked(runner.cache_dir(cfg) / "invert" / keys["invert"][:20])
    lock.acquire()
    try:
        cmd, env = _sweep_cmd(tmp_path, partition, "sweep", *over)
        with open(tmp_path / "launcher.log", "w") as log:
            launcher = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            def held():   # the job's stderr says it waits for the entry: the stages before it are done
                for err in (tmp_path / "sweep" / ".submitit").glob("*/*_log.err"):
                    if "invert: waiting for another job" in err.read_text(errors="replace"):
                        return err.parent.name
            job = _wait("the job waiting at invert", held, launcher)
            assert _run("scancel", job).returncode == 0
            launcher.wait(timeout=TIMEOUT)        # submitit sees the job CANCELLED in sacct and raises
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.wait()
    finally:
        lock.release()
    assert launcher.returncode != 0, (tmp_path / "launcher.log").read_text()[-3000:]
    raw, state = _sacct_ended(job)[job]
    assert state.startswith("CANCELLED"), state        # "CANCELLED by 0"
    first = _runs(env, "physics_baseline")
    [cancelled] = first[first["tags.sweep"] == "child"].itertuples()
    assert _slurm_ids(first[first["tags.sweep"] == "child"]) == {job: raw}
    assert set(first[first["tags.sweep"] == "parent"]["status"]) == {"FAILED"}
    assert not (tmp_path / "cache" / "invert").exists() or not any((tmp_path / "cache" / "invert").iterdir())

    _sweep(tmp_path, partition, "sweep2", *over)
    runs = _runs(env, "physics_baseline")
    kids = runs[(runs["tags.sweep"] == "child") & (runs["run_id"] != cancelled.run_id)]
    assert len(kids) == 1 and kids["status"].iloc[0] == "FINISHED"
    rerun = kids.iloc[0]
    assert [rerun[f"tags.cache.{s}"] for s in STAGES] == ["hit", "hit", "hit", "miss", "miss"]
    assert runs[runs["run_id"] == cancelled.run_id]["status"].iloc[0] == "KILLED"   # not left RUNNING
    [job2] = _submitit_jobs(tmp_path / "sweep2")
    assert _sacct_ended(job2)[job2] == (rerun["tags.slurm.job_id"], "COMPLETED")


def test_the_queue_of_experiments_runs_on_slurm(partition, tmp_path):
    """hydra/sweeper=queue (make reproduce's one job list, longest first) with the SLURM launcher:
    physics_arx (one job) and b2_rot_trans_linear (a 4-job sweep) as one job array. The sweep's four
    runs are children of its parent 'b2_rot_trans_linear-sweep', FINISHED; the single job has no
    parent; every job is a COMPLETED SLURM job named in its run's tags; the job times are written."""
    import mlflow
    import pandas as pd
    timings = tmp_path / "timings.csv"
    env = _sweep(tmp_path, partition, "sweep", "hydra/sweeper=queue",
                 "hydra.sweeper.experiments=[physics_arx,b2_rot_trans_linear]", f"hydra.sweeper.timings={timings}")
    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    runs = mlflow.search_runs(search_all_experiments=True)
    parents = runs[runs["tags.sweep"] == "parent"]
    assert list(parents["tags.mlflow.runName"]) == ["b2_rot_trans_linear-sweep"]
    assert parents["status"].iloc[0] == "FINISHED"
    kids = runs[runs["tags.mlflow.parentRunId"] == parents["run_id"].iloc[0]]
    assert len(kids) == 4 and set(kids["status"]) == {"FINISHED"}
    single = runs[runs["tags.mlflow.runName"] == "arx_bias-physics-s0"]
    assert len(single) == 1 and single["tags.sweep"].iloc[0] == "single" and single["status"].iloc[0] == "FINISHED"

    jobs = runs[runs["tags.sweep"] != "parent"]
    ids = _slurm_ids(jobs)
    [array] = set(jobs["tags.slurm.array_job_id"])
    assert len(ids) == 5 and _sacct_ended(array) == {jid: (raw, "COMPLETED") for jid, raw in ids.items()}
    table = pd.read_csv(timings, keep_default_na=False)
    assert sorted(table["experiment"]) == ["b2_rot_trans_linear"] * 4 + ["physics_arx"]
    assert (table["wall_seconds"] > 0).all()
