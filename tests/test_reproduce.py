"""make reproduce's driver: per-experiment wall time, jobs, ETA, results/timings.csv (issue 10, item 4)."""
from __future__ import annotations

import pandas as pd

from pipeline import reproduce


def test_eta_and_merge_from_the_previous_timings():
    prev = pd.DataFrame([{"experiment": e, "jobs": 1, "wall_seconds": s, "cores_used": 1, "cores_available": 2,
                          "git_sha": "old"} for e, s in (("a", 10.0), ("b", 20.0), ("c", 30.5))])
    assert reproduce.eta_seconds(prev, ["b", "c"]) == 50.5
    assert reproduce.eta_seconds(prev, ["b", "new"]) is None and reproduce.eta_seconds(None, ["a"]) is None
    merged = reproduce.merge(prev, [{"experiment": "b", "jobs": 4, "wall_seconds": 7.0, "cores_used": 1,
                                     "cores_available": 2, "git_sha": "new"}])
    assert list(merged["experiment"]) == ["b", "a", "c"]                 # the rerun first, the rest kept
    assert merged.set_index("experiment").loc["b", "wall_seconds"] == 7.0


def test_driver_times_an_experiment_and_counts_its_jobs(store, capsys):
    results = store / "results"
    table = reproduce.run(["physics_arx"], results)
    out = capsys.readouterr()
    assert "== physics_arx: " in out.out and "1 job(s)" in out.out and "done" in out.out
    assert "[arx_bias-" in out.err                                        # the job's own lines streamed
    on_disk = pd.read_csv(results / "timings.csv")
    assert list(on_disk.columns) == reproduce.COLUMNS and on_disk.loc[0, "experiment"] == "physics_arx"
    assert on_disk.loc[0, "jobs"] == 1 and on_disk.loc[0, "wall_seconds"] > 0
    assert len(table) == 1 and table.loc[0, "wall_seconds"] == on_disk.loc[0, "wall_seconds"]


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
