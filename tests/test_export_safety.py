"""Issue 22: a feedforward you can put on a machine. The guard (limits, training envelope, flags,
fallback) in C and in Python flag for flag, the rate check and zero-order hold, the symbol prefix
(several laws in one program), the float variant, test vectors, sanitizers and cppcheck/MISRA.

Tolerances: the guard adds comparisons, one subtraction and one addition per limit, done in the same
order in C and in Python, so C and Python agree to the bit wherever the law itself does (1e-12
relative covers glibc's tanh against numba's, as in test_export.py); flags are compared exactly.
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.export.guard import FLAG
from pipeline.export.law import Law, feedforward, from_k_filter, from_linear_motor_physics, from_pgnn, from_table, \
    guarded
from pipeline.export.package import compile_harness, run_harness, write_package
from pipeline.models.physics_maps import RigidBodyForward, RigidBodyInverse
from pipeline.models.rational import RationalFeedforward
from tests.test_export import Ts, _pgnn, _reference

TOL = 1e-12
CC = shutil.which("cc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler on this machine")


def _with_guard(law: Law, **guard) -> Law:
    d = dict(law.__dict__)
    d["guard"] = {**law.guard, **guard}
    return Law(**d)


def _law(kind: str) -> Law:
    if kind == "physics":
        from pipeline.systems.linear_motor import LinearMotorPhysics
        return from_linear_motor_physics(LinearMotorPhysics(Ts, averaged_input=True), np.array([0.05, 2.0, 0.5]))
    if kind == "newton":
        return from_pgnn(_pgnn("forward", RigidBodyForward(Ts, 2)), "newton", Ts, k=5)
    if kind == "direct":
        return from_pgnn(_pgnn("inverse", RigidBodyInverse(Ts), theta=(5.0, 10.0, 2.0)), "direct", Ts)
    if kind == "analytic":
        return from_pgnn(_pgnn("invertible", RigidBodyForward(Ts, 2)), "analytic", Ts)
    if kind == "shared_ar":
        from pipeline.models.shared_ar import ReferenceWindow, SharedARPGNN, make_approximator
        g = make_approximator("mlp", 3, seed=0, hidden=(6,), activation="tanh")
        r = _reference(600)
        return from_k_filter(SharedARPGNN(4, 2, g, ReferenceWindow(2, "delta", Ts).fit(r), basis="delta", Ts=Ts,
                                          a=[0.0, 0.0, 20.0, 0.0], b=[2e-3, 1e-6]))
    if kind == "rational":
        return from_k_filter(RationalFeedforward(4, 2, basis="delta", Ts=Ts, a=[0.0, 0.0, 20.0, 0.0], b=[2e-3, 1e-6]))
    if kind == "table":
        r = _reference(600)
        return from_table("fhofc", Ts, r, feedforward(_law("physics"), r))
    from pipeline.systems.measured import Recording
    sys_ = Recording("axis", Ts, controller={"kind": "cascade", "kp": 160.18, "kv": 243.45, "gtau": 35.15},
                     force_terms={"terms": ["viscous", "coulomb", "offset"]}, physics_input="averaged")
    theta = sys_.physics.theta_from_physical({"M": 12.0, "F_v": 40.0, "F_c": 8.0, "OF": -1.5})
    from pipeline.export.law import from_measured_physics
    return from_measured_physics(sys_.physics, theta, sys_.ctrl)


FAST = ["physics", "newton", "rational", "table"]
SLOW = ["direct", "analytic", "shared_ar", "measured"]
LAWS = FAST + [pytest.param(k, marks=pytest.mark.slow) for k in SLOW]


def _envelope(law: Law, r: np.ndarray, margin: float = 0.1) -> dict:
    from pipeline.export.guard import envelope_of
    lo, hi = envelope_of([r], law.Ts, margin)
    return {"env_lo": lo, "env_hi": hi}


def _c_run(law: Law, name: str, folder: Path, r: np.ndarray):
    """(u, flags) of the compiled C harness on r (a test runs one package on several references: its harness is
    built once, tests/conftest.py ``_built_once``)."""
    exe = compile_harness(folder / name, name, CC)
    f = folder / f"in_{name}.csv"
    f.write_text("r\n" + "\n".join(repr(float(v)) for v in r) + "\n")
    return run_harness(exe, f, flags=True)


@needs_cc
@pytest.mark.parametrize("kind", LAWS)
@pytest.mark.parametrize("fallback", ["hold", "ramp"])
def test_every_flag_path_in_c_equals_python_and_never_steps_to_zero(kind, fallback, tmp_path):
    """A reference that leaves the training envelope, one with NaN/inf during motion and one that
    demands more than the force and slew limits: the documented flags and fallback, the same in C
    and Python; on clean input inside the limits the study's u_ff to the bit."""
    law0 = _law(kind)
    r = law0.arrays["r"] if kind == "table" else _reference(600)
    u_study = feedforward(law0, r)
    umax = float(np.max(np.abs(u_study)))
    du = float(np.max(np.abs(np.diff(u_study, prepend=0.0))))   # from u(-1) = 0, the actuator at rest
    # clean input with the envelope and no limits: untouched (only OUT_OF_RANGE or the law's own flags)
    u, f = guarded(_with_guard(law0, **_envelope(law0, r)), r)
    np.testing.assert_array_equal(u, u_study)
    assert not np.any(f & (FLAG["SATURATED"] | FLAG["RATE_LIMITED"] | FLAG["FALLBACK"] | FLAG["NONFINITE_INPUT"]))
    # limits below what the reference demands: 0.8 x its largest force and force step
    law = _with_guard(law0, **_envelope(law0, r), fallback=fallback, ramp_time=0.05,
                      u_min=-0.8 * umax, u_max=0.8 * umax, rate=0.8 * du / Ts)
    man = write_package(law, "ff_x", tmp_path, {"ref": (r, u_study)}, source={}, timing_repeats=0)
    assert man["compiled"] and man["references"]["ref"]["c_flags_agree"]
    assert all(v["c_check"] == "pass" for v in man["vectors"].values())
    if kind == "physics":                             # --check fails (exit 1) on a vector the C does not meet
        exe = compile_harness(tmp_path / "ff_x", "ff_x", CC)
        vec = (tmp_path / "ff_x" / "vectors_normal.csv").read_text().splitlines()
        r_, u_, f_ = vec[50].split(",")
        for bad_line in (f"{r_},{float(u_) * (1 + 1e-6)!r},{f_}", f"{r_},{u_},{int(f_) ^ FLAG['SATURATED']}"):
            (tmp_path / "bad.csv").write_text("\n".join(vec[:50] + [bad_line] + vec[51:]) + "\n")
            out = subprocess.run([str(exe), "--check", str(tmp_path / "bad.csv")], capture_output=True, text=True)
            assert out.returncode == 1 and "sample 49" in out.stderr, out.stderr
    k = int(np.argmax(np.abs(np.diff(r))))            # the fastest sample: in motion
    bad = r.copy()
    bad[k:k + 10] = np.nan
    bad[k + 30] = np.inf
    cases = {"envelope": r[0] + 3.0 * (r - r[0]), "nan": bad, "limit": r}
    for case, rc in cases.items():
        u_py, f_py = guarded(law, rc)
        u_c, f_c = _c_run(law, "ff_x", tmp_path, rc)
        np.testing.assert_array_equal(f_c, f_py, err_msg=case)
        np.testing.assert_allclose(u_c, u_py, rtol=0, atol=TOL * max(np.max(np.abs(u_py)), 1e-300), err_msg=case)
        assert np.all(np.isfinite(u_py)), case
        if case == "envelope":
            assert np.any(f_py & (FLAG["OUT_OF_RANGE"] if kind != "table" else FLAG["OTHER_REFERENCE"]))
        if case == "limit":               # max|u| > u_max: clipped, or kept below by the slew limit
            assert np.any(f_py & (FLAG["SATURATED"] | FLAG["RATE_LIMITED"]))
            assert np.max(np.abs(u_py)) <= 0.8 * umax
        if case == "nan":
            win = slice(k - law.preview, k + 10)      # every window holding a NaN sample
            assert np.all(f_py[win] & FLAG["NONFINITE_INPUT"]) and np.all(f_py[win] & FLAG["FALLBACK"])
            # no jump to 0 N: each step is within the slew limit; hold keeps the last valid output
            assert np.all(np.abs(np.diff(u_py)) <= law.g.du_max(Ts) * (1 + 1e-12))
            if fallback == "hold":
                hold = u_py[k - law.preview - 1]
                assert hold != 0.0 and np.all(u_py[win] == hold)
            else:
                assert np.all(np.abs(u_py[win]) <= abs(u_py[k - law.preview - 1]) + 1e-12)
        # the limits hold on every path
        assert np.all(u_py <= law.g.u_max) and np.all(u_py >= law.g.u_min)


def test_physics_fallback_and_out_of_range_fallback_in_python():
    """envelope_action=fallback with the physics fallback: out of the envelope the rigid-body law
    M d2r + F_v dr + F_c sign dr replaces the learned one (here equal to the physics law itself)."""
    law0 = _law("physics")
    r = _reference(600)
    M, Fv, Fc = 1 / 0.05, 2.0 / 0.05, 0.5 / 0.05
    law = _with_guard(law0, env_lo=[-1.0, -1.0, -1e9], env_hi=[1.0, 1.0, 1e9], envelope_action="fallback",
                      fallback="physics", physics=[M, Fv, Fc])
    rc = 30.0 * r                                      # leaves |r| <= 1 m
    u, f = guarded(law, rc)
    out = (f & FLAG["OUT_OF_RANGE"]) != 0
    assert out.any() and np.all(f[out] & FLAG["FALLBACK"])
    t = np.flatnonzero(out)[5]
    v = (rc[t + 2] - rc[t + 1]) / Ts
    a = (rc[t + 2] - 2.0 * rc[t + 1] + rc[t]) / (Ts * Ts)
    assert u[t] == M * a + Fv * v + Fc * np.sign(v)


@needs_cc
def test_two_laws_and_two_runs_of_one_law_link_into_one_program(tmp_path):
    """The symbol prefix (default <package>_<law hash>): a physics law, a Newton law and a second
    physics law (another run: other θ) compile and link into one program and give their own u_ff."""
    from pipeline.systems.linear_motor import LinearMotorPhysics
    pm = LinearMotorPhysics(Ts)
    laws = {"a": from_linear_motor_physics(pm, np.array([0.05, 2.0, 0.5])), "b": _law("newton"),
            "c": from_linear_motor_physics(pm, np.array([0.04, 1.0, 0.2]))}
    names = {"a": "ff_physics", "b": "ff_newton", "c": "ff_physics"}
    r = _reference(300)
    mans, srcs = {}, []
    for k, law in laws.items():
        mans[k] = write_package(law, names[k], tmp_path / k, {"ref": (r, feedforward(law, r))}, source={},
                                timing_repeats=0)
        srcs.append(str(tmp_path / k / names[k] / f"{names[k]}.c"))
    prefixes = [m["prefix"] for m in mans.values()]
    assert len(set(prefixes)) == 3 and prefixes[0].startswith("ff_physics_") and prefixes[2].startswith("ff_physics_")
    main = ["#include <stdio.h>"] + [f'#include "{k}/{names[k]}/{names[k]}.h"' for k in laws]
    main += ["int main(void) {", "    double rp[3] = {0.0, 1e-6, 3e-6};"]
    for k, p in zip(laws, prefixes):
        main += [f"    {{ {p}_state s; {p}_init(&s, 0.0); printf(\"%.17g\\n\", {p}_step(&s, rp)); }}"]
    main += ["    return 0;", "}"]
    (tmp_path / "main.c").write_text("\n".join(main) + "\n")
    exe = tmp_path / "all"
    out = subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", f"-I{tmp_path}", "-o", str(exe),
                          str(tmp_path / "main.c"), *srcs, "-lm"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    got = [float(v) for v in subprocess.run([str(exe)], capture_output=True, text=True).stdout.split()]
    rp = np.array([0.0, 1e-6, 3e-6])
    for k, v in zip(laws, got):                        # u(0) of each law on its own window r(0) .. r(P)
        want = guarded(laws[k], rp[:laws[k].preview + 1])[0][0]
        assert v == pytest.approx(want, rel=TOL, abs=0)
    assert got[0] != got[2]                            # two runs, two laws


@needs_cc
def test_rate_is_checked_at_build_and_the_zero_order_hold_holds_the_law(tmp_path):
    """export.target_rate = 4 x the law's rate: the ZOH wrapper's output at every 4th loop sample is
    the law's u_ff, held in between; its measured effect is in the manifest. A build for another
    loop period stops with #error."""
    law = _law("physics")
    r = _reference(400)
    man = write_package(law, "ff_physics", tmp_path, {"ref": (r, feedforward(law, r))}, source={},
                        timing_repeats=0, zoh_n=4, prefix="axis1")
    z = man["zoh"]
    assert z["factor"] == 4 and z["loop_Ts"] == Ts / 4 and 0 < z["max_rel_diff_vs_interpolated"] < 1
    pkg = tmp_path / "ff_physics"
    h = (pkg / "ff_physics.h").read_text()
    assert "#define AXIS1_TS_NS 1000000" in h and "axis1_zoh_step" in h
    n = 4
    rf = np.interp(np.arange((r.size - 1) * n + 1) / n, np.arange(r.size), r)     # the loop-rate reference
    main = ['#include <stdio.h>', '#include "ff_physics.h"', f"static const double R[{rf.size}] = {{"
            + ", ".join(repr(float(v)) for v in rf) + "};",
            "int main(void) {", "    axis1_zoh_state z; long t; int i;", "    double w[AXIS1_ZOH_PREVIEW + 1];",
            "    axis1_zoh_init(&z, 0.0);",
            f"    for (t = 0; t < {rf.size}; ++t) {{",
            f"        for (i = 0; i <= AXIS1_ZOH_PREVIEW; ++i) w[i] = R[t + i < {rf.size} ? t + i : {rf.size - 1}];",
            "        printf(\"%.17g\\n\", axis1_zoh_step(&z, w));", "    }", "    return 0;", "}"]
    (pkg / "zoh.c").write_text("\n".join(main) + "\n")
    out = subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-o", str(pkg / "zoh"), str(pkg / "zoh.c"),
                          str(pkg / "ff_physics.c"), "-lm"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    u = np.array(subprocess.run([str(pkg / "zoh")], capture_output=True, text=True).stdout.split(), dtype=float)
    u_law = guarded(law, rf[::n])[0]
    np.testing.assert_array_equal(u[::n], u_law)
    np.testing.assert_array_equal(u.reshape(-1)[1:4], np.full(3, u_law[0]))
    wrong = subprocess.run([CC, "-std=c99", "-DAXIS1_LOOP_TS_NS=500000", "-c", "-o", str(pkg / "x.o"),
                            str(pkg / "zoh.c")], capture_output=True, text=True)
    assert wrong.returncode != 0 and "for Ts = 0.001 s only" in wrong.stderr
    ok = subprocess.run([CC, "-std=c99", "-DAXIS1_LOOP_TS_NS=1000000", "-c", "-o", str(pkg / "x.o"),
                         str(pkg / "zoh.c")], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr


@needs_cc
@pytest.mark.parametrize("kind", ["physics", pytest.param("direct", marks=pytest.mark.slow),
                                  pytest.param("rational", marks=pytest.mark.slow)])
def test_single_precision_is_measured_against_the_double_study(kind, tmp_path):
    """export.precision=single: the C in float; its max|Δu|/max|u| against the double study is in the
    manifest (physics on this reference: ~5e-3, the second difference of a float position)."""
    law = _law(kind)
    r = _reference(600)
    man = write_package(law, "ff_s", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0,
                        precision="single", single_rtol=0.5)
    src = (tmp_path / "ff_s" / "ff_s.c").read_text()
    assert "double" not in src and "float" in src
    d = man["single_max_rel_diff"]
    assert 1e-9 < d < 0.5 and man["precision"] == "single", d


def _sanitize_ok() -> bool:
    if CC is None:
        return False
    probe = subprocess.run([CC, "-fsanitize=address,undefined", "-x", "c", "-o", "/dev/null", "-"],
                           input="int main(void){return 0;}", capture_output=True, text=True)
    return probe.returncode == 0


needs_san = pytest.mark.skipif(not _sanitize_ok(), reason="the C compiler has no ASan/UBSan runtime")
SAN = ["-std=c99", "-O1", "-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-Wall", "-Wextra",
       "-Werror"]


def _sanitized(pkg: Path, name: str) -> Path:
    exe = pkg / f"san_{name}"
    out = subprocess.run([CC, *SAN, "-o", str(exe), str(pkg / f"main_{name}.c"), str(pkg / f"{name}.c"), "-lm"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return exe


def _san_run(exe: Path, *args):
    return subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, timeout=600,
                          env={"ASAN_OPTIONS": "detect_leaks=1", "UBSAN_OPTIONS": "halt_on_error=1"})


@needs_san
@pytest.mark.parametrize("kind", ["physics", *[pytest.param(k, marks=pytest.mark.slow)
                                              for k in ("newton", "direct", "analytic", "rational", "shared_ar",
                                                        "table", "measured")]])
def test_packages_pass_asan_ubsan_on_vectors_nan_empty_and_a_million_rows(kind, tmp_path):
    law = _law(kind)
    r = law.arrays["r"] if kind == "table" else _reference(600)
    law = _with_guard(law, **_envelope(law, r), u_min=-1e4, u_max=1e4, rate=1e7)
    write_package(law, "ff_x", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0)
    pkg = tmp_path / "ff_x"
    exe = _sanitized(pkg, "ff_x")
    for v in sorted(pkg.glob("vectors_*.csv")):
        out = _san_run(exe, "--check", v)
        assert out.returncode == 0, out.stderr[-2000:]
    nan = pkg / "nan.csv"
    nan.write_text("r\nnan\nnan\ninf\n-inf\n0.001\nnan\n")
    out = _san_run(exe, nan, "--flags")
    assert out.returncode == 0 and "runtime error" not in out.stderr, out.stderr
    rows = [line.split(",") for line in out.stdout.split()[1:]]
    assert all(math.isfinite(float(u)) for u, _ in rows) and int(rows[0][1]) & FLAG["NONFINITE_INPUT"]
    empty = pkg / "empty.csv"
    empty.write_text("r\n")
    out = _san_run(exe, empty)
    assert out.returncode == 1 and "no samples" in out.stderr and "Sanitizer" not in out.stderr


@pytest.mark.slow   # 10^6 rows through a sanitized harness: ~10 s
@needs_san
def test_a_million_rows_under_asan_ubsan(tmp_path):
    law = _law("newton")
    r = _reference(600)
    write_package(law, "ff_x", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0)
    pkg = tmp_path / "ff_x"
    exe = _sanitized(pkg, "ff_x")
    big = pkg / "big.csv"
    rb = 0.05 * np.sin(np.arange(10**6) * Ts * 2.0)
    big.write_text("r\n" + "\n".join(f"{v:.17g}" for v in rb) + "\n")
    out = _san_run(exe, big)
    assert out.returncode == 0 and "runtime error" not in out.stderr, out.stderr[-2000:]
    assert len(out.stdout.split()) == 10**6 + 1


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("cppcheck") is None, reason="cppcheck is not installed (apt-get install cppcheck)")
@pytest.mark.parametrize("kind", ["physics", "newton", "direct", "analytic", "rational", "shared_ar", "table",
                                  "measured"])
def test_cppcheck_clean_and_every_misra_finding_has_a_reason(kind, tmp_path):
    law = _law(kind)
    r = law.arrays["r"] if kind == "table" else _reference(300)
    man = write_package(law, "ff_x", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0,
                        cppcheck=True, cc=None)
    c = man["cppcheck"]
    assert c["ran"] and c["n_warnings"] == 0, c["warnings"]
    assert c["unexplained"] == [], c
    readme = (tmp_path / "ff_x" / "README.md").read_text()
    for rule, n in c["misra"].items():
        assert f"| {rule} | {n} |" in readme
    print(kind, c["misra_total"], json.dumps(c["misra"]))


@pytest.mark.slow   # one short linear-motor job with the export stage: ~20 s
@needs_cc
@pytest.mark.filterwarnings("ignore:the physics model of 'linear_motor' does not fit")
def test_stage_builds_the_guard_from_config(store, cfg_of, tmp_path):
    """export.limits / target_rate / prefix / precision through the stage: the envelope from the
    identification data's y, the physics fallback's [m, f_v, f_c] from the baseline θ (8), the ZOH
    effect and the float law's deviation in the manifest; the MLflow model returns the flags."""
    import mlflow
    import pandas as pd

    from pipeline import runner, tracking
    from tests.test_export import SHORT_B1
    cfg = cfg_of(*SHORT_B1, "invert=physics", "stages=[generate,baseline,train,invert,export]",
                 "export.limits.u_min=-150", "export.limits.u_max=150", "export.limits.rate=1e5",
                 "export.limits.fallback=physics", "export.target_rate=4000", "export.prefix=axis1",
                 "export.precision=single", "export.single_rtol=1")
    res = runner.run_job(cfg)
    man = res["export"]["packages"]["ff_physics"]
    assert man["prefix"] == "axis1" and man["precision"] == "single" and man["zoh"]["factor"] == 4
    assert man["limits"] == {"u_min": -150.0, "u_max": 150.0, "rate": 1e5}
    ds = res["generate"]["dataset"]
    y = ds["y"]
    lo, hi = man["envelope"]["lo"], man["envelope"]["hi"]
    assert lo[0] < float(np.min(y)) and hi[0] > float(np.max(y)) and all(map(math.isfinite, lo + hi))
    theta = res["baseline"]["theta"]
    np.testing.assert_allclose(man["fallback"]["physics"], np.array([1.0, theta[1], theta[2]]) / theta[0], rtol=1e-12)
    # float positions in metres: δ²r loses ~3 digits and sign(δr) flips near rest (f_c / max|u| ~ 0.1)
    assert 1e-4 < man["single_max_rel_diff"] <= 1
    assert all(v["c_check"] == "pass" for v in man["vectors"].values())
    run = tracking.search_runs("b1_linear_motor").iloc[0]
    model = mlflow.pyfunc.load_model(f"runs:/{run['run_id']}/ff_physics-{run['tags.run_key']}")   # named after its run
    r = np.array(res["invert"]["r"]["v0.15"])
    r[100:110] = np.nan
    out = model.predict(pd.DataFrame({"r": r}))
    assert np.all(np.isfinite(out["u_ff"])) and np.all(out["flags"].to_numpy()[100:110] & FLAG["NONFINITE_INPUT"])


@needs_cc
def test_an_overflowing_reference_falls_back_in_c_and_python(tmp_path):
    """A finite but absurd reference (1e306 m) overflows the law's arithmetic: SINGULAR and the
    fallback (hold) in C and in Python, never a jump to 0 N."""
    law = _law("direct")
    r = _reference(300)
    write_package(law, "ff_x", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0)
    rc = r.copy()
    rc[150] = 1e306                                   # d2r = 1e312 m/s2: inf
    u_py, f_py = guarded(law, rc)
    u_c, f_c = _c_run(law, "ff_x", tmp_path, rc)
    np.testing.assert_array_equal(f_c, f_py)
    np.testing.assert_allclose(u_c, u_py, rtol=0, atol=TOL * np.max(np.abs(u_py)))
    bad = np.flatnonzero(f_py & FLAG["FALLBACK"])
    assert bad.size and np.all(f_py[bad] & FLAG["SINGULAR"])
    hold = u_py[bad[0] - 1]
    assert hold != 0.0 and np.all(u_py[bad] == hold) and np.all(np.isfinite(u_c))


def test_the_report_counts_misra_findings_per_package():
    """Issue 22 acceptance: the MISRA count is in the report (a column of the exported-feedforward table
    and a summary row), n/a for a package built where cppcheck is not installed."""
    import pandas as pd

    from stages.report import _exports
    runs = pd.DataFrame([
        {"tags.mlflow.runName": "a-run", "metrics.export/max_rel_diff": 0.0,
         "metrics.export/ff_newton/c_max_rel_diff": 0.0, "metrics.export/ff_newton/python_max_rel_diff": 0.0,
         "metrics.export/ff_newton/misra_findings": 75.0, "metrics.export/ff_newton/flops": 700.0,
         "metrics.export/ff_newton/parameters": 84.0},
        {"tags.mlflow.runName": "b-run", "metrics.export/max_rel_diff": 0.0,
         "metrics.export/ff_direct/c_max_rel_diff": 0.0, "metrics.export/ff_direct/python_max_rel_diff": 0.0,
         "metrics.export/ff_newton/misra_findings": float("nan"), "metrics.export/ff_direct/flops": 200.0,
         "metrics.export/ff_direct/parameters": 84.0}])
    rows, md = _exports("some_experiment", runs)
    assert "| MISRA findings |" in md
    line_a = next(x for x in md.splitlines() if x.startswith("| `a-run`"))
    line_b = next(x for x in md.splitlines() if x.startswith("| `b-run`"))
    assert line_a.endswith("| 75 |") and line_b.endswith("| n/a |")
    misra = [r for r in rows if r["metric"] == "misra_findings"]
    assert [(r["variant"], r["value"]) for r in misra] == [("export/a-run/ff_newton", 75.0)]


@pytest.mark.parametrize("kind", ["physics", "newton"])
def test_a_step_is_flagged_on_every_sample_whose_window_holds_it_and_no_large_output_goes_unflagged(kind, tmp_path):
    """A 1 mm step in a reference at rest (found by a user: the envelope was checked at the newest preview
    sample only, so the kick after the step had left it, -2498 N, went out unflagged and, with
    envelope_action=fallback, unreplaced). Now every sample t whose window r(t-2) .. r(t+P) holds the step is
    OUT_OF_RANGE, exactly those; every output above the smooth reference's largest is among them; C = Python."""
    law0 = _law(kind)
    r_smooth = _reference(600)
    law = _with_guard(law0, **_envelope(law0, r_smooth))
    s, P = 40, law.preview
    step = np.r_[np.zeros(s), np.full(40, 1e-3)]
    u, f = guarded(law, step)
    out = (f & FLAG["OUT_OF_RANGE"]) != 0
    np.testing.assert_array_equal(np.flatnonzero(out), np.arange(s - P, s + 2))   # δr at n = s, δ²r at n = s, s + 1
    at_rest = 100.0 * np.max(np.abs(u[:s - P])) + 1e-6      # 100x the output before the step [N]
    big = np.abs(u) > at_rest                                # the kick (Newton: at its bounds, ±5000 N)
    assert big.sum() >= 2 and np.all(out[big])
    law_fb = _with_guard(law, envelope_action="fallback")
    u_fb, f_fb = guarded(law_fb, step)
    assert np.max(np.abs(u_fb)) <= at_rest and np.all(f_fb[out] & FLAG["FALLBACK"])
    if CC is not None:
        write_package(law_fb, "ff_s", tmp_path, {"ref": (r_smooth, feedforward(law0, r_smooth))}, source={},
                      timing_repeats=0)
        u_c, f_c = _c_run(law_fb, "ff_s", tmp_path, step)
        np.testing.assert_array_equal(f_c, f_fb)
        np.testing.assert_array_equal(u_c, u_fb)


@pytest.mark.parametrize("kind", ["physics", "table"])
def test_the_normal_vector_ends_at_rest_and_raises_no_flag_the_reference_does_not(kind, tmp_path):
    """Three moves of 1000 samples with 400 of rest before, between and after: the first 4000 samples end in
    the middle of the third move. The `normal` vector is the two whole moves (a prefix of the reference, ending
    in preview + 50 samples of rest); with limits at 1.5 x what the reference demands, and its envelope, neither
    it nor the reference raises a flag (cut at 4000 samples, the law stops at once: a force spike at the last
    sample, SATURATED). A reference whose first move outlasts 4000 samples keeps that move whole; one that never
    rests is cut, and the manifest says so."""
    from pipeline.export.package import VECTOR_SAMPLES, normal_window
    move, rest = _reference(1000), np.zeros(400)
    r = np.concatenate([rest, move, rest, move, rest, move, rest])            # the third move spans sample 4000
    assert np.any(np.diff(r[VECTOR_SAMPLES - 5:VECTOR_SAMPLES + 1]) != 0)
    law0 = _law("physics")
    law0 = from_table("fhofc", Ts, r, feedforward(law0, r)) if kind == "table" else law0
    u = feedforward(law0, r)
    du = float(np.max(np.abs(np.diff(u, prepend=0.0))))
    law = _with_guard(law0, **_envelope(law0, r), u_min=-1.5 * float(np.max(np.abs(u))),
                      u_max=1.5 * float(np.max(np.abs(u))), rate=1.5 * du / Ts)
    man = write_package(law, "ff_x", tmp_path, {"ref": (r, u)}, source={}, timing_repeats=0)
    assert man["references"]["ref"]["flags"] == {}
    normal = man["vectors"]["normal"]
    assert normal["cut"] == "whole moves" and normal["flags"] == {}, normal
    vec = np.loadtxt(tmp_path / "ff_x" / "vectors_normal.csv", delimiter=",", skiprows=1)
    n = 2 * (400 + 1000) + 400                                                # the two moves and the rest after
    assert vec.shape[0] == normal["samples"] and n - 400 < vec.shape[0] <= n
    np.testing.assert_array_equal(vec[:, 0], r[:vec.shape[0]])
    assert np.all(vec[-(law.preview + 51):, 0] == r[n - 1])
    if CC and kind == "physics":                                              # the C meets it: `--check` exits 0
        exe = compile_harness(tmp_path / "ff_x", "ff_x", CC)
        out = subprocess.run([str(exe), "--check", str(tmp_path / "ff_x" / "vectors_normal.csv")],
                             capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
    if kind == "physics":     # the old cut, the first 4000 samples in motion: a stop the reference never makes
        f_cut = guarded(law, r[:VECTOR_SAMPLES])[1]
        assert f_cut[-1] & FLAG["SATURATED"], f_cut[-5:]
    long_move = np.concatenate([rest, _reference(6000), rest])
    w, how = normal_window(long_move, 2)
    assert how == "the first move" and np.all(w[-53:] == 0.0) and np.any(w != 0.0)
    w, how = normal_window(np.linspace(0.0, 1.0, 6000), 2)
    assert how == "cut in motion" and w.size == VECTOR_SAMPLES
