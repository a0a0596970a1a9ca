"""The shared numba state-space step against python-control (the kernels' building block)."""
import control
import numpy as np
from numba import njit

from pipeline.systems._statespace import ss_step, ss_step_columns


@njit
def _run(A, B, C, D, u):
    x = np.zeros(A.shape[0])
    xn = np.zeros(A.shape[0])
    y = np.empty(u.size)
    for k in range(u.size):
        y[k] = ss_step(A, B, C, D, x, xn, u[k])
    return y


def test_ss_step_matches_forced_response_and_columns_variant():
    sys = control.ss(control.c2d(control.tf([5e3, 5e3 * 4 * np.pi], [1, 20 * np.pi]) *
                                 control.tf([1], [1, 3, 2]), 0.01))
    A, B, C, D = (np.asarray(m, dtype=np.float64) for m in (sys.A, sys.B, sys.C, sys.D))
    u = np.random.default_rng(0).standard_normal(400)
    y = _run(A, B[:, 0].copy(), C[0].copy(), float(D[0, 0]), u)
    ref = control.forced_response(sys, T=np.arange(400) * 0.01, U=u).outputs
    np.testing.assert_allclose(y, ref, rtol=1e-10, atol=1e-12 * np.max(np.abs(ref)))
    # the column variant does each column's step with the same operations (bit-identical)
    X = np.zeros((A.shape[0], 3))
    Xn, Y = np.zeros_like(X), np.zeros(3)
    ys = np.empty((400, 3))
    for k in range(400):
        ss_step_columns(A, B[:, 0].copy(), C[0].copy(), float(D[0, 0]), X, Xn,
                        np.array([u[k], 2 * u[k], 0.0]), Y, 3)
        ys[k] = Y
    np.testing.assert_array_equal(ys[:, 0], y)
    np.testing.assert_array_equal(ys[:, 2], 0.0)
