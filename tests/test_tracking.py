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


def test_runs_read_back_through_mlflow_server_rest_api(sweep_store):
    tmp, env = sweep_store
    port = _free_port()
    server = subprocess.Popen(
        [os.path.join(os.path.dirname(sys.executable), "mlflow"), "server",
         "--backend-store-uri", env["MLFLOW_TRACKING_URI"], "--host", "127.0.0.1",
         "--port", str(port), "--workers", "1"],
        cwd=tmp, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
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
        exp = requests.get(f"{base}/api/2.0/mlflow/experiments/get-by-name",
                           params={"experiment_name": "physics_baseline"}, timeout=10).json()
        exp_id = exp["experiment"]["experiment_id"]
        found = requests.post(f"{base}/api/2.0/mlflow/runs/search",
                              json={"experiment_ids": [exp_id],
                                    "filter": "tags.sweep = 'child'"}, timeout=10).json()["runs"]
        assert len(found) == 3
        metrics = {m["key"]: m["value"] for m in found[0]["data"]["metrics"]}
        assert metrics["evaluate/held/rms"] > 0
        tags = {t["key"]: t["value"] for t in found[0]["data"]["tags"]}
        assert tags["system"] == "two_mass_stribeck" and tags["invert"] == "physics"
    finally:
        try:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(timeout=180)         # measured 47 s to stop on a busy machine
        except ProcessLookupError:           # already gone
            pass
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()


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
