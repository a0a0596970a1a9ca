"""Simulated plants of SPEC §2.2-§2.4: cross-checks against python-control, loop properties,
determinism, physics-model least squares and feedforward, and input validation."""
import time

import control as ct
import numpy as np
import pytest

from pipeline import references as R
from pipeline.identify.least_squares import solve_scaled as least_squares
from pipeline.systems.arx_bias import ARXPhysics, ArxBias
from pipeline.systems.linear_motor import LinearMotor, LinearMotorPhysics
from pipeline.systems.rot_trans_nmp import RotTransNMP, zpetc_feedforward

LINEAR_REL = 1e-8     # SPEC §2: RK4 with 20 substeps vs c2d (10 substeps reach only ~5e-9)


def _closed_loop_reference(P, Cz, r, w, v):
    """y_clean of the discrete loop u = C(r - y - v) + w, y = P u, by python-control."""
    t = np.arange(r.size) * P.dt
    T = ct.feedback(P * Cz, 1)
    PS = ct.feedback(P, Cz)
    return ct.forced_response(T, t, r - v).outputs + ct.forced_response(PS, t, w).outputs


def _nyquist_content(u, win=50):
    """Largest window mean of (-1)^k u(k): the amplitude of a persistent oscillation at the
    Nyquist frequency (a smooth signal averages out, an alternating one does not)."""
    s = (-1.0) ** np.arange(u.size) * u
    k = u.size // win * win
    return np.abs(s[:k].reshape(-1, win).mean(axis=1)).max()


@pytest.fixture(scope="module")
def b1_eval():
    return R.b1_evaluation_reference(0.1)


# --------------------------------------------------------------------------- loop properties
@pytest.mark.filterwarnings("ignore:stability_margins")
def test_linear_motor_controller_margins():
    s = LinearMotor()
    # |C P|(j wc) = 1 for the continuous nominal loop (how K is defined, SPEC §2.2)
    wc = 2 * np.pi * 20.0
    P_s = ct.tf([1.0], [s.m, s.f_v, 0.0])
    assert abs(complex((ct.tf(s._Cs) * P_s)(1j * wc))) == pytest.approx(1.0, rel=1e-9)
    L = s.controller() * ct.tf(s.linear_plant())
    gm, pm, sm, wg, wp, ws = ct.stability_margins(L)
    assert pm == pytest.approx(31.0, abs=3.0)                 # SPEC: ≈ 31°
    assert 1.0 / sm == pytest.approx(2.0, abs=0.2)            # SPEC: peak sensitivity ≈ 2.0
    assert wp / (2 * np.pi) == pytest.approx(20.0, rel=0.05)  # crossover 20 Hz
    assert np.all(np.abs(ct.poles(s.sensitivity())) < 1.0)    # closed loop stable
    # the Tustin controller has direct feedthrough (no computational delay)
    assert abs(float(np.squeeze(s._Cz.D))) > 0


@pytest.mark.filterwarnings("ignore:stability_margins")
def test_rot_trans_discretisation_and_loop():
    s = RotTransNMP()
    # the physical realisation is [B2] (27)
    G_ss, G_27 = ct.tf(s.continuous_ss()), s.continuous_tf()
    n1, d1 = np.asarray(G_ss.num[0][0], float), np.asarray(G_ss.den[0][0], float)
    n2, d2 = np.asarray(G_27.num[0][0], float), np.asarray(G_27.den[0][0], float)
    n1 = n1[np.argmax(np.abs(n1) > 1e-12 * np.abs(n1).max()):]
    np.testing.assert_allclose(n1 / d1[0], n2 / d2[0], rtol=1e-10)
    np.testing.assert_allclose(d1 / d1[0], d2 / d2[0], rtol=1e-10, atol=1e-9)
    assert np.max(np.real(ct.zeros(G_27))) == pytest.approx(80.9, abs=0.1)
    Gz = s.linear_plant()
    assert len(Gz.den[0][0]) == 5 and len(np.trim_zeros(Gz.num[0][0], "f")) == 4   # n_a=n_b=4, n_k=0
    z = ct.zeros(Gz)
    assert np.max(np.abs(z)) == pytest.approx(2.25, abs=0.01)                     # SPEC §2.3
    # the ARX θ of the physics model has the discretised plant's zeros
    zb = np.sort(np.real(s.physics.input_zeros(s.linear_theta())))
    assert zb == pytest.approx(np.sort(np.real(z)), rel=1e-9)
    gm, pm, sm, wg, wp, ws = ct.stability_margins(s.controller() * Gz)
    assert pm == pytest.approx(45.0, abs=2.0)                 # SPEC: ≈ 45°
    assert wp / (2 * np.pi) == pytest.approx(1.3, abs=0.1)    # crossover ≈ 1.3 Hz
    assert np.all(np.abs(ct.poles(s.sensitivity())) < 1.0)
    assert np.all(np.abs(ct.poles(s.process_sensitivity())) < 1.0)


# --------------------------------------------------------------------------- python-control
def test_linear_motor_continuous_matches_c2d(b1_eval):
    rng = np.random.default_rng(1)
    n = len(b1_eval)
    w, v = 20 * rng.standard_normal(n), 1e-6 * rng.standard_normal(n)
    s = LinearMotor(f_c=0.0, f_s=0.0, cogging=False, noise={"structure": "output", "std": 1e-6})
    sim = s.simulate(b1_eval.r, u_ff=0.5 * w, du=0.5 * w, v=v)
    y_ref = _closed_loop_reference(s.linear_plant(), s._Cz, b1_eval.r, w, v)
    assert np.max(np.abs(sim.y_clean - y_ref)) <= LINEAR_REL * np.max(np.abs(y_ref))
    np.testing.assert_array_equal(sim.y, sim.y_clean + v)


def test_linear_motor_equation_plant_matches_its_difference_equation(b1_eval):
    rng = np.random.default_rng(2)
    n = len(b1_eval)
    w = 20 * rng.standard_normal(n)
    s = LinearMotor(f_c=0.0, cogging=False, friction="sign", noise={"structure": "equation", "std": 0})
    sim = s.simulate(b1_eval.r, du=w)
    Ts, m, fv = s.Ts, s.m, s.f_v
    # y(t) = 2y(t-1) - y(t-2) + Ts²/m (u(t-1) - f_v (y(t-1) - y(t-2))/Ts)
    G = ct.ss(ct.tf([0.0, Ts ** 2 / m, 0.0], [1.0, -2.0 + Ts * fv / m, 1.0 - Ts * fv / m], Ts))
    y_ref = _closed_loop_reference(G, s._Cz, b1_eval.r, w, np.zeros(n))
    assert np.max(np.abs(sim.y_clean - y_ref)) <= LINEAR_REL * np.max(np.abs(y_ref))


def test_rot_trans_linear_matches_c2d():
    Rd = R.b2_training_reference()
    rng = np.random.default_rng(3)
    n = len(Rd)
    w, v = 20 * rng.standard_normal(n), 1e-6 * rng.standard_normal(n)
    s = RotTransNMP(c=0.0)
    sim = s.simulate(Rd.r, du=w, v=v)
    # reference built from the (27) transfer function, not from our realisation
    Pz = ct.ss(ct.sample_system(s.continuous_tf(), s.Ts, "zoh"))
    y_ref = _closed_loop_reference(Pz, ct.ss(s.controller()), Rd.r, w, v)
    assert np.max(np.abs(sim.y_clean - y_ref)) <= LINEAR_REL * np.max(np.abs(y_ref))
    # process sensitivity helper = the simulator's u_ff -> y map
    y_ps = ct.forced_response(s.process_sensitivity(), np.arange(n) * s.Ts, w).outputs
    y_sim = s.simulate(np.zeros(n), u_ff=w).y
    assert np.max(np.abs(y_sim - y_ps)) <= LINEAR_REL * np.max(np.abs(y_ps))


def test_arx_matches_python_control():
    s = ArxBias()
    rng = np.random.default_rng(4)
    sim = s.generate(500, rng)
    t = np.arange(500.0)
    G = ct.tf([1.0, 0.5], [1.0, -1.5, 0.7], 1.0)            # (z + 0.5)/(z² - 1.5z + 0.7)
    H = ct.tf([1.0, 0.0, 0.0], [1.0, -1.5, 0.7], 1.0)       # 1/A(q)
    y_ref = ct.forced_response(G, t, sim.u).outputs + ct.forced_response(H, t, sim.v).outputs
    np.testing.assert_allclose(sim.y, y_ref, rtol=0, atol=1e-12 * np.abs(y_ref).max())
    np.testing.assert_array_equal(sim.u_fb, 0.0)             # open loop


# --------------------------------------------------------------------------- causality, seeds
@pytest.mark.parametrize("make", [
    lambda: LinearMotor(noise={"structure": "output", "std": 0}),
    lambda: LinearMotor(noise={"structure": "equation", "std": 0}),
    lambda: RotTransNMP()])
def test_no_computational_delay(make):
    """u(k) responds to e(k) of the same sample: a reference step at k0 moves u_fb(k0) by
    D e(k0) (D = the controller's feedthrough), while y(k0) is still untouched."""
    s = make()
    n, k0 = 200, 50
    r0 = np.zeros(n)
    r1 = r0.copy()
    r1[k0:] = 1e-4
    a, b = s.simulate(r0), s.simulate(r1)
    D = float(np.squeeze(s._Cz.D))
    assert np.array_equal(a.y[:k0 + 1], b.y[:k0 + 1])          # y(k0) depends on u up to k0-1
    assert np.array_equal(a.u_fb[:k0], b.u_fb[:k0])
    assert b.u_fb[k0] - a.u_fb[k0] == pytest.approx(D * 1e-4, rel=1e-9)
    assert abs(D * 1e-4) > 1e-6


@pytest.mark.parametrize("make", [
    lambda: LinearMotor(noise={"structure": "output", "std": 1e-6}),
    lambda: LinearMotor(noise={"structure": "equation", "std": 1e-6}),
    lambda: RotTransNMP(),
    lambda: ArxBias()])
def test_same_seed_bit_identical(make):
    s = make()
    r = R.from_spec({"kind": "b2_R"}, s.Ts)[:300] if s.name != "arx_bias" else np.zeros(300)

    def run(seed):
        rng = np.random.default_rng(seed)
        du = rng.standard_normal(r.size)
        v = s.noise(r.size, rng)
        return s.simulate(r, du=du, v=v).as_dict()

    a, b, c = run(7), run(7), run(8)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert not np.array_equal(a["y"], c["y"])


# --------------------------------------------------------------------------- physics models
def test_arx_forward_ls_recovers_parameters_and_inverse_form():
    s = ArxBias(noise={"std": 0.0})
    sim = s.generate(2000, np.random.default_rng(5))
    theta = s.physics.fit(sim.y, sim.u)
    np.testing.assert_allclose(theta, s.theta0, rtol=1e-6)
    Phi, z = s.physics.inverse_regressor(sim.y, sim.u)
    np.testing.assert_allclose(least_squares(Phi, z), s.physics.inverse_theta(s.theta0), rtol=1e-6)
    np.testing.assert_allclose(s.physics.predict(theta, s.physics.phi(sim.y, sim.u)), sim.y,
                               atol=1e-10)


def test_arx_inverse_is_biased_under_noise_forward_is_not():
    """[B1] §II-C in miniature: with v ~ N(0, 0.1²) the forward LS error is small, the direct
    inverse estimate is biased well beyond its sampling spread."""
    s = ArxBias()
    sim = s.generate(100_000, np.random.default_rng(6))
    th_f = s.physics.fit(sim.y, sim.u)
    th_i = least_squares(*s.physics.inverse_regressor(sim.y, sim.u))
    err_f = np.linalg.norm(th_f - s.theta0)
    err_i = np.linalg.norm(th_i - s.physics.inverse_theta(s.theta0))
    assert err_f < 0.01
    assert err_i > 10 * err_f


def test_arx_exact_inverse_tracks():
    s = ArxBias(noise={"std": 0.0})
    r = R.b2_reference(1.0).r[:300]
    u = s.exact_inverse(r)
    sim = s.simulate(r, u_ff=u)
    np.testing.assert_allclose(sim.y, r, atol=1e-12)


def test_rot_trans_ls_recovers_linear_part_with_c0():
    Rd = R.b2_training_reference()
    rng = np.random.default_rng(8)
    du = 20 * rng.standard_normal(len(Rd))
    du[(Rd.t < 10) | (Rd.t >= 40)] = 0.0                   # [B2] §VI excitation window
    s = RotTransNMP(c=0.0, noise={"std": 0.0})
    sim = s.simulate(Rd.r, du=du)
    theta = s.physics.fit(sim.y, sim.u)
    np.testing.assert_allclose(theta, s.linear_theta(), rtol=1e-6)


def test_rot_trans_feedforward_is_not_stably_invertible_zpetc_is():
    s = RotTransNMP(c=0.0, noise={"std": 0.0})
    r = R.b2_reference().r
    with pytest.raises(ValueError, match=r"2\.25.*(?s:.*)fhofc"):
        s.physics.feedforward(s.linear_theta(), r)
    u = zpetc_feedforward(s.physics, s.linear_theta(), r)
    assert np.all(np.isfinite(u)) and np.abs(u).max() < 1e3
    e_ff = np.sqrt(np.mean((s.simulate(r, u_ff=u).y - r) ** 2))
    e_0 = np.sqrt(np.mean((s.simulate(r).y - r) ** 2))
    assert e_ff < 0.1 * e_0


def test_linear_motor_ls_recovers_parameters_in_model_class():
    """Equation plant, sign friction, cogging off, noise-free: [B1] (32) contains it."""
    ref = R.b1_training_reference()
    s = LinearMotor(cogging=False, friction="sign", noise={"structure": "equation", "std": 0.0})
    du = 50 * np.random.default_rng(9).standard_normal(len(ref))
    sim = s.simulate(ref.r, du=du)
    ph = s.physics
    assert not ph.averaged_input and ph.n_b == 1
    theta = ph.fit(sim.y, sim.u)
    np.testing.assert_allclose(theta, s.nominal_theta(), rtol=1e-6)
    phys = ph.physical(theta)
    assert phys["m"] == pytest.approx(20.0, rel=1e-6) and phys["f_c"] == pytest.approx(10.0, rel=1e-6)
    # inverse form: same parameters, physical units
    th_inv = least_squares(*ph.inverse_regressor(sim.y, sim.u))
    np.testing.assert_allclose(th_inv, [20.0, 50.0, 10.0], rtol=1e-6)
    # one-step predictor API (numpy and torch agree with the data)
    phi = ph.phi(sim.y, sim.u)
    np.testing.assert_allclose(ph.predict(theta, phi), sim.y, atol=1e-12)
    torch = pytest.importorskip("torch")
    yt = ph.predict(torch.as_tensor(theta), torch.as_tensor(phi))
    np.testing.assert_allclose(yt.numpy(), sim.y, atol=1e-12)


def test_linear_motor_exact_inverse_tracks_nonlinear_equation_plant(b1_eval):
    s = LinearMotor(noise={"structure": "equation", "std": 0.0})      # Stribeck + cogging on
    u = s.exact_inverse(b1_eval.r)
    sim = s.simulate(b1_eval.r, u_ff=u)
    assert np.max(np.abs(sim.y - b1_eval.r)) <= 1e-12
    with pytest.raises(NotImplementedError, match="ILC|ilc"):
        LinearMotor(noise={"structure": "output", "std": 0}).exact_inverse(b1_eval.r)


def test_sampling_pitfall_averaged_input_removes_mass_bias():
    """SPEC §2.2: on the continuous plant u(t-1) alone biases the forward mass ~2×; the
    averaged input ū(t-1) gets it within a few percent (friction stays biased: not in the
    model class)."""
    ref = R.b1_training_reference(duration=30.0)
    s = LinearMotor(noise={"structure": "output", "std": 0.0})
    du = 50 * np.random.default_rng(10).standard_normal(len(ref))
    sim = s.simulate(ref.r, du=du)
    m_avg = LinearMotorPhysics(s.Ts, averaged_input=True).physical(
        LinearMotorPhysics(s.Ts, True).fit(sim.y, sim.u))["m"]
    m_dir = LinearMotorPhysics(s.Ts, averaged_input=False).physical(
        LinearMotorPhysics(s.Ts, False).fit(sim.y, sim.u))["m"]
    assert m_avg == pytest.approx(20.0, rel=0.05)
    assert m_dir > 1.5 * 20.0


@pytest.mark.parametrize("vmax", R.B1_EVAL_VMAX)
def test_physics_feedforward_bounded_without_nyquist_oscillation(vmax):
    s = LinearMotor(noise={"structure": "output", "std": 0.0})
    ph = s.physics
    assert ph.averaged_input
    ref = R.b1_evaluation_reference(vmax)
    theta = s.nominal_theta()
    u = ph.feedforward(theta, ref.r)
    # |δ²r| ≤ a_max and |δr| ≤ v_max (means of r'' and r'), so |u_ff| ≤ m a + f_v v + f_c
    assert np.abs(u).max() <= s.m * 4.0 + s.f_v * vmax + s.f_c + 1e-9
    assert np.all(u[ref.t < 0.5 - 2e-3] == 0.0) and u[-1] == 0.0       # zero at rest
    ny = _nyquist_content(u)
    assert ny <= 0.02 * np.abs(u).max()
    # the detector does flag the sample-by-sample inversion u(t) = 2ū(t) - u(t-1) (pole at -1)
    m, f_v, f_c = ph.inverse_theta(theta)
    rp = np.concatenate([[0.0], ref.r, ref.r[-1:]])
    wbar = m * (rp[2:] - 2 * rp[1:-1] + rp[:-2]) / s.Ts ** 2 + f_v * np.diff(rp[:-1]) / s.Ts \
        + f_c * np.sign(np.diff(rp[:-1]))
    naive = np.zeros_like(wbar)
    for k in range(wbar.size):
        naive[k] = 2 * wbar[k] - (naive[k - 1] if k else 0.0)
    assert _nyquist_content(naive) > 5 * ny


def test_averaged_feedforward_tracks_continuous_mass_better(b1_eval):
    """On the frictionless continuous plant the averaged-input inverse (with the half-sample
    preview) tracks ≥ 5× better than the u(t-1) form (measured ~13×)."""
    s = LinearMotor(f_c=0.0, f_s=0.0, cogging=False, noise={"structure": "output", "std": 0})
    th = s.nominal_theta()
    e = {}
    for avg in (True, False):
        u = LinearMotorPhysics(s.Ts, avg).feedforward(th, b1_eval.r)
        e[avg] = np.max(np.abs(s.simulate(b1_eval.r, u_ff=u).y_clean - b1_eval.r))
    e_fb = np.max(np.abs(s.simulate(b1_eval.r).y_clean - b1_eval.r))
    assert e[True] < 0.2 * e[False] and e[False] < e_fb


def test_simulation_speed():
    """SPEC §2.2: the 120 s data set simulates in a few seconds (after numba compilation)."""
    ref = R.b1_training_reference()
    s = LinearMotor(noise={"structure": "output", "std": 1e-6})
    s.simulate(ref.r[:10])                                   # compile / load cache
    t0 = time.perf_counter()
    s.simulate(ref.r, du=50 * np.random.default_rng(0).standard_normal(len(ref)))
    assert time.perf_counter() - t0 < 10.0


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize("make", [lambda: LinearMotor(), lambda: RotTransNMP()])
def test_bad_inputs_raise_clear_errors(make):
    s = make()
    r = np.zeros(100)
    bad = r.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        s.simulate(bad)
    with pytest.raises(ValueError, match="samples"):
        s.simulate(r, u_ff=np.zeros(99))
    with pytest.raises(ValueError, match="1-D"):
        s.simulate(np.zeros((2, 50)))
    far = np.linspace(0.0, 0.6, 10_000)                      # slow but out of range
    with pytest.raises(ValueError, match="stroke|range"):
        s.simulate(far)
    fast = np.linspace(0.0, 0.1, 3)                          # within range, far too fast
    with pytest.raises(ValueError, match="too fast"):
        s.simulate(fast)


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="structure"):
        LinearMotor(noise={"structure": "colored", "std": 1e-6})
    with pytest.raises(ValueError, match="unknown key"):
        LinearMotor(noise={"sigma": 1e-6})
    with pytest.raises(ValueError, match="friction"):
        LinearMotor(friction="viscous")
    with pytest.raises(ValueError, match="structure"):
        RotTransNMP(noise={"structure": "equation", "std": 0})
    with pytest.raises(ValueError, match="m must be positive"):
        LinearMotor(m=0.0)
    with pytest.raises(ValueError, match="θ"):
        ARXPhysics(2, 2).feedforward([1.0, 2.0], np.zeros(5))
    with pytest.raises(ValueError, match="mass|1/m"):
        LinearMotorPhysics().feedforward([-1.0, 0.0, 0.0], np.zeros(5))


def test_configs_instantiate():
    hydra_utils = pytest.importorskip("hydra.utils")
    from omegaconf import OmegaConf
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[1] / "conf" / "system"
    for name, cls in [("linear_motor", LinearMotor), ("rot_trans_nmp", RotTransNMP),
                      ("arx_bias", ArxBias)]:
        s = hydra_utils.instantiate(OmegaConf.load(root / f"{name}.yaml"))
        assert isinstance(s, cls) and s.name == name
    # the config's defaults are the SPEC defaults the classes also carry
    s = hydra_utils.instantiate(OmegaConf.load(root / "rot_trans_nmp.yaml"))
    np.testing.assert_allclose(s.linear_theta(), RotTransNMP().linear_theta(), rtol=1e-12)
