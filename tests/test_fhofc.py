"""FHOFC [B2] (17)/(18), IL-FHOFC (22), linear ILC (23), Lemmas 5.1/5.2, and the (15) bound terms."""
from __future__ import annotations

import control
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.optimize as so

from pipeline.models.closed_loop import ArxPGNN, DiscreteController, arx_from_tf, simulate_closed_loop
from pipeline.invert.fhofc import (difference_matrix, fhofc, fhofc_receding, il_fhofc, linear_ilc)
from pipeline.invert.ilc import lifted_matrix, process_sensitivity
from pipeline.metrics_bound import (bound_holds, bound_terms, epsilon, identification_error,
                                    inversion_error, normalised_norm)
from pipeline.systems.rot_trans_nmp import RotTransNMP

Ts_MP = 0.01


@pytest.fixture(scope="module")
def mp():
    """Minimum-phase loop: the ARX of SPEC §2.4 (zero at z = -0.5) with a stable lead controller."""
    G = control.tf([1.0, 0.5], [1.0, -1.5, 0.7], Ts_MP)
    C = control.tf([0.3, -0.2], [1.0, -0.5], Ts_MP)
    assert np.all(np.abs(control.poles(control.feedback(G * C, 1))) < 1)
    theta, orders = arx_from_tf(G)
    return ArxPGNN(*orders, theta), DiscreteController.from_tf(C), G, C


@pytest.fixture(scope="module")
def nmp():
    """rot_trans_nmp: its ZOH linear part (zero at z ≈ 2.25), controller and plant."""
    plant = RotTransNMP(noise={"structure": "output", "std": 0.0})
    theta, orders = arx_from_tf(plant.linear_plant())
    return ArxPGNN(*orders, theta), DiscreteController.from_tf(plant.controller()), plant


def smooth_move(N, amp):
    """A smooth move that starts at rest (r(0) = 0) [m]."""
    t = np.arange(N) / (N - 1)
    return amp * (1 - np.cos(np.pi * t)) / 2


def nonlinear_mp_model(lin: ArxPGNN, seed=0, n1=5, out_scale=0.02) -> ArxPGNN:
    """The minimum-phase ARX plus a small tanh layer, zero at rest (ŷ = 0 for φ = 0)."""
    rng = np.random.default_rng(seed)
    W1 = rng.uniform(-1, 1, (n1, lin.n_phi))
    b1 = rng.uniform(-0.5, 0.5, n1)
    W2 = rng.uniform(-1, 1, n1)
    b2 = -float(W2 @ np.tanh(b1))
    return ArxPGNN(lin.n_a, lin.n_b, lin.n_k, lin.theta_phy, W1, b1, W2, b2, out_scale=out_scale)


def inverse_model_feedforward(model: ArxPGNN, r):
    """[B2] (20): u_ff(k) solving r(k+n_k+1) = f(θ, [r(k+n_k)..., u_ff(k), u_ff(k-1), ...]) per sample
    (brentq on the scalar one-step model; n_k = 0, unique root); u_ff(N-1) = u_ff(N-2)."""
    N = r.shape[0]
    u = np.zeros(N)
    for k in range(N - 1):
        def f(uk):
            phi = np.zeros(model.n_phi)
            for i in range(1, model.n_a + 1):
                phi[i - 1] = r[k + 1 - i] if k + 1 - i >= 0 else 0.0
            for i in range(1, model.n_b + 1):
                j = k + 1 - i
                phi[model.n_a + i - 1] = uk if j == k else (u[j] if j >= 0 else 0.0)
            return model.one_step(phi[None, :])[0] - r[k + 1]
        # linear part alone gives the bracket centre; widen until the sign changes
        c = f(0.0)
        g = model.theta_phy[model.n_a]
        u0 = -c / g
        w = 1.0 + abs(u0)
        while f(u0 - w) * f(u0 + w) > 0:
            w *= 2
        u[k] = so.brentq(f, u0 - w, u0 + w, xtol=1e-15 * max(1.0, abs(u0)), rtol=1e-15, maxiter=500)
    u[N - 1] = u[N - 2]
    return u


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


# ---------------------------------------------------------------------------- Lemma 5.1
@pytest.mark.parametrize("case", ["mp_linear", "mp_pgnn", "nmp_linear"])
def test_lemma_5_1_receding_horizon_is_inverse_model(case, mp, nmp):
    """Receding-horizon FHOFC (18), h = n_k + 1, Γ = 0 equals the inverse-model feedforward (20)."""
    if case.startswith("mp"):
        lin, ctrl = mp[0], mp[1]
        model = lin if case == "mp_linear" else nonlinear_mp_model(lin)
        r, N = smooth_move(60, 1.0), 60
    else:
        model, ctrl = nmp[0], nmp[1]
        N = 30
        r = smooth_move(N, 1e-3)
    res = fhofc_receding(model, ctrl, r, h=model.n_k + 1, gamma=0.0, check_range=False)
    u_inv = inverse_model_feedforward(model, r)
    assert res.converged
    assert rel(res.u_ff[:-1], u_inv[:-1]) <= 1e-8
    # and the model then tracks with zero feedback: û = u_ff, ŷ = r
    assert np.max(np.abs(res.y_hat - r)) <= 1e-8 * np.max(np.abs(r)) * (1 if case != "nmp_linear" else 1e3)
    if case == "mp_pgnn":   # the NN matters: the linear inverse is different
        assert rel(inverse_model_feedforward(mp[0], r)[:-1], u_inv[:-1]) > 1e-3


# ---------------------------------------------------------------------------- FHOFC = lifted LS
def lifted_problem(G, C, r, N):
    """Free response T r and lifted PS from python-control / pipeline.invert.ilc (independent of
    the closed-loop model simulation)."""
    t = np.arange(N) * G.dt
    T = control.feedback(G * C, 1)
    y0 = control.forced_response(T, t, r).outputs
    return y0, lifted_matrix(process_sensitivity(G, C), N)


@pytest.mark.parametrize("case,gamma", [("mp", 0.0), ("mp", 1e-3), ("nmp", 0.0), ("nmp", 1e-6)])
def test_fhofc_linear_equals_lifted_least_squares(case, gamma, mp, nmp):
    """FHOFC on a linear model = argmin ‖R - Y0 - G U‖² + γ²‖ΔU‖² from the lifted matrix (1e-8)."""
    if case == "mp":
        model, ctrl, G, C = mp
        N = 300
        r = smooth_move(N, 1.0)
    else:
        model, ctrl, plant = nmp
        G, C = plant.linear_plant(), plant.controller()
        N = 30 if gamma == 0 else 300
        r = smooth_move(N, 0.1)
    res = fhofc(model, ctrl, r, gamma=gamma, check_range=False)
    y0, Gl = lifted_problem(G, C, r, N)
    if gamma == 0:
        # ŷ(0) and u_ff(N-1) are decoupled (one sample delay): the least-squares solution is the
        # square lower-triangular block solved exactly, with the free u_ff(N-1) at its minimum
        # norm 0.  (A dense SVD solve loses cond·eps ≈ 1e-8 at N = 30 on the NMP loop.)
        u_ls = np.r_[sla.solve_triangular(Gl[1:, :-1], (r - y0)[1:], lower=True), 0.0]
        if case == "mp":
            assert rel(np.linalg.lstsq(Gl, r - y0, rcond=None)[0], u_ls) <= 1e-10
    else:
        A = np.vstack([Gl, gamma * difference_matrix(N)])
        b = np.concatenate([r - y0, np.zeros(N)])
        u_ls = np.linalg.lstsq(A, b, rcond=None)[0]
    assert res.converged, res.message
    assert rel(res.u_ff, u_ls) <= 1e-8, res.message


def test_fhofc_pgnn_speed_and_optimality(nmp):
    """FHOFC on an NMP PGNN (N_k = 300, n1 = 32): converges, gradient ~ 0, inversion error far
    below the linear model's on the PGNN, and well under the 0.5 s target (B2d; loose bound here)."""
    lin, ctrl, plant = nmp
    rng = np.random.default_rng(0)
    n1 = 32
    m = ArxPGNN(4, 4, 0, lin.theta_phy, rng.uniform(-0.5, 0.5, (n1, 8)), rng.uniform(-0.5, 0.5, n1),
                rng.uniform(-1, 1, n1), 0.0, nn_P=np.diag(1 / np.r_[np.full(4, 0.05), np.full(4, 20.0)]),
                out_scale=2e-8)
    from pipeline.references import b2_reference
    r = b2_reference(plant.Ts).r
    fhofc(m, ctrl, r, gamma=1e-6)                      # compile
    res = fhofc(m, ctrl, r, gamma=1e-6)
    assert res.converged and res.time_s < 2.0, (res.message, res.time_s)
    # first-order optimality of the smooth problem: Jᵀ res ≈ 0 relative to its initial size
    from pipeline.models.closed_loop import jacobian_uff
    y, _, J, _ = jacobian_uff(m, ctrl, r, res.u_ff)
    D = difference_matrix(r.size)
    g = -J.T @ (r - y) + 1e-12 * D.T @ (D @ res.u_ff)
    _, _, J0, _ = jacobian_uff(m, ctrl, r, np.zeros(r.size))
    y_0, _ = simulate_closed_loop(m, ctrl, r, np.zeros(r.size))
    g0 = -J0.T @ (r - y_0)
    assert np.linalg.norm(g) <= 1e-6 * np.linalg.norm(g0)
    # the linear model's feedforward leaves a larger inversion error on the PGNN
    lin_ff = fhofc(lin, ctrl, r, gamma=1e-6).u_ff
    y_lin, _ = simulate_closed_loop(m, ctrl, r, lin_ff)
    assert res.inversion_error < 0.5 * inversion_error(r, y_lin)


# ---------------------------------------------------------------------------- Lemma 5.2
@pytest.mark.parametrize("case", ["mp", "nmp"])
def test_lemma_5_2_il_fhofc_is_linear_ilc(case, mp, nmp):
    """IL-FHOFC (22) with a linear model and Γ = 0 applies the ILC update (23) (1e-8 relative)."""
    if case == "mp":
        model, ctrl = mp[0], mp[1]
        N = 60
        r = smooth_move(N, 1.0)
        true = nonlinear_mp_model(ArxPGNN(2, 2, 0, model.theta_phy * [1.0, 1.0, 1.1, 0.9]), seed=1)
    else:
        model, ctrl = nmp[0], nmp[1]
        N = 30
        r = smooth_move(N, 1e-3)
        true = ArxPGNN(4, 4, 0, model.theta_phy * np.r_[np.ones(4), np.full(4, 1.05)])

    def plant(u):
        return simulate_closed_loop(true, ctrl, r, u)[0]

    for alpha in (1.0, 0.5):
        a = il_fhofc(model, ctrl, r, plant, n_trials=4, alpha=alpha, gamma=0.0, check_range=False)
        b = linear_ilc(model, ctrl, r, plant, n_trials=4, alpha=alpha, u_ff0=a.u_ff[0])
        for i in range(4):
            assert rel(a.u_ff[i], b.u_ff[i]) <= 1e-8, (alpha, i)
        # errors are compared to the first trial's: late trials reach the rounding of huge NMP inputs
        assert np.max(np.abs(a.e_rms - b.e_rms)) <= 1e-6 * a.e_rms[0]
        assert a.e_rms[-1] < 0.3 * a.e_rms[0]


def test_il_fhofc_converges_on_mismatched_plant(mp):
    """IL-FHOFC with γ > 0 on a nonlinear, mismatched plant: the error falls by orders of magnitude."""
    model, ctrl = mp[0], mp[1]
    r = smooth_move(200, 1.0)
    true = nonlinear_mp_model(ArxPGNN(2, 2, 0, model.theta_phy * [1.0, 1.0, 1.2, 0.8]), seed=2)
    out = il_fhofc(model, ctrl, r, lambda u: simulate_closed_loop(true, ctrl, r, u)[0], n_trials=8,
                   alpha=1.0, gamma=1e-6, check_range=False)
    assert out.e_rms[-1] < 1e-4 * out.e_rms[0]
    assert np.all(np.diff(out.e_rms) < 0)


# ---------------------------------------------------------------------------- constraints
def test_uff_bounds_equal_bounded_least_squares(mp):
    """Box bounds on U_ff with a linear model = scipy's bounded linear least squares."""
    model, ctrl, G, C = mp
    N = 100
    r = smooth_move(N, 1.0)
    free = fhofc(model, ctrl, r, gamma=1e-3, check_range=False)
    hi = 0.6 * np.max(free.u_ff)
    res = fhofc(model, ctrl, r, gamma=1e-3, uff_bounds=(None, hi), check_range=False)
    y0, Gl = lifted_problem(G, C, r, N)
    A = np.vstack([Gl, 1e-3 * difference_matrix(N)])
    b = np.concatenate([r - y0, np.zeros(N)])
    ref = so.lsq_linear(A, b, bounds=(-np.inf, hi), tol=1e-14, lsmr_tol="auto", method="bvls")
    assert res.feasible and np.max(res.u_ff) <= hi + 1e-12
    assert np.sum(res.u_ff > hi - 1e-9) >= 1                      # a bound is active
    np.testing.assert_allclose(res.cost, 2 * ref.cost, rtol=1e-6)  # lsq_linear cost = ½‖·‖²
    assert rel(res.u_ff, ref.x) <= 1e-5


def test_u_bounds_on_total_input(mp):
    """Bounds on Û: respected at the solution, cost no lower than unconstrained; infeasible → flagged."""
    model, ctrl = mp[0], mp[1]
    N = 60
    r = smooth_move(N, 1.0)
    free = fhofc(model, ctrl, r, gamma=1e-3, check_range=False)
    hi = 0.7 * np.max(free.u_hat)
    res = fhofc(model, ctrl, r, gamma=1e-3, u_bounds=(-np.inf, hi), check_range=False, max_iter=200)
    assert res.feasible and res.converged, res.message
    assert np.max(res.u_hat) <= hi * (1 + 1e-8)
    assert res.cost >= free.cost
    # |u_ff| ≤ 1e-3 and |û| ≤ 1e-6 contradict each other on a 1 m move: the feedback alone exceeds it
    bad = fhofc(model, ctrl, r, gamma=1e-3, uff_bounds=(-1e-3, 1e-3), u_bounds=(-1e-6, 1e-6), check_range=False,
                max_iter=50)
    assert not bad.converged and not bad.feasible


def test_bad_input(mp):
    model, ctrl = mp[0], mp[1]
    r = smooth_move(50, 1.0)
    with pytest.raises(ValueError, match="infeasible"):
        fhofc(model, ctrl, r, uff_bounds=(1.0, -1.0), check_range=False)
    ranged = ArxPGNN(2, 2, 0, model.theta_phy, y_range=(0.0, 0.2))
    with pytest.raises(ValueError, match="validity range"):
        fhofc(ranged, ctrl, r)
    with pytest.raises(ValueError, match="max_horizon"):
        fhofc(model, ctrl, smooth_move(6000, 1.0), check_range=False)
    with pytest.raises(ValueError, match="gamma"):
        fhofc(model, ctrl, r, gamma=-1.0, check_range=False)
    unstable = ArxPGNN(2, 2, 0, np.array([2.5, -0.5, 1.0, 0.5]))
    with pytest.raises(ValueError, match="diverges"):
        fhofc(unstable, ctrl, smooth_move(5000, 1.0), check_range=False)
    with pytest.raises(ValueError, match="alpha"):
        il_fhofc(model, ctrl, r, lambda u: r, n_trials=2, alpha=1.5)
    with pytest.raises(ValueError, match="finite output"):
        il_fhofc(model, ctrl, r, lambda u: r[:-1], n_trials=1, check_range=False)
    with pytest.raises(ValueError, match="linear model"):
        linear_ilc(ArxPGNN(2, 2, 0, model.theta_phy, np.ones((2, 4))), ctrl, r, lambda u: r, n_trials=1)


def test_fhofc_flags_non_convergence(nmp):
    """max_iter reached on a nonlinear problem → converged False, best iterate returned."""
    lin, ctrl, plant = nmp
    rng = np.random.default_rng(1)
    m = ArxPGNN(4, 4, 0, lin.theta_phy, rng.uniform(-1, 1, (8, 8)), rng.uniform(-1, 1, 8), rng.uniform(-1, 1, 8),
                0.0, nn_P=np.diag(1 / np.r_[np.full(4, 0.05), np.full(4, 20.0)]), out_scale=1e-7)
    r = smooth_move(300, 0.1)
    res = fhofc(m, ctrl, r, gamma=1e-6, max_iter=1, check_range=False)
    assert not res.converged and res.message == "max_iter"
    assert res.history[-1] < res.history[0]


# ---------------------------------------------------------------------------- (15) bound terms
def test_bound_terms_closed_form():
    r = np.array([1.0, 2.0, 3.0, 4.0])
    y = np.array([1.0, 2.0, 3.0, 2.0])
    y_hat = np.array([1.0, 2.0, 2.0, 4.0])
    y_d = np.array([0.0, 1.0])
    y_hat_d = np.array([0.0, 0.0])
    t = bound_terms(r, y, y_hat, y_d, y_hat_d)
    assert t["tracking_error"] == pytest.approx(2.0 / 2.0)               # ‖[0,0,0,2]‖/2
    assert t["inversion_error"] == pytest.approx(1.0 / 2.0)              # ‖[0,0,1,0]‖/2
    assert t["identification_error"] == pytest.approx(1.0 / np.sqrt(2))  # ‖[0,1]‖/√2
    assert t["model_error"] == pytest.approx(np.sqrt(5) / 2)             # ‖[0,0,1,-2]‖/2
    assert t["epsilon"] == pytest.approx(np.sqrt(5) / 2 - 1 / np.sqrt(2))
    assert t["bound_holds"] and t["slack"] == pytest.approx(0.5 + np.sqrt(5) / 2 - 1.0)
    assert normalised_norm([3.0, -4.0], p=np.inf) == 4.0
    assert normalised_norm([3.0, 4.0], p=1) == 3.5


@pytest.mark.parametrize("p", [1, 2, 3, np.inf])
def test_bound_15_holds_on_random_data(p):
    """(15) is the triangle inequality: it holds for every draw, also with N_d ≠ N_k."""
    rng = np.random.default_rng(7)
    for _ in range(500):
        nk, nd = rng.integers(1, 50), rng.integers(1, 80)
        scale = 10.0 ** rng.uniform(-9, 2)
        r, y, yh = (scale * rng.standard_normal(nk) for _ in range(3))
        yd, yhd = (scale * rng.standard_normal(nd) for _ in range(2))
        t = bound_terms(r, y, yh, yd, yhd, p=p)
        assert t["bound_holds"]
        assert t["epsilon"] == epsilon(y, yh, yd, yhd, p)
        assert t["identification_error"] == identification_error(yd, yhd, p)
    # a violated inequality is reported as such
    assert not bound_holds(tracking=1.0, inversion=0.3, identification=0.3, eps=0.3)


def test_bound_terms_bad_input():
    with pytest.raises(ValueError, match="one length"):
        bound_terms(np.ones(3), np.ones(4), np.ones(3), np.ones(2), np.ones(2))
    with pytest.raises(ValueError, match="NaN"):
        inversion_error(np.ones(3), np.array([1.0, np.nan, 1.0]))


@pytest.mark.parametrize("case", ["mp_linear", "mp_pgnn", "nmp_linear"])
def test_inverse_model_feedforward_matches_root_finding(case, mp, nmp):
    """The library's per-sample Newton inverse (20) equals an independent brentq root search."""
    from pipeline.invert.fhofc import inverse_model_feedforward as lib_inverse
    if case.startswith("mp"):
        model = mp[0] if case == "mp_linear" else nonlinear_mp_model(mp[0])
        r = smooth_move(60, 1.0)
    else:
        model, r = nmp[0], smooth_move(30, 1e-3)
    assert rel(lib_inverse(model, r), inverse_model_feedforward(model, r)) <= 1e-12


def test_lemma_gap_functions(mp, nmp):
    """The library's Lemma checks (used by the B2e report rows) agree with the tests above."""
    from pipeline.invert.fhofc import lemma_5_1_gap, lemma_5_2_gap
    lin, ctrl = nmp[0], nmp[1]
    r = smooth_move(30, 1e-3)
    assert lemma_5_1_gap(lin, ctrl, r) <= 1e-8
    true = ArxPGNN(4, 4, 0, lin.theta_phy * np.r_[np.ones(4), np.full(4, 1.05)])
    assert lemma_5_2_gap(lin, ctrl, r, lambda u: simulate_closed_loop(true, ctrl, r, u)[0]) <= 1e-8
    # a model that is not the one inverted: the gap is large (the check can fail)
    other = ArxPGNN(4, 4, 0, lin.theta_phy * np.r_[np.ones(4), np.full(4, 1.01)])
    from pipeline.invert.fhofc import inverse_model_feedforward, fhofc_receding
    u_rh = fhofc_receding(lin, ctrl, r, h=1, check_range=False).u_ff
    assert rel(u_rh[:-1], inverse_model_feedforward(other, r)[:-1]) > 1e-3


# ---------------------------------------------------------------------------- pipeline stages
B2_SMALL = ["experiment=b2_rot_trans", "data.references=[{name:R_d,kind:b2_R,repeats:3}]",
            "data.excitation.t_start=3.0", "data.excitation.t_stop=6.0", "model.hidden=[2]",
            "identify.max_iter=3", "identify.linear_max_iter=3"]


@pytest.mark.slow
def test_b2_stages_run_and_log_bound_terms(store, cfg_of):
    """train=sim_error → invert=fhofc → evaluate on a short record; the (15) terms are logged and
    consistent with the evaluate stage's tracking error; IL-FHOFC logs one rms per trial."""
    from pipeline import runner
    out = runner.run_job(cfg_of(*B2_SMALL))
    tr = out["train"]
    assert tr["arx"].n1 == 2 and tr["y_d"].shape == tr["y_hat_d"].shape == (900,)
    assert tr["identification_error"] == pytest.approx(
        np.linalg.norm(tr["y_d"] - tr["y_hat_d"]) / np.sqrt(900), rel=1e-12)
    import mlflow
    runs = mlflow.search_runs(experiment_names=["b2_rot_trans"])
    m = runs.iloc[0]
    assert m["metrics.invert/R/bound/bound_holds"] == 1.0
    assert m["metrics.invert/R/bound/identification_error"] == pytest.approx(tr["identification_error"])
    # evaluate noise = same realisation: its rms of r - y_clean is close to the measured tracking error
    assert m["metrics.invert/R/bound/tracking_error"] == pytest.approx(m["metrics.evaluate/R/rms"], rel=0.05)
    il = runner.run_job(cfg_of(*B2_SMALL, "invert=il_fhofc", "invert.n_trials=2", "invert.trial_noise=false"))
    assert il["invert"]["u_ff"]["R"].shape == (300,)
    hist = mlflow.MlflowClient().get_metric_history(
        mlflow.search_runs(experiment_names=["b2_rot_trans"]).iloc[0]["run_id"], "invert/R/trial_rms")
    assert len(hist) == 2 and hist[1].value < hist[0].value


@pytest.mark.parametrize("override,message", [
    ("identify=narx", "identify.kind=sim_error"),
    ("model.hidden=[4,4]", "one tanh hidden layer"),
    ("identify.theta_star=ls", "theta_star"),
    ("invert.gamma=-1", "gamma"),
])
def test_b2_bad_config_fails_before_work(store, cfg_of, override, message):
    from pipeline import runner
    base = [o for o in B2_SMALL if not o.startswith("identify.")] if override.startswith("identify=") else B2_SMALL
    with pytest.raises(runner.ConfigError, match=message):
        runner.run_job(cfg_of(*base, override))


@pytest.mark.parametrize("gamma", [0.3, 1.0])
def test_gamma_floor_of_il_fhofc_is_the_regularised_optimum(gamma, mp):
    """Issue 11: with the plant's true linear part as model, IL-FHOFC (22) (α = 1) sits at the
    closed-form regularised optimum u* = argmin ‖R - Y0 - G U‖² + γ²‖ΔU‖² in every trial: its rms
    error is the γ-floor no model can beat (Γ penalises U_ff itself, not its change); 1e-8."""
    model, ctrl, G, C = mp
    N = 200
    r = smooth_move(N, 1.0)
    out = il_fhofc(model, ctrl, r, lambda u: simulate_closed_loop(model, ctrl, r, u)[0], n_trials=4,
                   alpha=1.0, gamma=gamma, check_range=False)
    y0, Gl = lifted_problem(G, C, r, N)
    u_star = np.linalg.lstsq(np.vstack([Gl, gamma * difference_matrix(N)]),
                             np.concatenate([r - y0, np.zeros(N)]), rcond=None)[0]
    floor = np.linalg.norm(r - y0 - Gl @ u_star) / np.sqrt(N)
    assert floor > 3e-7                                   # γ > 0 leaves a visible error (R peaks at 1)
    assert np.max(np.abs(out.e_rms / floor - 1)) <= 1e-8
    assert rel(out.u_ff[-1], u_star) <= 1e-8


def test_receding_horizon_backtracks_an_overshooting_gauss_newton_step():
    """ŷ(k) = 1e-3·u(k-1) + tanh(u(k-1)), no feedback: from u = 2.773 (ŷ = 0.995) the undamped Gauss–Newton step
    toward r = 0 overshoots (tanh is flat there). The window solve took that failed first step for a minimum and
    reported converged with u stuck at 2.773 and |e| = 0.995; halving the step reaches the exact inverse, as the
    whole-horizon FHOFC and the inverse-model feedforward (Lemma 5.1) do."""
    from pipeline.invert.fhofc import fhofc_receding, inverse_model_feedforward
    m = ArxPGNN(0, 1, 0, np.array([1e-3]), W1=np.array([[1.0]]), b1=np.zeros(1), W2=np.ones(1), b2=0.0,
                out_scale=1.0)
    r = np.r_[0.0, 0.995 * np.ones(10), np.zeros(10)]
    res = fhofc_receding(m, DiscreteController.from_tf(None), r, h=1, check_range=False)
    assert res.converged
    assert np.abs(r - res.y_hat).max() < 1e-12
    np.testing.assert_allclose(res.u_ff[:-1], inverse_model_feedforward(m, r)[:-1], atol=1e-9)
