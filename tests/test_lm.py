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
