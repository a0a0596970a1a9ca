"""Orthogonal projection-based regulariser ([K] Section IV–V, Alg. 19) and the PGNN with
shared AR dynamics ([K] (6)).

Tolerances: the filter-based regulariser is compared with dense linear algebra on the
convolution matrix of [K] (26) (same quantity, different rounding: 1e-10 relative); exact
statements of [K] Corollary 17 are checked to 1e-8 (a quadratic problem solved by LM to
its stopping tolerance).
"""
import warnings

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import torch
from torch import nn

from pipeline.identify.orthogonal import (RankDeficientModelError, interpretability, model_subspace,
                                          orthogonal_regularizer, spread_over_inits, subspace_share)
from pipeline.identify.sk import SKNotConvergedWarning, oe_cost, prepare_data, sk_iterations
from pipeline.models.rational import (RationalFeedforward, Segments, basis_coefficients,
                                      filter_segments)
from pipeline.models.shared_ar import (MLP, ReferenceWindow, ResidualMLP, SharedARPGNN,
                                       make_approximator, per_sample_jacobian)

TS = 1e-3


def _dense_W(den, n):
    """Convolution matrix of 1/B ([K] (26)) from its impulse response."""
    h = scipy.signal.lfilter([1.0], den, np.r_[1.0, np.zeros(n - 1)])
    return scipy.linalg.toeplitz(h, np.zeros(n))


def _smooth_refs(rng, n=(300, 250)):
    return [np.cumsum(np.cumsum(rng.standard_normal(k))) * 1e-6 for k in n]


def _true_rational(n_a=3, poles=(0.99, 0.95 + 0.03j, 0.95 - 0.03j)):
    beta = basis_coefficients(np.real(np.poly(poles)), "delta", TS)
    m = RationalFeedforward(n_a, len(poles), basis="delta", Ts=TS)
    m.set_theta(np.r_[np.linspace(1.0, 0.2, n_a) * 10.0 ** -np.arange(n_a) * 3, beta[1:] / beta[0]])
    return m


# ----------------------------------------------------------------------------- regulariser
@pytest.mark.parametrize("column_scale", [False, True])
def test_regularizer_equals_dense_linear_algebra(column_scale):
    rng = np.random.default_rng(0)
    N, seg = 60, Segments((60,))
    M = rng.standard_normal((N, 4))
    g = rng.standard_normal(N)
    den = np.real(np.poly([0.9, 0.5]))
    W = _dense_W(den, N)
    # dense: W M D = U1 Σ Vᵀ, R = ‖(ΣVᵀ)^{-1} U1ᵀ W g‖²  ([K] (28), (29))
    D = np.diag(1 / np.linalg.norm(W @ M, axis=0)) if column_scale else np.eye(4)
    U1, s, Vt = np.linalg.svd(W @ M @ D, full_matrices=False)
    R_dense = np.sum((np.linalg.inv(np.diag(s) @ Vt) @ U1.T @ W @ g) ** 2)
    sub = model_subspace(filter_segments(M, [1.0], den, seg), column_scale=column_scale)
    R = orthogonal_regularizer(sub, filter_segments(g, [1.0], den, seg))
    assert R == pytest.approx(R_dense, rel=1e-10)
    # [K] (20): the coordinates are the (scaled) least-squares coefficients of W g on W M
    th = np.linalg.lstsq(W @ M @ D, W @ g, rcond=None)[0]
    np.testing.assert_allclose(sub.coordinates(filter_segments(g, [1.0], den, seg)), th, rtol=1e-10)
    # share of W g in im(W M)
    P = U1 @ U1.T
    share = np.linalg.norm(U1.T @ W @ g) / np.linalg.norm(W @ g)
    assert subspace_share(sub, W @ g) == pytest.approx(share, rel=1e-12)
    assert np.linalg.norm(sub.project_out(W @ g) - (np.eye(N) - P) @ W @ g) < 1e-12 * np.linalg.norm(W @ g)


def test_rank_deficient_subspace_raises_with_smallest_singular_value():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((50, 2))
    M = np.column_stack([a, a @ [1.0, -2.0]])          # third column dependent
    with pytest.raises(RankDeficientModelError, match=r"Assumption 10.*smallest singular value"):
        model_subspace(M)
    sub = model_subspace(M, rank_deficient="truncate")  # minimum-norm least squares
    assert sub.p == 2 and sub.n_truncated == 1
    y = rng.standard_normal(50)
    D = 1 / np.linalg.norm(M, axis=0)
    np.testing.assert_allclose(sub.solve(y), D * (np.linalg.pinv(M * D, rcond=1e-12) @ y), rtol=1e-9)


# ----------------------------------------------------------------------------- PGNN pieces
class _TiedLayers(nn.Module):
    """The same Linear applied twice (shared weights: per-sample gradients add up)."""

    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(3, 3, dtype=torch.float64)
        self.out = nn.Linear(3, 1, bias=False, dtype=torch.float64)

    def forward(self, x):
        return self.out(torch.tanh(self.lin(torch.tanh(self.lin(x))))).squeeze(-1)


@pytest.mark.parametrize("module", [MLP(3, (4, 5), seed=1), ResidualMLP(3, width=4, n_blocks=2, seed=2),
                                    _TiedLayers()])
def test_per_sample_jacobian_matches_autograd(module):
    X = torch.from_numpy(np.random.default_rng(2).standard_normal((40, 3)))
    y, J = per_sample_jacobian(module, X)
    phi = nn.utils.parameters_to_vector(module.parameters()).detach()

    def jac_ref():   # one backward pass per sample (plain autograd)
        rows = []
        for k in range(X.shape[0]):
            module.zero_grad()
            module(X[k:k + 1]).sum().backward()
            rows.append(torch.cat([p.grad.reshape(-1) for p in module.parameters()]))
        return torch.stack(rows)
    with torch.no_grad():
        y_ref = module(X).reshape(-1)
    assert torch.allclose(J, jac_ref(), rtol=0, atol=1e-13) and torch.allclose(y, y_ref, atol=0)
    # at other parameters, the module is left unchanged
    y2, J2 = per_sample_jacobian(module, X, phi + 0.1)
    assert torch.equal(nn.utils.parameters_to_vector(module.parameters()), phi)
    nn.utils.vector_to_parameters(phi + 0.1, module.parameters())
    assert torch.allclose(J2, jac_ref(), atol=1e-13)
    nn.utils.vector_to_parameters(phi, module.parameters())


@pytest.mark.parametrize("approx", ["mlp", "mlp_no_out_bias", "residual"])
def test_g_jvp_and_vjp_equal_the_jacobian_products(approx):
    """∂g/∂φ v and (∂g/∂φ)ᵀ w without ∂g/∂φ (closed form for a tanh MLP, with and without the kept
    activations; torch.func otherwise) against g_and_jacobian's J, at a φ that is not the model's
    (left unchanged), with g_gain ≠ 1.  Tolerance 1e-13 of ‖J‖‖v‖: other sums of the same products."""
    rng = np.random.default_rng(5)
    rs = _smooth_refs(rng)
    w = ReferenceWindow(3, "delta", TS).fit(rs)
    g = {"mlp": MLP(4, (6, 5), seed=0, out_bias=True), "mlp_no_out_bias": MLP(4, (6,), seed=1),
         "residual": ResidualMLP(4, width=4, n_blocks=2, seed=2)}[approx]
    m = SharedARPGNN(3, 3, g, w, basis="delta", Ts=TS)
    m.scale_extra(0.7)
    assert m.closed_form_jacobian == approx.startswith("mlp")
    inp = m.inputs(rs)
    phi0 = m.phi
    phi = phi0 + 0.1 * torch.from_numpy(rng.standard_normal(phi0.numel()))
    _, J = m.g_and_jacobian(inp, phi)
    J = J.numpy()
    acts = m.g_forward(inp, phi)[1] if m.closed_form_jacobian else None
    for a in ([None, acts] if acts is not None else [None]):
        v, wv = rng.standard_normal(J.shape[1]), rng.standard_normal(J.shape[0])
        tol = 1e-13 * np.linalg.norm(J)
        np.testing.assert_allclose(m.g_jvp(inp, phi, torch.from_numpy(v), a).numpy(), J @ v, rtol=0,
                                   atol=tol * np.linalg.norm(v))
        np.testing.assert_allclose(m.g_vjp(inp, phi, wv, a).numpy(), J.T @ wv, rtol=0, atol=tol * np.linalg.norm(wv))
    assert torch.equal(m.phi, phi0)


def test_per_sample_jacobian_generic_module_falls_back_to_torch_func():
    class Scaled(nn.Module):                       # a parameter outside any nn.Linear
        def __init__(self):
            super().__init__()
            self.lin = nn.Linear(2, 1, dtype=torch.float64)
            self.s = nn.Parameter(torch.tensor(1.5, dtype=torch.float64))

        def forward(self, x):
            return torch.tanh(self.s * self.lin(x)).squeeze(-1)
    m = Scaled()
    X = torch.from_numpy(np.random.default_rng(3).standard_normal((10, 2)))
    y, J = per_sample_jacobian(m, X)
    eps = 1e-6
    phi = nn.utils.parameters_to_vector(m.parameters()).detach()
    for i in range(phi.numel()):
        e = torch.zeros_like(phi)
        e[i] = eps
        yp, _ = per_sample_jacobian(m, X, phi + e)
        ym, _ = per_sample_jacobian(m, X, phi - e)
        assert torch.allclose(J[:, i], (yp - ym) / (2 * eps), atol=1e-8)


def test_reference_window_delta_features_and_normalisation():
    rng = np.random.default_rng(4)
    r, seg = Segments.concat(_smooth_refs(rng))
    w = ReferenceWindow(2, "delta", TS).fit(r, seg)
    X = w.features(r, seg)
    a = seg.split(r)[1]
    np.testing.assert_allclose(X[seg.bounds[1][0]:, 1], np.diff(a, prepend=0.0) / TS, rtol=1e-12)
    Xn = w(torch.from_numpy(X)).numpy()
    np.testing.assert_allclose(Xn.mean(axis=0), 0, atol=1e-12)
    np.testing.assert_allclose(Xn.std(axis=0), 1, rtol=1e-12)


def test_pgnn_output_is_model_plus_approximator_through_shared_ar():
    rng = np.random.default_rng(5)
    rs = _smooth_refs(rng)
    true = _true_rational()
    w = ReferenceWindow(4, "delta", TS).fit(rs)
    m = SharedARPGNN(3, 3, make_approximator("residual", 5, seed=3), w, basis="delta", Ts=TS,
                     a=true.a.detach().numpy(), b=true.b.detach().numpy())
    inp = m.inputs(rs)
    with torch.no_grad():
        f = m.simulate(inp).numpy()
        f_M, f_C = m.parts(inp)
        g = m.g(w(inp["X"])).numpy()
    ref = np.concatenate([scipy.signal.lfilter([1.0], m.denominator(), x)
                          for x in inp["segments"].split(inp["R"] @ true.a.detach().numpy() + g)])
    np.testing.assert_allclose(f, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_allclose(f_M.numpy() + f_C.numpy(), f, rtol=0, atol=1e-12 * np.abs(f).max())


# ----------------------------------------------------------------------------- Corollary 17
def _linear_in_span_pgnn(seed, n_a=3):
    """PGNN whose g_φ = φᵀ [r, δr] is exactly a combination of M's first columns
    (unnormalised window: mean 0, std 1, no bias)."""
    g = nn.Linear(2, 1, bias=False, dtype=torch.float64)
    with torch.no_grad():
        g.weight.copy_(torch.from_numpy(np.random.default_rng(seed).normal(0, 1.0, (1, 2))))

    class G(nn.Module):
        def __init__(self):
            super().__init__()
            self.lin = g

        def forward(self, x):
            return self.lin(x).squeeze(-1)
    return SharedARPGNN(n_a, 3, G(), ReferenceWindow(1, "delta", TS), basis="delta", Ts=TS)


def _corollary_data():
    rng = np.random.default_rng(6)
    rs = _smooth_refs(rng)
    true = _true_rational()
    # plus an effect outside the model class, so that the optimum has a nonzero cost
    fs = [f + 0.05 * np.tanh(100 * np.diff(r, prepend=0.0) / TS) for f, r in zip(true.feedforward(rs), rs)]
    return rs, fs


def test_regularizer_drives_in_span_approximator_to_zero_and_theta_absorbs_it():
    rs, fs = _corollary_data()
    kw = dict(max_iter=30, tol=1e-12, lm_max_iter=50, lm_ftol=1e-15, lm_gtol=1e-15)
    rat = sk_iterations(RationalFeedforward(3, 3, basis="delta", Ts=TS), rs, fs, **kw)
    res = sk_iterations(_linear_in_span_pgnn(seed=0), rs, fs, regularizer="orthogonal", lam=1.0, **kw)
    m = res.model
    d = prepare_data(m, rs, fs)
    with torch.no_grad():
        g = m.exogenous_extra(d["inputs"]).numpy()
    assert np.linalg.norm(g) < 1e-8 * np.linalg.norm(d["f"])            # g_φ → 0
    np.testing.assert_allclose(m.theta, rat.model.theta, rtol=1e-8)     # θ = model-only fit
    assert oe_cost(m, d) == pytest.approx(oe_cost(rat.model, d), rel=1e-8)


def test_without_regularizer_theta_is_not_unique():
    rs, fs = _corollary_data()
    kw = dict(max_iter=30, tol=1e-12, lm_max_iter=50, regularizer="none")
    r1 = sk_iterations(_linear_in_span_pgnn(seed=1), rs, fs, **kw)
    r2 = sk_iterations(_linear_in_span_pgnn(seed=2), rs, fs, **kw)
    d = prepare_data(r1.model, rs, fs)
    J1, J2 = oe_cost(r1.model, d), oe_cost(r2.model, d)
    assert J1 == pytest.approx(J2, rel=1e-8)                             # equal cost ...
    rel = np.abs(r1.model.theta - r2.model.theta) / np.abs(r1.model.theta)
    assert rel[:2].max() > 1e-3                                         # ... different θ
    # the difference is exactly the approximator's weights moved into a (Corollary 14)
    w1 = r1.model.g.lin.weight.detach().numpy().ravel() * float(r1.model.g_gain)
    w2 = r2.model.g.lin.weight.detach().numpy().ravel() * float(r2.model.g_gain)
    np.testing.assert_allclose(r1.model.theta[:2] + w1, r2.model.theta[:2] + w2, rtol=1e-8)


def test_interpretability_quantities():
    rs, fs = _corollary_data()
    w = ReferenceWindow(3, "delta", TS).fit(rs)
    m = SharedARPGNN(3, 3, MLP(4, (6,), seed=0), w, basis="delta", Ts=TS)
    with warnings.catch_warnings():   # 3 short iterations: not converged, on purpose
        warnings.simplefilter("ignore", SKNotConvergedWarning)
        res = sk_iterations(m, rs, fs, max_iter=3, tol=1e-6, lm_max_iter=10, regularizer="orthogonal")
    it = interpretability(res.model, rs, fs, theta_true=_true_rational().theta)
    f_M, f_C = it["f_M"], it["f_C"]
    assert 0 <= it["share_C_in_model"] <= 1
    assert it["ratio_C_M"] == pytest.approx(np.linalg.norm(f_C) / np.linalg.norm(f_M))
    assert it["corr_M_C"] == pytest.approx(np.corrcoef(f_M, f_C)[0, 1])
    assert it["theta_rel_err"].shape == (6,)
    # spread: identical runs have none; a shifted copy has |shift| / rms
    assert spread_over_inits([f_M, f_M], f_M) == 0
    assert spread_over_inits([f_M, f_M + 2.0], np.full_like(f_M, 1.0)) == pytest.approx(1.0)


@pytest.mark.slow
def test_sk_restarts_in_worker_processes_match_sequential_runs():
    # the process pool (spawn) returns the same results as running the restarts in-process
    from pipeline.identify.sk import sk_restarts
    rs, fs = _corollary_data()
    w = ReferenceWindow(3, "delta", TS).fit(rs)
    models = [SharedARPGNN(3, 3, MLP(4, (6,), seed=s), w, basis="delta", Ts=TS) for s in (0, 1)]
    kw = dict(max_iter=2, tol=0.0, lm_max_iter=5, regularizer="orthogonal")
    par = sk_restarts(models, rs, fs, n_jobs=2, **kw)
    seq = sk_restarts(models, rs, fs, n_jobs=1, **kw)
    for (a, _, wa), (b, _, wb) in zip(par, seq):
        assert a.J_OE == b.J_OE and wa and wb
        np.testing.assert_array_equal(a.model.theta, b.model.theta)


# ----------------------------------------------------------------------------- geodesic J v, Jᵀ w
def _captured_varpro(monkeypatch, model, rs, fs, regularizer, lam):
    """The residual and Jacobian closures of the last SK step's variable projection (sk._varpro_step)."""
    import pipeline.identify.sk as sk
    seen, lm = [], sk.levenberg_marquardt

    def spy(residual, phi0, *, jacobian, **kw):
        seen.append((residual, phi0.clone(), jacobian))
        return lm(residual, phi0, jacobian=jacobian, **kw)
    monkeypatch.setattr(sk, "levenberg_marquardt", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SKNotConvergedWarning)
        sk_iterations(model, rs, fs, regularizer=regularizer, lam=lam, max_iter=2, tol=1e-30,
                      lm_max_iter=5, geodesic=True)
    return seen[-1]


@pytest.mark.parametrize("case", ["mlp-orthogonal", "mlp-none", "in_span-orthogonal"])
def test_geodesic_products_equal_the_explicit_jacobian(monkeypatch, case):
    """The geodesic LM's J v and Jᵀ w of the SK step (one directional derivative of g and one
    filtering pass, J never formed) equal the explicit J's products, flat columns included (the
    in-span approximator moves g only inside im(W M): every column is flat, [K] Corollary 14).
    Tolerance 1e-11 of ‖J‖‖v‖: the same sums in another order (torch.func vs per-sample rows)."""
    model, reg = case.split("-")
    rs, fs = _corollary_data()
    if model == "mlp":
        m = SharedARPGNN(3, 3, MLP(4, (6,), seed=0), ReferenceWindow(3, "delta", TS).fit(rs),
                         basis="delta", Ts=TS)
    else:
        m = _linear_in_span_pgnn(seed=0)
    residual, phi0, jac = _captured_varpro(monkeypatch, m, rs, fs, reg, 1.0 if reg == "orthogonal" else 0.0)
    rng = np.random.default_rng(0)
    phi = phi0 + 1e-3 * torch.from_numpy(rng.standard_normal(phi0.numel())) * phi0.abs().max()
    r = residual(phi)
    jac.normal_equations(phi, r)                     # as LM does before a geodesic step
    J = jac(phi).numpy()
    if model == "in_span":
        n_main = rs[0].size + rs[1].size
        assert np.all(J[:n_main] == 0)               # every column flat in the main rows
        assert reg != "orthogonal" or np.linalg.norm(J[n_main:]) > 0   # the regulariser rows see them
    for _ in range(3):
        v = torch.from_numpy(rng.standard_normal(J.shape[1]))
        w = torch.from_numpy(rng.standard_normal(J.shape[0]))
        jv, jtw = jac.jvp(phi, v).numpy(), jac.vjp(phi, w).numpy()
        scale = np.linalg.norm(J)
        np.testing.assert_allclose(jv, J @ v.numpy(), rtol=0, atol=1e-11 * scale * np.linalg.norm(v))
        np.testing.assert_allclose(jtw, J.T @ w.numpy(), rtol=0, atol=1e-11 * scale * np.linalg.norm(w))
