"""Issue 24 item 4: the team tracking server, `make server` (MLflow on PostgreSQL, artifacts proxied
into a shared folder). The slow test starts a throwaway PostgreSQL and the server as `make server`
runs it, sends two parallel sweeps at once to it and reads everything back over REST."""
from __future__ import annotations

import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import requests

from tests.conftest import ROOT


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_make_server_without_pg_uri_refuses_with_the_fix():
    if not shutil.which("make"):
        pytest.skip("make is not installed")
    env = {k: v for k, v in os.environ.items() if k not in ("PG_URI", "MAKEFLAGS")}
    out = subprocess.run(["make", "--no-print-directory", "server"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    lines = (out.stdout + out.stderr).strip().splitlines()
    assert len(lines) == 1 and "PG_URI is missing: make server PG_URI=postgresql+psycopg://" in lines[0], lines


@pytest.fixture
def postgres():
    """A throwaway PostgreSQL on 127.0.0.1 (free port, its socket in its own folder) with an empty
    database `mlflow`; yields the URI the MLflow server takes. Stopped and removed however the test ends."""
    initdb, pg_ctl = shutil.which("initdb"), shutil.which("pg_ctl")
    if not (initdb and pg_ctl):
        pytest.skip("PostgreSQL's initdb and pg_ctl are not on PATH (install PostgreSQL, put its bin/ on PATH)")
    pytest.importorskip("psycopg", reason="psycopg is not installed: pip install -c constraints.txt -e '.[postgres]'")
    as_postgres: list[str] = []
    owner = None
    if os.geteuid() == 0:             # PostgreSQL refuses to run as root: initdb and the server run as postgres
        try:
            owner = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no 'postgres' user to run PostgreSQL as")
        if not shutil.which("runuser"):
            pytest.skip("running as root and runuser is missing: cannot run PostgreSQL as the postgres user")
        as_postgres = ["runuser", "-u", "postgres", "--"]
    # not under pytest's tmp_path (root's, mode 0700): the postgres user writes here
    base = Path(tempfile.mkdtemp(prefix="pgnn-pg-"))
    if owner:
        os.chown(base, owner.pw_uid, owner.pw_gid)
    data, port = base / "data", _free_port()

    def run(*argv, timeout=300):
        out = subprocess.run([*as_postgres, *argv], capture_output=True, text=True, timeout=timeout)
        assert out.returncode == 0, f"{argv[0]}: {out.stdout[-2000:]}{out.stderr[-2000:]}"

    try:
        run(initdb, "-D", str(data), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--no-sync")
        run(pg_ctl, "-D", str(data), "-l", str(base / "postgres.log"), "-w", "-t", "300", "-o",
            f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off", "start", timeout=400)
        # the README's first step; where the client tools are missing, the same through psycopg
        createdb = shutil.which("createdb") or shutil.which("createdb", path=str(Path(os.path.realpath(initdb)).parent))
        if createdb:
            run(createdb, "-h", "127.0.0.1", "-p", str(port), "-U", "postgres", "mlflow")
        else:
            import psycopg
            with psycopg.connect(f"host=127.0.0.1 port={port} user=postgres dbname=postgres", autocommit=True) as c:
                c.execute("CREATE DATABASE mlflow")
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/mlflow"
    finally:
        if (data / "postmaster.pid").exists():
            subprocess.run([*as_postgres, pg_ctl, "-D", str(data), "-m", "fast", "-w", "-t", "300", "stop"],
                           capture_output=True, timeout=400)
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture
def team_server(postgres, tmp_path):
    """`make server` on the throwaway database (this interpreter's venv, not reinstalled), on a free port,
    artifacts in tmp_path; yields its base URL once its health endpoint answers. Stopped at the end."""
    if not shutil.which("make"):
        pytest.skip("make is not installed")
    venv = Path(sys.prefix)
    if not (venv / "bin" / "mlflow").exists():
        pytest.skip(f"no mlflow in {venv}/bin: run the tests with the project's virtualenv")
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTEST_CURRENT_TEST", "MAKEFLAGS")}
    log = open(tmp_path / "server.log", "w")
    server = subprocess.Popen(
        ["make", "--no-print-directory", "-o", f"{venv}/.installed", "server", f"VENV={venv}",
         f"PG_URI={postgres}", f"ARTIFACTS={tmp_path / 'artifacts'}", "HOST=127.0.0.1", f"PORT={port}",
         f"ALLOWED_HOSTS=teamhost:{port}"],
        cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
        start_new_session=True)          # its own process group: make, mlflow and its workers stop together
    base = f"http://127.0.0.1:{port}"
    try:
        # poll up to a generous deadline: MLflow starts uvicorn and its workers, and migrates the new
        # database, on a machine busy with other work; the test waits only as long as the server needs
        deadline = time.monotonic() + 600
        while True:
            try:
                if requests.get(f"{base}/health", timeout=10).status_code == 200:
                    break
            except requests.RequestException:
                pass
            if server.poll() is not None:
                pytest.fail(f"make server exited with code {server.returncode}:\n"
                            + (tmp_path / "server.log").read_text()[-3000:])
            if time.monotonic() > deadline:
                pytest.fail("the MLflow server did not answer within 600 s:\n"
                            + (tmp_path / "server.log").read_text()[-3000:])
            time.sleep(0.5)
        yield base, tmp_path
    finally:
        try:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(timeout=180)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
        log.close()


#: two sweeps of physics_arx (a few seconds per job), overlapping on seeds 3 and 4: those jobs share their
#: stage results through the cache (computed once) and log the same training dataset at about the same time
SWEEPS = {"a": [1, 2, 3, 4], "b": [3, 4, 5, 6]}
ARTIFACTS = {"evaluate/errors.npz", "figures/feedforward.png", "figures/tracking_error.png"}


@pytest.mark.slow   # ~2-2.5 min: PostgreSQL, an MLflow server with its workers, 8 jobs at once (make test-full)
def test_two_parallel_sweeps_to_the_team_server_lose_nothing(team_server):
    base, tmp = team_server
    env = {**os.environ, "MLFLOW_TRACKING_URI": base, "PIPELINE_CACHE": str(tmp / "cache"),
           "PIPELINE_CACHE_KEY_FILE": str(tmp / "key"), "OMP_NUM_THREADS": "1"}
    sweeps = {name: subprocess.Popen(
        [sys.executable, "-m", "pipeline", "-m", "experiment=physics_arx", "seed=" + ",".join(map(str, seeds)),
         "hydra/launcher=local", "hydra.launcher.n_jobs=4", f"hydra.sweep.dir={tmp / name}"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
        for name, seeds in SWEEPS.items()}
    try:
        outs = {name: p.communicate(timeout=1200)[0] for name, p in sweeps.items()}
    finally:
        for p in sweeps.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    for name, p in sweeps.items():
        assert p.returncode == 0, f"sweep {name}:\n{outs[name][-3000:]}"

    # MLflow's default guard on Host headers, widened by ALLOWED_HOSTS for nodes that use a name
    assert requests.get(f"{base}/api/2.0/mlflow/experiments/search", params={"max_results": 1},
                        headers={"Host": f"teamhost:{base.rsplit(':', 1)[1]}"}, timeout=30).status_code == 200
    assert requests.get(f"{base}/api/2.0/mlflow/experiments/search", params={"max_results": 1},
                        headers={"Host": "elsewhere.example:80"}, timeout=30).status_code == 403

    from mlflow import MlflowClient
    c = MlflowClient(base)
    exp = c.get_experiment_by_name("physics_baseline")
    runs = c.search_runs([exp.experiment_id], max_results=1000)
    assert {r.info.status for r in runs} == {"FINISHED"}, [(r.info.run_name, r.info.status) for r in runs]
    parents = [r for r in runs if r.data.tags.get("sweep") == "parent"]
    children = [r for r in runs if r.data.tags.get("sweep") == "child"]
    assert len(parents) == 2 and len(children) == 8 and len(runs) == 10
    seeds_of = {p.info.run_id: sorted(int(k.data.params["seed"]) for k in children
                                      if k.data.tags["mlflow.parentRunId"] == p.info.run_id) for p in parents}
    assert sorted(seeds_of.values()) == sorted(SWEEPS.values())       # every child under its own sweep's parent
    assert all(p.info.run_name == "physics_arx-sweep" for p in parents)

    metric_keys = {frozenset(k.data.metrics) for k in children}
    assert len(metric_keys) == 1, metric_keys                          # no child is missing a metric
    assert {"evaluate/move/rms", "evaluate/move/max_abs", "baseline/a1"} <= next(iter(metric_keys))

    def science(run):
        return {k: v for k, v in run.data.metrics.items() if not k.startswith("time/") and "seconds" not in k}

    by_seed: dict[int, list] = {}
    for k in children:
        by_seed.setdefault(int(k.data.params["seed"]), []).append(k)
        assert k.data.metrics["evaluate/move/rms"] > 0 and k.data.tags["cache.evaluate"] in ("hit", "miss")
        files = set()
        stack = [""]
        while stack:
            for f in c.list_artifacts(k.info.run_id, stack.pop()):
                if f.is_dir:
                    stack.append(f.path)
                else:
                    files.add(f.path)
        assert files == ARTIFACTS | {f"{k.info.run_id}.yaml"}, files   # the resolved config is named by run id
        assert [d.dataset.name for d in k.inputs.dataset_inputs] == ["train"]
        npz = Path(c.download_artifacts(k.info.run_id, "evaluate/errors.npz", str(tmp / "dl" / k.info.run_id)))
        assert npz.stat().st_size > 0
    for seed in (3, 4):                                                  # run by both sweeps: equal numbers
        a, b = by_seed[seed]
        assert science(a) == science(b) and science(a)
    # the artifacts sit in the server's ARTIFACTS folder (proxied uploads), one folder per run
    on_disk = {p.name for p in (tmp / "artifacts").glob("*/*")}
    assert {k.info.run_id for k in children} <= on_disk
