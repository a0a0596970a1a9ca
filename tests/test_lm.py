"""Tests of the shared Levenberg–Marquardt solver (pipeline/identify/lm.py)."""
import numpy as np
import pytest
import torch

from pipeline.identify.lm import autodiff_jacobian, levenberg_marquardt


def _lip_problem(col_scales, seed=0, n=400):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(n, len(col_scales), generator=g, dtype=torch.float64) * torch.tensor(col_scales)
    b = torch.randn(n, generator=g, dtype=torch.float64)
    return A, b, torch.linalg.lstsq(A, b).solution  # QR-based reference (gelsy)


def test_reaches_closed_form_least_squares_optimum():
    # well-scaled linear-in-parameters problem, default tolerances: the LS optimum to 1e-10
    # (cond(A) ~ 3, so rounding of the reference is ~1e-15)
    A, b, x = _lip_problem([1.0, 2.0, 0.5, 1.5, 1.0])
    res = levenberg_marquardt(lambda t: A @ t - b, torch.zeros(5, dtype=torch.float64),
                              jacobian=lambda t: A)
    assert res.converged, res.message
    assert float((res.theta - x).norm() / x.norm()) < 1e-10
    assert res.cost == pytest.approx(float((A @ x - b).square().sum()), rel=1e-12)


def test_badly_scaled_columns_reach_optimum_with_ftol_zero():
    # columns spanning 1e-3..1e3 (cond ~ 1e6): cost-based stopping cannot see parameter
    # errors below ~sqrt(eps); with ftol = 0 the scaled gradient test drives the relative
    # error to rounding (bound: cond · eps ~ 1e-10)
    A, b, x = _lip_problem(list(np.logspace(-3, 3, 8)))
    res = levenberg_marquardt(lambda t: A @ t - b, torch.zeros(8, dtype=torch.float64),
                              jacobian=lambda t: A, ftol=0.0, gtol=1e-13, max_iter=200)
    assert float((res.theta - x).norm() / x.norm()) < 1e-10


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_autodiff_jacobian_default_matches_explicit():
    A, b, x = _lip_problem([1.0, 3.0, 0.3])
    r1 = levenberg_marquardt(lambda t: A @ t - b, torch.zeros(3, dtype=torch.float64))
    assert float((r1.theta - x).norm() / x.norm()) < 1e-10
    # jacfwd (tall) and jacrev (wide) give the exact Jacobian of a nonlinear residual
    f = lambda t: torch.stack([t[0] * t[1], torch.sin(t[1]), t[0] ** 3])
    t0 = torch.tensor([0.3, -1.2], dtype=torch.float64)
    J = autodiff_jacobian(f, t0)
    Je = torch.tensor([[-1.2, 0.3], [0.0, np.cos(-1.2)], [3 * 0.09, 0.0]], dtype=torch.float64)
    assert torch.allclose(J, Je, rtol=1e-14, atol=1e-15)
    g = lambda t: t[:1] * t[1]  # wide: 1 residual, 2 parameters -> jacrev
    assert torch.allclose(autodiff_jacobian(g, t0), torch.tensor([[-1.2, 0.3]], dtype=torch.float64))


def test_rosenbrock_and_history():
    rosen = lambda t: torch.stack([10 * (t[1] - t[0] ** 2), 1 - t[0]])
    hist = []
    res = levenberg_marquardt(rosen, torch.tensor([-1.2, 1.0], dtype=torch.float64), max_iter=200,
                              callback=lambda it, th, c: hist.append((it, c)))
    assert torch.allclose(res.theta, torch.ones(2, dtype=torch.float64), atol=1e-8)
    assert res.history[0] == pytest.approx(24.2)  # 100·(1 - 1.44)² + 2.2²
    assert all(b <= a for a, b in zip(res.history, res.history[1:]))  # accepted steps only
    assert [c for _, c in hist] == res.history[1:]
    assert res.n_iter >= len(res.history) - 1


def test_max_iter_and_callback_stop():
    rosen = lambda t: torch.stack([10 * (t[1] - t[0] ** 2), 1 - t[0]])
    res = levenberg_marquardt(rosen, torch.tensor([-1.2, 1.0], dtype=torch.float64), max_iter=3)
    assert res.message == "max_iter" and res.n_iter == 3 and not res.converged
    res = levenberg_marquardt(rosen, torch.tensor([-1.2, 1.0], dtype=torch.float64),
                              callback=lambda it, th, c: it >= 2)
    assert res.message == "callback" and len(res.history) == 3


def test_early_stopping_returns_best_validation_iterate():
    # training optimum (1, 1); the validation optimum lies on the way there, so the
    # validation cost first falls then rises
    rosen = lambda t: torch.stack([10 * (t[1] - t[0] ** 2), 1 - t[0]])
    target = torch.tensor([0.0, 0.0], dtype=torch.float64)
    val = lambda t: float((t - target).square().sum())
    its = []
    res = levenberg_marquardt(rosen, torch.tensor([-1.2, 1.0], dtype=torch.float64), max_iter=200,
                              val_cost=val, patience=3, callback=lambda it, th, c: its.append(th.clone()))
    all_its = [torch.tensor([-1.2, 1.0], dtype=torch.float64)] + its
    vals = [val(t) for t in all_its]
    assert res.message == "early_stop"
    assert res.val_history == pytest.approx(vals)
    k = int(np.argmin(vals))
    assert torch.equal(res.theta, all_its[k])
    assert res.val_cost == pytest.approx(vals[k])
    assert len(vals) - 1 - k == 3  # stopped after exactly `patience` non-improving steps
    assert res.cost == pytest.approx(float(rosen(res.theta).square().sum()))


def test_bad_input_raises():
    with pytest.raises(TypeError, match="float64"):
        levenberg_marquardt(lambda t: t, torch.zeros(2, dtype=torch.float32))
    with pytest.raises(ValueError, match="shape"):
        levenberg_marquardt(lambda t: t, torch.ones(2, dtype=torch.float64),
                            jacobian=lambda t: torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="NaN"):
        levenberg_marquardt(lambda t: t / 0.0 * 0.0, torch.zeros(2, dtype=torch.float64))


def test_nonfinite_jacobian_is_not_read_as_a_stationary_point():
    """∂√|θ|/∂θ is inf at θ = 0: the scaled gradient test saw NaN columns as zero and stopped 'gtol', converged,
    at cost 5 (the minimum is 0). Now the stop says what happened and is not converged."""
    res = levenberg_marquardt(lambda th: torch.stack([torch.sqrt(th[0].abs()) - 1.0, th[1] - 2.0]),
                              torch.zeros(2, dtype=torch.float64), max_iter=50)
    assert res.message == "nonfinite_jacobian" and not res.converged and res.n_iter == 0
    assert res.cost == pytest.approx(5.0, rel=1e-15)


def test_normal_equations_from_row_blocks():
    # JᵀJ, Jᵀr summed over row blocks equal the unblocked ones to rounding, and an LM given them
    # (jacobian.normal_equations) reaches the same least-squares optimum without forming J
    from pipeline.identify.lm import normal_equations_from_blocks
    A, b, x = _lip_problem([1.0, 2.0, 0.5, 1.5, 1.0], n=1000)
    r = torch.randn(1000, dtype=torch.float64)
    G, g = normal_equations_from_blocks(((a, A[a:a + 300]) for a in range(0, 1000, 300)), r, 5)
    assert torch.equal(G, G.T)
    assert torch.allclose(G, A.T @ A, rtol=1e-14, atol=1e-14 * float(G.diagonal().max()))
    assert torch.allclose(g, A.T @ r, rtol=1e-14, atol=1e-13)

    def jac(t):
        raise AssertionError("J must not be formed")
    jac.normal_equations = lambda t, res: normal_equations_from_blocks(
        ((a, A[a:a + 300]) for a in range(0, 1000, 300)), res, 5)
    out = levenberg_marquardt(lambda t: A @ t - b, torch.zeros(5, dtype=torch.float64), jacobian=jac)
    assert out.converged, out.message
    assert float((out.theta - x).norm() / x.norm()) < 1e-10


# ---------------------------------------------------------------------------------------------
# geodesic acceleration and the statistical stop (issue 19)
# ---------------------------------------------------------------------------------------------
def _tanh_net_problem(noise: float, n1: int = 8, N: int = 400):
    """A one-hidden-layer tanh fit: curvature-limited like the PGNN criteria (plain LM crawls)."""
    x = torch.linspace(-2, 2, N, dtype=torch.float64)

    def net(th):
        return torch.tanh(x[:, None] * th[:n1] + th[n1:2 * n1]) @ th[2 * n1:3 * n1] + th[3 * n1]

    y = torch.sin(2 * x) * torch.exp(-0.3 * x ** 2) + 0.3 * x
    y = y + noise * torch.randn(N, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    th0 = torch.randn(3 * n1 + 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return (lambda th: net(th) - y), th0


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_geodesic_reaches_plain_lm_minimum_in_fewer_jacobians():
    # a linear-in-parameters problem has r_vv = 0: the geodesic step is the plain step and both
    # reach the closed-form optimum
    A, b, x = _lip_problem([1.0, 2.0, 0.5, 1.5, 1.0])
    res = levenberg_marquardt(lambda t: A @ t - b, torch.zeros(5, dtype=torch.float64),
                              jacobian=lambda t: A, geodesic=True)
    assert res.converged and float((res.theta - x).norm() / x.norm()) < 1e-10
    # the tanh fit: plain LM with 600 Jacobians against geodesic LM with at most 300
    res_fn, th0 = _tanh_net_problem(0.0)
    plain = levenberg_marquardt(res_fn, th0, max_iter=600, ftol=0.0, gtol=0.0)
    geo = levenberg_marquardt(res_fn, th0, max_iter=300, ftol=0.0, gtol=0.0, geodesic=True)
    assert geo.n_jac <= 300 < plain.n_jac
    assert geo.n_accel > 0.5 * (len(geo.history) - 1)       # the acceleration is taken, not refused
    # fewer Jacobians and a lower cost than plain LM with twice as many (measured: 3e-12 vs 2e-7)
    assert geo.cost < 0.1 * plain.cost
    assert all(b <= a for a, b in zip(geo.history, geo.history[1:]))


def test_geodesic_needs_jvp_vjp_with_normal_equations():
    A, b, _ = _lip_problem([1.0, 2.0])

    def jac(t):
        return A
    jac.normal_equations = lambda t, r: (A.T @ A, A.T @ r)
    with pytest.raises(ValueError, match="jvp"):
        levenberg_marquardt(lambda t: A @ t - b, torch.zeros(2, dtype=torch.float64), jacobian=jac,
                            geodesic=True)
    jac.jvp = lambda t, v: A @ v
    jac.vjp = lambda t, w: A.T @ w
    res = levenberg_marquardt(lambda t: A @ t - b, torch.zeros(2, dtype=torch.float64), jacobian=jac,
                              geodesic=True)
    assert res.converged


def test_statistical_stop_fires_on_noisy_data_not_on_noise_free():
    # noisy (σ = 1e-3, N = 400): the cost settles at N σ² ≈ 4e-4 and the rule fires, within the
    # cost's sampling fluctuation sqrt(2/N) ≈ 7 % of the optimum. The optimum: a run to ftol = 1e-10 (845 steps,
    # 1.4e-6 above the cost after 1500 steps, measured; stat stops 3 % above, 81-150 steps)
    res_fn, th0 = _tanh_net_problem(1e-3)
    long = levenberg_marquardt(res_fn, th0, max_iter=1500, ftol=1e-10, gtol=0.0, geodesic=True)
    assert long.message == "ftol"
    for geodesic in (False, True):
        stat = levenberg_marquardt(res_fn, th0, max_iter=3000, ftol=0.0, gtol=0.0, geodesic=geodesic,
                                   stat_window=10, stat_tol=0.1)
        assert stat.message == "stat" and stat.converged
        assert stat.n_iter < 500
        assert long.cost <= stat.cost <= long.cost * (1 + np.sqrt(2 / 400))
    # noise-free data of a model that can fit them exactly (sum of exponentials): the cost falls
    # geometrically to zero, so the rule never fires (the run ends on zero_cost / mu_max / gtol)
    t = torch.linspace(0, 5, 200, dtype=torch.float64)

    def model(th):
        return torch.exp(-th[0] * t) + torch.exp(-th[1] * t) + th[2] * torch.sin(th[3] * t)
    y = model(torch.tensor([0.5, 2.0, 0.3, 1.7], dtype=torch.float64))
    for geodesic in (False, True):
        res = levenberg_marquardt(lambda th: model(th) - y, torch.tensor([1.0, 3.0, 0.1, 1.2], dtype=torch.float64),
                                  max_iter=500, ftol=0.0, gtol=1e-14, geodesic=geodesic, stat_window=3)
        assert res.message != "stat" and res.converged
        assert res.cost < 1e-20


def test_statistical_stop_uses_n_data():
    # N enters as sqrt(2/N): a huge N makes the rule so strict it cannot fire before the cap
    res_fn, th0 = _tanh_net_problem(1e-3)
    res = levenberg_marquardt(res_fn, th0, max_iter=200, ftol=0.0, gtol=0.0, stat_window=10,
                              stat_tol=0.1, n_data=10 ** 14)
    assert res.message == "max_iter"
    with pytest.raises(ValueError, match="stat_window"):
        levenberg_marquardt(res_fn, th0, stat_window=-1)


def test_gauss_newton_decrement_is_the_remaining_decrease_of_a_linear_problem():
    # r = A θ - b is its own Gauss–Newton model: gᵀ(AᵀA)⁻¹g = C(θ) - min C exactly (up to the
    # ε = 1e-8 damping, a relative error below 1e-7 for this well-conditioned A)
    from pipeline.identify.lm import _gauss_newton_decrement
    A, b, x = _lip_problem([1.0, 2.0, 0.5, 1.5, 1.0])
    th = torch.zeros(5, dtype=torch.float64)
    r = A @ th - b
    s = 1.0 / torch.sqrt(torch.diagonal(A.T @ A))          # the solver's scaled variables
    A_s = (A.T @ A) * s[:, None] * s[None, :]
    dec = _gauss_newton_decrement(A_s, (A.T @ r) * s, torch.eye(5, dtype=torch.float64))
    c_min = float((A @ x - b) @ (A @ x - b))
    assert dec == pytest.approx(float(r @ r) - c_min, rel=1e-7)


def test_statistical_stop_waits_for_the_decrement_on_a_slow_crawl(monkeypatch):
    # Rosenbrock's curved valley (a = 1000) under N = 400 noise residuals: LM crawls along the
    # valley and the window rule alone stops after 17 steps, 1.65x the threshold 0.1·sqrt(2/N)·C
    # above the minimum C = ||e||². With the Gauss–Newton decrement (the remaining decrease of the
    # local model below the threshold) it stops within the threshold up to the valley's curvature,
    # which the quadratic model does not see (measured 1.08x; allowed 1.25x).
    import pipeline.identify.lm as lm
    N = 400
    e = torch.randn(N, generator=torch.Generator().manual_seed(3), dtype=torch.float64)

    def res_fn(th):
        return torch.cat([e, torch.stack([1000.0 * (th[1] - th[0] ** 2), 1 - th[0]])])
    th0 = torch.tensor([-1.2, 1.0], dtype=torch.float64)
    c_min = float(e @ e)
    threshold = 0.1 * np.sqrt(2 / N) * c_min
    res = levenberg_marquardt(res_fn, th0, max_iter=5000, ftol=0.0, gtol=0.0, stat_window=10, stat_tol=0.1,
                              mu0=100.0)
    assert res.message == "stat"
    assert res.cost - c_min <= 1.25 * threshold
    monkeypatch.setattr(lm, "DECREMENT_EPS", 1e300)      # decrement ~0: the window rule alone
    window = levenberg_marquardt(res_fn, th0, max_iter=5000, ftol=0.0, gtol=0.0, stat_window=10,
                                 stat_tol=0.1, mu0=100.0)
    assert window.message == "stat" and window.n_iter < res.n_iter
    assert window.cost - c_min > 1.5 * threshold


def test_the_damped_promise_stops_a_crawl_within_two_thresholds_and_the_full_one_within_one():
    # stat_promise='damped' (the measured fits) regularises the decrement by μ as well: on Rosenbrock's valley
    # (the crawl above) it stops where the window rule alone does, 1.47-1.68 thresholds above the minimum
    # (measured, noise seeds 3-5), the full Gauss–Newton promise at 1.08. That is the price: the damped one
    # ends a crawl whose full promise never comes true (the EMPS loop, pipeline/identify/lm.py)
    from pipeline.identify.lm import _gauss_newton_decrement
    N = 400
    for seed in (3, 4, 5):
        e = torch.randn(N, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)

        def res_fn(th):
            return torch.cat([e, torch.stack([1000.0 * (th[1] - th[0] ** 2), 1 - th[0]])])
        th0 = torch.tensor([-1.2, 1.0], dtype=torch.float64)
        c_min = float(e @ e)
        threshold = 0.1 * np.sqrt(2 / N) * c_min
        kw = dict(max_iter=5000, ftol=0.0, gtol=0.0, stat_window=10, stat_tol=0.1, mu0=100.0)
        full = levenberg_marquardt(res_fn, th0, **kw)
        damped = levenberg_marquardt(res_fn, th0, stat_promise="damped", **kw)
        assert full.message == damped.message == "stat" and damped.n_iter < full.n_iter
        assert full.cost - c_min <= 1.25 * threshold < damped.cost - c_min <= 2.0 * threshold
    # the damped decrement is gᵀ(A + μI)⁻¹g (a linear problem's closed form)
    A, b, _ = _lip_problem([1.0, 2.0, 0.5, 1.5, 1.0])
    g, eye = A.T @ (A @ torch.zeros(5, dtype=torch.float64) - b), torch.eye(5, dtype=torch.float64)
    want = float(g @ torch.linalg.solve(A.T @ A + 0.3 * eye, g))
    assert _gauss_newton_decrement(A.T @ A, g, eye, 0.3) == pytest.approx(want, rel=1e-12)
    with pytest.raises(ValueError, match="stat_promise"):
        levenberg_marquardt(res_fn, th0, stat_promise="trust")


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_statistical_stop_with_a_growing_window_waits_out_a_crawl():
    # a tanh fit under σ = 1e-4 noise crawls (plain LM: the cost still falls after 2000 steps).
    # A fixed window of 10 steps stops at step ~330; the window of the last 30 % of the run
    # (stat_frac, the [B2] setting) stops at ~1090, ~25 thresholds 0.1·sqrt(2/N)·C lower (measured
    # beside a 4000-step run: the fixed window stops 25 thresholds above its cost, the grown one 2)
    res_fn, th0 = _tanh_net_problem(1e-4)
    fixed = levenberg_marquardt(res_fn, th0, max_iter=2000, ftol=0.0, gtol=0.0, stat_window=10, stat_tol=0.1)
    grown = levenberg_marquardt(res_fn, th0, max_iter=2000, ftol=0.0, gtol=0.0, stat_window=10, stat_tol=0.1,
                                stat_frac=0.3)
    threshold = 0.1 * np.sqrt(2 / 400) * grown.cost
    assert fixed.message == grown.message == "stat"
    assert fixed.cost - grown.cost > 10 * threshold and grown.n_iter > 2 * fixed.n_iter
    # a restart continued after 300 screening steps (best_of_restarts): with the screening costs as
    # stat_history the window spans the whole run and the continuation stops where the uninterrupted
    # run does (measured 0.6 thresholds apart); without them its 10-step window stops it at once
    kw = dict(max_iter=2000, ftol=0.0, gtol=0.0, stat_window=10, stat_tol=0.1, stat_frac=0.3)
    first = levenberg_marquardt(res_fn, th0, max_iter=300, ftol=0.0, gtol=0.0)
    alone = levenberg_marquardt(res_fn, first.theta, **kw)
    cont = levenberg_marquardt(res_fn, first.theta, stat_history=first.history[:-1], **kw)
    assert alone.message == cont.message == "stat"
    assert alone.n_iter < 50 < 300 < cont.n_iter
    assert abs(cont.cost - grown.cost) < 2 * threshold < alone.cost - grown.cost
    with pytest.raises(ValueError, match="stat_frac"):
        levenberg_marquardt(res_fn, th0, stat_window=10, stat_frac=1.0)


def test_the_decrement_leaves_out_directions_below_its_eps_and_a_smaller_eps_counts_them(monkeypatch):
    """The statistical stop's Gauss–Newton decrement counts a direction of scaled curvature λ < ε as ε (lm.py
    docstring): a linear problem whose start is off its minimum along a 4.6e-12 direction, by 100 stop thresholds,
    stops there on 'stat' (the window saw no decrease, the discounted promise is small). With ε below λ the promise
    is the whole remaining decrease (the closed form of a linear problem) and the run goes on to the minimum."""
    import math

    from pipeline.identify import lm
    g = torch.Generator().manual_seed(0)
    N = 10000
    a, b, c = (torch.randn(N, generator=g, dtype=torch.float64) for _ in range(3))
    X = torch.stack([a, a + 3e-6 * b, c], 1)                     # two nearly collinear columns
    y = X.sum(1) + 0.1 * torch.randn(N, generator=g, dtype=torch.float64)
    xs = torch.linalg.lstsq(X, y[:, None]).solution[:, 0]
    c_min = float((X @ xs - y).square().sum())
    thr = 0.1 * math.sqrt(2 / N) * c_min
    s = torch.diagonal(X.T @ X).rsqrt()
    lam, V = torch.linalg.eigh(s[:, None] * (X.T @ X) * s[None, :])
    assert float(lam[0]) < 1e-10 < lm.DECREMENT_EPS * 1e3    # the weak direction is below ε
    v = s * V[:, 0]
    x0 = xs + math.sqrt(100 * thr / float(v @ (X.T @ X) @ v)) * v
    kw = dict(max_iter=500, ftol=1e-15, gtol=1e-15, stat_window=10, stat_tol=0.1)
    res = lm.levenberg_marquardt(lambda th: X @ th - y, x0, **kw)
    assert res.message == "stat" and 50 < (res.cost - c_min) / thr <= 100.01
    monkeypatch.setattr(lm, "DECREMENT_EPS", 1e-14)
    res = lm.levenberg_marquardt(lambda th: X @ th - y, x0, **kw)
    assert (res.cost - c_min) / thr < 1.0
