"""Issue 48 item 4: the holes an embedded engineer's review found in the guard around every exported law.

1. the return from a fallback (after a NaN hold) never steps more than the slew limit; with finite limits
   no sample leaves [u_min, u_max] and no step exceeds rate·Ts, for a NaN burst, a 1e30 sample, a sign
   glitch and a 1e302 reference through every law family; without a rate limit the return ramps;
2. ``-Ofast`` / ``-ffast-math`` (which delete every ``isfinite()``) stop the build with ``#error``;
3. every overflow (a non-finite regressor, a non-finite or SINGULAR law output) gives FALLBACK;
4. a non-finite law output latches the fallback until init (as the README says);
5. under ``export.target_rate`` the zero-order hold limits the slew per loop sample and the loop period
   passes the rate check;
6. the physics fallback has every configured force term (the offset: gravity on a vertical axis);
7. the harness checks flags exactly and u_ff per sample; float and double packages link together;
8. every family compiles clean under gcc and clang with -Wconversion -Wdouble-promotion.

Tolerances: C and Python run the same operations in the same order, so flags are compared exactly and
u_ff to 1e-12 relative (glibc's tanh against numba's, as in test_export_safety.py).
"""
from __future__ import annotations

import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.export.c_code import write_c
from pipeline.export.guard import FLAG
from pipeline.export.law import Law, feedforward, guarded
from pipeline.export.package import compile_harness, write_package
from tests.test_export import Ts, _reference
from tests.test_export_safety import CC, TOL, _c_run, _envelope, _law, _with_guard, needs_cc

CLANG = shutil.which("clang")
GCC = shutil.which("gcc")
STRICT = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-Wconversion", "-Wdouble-promotion"]
FAST = ["physics", "newton", "rational", "table"]
SLOW = ["direct", "analytic", "shared_ar", "measured"]
KINDS = FAST + [pytest.param(k, marks=pytest.mark.slow) for k in SLOW]
FB = FLAG["FALLBACK"]


def _ref(law: Law, kind: str) -> np.ndarray:
    return law.arrays["r"] if kind == "table" else _reference(600)


def _window_holds(mask: np.ndarray, P: int) -> np.ndarray:
    """[t]: the guard's window r(t-2) .. r(t+P) holds a sample of ``mask`` (the end held)."""
    ext = np.concatenate([[False, False], mask, np.full(P, mask[-1])])
    return np.lib.stride_tricks.sliding_window_view(ext, P + 3).any(axis=1)


def _glitches(r: np.ndarray) -> dict:
    k = int(np.argmax(np.abs(np.diff(r))))            # the fastest sample: in motion
    nan, big, sign = r.copy(), r.copy(), r.copy()
    nan[k:k + 10] = np.nan
    big[k] = 1e30
    sign[k] = -r[k]
    huge = 1e302 * (1.0 + r / np.max(np.abs(r)))     # every sample >= 1e302, moving
    return {"nan": nan, "1e30": big, "sign": sign, "1e302": huge}


# ---- 1 (with 3): finite limits hold on every glitch, the right flags, C = Python --------------------------
@needs_cc
@pytest.mark.parametrize("kind", KINDS)
def test_glitches_stay_inside_the_limits_with_the_right_flags(kind, tmp_path):
    law0 = _law(kind)
    r = _ref(law0, kind)
    u_study = feedforward(law0, r)
    umax = float(np.max(np.abs(u_study)))
    du = float(np.max(np.abs(np.diff(u_study))))
    law = _with_guard(law0, **_envelope(law0, r), u_min=-1.5 * umax, u_max=1.5 * umax, rate=1.5 * du / Ts)
    write_package(law, "ff_x", tmp_path, {"ref": (r, u_study)}, source={}, timing_repeats=0)
    P, du_max = law.preview, law.g.du_max(Ts)
    for case, rc in _glitches(r).items():
        u, f = guarded(law, rc)
        u_c, f_c = _c_run(law, "ff_x", tmp_path, rc)
        np.testing.assert_array_equal(f_c, f, err_msg=case)
        np.testing.assert_allclose(u_c, u, rtol=0, atol=TOL * np.max(np.abs(u)), err_msg=case)
        assert np.all(np.isfinite(u)) and np.all(u <= law.g.u_max) and np.all(u >= law.g.u_min), case
        assert np.all(np.abs(np.diff(u)) <= du_max * (1 + 1e-12)), case          # the return too
        bad = _window_holds(~np.isfinite(rc), P)                                 # NaN in r(t-2) .. r(t+P)
        assert np.all(f[bad] & FLAG["NONFINITE_INPUT"]) and np.all(f[bad] & FB), case
        assert not np.any(f[~bad] & FLAG["NONFINITE_INPUT"]), case
        assert np.all(f[(f & FLAG["SINGULAR"]) != 0] & FB), case                 # an overflow: never silent
        if case in ("1e30", "sign"):                                             # the glitch's windows
            hit = _window_holds(rc != r, P)
            assert np.all(f[hit] & FLAG["OUT_OF_RANGE"]), case
        if case == "1e302":
            assert np.all(f & FLAG["OUT_OF_RANGE"]), case


# ---- 1: without a rate limit the return from a fallback ramps (no kick from the held samples) ------------
@needs_cc
@pytest.mark.parametrize("kind", KINDS)
def test_the_return_from_a_hold_ramps_without_a_rate_limit(kind, tmp_path):
    """One NaN in motion gave a 3 kN kick (clean peak 94 N): the forward-filled sample in the law's regressors
    (M/Ts² amplification) on the samples after it, flagged nothing. Now those samples hold too (their window
    r(t-2) .. r(t+P) held a NaN) and the return goes from the held value to the law's linearly over
    ramp_time (FALLBACK until it is back). A law without memory beyond that window (physics, a table, the
    direct law, a measured axis here) then gives the study's u_ff again, and no step or value beyond the
    clean one's; a recursive law ([K] 1/B(q), Newton's model) carries the held samples in its state, which
    the ramp spreads over ramp_time (a slew limit bounds it: the test above)."""
    law0 = _law(kind)
    r = _ref(law0, kind)
    u_study = feedforward(law0, r)
    law = _with_guard(law0, ramp_time=0.02)              # no limits (rate = inf), hold
    write_package(law, "ff_x", tmp_path, {"ref": (r, u_study)}, source={}, timing_repeats=0)
    umax = float(np.max(np.abs(u_study)))
    du = float(np.max(np.abs(np.diff(u_study))))
    R, P = law.g.ramp_n(Ts), law.preview
    k = int(np.argmax(np.abs(np.diff(r))))
    for n_nan in (1, 10):
        rc = r.copy()
        rc[k:k + n_nan] = np.nan
        u, f = guarded(law, rc)
        u_c, f_c = _c_run(law, "ff_x", tmp_path, rc)
        np.testing.assert_array_equal(f_c, f)
        np.testing.assert_allclose(u_c, u, rtol=0, atol=TOL * np.max(np.abs(u)))
        held = _window_holds(~np.isfinite(rc), P)
        t_hold = np.flatnonzero(held)
        hold = u[t_hold[0] - 1]
        assert np.all(u[held] == hold) and np.all(f[held] & FB) and np.all(f[held] & FLAG["NONFINITE_INPUT"])
        # the return: u_from + (u_law - u_from) j / R on the j-th valid sample, u_law the law on the filled r
        rf = rc.copy()
        for i in np.flatnonzero(~np.isfinite(rf)):
            rf[i] = rf[i - 1]
        u_law = u_study if kind == "table" else feedforward(law0, rf)
        ret = np.arange(t_hold[-1] + 1, t_hold[-1] + int(math.ceil(R)))
        want = hold + (u_law[ret] - hold) * ((ret - t_hold[-1]) / R)
        np.testing.assert_allclose(u[ret], want, rtol=1e-12, atol=1e-12 * umax)
        assert np.all(f[ret] & FB) and not np.any(f[ret[-1] + 1:] & FB)
        np.testing.assert_array_equal(u[ret[-1] + 1:], u_law[ret[-1] + 1:])       # back: the law's own
        if kind in ("physics", "table", "direct", "measured"):                    # no memory past the window
            np.testing.assert_array_equal(u[ret[-1] + 1:], u_study[ret[-1] + 1:])
            assert np.max(np.abs(u)) <= umax and np.max(np.abs(np.diff(u))) <= du * (1 + 1e-12), n_nan


# ---- 2: no fast-math build ---------------------------------------------------------------------------------
@needs_cc
@pytest.mark.parametrize("cc", ["gcc", "clang"])
def test_fast_math_stops_the_build_with_a_reason(cc, tmp_path):
    exe = shutil.which(cc)
    if exe is None:
        pytest.skip(f"{cc} is not installed (apt-get install {cc})")
    law = _law("physics")
    write_c(law, "ff_x", tmp_path, "src")
    for flag in ("-Ofast", "-ffast-math", "-ffinite-math-only"):
        out = subprocess.run([exe, "-std=c99", "-O2", flag, "-c", "-o", str(tmp_path / "x.o"),
                              str(tmp_path / "ff_x.c")], capture_output=True, text=True)
        assert out.returncode != 0 and "isfinite" in out.stderr and "-ffast-math" in out.stderr, (flag, out.stderr)
    out = subprocess.run([exe, *STRICT, "-c", "-o", str(tmp_path / "x.o"), str(tmp_path / "ff_x.c")],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


# ---- 3: every overflow falls back ----------------------------------------------------------------------------
@needs_cc
@pytest.mark.parametrize("kind", KINDS)
def test_every_overflow_falls_back_and_is_flagged(kind, tmp_path):
    """A reference sample of 1e306 (its differences overflow to inf) and a reference of 1e302 and more (Newton
    returned 0 N with SINGULAR and no FALLBACK): FALLBACK on every sample whose regressors or law output
    overflowed, OUT_OF_RANGE on the inf regressors even with no envelope; C = Python flag for flag."""
    law0 = _law(kind)
    r = _ref(law0, kind)
    law = law0                                            # the defaults: no envelope, no limits
    write_package(law, "ff_x", tmp_path, {"ref": (r, feedforward(law0, r))}, source={}, timing_repeats=0)
    spike = r.copy()
    spike[300] = 1e306
    jump = r.copy()
    jump[300:] = 1e302                                    # Newton's start overflows: 0 N and SINGULAR
    for case, rc in {"spike": spike, "jump": jump, "1e302": _glitches(r)["1e302"]}.items():
        u, f = guarded(law, rc)
        u_c, f_c = _c_run(law, "ff_x", tmp_path, rc)
        np.testing.assert_array_equal(f_c, f, err_msg=case)
        np.testing.assert_allclose(u_c, u, rtol=0, atol=TOL * max(np.max(np.abs(u)), 1e-300), err_msg=case)
        assert np.all(np.isfinite(u))
        assert np.all(f[(f & FLAG["SINGULAR"]) != 0] & FB), case
        if case == "spike":
            hit = _window_holds(rc != r, law.preview)
            assert np.all(f[hit] & FB) and np.all(f[hit] & FLAG["OUT_OF_RANGE"]), case
    if kind == "newton":                                  # the case of the review: 0 N, no FALLBACK
        u, f = guarded(law, jump)
        sing = (f & FLAG["SINGULAR"]) != 0               # the start overflowed: the kernel returned 0 N
        assert sing.sum() >= 2 and np.all(f[sing] & FB) and np.all(u[sing] == u[299 - law.preview])


# ---- 4: a non-finite law output latches the fallback until init ---------------------------------------------
@needs_cc
@pytest.mark.parametrize("kind", ["physics", "rational", pytest.param("direct", marks=pytest.mark.slow)])
def test_a_non_finite_law_output_latches_the_fallback_until_init(kind, tmp_path):
    """The README said "the fallback until the next init" and all laws recovered 3 samples later. A non-finite
    law output (an overflow inside the law: its filter or recursion may now hold inf/NaN) latches the
    fallback: SINGULAR | FALLBACK on every later sample; init starts the law clean again."""
    law = _law(kind)
    r = _reference(600)
    u_study = feedforward(law, r)
    write_package(law, "ff_x", tmp_path, {"ref": (r, u_study)}, source={}, timing_repeats=0, prefix="ffx")
    rc = r.copy()
    rc[300] = 1e306
    u, f = guarded(law, rc)
    t0 = int(np.flatnonzero(f & FB)[0])
    assert np.all(f[t0:] & FB) and np.all(f[t0 + law.preview + 3:] & FLAG["SINGULAR"])
    assert np.all(u[t0:] == u[t0 - 1])                    # hold, to the end: the law is not trusted again
    # C: the same, then init and the clean reference: the study's u_ff again
    pkg = tmp_path / "ff_x"
    n = r.size
    arr = lambda a: ", ".join(repr(float(v)) for v in a)  # noqa: E731
    main = ['#include <stdio.h>', '#include "ff_x.h"',
            f"static const double R1[{n}] = {{{arr(rc)}}};", f"static const double R2[{n}] = {{{arr(r)}}};",
            "static void run(const double *R, double r0) {",
            "    ffx_state s; double w[FFX_PREVIEW + 1], u; long t; int i;",
            "    ffx_init(&s, r0);",
            f"    for (t = 0; t < {n}; ++t) {{",
            f"        for (i = 0; i <= FFX_PREVIEW; ++i) w[i] = R[t + i < {n} ? t + i : {n - 1}];",
            "        u = ffx_step(&s, w);",                 # then the status: the order of arguments is unspecified
            '        printf("%.17g %d\\n", u, s.status);', "    }", "}",
            "int main(void) {", f"    run(R1, {float(r[0])!r}); run(R2, {float(r[0])!r});", "    return 0;", "}"]
    (pkg / "latch.c").write_text("\n".join(main) + "\n")
    out = subprocess.run([CC, *STRICT, "-o", str(pkg / "latch"), str(pkg / "latch.c"), str(pkg / "ff_x.c"), "-lm"],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    rows = np.array([line.split() for line in subprocess.run([str(pkg / "latch")], capture_output=True,
                                                              text=True).stdout.splitlines()], dtype=float)
    np.testing.assert_array_equal(rows[:n, 1].astype(int), f)
    np.testing.assert_array_equal(rows[:n, 0], u)
    np.testing.assert_allclose(rows[n:, 0], u_study, rtol=0, atol=TOL * np.max(np.abs(u_study)))
    assert not np.any(rows[n:, 1].astype(int) & FB)


# ---- 5: the zero-order hold limits the slew per loop sample ---------------------------------------------------
@needs_cc
def test_the_zero_order_hold_limits_the_slew_per_loop_sample(tmp_path):
    from pipeline.export.guard import zoh_loop     # the wrapper's Python twin (new with item 5)
    law0 = _law("physics")
    r = _reference(400)
    u_study = feedforward(law0, r)
    n = 4
    rate = 0.5 * float(np.max(np.abs(np.diff(u_study)))) / Ts     # the law is rate limited at times
    law = _with_guard(law0, rate=rate)
    man = write_package(law, "ff_physics", tmp_path, {"ref": (r, u_study)}, source={}, timing_repeats=0, zoh_n=n,
                        prefix="axis1")
    du_loop = rate * Ts / n
    assert man["zoh"]["du_loop"] == du_loop
    pkg = tmp_path / "ff_physics"
    rf = np.interp(np.arange((r.size - 1) * n + 1) / n, np.arange(r.size), r)     # the loop-rate reference
    main = ['#include <stdio.h>', '#include "ff_physics.h"', f"static const double R[{rf.size}] = {{"
            + ", ".join(repr(float(v)) for v in rf) + "};",
            "int main(void) {", "    axis1_zoh_state z; long t; int i;", "    double w[AXIS1_ZOH_PREVIEW + 1], u;",
            "    axis1_zoh_init(&z, 0.0);",
            f"    for (t = 0; t < {rf.size}; ++t) {{",
            f"        for (i = 0; i <= AXIS1_ZOH_PREVIEW; ++i) w[i] = R[t + i < {rf.size} ? t + i : {rf.size - 1}];",
            "        u = axis1_zoh_step(&z, w);", '        printf("%.17g %d\\n", u, z.status);', "    }",
            "    return 0;", "}"]
    (pkg / "zoh_main.c").write_text("\n".join(main) + "\n")
    for period in (250000, 1000000):                 # the loop's period and the law's both pass the rate check
        out = subprocess.run([CC, *STRICT, f"-DAXIS1_LOOP_TS_NS={period}", "-o", str(pkg / "zoh"),
                              str(pkg / "zoh_main.c"), str(pkg / "ff_physics.c"), "-lm"],
                             capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
    wrong = subprocess.run([CC, "-std=c99", "-DAXIS1_LOOP_TS_NS=500000", "-c", "-o", str(pkg / "x.o"),
                            str(pkg / "zoh_main.c")], capture_output=True, text=True)
    assert wrong.returncode != 0 and "0.00025" in wrong.stderr
    rows = np.array([line.split() for line in subprocess.run([str(pkg / "zoh")], capture_output=True,
                                                              text=True).stdout.splitlines()], dtype=float)
    u = rows[:, 0]
    assert np.all(np.abs(np.diff(u, prepend=0.0)) <= du_loop * (1 + 1e-12))
    u_law = guarded(law, rf[::n])[0]
    np.testing.assert_array_equal(u, zoh_loop(u_law, n, du_loop)[:u.size])
    assert np.any(rows[:, 1].astype(int) & FLAG["RATE_LIMITED"])
    # with no rate limit the wrapper is the plain hold
    np.testing.assert_array_equal(zoh_loop(u_law, n, math.inf)[:u.size], np.repeat(u_law, n)[:u.size])


# ---- 6: the physics fallback has every force term ---------------------------------------------------------
def _vertical_axis():
    from pipeline.systems.measured import Recording
    sys_ = Recording("axis", Ts, controller={"kind": "cascade", "kp": 160.18, "kv": 243.45, "gtau": 35.15},
                     force_terms={"terms": ["viscous", "coulomb", "stribeck", "offset", "cogging"],
                                  "coulomb_width": 0.002, "cogging_period": 0.03, "cogging_harmonics": 2},
                     physics_input="averaged")
    theta = sys_.physics.theta_from_physical({"M": 12.0, "F_v": 40.0, "F_c": 8.0, "F_s": 3.0, "OF": 50.0,
                                              "C_cos1": 1.5, "C_sin1": -0.7, "C_cos2": 0.4, "C_sin2": 0.2})
    return sys_, theta


@needs_cc
def test_the_physics_fallback_has_every_configured_force_term(tmp_path):
    """A vertical axis (offset OF = 50 N: gravity) out of its envelope falls back on the physics law: at rest
    it holds the load (50 N plus the cogging force there), in motion M d2r + Σ p_j T_j(r, dr) of every
    term; C = Python to the bit."""
    from pipeline.export.law import from_measured_physics
    from stages.export import physics_coefficients
    sys_, theta = _vertical_axis()
    law0 = from_measured_physics(sys_.physics, theta, sys_.ctrl)
    r = _reference(600)
    phys = physics_coefficients(sys_, theta)
    law = _with_guard(law0, env_lo=[-1.0, -1.0, -1e9], env_hi=[0.01, 1.0, 1e9], envelope_action="fallback",
                      fallback="physics", **phys)
    write_package(law, "ff_x", tmp_path, {"ref": (r, feedforward(law0, r))}, source={}, timing_repeats=0)
    rc = np.concatenate([r, np.full(100, r[-1])]) + 0.02          # ends at rest at 20 mm, above r <= 10 mm
    u, f = guarded(law, rc)
    u_c, f_c = _c_run(law, "ff_x", tmp_path, rc)
    np.testing.assert_array_equal(f_c, f)
    np.testing.assert_array_equal(u_c, u)
    assert np.all(f & FB)
    P = law.preview
    x = np.concatenate([[0.0, 0.0], rc, np.full(P, rc[-1])])      # r(t-2) .. r(t+P), r0 = 0 (rest 'zero')
    q, v = x[2 + P:], (x[2 + P:] - x[1 + P:-1]) / Ts
    a = (x[2 + P:] - 2.0 * x[1 + P:-1] + x[P:-2]) / Ts ** 2
    t_inv = sys_.physics.inverse_theta(theta)
    want = t_inv[0] * a + sum(p * c for p, c in zip(t_inv[1:], sys_.physics.terms.columns(q, v)))
    np.testing.assert_allclose(u[3:], want[3:], rtol=1e-12, atol=1e-9)
    at_rest = u[-50:]
    load = 50.0 + sum(p * c for p, c in zip(t_inv[5:], sys_.physics.terms.columns(rc[-50:], 0.0 * rc[-50:])[4:]))
    np.testing.assert_allclose(at_rest, load, rtol=1e-12)
    assert np.all(at_rest > 45.0)                                   # the load is held, not dropped


# ---- 7: the harness checks flags exactly and u_ff per sample; float and double link together ---------------
@needs_cc
def test_the_float_harness_checks_flags_exactly_and_u_per_sample(tmp_path):
    """The float harness checked u_ff to single_rtol x max|u| (one spike sets max|u|) and no flags, though it
    printed "flags exactly". Now per sample, |u_c(t) - u(t)| <= atol + rtol |u(t)| (the manifest's "check"),
    and the flags exactly but the threshold ones (a float on a limit falls either side by rounding): one sample
    off by more than its own bound (but less than single_rtol x max|u|), or one flag off, fails."""
    law = _law("physics")
    r = _reference(600)
    single_rtol = 0.1
    man = write_package(law, "ff_s", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0,
                        precision="single", single_rtol=single_rtol)
    chk = man["check"]
    assert chk["rtol"] == single_rtol and chk["atol"] > 0 and "|u_c(t) - u(t)|" in chk["bound"]
    exe = compile_harness(tmp_path / "ff_s", "ff_s", CC)
    vec = (tmp_path / "ff_s" / "vectors_normal.csv").read_text().splitlines()
    rows = np.array([line.split(",") for line in vec[1:]], dtype=float)
    out = subprocess.run([str(exe), "--check", str(tmp_path / "ff_s" / "vectors_normal.csv")], capture_output=True,
                         text=True)
    assert out.returncode == 0 and "flags under mask" in out.stderr, out.stderr
    assert not chk["flag_mask"] & (FLAG["SATURATED"] | FLAG["RATE_LIMITED"] | FLAG["OUT_OF_RANGE"])
    u = rows[:, 1]
    t = int(np.argmin(np.abs(u[100:500]))) + 100          # in motion, |u| small
    bound, old = chk["atol"] + chk["rtol"] * abs(u[t]), single_rtol * np.max(np.abs(u))
    off = float(0.5 * (bound + old))                        # beyond the sample's bound, inside the old one
    assert bound < off < old
    r_, u_, f_ = vec[t + 1].split(",")
    for bad_line in (f"{r_},{float(u_) + off!r},{f_}", f"{r_},{u_},{int(f_) ^ FLAG['FALLBACK']}"):
        (tmp_path / "bad.csv").write_text("\n".join(vec[:t + 1] + [bad_line] + vec[t + 2:]) + "\n")
        out = subprocess.run([str(exe), "--check", str(tmp_path / "bad.csv")], capture_output=True, text=True)
        assert out.returncode == 1 and f"sample {t}:" in out.stderr, out.stderr


@needs_cc
def test_a_float_and_a_double_package_of_one_law_link_into_one_program(tmp_path):
    law = _law("physics")
    r = _reference(300)
    mans, srcs = {}, []
    for prec in ("double", "single"):
        mans[prec] = write_package(law, "ff_physics", tmp_path / prec, {"ref": (r, feedforward(law, r))}, source={},
                                   timing_repeats=0, precision=prec, single_rtol=0.5)
        srcs.append(str(tmp_path / prec / "ff_physics" / "ff_physics.c"))
    pd, ps = mans["double"]["prefix"], mans["single"]["prefix"]
    assert pd != ps
    main = ["#include <stdio.h>", '#include "double/ff_physics/ff_physics.h"',
            '#include "single/ff_physics/ff_physics.h"',
            "int main(void) {", "    double rp[3] = {0.0, 1e-6, 3e-6};", "    float rf[3] = {0.0f, 1e-6f, 3e-6f};",
            f"    {pd}_state a; {ps}_state b;", f"    {pd}_init(&a, 0.0); {ps}_init(&b, 0.0f);",
            f'    printf("%.17g %.17g\\n", {pd}_step(&a, rp), (double){ps}_step(&b, rf));', "    return 0;", "}"]
    (tmp_path / "main.c").write_text("\n".join(main) + "\n")
    out = subprocess.run([CC, *STRICT, f"-I{tmp_path}", "-o", str(tmp_path / "both"), str(tmp_path / "main.c"), *srcs,
                          "-lm"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    got = [float(v) for v in subprocess.run([str(tmp_path / "both")], capture_output=True, text=True).stdout.split()]
    want = guarded(law, np.array([0.0, 1e-6, 3e-6]))[0][0]
    assert got[0] == pytest.approx(want, rel=TOL) and got[1] == pytest.approx(want, rel=1e-3)


# ---- 8: clean under gcc and clang with the strict warnings ---------------------------------------------------
@pytest.mark.parametrize("cc", ["gcc", "clang"])
@pytest.mark.parametrize("kind", ["physics", "newton", "direct", "analytic", "rational", "shared_ar", "table",
                                  "measured"])
def test_every_family_compiles_clean_with_strict_warnings(cc, kind, tmp_path):
    exe = shutil.which(cc)
    if exe is None:
        pytest.skip(f"{cc} is not installed (apt-get install {cc}): the strict build is checked where it is")
    law = _law(kind)
    law = _with_guard(law, fallback="physics", physics=[2.0, 1.0, 0.5]) if kind != "table" else law
    for prec in ("double", "single"):
        for zoh in (1, 3):
            d = tmp_path / f"{prec}{zoh}"
            d.mkdir()
            write_c(law, "ff_x", d, "src", precision=prec, zoh_n=zoh)
            out = subprocess.run([exe, *STRICT, "-o", str(d / "m"), str(d / "main_ff_x.c"), str(d / "ff_x.c"), "-lm"],
                                 capture_output=True, text=True)
            assert out.returncode == 0, f"{cc} {kind} {prec} zoh {zoh}:\n{out.stderr[-3000:]}"


def test_the_readme_says_what_the_guard_does():
    """The flag table and the guard paragraphs of README "Deploy the feedforward" say what is true."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    deploy = text[text.index("## Deploy the feedforward"):]
    deploy = deploy[:deploy.index("\n## ", 5)]
    assert "latched" in deploy and "until the next init" in deploy
    assert "-ffast-math" in deploy and "every configured force term" in deploy
    assert "per loop sample" in deploy and "flags exactly" in deploy


@pytest.mark.parametrize("cc", ["gcc", "clang"])
def test_the_readme_compile_line_builds_a_package_and_checks_its_vectors(cc, tmp_path):
    """README "Deploy the feedforward"'s compile line, as written (its flags, with gcc and clang for `cc`), builds
    an exported package and its harness passes `--check vectors_normal.csv`; its flags are the stage's CFLAGS."""
    import re
    import shlex

    from pipeline.export.c_code import CFLAGS
    exe = shutil.which(cc)
    if exe is None:
        pytest.skip(f"{cc} is not installed (apt-get install {cc}): the README's line is checked where it is")
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    m = re.search(r"cd export/ff_newton && cc (.*?)\\\n\s+(-o main_ff_newton main_ff_newton\.c ff_newton\.c -lm)", text)
    assert m, "the README's compile line moved: update this test"
    flags = shlex.split(m.group(1))
    assert tuple(flags) == CFLAGS
    law = _law("newton")
    r = _ref(law, "newton")
    write_package(law, "ff_newton", tmp_path, {"ref": (r, feedforward(law, r))}, source={}, timing_repeats=0)
    d = tmp_path / "ff_newton"
    out = subprocess.run([exe, *flags, *shlex.split(m.group(2))], cwd=d, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    out = subprocess.run([str(d / "main_ff_newton"), "--check", "vectors_normal.csv"], cwd=d, capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr[-2000:]
