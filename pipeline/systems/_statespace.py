"""One step of a SISO discrete state-space system, for the numba simulation kernels.

Shared by the plant simulators' feedback controllers (:mod:`pipeline.systems.linear_motor`,
:mod:`pipeline.systems.rot_trans_nmp`), the closed-loop PGNN simulation and its forward
sensitivities (:mod:`pipeline.models.closed_loop`) and the ILC filters
(:mod:`pipeline.invert.ilc`).

Both functions are inlined into their callers (``inline="always"``): a plain njit call costs
about 3x in a filter loop (per-call reference counting of the array arguments).  numba caches
a ``cache=True`` caller by its own source file only; the package keeps its numba cache in a
folder per version of its numba modules (:func:`pipeline.numba_cache_dir`), so editing this
module recompiles the callers.
"""
from __future__ import annotations

from numba import njit


@njit(cache=True, inline="always")
def ss_step(A, B, C, D, x, xn, e, y0=-0.0):  # pragma: no cover - compiled
    """SISO discrete state space, no computational delay: output, then state advanced in place.

    ``y(k) = C x(k) + D e(k)`` is computed from the current state and input, then
    ``x(k+1) = A x(k) + B e(k)`` overwrites ``x``.  The floating-point order is fixed (the
    kernels' results are bit-reproducible): ``y = ((D e + y0) + C_0 x_0) + C_1 x_1 + …`` and
    ``x_i(k+1) = (B_i e + A_i0 x_0) + A_i1 x_1 + …``.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B, C : ndarray, shape (n,)
    D : float
    x : ndarray, shape (n,)
        State x(k); overwritten with x(k+1).
    xn : ndarray, shape (n,)
        Scratch space (contents ignored and overwritten).
    e : float
        Input e(k).
    y0 : float
        Added to ``D e`` before the ``C x`` terms (e.g. a feedforward summed into the
        controller output in that order).  The default -0.0 is IEEE 754's exact additive
        identity (``a + -0.0`` is ``a`` bit for bit, signed zeros included): nothing is added.

    Returns
    -------
    float
        y(k).  Units: those of the caller's realisation (e.g. e [m] -> y [N] for a controller).
    """
    # One sweep over i for the output and the next state: every array is then last used in
    # the same loop, and numba prunes the inlined arguments' incref/decref pairs.
    n = x.shape[0]
    y = D * e + y0
    for i in range(n):
        y += C[i] * x[i]
        s = B[i] * e
        for j in range(n):
            s += A[i, j] * x[j]
        xn[i] = s
    for i in range(n):
        x[i] = xn[i]
    return y


@njit(cache=True, inline="always")
def ss_step_columns(A, B, C, D, X, Xn, E, Y, m):  # pragma: no cover - compiled
    """:func:`ss_step` (with ``y0`` = -0.0) applied to the columns ``p < m`` of X at once.

    For forward sensitivities of a state-space block: column p holds ``∂x/∂θ_p`` driven by
    ``∂e/∂θ_p = E[p]``; ``Y[p] = C X[:, p] + D E[p]``, then ``X[:, p] = A X[:, p] + B E[p]``.
    Each column gets exactly :func:`ss_step`'s floating-point operations in its order; the
    loop over p is innermost (contiguous rows, vectorised), which is why this is not a loop
    of :func:`ss_step` calls (~1.5x slower on the closed-loop Jacobians).

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B, C : ndarray, shape (n,)
    D : float
    X : ndarray, shape (n, M)
        States; columns ``p < m`` are advanced in place, the others are untouched.
    Xn : ndarray, shape (n, M)
        Scratch space.
    E : ndarray, shape (≥ m,)
        Inputs, one per column.
    Y : ndarray, shape (≥ m,)
        Outputs, written for ``p < m``.
    m : int
        Number of leading columns to step.
    """
    n = X.shape[0]
    for p in range(m):
        Y[p] = D * E[p]
    for i in range(n):
        ci = C[i]
        bi = B[i]
        for p in range(m):
            Y[p] += ci * X[i, p]
            Xn[i, p] = bi * E[p]
        for j in range(n):
            a = A[i, j]
            for p in range(m):
                Xn[i, p] += a * X[j, p]
    for i in range(n):
        for p in range(m):
            X[i, p] = Xn[i, p]
