"""One honest replay of a measured system (issue 20 item 3): the start from the recorded state,
the one integrator against the continuous-time model, the benchmark's open-loop R²."""
from __future__ import annotations

import control
import numpy as np
import pytest

from pipeline.identify.continuous_replay import replay_rk4
from pipeline.identify.measured_loop import (LoopModel, LoopSignals, _NO_FEEDBACK, benchmark_scores,
                                             loop_errors, simulate_loop, simulate_open_loop)
from pipeline.systems.controller import LTIController
from pipeline.systems.force_terms import ForceTerms
from pipeline.systems.measured import RigidBodyPhysics

TS = 1e-3


def _moving_record(n=3000, k_cut=700, delay=0):
    """A record of the physics loop (EMPS-like cascade, mass 95 kg, viscous + Coulomb) cut at
    sample k_cut, where the axis moves: the recorded start is in motion."""
    t = np.arange(n + k_cut) * TS
    r = 0.1 * (1 - np.cos(2 * np.pi * t / 2.0))
    phys = RigidBodyPhysics(TS, True, ForceTerms(("viscous", "coulomb")))
    th = phys.theta_from_physical({"M": 95.0, "F_v": 200.0, "F_c": 20.0})
    ctrl = LTIController.cascade(kp=160.18, kv=243.45, gtau=35.15, v_sat=10.0, Ts=TS, delay=delay)
    model = LoopModel.physics_only(phys, th)
    y, tau, _ = simulate_loop(model, ctrl, LoopSignals(r, np.zeros_like(r), 0.0, t))
    cut = slice(k_cut, None)
    return phys, th, ctrl, model, r[cut], y[cut], tau[cut], t[cut] - t[k_cut]


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_recorded_start_replays_its_own_record_exactly_and_rest_does_not(delay):
    """The model that made the record, replayed from the record's first 20 samples, reproduces it
    to rounding, whatever the controller's delay (the commands issued before the start and applied
    after it come from the record and the law); started at rest it carries a start-up transient."""
    phys, th, ctrl, model, r, y, tau, t = _moving_record(delay=delay)
    assert abs(y[1] - y[0]) / TS > 0.05                     # the record starts at > 5 cm/s
    d = np.zeros_like(r)
    yh, th_, _ = simulate_loop(model, ctrl, LoopSignals.recorded(r, d, y, tau, t, 20))
    e = loop_errors(y, tau, yh, th_, 20)
    assert e["force_rel_error"] < 1e-9 and e["loop_rmse_mm"] < 1e-9
    yr, tr, _ = simulate_loop(model, ctrl, LoopSignals(r, d, float(y[0]), t))
    assert loop_errors(y, tau, yr, tr, 20)["force_rel_error"] > 1.0   # percent: the transient of a rest start


def test_recorded_start_sensitivities_match_finite_differences():
    """∂τ̂/∂θ with the recorded history fixed (the training Jacobian from the recorded state)."""
    phys, th, ctrl, model, r, y, tau, t = _moving_record(800)
    th = th.copy()
    th[2] = 0.0                                   # smooth in θ (no Coulomb)
    sig = LoopSignals.recorded(r, np.zeros_like(r), y, tau, t, 20)
    m = LoopModel.physics_only(phys, th)
    _, tau0, _, _, St = simulate_loop(m, ctrl, sig, sens=True)
    assert np.all(St[:20] == 0)
    for p in range(th.size):
        h = 1e-4 * max(abs(th[p]), 0.1)            # θ2 = 0: step on the scale of F_c/M
        tp, tm = th.copy(), th.copy()
        tp[p] += h
        tm[p] -= h
        fd = (simulate_loop(m.with_theta(tp), ctrl, sig)[1] - simulate_loop(m.with_theta(tm), ctrl, sig)[1]) / (2 * h)
        # central differences: O(h²) truncation plus rounding of τ / h; a wrong chain term errs by O(1)
        assert np.linalg.norm(fd - St[:, p]) <= 1e-4 * np.linalg.norm(fd) + 1e-12 * np.linalg.norm(tau0) / h, p


def test_rk4_replay_converges_to_the_exact_zoh_solution_of_the_linear_body():
    """Mass + viscous friction, open loop (u enters as the disturbance): RK4 with n sub-steps
    against python-control's exact ZOH discretisation of 1/(M s² + F_v s), started from the
    recorded state at rest.  The time constant M/F_v = 2.5 ms is near Ts, so the one-step error
    is visible and must fall as n⁻⁴ (RK4; ≥ 8x per halving allows the last halvings' rounding)."""
    M, Fv = 1.0, 400.0
    phys = RigidBodyPhysics(TS, True, ForceTerms(("viscous",)))
    th = phys.theta_from_physical({"M": M, "F_v": Fv})
    n = 2000
    u = np.repeat(np.random.default_rng(1).normal(0, 50, n // 20), 20)
    u[:20] = 0.0                      # at rest for the first 20 samples: the recorded velocity at 19 is 0
    sysd = control.c2d(control.ss(control.tf([1.0], [M, Fv, 0.0])), TS, "zoh")
    y = control.forced_response(sysd, T=np.arange(n) * TS, U=u).outputs
    sig = LoopSignals.recorded(np.zeros(n), u, y, u, None, 20)
    errs = []
    for ns in (1, 2, 4, 8):
        y_c, _ = replay_rk4(phys, th, _NO_FEEDBACK, sig, ns)
        errs.append(np.max(np.abs(y_c - y)) / np.max(np.abs(y)))
    assert errs[0] > 1e-6                                     # the one-step error is there to be seen
    assert errs[1] < errs[0] / 8 and errs[2] < errs[1] / 8 and errs[3] < errs[2] / 8
    assert errs[3] < 1e-6


def test_benchmark_r2_and_rmse():
    """R² = 1 for the record itself, 0 for its mean; RMSE in mm over the samples after the first 20."""
    y = np.sin(np.linspace(0, 6, 500))
    assert benchmark_scores(y, y)["benchmark_r2"] == 1.0
    s = benchmark_scores(y, np.full_like(y, y[20:].mean()))
    assert abs(s["benchmark_r2"]) < 1e-12
    assert abs(s["benchmark_rmse_mm"] - 1e3 * y[20:].std()) < 1e-9


def test_open_loop_from_the_record_is_exact_for_the_model_that_made_it():
    phys, th, ctrl, model, r, y, tau, t = _moving_record()
    y_ol = simulate_open_loop(model, tau, float(y[0]), y, 20)
    assert benchmark_scores(y, y_ol)["benchmark_r2"] > 1 - 1e-12
    assert benchmark_scores(y, simulate_open_loop(model, tau, float(y[0])))["benchmark_r2"] < 0.99   # rest start


def test_bad_recorded_start_is_named():
    phys, th, ctrl, model, r, y, tau, t = _moving_record(200)
    with pytest.raises(ValueError, match="needs y_rec and u_rec"):
        LoopSignals(r, np.zeros_like(r), 0.0, t, n_init=5)
    with pytest.raises(ValueError, match="whole history"):
        simulate_loop(model, ctrl, LoopSignals.recorded(r, np.zeros_like(r), y, tau, t, 1))
    with pytest.raises(ValueError, match="starts at rest"):
        simulate_loop(model, ctrl, LoopSignals.recorded(r, np.zeros_like(r), y, tau, t, 20), "published")


def test_sim_error_fit_over_several_records_recovers_the_loop():
    """Two recordings (data.files), each simulated from its own recorded state: the closed-loop
    simulation-error LM from a 10 %-off start returns the θ that made both to 1e-6 relative."""
    import torch
    from pipeline.identify.measured_loop import identify_loop_sim_error
    from pipeline.models.pgnn import PGNN
    from pipeline.models.physics_maps import physics_features_for
    phys, th, ctrl, model, r, y, tau, t = _moving_record(1500, k_cut=700)
    _, _, _, _, r2, y2, tau2, t2 = _moving_record(1200, k_cut=1500)
    sigs = [LoopSignals.recorded(a, np.zeros_like(a), b, c, tt, 20)
            for a, b, c, tt in ((r, y, tau, t), (r2, y2, tau2, t2))]
    pg = PGNN(2, 1, 0, structure="invertible", physics=physics_features_for(phys, "forward", 2, 1, 0, True),
              hidden=(), use_nn=False)
    with torch.no_grad():
        pg.theta_phy.copy_(torch.as_tensor(th * np.array([1.1, 0.9, 1.1])))
    fit = identify_loop_sim_error(pg, True, ctrl, sigs, [tau, tau2], n_train=[1200, 1000], max_iter=100,
                                  ftol=1e-14, gtol=1e-14)
    np.testing.assert_allclose(fit.loop.theta_phy, th, rtol=1e-6)
    assert fit.n_train == 2200 and fit.tau_hat.size == tau.size + tau2.size
    assert fit.val_force_rel_error < 1e-6


def test_recorded_start_holds_an_iir_controllers_state():
    """A filtered PID (IIR, integrating) with a delay of 2: the replay from the record's first 20
    samples reproduces the record (the filter's state and the commands in flight come from it)."""
    M, Fv = 12.0, 40.0
    phys = RigidBodyPhysics(5e-4, True, ForceTerms(("viscous",)))
    th = phys.theta_from_physical({"M": M, "F_v": Fv})
    ctrl = LTIController.lti(num=[4.279e6, -8.212e6, 3.939e6], den=[1.0, -1.4361, 0.4361], num_r=None,
                             gtau=1.0, v_sat=1e9, delay=2)
    n = 4000
    t = np.arange(n) * 5e-4
    r = 0.05 * np.sin(2 * np.pi * 1.0 * t) ** 2
    model = LoopModel.physics_only(phys, th)
    y, tau, _ = simulate_loop(model, ctrl, LoopSignals(r, np.zeros(n), 0.0, t))
    cut = slice(1500, None)
    sig = LoopSignals.recorded(r[cut], np.zeros(n - 1500), y[cut], tau[cut], t[cut], 20)
    yh, th_, _ = simulate_loop(model, ctrl, sig)
    assert loop_errors(y[cut], tau[cut], yh, th_, 20)["force_rel_error"] < 1e-8


def test_rk4_replay_of_a_mass_equals_the_one_step_replay_from_a_noisy_record():
    """For a pure mass the one-step (ZOH on ū) replay is exact, so the RK4 replay must equal it
    from the same recorded start, even when the record's positions carry noise: both start from the
    state the record implies (the integrator check compares integrators, not start states)."""
    phys = RigidBodyPhysics(TS, True, ForceTerms(("viscous",)))
    th = phys.theta_from_physical({"M": 95.0, "F_v": 0.0})
    _, _, ctrl, _, r, y, tau, t = _moving_record(1500)
    y = y + np.random.default_rng(3).normal(0, 1e-6, y.size)        # 1 µm position noise
    sig = LoopSignals.recorded(r, np.zeros_like(r), y, tau, t, 20)
    _, tau1, _ = simulate_loop(LoopModel.physics_only(phys, th), ctrl, sig)
    for n in (1, 16):
        _, tau_c = replay_rk4(phys, th, ctrl, sig, n)
        assert np.linalg.norm(tau_c - tau1) <= 1e-9 * np.linalg.norm(tau1), n


def test_a_disturbance_step_at_the_first_scored_sample_counts():
    """The force-error share after disturbance steps, scored from sample 20: a step exactly at 20
    is a step (found on the whole record, then windowed), like one later on."""
    from stages.evaluate import _after_disturbance_edges
    tau, tau_hat = np.ones(100), np.zeros(100)
    for k in (20, 50):
        d = np.zeros(100)
        d[k:] = 1.0
        assert _after_disturbance_edges(d, tau, tau_hat, 5, 20)["data/force_error_share_after_steps"] == 5 / 80
