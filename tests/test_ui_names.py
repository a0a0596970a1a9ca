"""Issue 23: run names that lead with what varies, notes, the per-sweep comparison, µm/µs twins, the
report's regularised-vs-not part and the registry's champion (fast: synthetic runs, one tiny model)."""
from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest

from pipeline import compare, naming

B1 = {"invert": ["newton", "physics", "direct", "analytic"], "system.noise.structure": ["equation", "output"]}
MODEL = {"newton": "pgnn-forward", "physics": "pgnn-forward", "direct": "pgnn-inverse", "analytic": "pgnn-invertible"}
#: characters of a run name the runs table shows at 1600 px (measured by tests/test_ui_browser.py: ~26)
VISIBLE = 25


def _names(sweep: dict) -> list[str]:
    keys = naming.varying_keys({k: ",".join(map(str, v)) for k, v in sweep.items()})
    out = []
    for combo in itertools.product(*sweep.values()):
        values = dict(zip(sweep, combo))
        out.append(naming.display_name(values, keys, "linear_motor", 0, "key", MODEL[values["invert"]]))
    return out


@pytest.mark.parametrize("sweep", [B1 | {"regularizer": ["physics_l2", "none"]},
                                   B1 | {"system.noise.std": [0.0, 1e-8, 1e-7, 1e-6]}],
                         ids=["b1_linear_motor", "b1_noise_sweep"])
def test_display_names_lead_with_what_varies_and_fit_the_column(sweep):
    names = _names(sweep)
    leads = [n.split(" | ")[0] for n in names]
    assert len(set(leads)) == len(names)                      # told apart by the lead alone
    assert max(map(len, leads)) <= VISIBLE, max(leads, key=len)
    assert all(n.endswith(" | linear_motor s0") for n in names)
    assert "direct·inv·eq" in leads[len(leads) // 2]            # inversion first, then what it inverts
    if "system.noise.std" in sweep:
        assert "direct·inv·eq·σ1e-7" in leads and "newton·fwd·out·σ0" in leads
    else:
        assert "analytic·invt·out·noreg" in leads and "physics·eq·L2" in leads


def test_varying_keys_from_the_sweep_and_the_command_line():
    params = {"invert": "newton,physics,direct,analytic", "system.noise.structure": "equation,output",
              "model.hidden": "choice([])", "invert.gamma": "1.0e-8", "regularizer": "physics_l2"}
    assert naming.varying_keys(params) == ["invert", "system.noise.structure"]
    # a single value on the command line replaces the sweep of that key; a list there sweeps it
    assert naming.varying_keys(params, ["invert=newton", "system.noise.std=0,1e-7", "data.references=[{a:1,b:2}]",
                                        "hydra.launcher.n_jobs=2"]) == ["system.noise.structure", "system.noise.std"]
    assert naming.varying_keys({"model.hidden": "choice([48],[32])"}) == ["model.hidden"]
    assert naming.short_value("model.hidden", [48]) == "n48" and naming.short_value("invert.gamma", 5e-5) == "γ5e-5"
    # issue 52: names sort numerically as text (the MLflow UI's order): n00 (linear) < n01 < n08 < n16 < n48
    hidden = [[48], [32], [8], [1], [], [16, 4]]
    names = [naming.short_value("model.hidden", h) for h in hidden]
    assert sorted(names) == ["n00", "n01", "n08", "n16-04", "n32", "n48"]
    got = sorted(["n16", "n1", "n8", "σ1e-6", "σ1e-7"], key=compare.natural_key)
    assert got == ["n1", "n8", "n16", "σ1e-7", "σ1e-6"]
    assert naming.short_value("invert.trial_noise", True) == "trialnoise"
    assert naming.short_value("invert.trial_noise", False) == "noiseless"
    assert naming.short_value("identify.theta_star", "oracle") == "θ*oracle"
    assert naming.short_value("data.use_exact", True) == "use_exact"
    # nothing varies: the run keeps its key as name
    assert naming.display_name({}, [], "linear_motor", 0, "linear_motor-equation-physics-s0") == \
        "linear_motor-equation-physics-s0"


def _runs() -> pd.DataFrame:
    """b1_linear_motor-like runs: the physics feedforward ignores the regulariser, the others do not."""
    rows = []
    for inv, structure, reg in itertools.product(["physics", "newton", "direct"], ["equation", "output"],
                                                 ["physics_l2", "none"]):
        mae = {"physics": 1.5e-5, "newton": 1e-6, "direct": 3e-6}[inv] * (2 if structure == "output" else 1)
        if inv != "physics" and reg == "none":
            mae *= 1.1
        rows.append({"tags.mlflow.runName": f"{inv}·{structure}·{reg} | linear_motor s0", "tags.invert": inv,
                     "tags.model": MODEL[inv], "tags.regularizer": reg, "params.system.noise.structure": structure,
                     "params.regularizer.lam": "0.01" if reg == "physics_l2" else np.nan,
                     "params.seed": "0", "tags.config_hash": f"{inv}{structure}{reg}",
                     "metrics.evaluate/v0.15/mae": mae, "metrics.evaluate/v0.15/mae_um": 1e6 * mae,
                     "metrics.train/theta_phy/m": 20.0 + (0.1 if reg == "none" else 0)})
    return pd.DataFrame(rows)


def test_comparison_groups_by_the_factors_and_states_identical_results(tmp_path):
    table, findings = compare.comparison(_runs(), ["evaluate/v0.15/mae", "train/theta_phy/m"])
    # λ only follows the regulariser, the seed does not vary: neither is a factor
    assert list(table.columns) == ["run", "inversion", "structure", "regulariser", "noise",
                                   "evaluate/v0.15/mae_um", "train/theta_phy/m"]
    assert table["evaluate/v0.15/mae_um"].iloc[0] == pytest.approx(3.3)   # µm; sorted: direct, equation, none first
    # issue 52: the regulariser sorts last, so each run sits beside its twin with the other regulariser
    for a in range(0, len(table), 2):
        pair = table.iloc[a:a + 2]
        assert pair["inversion"].nunique() == pair["noise"].nunique() == 1 and pair["regulariser"].nunique() == 2
    # the physics feedforward's MAE does not move with the regulariser (its mass does: the unused PGNN)
    (finding,) = findings
    assert finding.startswith("Identical across regulariser (none, physics_l2) where inversion = physics")
    assert "2 group(s); 4 other group(s) differ" in finding and "baseline least-squares θ*_phy" in finding
    md = compare.markdown(table, findings)
    assert md.count("\n| ") == len(table) + 1 and "\\|" in md    # the name's '|' escaped in the table
    assert compare.figure(table, tmp_path / "c.png", "t").stat().st_size > 5000
    # the rational model with and without the orthogonal regulariser: stated with its reason
    k = pd.DataFrame([{"tags.model": m, "tags.regularizer": r, "metrics.evaluate/a/sq_norm2": v}
                      for m, r, v in [("rational", "orthogonal", 2.0), ("rational", "none", 2.0),
                                      ("pgnn_shared_ar", "orthogonal", 1.0), ("pgnn_shared_ar", "none", 0.5)]])
    (finding,) = compare.identical(k, compare.varying_factors(k), ["metrics.evaluate/a/sq_norm2"])
    assert "where structure = rational" in finding and "rational model has none" in finding


def test_display_twins_in_micrometres_and_microseconds():
    m = [("evaluate/v0.15/mae", 1.5e-5, None), ("evaluate/v0.15/max_abs_accel", 2e-5, None),
         ("invert/v0.15/sample_seconds_median", 3e-6, None), ("evaluate/v0.15/sq_norm2", 1.0, None),
         ("train/loss/restart0", 0.1, 3)]
    twins = dict((k, v) for k, v, _ in compare.display_metrics(m, "linear_motor"))
    assert twins == pytest.approx({"evaluate/v0.15/mae_um": 15.0, "evaluate/v0.15/max_abs_accel_um": 20.0,
                                   "invert/v0.15/sample_seconds_median_us": 3.0})
    assert all(not k.endswith("_um") for k, _, _ in compare.display_metrics(m, "arx_bias"))   # not a length


def test_report_side_study_regularised_vs_not(tmp_path, store, monkeypatch):
    """b1_linear_motor's regularizer=none runs stay out of the claims and get their own table and rows."""
    from stages.report import claims_b1, split_side
    monkeypatch.setattr(claims_b1, "copy_figures", lambda *a, **k: [])   # synthetic runs: no artifacts
    monkeypatch.setattr(claims_b1, "load_errors", lambda run_id: None)
    runs = []
    for inv, reg in itertools.product(["physics", "direct", "newton", "analytic"], ["physics_l2", "none"]):
        mae = {"physics": 1.5e-5, "direct": 3e-6, "newton": 1e-6, "analytic": 1.2e-6}[inv]
        if reg == "none" and inv != "physics":
            mae *= 1.25
        runs.append({"tags.mlflow.runName": f"linear_motor-equation-{inv}-s0" + ("-regularizer=none" if reg == "none"
                                                                                 else ""),
                     "run_id": f"{inv}{reg}", "tags.invert": inv, "tags.regularizer": reg,
                     "params.system.noise.structure": "equation", "metrics.evaluate/v0.15/mae": mae,
                     "metrics.evaluate/v0.15/max_abs": 4 * mae, "metrics.train/theta_phy/m": 20.0})
    head, side = split_side("b1_linear_motor", pd.DataFrame(runs))
    assert len(head) == len(side) == 4 and set(side["tags.regularizer"]) == {"none"}
    rows, md = claims_b1.side_section("b1_linear_motor", head, side, tmp_path)
    assert "### Regularised vs not" in md and "+25.0%" in md and "4 of 16" not in md
    assert "2 of 8 MAEs are identical to the bit" not in md and "1 of 4 MAEs are identical" in md
    assert all(r["variant"].startswith("regularizer=none/") and r["claim"] == "" for r in rows)
    ratio = {r["variant"]: r["value"] for r in rows if r["metric"] == "mae_over_regularised"}
    assert ratio["regularizer=none/equation/newton/v0.15"] == pytest.approx(1.25)
    assert ratio["regularizer=none/equation/physics/v0.15"] == 1.0
    assert "B1b conditions (`equation` noise) with the unregularised PGNNs" in md


def _zero(model_input):   # a pyfunc model (a callable): u_ff = 0
    return model_input * 0


def test_champion_is_registered_once_and_moves_to_a_better_run(store):
    import warnings

    import mlflow
    import mlflow.pyfunc

    from pipeline import tracking
    from stages.report import champion

    def job(mae: float, invert: str, reg: str = "physics_l2") -> str:
        run = tracking.JobRun("b1_linear_motor", f"{invert}·eq·{reg} | linear_motor s0",
                              {"invert": invert, "regularizer": reg, "run_key": f"lm-{invert}-{mae:g}"},
                              {"compare_metrics": ["evaluate/v0.15/mae"]}, description="Compare ...")
        run.log_metrics([("evaluate/v0.15/mae", mae, None), ("evaluate/v0.15/mae_um", 1e6 * mae, None)])
        with warnings.catch_warnings(), mlflow.start_run(run_id=run.run_id):
            warnings.simplefilter("ignore")
            mlflow.pyfunc.log_model(name=run.model_name(f"ff_{invert}"), python_model=_zero,
                                    pip_requirements=["mlflow"])
        run.end()
        return run.run_id

    best = job(1e-6, "newton")
    job(3e-6, "direct")
    name, version = champion("b1_linear_motor")
    c = tracking.client()
    v = c.get_model_version_by_alias(name, tracking.CHAMPION)
    assert name == "b1_linear_motor-feedforward" and v.version == int(version) and v.run_id == best
    assert v.tags["evaluate/v0.15/mae_um"] == "1" and v.tags["run_key"] == "lm-newton-1e-06"
    assert v.tags["chosen_by"] == "min evaluate/v0.15/mae"
    assert champion("b1_linear_motor") == (name, version)          # the report rerun: no new version
    assert len(c.search_model_versions(f"name='{name}'")) == 1
    better = job(5e-7, "analytic")
    assert champion("b1_linear_motor") == (name, "2")
    assert c.get_model_version_by_alias(name, tracking.CHAMPION).run_id == better
    # issue 52: an unregularised run (a side study of the report) with the lowest MAE is the champion, the
    # version says by which rule and what the run is; the metric is a tag once (µm), not twice
    noreg = job(4e-7, "analytic", "none")
    assert champion("b1_linear_motor") == (name, "3")
    v = c.get_model_version_by_alias(name, tracking.CHAMPION)
    assert v.run_id == noreg and v.tags["regularizer"] == "none" and v.tags["inversion"] == "analytic"
    assert "evaluate/v0.15/mae" not in v.tags and v.tags["evaluate/v0.15/mae_um"] == "0.4"
    assert v.description.startswith("Lowest `evaluate/v0.15/mae` (4e-07) among all 4 runs")
    assert "regularizer none" in v.description
    # logged models are named after their run
    names = {m.name for ms in tracking.logged_models("b1_linear_motor").values() for m in ms}
    assert names == {"ff_newton-lm-newton-1e-06", "ff_direct-lm-direct-3e-06", "ff_analytic-lm-analytic-5e-07",
                     "ff_analytic-lm-analytic-4e-07"}


def test_report_keys_runs_by_run_key_and_reads_stores_made_before_it():
    from stages.report._runs import _identity
    old = pd.DataFrame({"tags.mlflow.runName": ["linear_motor-equation-newton-s0"], "run_id": ["a"]})
    assert _identity(old).equals(old)                       # no run_key tag: the name is the key
    new = pd.DataFrame({"tags.mlflow.runName": ["newton·fwd·eq·L2 | linear_motor s0", "b1_linear_motor-sweep"],
                        "tags.run_key": ["linear_motor-equation-newton-s0", np.nan], "run_id": ["a", "p"]})
    got = _identity(new)
    assert list(got["tags.mlflow.runName"]) == ["linear_motor-equation-newton-s0", "b1_linear_motor-sweep"]
    assert list(got["tags.display_name"]) == list(new["tags.mlflow.runName"])


def test_experiments_carry_kind_and_note_and_links_open_the_model_training_view(store):
    from pipeline import tracking
    run = tracking.JobRun("b1_linear_motor", "direct·inv·eq | linear_motor s0", {"mlflow.note.content": "this run"},
                          {"seed": 0}, description="Compare direct with indirect.")
    run.end()
    exp = tracking.client().get_experiment_by_name("b1_linear_motor")
    assert exp.tags[tracking.NOTE] == "Compare direct with indirect."
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"
    tracking.experiment_id("b1_linear_motor", "Compare, revised.")          # a changed description replaces it
    assert tracking.client().get_experiment_by_name("b1_linear_motor").tags[tracking.NOTE] == "Compare, revised."
    (line,) = tracking.experiment_links("http://h:1")
    assert line.split()[-1] == (f"http://h:1/#/experiments/{exp.experiment_id}/runs?workflowType=machine_learning"
                                "&orderByKey=attributes.run_name&orderByAsc=true")


def test_sweep_parent_gets_one_loss_overlay_of_each_childs_best_restart(store, tmp_path):
    """Issue 52: the loss curves of a sweep compared on one figure, each child by its best restart."""
    import matplotlib.image

    from pipeline import tracking
    c = tracking.client()
    exp = c.create_experiment("sweep")
    parent = c.create_run(exp, tags={"sweep": "parent"}).info.run_id
    for name, scale in (("n16·L2 | s0", 1.0), ("n08·L2 | s0", 10.0)):
        kid = c.create_run(exp, run_name=name, tags={"mlflow.parentRunId": parent, "sweep": "child"}).info.run_id
        for step in range(5):   # restart 1 ends lower than restart 0: the best restart
            c.log_metric(kid, "train/loss/restart0", scale * 2.0 ** -step, step=step)
            c.log_metric(kid, "train/loss/restart1", scale * 3.0 ** -step, step=step)
        c.log_metric(kid, "evaluate/v/mae", scale)
        c.set_terminated(kid)
    curves = tracking.best_loss_curves(tracking.children(parent))
    assert curves["n08·L2 | s0"] == pytest.approx([10 * 3.0 ** -k for k in range(5)])
    assert curves["n16·L2 | s0"][-1] == pytest.approx(3.0 ** -4)
    tracking.log_comparison(parent, ["evaluate/*/mae"], "sweep")
    arts = {a.path for a in c.list_artifacts(parent, "compare")}
    assert "compare/loss_overlay.png" in arts
    png = c.download_artifacts(parent, "compare/loss_overlay.png", str(tmp_path))
    assert matplotlib.image.imread(png).shape[1] > 400
