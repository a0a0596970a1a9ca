"""MLflow tracking end to end: a Hydra multirun (parent + children) and reading runs back
through a real `mlflow server` over its REST API."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest
import requests

from tests.conftest import ROOT, SHORT_TWO_MASS


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sweep_store(tmp_path_factory):
    """One 3-job multirun (seed=0,1,2) through the real CLI, into a fresh store."""
    tmp = tmp_path_factory.mktemp("sweep")
    env = {**os.environ, "PIPELINE_CACHE": str(tmp / "cache"),
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp / 'mlflow.db'}", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "pipeline", "-m", *SHORT_TWO_MASS, "seed=0,1,2",
                          f"hydra.sweep.dir={tmp / 'sweep'}"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return tmp, env


@pytest.mark.slow   # a real multirun (~30 s): the default run stays under 5 min on 2 cores (make test-full)
def test_multirun_has_one_parent_with_three_children(sweep_store):
    import mlflow
    tmp, env = sweep_store
    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    runs = mlflow.search_runs(experiment_names=["physics_baseline"])
    parents = runs[runs["tags.sweep"] == "parent"]
    assert len(parents) == 1
    children = runs[runs["tags.mlflow.parentRunId"] == parents["run_id"].iloc[0]]
    assert sorted(children["params.seed"]) == ["0", "1", "2"]
    assert set(children["status"]) == {"FINISHED"} and parents["status"].iloc[0] == "FINISHED"


def _sweep(tmp, *overrides, uri=None, timeout=600):
    """A multirun of SHORT_TWO_MASS through the real CLI into a fresh cache (and store)."""
    env = {**os.environ, "PIPELINE_CACHE": str(tmp / "cache"), "OMP_NUM_THREADS": "1",
           "MLFLOW_TRACKING_URI": uri or f"sqlite:///{tmp / 'mlflow.db'}"}
    out = subprocess.run([sys.executable, "-m", "pipeline", "-m", *SHORT_TWO_MASS, *overrides,
                          f"hydra.sweep.dir={tmp / 'sweep'}"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return env


def _children(uri):
    """(parent status, {seed: child run}) of the one sweep in the physics_baseline experiment."""
    import mlflow
    mlflow.set_tracking_uri(uri)
    runs = mlflow.search_runs(experiment_names=["physics_baseline"])
    parents = runs[runs["tags.sweep"] == "parent"]
    assert len(parents) == 1
    kids = runs[runs["tags.mlflow.parentRunId"] == parents["run_id"].iloc[0]]
    assert set(kids["status"]) == {"FINISHED"}
    return parents["status"].iloc[0], {r["params.seed"]: r for _, r in kids.iterrows()}


def _science(run) -> dict:
    """A run's metrics that do not measure time."""
    return {k: v for k, v in run.items() if k.startswith("metrics.") and v == v and not _timing(k)}


def _timing(key: str) -> bool:
    return "time/" in key or "seconds" in key


# real launchers sweep (~50 s each): slow (make test-full), as the README's test section says
@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["local", "submitit_local"])
def test_parallel_launchers_match_the_serial_sweep(sweep_store, tmp_path, launcher):
    """Issue 10: joblib (conf/hydra/launcher/local.yaml) and submitit's local executor run a 2-job
    sweep into one store: parent and both children FINISHED, every metric equal to the serial run."""
    _, serial_env = sweep_store
    env = _sweep(tmp_path, "seed=0,1", f"hydra/launcher={launcher}")
    status, par = _children(env["MLFLOW_TRACKING_URI"])
    _, ser = _children(serial_env["MLFLOW_TRACKING_URI"])
    assert status == "FINISHED" and sorted(par) == ["0", "1"]
    for seed in par:
        assert _science(par[seed]) and _science(par[seed]) == _science(ser[seed])


@pytest.mark.slow   # a two-job joblib sweep (~40 s); test_runner.py keeps the fast lock-wait test
def test_concurrent_jobs_sharing_stages_compute_them_once(tmp_path):
    """Two parallel jobs with one config (only the run name differs) need the same five stage
    results: each is computed once (one cache miss, one entry), the other job waits and loads it."""
    env = _sweep(tmp_path, "run_name=a,b", "hydra/launcher=local", "hydra.launcher.n_jobs=2")
    import mlflow
    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    runs = mlflow.search_runs(experiment_names=["physics_baseline"])
    kids = runs[runs["tags.sweep"] == "child"]
    assert len(kids) == 2
    for stage in ("generate", "baseline", "train", "invert", "evaluate"):
        assert sorted(kids[f"tags.cache.{stage}"]) == ["hit", "miss"], stage
        entries = [d for d in (tmp_path / "cache" / stage).iterdir()]
        assert len(entries) == 1, entries                      # no duplicate, no torn temporary


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory):
    """A real `mlflow server` on 127.0.0.1 with its own SQLite store and proxied artifacts."""
    tmp = tmp_path_factory.mktemp("server")
    port = _free_port()
    server = subprocess.Popen(
        [os.path.join(os.path.dirname(sys.executable), "mlflow"), "server",
         "--backend-store-uri", f"sqlite:///{tmp / 'server.db'}", "--artifacts-destination",
         str(tmp / "artifacts"), "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
        cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True)          # its own process group: its workers are stopped with it
    base = f"http://127.0.0.1:{port}"
    try:
        # poll up to a generous deadline: MLflow 3.x starts uvicorn and background workers, measured
        # at 87 s on a busy 2-core machine; the test waits only as long as the server needs
        deadline = time.monotonic() + 300
        while True:
            try:
                if requests.get(f"{base}/health", timeout=5).status_code == 200:
                    break
            except requests.RequestException:
                pass
            if server.poll() is not None:
                pytest.fail(f"mlflow server exited with code {server.returncode} before answering")
            if time.monotonic() > deadline:
                pytest.fail("mlflow server did not come up within 300 s")
            time.sleep(0.5)
        yield base, tmp
    finally:
        try:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(timeout=180)         # measured 47 s to stop on a busy machine
        except ProcessLookupError:           # already gone
            pass
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()


@pytest.mark.slow   # ~30 s: a real server and four workers (make test-full)
def test_four_parallel_jobs_to_an_mlflow_server_lose_nothing(sweep_store, mlflow_server):
    """Issue 10: a 4-job multirun with 4 parallel workers tracking to a server: the parent and all
    four children FINISHED; every child has the metrics, tags and artifacts of the serial run (read
    back over the server's REST API)."""
    base, tmp = mlflow_server
    _sweep(tmp, "seed=0,1,2,3", "hydra/launcher=local", "hydra.launcher.n_jobs=4", uri=base)
    exp = requests.get(f"{base}/api/2.0/mlflow/experiments/get-by-name",
                       params={"experiment_name": "physics_baseline"}, timeout=30).json()
    exp_id = exp["experiment"]["experiment_id"]
    runs = requests.post(f"{base}/api/2.0/mlflow/runs/search", json={"experiment_ids": [exp_id]},
                         timeout=30).json()["runs"]
    parents = [r for r in runs if {"key": "sweep", "value": "parent"} in r["data"]["tags"]]
    assert len(parents) == 1 and parents[0]["info"]["status"] == "FINISHED"
    kids = [r for r in runs if {"key": "mlflow.parentRunId", "value": parents[0]["info"]["run_id"]}
            in r["data"]["tags"]]
    assert len(kids) == 4 and {k["info"]["status"] for k in kids} == {"FINISHED"}

    _, serial = _children(sweep_store[1]["MLFLOW_TRACKING_URI"])
    from mlflow.tracking import MlflowClient
    ser_client = MlflowClient(sweep_store[1]["MLFLOW_TRACKING_URI"])
    srv_client = MlflowClient(base)

    def artifacts(c, run_id, path=""):
        out = []
        for f in c.list_artifacts(run_id, path):
            out += artifacts(c, run_id, f.path) if f.is_dir else [f.path]
        return sorted(p for p in out if not p.endswith(".yaml"))   # the config file is named by run id

    for kid in kids:
        params = {p["key"]: p["value"] for p in kid["data"]["params"]}
        metrics = {m["key"]: m["value"] for m in kid["data"]["metrics"] if not _timing(m["key"])}
        tags = {t["key"]: t["value"] for t in kid["data"]["tags"]}
        assert tags["system"] == "two_mass_stribeck" and tags["invert"] == "physics"
        assert metrics["evaluate/held/rms"] > 0
        if params["seed"] in serial:       # seeds 0-2 also ran serially into SQLite
            ref = serial[params["seed"]]
            assert metrics == {k[len("metrics."):]: v for k, v in _science(ref).items()}
            assert artifacts(srv_client, kid["info"]["run_id"]) == artifacts(ser_client, ref["run_id"]) != []
        else:
            assert len(metrics) == len(_science(next(iter(serial.values()))))


@pytest.mark.slow     # a real failing sweep (~9 s)
def test_failed_sweep_marks_parent_failed(tmp_path):
    import mlflow
    env = {**os.environ, "PIPELINE_CACHE": str(tmp_path / "cache"),
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "pipeline", "-m", *SHORT_TWO_MASS, "stages=[generate]",
                          "seed=0,abc", f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "seed='abc' is not an integer" in out.stderr
    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    runs = mlflow.search_runs(experiment_names=["physics_baseline"])
    parent = runs[runs["tags.sweep"] == "parent"]
    assert list(parent["status"]) == ["FAILED"]                 # never left RUNNING
    assert (tmp_path / "artifacts").exists()                   # artifacts beside the database


_OPEN_AT_ONCE = """
import os, sys, time
from pathlib import Path
from pipeline import tracking                      # imports done before the barrier
me, other = Path(sys.argv[1] + ".ready" + sys.argv[2]), Path(sys.argv[1] + ".ready" + sys.argv[3])
me.touch()
while not other.exists():
    time.sleep(0.001)
c = tracking.client()
c.create_run(tracking.experiment_id("race"), run_name="r" + sys.argv[2])
print("ok")
"""


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_two_jobs_opening_a_fresh_sqlite_store_at_once_both_finish(tmp_path):
    """Issue 24 item 1: two processes that first open a new SQLite store at the same moment (a parallel
    sweep's first jobs) both create their runs; without the lock one died in MLflow's migration in every
    try ("duplicate column name", "table experiments already exists"). A fresh store, the two
    processes released together by a file barrier after their imports."""
    for trial in range(1):
        db = tmp_path / f"s{trial}" / "m.db"
        db.parent.mkdir()
        env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{db}"}
        procs = [subprocess.Popen([sys.executable, "-c", _OPEN_AT_ONCE, str(db), a, b], env=env, cwd=ROOT,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for a, b in (("1", "2"), ("2", "1"))]
        outs = [p.communicate(timeout=300) for p in procs]
        for p, (out, err) in zip(procs, outs):
            assert p.returncode == 0 and out.strip() == "ok", err[-2000:]
        import mlflow
        runs = mlflow.MlflowClient(f"sqlite:///{db}").search_runs(
            [mlflow.MlflowClient(f"sqlite:///{db}").get_experiment_by_name("race").experiment_id])
        assert sorted(r.info.run_name for r in runs) == ["r1", "r2"]


def test_queue_callback_one_parent_per_experiment_file_even_when_files_share_an_experiment(store):
    """make reproduce's queue: b2_rot_trans and b2_rot_trans_linear both log to the MLflow experiment
    b2_rot_trans; each sweep gets its own parent, each job attaches to its own file's parent, a job of an
    unswept file (physics_arx) to none, and every parent ends FINISHED (none left RUNNING)."""
    import mlflow
    from omegaconf import OmegaConf

    from pipeline.tracking import PARENT_ENV, MultirunCallback

    def cfg(choice, name):
        return OmegaConf.create({"experiment_name": name, "paths": {"cache": str(store / "cache")},
                                 "hydra": {"runtime": {"choices": {"experiment": choice}},
                                           "sweeper": {"experiments": ["b2_rot_trans", "b2_rot_trans_linear",
                                                                       "physics_arx"]}}})
    master = OmegaConf.create({"experiment_name": "default", "paths": {"cache": str(store / "cache")},
                               "hydra": {"runtime": {"choices": {"experiment": None}},
                                         "sweeper": {"experiments": ["b2_rot_trans"]}}})
    cb = MultirunCallback()
    cb.on_multirun_start(master)                       # the queue itself opens nothing
    assert cb.parents == {}
    cb.on_multirun_start(cfg("b2_rot_trans", "b2_rot_trans"))
    cb.on_multirun_start(cfg("b2_rot_trans_linear", "b2_rot_trans"))
    assert set(cb.parents) == {"b2_rot_trans", "b2_rot_trans_linear"} and len(set(cb.parents.values())) == 2
    seen = {}
    for choice, name in (("b2_rot_trans", "b2_rot_trans"), ("b2_rot_trans_linear", "b2_rot_trans"),
                         ("physics_arx", "physics_baseline")):
        cb.on_job_start(cfg(choice, name))
        seen[choice] = os.environ.get(PARENT_ENV)
    assert seen["b2_rot_trans"] == cb.parents["b2_rot_trans"]
    assert seen["b2_rot_trans_linear"] == cb.parents["b2_rot_trans_linear"]
    assert seen["physics_arx"] is None
    ids = list(cb.parents.values())
    cb.on_multirun_end(master)
    c = mlflow.MlflowClient()
    assert [c.get_run(i).info.status for i in ids] == ["FINISHED", "FINISHED"] and cb.parents == {}
    assert PARENT_ENV not in os.environ


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_a_sigkilled_workers_child_run_is_not_left_running(store):
    """Issue 24, tracebacks: a joblib worker SIGKILLed (the OOM killer) cannot end its run; when the
    sweep ends (failed, or its atexit hook), the child whose process is gone is marked KILLED at
    once, not when some later job of the same experiment happens to start."""
    from omegaconf import OmegaConf

    from pipeline import tracking
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    cb = tracking.MultirunCallback()
    cb.on_multirun_start(OmegaConf.create({"experiment_name": "killed_worker", "paths": {"cache": str(store)}}))
    parent = cb.parent_run_id
    c = tracking.client()
    exp = c.get_run(parent).info.experiment_id
    child = c.create_run(exp, tags={"mlflow.parentRunId": parent, "host": tracking.HOST, "pid": str(dead.pid),
                                    "sweep": "child"}).info.run_id
    alive = c.create_run(exp, tags={"mlflow.parentRunId": parent, "host": tracking.HOST,
                                    "pid": str(os.getpid()), "sweep": "child"}).info.run_id
    cb._close("FAILED")
    assert c.get_run(parent).info.status == "FAILED"
    assert c.get_run(child).info.status == "KILLED"
    assert c.get_run(alive).info.status == "RUNNING"          # a live process's run is its own to end


def test_a_postgresql_unique_violation_on_log_inputs_is_retried(store, monkeypatch):
    """Two jobs logging one dataset race on MLflow's get-or-create; PostgreSQL words the loser's error
    differently from SQLite ("duplicate key value violates unique constraint"): retried all the same."""
    import mlflow
    import pandas as pd

    from pipeline.tracking import JobRun
    run = JobRun("race", "r", {}, {})
    real, calls = run.client.log_inputs, []

    def log_inputs(run_id, datasets):
        calls.append(run_id)
        if len(calls) == 1:
            raise mlflow.exceptions.MlflowException(   # what an MLflow server on PostgreSQL answered
                '(psycopg.errors.UniqueViolation) duplicate key value violates unique constraint "dataset_pk"')
        return real(run_id, datasets=datasets)

    monkeypatch.setattr(run.client, "log_inputs", log_inputs)
    run.log_dataset(pd.DataFrame({"u": [0.0, 1.0]}), "train", "/data/train.parquet")
    assert len(calls) == 2 and len(run.client.get_run(run.run_id).inputs.dataset_inputs) == 1
    run.end()


def test_a_logged_dataset_carries_the_schema_mlflow_infers_from_every_value(store):
    """log_dataset infers a numeric frame's schema from its first SCHEMA_ROWS rows: the logged schema
    equals MLflow's own inference over every value, for a clean frame and for one whose NaN (an
    optional column) sits past those rows."""
    import json
    import warnings

    import numpy as np
    import pandas as pd
    from mlflow.types.utils import _infer_schema

    from pipeline.tracking import SCHEMA_ROWS, JobRun
    n = 3 * SCHEMA_ROWS
    clean = pd.DataFrame({"u": np.linspace(0, 1, n), "segment": np.arange(n) // SCHEMA_ROWS})
    late_nan = clean.assign(y=np.where(np.arange(n) == n - 1, np.nan, 1.0))
    run = JobRun("schema", "r", {}, {})
    for i, df in enumerate((clean, late_nan)):
        run.log_dataset(df, f"train{i}", f"/data/train{i}.parquet")
    logged = {d.dataset.name: json.loads(d.dataset.schema)["mlflow_colspec"]
              for d in run.client.get_run(run.run_id).inputs.dataset_inputs}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, df in enumerate((clean, late_nan)):
            assert logged[f"train{i}"] == _infer_schema(df).to_dict()
    assert [c["required"] for c in logged["train1"]] == [True, True, False]
    run.end()


def test_a_job_run_by_slurm_names_its_slurm_job_in_tags(store, monkeypatch):
    """Issue 24 item 3: a run made inside a SLURM job (an array task of hydra/launcher=slurm) carries
    slurm.job_id, slurm.array_job_id and slurm.array_task_id; outside SLURM it has no slurm tag."""
    from pipeline.tracking import JobRun
    for var in ("SLURM_JOB_ID", "SLURM_ARRAY_JOB_ID", "SLURM_ARRAY_TASK_ID"):
        monkeypatch.delenv(var, raising=False)
    plain = JobRun("slurm_tags", "plain", {}, {})
    monkeypatch.setenv("SLURM_JOB_ID", "4243")
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "4242")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "1")
    job = JobRun("slurm_tags", "in_slurm", {}, {})
    for run in (plain, job):
        run.end()
    tags = job.client.get_run(job.run_id).data.tags
    assert (tags["slurm.job_id"], tags["slurm.array_job_id"], tags["slurm.array_task_id"]) == ("4243", "4242", "1")
    assert not [k for k in plain.client.get_run(plain.run_id).data.tags if k.startswith("slurm.")]
