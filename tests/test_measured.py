"""Measured systems (SPEC §2.5, issue 9): the EMPS recording, its loop, its checks.

The real files are read from ``../shared/data/emps`` (skipped with the reason when absent).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline import data, runner
from pipeline.identify.measured_loop import (LoopModel, LoopSignals, benchmark_rmse_mm, identify_loop_sim_error,
                                            loop_errors, simulate_loop, simulate_open_loop)
from pipeline.systems.controller import LTIController
from pipeline.systems.measured import Recording, RigidBodyPhysics

EMPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"
needs_emps = pytest.mark.skipif(not (EMPS / "DATA_EMPS.mat").exists(),
                                reason="../shared/data/emps (the EMPS benchmark files) is not beside the repo")
CTRL = dict(kp=160.18, kv=243.45, gtau=35.150652)
PUBLISHED = dict(M=95.1089, F_v=203.5034, F_c=20.3935, OF=-3.1648)


def _emps_system(physics_input="averaged"):
    return Recording("emps", 1e-3, CTRL, physics_input=physics_input, published=PUBLISHED,
                     idim=dict(cutoff_hz=50.0, order=4, decimation=10, trim=50))


def _signals(ds):
    d = ds["d"] if "d" in ds.frame else np.zeros(len(ds))
    return LoopSignals(ds["r"], d, float(ds["y"][0]), ds["t"])


# ------------------------------------------------------------------------------ real data
@needs_emps
def test_physics_baseline_within_2_percent_of_published():
    ds = data.load_emps(EMPS, "DATA_EMPS")
    s = _emps_system()
    phys = s.physics.physical(s.fit_physics(ds["y"], ds["u"]))
    for k, v in PUBLISHED.items():       # issue 9 acceptance: within 2 % (measured: 0.03-0.2 %)
        assert abs(phys[k] - v) <= 0.02 * abs(v), (k, phys[k], v)


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
@needs_emps
def test_published_model_reproduces_published_figures_in_their_convention():
    """EMPS README: 8.94 % test force error, 0.0138 % / 0.0080 % position errors in the authors'
    convention (issue 9 tolerances 0.5 / 0.001 points); in the data's own timing the force error is lower."""
    s = _emps_system()
    model = LoopModel.physics_only(RigidBodyPhysics(1e-3, averaged_input=False), s.published_theta())
    got = {}
    for f in ("DATA_EMPS", "DATA_EMPS_PULSES"):
        ds = data.load_emps(EMPS, f)
        for conv in ("published", "data"):
            y, tau, _ = simulate_loop(model, s.ctrl, _signals(ds), conv)
            got[f, conv] = loop_errors(ds["y"], ds["u"], y, tau)
    assert abs(got["DATA_EMPS_PULSES", "published"]["force_rel_error"] - 8.94) <= 0.5
    assert abs(got["DATA_EMPS", "published"]["position_rel_error"] - 0.0138) <= 0.001
    assert abs(got["DATA_EMPS_PULSES", "published"]["position_rel_error"] - 0.0080) <= 0.001
    test = {c: got["DATA_EMPS_PULSES", c]["force_rel_error"] for c in ("data", "published")}
    assert test["data"] < test["published"] - 1


@needs_emps
def test_controller_law_is_the_recording_and_a_sign_error_is_caught():
    from stages.generate.measured import check_record
    ds = data.load_emps(EMPS, "DATA_EMPS")
    s = _emps_system()
    # the recorded vir is the law on qm of the same sample (no delay): 0.2 % rms residual
    assert s.ctrl.check(ds["r"], ds["y"], ds["u"], ds["d"]) < 0.005
    check_record(ds, s, "DATA_EMPS")
    flipped = data.Dataset(ds.frame.assign(u=-ds.frame["u"]), ds.meta)
    with pytest.raises(ValueError, match="DATA_EMPS.*not the output of the configured controller, the position/"
                                         "velocity cascade.*gain ×-(0.99|1.00).*sign error"):
        check_record(flipped, s, "DATA_EMPS")
    with pytest.raises(ValueError, match="kp = 160.18 differs from system.controller.kp"):
        check_record(ds, Recording("emps", 1e-3, dict(CTRL, kp=100.0)), "DATA_EMPS")


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
@needs_emps
def test_emps_pipeline_job_scores_on_the_test_file(store, cfg_of):
    """The physics experiment end to end: re-identified parameters, the replay on the test file
    in both conventions, and the model-based feedforward (no plant is ever simulated)."""
    from pipeline import tracking
    runner.run_job(cfg_of("experiment=emps_physics"))
    run = tracking.search_runs("emps").iloc[0]
    assert abs(run["metrics.baseline/rel_error_published/M"]) < 0.02
    assert abs(run["metrics.evaluate/test/published_model/published/force_rel_error"] - 8.94) < 0.5
    assert run["metrics.evaluate/test/data/force_rel_error"] < run["metrics.evaluate/test/published/force_rel_error"]
    # the model's own feedforward (with the cascade's velocity feedback cancelled) tracks its own
    # loop on the disturbance-free training reference far below the recorded error
    assert run["metrics.evaluate/train/model_based/mae"] < 1e-2 * run["metrics.evaluate/train/recorded/mae"]
    assert run["tags.feedforward_scoring"].startswith("model-based")


# ------------------------------------------------------------------------------ the loop kernel
def _toy_loop(n=1500, seed=0):
    """A reference like EMPS (smooth moves) and the physics loop model of the published values."""
    t = np.arange(n) * 1e-3
    r = 0.02 * (1 - np.cos(2 * np.pi * t / 1.5)) + 0.002 * (1 - np.cos(2 * np.pi * 3 * t))  # from rest, inside ±10 V
    s = _emps_system()
    return s, LoopSignals(r, np.zeros(n), 0.0, t)


def test_loop_sensitivities_match_finite_differences():
    s, sig = _toy_loop()
    th = s.published_theta().copy()
    th[2] = 0.0                                  # no Coulomb term: the loop is smooth in θ
    rng = np.random.default_rng(0)
    m = LoopModel(1e-3, 2, 2, True, th, W1=rng.normal(size=(3, 4)), b1=rng.normal(size=3),
                  W2=rng.normal(size=3), b2=0.1, nn_P=np.diag([10.0, 1e4, 0.02, 0.02]), out_scale=1e-7)
    theta = m.theta()
    _, tau, _, _, St = simulate_loop(m, s.ctrl, sig, sens=True)
    for p in range(theta.size):
        h = 1e-4 * max(abs(theta[p]), 1e-3)
        tp, tm = theta.copy(), theta.copy()
        tp[p] += h
        tm[p] -= h
        fd = (simulate_loop(m.with_theta(tp), s.ctrl, sig)[1]
              - simulate_loop(m.with_theta(tm), s.ctrl, sig)[1]) / (2 * h)
        # central differences: O(h²) truncation (1e-4 relative) plus rounding of τ (~1e-13 |τ| per
        # sample, divided by h); a wrong chain term errs by O(1)
        assert np.linalg.norm(fd - St[:, p]) <= 1e-4 * np.linalg.norm(fd) + 1e-12 * np.linalg.norm(tau) / h, p


def test_sim_error_fit_recovers_the_loop_it_recorded():
    """Record τ from the physics loop with known θ, start from a 10 %-off θ*, no regulariser:
    the closed-loop simulation-error LM returns θ to 1e-6 relative."""
    import torch
    from pipeline.models.pgnn import PGNN
    from pipeline.models.physics_maps import physics_features_for
    s, sig = _toy_loop(3000)
    true = s.published_theta()
    _, tau, _ = simulate_loop(LoopModel.physics_only(s.physics, true), s.ctrl, sig)
    model = PGNN(2, 1, 0, structure="invertible", physics=physics_features_for(s.physics, "forward", 2, 1, 0, True),
                 hidden=(), use_nn=False)
    with torch.no_grad():
        model.theta_phy.copy_(torch.as_tensor(true * np.array([1.1, 0.9, 1.1, 0.9])))
    fit = identify_loop_sim_error(model, True, s.ctrl, sig, tau, lam=0.0, max_iter=100, ftol=1e-14, gtol=1e-14)
    assert fit.restarts[fit.best].message in ("ftol", "gtol", "zero_cost", "mu_max")   # converged stops (lm.py)
    np.testing.assert_allclose(fit.loop.theta_phy, true, rtol=1e-6)


@pytest.mark.parametrize("physics_input, bound", [("direct", 1e-9), ("averaged", 1e-2)])
def test_feedforward_cancels_the_cascade_and_tracks_the_models_loop(physics_input, bound):
    """u_ff = model inverse - the controller's force on q = r: the model in its loop then tracks r.
    Exactly (to rounding) with the direct input; with the averaged (ZOH) input the inverse
    u_ff(t) = (w(t) + w(t+1))/2 is the bounded one-sample-preview approximation of SPEC §2.2."""
    s, sig = _toy_loop()
    s = _emps_system(physics_input)
    th = s.published_theta()
    model = LoopModel.physics_only(s.physics, th)
    uff = s.physics.feedforward(th, sig.r) - s.ctrl.reference_force(sig.r)
    y, _, _ = simulate_loop(model, s.ctrl, LoopSignals(sig.r, sig.d, 0.0, sig.t, uff))
    y0, _, _ = simulate_loop(model, s.ctrl, sig)
    e, e0 = np.abs(sig.r - y)[:-2], np.abs(sig.r - y0)[:-2]   # the last samples lack r(N+1)
    assert e.max() < bound * e0.max()


def test_published_convention_delays_the_controller_by_one_sample():
    """Data timing applies the controller's force in the same sample; the published convention
    one sample later (the disturbance is not delayed)."""
    s, sig = _toy_loop(400)
    sig.d = np.where(np.arange(400) % 100 < 50, 0.0, 5.0)
    m = LoopModel.physics_only(s.physics, s.published_theta())
    _, tau_d, u_d = simulate_loop(m, s.ctrl, sig, "data")
    _, tau_p, u_p = simulate_loop(m, s.ctrl, sig, "published")
    np.testing.assert_array_equal(u_d, tau_d)
    g = s.ctrl.gtau
    np.testing.assert_allclose(u_p[1:] - g * sig.d[1:], tau_p[:-1] - g * sig.d[:-1], rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------ bad input
def _csv(tmp_path, name="rec", n=2000, dt=1e-3, **change):
    """A CSV record of the toy loop (the physics model in the EMPS cascade): t, r, u, y."""
    s, sig = _toy_loop(n)
    y, tau, _ = simulate_loop(LoopModel.physics_only(s.physics, s.published_theta()), s.ctrl, sig)
    df = pd.DataFrame({"t": np.arange(n) * dt, "r": sig.r, "u": tau, "y": y})
    for k, v in change.items():
        df[k] = v
    path = tmp_path / f"{name}.csv"
    df.to_csv(path, index=False)
    return path


def _measured_overrides(path):
    return ["system=measured", "system.controller.kind=cascade", "system.controller.num=null",
            "system.controller.kp=160.18", "system.controller.kv=243.45",
            "system.controller.gtau=35.150652", "data=measured", f"data.path={path.parent}", f"data.file={path.name}",
            "evaluate=emps", f"evaluate.references=[{{name:test,kind:measured,file:{path.name}}}]",
            "model=physics", "identify=none", "invert=physics", "experiment_name=user"]


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_user_csv_round_trips_load_identify_evaluate(store, cfg_of, tmp_path):
    """A user's CSV (recorded by the physics model in the cascade, force in N so gtau = 1)
    through load -> identify -> evaluate: the replay of the identified model matches the record."""
    from pipeline import tracking
    path = _csv(tmp_path)
    cfg = cfg_of(*_measured_overrides(path))
    runner.run_job(cfg)
    run = tracking.search_runs("user").iloc[0]
    assert run["metrics.evaluate/test/data/force_rel_error"] < 1.0   # the model class holds the record


def test_a_recording_replaced_under_its_name_is_reread_not_served_from_the_cache(store, cfg_of, tmp_path):
    """Issue 24 item 6: the measured data's cache key holds the files' SHA-256, so another valid
    recording written under the same name changes the key of generate and of every stage after it
    (the job reruns them; before, every stage was served from the old file's cache)."""
    path = _csv(tmp_path, n=2000)
    cfg = cfg_of(*_measured_overrides(path))

    def keys():
        names, _, modules = runner.validate(cfg)
        return runner.plan(cfg, names, modules)
    first = keys()
    assert keys() == first                                    # same bytes, same keys
    _csv(tmp_path, n=2500)                                    # another valid record, same file name
    again = keys()
    assert set(first) == set(again) and all(first[k] != again[k] for k in first)


@pytest.mark.parametrize("case, match", [
    ("dt10ms", r"rec\.csv: the data are sampled at Ts = 0\.01 s but system 'measured' has Ts = 0\.001 s; "
               r"set system\.Ts"),
    ("decreasing", r"rec\.csv: column 't' is not increasing.*sort the samples"),
    ("nonuniform", r"rec\.csv: column 't' is not uniformly sampled.*resample"),
    ("sidecar0", r"rec\.csv: sidecar 'Ts' = 0\.0 is not a positive sample time"),
    ("string", r"rec\.csv: column 'y' is not numeric.*SI units"),
    ("nan", r"rec\.csv: column 'u' has 1 NaN/inf"),
    ("huge", r"rec\.csv: column 'y' has \|value\| = 1e\+300.*units and scaling"),
    ("sign", r"rec\.csv: the recorded force u is not the output of the configured controller.*sign error"),
])
def test_bad_measured_input_fails_before_work(store, cfg_of, tmp_path, case, match):
    n = 2000
    kw = {}
    if case == "dt10ms":
        path = _csv(tmp_path, dt=1e-2)
    else:
        path = _csv(tmp_path)
        df = pd.read_csv(path)
        if case == "decreasing":
            df.loc[10, "t"] = df.loc[5, "t"]
        elif case == "nonuniform":
            df["t"] = df["t"] * (1 + 0.01 * (np.arange(n) > n // 2))
        elif case == "sidecar0":
            (tmp_path / "rec.json").write_text(json.dumps({"Ts": 0.0}))
        elif case == "string":
            df["y"] = df["y"].astype(object)
            df.loc[3, "y"] = "12 mm"
        elif case == "nan":
            df.loc[7, "u"] = np.nan
        elif case == "huge":
            df.loc[7, "y"] = 1e300
        elif case == "sign":
            df["u"] = -df["u"]
        df.to_csv(path, index=False, **kw)
    with pytest.raises(runner.ConfigError, match=match):
        runner.run_job(cfg_of(*_measured_overrides(path)))
    assert not (store / "cache").exists() or not any((store / "cache").glob("*/*"))


def test_empty_and_missing_files_are_named(store, cfg_of, tmp_path):
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(runner.ConfigError, match=r"empty\.csv: the file is empty"):
        runner.run_job(cfg_of(*_measured_overrides(tmp_path / "empty.csv")))
    with pytest.raises(runner.ConfigError, match=r"none\.csv does not exist"):
        runner.run_job(cfg_of(*_measured_overrides(tmp_path / "none.csv")))


@needs_emps
def test_measured_model_on_a_simulator_is_refused_or_tagged(store, cfg_of):
    ov = ["data=measured", "data.format=emps", f"data.path={EMPS}", "data.file=DATA_EMPS", "evaluate=b1_vmax",
          "experiment_name=misuse"]
    with pytest.raises(runner.ConfigError, match="identified on measured data.*simulator.*allow_simulator=true"):
        runner.run_job(cfg_of(*ov))
    # the EMPS record is not the simulated linear motor's loop: its sample time agrees, so only the
    # explicit choice lets it through, and the run says so
    from pipeline import tracking
    runner.run_job(cfg_of(*ov, "evaluate.allow_simulator=true"))
    run = tracking.search_runs("misuse").iloc[0]
    assert "not the plant the data came from" in run["tags.evaluated_on"]


@needs_emps
def test_physics_that_cannot_fit_the_data_is_flagged(store, cfg_of):
    """The two-mass physics on the EMPS record: non-physical parameters become a warning tag."""
    from pipeline import tracking
    ov = ["system=two_mass_stribeck", "data=measured", "data.format=emps", f"data.path={EMPS}", "data.file=DATA_EMPS",
          "stages=[generate,baseline]", "experiment_name=wrongphys"]
    with pytest.warns(UserWarning, match="does not fit these data"):
        runner.run_job(cfg_of(*ov))
    run = tracking.search_runs("wrongphys").iloc[0]
    assert "must be positive" in run["tags.physics_warning"]


def test_recording_has_no_plant():
    s = _emps_system()
    with pytest.raises(RuntimeError, match="recording of a real machine: it has no true plant"):
        s.simulate(np.zeros(10))
    with pytest.raises(ValueError, match="controller.kp"):
        LTIController.cascade(kp=-1.0, kv=1.0, gtau=1.0)


def test_unknown_convention_is_named(store, cfg_of, tmp_path):
    path = _csv(tmp_path)
    with pytest.raises(runner.ConfigError,
                       match=r"evaluate.convention='matlab'; choose one of \('data', 'published'\)"):
        runner.run_job(cfg_of(*_measured_overrides(path), "evaluate.convention=matlab"))


def test_open_loop_benchmark_simulation_is_the_rigid_body_recursion():
    """simulate_open_loop (the loop kernel with zero gains) = the one-step rigid body driven by u,
    written out here: y(k) = 2y(k-1) - y(k-2) + Ts² (ū(k-1) - F_v δy - F_c sign δy - OF)/M."""
    s = _emps_system()
    th = s.published_theta()
    M, Fv, Fc, OF = 95.1089, 203.5034, 20.3935, -3.1648
    rng = np.random.default_rng(1)
    u = 50.0 * np.sin(np.arange(300) * 0.05) + rng.normal(0, 5, 300)
    y = simulate_open_loop(LoopModel.physics_only(s.physics, th), u, 0.01)
    ref = np.full(300, 0.01)
    for k in range(1, 300):
        y1, y2 = ref[k - 1], ref[k - 2] if k >= 2 else 0.01
        w = 0.5 * (u[k - 1] + (u[k - 2] if k >= 2 else 0.0))
        v = (y1 - y2) / 1e-3
        ref[k] = 2 * y1 - y2 + 1e-6 * (w - Fv * v - Fc * np.sign(v) - OF) / M
    # θ = [1/M, F_v/M, …] rounds differently from dividing by M, and the double integrator sums that
    # rounding over 300 steps (~1e-14 m); a wrong term (delay, averaging, sign) errs by > 1e-6 m
    np.testing.assert_allclose(y, ref, rtol=0, atol=1e-12)
    assert benchmark_rmse_mm(ref, y) < 1e-9


def test_measured_reference_needs_its_file_and_a_useful_length(store, cfg_of, tmp_path):
    path = _csv(tmp_path)
    ov = _measured_overrides(path)
    with pytest.raises(runner.ConfigError, match="reference 'test' of kind 'measured' names no file"):
        runner.run_job(cfg_of(*ov[:-5], "evaluate=emps", "evaluate.references=[{name:test,kind:measured}]",
                              *ov[-4:]))
    pd.read_csv(path).iloc[:8].to_csv(tmp_path / "short.csv", index=False)
    with pytest.raises(runner.ConfigError, match=r"short\.csv: 8 samples; at least 20"):
        runner.run_job(cfg_of(*ov[:-5], "evaluate=emps",
                              "evaluate.references=[{name:test,kind:measured,file:short.csv}]", *ov[-4:]))
    with pytest.raises(runner.ConfigError,
                       match=r"reference 'test': .*gone\.csv does not exist \(files there: .*rec\.csv.*\); "
                             r"check data\.path"):
        runner.run_job(cfg_of(*ov[:-5], "evaluate=emps",
                              "evaluate.references=[{name:test,kind:measured,file:gone.csv}]", *ov[-4:]))


def test_emps_file_with_signals_of_different_lengths_is_named(tmp_path):
    from scipy.io import loadmat, savemat
    if not (EMPS / "DATA_EMPS.mat").exists():
        pytest.skip("../shared/data/emps (the EMPS benchmark files) is not beside the repo")
    m = {k: v for k, v in loadmat(EMPS / "DATA_EMPS.mat").items() if not k.startswith("__")}
    m["vir"] = m["vir"][:-100]
    savemat(tmp_path / "DATA_EMPS.mat", m)
    with pytest.raises(ValueError, match=r"DATA_EMPS\.mat: variables of different lengths.*'vir': 24741"):
        data.load_emps(tmp_path, "DATA_EMPS")


def test_negative_mass_is_returned_for_the_warning_not_hidden():
    """A sign error the controller check cannot see (e.g. a user's own loop) gives M < 0 from the
    filtered least squares; the baseline turns it into the physics_warning tag."""
    from stages.baseline import nonphysical
    s, sig = _toy_loop(3000)
    y, tau, _ = simulate_loop(LoopModel.physics_only(s.physics, s.published_theta()), s.ctrl, sig)
    th = s.physics.fit_filtered(y, -tau, decimation=1, trim=50)
    phys = s.physics.physical(th)
    assert phys["M"] < 0 and nonphysical(phys)[0].startswith("M=-")


def test_system_config_name_is_the_recordings_name(cfg_of):
    assert runner.make_system(cfg_of("system=emps")).name == "emps"


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_measured_pgnn_trainings_and_the_emps_report_section(store, cfg_of, tmp_path):
    """Both PGNN criteria on a user record through train -> analytic inversion -> replay, and the
    report section that chooses on the validation tail: smoke budgets, real code paths."""
    import pandas as pd
    from pipeline import tracking
    _csv(tmp_path, n=3000)                 # rec.csv: the physics model in the EMPS cascade
    user = ["system=measured", "system.controller.kind=cascade", "system.controller.num=null",
            "system.controller.kp=160.18", "system.controller.kv=243.45",
            "system.controller.gtau=35.150652", "data.format=table", f"data.path={tmp_path}", "data.file=rec.csv",
            "evaluate.references=[{name:train,kind:measured,file:rec.csv},{name:test,kind:measured,file:rec.csv}]"]
    # experiment and run names come from the system (a user's machine is not 'emps')
    runner.run_job(cfg_of("experiment=emps_physics", *user, "system.name=my_axis", "stages=[generate,baseline]"))
    assert list(tracking.search_runs("my_axis")["tags.mlflow.runName"]) == ["my_axis-physics-s0"]
    user.append("system.name=emps")        # named emps below, so the EMPS report section reads the runs
    runner.run_job(cfg_of("experiment=emps_physics", *user))
    for e in ("emps", "emps_narx"):
        runner.run_job(cfg_of(f"experiment={e}", *user, "model.hidden=[2]", "identify.n_restarts=1",
                              "identify.max_iter=3"))
    runs = tracking.search_runs("emps")
    assert len(runs) == 3
    pgnn = runs[runs["tags.identify"] != "none"]
    assert set(pgnn["tags.lm_stop"]) <= {"max_iter", "ftol", "gtol", "mu_max"}
    # the record is the physics model's own loop: every model replays it to well below 1 %
    assert (runs["metrics.evaluate/test/data/force_rel_error"] < 1.0).all()
    results = store / "results"
    runner.run_job(cfg_of("stages=[report]", "experiment_name=report", f"paths.results={results}",
                          "report.experiments=[emps]"))
    table = pd.read_csv(results / "summary.csv")
    x1 = table[table["claim"] == "X1"]
    assert {"force_rel_error<4.5", "force_rel_error<physics", "benchmark_r2>=0.99"} <= set(x1["metric"])
    md = (results / "REPORT.md").read_text()
    assert "Stopped on the iteration cap (not converged)" in md     # max_iter=3 is flagged
    assert "model-based" in md


def test_a_reference_file_is_read_beside_a_data_path_that_is_a_file(tmp_path):
    """Issue 24 item 7: with the training file itself as data.path, a reference's own file is read
    from the same folder, not replaced by the training file."""
    from omegaconf import OmegaConf
    from stages.generate import measured
    train, test = _csv(tmp_path, "train", n=2000), _csv(tmp_path, "test", n=1500)
    cfg = OmegaConf.create({"data": {"path": str(train), "format": "table", "file": None}})
    assert len(measured.load_file(cfg).frame) == 2000                     # data.path: the training file
    assert len(measured.load_file(cfg, test.name).frame) == 1500          # the reference's own file
    assert len(measured.load_file(cfg, train.name).frame) == 2000
    if (EMPS / "DATA_EMPS.mat").exists():                                 # EMPS: a .mat file as data.path
        emps = OmegaConf.create({"data": {"path": str(EMPS / "DATA_EMPS.mat"), "format": "emps", "file": None}})
        trained_on = measured.load_file(emps).frame
        assert not measured.load_file(emps, "DATA_EMPS_PULSES").frame.equals(trained_on)


def test_the_cache_key_hashes_every_file_read_wherever_it_is(store, cfg_of, tmp_path):
    """Probe re-run of issue 24 item 6: with the training file as data.path, a reference read beside
    it, in a sub-folder or by an absolute path is in the key too (before, only data.path's file was
    hashed: a replaced test file was served from the cache). A data.file naming another file than
    a data.path that is a file is refused (before, the file named in data.path was ignored)."""
    train = _csv(tmp_path, "train", n=2000)
    (tmp_path / "sub").mkdir()
    beside, below = _csv(tmp_path, "test", n=1500), _csv(tmp_path / "sub", "deep", n=1500)
    elsewhere = _csv(tmp_path / "sub", "abs", n=1500)
    refs = (f"evaluate.references=[{{name:a,kind:measured,file:{beside.name}}},{{name:b,kind:measured,file:sub/"
            f"{below.name}}},{{name:c,kind:measured,file:{elsewhere}}}]")
    cfg = cfg_of(*_measured_overrides(train), f"data.path={train}", "data.file=null", refs)

    def generate_key():
        names, _, modules = runner.validate(cfg)
        return runner.plan(cfg, names, modules)["generate"]
    first = generate_key()
    for f in (beside, below, elsewhere):
        _csv(f.parent, f.stem, n=1600)                        # another valid record under the same name
        again = generate_key()
        assert again != first, f
        first = again
    with pytest.raises(runner.ConfigError, match=r"data.path=.*train.csv is a file and data.file\(s\)=\['other'\]"):
        runner.validate(cfg_of(*_measured_overrides(train), f"data.path={train}", "data.file=other"))


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
@pytest.mark.skipif(not (EMPS / "DATA_EMPS.mat").exists(), reason="EMPS data not found beside the repo")
def test_a_physics_fit_that_explains_almost_nothing_is_flagged(store, cfg_of):
    """Probe re-run of issue 24 item 9: an IDIM prefilter cutoff far below the motion's bandwidth
    (0.001 Hz) filtered the motion away and finished with M = 3e6 kg, unflagged; a physics fit that
    leaves over half of the recorded force unexplained is now flagged (warning and run tag). The
    EMPS benchmark's own settings leave 4 % and are not."""
    import warnings as w
    with pytest.warns(UserWarning, match=r"leaves 9\d % of the force unexplained .*cutoff_hz=0.001 Hz"):
        runner.run_job(cfg_of("experiment=emps_physics", "system.idim.order=1", "system.idim.cutoff_hz=0.001",
                              "stages=[generate,baseline]"))
    with w.catch_warnings(record=True) as caught:
        w.simplefilter("always")
        runner.run_job(cfg_of("experiment=emps_physics", "stages=[generate,baseline]"))
    assert not [c for c in caught if "unexplained" in str(c.message)]


def test_a_pgnn_regressor_other_than_the_plant_models_layout_is_refused():
    """The measured rigid body reads φ as [y(t-1), y(t-2), w(t-1)] ([B1] (32)): a PGNN with n_a = 3
    would feed it y(t-3) as the force (a wrong model, silently). physics_features_for refuses it with
    the fix; n_a = 2 with extra input lags (seen by the NN only) is fine."""
    from pipeline.models.physics_maps import physics_features_for
    from pipeline.systems.measured import RigidBodyPhysics
    pm = RigidBodyPhysics(1e-3, averaged_input=True)
    with pytest.raises(ValueError, match="set model.n_a=2"):
        physics_features_for(pm, "forward", 3, 1, 0, True)
    with pytest.raises(ValueError, match="model.n_b>=2"):
        physics_features_for(pm, "forward", 2, 1, 0, False)      # raw u: the physics averages two lags
    assert physics_features_for(pm, "forward", 2, 3, 0, True).fast_kind == 3


def test_a_pgnn_whose_regressor_misreads_the_rigid_body_is_refused_before_any_work(tmp_path, store, cfg_of):
    """model.n_a=3 on a measured axis: the closed-loop fit's config is refused in one line naming the
    fix, before any stage runs (nothing cached); the one-step fit's check builds the same model."""
    identify = "sim_error"
    path = _csv(tmp_path)
    over = [o for o in _measured_overrides(path) if not o.startswith(("model=", "identify=", "invert="))]
    cfg = cfg_of(*over, "model=pgnn", f"identify={identify}", "invert=analytic", "model.structure=invertible",
                 "model.n_a=3", "model.n_b=1", "model.hidden=[4]")
    with pytest.raises(runner.ConfigError, match=r"model: RigidBodyPhysics .*set model.n_a=2"):
        runner.run_job(cfg)
    assert not (store / "cache").exists() or not any((store / "cache").glob("*/*"))


def test_measured_sim_error_stage_passes_every_restart_option(store, cfg_of, tmp_path, monkeypatch):
    """The measured loop's fit gets the restart options of the config, screen_iter included (it was
    once dropped on this path: every EMPS restart ran to its stop, 2.6x the training time), read in
    one place (stages.train.restart_options) for narx and both sim_error paths."""
    import pipeline.identify.measured_loop as measured_loop
    from stages.train import restart_options
    _csv(tmp_path, n=3000)
    user = ["system=measured", "system.controller.kind=cascade", "system.controller.num=null",
            "system.controller.kp=160.18", "system.controller.kv=243.45",
            "system.controller.gtau=35.150652", "data.format=table", f"data.path={tmp_path}", "data.file=rec.csv",
            "evaluate.references=[{name:train,kind:measured,file:rec.csv}]"]
    seen = {}

    class Stop(Exception):
        pass

    def spy(*args, **kw):
        seen.update(kw)
        raise Stop
    monkeypatch.setattr(measured_loop, "identify_loop_sim_error", spy)   # the stage imports it when it runs
    cfg = cfg_of("experiment=emps", *user, "model.hidden=[2]", "identify.n_restarts=3", "identify.screen_iter=7",
                 "identify.max_iter=11", "identify.stat_frac=0.25")
    with pytest.raises(Stop):
        runner.run_job(cfg)
    want = restart_options(cfg.identify, measured=True)
    assert {k: seen[k] for k in want} == want
    assert (want["screen_iter"], want["n_restarts"], want["max_iter"], want["stat_frac"]) == (7, 3, 11, 0.25)
    # identify.stat_promise=auto: the damped promise on a recording, the full one on a simulated plant
    assert want["stat_promise"] == "damped" and restart_options(cfg.identify)["stat_promise"] == "gauss_newton"


def test_bad_recordings_are_named_with_what_was_found_and_the_fix(tmp_path):
    """Found by a user trying their own recording: each message names the file, what is there and the fix."""
    import pandas as pd

    from pipeline import data
    from pipeline.references import from_spec
    from pipeline.runner import ConfigError
    from stages.generate.measured import reference
    t = np.arange(50) * 1e-3
    pd.DataFrame({"t": t, "r": t, "u": t, "y": t}).to_csv(tmp_path / "own.csv", sep=";", index=False)
    with pytest.raises(ValueError, match=r"found \['t;r;u;y'\].*separated by ';'"):
        data.load(tmp_path / "own.csv")
    pd.DataFrame({"T": t, "R": t, "U": t, "Y": t}).to_csv(tmp_path / "caps.csv", index=False)
    with pytest.raises(ValueError, match=r"found \['T', 'R', 'U', 'Y'\].*lower case"):
        data.load(tmp_path / "caps.csv")
    with pytest.raises(FileNotFoundError, match=r"folder .*nodir does not exist either.*data.file"):
        data.load(tmp_path / "nodir" / "train.csv")
    pd.DataFrame({"t": t, "r": t, "u": t, "y": t}).to_csv(tmp_path / "ok.csv", index=False)
    (tmp_path / "ok.json").write_text("{Ts: 0.001")
    with pytest.raises(ValueError, match=r"ok\.json: the sidecar is not valid JSON"):
        data.load(tmp_path / "ok.csv")
    with pytest.raises(FileNotFoundError, match=r"holds \[.*'ok.csv'.*data.format=table"):
        data.load_emps(tmp_path, "own")
    with pytest.raises(ValueError, match=r"'measured' \(a recorded file"):
        from_spec({"name": "test", "kind": "measure", "file": "x.csv"}, 1e-3)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['fle'\]"):
        reference(None, {"name": "test", "kind": "measured", "fle": "test.csv"}, None)


@needs_emps
def test_a_wrong_delay_under_the_tolerance_is_warned_about_and_the_right_one_is_not():
    """EMPS with delay 1: the equation error (3.5 %) stays under the 5 % check, but delay 0 fits ~20x better
    (0.2 %): a warning names the delay; the true delay 0 gets none."""
    import warnings as w

    from stages.generate.measured import check_record
    ds = data.load_emps(EMPS, "DATA_EMPS")
    with w.catch_warnings():
        w.simplefilter("error")
        check_record(ds, _emps_system(), "DATA_EMPS")
    s1 = Recording("emps", 1e-3, dict(CTRL, delay=1))
    rel = s1.ctrl.check(ds["r"], ds["y"], ds["u"], ds["d"])
    assert 0.01 < rel < 0.05
    with pytest.warns(UserWarning, match=r"delay of 0 samples instead of 1 it fits \d+x better"):
        check_record(ds, s1, "DATA_EMPS")


def test_a_recording_in_millimetres_is_warned_about(tmp_path):
    """r and y in mm with the gains scaled to match pass the controller check; the speed (1000x a metre
    recording's) says the units are wrong."""
    from stages.generate.measured import PLAUSIBLE_SPEED, units_warning
    Ts = 1e-3
    t = np.arange(2000) * Ts
    y = 0.2 * np.sin(2 * np.pi * t)                 # 0.2 m at 1 Hz: 1.26 m/s
    ds = data.Dataset(pd.DataFrame({"t": t, "r": y, "u": 0 * y, "y": y}), {"Ts": Ts})
    assert units_warning(ds, Ts) is None
    ds_mm = data.Dataset(pd.DataFrame({"t": t, "r": 1e3 * y, "u": 0 * y, "y": 1e3 * y}), {"Ts": Ts})
    msg = units_warning(ds_mm, Ts)
    assert msg and "1257 m/s" in msg and f"{PLAUSIBLE_SPEED:g} m/s" in msg and "metres" in msg


def test_an_evaluation_file_at_another_ts_is_told_to_match_the_training_data():
    """Setting system.Ts to the evaluation file's Ts (the advice for the training file) would break the training
    data: for an evaluation recording the fix is to record or resample it at the system's Ts."""
    from stages.generate.measured import check_record
    t = np.arange(200) * 5e-4
    ds = data.Dataset(pd.DataFrame({"t": t, "r": 0 * t, "u": 0 * t, "y": 0 * t}), {"Ts": 5e-4})
    s = _emps_system()
    with pytest.raises(ValueError, match=r"test\.csv: this evaluation recording is sampled at Ts = 0\.0005 s.*"
                                         r"resample the evaluation run at 0\.001 s"):
        check_record(ds, s, "test.csv", reference=True)
    with pytest.raises(ValueError, match=r"train\.csv: the data are sampled at Ts = 0\.0005 s.*set system\.Ts=0\.0005"):
        check_record(ds, s, "train.csv")
