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
