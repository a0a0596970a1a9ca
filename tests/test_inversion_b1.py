"""Tests of the [B1] feedforward inversions (pipeline/invert/{direct,analytic,newton}.py):
Newton [B1] Alg. 1, analytic [B1] (27), direct inverse [B1] (13), physics [B1] (8)."""
import numpy as np
import pytest
import torch

from pipeline.invert.analytic import analytic_feedforward, physics_feedforward
from pipeline.invert.direct import direct_feedforward
from pipeline.invert.newton import BOUNDS, DIVERGED, newton_feedforward, newton_solve
from pipeline.models.fast_pgnn import fast_pgnn
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import LinearFeatures, RigidBodyForward, RigidBodyInverse

TS = 1e-3
THETA_ARX = [1.5, -0.7, 1.0, 0.5]  # SPEC §2.4: stable, minimum phase (zero at -0.5)


def known_model(structure, n_k=1, out_scale=0.3, seed=0):
    """ARX physics + tanh NN with f_NN(0) = 0 exactly (zero biases, no input offset), so
    y = 0, u = 0 is an equilibrium and a simulation from rest matches the inversions'
    at-rest padding."""
    m = PGNN(2, 2, n_k, structure=structure, physics=LinearFeatures(4), hidden=(8,),
             out_init_scale=1.0, seed=seed, input_transform="raw")
    m.set_physics_estimate(THETA_ARX)
    with torch.no_grad():
        m.out_scale.fill_(out_scale)
    return m


def simulate(model, u):
    """y(t) = ŷ(φ(t)) from rest (past y and u zero), noise free, forward layout."""
    n_a, n_b, n_k = model.n_a, model.n_b, model.n_k
    N = u.shape[0]
    y = np.zeros(N + n_k + 1)
    up = lambda j: u[j] if 0 <= j < N else 0.0
    yp = lambda j: y[j] if j >= 0 else 0.0
    with torch.no_grad():
        for t in range(N + n_k + 1):
            phi = [yp(t - i) for i in range(1, n_a + 1)] + [up(t - n_k - i) for i in range(1, n_b + 1)]
            y[t] = float(model(torch.tensor([phi], dtype=torch.float64))[0])
    return y


def smooth_input(N, seed=0):
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.standard_normal(N), np.ones(10) / 10, mode="same")
    u[:5] = 0.0
    return u


@pytest.mark.parametrize("structure", ["forward", "invertible"])
def test_newton_recovers_the_known_inverse(structure):
    m = known_model(structure)
    u_true = smooth_input(300)
    r = simulate(m, u_true)[:300]  # r(t) for t < N; later samples held by the padding
    res = newton_feedforward(m, r, k=5)
    # the last n_k + 1 samples need r beyond the record (held at r(N-1)): compare before
    n = 300 - m.n_k - 1
    assert res.residual.max() < 1e-10  # [B1] (23) solved
    assert res.n_fallback == 0
    np.testing.assert_allclose(res.u_ff[:n], u_true[:n], rtol=0, atol=1e-10 * np.abs(u_true).max())
    if structure == "invertible":
        # Assumption 5.1 holds: ŷ is affine in u(t-n_k-1), Newton = analytic [B1] (27)
        u_an = analytic_feedforward(m, r)
        np.testing.assert_allclose(res.u_ff, u_an, rtol=0, atol=1e-12 * np.abs(u_an).max())
        np.testing.assert_allclose(u_an[:n], u_true[:n], rtol=0, atol=1e-12 * np.abs(u_true).max())
        # one Newton step solves an affine equation (up to rounding)
        assert newton_feedforward(m, r, k=1).residual.max() < 1e-13


@pytest.mark.parametrize("fn", ["direct", "analytic", "newton", "physics_fwd", "physics_inv"])
def test_fast_path_equals_torch_reference(fn):
    r = 0.5 * np.sin(np.linspace(0, 6, 400)) + 0.1 * np.linspace(0, 1, 400) ** 2
    structure = {"direct": "inverse", "analytic": "invertible", "newton": "forward",
                 "physics_fwd": "forward", "physics_inv": "inverse"}[fn]
    m = known_model(structure, n_k=0, seed=4)
    if fn == "direct":
        a, b = direct_feedforward(m, r), direct_feedforward(m, r, fast=False)
    elif fn == "analytic":
        a, b = analytic_feedforward(m, r), analytic_feedforward(m, r, fast=False)
    elif fn == "newton":
        ra = newton_feedforward(m, r, k=5, u_bounds=(-40, 40))
        rb = newton_feedforward(m, r, k=5, u_bounds=(-40, 40), fast=False)
        np.testing.assert_array_equal(ra.flags, rb.flags)
        a, b = ra.u_ff, rb.u_ff
    else:
        a, b = physics_feedforward(m, r), physics_feedforward(m, r, fast=False)
    assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b))
    with pytest.raises(ValueError, match="fast=True"):
        PGNN_deep = PGNN(2, 2, structure=structure, physics=LinearFeatures(4), hidden=(3, 3))
        {"direct": direct_feedforward, "analytic": analytic_feedforward,
         "physics_fwd": physics_feedforward, "physics_inv": physics_feedforward,
         "newton": newton_feedforward}[fn](PGNN_deep, r, fast=True)


def test_fast_newton_on_rigid_body_physics():
    # linear-motor physics [B1] (32): u is determined to ~ulp(y)/ψ (ψ = Ts²/m ~ 5e-8 m/N),
    # so fast and reference agree to that level, not to 1e-10 relative
    r = 0.05 * (1 - np.cos(np.linspace(0, 2 * np.pi, 500)))
    m = PGNN(2, 1, physics=RigidBodyForward(TS), hidden=(8,), out_init_scale=1.0, seed=2)
    m.set_physics_estimate([1 / 20, 50 / 20, 10 / 20])
    with torch.no_grad():
        m.out_scale.fill_(2e-8)  # NN worth ~0.4 N of force
    a = newton_feedforward(m, r)
    b = newton_feedforward(m, r, fast=False)
    psi = TS ** 2 / 20
    # u is defined to ~1 ulp of y (1.4e-17 m at 0.1 m) over ψ: 2.8e-10 N; allow 4 such quanta
    assert np.max(np.abs(a.u_ff - b.u_ff)) < 4 * np.spacing(0.1) / psi
    assert a.residual.max() < 1e-15 and a.n_fallback == 0


def test_physics_feedforward_closed_form_and_layouts():
    # [B1] (32) inverted: u(t) = m δ²r(t+1) + f_v δr(t) + f_c sign(δr(t)), n_k = 0
    m_, fv, fc = 20.0, 50.0, 10.0
    t = np.arange(800) * TS
    r = 0.02 * np.sin(2 * np.pi * 2 * t)
    fwd = PGNN(2, 1, physics=RigidBodyForward(TS), use_nn=False)
    fwd.set_physics_estimate([1 / m_, fv / m_, fc / m_])
    inv = PGNN(2, 1, structure="inverse", physics=RigidBodyInverse(TS), use_nn=False)
    inv.set_physics_estimate([m_, fv, fc])
    re = np.concatenate([[r[0]], r, [r[-1]]])  # held before/after
    acc = (re[2:] - 2 * re[1:-1] + re[:-2]) / TS ** 2
    vel = (re[1:-1] - re[:-2]) / TS
    u_ref = m_ * acc + fv * vel + fc * np.sign(vel)
    for model in (fwd, inv):
        for fast in (None, False):
            u = physics_feedforward(model, r, fast=fast)
            # forward form: u = (r - 2r1 + r2 + ...)/ψ, cancellation ~ ulp(r)/ψ ~ 1e-10 N
            np.testing.assert_allclose(u, u_ref, rtol=0, atol=1e-6)


def test_newton_bounds_are_reported():
    m = known_model("forward", n_k=0, seed=1)
    u_true = smooth_input(200, seed=3)
    r = simulate(m, u_true)[:200]
    lim = 0.5 * np.abs(u_true).max()
    res = newton_feedforward(m, r, k=5, u_bounds=(-lim, lim))
    assert np.all(np.abs(res.u_ff) <= lim)
    assert res.n_bounds > 0
    # never silent: a sample is either solved ([B1] (23) to rounding) or flagged
    unsolved = res.residual > 1e-12
    assert np.all(res.flags[unsolved] & BOUNDS)
    assert np.all(res.residual[res.flags == 0] < 1e-12)


def test_newton_divergence_falls_back_to_best_iterate():
    # a NN with a large gain on u(t-1) makes ∂ŷ/∂u change sign: Newton wanders off
    m = known_model("forward", n_k=0, seed=1, out_scale=50.0)
    with torch.no_grad():
        m.layers[0].weight.mul_(20.0)
    fm = fast_pgnn(m)
    rng = np.random.default_rng(0)
    n_div = 0
    for _ in range(300):
        phi = rng.standard_normal(4)
        phi[m.u_index] = 0.0
        r_next = 3.0 * rng.standard_normal()
        u0, v0, f0, i0 = newton_solve(fm.blob, fm.meta, phi.copy(), r_next, 0, -np.inf, np.inf)
        u5, v5, f5, i5 = newton_solve(fm.blob, fm.meta, phi.copy(), r_next, 5, -np.inf, np.inf)
        assert v5 <= v0 and i0 == 0  # the returned iterate is the best one, start included
        p = phi.copy()
        p[m.u_index] = u5
        with torch.no_grad():  # reported residual is |V_R| at the returned input
            assert abs(r_next - float(m(torch.tensor(p[None]))[0])) == pytest.approx(v5, abs=1e-12)
        n_div += bool(f5 & DIVERGED)
    assert n_div > 0  # this model does make Newton diverge, and it is reported
    rb = newton_feedforward(m, np.linspace(0, 3, 200), k=5)
    assert rb.n_diverged > 0 and rb.n_fallback >= rb.n_diverged


def test_wrong_model_for_the_method_raises():
    fwd = known_model("forward")
    with pytest.raises(ValueError, match="NN does not see"):
        analytic_feedforward(fwd, np.zeros(10))
    with pytest.raises(ValueError, match="direct-inverse PGNN"):
        direct_feedforward(fwd, np.zeros(10))
    with pytest.raises(ValueError, match="forward-layout"):
        newton_feedforward(known_model("inverse"), np.zeros(10))
    with pytest.raises(ValueError, match="u_min < u_max"):
        newton_feedforward(fwd, np.zeros(10), u_bounds=(1, -1))


def test_direct_inverse_of_a_linear_model_is_exact():
    # inverse ARX (16) with the exact inverse parameters of SPEC §2.4 (n_k = 0, ψ0 = 1):
    # u(t) = y(t+1) - 1.5 y(t) + 0.7 y(t-1) - 0.5 u(t-1)
    fwd = PGNN(2, 2, physics=LinearFeatures(4), use_nn=False)
    fwd.set_physics_estimate(THETA_ARX)
    inv = PGNN(2, 2, structure="inverse", physics=LinearFeatures(4), use_nn=False)
    inv.set_physics_estimate([1.0, -1.5, 0.7, -0.5])
    u_true = smooth_input(300, seed=5)
    r = simulate(fwd, u_true)[:300]
    for u in (direct_feedforward(inv, r), analytic_feedforward(fwd, r),
              newton_feedforward(fwd, r, k=1).u_ff):
        np.testing.assert_allclose(u[:299], u_true[:299], rtol=0, atol=1e-12)


def test_averaged_input_feedforward_is_bounded_without_nyquist_oscillation():
    # SPEC §2.2 sampling pitfall: the continuous (ZOH) motor is identified with the averaged
    # input w = ū; inverting for w and applying u_ff(t) = (w(t) + w(t+1))/2 gives a smooth,
    # bounded feedforward, while inverting the averaged model for u itself (u(t) = 2w(t) -
    # u(t-1)) oscillates at the Nyquist frequency
    from pipeline.identify.narx import identify_pgnn
    from pipeline.invert.direct import nyquist_fraction
    from pipeline.models.physics_maps import PhysicsModelFeatures, physics_features_for
    from pipeline.references import b1_evaluation_reference, b1_training_reference
    from pipeline.systems.linear_motor import LinearMotor
    plant = LinearMotor(noise={"structure": "output", "std": 1e-7}, cogging=False)
    pm = plant.physics
    assert pm.averaged_input
    rng = np.random.default_rng(0)
    r = b1_training_reference(TS, duration=10.0).r
    sim = plant.simulate(r, du=50 * rng.standard_normal(r.size), v=plant.noise(r.size, rng))
    w = pm.model_input(sim.u)
    m = PGNN(2, 1, physics=physics_features_for(pm, "forward", 2, 1, input_is_model_input=True),
             use_nn=False)
    identify_pgnn(m, sim.y, w)
    assert m.physics.physical(m.theta_phy.detach().numpy())["m"] == pytest.approx(20.0, rel=0.05)
    r_ev = b1_evaluation_reference(0.15, TS).r
    u_exact_phys = pm.feedforward(m.theta_phy.detach().numpy(), r_ev)
    for u in (pm.applied_input(analytic_feedforward(m, r_ev)),
              pm.applied_input(newton_feedforward(m, r_ev, k=5).u_ff)):
        assert nyquist_fraction(u) < 1e-3
        assert np.max(np.abs(u)) <= 1.01 * np.max(np.abs(u_exact_phys))
        np.testing.assert_allclose(u, u_exact_phys, rtol=0, atol=1e-6 * np.abs(u_exact_phys).max())
    # negative control: the same physics written on (u(t-1), u(t-2)) and inverted for u
    m2 = PGNN(2, 2, physics=PhysicsModelFeatures(pm), use_nn=False)
    m2.set_physics_estimate(m.theta_phy.detach().numpy())
    u_bad = analytic_feedforward(m2, r_ev)
    assert nyquist_fraction(u_bad) > 0.1


B1_SMOKE = [
    "experiment=b1_linear_motor", "hydra.mode=RUN", "experiment_name=b1_linear_motor",
    "data.references=[{name:train,kind:b1_training,duration:6.0}]",
    "evaluate.references=[{name:v0.15,kind:b1_evaluation,v_max:0.15}]",
    "identify.n_restarts=2", "identify.max_iter=4", "model.hidden=[4]",
]


@pytest.mark.slow
def test_b1_stages_and_report_section(store, cfg_of, tmp_path):
    # the [B1] stage implementations end to end on tiny sizes (one reference, 4 LM steps),
    # then the report section reads the runs back from the tracking store
    from pipeline import runner, tracking
    from stages.report import claims_b1
    out = {}
    for inv in ("newton", "physics", "direct", "analytic"):
        res = runner.run_job(cfg_of(*B1_SMOKE, f"invert={inv}"))
        u = res["invert"]["u_ff"]["v0.15"]
        assert np.all(np.isfinite(u)) and u.shape == res["invert"]["r"]["v0.15"].shape
        out[inv] = res
    assert out["newton"]["train"]["model"].structure == "forward"
    assert out["direct"]["train"]["model"].structure == "inverse"
    assert out["analytic"]["train"]["model"].structure == "invertible"
    # physics reuses the forward model (cache) and only the baseline θ*
    assert out["physics"]["train"]["model"] is not None
    runs = tracking.search_runs("b1_linear_motor")
    assert len(runs) == 4
    m = runs.iloc[0]
    assert np.isfinite(m.get("metrics.evaluate/v0.15/mae"))
    rows, md = claims_b1.section("b1_linear_motor", runs, tmp_path)
    claims = {r["claim"] for r in rows if r["claim_holds"] is not None}
    assert {"B1b", "B1c"} <= claims
    assert "Newton k=5" in md and (tmp_path / "b1_linear_motor-equation-mae.png").exists()
    assert (tmp_path / "b1_linear_motor-equation-fig3.png").exists()  # from the runs' errors.npz
    newton = runs[runs["tags.invert"] == "newton"].iloc[0]
    assert newton["metrics.invert/v0.15/newton_diverged"] >= 0
    assert newton["metrics.invert/v0.15/sample_seconds_median"] < 1e-3
    # diagnostics: the 0.15 m/s reference is faster than the 0.05 m/s training data (whose
    # measured max |δy| includes the Δu-driven motion, ~0.08 m/s)
    assert 1.2 < newton["metrics.invert/v0.15/velocity_over_training"] < 3.5
    assert newton["metrics.invert/nn_r2_unmodelled"] <= 1.0


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_noise_sweep_report_section(store, tmp_path, monkeypatch):
    # the b1_noise_sweep section reads (structure, σ, method) from the runs' params/tags, puts
    # every model's mass and every MAE in summary rows, and states the inverse-mass drift it sees
    import pandas as pd

    from stages.report import claims_b1
    recs = []
    for s in ("equation", "output"):
        for sg in (0.0, 1e-6):
            for mt in claims_b1.METHODS:
                m_inv = 20.0 - 1e7 * sg  # inverse LS drifts by -10 kg at σ = 1e-6
                rec = {"tags.mlflow.runName": f"linear_motor-{s}-sigma{sg}-{mt}-s0", "run_id": f"{s}{sg}{mt}",
                       "params.system.noise.std": str(sg), "params.system.noise.structure": s,
                       "params.system.m": "20.0", "params.identify.n_restarts": "3", "tags.invert": mt,
                       "metrics.train/theta_phy_star/m": m_inv if mt == "direct" else 20.0 + 1e5 * sg,
                       "metrics.train/theta_phy/m": 19.0 if mt == "analytic" else 20.5,
                       "metrics.evaluate/v0.05/mae": 1e-6 * (1 + 1e6 * sg * (mt == "direct")),
                       "metrics.evaluate/v0.15/mae": 2e-6, "metrics.evaluate/v0.20/mae": 3e-6,
                       "metrics.evaluate/v0.15/max_abs": 4e-5 if mt == "direct" else 1e-5}
                recs.append(rec)
    rows, md = claims_b1.section("b1_noise_sweep", pd.DataFrame(recs), tmp_path)
    mass = [r for r in rows if r["metric"].endswith("/m")]
    mae = [r for r in rows if r["metric"] == "mae"]
    assert len(mass) == 2 * 2 * len(claims_b1.MASS) and len(mae) == 2 * 2 * 4 * 3
    assert all(r["claim_holds"] is None for r in rows)  # a study, not a SPEC §8 claim
    inv = {r["variant"]: r["value"] for r in mass if r["variant"].endswith("/direct")
           and r["metric"] == "theta_phy_star/m"}
    assert inv == {"equation/sigma0/direct": 20.0, "equation/sigma1e-06/direct": 10.0,
                   "output/sigma0/direct": 20.0, "output/sigma1e-06/direct": 10.0}
    assert "from 20.00 (σ = 0) to 10.00 kg (σ = 1e-06), -50.0% off the true mass" in md
    assert "within 0.5% of the true mass" in md  # forward LS: 20 + 0.1 at σ = 1e-6
    assert "best of 3 restarts" in md and (tmp_path / "b1_noise_sweep.png").exists()
    assert "Newton / direct peak error at 0.15 m/s: 0.25 at σ = 0, 0.25 at σ = 1e-06." in md
    # method and noise from the logged tag and param, never from the run's name
    run = pd.Series({"tags.mlflow.runName": "linear_motor-equation-sigma1e-08-newton-s0", "tags.invert": "analytic",
                     "params.system.noise.structure": "output"})
    assert claims_b1._variant(run) == ("output", "analytic")
    # the headline comparison reads the headline's σ and restarts from its params
    head = pd.DataFrame([{"tags.mlflow.runName": "linear_motor-equation-newton-s0", "tags.invert": "newton",
                          "params.system.noise.structure": "equation", "params.system.noise.std": "1e-06",
                          "params.identify.n_restarts": "10", "metrics.evaluate/v0.15/mae": 1.6e-6}])
    monkeypatch.setattr("stages.report._runs.latest_runs", lambda name: (head, []))
    _, md = claims_b1.section("b1_noise_sweep", pd.DataFrame(recs), tmp_path)
    assert "σ = 1e-06, this sweep vs the `b1_linear_motor` headline (best of 10): equation/newton 2e-06 " \
           "vs 1.6e-06. They differ by up to 25%" in md


def test_peak_diagnosis_reads_the_cause_from_the_phase_metrics():
    # B1b's peak condition: the per-phase peaks and force errors say why the indirect PGNNs lose
    from stages.report import claims_b1
    peaks = {"direct": (8e-5, 7e-5, 7.5e-5), "newton": (2.6e-5, 4.4e-5, 2.7e-5),
             "analytic": (2.8e-5, 3.5e-5, 2.6e-5), "physics": (3e-5, 7e-5, 3e-5)}
    ff = {"direct": (7.3, 1.0, 8.9, 4.7), "newton": (2.7, 0.9, 3.0, 4.1), "analytic": (2.7, 0.8, 3.0, 4.1),
          "physics": (4.0, 3.8, 4.5, 5.5)}   # accel/constvel at 0.05, then at 0.15 m/s
    table = {}
    for mt in peaks:
        m = {f"evaluate/v0.15/max_abs_{k}": v for k, v in zip(claims_b1.PHASE_LABEL, peaks[mt])}
        m |= {f"evaluate/{r}/ff_rms_{k}": v for (r, k), v in
              zip([(r, k) for r in ("v0.05", "v0.15") for k in ("accel", "constvel")], ff[mt])}
        m |= {"train/theta_phy/m": 17.7 if mt == "direct" else 20.1, "invert/v0.15/velocity_over_training": 1.6}
        table[("equation", mt)] = m
    rows = []
    kw = dict(m_true=20.0, lags={"direct": 0.0, "newton": 0.016, "analytic": 0.012})
    md = "\n".join(claims_b1._peak_diagnosis(table, rows, "b1_linear_motor", **kw))
    assert "force error is 3.0× Newton k=5 (Alg. 1)'s, 3.0× analytic (27)'s (its mass 17.70 kg, the " \
           "forward PGNN's 20.10 kg, true 20 kg)" in md
    assert "by 4.6× (Newton k=5 (Alg. 1), to 4.10 N)" in md and "1.60× the fastest" in md
    assert "comes 0 ms (physics" not in md and "16 ms (Newton k=5 (Alg. 1))" in md
    assert "extrapolates alike above the training speeds" in md
    ratio = {(r["variant"], r["metric"]): r["value"] for r in rows}
    assert ratio[("equation/newton/v0.15", "peak_over_direct_constvel")] == pytest.approx(4.4 / 7)
    # no conclusion the numbers do not carry: each condition on its own withholds it
    md = "\n".join(claims_b1._peak_diagnosis(table, [], "b1_linear_motor", **(kw | {"m_true": 25.0})))
    assert "extrapolates alike" not in md
    # a peak while accelerating is not the extrapolated velocity-dependent force: that method is left out
    table[("equation", "analytic")]["evaluate/v0.15/max_abs_accel"] = 5e-5
    md = "\n".join(claims_b1._peak_diagnosis(table, [], "b1_linear_motor", **kw))
    assert "So: Newton k=5 (Alg. 1) has the mass within 2%" in md and "its peak is not 3×" in md
    table[("equation", "analytic")]["evaluate/v0.15/max_abs_accel"] = 2.8e-5
    table[("equation", "newton")]["evaluate/v0.15/ff_rms_accel"] = 6.0   # no clear mass advantage
    md = "\n".join(claims_b1._peak_diagnosis(table, [], "b1_linear_motor", **kw))
    assert "1.5× Newton k=5 (Alg. 1)'s" in md and "So: analytic (27) has the mass" in md   # Newton left out
    del table[("equation", "analytic")]["evaluate/v0.15/max_abs_accel"]   # a run from evaluate v1
    md = "\n".join(claims_b1._peak_diagnosis(table, [], "b1_linear_motor", **kw))
    assert "analytic (27) |" not in md


def test_fast_path_of_a_measured_rigid_body_with_force_terms_equals_torch_reference():
    """A measured axis's physics (RigidBodyPhysics with every force term: viscous, smooth Coulomb,
    Stribeck, offset, two cogging harmonics) on its direct input has a numba fast path (kind 3):
    analytic [B1] (27), Newton and physics feedforwards equal their torch references to the
    resolution of u (ulp(y)/ψ, ψ = Ts²/M); on the averaged input there is no fast path; the C exporter
    ships kind 3 (issue 49, tests/test_export_pgnn_measured.py)."""
    from pipeline.export.law import ExportError, from_pgnn
    from pipeline.models.physics_maps import PhysicsModelFeatures, physics_features_for
    from pipeline.systems.force_terms import ForceTerms
    from pipeline.systems.measured import RigidBodyPhysics
    terms = ForceTerms(("viscous", "coulomb", "stribeck", "offset", "cogging"), coulomb_width=0.002,
                       stribeck_velocity=0.01, cogging_period=0.03, cogging_harmonics=2)
    pm = RigidBodyPhysics(TS, averaged_input=True, terms=terms)
    M = 95.0
    theta = pm.theta_from_physical({"M": M, "F_v": 200.0, "F_c": 20.0, "F_s": 5.0, "OF": -3.0,
                                    "C_cos1": 2.0, "C_sin1": -1.0, "C_cos2": 0.5, "C_sin2": 0.3})
    phys = physics_features_for(pm, "invertible", 2, 1, input_is_model_input=True)
    assert phys.fast_kind == 3 and PhysicsModelFeatures(pm).fast_kind == -1
    m = PGNN(2, 1, structure="invertible", physics=phys, hidden=(8,), out_init_scale=1.0, seed=3,
             input_transform="delta")
    m.set_physics_estimate(theta)
    with torch.no_grad():
        m.out_scale.fill_(TS ** 2 / M * 3.0)   # NN worth ~3 N of force
    assert fast_pgnn(m) is not None
    r = 0.1 * (1 - np.cos(np.linspace(0, 2 * np.pi, 600))) + 0.02 * np.sin(np.linspace(0, 9, 600))
    quantum = np.spacing(0.25) / (TS ** 2 / M)          # u is defined to ~1 ulp of y over ψ
    pairs = [(analytic_feedforward(m, r), analytic_feedforward(m, r, fast=False)),
             (physics_feedforward(m, r), physics_feedforward(m, r, fast=False)),
             (newton_feedforward(m, r).u_ff, newton_feedforward(m, r, fast=False).u_ff)]
    for a, b in pairs:
        assert np.all(np.isfinite(a)) and np.max(np.abs(b)) > 10.0
        assert np.max(np.abs(a - b)) < 8 * quantum
    assert from_pgnn(m, "analytic", TS).ints["kind"] == 3
    with pytest.raises(ExportError, match="built-in physics"):   # the averaged input: no kernel
        from_pgnn(PGNN(2, 1, structure="invertible", physics=PhysicsModelFeatures(pm), hidden=(8,)), "analytic", TS)


def test_mae_diagnosis_names_the_motion_phase_that_decides_a_failed_mae_ratio():
    """B1b's 'MAE <= 0.8x direct' rows: the MAE is split by motion phase (Σ_phase |e| / N sums to the MAE).
    Newton at v0.05 loses 1.2 µm to the direct inverse at constant velocity (79 % of the samples) and gains
    0.1 + 1.0 µm elsewhere: constant velocity decides; where it gains more than it loses, no clause."""
    from stages.report import claims_b1
    parts = {("newton", "v0.05"): {"accel": (0.01, 0.05e-6), "constvel": (0.79, 4.05e-6), "standstill": (0.2, 0.26e-6)},
             ("direct", "v0.05"): {"accel": (0.01, 0.15e-6), "constvel": (0.79, 2.85e-6), "standstill": (0.2, 1.26e-6)}}
    table = {("equation", "newton"): {"evaluate/v0.05/ff_rms_constvel": 1.18},
             ("equation", "direct"): {"evaluate/v0.05/ff_rms_constvel": 0.78}}
    failed = [("newton MAE ≤ 0.8× direct at v0.05", False, 1.02)]
    md = "\n".join(claims_b1._mae_diagnosis(failed, table, ["v0.05"], parts))
    assert "Newton k=5 (Alg. 1) at v0.05: 79% of its samples are constant velocity, where its errors add 4.05 µm " \
           "to the MAE against the direct inverse's 2.85 µm (force error 1.18 against 0.78 N rms); it gains " \
           "only 1.10 µm in the other phases" in md
    parts[("newton", "v0.05")]["standstill"] = (0.2, 0.0)   # gains 1.36 µm > loses 1.2 µm: not the cause
    assert claims_b1._mae_diagnosis(failed, table, ["v0.05"], parts) == []
