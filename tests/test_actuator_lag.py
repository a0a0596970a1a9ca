"""Actuator lag (issue 49 item 3): a drive whose current loop lags the commanded force, τ Ḟ + F = u.

The generator is here, numpy/scipy only (nothing of ``pipeline``): a rigid body with viscous and smooth
Coulomb friction and a constant load behind a first-order force lag (RK4 sub-steps under a zero-order-hold
command), closed by a Tustin PID with a filtered D at Ts = 0.25 ms, τ = 0.4 ms, 5 nm position noise.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from pipeline.identify.measured_loop import LoopModel, LoopSignals, simulate_loop
from pipeline.systems.actuator_lag import ActuatorLag
from pipeline.systems.measured import Recording

TS, TAU = 0.25e-3, 0.4e-3
M, FV, FC, WC, OF = 4.0, 25.0, 3.0, 1e-3, 2.0
NOISE, SUB = 5e-9, 4
TERMS = {"terms": ["viscous", "coulomb", "offset"], "coulomb_width": WC}


def _pid():
    """C(s) = kp + ki/s + kd s wf/(s + wf), 60 Hz crossover on the mass, Tustin (z⁻¹ powers)."""
    wc = 2 * math.pi * 60
    kp = M * wc ** 2 / 3
    ki, kd, wf = kp * wc / 8, kp * 3 / wc, 6 * wc
    n, d = signal.bilinear(np.polyadd(np.polymul([kp, ki], [1, wf]), [kd * wf, 0, 0]), np.polymul([1, 0], [1, wf]),
                           fs=1 / TS)
    return n / d[0], d / d[0]


NUM, DEN = _pid()
CTRL = {"kind": "lti", "num": [float(x) for x in NUM], "den": [float(x) for x in DEN]}


def _rk4(q, v, F, u, dt, n):
    def f(q_, v_, F_):
        return v_, (F_ - FV * v_ - FC * math.tanh(v_ / WC) - OF) / M, (u - F_) / TAU
    for _ in range(n):
        a1 = f(q, v, F)
        a2 = f(q + dt / 2 * a1[0], v + dt / 2 * a1[1], F + dt / 2 * a1[2])
        a3 = f(q + dt / 2 * a2[0], v + dt / 2 * a2[1], F + dt / 2 * a2[2])
        a4 = f(q + dt * a3[0], v + dt * a3[1], F + dt * a3[2])
        q += dt / 6 * (a1[0] + 2 * a2[0] + 2 * a3[0] + a4[0])
        v += dt / 6 * (a1[1] + 2 * a2[1] + 2 * a3[1] + a4[1])
        F += dt / 6 * (a1[2] + 2 * a2[2] + 2 * a3[2] + a4[2])
    return q, v, F


def simulate(r, u_ff=None, seed=0):
    """The PID loop from rest at 0; u_ff [N] is added to the PID's command.  Returns r, u, y, e."""
    N = r.size
    u_ff = np.zeros(N) if u_ff is None else u_ff
    noise = NOISE * np.random.default_rng(seed).standard_normal(N)
    q = v = F = 0.0
    e_h, c_h = np.zeros(NUM.size), np.zeros(DEN.size)
    y, u = np.empty(N), np.empty(N)
    for k in range(N):
        y[k] = q + noise[k]
        e_h = np.roll(e_h, 1)
        e_h[0] = r[k] - y[k]
        ck = NUM @ e_h - DEN[1:] @ c_h[:-1]
        c_h = np.roll(c_h, 1)
        c_h[0] = ck
        u[k] = ck + u_ff[k]
        q, v, F = _rk4(q, v, F, u[k], TS / SUB, SUB)
    return {"r": r, "u": u, "y": y, "e": r - y}


def _reference(moves):
    """Cosine-bell velocity moves (to b in T s), each followed by a 0.1 s dwell."""
    parts, pos = [np.zeros(200)], 0.0
    for b, T in moves:
        s = np.arange(1, int(round(T / TS)) + 1) * TS / T
        parts += [pos + (b - pos) * (s - np.sin(2 * np.pi * s) / (2 * np.pi)), np.full(400, b)]
        pos = b
    return np.concatenate(parts)


TRAIN = _reference([(0.02, 0.08), (-0.01, 0.05), (0.03, 0.1), (0.0, 0.04), (-0.02, 0.07), (0.01, 0.03),
                    (0.025, 0.06), (-0.015, 0.09), (0.005, 0.05), (0.0, 0.06)])
TEST = _reference([(0.015, 0.05), (-0.01, 0.06), (0.02, 0.04), (0.0, 0.07)])


@pytest.fixture(scope="module")
def recording():
    return simulate(TRAIN, seed=1)


# ------------------------------------------------------------------------------------ the sampled lag
@pytest.mark.parametrize("tau_over_ts", [0.05, 0.6, 1.6, 8.0])
def test_model_input_is_the_exact_sampling_of_mass_and_lag(tau_over_ts):
    """Against scipy's ZOH discretisation of 1/(M s² (τ s + 1)): the mass's second difference of the
    sampled position is Ts²/M · w (module docstring), to rounding."""
    tau = tau_over_ts * TS
    sysd = signal.cont2discrete(signal.tf2ss([1.0], np.polymul([M, 0.0, 0.0], [tau, 1.0])), TS, method="zoh")
    u = np.random.default_rng(3).standard_normal(400)
    _, q, _ = signal.dlsim(sysd[:4] + (TS,), u)
    q = q[:, 0]
    d2 = q[2:] - 2 * q[1:-1] + q[:-2]                  # y(k+1) - 2y(k) + y(k-1), k = 1 ..
    w = ActuatorLag(tau, TS).model_input(u)
    np.testing.assert_allclose(d2, TS ** 2 / M * w[1:-1], rtol=0, atol=1e-12 * np.abs(d2).max())


def test_inverse_is_stable_and_tends_to_the_averaged_inverse():
    for x in np.geomspace(0.01, 100, 30):
        lag = ActuatorLag(x * TS, TS)
        zs, zu = lag.zeros()
        assert abs(zs) < 0.3 and zu < -1.0           # the IIR pole z_s of the inverse is stable
        assert abs(lag.coefficients()[0].sum() / (1 - lag.a) - 1.0) < 1e-12   # unit DC gain
    w = np.random.default_rng(0).standard_normal(50)
    for x in (0.02, 0.002):                          # the deviation is O(τ/Ts)
        fast = ActuatorLag(x * TS, TS).applied_input(w, 0.3)
        np.testing.assert_allclose(fast, 0.5 * (w + np.append(w[1:], 0.3)), atol=2 * x * np.abs(w).max())
    # inverse after forward on a sine: the ZPETC's zero-phase gain |1 - z_u e^{jω}|²/(1 - z_u)², nothing else
    lag = ActuatorLag(TAU, TS)
    zu = lag.zeros()[1]
    for f in (50.0, 400.0):
        om = 2 * np.pi * f * TS
        gain = abs(1 - zu * np.exp(1j * om)) ** 2 / (1 - zu) ** 2
        u = np.sin(om * np.arange(4000))
        back = lag.applied_input(lag.model_input(u))
        np.testing.assert_allclose(back[100:-100], gain * u[100:-100], atol=1e-9)
        assert 1 - gain < 0.2 * om ** 2                 # 50 Hz: 0.1 %


def test_bad_lag_is_refused_with_its_key():
    with pytest.raises(ValueError, match="lag_tau"):
        ActuatorLag(-1e-4, TS)
    with pytest.raises(ValueError, match="physics_input: averaged"):
        Recording(Ts=TS, controller=CTRL, physics_input="direct", actuator={"lag_tau": 4e-4})
    with pytest.raises(ValueError, match="unknown actuator key"):
        Recording(Ts=TS, controller=CTRL, actuator={"lag": 4e-4})


# ------------------------------------------------------------------------------------ acceptance
def test_lag_identified_within_10_percent_with_its_uncertainty(recording):
    s = Recording(Ts=TS, controller=CTRL, force_terms=TERMS, actuator={"lag_tau": "auto"})
    theta = s.fit_physics(recording["y"], recording["u"])
    fit = s.lag_fit
    assert abs(fit["tau"] - TAU) <= 0.1 * TAU, fit
    assert 0 < fit["tau_std"] < 0.05 * TAU and not fit["at_bound"]
    assert fit["rss"] < 0.1 * fit["rss_no_lag"]      # the lag explains > 90 % of the no-lag residual
    phys = s.physics.physical(theta)
    assert abs(phys["M"] - M) < 0.01 * M and abs(phys["OF"] - OF) < 0.05 * OF


def test_feedforward_with_the_lag_inverse_tracks_3x_better(recording):
    with_lag = Recording(Ts=TS, controller=CTRL, force_terms=TERMS, actuator={"lag_tau": "auto"})
    without = Recording(Ts=TS, controller=CTRL, force_terms=TERMS)
    mae = {}
    for name, s in (("lag", with_lag), ("none", without)):
        theta = s.fit_physics(recording["y"], recording["u"])
        u_ff = s.physics.feedforward(theta, TEST)
        mae[name] = float(np.mean(np.abs(simulate(TEST, u_ff, seed=5)["e"])))
    mae["no_ff"] = float(np.mean(np.abs(simulate(TEST, seed=5)["e"])))
    # measured: lag 0.57 µm, without 16.2 µm, no feedforward 271 µm
    assert mae["lag"] * 3 <= mae["none"] < mae["no_ff"], mae


def test_loop_replay_and_its_sensitivities_with_the_lag(recording):
    """The recorded loop replayed with the lag follows the record ~10× closer than without; the kernel's
    sensitivities match central differences."""
    r, y, u = TRAIN, recording["y"], recording["u"]
    sig = LoopSignals.recorded(r, np.zeros_like(r), y, u, None, 20)
    rms = {}
    for name, lag in (("lag", {"lag_tau": TAU}), ("none", None)):
        s = Recording(Ts=TS, controller=CTRL, force_terms=TERMS, actuator=lag)
        loop = LoopModel.physics_only(s.physics, s.fit_physics(y, u))
        rms[name] = float(np.sqrt(np.mean((simulate_loop(loop, s.ctrl, sig)[0] - y) ** 2)))
    assert rms["lag"] * 10 < rms["none"], rms
    s = Recording(Ts=TS, controller=CTRL, force_terms=TERMS, actuator={"lag_tau": TAU})
    loop = LoopModel.physics_only(s.physics, s.fit_physics(y, u))
    n = 3000
    short = LoopSignals.recorded(r[:n], np.zeros(n), y[:n], u[:n], None, 20)
    _, _, _, Sy, St = simulate_loop(loop, s.ctrl, short, sens=True)
    th = loop.theta()
    for j in range(th.size):
        h = 1e-4 * abs(th[j])                     # (1e-6: the differences round off)
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        yp, taup, _ = simulate_loop(loop.with_theta(tp), s.ctrl, short)
        ym, taum, _ = simulate_loop(loop.with_theta(tm), s.ctrl, short)
        np.testing.assert_allclose(Sy[:, j], (yp - ym) / (2 * h), rtol=0, atol=1e-5 * np.abs(Sy[:, j]).max())
        np.testing.assert_allclose(St[:, j], (taup - taum) / (2 * h), rtol=0, atol=1e-5 * np.abs(St[:, j]).max())


# ------------------------------------------------------------------------------------ the exported law
@pytest.mark.parametrize("controller", [CTRL, {"kind": "cascade", "kp": 160.18, "kv": 243.45, "gtau": 35.15}],
                         ids=["pid", "cascade"])
def test_exported_law_runs_the_lag_inverse_in_c_as_in_python(controller, tmp_path):
    """The law's lag stage (templates/averaged_step.c) against the invert stage's u_ff, C to 1e-9."""
    import shutil

    from pipeline.export.law import Law, feedforward, from_measured_physics, guarded
    from pipeline.export.package import write_package
    s = Recording("axis", TS, controller=controller, force_terms=TERMS, actuator={"lag_tau": TAU})
    theta = s.physics.theta_from_physical({"M": M, "F_v": FV, "F_c": FC, "OF": OF})
    r = TEST[:3000]
    phys = s.physics.feedforward(theta, r)
    u = phys - s.ctrl.reference_force(r)                                      # stages/invert
    plain = s.physics.with_lag(None).feedforward(theta, r)
    assert np.max(np.abs(phys - plain)) > 0.05 * np.max(np.abs(phys))         # the lag stage does something
    law = from_measured_physics(s.physics, theta, s.ctrl)
    assert law.floats["lag_tau"] == TAU and law.preview == 2
    np.testing.assert_array_equal(feedforward(law, r), u)
    law.save(tmp_path / "law")
    np.testing.assert_array_equal(feedforward(Law.load(tmp_path / "law"), r), u)
    if shutil.which("cc") is None:
        pytest.skip("no C compiler on this machine")
    man = write_package(law, "ff_physics", tmp_path / "pkg", {"ref": (r, u)}, source={"run_id": "test"},
                        rtol=1e-9, timing_repeats=0)
    assert man["compiled"] and man["c_max_rel_diff"] <= 1e-9 and man["python_max_rel_diff"] <= 1e-9, man
    # started at rest at r0 = 5 mm with the static force excluded (the measured default): the lag's registers
    # settle at init in C as the study's law does on its rest samples
    from stages.export import set_start
    r5 = r + 0.005
    set_start(law, {"at": "rest", "static": "exclude"}, [0.005])
    u5, _ = guarded(law, r5)
    assert law.settle > 0 and abs(u5[0]) < 1e-9 * np.abs(u5).max()
    man = write_package(law, "ff_rest", tmp_path / "pkg_rest", {"ref": (r5, u5)}, source={"run_id": "test"},
                        rtol=1e-9, timing_repeats=0)
    assert man["compiled"] and man["c_max_rel_diff"] <= 1e-9 and man["python_max_rel_diff"] <= 1e-9, man


# ------------------------------------------------------------------------------------ through the pipeline
def _write_records(folder, recording):
    import pandas as pd
    test = simulate(TEST, seed=2)
    for name, r, rec in (("train.csv", TRAIN, recording), ("test.csv", TEST, test)):
        pd.DataFrame({"t": np.arange(r.size) * TS, "r": r, "u": rec["u"], "y": rec["y"]}).to_csv(folder / name,
                                                                                              index=False)


def _overrides(folder, lag: str) -> list[str]:
    fl = lambda p: "[" + ",".join(repr(float(x)) for x in p) + "]"   # noqa: E731
    return ["system=measured", "system.name=lag_axis", f"system.Ts={TS}", f"system.controller.num={fl(NUM)}",
            f"system.controller.den={fl(DEN)}", "system.force_terms.terms=[viscous,coulomb,offset]",
            f"system.force_terms.coulomb_width={WC}", f"system.actuator.lag_tau={lag}", "data=measured",
            f"data.path={folder}", "data.file=train.csv", "evaluate=measured",
            "evaluate.references=[{name:test,kind:measured,file:test.csv}]"]


def test_the_pipeline_identifies_the_lag_and_ships_its_inverse(store, cfg_of, tmp_path, recording):
    """``system.actuator.lag_tau=auto`` on the command line: the baseline logs τ and its uncertainty, the
    physics feedforward (invert stage) carries the lag's inverse, a rerun from the cache uses the same τ."""
    from pipeline import runner, tracking
    _write_records(tmp_path, recording)
    args = _overrides(tmp_path, "auto") + ["model=physics", "identify=none", "invert=physics"]
    runner.run_job(cfg_of(*args, "stages=[generate,baseline]", "experiment_name=lag_axis"))
    run = tracking.search_runs("lag_axis").iloc[0]
    assert abs(run["metrics.baseline/lag_tau"] - TAU) <= 0.1 * TAU
    assert 0 < run["metrics.baseline/lag_tau_std"] < 0.05 * TAU
    # a second job: the baseline comes from the cache (fit_physics does not run), the invert stage still inverts τ
    res = runner.run_job(cfg_of(*args, "stages=[generate,baseline,train,invert]", "experiment_name=lag_axis_2"))
    s = Recording(Ts=TS, controller=CTRL, force_terms=TERMS, actuator={"lag_tau": "auto"})
    theta = s.fit_physics(recording["y"], recording["u"])
    assert abs(s.lag_fit["tau"] - run["metrics.baseline/lag_tau"]) < 1e-12
    # the invert stage starts at rest at r(0) with the static force excluded (the measured default): the
    # study's lagged feedforward from zero force, less its value at rest, once its start transient (pole z_s) died
    ff = s.physics.feedforward(theta, TEST)
    got = res["invert"]["u_ff"]["test"]
    np.testing.assert_allclose(got[20:], ff[20:] - ff[150], rtol=0, atol=1e-9 * np.abs(ff).max())
    plain = s.physics.with_lag(None).feedforward(theta, TEST)
    assert np.abs(got[20:] - plain[20:] + plain[150]).max() > 0.05 * np.abs(got).max()   # without the lag: far


@pytest.mark.slow
def test_the_pgnn_learns_and_inverts_through_the_lag(store, cfg_of, tmp_path, recording):
    """A simulation-error PGNN (one tanh layer, analytic inversion) with lag_tau=auto: its loop model carries the
    lag, and its feedforward tracks the generator ≥ 3x better than the same PGNN without the lag (measured:
    0.66 against 10.6 µm MAE; no feedforward 271 µm).  ~60 s (numba compiles the lagged loop kernel)."""
    from pipeline import runner
    _write_records(tmp_path, recording)
    pgnn = ["model=pgnn", "identify=sim_error", "model.structure=invertible", "model.n_a=2", "model.n_b=1",
            "model.hidden=[4]", "model.input_transform=delta", "identify.n_restarts=2", "identify.max_iter=200",
            "regularizer=physics_l2", "regularizer.lam=0.01", "invert=analytic",
            "stages=[generate,baseline,train,invert]"]
    mae = {}
    for lag in ("auto", "null"):
        res = runner.run_job(cfg_of(*_overrides(tmp_path, lag), *pgnn, f"experiment_name=pgnn_{lag}"))
        assert res["train"]["loop"].lag_b.size == (3 if lag == "auto" else 0)
        mae[lag] = float(np.mean(np.abs(simulate(TEST, res["invert"]["u_ff"]["test"], seed=5)["e"])))
    assert 3 * mae["auto"] <= mae["null"], mae


def test_continuous_replay_integrates_the_lag(recording):
    """The integrator check (RK4 sub-steps of the continuous physics, now with F as a third state) agrees with the
    one-step replay on the exact sampling of mass and lag: their difference shrinks to the friction terms' own."""
    from pipeline.identify.continuous_replay import replay_rk4
    r, y, u = TRAIN, recording["y"], recording["u"]
    sig = LoopSignals.recorded(r, np.zeros_like(r), y, u, None, 20)
    gap = {}
    for name, lag in (("lag", {"lag_tau": TAU}), ("none", None)):
        s = Recording(Ts=TS, controller=CTRL, force_terms=TERMS, actuator=lag)
        theta = s.fit_physics(y, u)
        one = simulate_loop(LoopModel.physics_only(s.physics, theta), s.ctrl, sig)[0]
        cont = replay_rk4(s.physics, theta, s.ctrl, sig, 16)[0]
        gap[name] = float(np.sqrt(np.mean((cont - one) ** 2)) / np.sqrt(np.mean((y - one) ** 2)))
        if name == "lag":
            no_lag = replay_rk4(s.physics.with_lag(None), theta, s.ctrl, sig, 16)[0]
            assert np.sqrt(np.mean((no_lag - one) ** 2)) > 10 * np.sqrt(np.mean((cont - one) ** 2))
    assert gap["lag"] < 0.5, gap


@pytest.mark.parametrize("bad,why", [("fast", "'auto'"), ("-0.001", "> 0"), ("2.0", "<= 1"), ("true", "'auto'")])
def test_a_bad_lag_tau_is_one_config_line(cfg_of, bad, why):
    from pipeline import schema
    from pipeline.errors import ConfigError
    with pytest.raises(ConfigError, match=r"^system\.actuator\.lag_tau=") as err:
        schema.check(cfg_of("system=measured", "system.controller.num=[1.0]", f"system.actuator.lag_tau={bad}"))
    assert why in str(err.value) and "\n" not in str(err.value), str(err.value)
    schema.check(cfg_of("system=measured", "system.controller.num=[1.0]", "system.actuator.lag_tau=0.0004"))
