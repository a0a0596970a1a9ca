"""Tracking metrics (SPEC §7)."""
from __future__ import annotations

import numpy as np


def tracking_metrics(r: np.ndarray, y: np.ndarray, f_hat: np.ndarray | None = None,
                     f: np.ndarray | None = None) -> dict[str, float]:
    """Metrics of the tracking error e = r - y [m].

    Returns ``mae`` (mean |e|), ``max_abs``, ``norm2`` (‖e‖₂), ``sq_norm2`` (‖e‖₂²), ``rms``
    (‖e‖₂/√N, [B2]'s "normalised 2-norm") and, when the optimal input ``f_hat`` and the applied
    feedforward ``f`` are both given, ``ff_error`` = ‖f̂ − f‖₂ [N] and ``ff_error_rel`` = ‖f̂ − f‖/‖f̂‖.
    """
    r = np.asarray(r, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if r.shape != y.shape:
        raise ValueError(f"r and y must have one shape, got {r.shape} and {y.shape}")
    e = r - y
    n2 = float(np.linalg.norm(e))
    out = {"mae": float(np.mean(np.abs(e))), "max_abs": float(np.max(np.abs(e))), "norm2": n2,
           "sq_norm2": n2 ** 2, "rms": n2 / np.sqrt(e.size)}
    if f_hat is not None and f is not None:
        d = float(np.linalg.norm(np.asarray(f_hat) - np.asarray(f)))
        out["ff_error"] = d
        out["ff_error_rel"] = d / max(float(np.linalg.norm(f_hat)), np.finfo(float).tiny)
    return out


PHASES = ("accel", "constvel", "standstill")


def motion_phases(r: np.ndarray, rel_tol: float = 1e-6) -> dict[str, np.ndarray]:
    """Masks of the samples where the reference accelerates (|Δ²r| > tol: jerk and acceleration
    segments of a third-order profile), moves at constant velocity (|Δr| > tol, Δ²r ≈ 0) and
    stands still (both ≈ 0). Central differences; tol = ``rel_tol`` × the signal's maximum, so
    the rounding of a piecewise-polynomial reference (~1e-16 relative) never counts as motion."""
    r = np.asarray(r, dtype=np.float64)
    if r.ndim != 1 or r.size < 3:
        raise ValueError(f"r must be 1-D with at least 3 samples, got shape {r.shape}")
    d1 = np.gradient(r)
    d2 = np.gradient(d1)
    acc = np.abs(d2) > rel_tol * max(float(np.max(np.abs(d2))), np.finfo(float).tiny)
    mov = np.abs(d1) > rel_tol * max(float(np.max(np.abs(d1))), np.finfo(float).tiny)
    return {"accel": acc, "constvel": mov & ~acc, "standstill": ~mov & ~acc}


def phase_ff_errors(r: np.ndarray, f_hat: np.ndarray, f: np.ndarray) -> dict[str, float]:
    """``ff_rms_<phase>`` [N]: the rms of the feedforward's force error f - f̂ (f̂ the exact optimal
    input) within each :func:`motion_phases` phase of r (0 where there is none): whether a
    feedforward errs where the reference accelerates (mass) or where it moves steadily (friction)."""
    d = np.asarray(f, dtype=np.float64) - np.asarray(f_hat, dtype=np.float64)
    return {f"ff_rms_{k}": float(np.sqrt(np.mean(d[m] ** 2))) if m.any() else 0.0
            for k, m in motion_phases(r).items()}


def phase_peaks(r: np.ndarray, y: np.ndarray) -> dict[str, float]:
    """``max_abs_<phase>``: the peak |r - y| within each :func:`motion_phases` phase (0 where the
    reference has no such samples): where a feedforward's peak error comes from."""
    e = np.abs(np.asarray(r, dtype=np.float64) - np.asarray(y, dtype=np.float64))
    return {f"max_abs_{k}": float(e[m].max()) if m.any() else 0.0 for k, m in motion_phases(r).items()}
