"""make reproduce's driver: one queue of every experiment's jobs, longest first, results/timings.csv (issues 10, 19)."""
from __future__ import annotations

import pandas as pd
import pytest

from pipeline import reproduce


def _prev(rows):
    return pd.DataFrame([{"experiment": e, "job": j, "wall_seconds": w, "git_sha": "old"} for e, j, w in rows])


def test_longest_first_from_the_previous_job_times():
    """LPT order: a job's own previous time, else its experiment's mean, unknown jobs first (in the
    given order), ties in the given order; the written file keeps other experiments' rows."""
    from pipeline.job_queue import Job, longest_first, read_timings, write_timings
    jobs = [Job("a", ("x=1", "experiment=a")), Job("a", ("x=2", "experiment=a")), Job("b", ("experiment=b",)),
            Job("new", ("experiment=new",)), Job("a", ("x=3", "experiment=a")), Job("c", ("experiment=c",))]
    prev = _prev([("a", "x=1", 5.0), ("a", "x=2", 30.0), ("b", "", 12.0), ("c", "", 12.0)])
    got = [(j.experiment, j.key) for j in longest_first(jobs, prev)]
    # x=3 has no time of its own: its experiment's mean (17.5) places it between 30 and 12
    assert got == [("new", ""), ("a", "x=2"), ("a", "x=3"), ("b", ""), ("c", ""), ("a", "x=1")]
    assert [j.key for j in longest_first(jobs, None)] == [j.key for j in jobs]      # no times: as given
    import tempfile
    from pathlib import Path
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "timings.csv"
        _prev([("a", "x=1", 5.0), ("z", "", 99.0)]).to_csv(path, index=False)
        write_timings(path, jobs[:2], [1.0, 2.0], read_timings(path))
        t = read_timings(path)
        assert list(zip(t["experiment"], t["job"], t["wall_seconds"])) == [("a", "x=1", 1.0), ("a", "x=2", 2.0),
                                                                             ("z", "", 99.0)]


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_queue_holds_every_job_of_each_experiments_sweep(tmp_path):
    """hydra/sweeper=queue expands each experiment's own sweep as Hydra's basic sweeper does (b2_rot_trans:
    2 γ x 10 n1 = 20 jobs, physics_arx: 1) into one list, longest first by the timings given."""
    import subprocess
    import sys
    from pathlib import Path
    _prev([("b2_rot_trans", "invert.gamma=5e-05 model.hidden=[4]", 50.0), ("physics_arx", "", 20.0),
           ("b2_rot_trans", "invert.gamma=1e-06 model.hidden=[48]", 40.0)]).to_csv(tmp_path / "t.csv", index=False)
    out = subprocess.run([sys.executable, "-m", "pipeline", "-m", "hydra/sweeper=queue",
                          "hydra.sweeper.experiments=[physics_arx,b2_rot_trans]", "hydra.sweeper.dry_run=true",
                          f"hydra.sweeper.timings='{tmp_path / 't.csv'}'", f"hydra.sweep.dir={tmp_path}/sweep"],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], check=True).stdout
    lines = [ln.split("\t") for ln in out.splitlines() if "\t" in ln]
    assert len(lines) == 21 and "queue: 21 jobs of 2 experiments" in out
    hidden = ["[48]", "[32]", "[24]", "[20]", "[16]", "[8]", "[4]", "[2]", "[1]", "[]"]
    want = {("b2_rot_trans", f"invert.gamma={g} model.hidden={h}") for g in ("1e-06", "5e-05") for h in hidden}
    assert {(e, k) for _, e, k in lines} == want | {("physics_arx", "")}
    # the jobs of b2_rot_trans without a time of their own are estimated at its mean (45 s): after
    # the 50 s job, before its own 40 s one and physics_arx's 20 s, in their sweep order
    assert lines[0][1:] == ["b2_rot_trans", "invert.gamma=5e-05 model.hidden=[4]"]
    assert [float(t) for t, _, _ in lines[1:-2]] == [45.0] * 18
    assert [k for _, e, k in lines[1:3]] == ["invert.gamma=1e-06 model.hidden=[32]",
                                             "invert.gamma=1e-06 model.hidden=[24]"]
    assert lines[-2][1:] == ["b2_rot_trans", "invert.gamma=1e-06 model.hidden=[48]"]
    assert lines[-1][1:] == ["physics_arx", ""] and float(lines[-1][0]) == 20.0


@pytest.mark.slow     # real jobs through the queue (~11 s); make reproduce runs the same path
def test_driver_times_the_queue_and_counts_its_jobs(store, capsys):
    results = store / "results"
    table = reproduce.run(["physics_arx"], results)
    out = capsys.readouterr()
    assert "== done: " in out.out and "1 jobs of 1 experiments" in out.out
    assert "[arx_bias-" in out.err                                        # the job's own lines streamed
    on_disk = pd.read_csv(results / "timings.csv", keep_default_na=False)
    # this run's job first, the total last; rows of experiments it did not run are kept (order estimates)
    assert on_disk.iloc[0]["experiment"] == "physics_arx" and on_disk.iloc[-1]["experiment"] == "total"
    assert (on_disk["experiment"] == "physics_arx").sum() == 1 and (on_disk["experiment"] == "total").sum() == 1
    job, total = on_disk.iloc[0], on_disk.iloc[-1]
    assert 0 < job["wall_seconds"] <= total["wall_seconds"]
    assert f"{reproduce.cores_available()} at once" in total["job"]
    assert len(table) == len(on_disk)


def test_job_lines_with_brackets_in_run_names_are_counted():
    """Run names such as rot_trans_nmp-fhofc-n[32]-g1e-06-s0 hold brackets: each is one job."""
    from pipeline.reproduce import _STAGE_LINE
    lines = ["[rot_trans_nmp-fhofc-n[32]-g1e-06-s0] train: 3.0 s", "[rot_trans_nmp-fhofc-n[]-g1e-06-s0] invert: cached",
             "[a] evaluate: 0.1 s", "[b] something else", "progress [x] train 10%"]
    runs = {m.group("run") for m in map(_STAGE_LINE.match, lines) if m}
    assert runs == {"rot_trans_nmp-fhofc-n[32]-g1e-06-s0", "rot_trans_nmp-fhofc-n[]-g1e-06-s0", "a"}


def test_a_subset_reproduce_updates_the_report_instead_of_replacing_it():
    """Issue 14: `make reproduce EXPERIMENTS="physics_arx k_two_mass"` runs the report with
    report.update=true (only those sections, rows and figures rebuilt: tests/test_runner.py
    test_report_update_rebuilds_only_the_named_sections); the full run replaces it."""
    import shutil
    import subprocess
    from pathlib import Path
    if shutil.which("make") is None:
        import pytest
        pytest.skip("no make")
    root = Path(__file__).resolve().parents[1]

    def report_line(*args):
        out = subprocess.run(["make", "-n", "reproduce", *args], cwd=root, capture_output=True, text=True)
        return [ln for ln in out.stdout.splitlines() if "stages=[report]" in ln][0]
    assert "report.update=true" in report_line("EXPERIMENTS=physics_arx k_two_mass")
    assert "report.update=false" in report_line()


def test_committed_summary_has_one_row_per_key():
    """Issue 14: no (experiment, claim, variant, metric) key twice in results/summary.csv (the report
    stage refuses to write one; this checks the committed file)."""
    from pathlib import Path

    import pandas as pd

    from stages.report import KEY
    table = pd.read_csv(Path(__file__).resolve().parents[1] / "results" / "summary.csv", dtype=str,
                        keep_default_na=False)
    dup = table[table.duplicated(KEY, keep=False)]
    assert dup.empty, dup[KEY].to_string()
    assert len(table) > 100


@pytest.mark.slow      # a 4-job sweep and a single job through the joblib launcher (~40 s on 2 cores)
def test_queue_gives_each_swept_experiment_its_parent_and_the_same_runs(store):
    """A queue of physics_arx (one job, no sweep) and b2_rot_trans_linear (a 4-job sweep): the sweep's
    four runs are children of one parent 'b2_rot_trans_linear-sweep' that ends FINISHED; the single job
    has no parent (as when it runs alone); the run names are the experiments' own."""
    import mlflow
    reproduce.run(["physics_arx", "b2_rot_trans_linear"], store / "results")
    c = mlflow.MlflowClient()
    runs = mlflow.search_runs(search_all_experiments=True)
    parents = runs[runs["tags.sweep"] == "parent"]
    assert list(parents["tags.mlflow.runName"]) == ["b2_rot_trans_linear-sweep"]
    assert c.get_run(parents["run_id"].iloc[0]).info.status == "FINISHED"
    kids = runs[runs["tags.mlflow.parentRunId"] == parents["run_id"].iloc[0]]
    assert len(kids) == 4 and set(kids["status"]) == {"FINISHED"}
    assert all(n.startswith("rot_trans_nmp-il_fhofc-linear_") for n in kids["tags.run_key"])
    # each run names the experiment file it came from, inside the one queue too (the report selects by it)
    assert set(kids["tags.experiment_file"]) == {"b2_rot_trans_linear"}
    assert set(runs.loc[runs["tags.sweep"] == "single", "tags.experiment_file"]) == {"physics_arx"}
    # the parent's comparison of its children (issue 23), logged when the queue ended its sweep
    arts = {a.path for a in c.list_artifacts(parents["run_id"].iloc[0], "compare")}
    assert {"compare/comparison.csv", "compare/comparison.md", "compare/comparison.png"} <= arts
    assert arts <= {"compare/comparison.csv", "compare/comparison.md", "compare/comparison.png",
                    "compare/loss_overlay.png"}
    # the MLflow names lead with what the sweep varies (issue 23): trial noise, then θ*
    assert set(kids["tags.mlflow.runName"]) == {f"{a}·θ*{b} | rot_trans_nmp s0"
                                                for a in ("trialnoise", "noiseless") for b in ("arx", "oracle")}
    single = runs[runs["tags.mlflow.runName"] == "arx_bias-physics-s0"]
    assert len(single) == 1 and single["tags.sweep"].iloc[0] == "single"


def test_committed_results_are_the_pipelines_own():
    """results/.pgnn-owned.json lists every committed report output with its sha256: otherwise the report stage
    of `make reproduce` on a fresh clone refuses to replace them (pipeline.owned; a REPORT.md copied in
    without its manifest once made a fresh clone's subset reproduce fail at its last step)."""
    from pathlib import Path

    from pipeline import owned
    from stages.report import OUTPUTS
    results = Path(__file__).resolve().parents[1] / "results"
    assert owned.foreign(results, OUTPUTS) == []
