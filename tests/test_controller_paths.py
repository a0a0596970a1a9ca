"""Issue 49 item 1: a 2-DOF controller given as the drive's tuning tool gives it, C_r = N_r/D_r and
C_y = N_y/D_y with different denominators, accepted as written, written over the least common multiple
(the shared integrator once), and checked against a recording.

The generator here is the test's own: a continuous 2-DOF PID designed per path (reference path: set-point
weighted P + I behind a first-order reference prefilter; measurement path: P + I + filtered D behind a lead),
each path discretised on its own with scipy's Tustin (``signal.cont2discrete``), a rigid mass with viscous
friction simulated by RK4 under a zero-order hold. Nothing here builds the common denominator.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from pipeline.systems.controller import LTIController, common_denominator

TS = 1.0 / 2000.0
M, FV = 2.0, 8.0


def _tustin(num_s, den_s):
    """(num, den) in powers of z⁻¹ of a continuous C(s), Tustin at TS, den[0] = 1."""
    n, d, _ = signal.cont2discrete((num_s, den_s), TS, method="bilinear")
    n, d = np.atleast_1d(np.squeeze(n)), np.atleast_1d(np.squeeze(d))
    return n / d[0], d / d[0]


def paths(fc: float = 40.0, weight: float = 0.5, prefilter_hz: float = 120.0):
    """(N_r, D_r, N_y, D_y): a PID tuned to crossover fc on the mass, with a set-point weight on P and a
    prefilter on r, a filtered D and a lead on y. Both contain the integrator 1/s."""
    wc = 2 * math.pi * fc
    kp, wi, wd = M * wc ** 2 / 3.0, wc / 4.0, 3.0 / wc
    wf, wp = 5 * wc, 2 * math.pi * prefilter_hz
    lead_z, lead_p = 2 * math.pi * 90.0, 2 * math.pi * 400.0
    # C_r(s) = kp (weight s + wi) / s · wp/(s + wp)
    num_r = np.polymul([kp * weight, kp * wi], [wp])
    den_r = np.polymul([1.0, 0.0], [1.0, wp])
    # C_y(s) = kp (s + wi + wd s²·wf/(s + wf)) / s · (s/lead_z + 1)/(s/lead_p + 1)
    pid_n = np.polyadd(np.polymul([1.0, wi], [1.0, wf]), [wd * wf, 0.0, 0.0]) * kp
    pid_d = np.polymul([1.0, 0.0], [1.0, wf])
    num_y = np.polymul(pid_n, [1.0 / lead_z, 1.0])
    den_y = np.polymul(pid_d, [1.0 / lead_p, 1.0])
    return (*_tustin(num_r, den_r), *_tustin(num_y, den_y))


def closed_loop(n_r, d_r, n_y, d_y, r, noise=0.0, seed=0):
    """The loop with each path as its own difference equation (direct form, its own state), RK4 plant under
    ZOH, one sample of computational delay. Returns (y, u)."""
    rng = np.random.default_rng(seed)
    n = r.size
    y, u, v_r, v_y = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    q, qd, c_prev = 0.0, 0.0, 0.0

    def acc(vel, f):
        return (f - FV * vel) / M

    for k in range(n):
        y[k] = q + noise * rng.standard_normal()
        # D v(k) = N x(k): v(k) = Σ N_i x(k-i) - Σ_{i≥1} D_i v(k-i)
        v_r[k] = sum(n_r[i] * r[k - i] for i in range(n_r.size) if k - i >= 0) \
            - sum(d_r[i] * v_r[k - i] for i in range(1, d_r.size) if k - i >= 0)
        v_y[k] = sum(n_y[i] * y[k - i] for i in range(n_y.size) if k - i >= 0) \
            - sum(d_y[i] * v_y[k - i] for i in range(1, d_y.size) if k - i >= 0)
        u[k] = c_prev
        c_prev = v_r[k] - v_y[k]
        f, h = u[k], TS / 4
        for _ in range(4):
            k1q, k1v = qd, acc(qd, f)
            k2q, k2v = qd + h / 2 * k1v, acc(qd + h / 2 * k1v, f)
            k3q, k3v = qd + h / 2 * k2v, acc(qd + h / 2 * k2v, f)
            k4q, k4v = qd + h * k3v, acc(qd + h * k3v, f)
            q += h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
            qd += h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return y, u


def _reference(n):
    t = np.arange(n) * TS
    return 0.02 * (1 - np.cos(2 * np.pi * 1.5 * t)) * np.minimum(t / 0.3, 1.0)


def test_two_denominators_are_written_over_their_least_common_multiple_once():
    n_r, d_r, n_y, d_y = paths()
    ctrl = LTIController.from_config({"kind": "lti", "num": list(n_y), "den": list(d_y), "num_r": list(n_r),
                                      "den_r": list(d_r), "delay": 1}, TS)
    # the shared integrator once: order deg D_r + deg D_y - 1, one root at z = 1 exactly
    assert ctrl.a.size - 1 == (d_r.size - 1) + (d_y.size - 1) - 1
    assert np.sum(np.abs(np.roots(ctrl.a) - 1.0) < 1e-12) == 1
    assert ctrl.integral_action and ctrl.structure == "2-DOF"
    # the law equals the two paths filtered on their own (scipy), on signals with every frequency in them
    rng = np.random.default_rng(3)
    r, y = rng.standard_normal(4000) * 1e-3, rng.standard_normal(4000) * 1e-3
    want = signal.lfilter(n_r, d_r, r) - signal.lfilter(n_y, d_y, y)
    got = ctrl.law(r, y)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))
    # python-control's frequency responses of the combined paths equal the given ones
    Cr, Cy = ctrl.transfer_functions(TS)
    w = np.geomspace(1.0, 0.9 * math.pi / TS, 50)
    z = np.exp(1j * w * TS)
    for tf, (nn, dd) in ((Cr, (n_r, d_r)), (Cy, (n_y, d_y))):
        given = np.polyval(nn[::-1], 1 / z) / np.polyval(dd[::-1], 1 / z)
        assert np.max(np.abs(tf(z) - given) / np.abs(given)) < 1e-9
    # same denominators: as before, nothing multiplied
    b_r, b_y, a = common_denominator(n_y, d_y, n_y, d_y)
    assert np.array_equal(a, d_y) and np.array_equal(b_r, n_y)
    assert "C_r(z) = (" in ctrl.describe() and "common denominator of order" in ctrl.describe()


def test_a_recording_of_the_per_path_controller_is_accepted_as_written_and_a_wrong_path_is_refused():
    n_r, d_r, n_y, d_y = paths()
    r = _reference(6000)
    y, u = closed_loop(n_r, d_r, n_y, d_y, r, noise=1e-8)
    d = np.zeros_like(r)
    cfg = {"kind": "lti", "num": list(n_y), "den": list(d_y), "num_r": list(n_r), "den_r": list(d_r), "delay": 1}
    ctrl = LTIController.from_config(cfg, TS)
    assert ctrl.check(r, y, u, d) < 1e-9        # the equation error of an exact replay: rounding only
    # C_r's prefilter left out (den_r = its integrator only): the check sees another controller
    wrong = dict(cfg, den_r=list(np.polymul([1.0, -1.0], [1.0])), num_r=list(n_r[:2]))
    assert LTIController.from_config(wrong, TS).check(r, y, u, d) > 1e-2
    # the rest of the pipeline's contract: at rest the reference filter is finite and cancels the integrator
    k0 = ctrl.rest_gain()
    assert k0 == 0.0
    f = ctrl.reference_force(r + 0.05, r0=0.05)
    assert np.all(np.isfinite(f)) and abs(f[0]) < 1e-9 * np.max(np.abs(f))


def test_den_r_without_num_r_and_an_unstable_den_r_are_refused_before_any_work():
    n_r, d_r, n_y, d_y = paths()
    with pytest.raises(ValueError, match="den_r is the denominator of the reference path.*give num_r"):
        LTIController.from_config({"kind": "lti", "num": list(n_y), "den": list(d_y), "den_r": list(d_r)}, TS)
    with pytest.raises(ValueError, match=r"controller\.den_r=.*poles outside the unit circle"):
        LTIController.from_config({"kind": "lti", "num": list(n_y), "den": list(d_y), "num_r": list(n_r),
                                   "den_r": [1.0, -1.5]}, TS)
    with pytest.raises(ValueError, match="kind=cascade takes"):
        LTIController.from_config({"kind": "cascade", "kp": 1.0, "kv": 1.0, "den_r": [1.0]}, TS)


def test_the_pipeline_takes_the_paths_as_typed_on_the_command_line(store, cfg_of, tmp_path):
    """The generate stage's controller check and the physics baseline, driven by CLI overrides with
    ``den_r``: the per-path controller passes the check (no user algebra) and the mass comes out."""
    import mlflow  # noqa: F401  (the store fixture points MLflow at tmp_path)
    import pandas as pd

    from pipeline import runner, tracking
    n_r, d_r, n_y, d_y = paths()
    for name, (amp, f, seed) in {"train": (0.03, 1.3, 1), "test": (0.02, 1.9, 2)}.items():
        t = np.arange(8000) * TS
        r = amp * np.sin(2 * np.pi * f * t) * np.minimum(t / 0.4, 1.0) ** 3
        y, u = closed_loop(n_r, d_r, n_y, d_y, r, noise=1e-8, seed=seed)
        pd.DataFrame({"t": t, "r": r, "u": u, "y": y}).to_csv(tmp_path / f"{name}.csv", index=False)
    fl = lambda p: "[" + ",".join(repr(float(x)) for x in p) + "]"
    runner.run_job(cfg_of(
        "system=measured", "system.name=paths_axis", f"system.Ts={TS}", f"system.controller.num={fl(n_y)}",
        f"system.controller.den={fl(d_y)}", f"system.controller.num_r={fl(n_r)}",
        f"system.controller.den_r={fl(d_r)}", "system.controller.delay=1",
        "system.force_terms.terms=[viscous]", "system.idim.cutoff_hz=100", "data=measured", f"data.path={tmp_path}",
        "data.file=train.csv", "evaluate=measured", "evaluate.references=[{name:test,kind:measured,file:test.csv}]",
        "model=physics", "identify=none", "invert=physics", "experiment_name=paths_axis",
        "stages=[generate,baseline]"))
    run = tracking.search_runs("paths_axis").iloc[0]
    assert run["metrics.generate/controller_equation_error"] < 1e-6
    assert abs(run["metrics.baseline/M"] - M) <= 0.02 * M and abs(run["metrics.baseline/F_v"] - FV) <= 0.05 * FV
