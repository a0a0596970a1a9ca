"""Tests of the PGNN models (pipeline/models/pgnn.py) and the NARX / direct-inverse
identification (pipeline/identify/narx.py), [B1] (7), (10)-(14), (26), (29)."""
import math

import numpy as np
import pytest
import torch

from pipeline.identify.narx import (criterion, forward_regressor, identify_pgnn,
                                    inverse_regressor, physics_least_squares, regularizer_sqrt)
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import LinearFeatures, RigidBodyForward, RigidBodyInverse

TS = 1e-3


def motor_equation_noise(N, seed=0, sigma_v=1e-6, parasitics=True, m=20.0, f_v=50.0, f_c=10.0):
    """Exactly-NARX linear motor (SPEC §2.2 'equation' noise) under a PD loop with white
    input excitation Δu ~ N(0, 50²); returns (r, y, u)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * TS
    r = 0.05 * np.sin(2 * np.pi * 0.5 * t) * np.minimum(1.0, t / 0.2)
    v = sigma_v * rng.standard_normal(N)
    du = 50.0 * rng.standard_normal(N)
    y, u = np.zeros(N), np.zeros(N)
    for k in range(N):
        if k >= 2:
            vel = (y[k - 1] - y[k - 2]) / TS
            if parasitics:
                fr = (f_c + 5.0 * np.exp(-(vel / 0.01) ** 2)) * np.tanh(vel / 1e-3)
                fr += 5.0 * np.sin(2 * np.pi * y[k - 1] / 0.025 + 0.3)
            else:
                fr = f_c * np.sign(vel)
            y[k] = 2 * y[k - 1] - y[k - 2] + TS ** 2 / m * (u[k - 1] - f_v * vel - fr) + v[k]
        e = r[k] - y[k]
        ed = (e - (r[k - 1] - y[k - 1])) / TS if k > 0 else 0.0
        u[k] = 2e5 * e + 3e3 * ed + du[k]
    return r, y, u


def _fd_jacobian(model, theta, prep, h=1e-6):
    cols = []
    for i in range(theta.numel()):
        e = torch.zeros_like(theta)
        e[i] = h * max(1.0, abs(float(theta[i])))
        cols.append((model.predict(theta + e, prep) - model.predict(theta - e, prep)) / (2 * e[i]))
    return torch.stack(cols, 1)


# ---- regressors ----------------------------------------------------------------------------
def test_forward_regressor_time_shifts():
    k = np.arange(10.0)
    reg = forward_regressor(k, 1000 * k, n_a=2, n_b=3, n_k=1)
    # first complete row t = max(n_a, n_k + n_b) = 4: [y(3), y(2), u(2), u(1), u(0)]
    assert reg.t[0] == 4 and reg.t[-1] == 9
    np.testing.assert_array_equal(reg.phi[0], [3, 2, 2000, 1000, 0])
    np.testing.assert_array_equal(reg.phi[:, 0], reg.t - 1)
    np.testing.assert_array_equal(reg.phi[:, 2], 1000 * (reg.t - 2))  # u(t - n_k - 1)
    np.testing.assert_array_equal(reg.target, reg.t)


def test_inverse_regressor_time_shifts():
    k = np.arange(10.0)
    reg = inverse_regressor(k, 1000 * k, n_a=2, n_b=3, n_k=1)
    # φ'(t) = [y(t+2), y(t+1), y(t), u(t-1), u(t-2)], target u(t); t = 2 .. N-3 = 7
    assert reg.t[0] == 2 and reg.t[-1] == 7
    np.testing.assert_array_equal(reg.phi[0], [4, 3, 2, 1000, 0])
    np.testing.assert_array_equal(reg.target, 1000 * reg.t)
    reg = inverse_regressor(k, 1000 * k, n_a=2, n_b=1, n_k=0)
    np.testing.assert_array_equal(reg.phi[0], [2, 1, 0])  # t = 1: y(2), y(1), y(0)
    assert reg.phi.shape == (8, 3)


def test_orders_the_data_cannot_support_raise():
    with pytest.raises(ValueError, match="need more than 5 samples"):
        forward_regressor(np.zeros(5), np.zeros(5), n_a=5, n_b=2, n_k=0)
    with pytest.raises(ValueError, match="at least"):
        inverse_regressor(np.zeros(3), np.zeros(3), n_a=3, n_b=1, n_k=2)
    with pytest.raises(ValueError, match="n_b >= 1"):
        forward_regressor(np.zeros(50), np.zeros(50), n_a=2, n_b=0, n_k=0)
    m = PGNN(2, 1, physics=RigidBodyForward(TS), hidden=(16,))
    with pytest.raises(ValueError, match="training rows cannot identify"):
        identify_pgnn(m, np.arange(30.0), np.ones(30), n_restarts=1, val_fraction=0.0)


# ---- model structure ------------------------------------------------------------------------
@pytest.mark.parametrize("structure", ["forward", "inverse", "invertible"])
@pytest.mark.parametrize("hidden,activation", [((6,), "tanh"), ((), "tanh"), ((5, 4), "tanh"),
                                               ((6,), "sigmoid")])
def test_jacobian_matches_finite_differences(structure, hidden, activation):
    phys = RigidBodyInverse(TS) if structure == "inverse" else LinearFeatures(4)
    m = PGNN(2, 2, 1, structure=structure, physics=phys, hidden=hidden, activation=activation,
             out_init_scale=1.0, seed=3)
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(200, 4, generator=g, dtype=torch.float64)
    if structure == "inverse":  # positions on the scale of Ts^2, so m d2y is O(1) like the NN part
        phi[:, :3] *= TS ** 2
    m.fit_normalisation(phi)
    with torch.no_grad():
        m.out_scale.fill_(0.7)
        m.theta_phy.copy_(torch.randn(3 if structure == "inverse" else 4, generator=g, dtype=torch.float64))
    # a generic point: random biases too
    th = m.parameter_vector() + 0.3 * torch.randn(m.n_params, generator=g, dtype=torch.float64)
    prep = m.prepare(phi)
    J = m.jacobian(th, prep)
    Jfd = _fd_jacobian(m, th, prep)
    # central differences with h ~ 1e-6: truncation ~h^2 |f'''| ~ 1e-12, rounding ~eps |f| / h ~ 1e-10;
    # tolerance per column, so every column is checked on its own scale
    assert bool(((J - Jfd).abs() <= 1e-6 * Jfd.abs().amax(0)).all())
    Jad = torch.func.jacfwd(lambda t: m.predict(t, prep))(th)
    assert torch.allclose(J, Jad, rtol=1e-12, atol=1e-14)
    # the LM's path: row blocks written into a reused buffer and scaled in place is the same
    # arithmetic, so it must equal the one-block J times the scale to the bit
    buf = torch.full_like(J, float("nan"))
    assert torch.equal(m.jacobian(th, prep, out=buf, scale=-0.37, block=64), J * (-0.37))


@pytest.mark.parametrize("hidden,activation", [((6,), "tanh"), ((), "tanh"), ((5, 4), "tanh"),
                                               ((6,), "sigmoid")])
def test_criterion_normal_equations_equal_the_full_jacobian(hidden, activation):
    # the LM's path: JᵀJ and Jᵀr summed over row blocks (syrk/gemv in cache, J never stored),
    # hidden activations reused from the residual at the same θ; J itself is bit-identical
    m = PGNN(2, 2, 1, physics=LinearFeatures(4), hidden=hidden, activation=activation,
             out_init_scale=1.0, seed=3)
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(2500, 4, generator=g, dtype=torch.float64)  # 2500 = 2 blocks + a tail
    m.fit_normalisation(phi)
    prep = m.prepare(phi)
    target = torch.randn(2500, generator=g, dtype=torch.float64)
    ts = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=torch.float64)
    res, jac = criterion(m, prep, target, 0.8, ts, torch.eye(4, dtype=torch.float64))
    th = m.parameter_vector() + 0.3 * torch.randn(m.n_params, generator=g, dtype=torch.float64)
    r = res(th)
    assert torch.equal(m.predict(th, prep, block=1024), m.predict(th, prep))
    J = jac(th).clone()
    A, gr = jac.normal_equations(th, r)
    assert torch.allclose(A, J.T @ J, rtol=1e-13, atol=1e-13 * float(A.diagonal().max()))
    assert torch.equal(A, A.T)
    assert torch.allclose(gr, J.T @ r, rtol=1e-13, atol=1e-13 * float(gr.abs().max()))
    blocks = torch.cat([b.clone() for _, b in m.jacobian_blocks(th, prep, scale=-0.5, block=1024)])
    assert torch.equal(blocks, m.jacobian(th, prep, scale=-0.5, block=2500))  # the same products
    if len(hidden) == 1:
        h = torch.empty(2500, hidden[0], dtype=torch.float64)
        m.predict(th, prep, block=1024, hidden=h)
        cached = torch.cat([b.clone() for _, b in m.jacobian_blocks(th, prep, scale=-0.5, block=1024,
                                                                    hidden=h)])
        assert torch.equal(cached, blocks)


def test_initial_pgnn_equals_physics_and_parts():
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(50, 3, generator=g, dtype=torch.float64)
    m = PGNN(2, 1, physics=RigidBodyForward(TS), out_init_scale=0.0)
    m.fit_normalisation(phi)
    m.set_physics_estimate([0.05, 2.5, 0.5])
    assert torch.equal(m(phi), m.physics_part(phi))
    m = PGNN(2, 1, physics=RigidBodyForward(TS))  # default: tiny output layer
    m.set_physics_estimate([0.05, 2.5, 0.5])
    with torch.no_grad():
        nn_rel = float(m.nn_part(phi).abs().max() / m.physics_part(phi).abs().max())
    assert 0 < nn_rel < 1e-2
    # the physics-only and black-box models are the same class with one part switched off
    p_only = PGNN(2, 1, physics=RigidBodyForward(TS), use_nn=False)
    assert p_only.n_params == 3 and not any(True for _ in p_only.layers)
    bb = PGNN(2, 1, physics=None, use_physics=False, hidden=(4,))
    assert bb.n_params == 3 * 4 + 4 + 4 + 1
    assert torch.equal(bb(phi), bb.nn_part(phi))
    with pytest.raises(ValueError, match="at least one part"):
        PGNN(2, 1, physics=RigidBodyForward(TS), use_physics=False, use_nn=False)


def test_invertible_nn_ignores_latest_input_and_forward_does_not():
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(20, 4, generator=g, dtype=torch.float64)
    phi2 = phi.clone()
    phi2[:, 2] += 1.0  # u(t - n_k - 1) at index n_a = 2
    kw = dict(physics=LinearFeatures(4), hidden=(5,), out_init_scale=1.0)
    inv = PGNN(2, 2, structure="invertible", **kw)
    fwd = PGNN(2, 2, structure="forward", **kw)
    assert torch.equal(inv.nn_part(phi), inv.nn_part(phi2))
    assert not torch.allclose(fwd.nn_part(phi), fwd.nn_part(phi2))
    assert inv.analytically_invertible and not fwd.analytically_invertible
    assert inv.psi_mask().tolist() == [False, False, True, False]
    assert PGNN(2, 1, physics=RigidBodyForward(TS)).psi_mask().tolist() == [True, False, False]


def test_normalisation_is_saved_with_the_model(tmp_path):
    g = torch.Generator().manual_seed(0)
    phi = 1e-2 * torch.randn(100, 3, generator=g, dtype=torch.float64) + 5.0
    m = PGNN(2, 1, physics=RigidBodyForward(TS), out_init_scale=1.0)
    m.fit_normalisation(phi)
    x = m.prepare(phi).x
    # 'delta' basis: y(t-1), y(t-1) - y(t-2), u(t-1), each standardised on the training data
    assert torch.allclose(x.mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(x.std(0), torch.ones(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(x[:, 1] * (phi[:, 0] - phi[:, 1]).std() + (phi[:, 0] - phi[:, 1]).mean(),
                          phi[:, 0] - phi[:, 1], atol=1e-12)
    torch.save(m.state_dict(), tmp_path / "m.pt")
    m2 = PGNN(2, 1, physics=RigidBodyForward(TS), out_init_scale=1.0, seed=5)
    m2.load_state_dict(torch.load(tmp_path / "m.pt"))
    assert torch.equal(m2(phi), m(phi))


# ---- criteria --------------------------------------------------------------------------------
def test_physics_least_squares_recovers_contained_plant():
    # parasitics off, F_fric = f_c sign: the physics model contains the plant (SPEC §2.2);
    # with σ_v = 0 the closed form [B1] (7) is exact up to rounding
    r, y, u = motor_equation_noise(3000, sigma_v=0.0, parasitics=False)
    for struct, phys in [("forward", RigidBodyForward(TS)), ("inverse", RigidBodyInverse(TS))]:
        m = PGNN(2, 1, structure=struct, physics=phys, use_nn=False)
        reg = (inverse_regressor if struct == "inverse" else forward_regressor)(y, u, 2, 1, 0)
        th = physics_least_squares(m, reg.phi, reg.target)
        p = phys.physical(th) if struct == "forward" else dict(zip(phys.param_names, th))
        assert p["m"] == pytest.approx(20.0, rel=1e-7)
        assert p["f_v"] == pytest.approx(50.0, rel=1e-6)
        assert p["f_c"] == pytest.approx(10.0, rel=1e-6)


def test_lm_on_pgnn_reaches_closed_form_regularised_optimum():
    # a PGNN with a linear NN (hidden=()) is linear in all its parameters: the regularised
    # criterion [B1] (12) in normalised units has a closed-form augmented LS solution
    r, y, u = motor_equation_noise(2000, seed=1)
    m = PGNN(2, 1, physics=RigidBodyForward(TS), hidden=(), out_init_scale=1.0)
    lam = 0.3
    fit = identify_pgnn(m, y, u, lam=lam, n_restarts=2, val_fraction=0.0, max_iter=200,
                        ftol=0.0, gtol=1e-14)
    reg = forward_regressor(y, u, 2, 1, 0)
    prep = m.prepare(torch.as_tensor(reg.phi))
    M = len(reg)
    c = 1 / (fit.sigma * np.sqrt(M))
    ones = torch.ones(M, 1, dtype=torch.float64)
    X = torch.cat([prep.T, prep.x * m.out_scale, m.out_scale * ones], 1).numpy()
    z = reg.target - prep.offset.numpy()
    ts = fit.theta_phy_star
    Raug = np.zeros((3, X.shape[1]))
    Raug[:, :3] = np.sqrt(lam) * np.diag(1 / np.abs(ts))
    A = np.vstack([c * X, Raug])
    b = np.concatenate([c * z, np.sqrt(lam) * ts / np.abs(ts)])
    sc = np.linalg.norm(A, axis=0)
    x_ls = np.linalg.lstsq(A / sc, b, rcond=None)[0] / sc
    th = m.parameter_vector().numpy()
    # relative error in the column-scaled coordinates (cond(A/sc) ~ 1.3, so the LS solution
    # is defined to ~1e-15 there; single NN entries can be near zero, hence not entrywise)
    assert np.linalg.norm(sc * (th - x_ls)) / np.linalg.norm(sc * x_ls) < 1e-10
    assert fit.cost == pytest.approx(float(np.sum((A @ x_ls - b) ** 2)), rel=1e-10)


def test_regulariser_units():
    # Λ = 0.01 I: a 10% change of all three physical parameters costs 3 · 0.01 · 0.1² = 3e-4
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(100, 3, generator=g, dtype=torch.float64)
    m = PGNN(2, 1, physics=RigidBodyForward(TS), use_nn=False)
    ts = torch.tensor([0.05, 2.5, -0.5], dtype=torch.float64)
    prep = m.prepare(phi)
    target = m.physics.forward(phi, ts)
    R = torch.as_tensor(regularizer_sqrt(0.01, 3))
    res, jac = criterion(m, prep, target, 1.0, ts, R)
    th = 1.1 * ts
    mse = float(((target - m.predict(th, prep)) ** 2).mean())
    assert float(res(th).square().sum()) == pytest.approx(mse + 3e-4, rel=1e-12)
    # [B1] (29): ψ (the 1/m entry multiplying u(t-1)) is not regularised
    keep = ~PGNN(2, 1, structure="invertible", physics=RigidBodyForward(TS)).psi_mask().numpy()
    R29 = torch.as_tensor(regularizer_sqrt(0.01, 3, keep))
    res29, _ = criterion(m, prep, target, 1.0, ts, R29)
    assert float(res29(th).square().sum()) == pytest.approx(mse + 2e-4, rel=1e-12)
    # the criterion is linear in θ here: central differences with a large step are exact up
    # to rounding (~eps·|r|/(h θ) ~ 1e-13 against entries >= 1e-7)
    assert torch.allclose(jac(th), _fd_jac_res(res, th), rtol=1e-6, atol=1e-12)


def _fd_jac_res(res, th, h=1e-2):
    cols = []
    for i in range(th.numel()):
        e = torch.zeros_like(th)
        e[i] = h * max(abs(float(th[i])), 1e-3)
        cols.append((res(th + e) - res(th - e)) / (2 * e[i]))
    return torch.stack(cols, 1)


def test_best_of_restarts_validation_block_and_determinism():
    r, y, u = motor_equation_noise(3000, seed=2)
    kw = dict(physics=RigidBodyForward(TS), hidden=(4,))
    m = PGNN(2, 1, **kw)
    fit = identify_pgnn(m, y, u, n_restarts=3, seed=7, val_fraction=0.25, max_iter=15)
    costs = [rr.cost for rr in fit.restarts]
    assert fit.best == int(np.argmin(costs)) and len(set(costs)) == 3
    assert torch.equal(m.parameter_vector(), fit.restarts[fit.best].theta)
    # the validation block is the contiguous tail: 750 samples -> 748 complete rows
    assert fit.n_val == 750 - 2 and fit.n_train == 2250 - 2
    for rr in fit.restarts:
        assert rr.history[0] >= rr.history[-1] and len(rr.val_history) == len(rr.history)
    # the returned cost is the criterion at the returned parameters
    reg = forward_regressor(y[:2250], u[:2250], 2, 1, 0)
    res, _ = criterion(m, m.prepare(torch.as_tensor(reg.phi)), torch.as_tensor(reg.target),
                       fit.sigma, torch.as_tensor(fit.theta_phy_star),
                       torch.as_tensor(regularizer_sqrt(0.01, 3)))
    assert float(res(m.parameter_vector()).square().sum()) == pytest.approx(fit.cost, rel=1e-12)
    m2 = PGNN(2, 1, **kw)
    identify_pgnn(m2, y, u, n_restarts=3, seed=7, val_fraction=0.25, max_iter=15)
    assert torch.equal(m2.parameter_vector(), m.parameter_vector())


def test_builtin_physics_maps_equal_the_plants_physics_models():
    from pipeline.models.physics_maps import PhysicsModelFeatures, physics_features_for
    from pipeline.systems.arx_bias import ARXPhysics
    from pipeline.systems.linear_motor import LinearMotorPhysics
    g = torch.Generator().manual_seed(0)
    phi = 1e-3 * torch.randn(64, 3, generator=g, dtype=torch.float64)
    phi[:, 2] = 100 * torch.randn(64, generator=g, dtype=torch.float64)
    lm = LinearMotorPhysics(TS)
    for structure in ("forward", "inverse"):
        ours = physics_features_for(lm, structure, 2, 1)
        assert isinstance(ours, RigidBodyInverse if structure == "inverse" else RigidBodyForward)
        theirs = PhysicsModelFeatures(lm, inverse=structure == "inverse")
        for a, b in zip(ours.features(phi), theirs.features(phi)):
            assert torch.allclose(a, b, rtol=1e-13, atol=0)
    arx = ARXPhysics(2, 2)
    assert isinstance(physics_features_for(arx, "forward", 2, 2), LinearFeatures)
    with pytest.raises(ValueError, match="make them equal"):
        physics_features_for(arx, "forward", 3, 2)
    with pytest.raises(ValueError, match="make them equal"):
        physics_features_for(arx, "forward", 2, 2, n_k=1)
    # a regressor that cannot hold [B1] (32): a clear error naming the orders, not an IndexError
    for structure, orders in (("inverse", (1, 1, 0)), ("forward", (2, 1, 1)), ("forward", (2, 0, 0))):
        with pytest.raises(ValueError, match=r"needs n_a >= 2, n_b >= 1 and n_k = 0"):
            physics_features_for(lm, structure, *orders)


def test_arx_inverse_asymptotic_bias_matches_simulation():
    # [B1] (18) in closed form vs a long simulation of SPEC §2.4 (N = 4e5, 4 seeds pooled):
    # the LS estimate's spread is ~ σ/sqrt(N) ~ 1e-3 against a bias of ~2e-2
    from scipy.signal import lfilter
    from pipeline.identify.narx import arx_inverse_asymptotics
    a, b, sv = [1.5, -0.7], [1.0, 0.5], 0.1
    th_inv, bias, M = arx_inverse_asymptotics(a, b, 1.0, sv)
    np.testing.assert_allclose(th_inv, [1.0, -1.5, 0.7, -0.5])
    rng = np.random.default_rng(0)
    N = 400_000
    u = rng.standard_normal(N)
    v = sv * rng.standard_normal(N)
    A = [1.0, -1.5, 0.7]
    y = lfilter([0.0, 1.0, 0.5], A, u) + lfilter([1.0], A, v)
    reg = inverse_regressor(y[1000:], u[1000:], 2, 2, 0)  # drop the start-up transient
    Mhat = reg.phi.T @ reg.phi / len(reg)
    np.testing.assert_allclose(Mhat, M, rtol=0.02, atol=0.02 * np.abs(M).max())
    m = PGNN(2, 2, structure="inverse", physics=LinearFeatures(4), use_nn=False)
    th = physics_least_squares(m, reg.phi, reg.target)
    assert np.linalg.norm(th - th_inv - bias) < 0.1 * np.linalg.norm(bias)
    assert np.linalg.norm(bias) > 0.01


def test_mirrored_init_is_exactly_physics_with_live_hidden_units():
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(40, 3, generator=g, dtype=torch.float64)
    m = PGNN(2, 1, physics=RigidBodyForward(TS), hidden=(6,), out_init="mirrored",
             out_init_scale=1.0, seed=4)
    m.fit_normalisation(phi)
    m.set_physics_estimate([0.05, 2.5, 0.5])
    with torch.no_grad():  # zero up to the rounding of the output sum
        assert float(m.nn_part(phi).abs().max()) < 1e-15 * float(m.out_scale)
    J = m.jacobian(m.parameter_vector(), m.prepare(phi))
    sl = m.param_slices()["layers.0.weight"]
    # hidden-layer columns are as large as the output-layer ones (not ~out_init_scale smaller)
    assert float(J[:, sl].abs().max()) > 0.1 * float(J[:, m.param_slices()["layers.1.weight"]].abs().max())
    assert torch.linalg.matrix_rank(J[:, 3:]) >= 6  # pairs are separable by LM
    with pytest.raises(ValueError, match="out_init"):
        PGNN(2, 1, physics=RigidBodyForward(TS), out_init="zero")


def test_mirror_jitter_moves_twins_off_the_overlap_singularity():
    """Exact twins (mirror_jitter 0) make each pair's Jacobian columns dependent: the input-weight
    and bias columns of j and j + h are opposite, the output columns equal, so JᵀJ loses
    h·(n_in + 2) ranks (Amari's overlap singularity).  A jitter restores full rank, keeps the
    other draws, and the initial NN output is O(jitter) (it vanishes with the jitter)."""
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(200, 3, generator=g, dtype=torch.float64)

    def made(jitter):
        m = PGNN(2, 1, physics=RigidBodyForward(TS), hidden=(6,), out_init="mirrored", out_init_scale=1.0,
                 seed=4, mirror_jitter=jitter)
        m.fit_normalisation(phi)
        m.set_physics_estimate([0.05, 2.5, 0.5])
        return m

    exact, small, jit = made(0.0), made(1e-3), made(0.1)
    # the draws before the jitter are unchanged: first units and the output layer equal
    assert torch.equal(exact.layers[0].weight[:3], jit.layers[0].weight[:3])
    assert torch.equal(exact.layers[1].weight, jit.layers[1].weight)
    d = (jit.layers[0].weight[3:] - jit.layers[0].weight[:3]).detach().abs()
    assert 0 < float(d.max()) <= 0.1 * math.sqrt(6.0 / 9) + 1e-15      # jitter × Glorot bound
    n_nn = exact.n_params - 3
    ranks = [int(torch.linalg.matrix_rank(m.jacobian(m.parameter_vector(), m.prepare(phi))[:, 3:]))
             for m in (exact, jit)]
    assert ranks[0] == n_nn - 3 * (3 + 2)      # 3 pairs × (3 inputs + bias + output weight)
    assert ranks[1] == n_nn
    with torch.no_grad():                      # the initial NN output scales with the jitter
        o_small, o_jit = (float(m.nn_part(phi).abs().max()) for m in (small, jit))
    assert 0 < o_small < o_jit and 50 < o_jit / o_small < 200
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="mirror_jitter"):
            made(bad)


@pytest.mark.parametrize("use_numpy", [True, False])
def test_tanh_is_numpys_on_plain_data_and_torchs_where_traced(use_numpy, monkeypatch):
    """pipeline/models/activations.py: one tanh for every plain forward pass (numpy's where it runs
    its AVX-512 loop, else torch's: the same bits in the training residual, its kept activations and
    g_value), torch's where autograd or torch.func traces the tensor, so derivatives stay exact
    (1 - tanh² to rounding) and never see numpy."""
    from pipeline.models import activations
    from pipeline.models.activations import Tanh, tanh, tanh_
    monkeypatch.setattr(activations, "_NUMPY", use_numpy)
    assert activations.IMPLEMENTATION.startswith("numpy (") == (activations._TARGET in activations._SIMD_TARGETS)
    z = torch.linspace(-20.0, 20.0, 4001, dtype=torch.float64).reshape(-1, 1) * torch.tensor([[1.0, 0.01]],
                                                                                             dtype=torch.float64)
    t = tanh(z)
    assert np.array_equal(t.numpy(), np.tanh(z.numpy()) if use_numpy else torch.tanh(z).numpy())
    # ≤ 1 ulp from torch's tanh (both claim ≤ 1 ulp from the exact value)
    assert np.all(np.abs(t.numpy() - torch.tanh(z).numpy()) <= np.spacing(np.abs(t.numpy())))
    w = z.clone()
    assert tanh_(w) is w and torch.equal(w, t)
    for s in (z[7, 0], z[::3, 1]):                           # a 0-d tensor, a strided view
        assert torch.equal(tanh(s), t[7, 0] if s.dim() == 0 else t[::3, 1])
    with torch.no_grad():                                  # data of a parameter, not traced
        p = z.clone().requires_grad_()
        assert np.array_equal(Tanh()(p * 1.0).numpy(), t.numpy())
    x = z[::400, 0].clone()
    d = 1.0 - torch.tanh(x) ** 2
    for J in (torch.func.jacfwd(tanh)(x), torch.func.jacrev(tanh)(x),
              torch.func.jacfwd(lambda v: tanh_(v * 1.0))(x)):
        torch.testing.assert_close(J, torch.diag(d), rtol=1e-15, atol=2e-16)   # 1 - tanh² ≤ 1: ulps of 1
    xr = x.clone().requires_grad_()
    Tanh()(xr).sum().backward()
    torch.testing.assert_close(xr.grad, d, rtol=1e-15, atol=2e-16)


def test_a_screened_restart_continues_from_its_best_validation_iterate_with_the_costs_before_it(monkeypatch):
    """With early stopping the screening run returns its best-validation iterate, here accepted step 2 of 4. The
    continuation starts there: the statistical window's past is the costs before it ([10, 9], not the run's
    [10, 9, 8, 7.5], whose later, lower costs made the window test pass at once), and the restart's history
    splices at it (no jump up from 7.4 to 8)."""
    from pipeline.identify import narx
    from pipeline.identify.lm import LMResult
    m = PGNN(2, 1, physics=RigidBodyForward(TS), hidden=(2,))
    p = m.parameter_vector().numel()
    calls = []

    def fake_lm(residual, theta0, *, max_iter, stat_history=None, **kw):
        calls.append((theta0.clone(), max_iter, stat_history))
        if stat_history is None:        # a screening run: best validation at accepted step 2 of 4
            c0 = 10.0 + len(calls)      # restart 0 has the lowest cost
            return LMResult(torch.full((p,), float(len(calls))), c0 - 2, [c0, c0 - 1, c0 - 2, c0 - 2.5, c0 - 2.6], 4,
                            False, "max_iter", [5.0, 4.0, 3.0, 3.2, 3.3], 3.0)
        return LMResult(theta0 + 1, 6.0, [9.0, 7.0, 6.0], 3, True, "early_stop", [3.0, 2.9, 2.8], 2.8)

    monkeypatch.setattr(narx, "levenberg_marquardt", fake_lm)
    out, best = narx.best_of_restarts(m, None, None, 2, 0, val_fn=lambda th: 0.0, max_iter=20, screen_iter=4)
    assert best == 0 and len(calls) == 3
    theta0, budget, past = calls[2]
    assert torch.equal(theta0, torch.full((p,), 1.0)) and budget == 16 and past == [11.0, 10.0]
    assert out[0].history == [11.0, 10.0, 9.0, 7.0, 6.0] and out[0].val_history == [5.0, 4.0, 3.0, 2.9, 2.8]
    assert out[0].n_iter == 7 and out[0].message == "early_stop"
