"""Runner: caching by config hash, atomic stage outputs, validation before work, tracking."""
from __future__ import annotations

import json
import os
import shutil
import sys

import mlflow
import numpy as np
import pytest

from pipeline import owned, runner, tracking
from tests.conftest import SHORT_TWO_MASS


def _cache_state(store):
    """{stage: set of completed key directories} in the cache."""
    root = store / "cache"
    return {p.name: {d.name for d in p.iterdir() if not d.name.startswith(".")}
            for p in root.iterdir() if p.is_dir() and p.name not in ("configs", ".locks")}


#: a few-second PGNN training on the linear motor (one short move, 4 neurons, 5 LM steps)
SHORT_PGNN = ["experiment=b1_linear_motor", "hydra.mode=RUN", "model.hidden=[4]", "identify.max_iter=5",
              "data.references=[{name:s,kind:out_and_back,distance:0.05,v_max:0.05,a_max:4,j_max:1000}]",
              "stages=[generate,baseline,train]"]


def _run_tags(run_id):
    return tracking.client().get_run(run_id).data.tags


def test_rerun_hits_cache_and_invert_change_reruns_only_downstream(store, cfg_of, monkeypatch):
    cfg = cfg_of(*SHORT_TWO_MASS)
    first = runner.run_job(cfg)
    state1 = _cache_state(store)
    assert set(state1) == {"generate", "baseline", "train", "invert", "evaluate"}

    calls = []
    for name in runner.ORDER[:-1]:
        mod = __import__(f"stages.{name}", fromlist=["run"])
        orig = mod.run
        monkeypatch.setattr(mod, "run", lambda ctx, _o=orig, _n=name: calls.append(_n) or _o(ctx))
    again = runner.run_job(cfg)
    assert calls == []                                   # nothing recomputed
    assert _cache_state(store) == state1
    np.testing.assert_array_equal(again["evaluate"]["per_reference"]["held"]["e"],
                                  first["evaluate"]["per_reference"]["held"]["e"])

    runner.run_job(cfg_of(*SHORT_TWO_MASS, "invert=none"))
    assert calls == ["invert", "evaluate"]               # generate, baseline, train from cache
    runs = tracking.search_runs("physics_baseline")
    assert len(runs) == 3
    latest = runs.iloc[0]
    assert latest["tags.cache.generate"] == "hit" and latest["tags.cache.invert"] == "miss"
    assert latest["tags.invert"] == "none"


def test_same_seed_bit_identical_and_seed_changes_noise(store, cfg_of, tmp_path, monkeypatch):
    over = [*SHORT_TWO_MASS, "system.noise.std=1e-6"]
    a = runner.run_job(cfg_of(*over))["generate"]["dataset"].frame
    monkeypatch.setenv("PIPELINE_CACHE", str(tmp_path / "cache2"))   # recompute from scratch
    b = runner.run_job(cfg_of(*over))["generate"]["dataset"].frame
    assert a.equals(b)
    c = runner.run_job(cfg_of(*over, "seed=1"))["generate"]["dataset"].frame
    assert not np.array_equal(a["v"].to_numpy(), c["v"].to_numpy())


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_interrupted_stage_leaves_nothing_trusted(store, cfg_of, monkeypatch):
    import stages.evaluate as ev
    cfg = cfg_of(*SHORT_TWO_MASS)
    original = ev.run

    def dies(ctx):
        ctx.path("partial.bin").write_bytes(b"half")      # a half-written artifact
        raise KeyboardInterrupt                           # Ctrl-C mid-stage
    monkeypatch.setattr(ev, "run", dies)
    with pytest.raises(KeyboardInterrupt):
        runner.run_job(cfg)
    assert not (store / "cache" / "evaluate").exists() or not any((store / "cache" / "evaluate").iterdir())
    # a hard kill (SIGKILL) would leave the temporary directory: it must not be trusted either
    leftover = store / "cache" / "evaluate" / ".tmp-deadbeef-1-1"
    leftover.mkdir(parents=True)
    (leftover / "record.json").write_text(json.dumps({"metrics": [], "tags": {}, "figures": [],
                                                       "seconds": 0}))
    monkeypatch.setattr(ev, "run", original)
    out = runner.run_job(cfg)
    assert "held" in out["evaluate"]["per_reference"]
    runs = tracking.search_runs("physics_baseline")
    assert runs.iloc[0]["tags.cache.evaluate"] == "miss"
    killed = mlflow.search_runs(experiment_names=["physics_baseline"],
                                filter_string="attributes.status = 'KILLED'")
    assert len(killed) == 1                               # the interrupted job is marked KILLED (issue 13)


def test_run_logs_params_tags_metrics_figures_config_dataset(fresh_store, cfg_of):
    """Into a store the pipeline creates itself (the other tests start from a copy of an empty one)."""
    cfg = cfg_of(*SHORT_TWO_MASS)
    runner.run_job(cfg)
    run = tracking.search_runs("physics_baseline").iloc[0]
    c = tracking.client()
    r = c.get_run(run["run_id"])
    assert r.data.params["system.m2"] == "2.0" and r.data.params["seed"] == "0"
    for tag in ("experiment", "system", "data", "model", "identify", "regularizer", "invert",
                "git_sha"):
        assert r.data.tags[tag]
    assert r.info.run_name == "two_mass_stribeck-physics-s0"
    assert "evaluate/held/mae" in r.data.metrics and "baseline/m1" in r.data.metrics
    arts = {a.path for a in c.list_artifacts(r.info.run_id)}
    figs = {a.path for a in c.list_artifacts(r.info.run_id, "figures")}
    assert any(p.endswith(".yaml") for p in arts)         # resolved config
    assert "figures/tracking_error.png" in figs
    assert len(r.inputs.dataset_inputs) == 1
    # the evaluate stage's error signals, as an artifact other runs' figures can be drawn from
    local = mlflow.artifacts.download_artifacts(run_id=r.info.run_id, artifact_path="evaluate/errors.npz",
                                                dst_path=str(fresh_store / "dl"))
    z = np.load(local)
    assert z["held/e"].shape == z["held/r"].shape
    assert np.max(np.abs(z["held/e"])) == pytest.approx(r.data.metrics["evaluate/held/max_abs"], rel=1e-15)
    exp = c.get_experiment(r.info.experiment_id)
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"


@pytest.mark.parametrize("override, message", [
    ("system.m_typo=3", "m_typo"),                          # unknown key (Hydra struct mode)
    ("system=warp_drive", "warp_drive"),                    # unknown group option
    ("invert.kind=teleport", "no 'invert' implementation for kind 'teleport'"),
    ("stages=[generate,fly]", "unknown stage"),
    ("system.m1=-1", "m1"),                                 # bad value caught by the plant
    ("experiment_name=../../evil", "is not a name"),       # a path: would write outside the store
    ("experiment_name=/some/abs/dir", "is not a name"),
])
def test_bad_config_fails_before_work(store, cfg_of, override, message):
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException
    with pytest.raises((runner.ConfigError, HydraException, OmegaConfBaseException, ValueError),
                       match=message):
        runner.run_job(cfg_of(*SHORT_TWO_MASS, override))
    assert not (store / "cache" / "generate").exists()       # no work was done


def test_reference_outside_limits_fails_before_work(store, cfg_of):
    far = "evaluate.references=[{name:far,kind:out_and_back,distance:0.5,v_max:0.05,a_max:4,j_max:1000}]"
    with pytest.raises(runner.ConfigError, match="far.*outside the limits.*stroke"):
        runner.run_job(cfg_of("experiment=physics_linear_motor", far))
    assert not (store / "cache").exists() or not any((store / "cache").glob("generate/*"))


def test_measured_data_missing_file_and_nan(store, cfg_of, tmp_path):
    with pytest.raises(runner.ConfigError, match="does not exist"):
        runner.run_job(cfg_of("experiment=physics_two_mass", "data=measured", f"data.path={tmp_path}/none.parquet"))
    import pandas as pd
    df = pd.DataFrame({"t": np.arange(5) * 1e-3, "r": np.zeros(5), "u": np.zeros(5),
                       "y": [0, 0, np.inf, 0, 0]})
    df.to_parquet(tmp_path / "bad.parquet")
    with pytest.raises(runner.ConfigError, match="column 'y'.*NaN/inf"):
        runner.run_job(cfg_of("experiment=physics_two_mass", "data=measured", f"data.path={tmp_path}/bad.parquet"))


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_stage_subset_needs_cached_upstream(store, cfg_of):
    with pytest.raises(runner.ConfigError,
                       match=r"\['generate', 'baseline', 'train', 'invert'\] are needed.*no cached"):
        runner.run_job(cfg_of(*SHORT_TWO_MASS, "stages=[evaluate]"))
    assert tracking.search_runs("physics_baseline").empty      # failed before any run was opened
    runner.run_job(cfg_of(*SHORT_TWO_MASS, "stages=[generate,baseline]"))
    assert set(_cache_state(store)) == {"generate", "baseline"}


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_dataset_contract_parquet_and_sidecar(store, cfg_of):
    from pipeline import data
    runner.run_job(cfg_of(*SHORT_TWO_MASS, "system.noise.std=1e-6"))
    [path] = list((store / "cache" / "generate").glob("*/data/train.parquet"))
    ds = data.load(path)
    meta = json.loads(path.with_suffix(".json").read_text())
    assert {"system", "Ts", "seed", "config_hash"} <= set(meta)
    assert meta["system"] == "two_mass_stribeck" and meta["Ts"] == 1e-3
    assert path.parent.parent.name == meta["config_hash"][:20]
    assert {"t", "r", "u", "y", "u_ff", "u_fb", "f_opt", "y_clean", "v"} <= set(ds.frame.columns)
    # simulated data replay exactly: y = y_clean + v
    np.testing.assert_array_equal(ds["y"], ds["y_clean"] + ds["v"])


def test_empty_evaluation_references_and_bad_seed_fail_before_work(store, cfg_of):
    with pytest.raises(runner.ConfigError, match="evaluate.references is empty"):
        runner.run_job(cfg_of(*SHORT_TWO_MASS[:2], "evaluate.references=[]"))
    with pytest.raises(runner.ConfigError, match="seed='abc' is not an integer"):
        runner.run_job(cfg_of(*SHORT_TWO_MASS, "seed=abc"))
    assert not (store / "cache").exists()


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_report_stage_writes_report_summary_and_only_current_figures(store, cfg_of):
    runner.run_job(cfg_of(*SHORT_TWO_MASS))
    results = store / "results"
    (results / "figures").mkdir(parents=True)
    (results / "figures" / "stale.png").write_bytes(b"old")  # from an earlier report
    owned.record(results, ["figures"])
    runner.run_job(cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                          "report.experiments=[physics_baseline,never_run]"))
    import pandas as pd
    table = pd.read_csv(results / "summary.csv")
    run = tracking.search_runs("physics_baseline").iloc[0]
    mae = table[(table["variant"] == "two_mass_stribeck-physics-s0/held") & (table["metric"] == "mae")]
    assert float(mae["value"].iloc[0]) == run["metrics.evaluate/held/mae"]
    md = (results / "REPORT.md").read_text()
    assert "## physics_baseline" in md and "## never_run\n\nNo finished runs" in md
    figs = {p.name for p in (results / "figures").iterdir()}
    assert "stale.png" not in figs and any(f.endswith("tracking_error.png") for f in figs)
    assert [p.name for p in results.iterdir() if p.name.startswith(".")] == [owned.MANIFEST]  # no temp leftovers


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_report_never_replaces_a_users_file(store, cfg_of):
    """Issue 24 item 2: the report replaces REPORT.md, summary.csv, figures/ and export/ under
    paths.results only where it wrote them (pipeline/owned.py): a file of the user's there, or one
    edited since, stops the job before any work, named, and nothing is deleted or overwritten."""
    runner.run_job(cfg_of(*SHORT_TWO_MASS))
    results = store / "results"
    report = cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                    "report.experiments=[physics_baseline]")
    (results / "figures").mkdir(parents=True)
    (results / "notes.txt").write_text("mine")                        # beside the outputs: never touched
    runner.run_job(report)
    assert (results / "notes.txt").read_text() == "mine"
    md = (results / "REPORT.md").read_text()
    (results / "figures" / "my_plot.png").write_bytes(b"user")
    with pytest.raises(runner.ConfigError, match=r"paths.results=.* holds file\(s\) .*figures/my_plot.png"):
        runner.run_job(report)
    assert (results / "figures" / "my_plot.png").read_bytes() == b"user"
    (results / "figures" / "my_plot.png").unlink()
    (results / "REPORT.md").write_text(md + "\nmy own notes\n")         # edited since the report wrote it
    with pytest.raises(runner.ConfigError, match="REPORT.md"):
        runner.run_job(report)
    assert (results / "REPORT.md").read_text().endswith("my own notes\n")
    (results / "REPORT.md").write_text(md)
    runner.run_job(report)                                            # as written: replaced again
    with pytest.raises(runner.ConfigError, match="inside the source tree"):
        runner.validate(cfg_of("stages=[report]", f"paths.results={runner.ROOT / 'pipeline' / 'out'}"))
    link = store / "looks_harmless"
    link.symlink_to(runner.ROOT / "conf")                             # a link into the source tree
    with pytest.raises(runner.ConfigError, match="inside the source tree"):
        runner.validate(cfg_of("stages=[report]", f"paths.results={link}"))


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_a_report_stopped_after_its_swaps_is_still_known_as_ours(store, cfg_of, monkeypatch):
    """A report stopped between swapping in its outputs and recording them (Ctrl-C at that instant):
    the new files' hashes were listed before each swap (owned.allow), so the next report replaces
    them instead of refusing them as a user's edits."""
    runner.run_job(cfg_of(*SHORT_TWO_MASS))
    results = store / "results"
    report = cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                    "report.experiments=[physics_baseline]")
    runner.run_job(report)
    first = (results / "REPORT.md").read_text()
    two = cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                 "report.experiments=[physics_baseline,never_run]")        # another report: other contents

    def stopped(*a, **k):
        raise KeyboardInterrupt
    with monkeypatch.context() as patched:   # only this patch undone (not the store's: its cache key signs the record)
        patched.setattr(owned, "record", stopped)
        with pytest.raises(KeyboardInterrupt):
            runner.run_job(two)
    assert (results / "REPORT.md").read_text() != first                        # swapped in, not recorded
    assert owned.foreign(results, ("REPORT.md", "summary.csv", "figures")) == []
    runner.run_job(report)


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_report_stage_failure_leaves_the_old_results(store, cfg_of, monkeypatch):
    results = store / "results"
    (results / "figures").mkdir(parents=True)
    (results / "figures" / "kept.png").write_bytes(b"old")
    owned.record(results, ["figures"])
    runner.run_job(cfg_of(*SHORT_TWO_MASS))

    def broken(*args):
        raise RuntimeError("provider failed")
    monkeypatch.setattr("stages.report.generic.section", broken)
    with pytest.raises(RuntimeError, match="provider failed"):
        runner.run_job(cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                              "report.experiments=[physics_baseline]"))
    assert sorted(p.name for p in results.iterdir()) == [owned.MANIFEST, "figures"]   # no temp dirs, no partial files
    assert [p.name for p in (results / "figures").iterdir()] == ["kept.png"]


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_report_update_rebuilds_only_the_named_sections(store, cfg_of):
    """report.update=true: the named experiment's section, rows and figures are rebuilt; every other
    section, summary row and figure of the existing results/ stays as it was."""
    import pandas as pd
    runner.run_job(cfg_of(*SHORT_TWO_MASS))
    results = store / "results"
    (results / "figures").mkdir(parents=True)
    (results / "figures" / "other_exp-fig.png").write_bytes(b"kept")
    (results / "figures" / "physics_baseline-stale.png").write_bytes(b"old")
    (results / "REPORT.md").write_text("# Results\n\nold header (runs made at git `abc`, report at `d`)\n\n"
                                       "## other_exp\n\nkept text\n\n## physics_baseline\n\nold physics text\n")
    pd.DataFrame([{"experiment": "other_exp", "claim": "Z1", "variant": "v", "metric": "m", "value": 0.125,
                   "paper_value": "", "claim_holds": "true"},
                  {"experiment": "physics_baseline", "claim": "", "variant": "old", "metric": "m", "value": 1.0,
                   "paper_value": "", "claim_holds": ""}]).to_csv(results / "summary.csv", index=False)
    owned.record(results, ["REPORT.md", "summary.csv", "figures"])     # as an earlier report left them
    runner.run_job(cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                          "report.experiments=[physics_baseline]", "report.update=true"))
    md = (results / "REPORT.md").read_text()
    assert "## other_exp\n\nkept text" in md and "old physics text" not in md
    assert md.index("## other_exp") < md.index("## physics_baseline")        # order kept
    assert "| Z1 | other_exp | yes |" in md
    # the header's commits come from the runs in the store, never from parsing the old header
    assert "`abc`" not in md and "the others kept from the previous report (their runs in this store made at " \
        "git unknown)" in md
    table = pd.read_csv(results / "summary.csv")
    assert set(table["experiment"]) == {"other_exp", "physics_baseline"}
    assert "old" not in set(table["variant"]) and float(table[table.claim == "Z1"]["value"].iloc[0]) == 0.125
    figs = {p.name for p in (results / "figures").iterdir()}
    assert "other_exp-fig.png" in figs and "physics_baseline-stale.png" not in figs
    # a second update: the rebuilt section's commit from its runs, the kept one's still unknown
    runner.run_job(cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                          "report.experiments=[physics_baseline]", "report.update=true"))
    md = (results / "REPORT.md").read_text()
    assert f"runs made at git `{tracking.git_sha()[:12]}`" in md and "made at git unknown)" in md


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_restarts_cached_one_by_one_and_reused_bit_identically(store, cfg_of, tmp_path, monkeypatch):
    """Issue 10 item 3: best of 2 after best of 3 loads restarts 0 and 1 (no LM runs), equal to the
    bit to a best of 2 trained from scratch in another cache."""
    three = runner.run_job(cfg_of(*SHORT_PGNN, "identify.n_restarts=3"))["train"]
    assert len(_cache_state(store)["train.parts"]) == 3
    import pipeline.identify.narx as narx

    def no_lm(*a, **k):
        raise AssertionError("restart recomputed instead of loaded")
    with monkeypatch.context() as m:
        m.setattr(narx, "levenberg_marquardt", no_lm)
        two = runner.run_job(cfg_of(*SHORT_PGNN, "identify.n_restarts=2"))["train"]
    assert len(_cache_state(store)["train.parts"]) == 3
    assert two["costs"] == three["costs"][:2]
    monkeypatch.setenv("PIPELINE_CACHE", str(tmp_path / "other"))
    fresh = runner.run_job(cfg_of(*SHORT_PGNN, "identify.n_restarts=2"))["train"]
    assert fresh["costs"] == two["costs"]
    assert torch_equal(fresh["model"].parameter_vector(), two["model"].parameter_vector())


def torch_equal(a, b) -> bool:
    return bool((a == b).all())


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_artifacts_never_leave_the_store(store):
    """A name that is a path is refused by the tracking layer too (before any artifact is written)."""
    with pytest.raises(ValueError, match="outside"):
        tracking.experiment_id("../escape")
    assert not (store.parent / "escape").exists() and not (store / "escape").exists()


class _Payload:
    """A pickle that runs code when loaded (what a hostile cache entry would hold)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_cache_entry_from_elsewhere_is_never_unpickled(store, cfg_of, capsys):
    """Issue 13: an entry not signed with this machine's cache key (a crafted pickle, or a signed
    entry altered afterwards) is set aside unread and recomputed; its code never runs."""
    import pickle
    cfg = cfg_of(*SHORT_TWO_MASS, "stages=[generate]")
    good = runner.run_job(cfg)["generate"]["dataset"].frame
    entry = next(d for d in (store / "cache" / "generate").iterdir() if not d.name.startswith("."))
    marker = store / "pwned"
    (entry / "result.pkl").write_bytes(pickle.dumps(_Payload(marker)))      # signature no longer matches
    again = runner.run_job(cfg)["generate"]["dataset"].frame
    assert not marker.exists()
    assert "not signed with this machine's cache key" in capsys.readouterr().err
    assert again.equals(good)                                  # recomputed, bit-identical
    # a cache copied from another machine (its own key) is not trusted either
    other = store / "other.key"
    import os
    other.write_bytes(os.urandom(32))
    os.environ["PIPELINE_CACHE_KEY_FILE"] = str(other)
    try:
        assert runner.run_job(cfg)["generate"]["dataset"].frame.equals(good)
        assert "not signed" in capsys.readouterr().err
    finally:
        os.environ["PIPELINE_CACHE_KEY_FILE"] = str(store / "cache.key")


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_leftovers_of_a_killed_process_are_cleaned_on_the_next_start(store, cfg_of):
    """Issue 13: a SIGKILLed job leaves its MLflow run RUNNING and a temporary stage directory;
    the next job on this machine marks the run KILLED and removes the directory, and leaves a
    temporary of another machine (a shared cache) and of a live process alone."""
    import subprocess
    import sys
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    cfg = cfg_of(*SHORT_TWO_MASS, "stages=[generate]")
    gen = store / "cache" / "generate"
    gen.mkdir(parents=True)
    stale = gen / f".tmp-{'a' * 20}-{runner.HOST}-{dead.pid}-1"
    other_host = gen / f".tmp-{'b' * 20}-elsewhere-{dead.pid}-1"
    live = gen / f".tmp-{'c' * 20}-{runner.HOST}-{__import__('os').getpid()}-1"
    for d in (stale, other_host, live):
        d.mkdir()
    exp_id = tracking.experiment_id("physics_baseline")
    orphan = tracking.client().create_run(exp_id, tags={"host": runner.HOST, "pid": str(dead.pid)}).info.run_id
    runner.run_job(cfg)
    assert not stale.exists() and other_host.exists() and live.exists()
    assert tracking.client().get_run(orphan).info.status == "KILLED"


def test_run_name_shows_every_override_its_template_does_not(cfg_of):
    """Issue 14: a run's name says what it is; the experiment's own sweep keys stay as they are."""
    over = ["model=pgnn", "identify=narx", "invert=newton", "system.c=0"]
    cfg = cfg_of("experiment=physics_rot_trans", *over)
    assert runner.run_name_with_overrides(cfg, ["experiment=physics_rot_trans", *over]) == \
        "rot_trans_nmp-physics-zpetc-s0-model=pgnn-forward-identify=narx-invert=newton-c=0"
    sweep = ["invert=direct", "system.noise.structure=output", "system.noise.std=1.0e-8", "hydra/launcher=local"]
    cfg = cfg_of("experiment=b1_noise_sweep", *sweep[:3])
    assert runner.run_name_with_overrides(cfg, ["experiment=b1_noise_sweep", *sweep]) == \
        "linear_motor-output-sigma1e-08-direct-s0"      # all in the template: the reproduce names are kept


@pytest.mark.slow   # 12 s: composes every sweep of every experiment (make test-full)
def test_no_two_configs_of_a_sweep_share_a_run_name(store):
    """Issue 14: a small sweep through the CLI; every run of the experiment has its own name, and one
    name never covers two configs."""
    import subprocess
    import sys
    from conftest import SHORT_TWO_MASS
    out = subprocess.run([sys.executable, "-m", "pipeline", "-m", *SHORT_TWO_MASS, "system.noise.std=0,1e-7",
                          "seed=0,1", "stages=[generate]", f"hydra.sweep.dir={store / 'sweep'}"],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    runs = tracking.search_runs("physics_baseline")
    runs = runs[runs["tags.sweep"] == "child"]
    assert len(runs) == 4
    assert runs["tags.mlflow.runName"].nunique() == 4 and runs["tags.run_key"].nunique() == 4
    assert (runs.groupby("tags.run_key")["tags.config_hash"].nunique() == 1).all()
    assert any(n.startswith("two_mass_stribeck-physics-s1-data.references=") and n.endswith("-noise.std=1e-07")
               for n in runs["tags.run_key"])
    # the MLflow name leads with what the command line sweeps (issue 23)
    assert set(runs["tags.mlflow.runName"]) == {f"σ{sg}·s{seed} | two_mass_stribeck" for sg in ("0", "1e-7")
                                                for seed in (0, 1)}


def test_a_short_or_empty_cache_key_is_refused_and_a_new_key_is_whole(tmp_path, monkeypatch, cfg_of):
    """Issue 24 item 3: an empty key file (what a full disk could leave) would let anyone sign a
    forged entry; a key under 32 bytes is refused with the fix named. A new key is written to a
    temporary and linked into place: the key file is whole (32 bytes) or absent, never partial."""
    from pipeline import cache
    for content in (b"", b"k" * 31):
        key = tmp_path / f"short{len(content)}.key"
        key.write_bytes(content)
        monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(key))
        with pytest.raises(cache.ShortKey, match=f"holds {len(content)} bytes.*Delete it"):
            cache._signing_key()
    with pytest.raises(runner.ConfigError, match="holds 31 bytes"):      # a job names it before any work
        runner.validate(cfg_of(*SHORT_TWO_MASS, "stages=[generate]"))
    fresh = tmp_path / "sub" / "new.key"
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(fresh))
    assert len(cache._signing_key()) == 32 and fresh.read_bytes() == cache._signing_key()
    assert (fresh.stat().st_mode & 0o777) == 0o600
    assert [p.name for p in fresh.parent.iterdir()] == ["new.key"]      # no temporary left

    def full_disk(fd):                       # the key cannot reach the disk: no key file is left
        raise OSError(28, "No space left on device")
    failing = tmp_path / "full" / "k.key"
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(failing))
    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space") as full:
        cache._signing_key()
    assert full.value.filename == str(failing)                           # the key is named, not "a file"
    assert not failing.exists() and list(failing.parent.iterdir()) == []


def test_every_file_of_a_cache_entry_is_signed(store, cfg_of, capsys):
    """Issue 24 item 4: the signature covers every file an entry holds (here the generate stage's
    Parquet dataset, which later stages and the tracking store trust), not only its pickle: a byte
    appended, a file added or a link planted sets the entry aside, recomputed bit-identically."""
    cfg = cfg_of(*SHORT_TWO_MASS, "stages=[generate]")
    good = runner.run_job(cfg)["generate"]["dataset"].frame
    gen = store / "cache" / "generate"

    def entry():
        (e,) = [d for d in gen.iterdir() if not d.name.startswith(".")]
        return e
    data = next(entry().glob("data/*.parquet"))
    assert runner.run_job(cfg)["generate"]["dataset"].frame.equals(good)          # untouched: loaded
    assert "not loaded" not in capsys.readouterr().err
    for tamper in (lambda e: open(next(e.glob("data/*.parquet")), "ab").write(b"#"),
                   lambda e: (e / "data" / "extra.c").write_text("int evil;"),
                   lambda e: (e / "data" / "link").symlink_to(data)):
        tamper(entry())
        assert runner.run_job(cfg)["generate"]["dataset"].frame.equals(good)
        err = capsys.readouterr().err
        assert "not loaded (moved to .untrusted-" in err, err
        assert not any(p.name in ("extra.c", "link") for p in entry().rglob("*"))   # a clean recomputation
    # a signed entry of another config (a longer move) copied under this config's key
    longer = SHORT_TWO_MASS[1].replace("distance:0.02", "distance:0.03")
    other = runner.run_job(cfg_of(SHORT_TWO_MASS[0], longer, *SHORT_TWO_MASS[2:], "stages=[generate]"))
    assert not other["generate"]["dataset"].frame.equals(good)
    entries = {d.name: d for d in gen.iterdir() if not d.name.startswith(".")}
    key0 = runner.plan(cfg, ["generate"], {"generate": __import__("stages.generate", fromlist=["x"])})["generate"][:20]
    (seed1,) = [d for n, d in entries.items() if n != key0]
    shutil.rmtree(entries[key0])
    shutil.copytree(seed1, gen / key0)
    assert runner.run_job(cfg)["generate"]["dataset"].frame.equals(good)       # not seed 1's data
    assert "moved from another key" in capsys.readouterr().err


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_a_broken_cache_entry_lock_or_key_is_one_line_or_recomputed(store, cfg_of, capsys, monkeypatch):
    """Issue 24, tracebacks: an entry missing a file (record.json) is recomputed, not a traceback on
    every rerun; a lock file planted as a link is replaced, its target never truncated; a key path
    that is a folder is bad input, named before any work."""
    cfg = cfg_of(*SHORT_TWO_MASS, "stages=[generate]")
    good = runner.run_job(cfg)["generate"]["dataset"].frame
    (e,) = [d for d in (store / "cache" / "generate").iterdir() if not d.name.startswith(".")]
    (e / "record.json").unlink()
    assert runner.run_job(cfg)["generate"]["dataset"].frame.equals(good)
    assert "recomputing" in capsys.readouterr().err and (e / "record.json").is_file()
    (lock,) = (store / "cache" / ".locks").glob("generate-*.lock")
    victim = store / "victim.txt"
    victim.write_text("precious")
    lock.unlink()
    lock.symlink_to(victim)
    shutil.rmtree(e)
    assert runner.run_job(cfg)["generate"]["dataset"].frame.equals(good)
    assert victim.read_text() == "precious" and not lock.is_symlink()
    folder = store / "key-is-a-folder"
    folder.mkdir()
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(folder))
    with pytest.raises(runner.ConfigError, match="is not a plain file"):
        runner.validate(cfg)


@pytest.mark.slow
def test_time_spent_waiting_for_another_jobs_entry_is_measured(store, cfg_of, monkeypatch, tmp_path):
    """The job queue orders by a job's own work (results/timings.csv): a job that waits while another
    job computes the same entry reports the wait in ``runner.WAITED``, which the job's seconds leave
    out (pipeline/__main__.py). Another process holds the generate entry's lock until 1 s after the
    job says it waits."""
    import builtins
    import subprocess
    import sys
    import threading
    import time
    from pipeline.cache import _locked
    cfg = cfg_of(*SHORT_TWO_MASS, "stages=[generate]")
    _, _, modules = runner.validate(cfg)
    key = runner.plan(cfg, ["generate"], modules)["generate"]
    lock = _locked(runner.cache_dir(cfg) / "generate" / key[:20])
    release = tmp_path / "release"
    holder = subprocess.Popen([sys.executable, "-c", "import os, sys, time; from filelock import FileLock; "
                               "l = FileLock(sys.argv[1]); l.acquire(); print('held', flush=True)\n"
                               "while not os.path.exists(sys.argv[2]): time.sleep(0.05)",
                               lock.lock_file, str(release)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"

    def said(*args, **kw):                  # the runner's "waiting for another job" line starts the clock
        if any("waiting for another job" in str(a) for a in args):
            threading.Timer(1.0, release.touch).start()
        builtins.print(*args, **kw)
    monkeypatch.setattr(runner, "print", said, raising=False)
    t0 = time.perf_counter()
    runner.run_job(cfg)
    took = time.perf_counter() - t0
    holder.wait(timeout=60)
    assert 0.9 < runner.WAITED <= took
    runner.run_job(cfg)                      # cached, nobody holds the lock: no wait
    assert runner.WAITED == 0.0


class _Moved:                      # a class of an older code layout (deleted below, as a move does)
    pass


def test_an_entry_whose_class_moved_is_recomputed_not_a_traceback(tmp_path, monkeypatch, capsys):
    """A signed entry written before a class moved to another module (pipeline/models/pgnn.py's
    physics maps and fast path) names that class where it no longer is: the entry is set aside and
    recomputed with one warning line, not an AttributeError on every rerun."""
    from pipeline import cache
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(tmp_path / "k.key"))
    entry = tmp_path / "train" / "abc"
    entry.mkdir(parents=True)
    cache._write_signed(entry, {"model": _Moved()})
    assert type(cache._load_trusted(entry)[0]["model"]) is _Moved       # loads while the class is there
    monkeypatch.delattr(sys.modules[__name__], "_Moved")
    assert cache._load_trusted(entry) is None
    err = capsys.readouterr().err
    assert "no longer has where it was" in err and "recomputing" in err
    assert not entry.exists() and len(list(entry.parent.glob(".untrusted-abc-*"))) == 1
