"""Direct-inverse PGNN feedforward, [B1] (13) evaluated on the reference (SPEC §6).

    u_ff(t) = û(θ̂, φ'_ff(t)),   φ'_ff(t) = [r(t+n_k+1), …, r(t+n_k+1-n_a), u_ff(t-1), …, u_ff(t-n_b+1)]

recursive in u_ff.  The reference is held at r(0) before the start and at r(N-1) after the
end, and past inputs are zero (at rest, SPEC §0).

Two implementations: a numba fast path (one-hidden-layer tanh NN, built-in physics maps; a
per-sample step :func:`direct_step` for real-time use and timing) and the torch reference
(any PGNN), which the tests hold equal to 1e-10.
"""
from __future__ import annotations

import time

import numba
import numpy as np
import torch

from pipeline.models.fast_pgnn import (
    FastPGNN,
    fast_build_phi,
    fast_pgnn,
    fast_predict,
    fast_push_input,
    fast_push_reference,
    fast_state,
    padded_reference,
)
from pipeline.models.pgnn import PGNN

__all__ = ["direct_feedforward", "direct_step", "reference_regressor", "resolve_fast",
           "initial_state", "per_sample_seconds", "nyquist_fraction"]


def resolve_fast(model: PGNN, fast: bool | None, **kw) -> FastPGNN | None:
    """The numba export of ``model`` if ``fast`` allows it (None: when available)."""
    if fast is False:
        return None
    fm = fast_pgnn(model, **kw)
    if fm is None and fast is True:
        raise ValueError("fast=True needs a PGNN with at most one tanh hidden layer and a "
                         "built-in physics map (LinearFeatures, RigidBodyForward, "
                         "RigidBodyInverse); use fast=None to fall back to the torch reference")
    return fm


def initial_state(fm: FastPGNN, r_ext: np.ndarray) -> np.ndarray:
    """Window state before t = 0 from the padded reference (``r_ext[j + n_a] = r(j)``)."""
    n_a, n_k = fm.n_a, fm.n_k
    return fast_state(fm, [r_ext[n_k - i + n_a] for i in range(n_a + 1)])


def reference_regressor(model: PGNN, r_ext: np.ndarray, u_ff: np.ndarray, t: int) -> torch.Tensor:
    """φ_ff(t+n_k+1) (forward layouts, u_ff(t) slot = 0) or φ'_ff(t) (inverse layout) as a
    [1, n_phi] tensor; ``u_ff`` holds the inputs computed so far (zero before t = 0)."""
    n_a, n_b, n_k = model.n_a, model.n_b, model.n_k
    past_u = [u_ff[t - 1 - i] if t - 1 - i >= 0 else 0.0 for i in range(n_b - 1)]
    if model.structure == "inverse":
        ys = [r_ext[t + n_k + 1 - i + n_a] for i in range(n_a + 1)]
        phi = ys + past_u
    else:
        ys = [r_ext[t + n_k - i + n_a] for i in range(n_a)]
        phi = ys + [0.0] + past_u
    return torch.tensor([phi], dtype=torch.float64)


@numba.njit(cache=True)
def direct_step(blob, meta, state, r_new):
    """One sample of the direct-inverse feedforward: push r(t+n_k+1), return u_ff(t)."""
    fast_push_reference(state, meta, r_new)
    phi = fast_build_phi(state, meta, True)
    u = fast_predict(blob, meta, phi)
    fast_push_input(state, meta, u)
    return u


@numba.njit(cache=True)
def _direct_run(blob, meta, state, r_ext, N):
    n_a, n_k = meta[7], meta[9]
    u = np.empty(N)
    for t in range(N):
        u[t] = direct_step(blob, meta, state, r_ext[t + n_k + 1 + n_a])
    return u


def direct_feedforward(model: PGNN, r, *, fast: bool | None = None) -> np.ndarray:
    """Feedforward u_ff [N] of a direct-inverse PGNN ([B1] (13), ``structure='inverse'``) for
    the reference r [m].

    Parameters
    ----------
    model : PGNN
        Identified direct-inverse model (criterion [B1] (14)).
    r : array [N]
        Reference.
    fast : bool or None
        Numba path (True), torch reference (False), or numba when available (None).
    """
    if model.structure != "inverse":
        raise ValueError(f"direct feedforward needs a direct-inverse PGNN (structure='inverse'), "
                         f"got structure={model.structure!r}; invert a forward model with "
                         "newton_feedforward or analytic_feedforward")
    r_ext = padded_reference(r, model.n_a, model.n_k)
    N = r_ext.shape[0] - model.n_a - model.n_k - 1
    fm = resolve_fast(model, fast)
    if fm is not None:
        return _direct_run(fm.blob, fm.meta, initial_state(fm, r_ext), r_ext, N)
    u = np.zeros(N)
    with torch.no_grad():
        for t in range(N):
            u[t] = float(model(reference_regressor(model, r_ext, u, t))[0])
    return u


def per_sample_seconds(step, fm: FastPGNN, r, *args, warmup: int = 200) -> np.ndarray:
    """Wall time [s] of each sample of a feedforward computed sample by sample, one call of
    the numba per-sample kernel ``step(blob, meta, state, r_new, *args)`` per sample from
    Python (dispatch overhead included, as a sample-by-sample loop pays it; SPEC §7 cost).
    The first ``warmup`` samples are dropped (one extra call compiles the kernel first)."""
    r_ext = padded_reference(r, fm.n_a, fm.n_k)
    N = r_ext.shape[0] - fm.n_a - fm.n_k - 1
    if N <= warmup:
        raise ValueError(f"the reference has {N} samples; timing needs more than warmup={warmup}")
    state = initial_state(fm, r_ext)
    step(fm.blob, fm.meta, state.copy(), r_ext[fm.n_k + 1 + fm.n_a], *args)  # compile
    out = np.empty(N)
    pc = time.perf_counter_ns
    for t in range(N):
        rn = r_ext[t + fm.n_k + 1 + fm.n_a]
        t0 = pc()
        step(fm.blob, fm.meta, state, rn, *args)
        out[t] = pc() - t0
    return out[warmup:] * 1e-9


def nyquist_fraction(u, band: float = 0.9) -> float:
    """Share of the energy of u - mean(u) at frequencies above ``band`` × Nyquist: ≈ 0 for a
    smooth feedforward, large for one oscillating at the Nyquist frequency (the z = -1 pole
    of a sample-by-sample inverse of a sampled mass, SPEC §2.2)."""
    u = np.asarray(u, dtype=float)
    U = np.abs(np.fft.rfft(u - u.mean())) ** 2
    tot = float(U.sum())
    if tot == 0.0:
        return 0.0
    f = np.fft.rfftfreq(u.shape[0])  # cycles per sample, Nyquist = 0.5
    return float(U[f > 0.5 * band].sum() / tot)
