"""Closed-form least squares of a linear-in-parameters physics model (SPEC §3 item 1, §5)."""
from __future__ import annotations

from typing import Iterable

import numpy as np
from scipy import signal

from pipeline.systems.base import PhysicsModel


def solve_scaled(Phi: np.ndarray, z: np.ndarray, rcond_warn: float = 1e-12) -> np.ndarray:
    """θ = argmin ‖z − Φθ‖² with the columns of Φ scaled to unit norm first (SPEC §5).

    Raises ValueError naming the weakest direction when Φ is (numerically) rank deficient: the
    data do not excite every parameter.
    """
    Phi = np.asarray(Phi, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if Phi.ndim != 2 or z.shape != (Phi.shape[0],):
        raise ValueError(f"least squares needs Φ [N, p] and z [N], got {Phi.shape} and {z.shape}")
    if not (np.all(np.isfinite(Phi)) and np.all(np.isfinite(z))):
        raise ValueError("least squares: Φ or z contains NaN/inf; clean the data first")
    if Phi.shape[0] < Phi.shape[1]:
        raise ValueError(f"{Phi.shape[0]} equations for {Phi.shape[1]} parameters; give more data")
    scale = np.linalg.norm(Phi, axis=0)
    if np.any(scale == 0):
        cols = np.flatnonzero(scale == 0).tolist()
        raise ValueError(f"regressor column(s) {cols} are identically zero: the data do not excite "
                         "those parameters; add excitation or remove them from the model")
    A = Phi / scale
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    if s[-1] < rcond_warn * s[0]:
        raise ValueError(f"regressor is rank deficient (singular values {s[0]:.3g} ... {s[-1]:.3g}); "
                         "the data do not excite every parameter: add excitation or drop a parameter")
    theta_scaled = Vt.T @ ((U.T @ z) / s)
    return theta_scaled / scale


def fit_physics(physics: PhysicsModel, segments: Iterable[dict]) -> np.ndarray:
    """Least-squares θ of ``physics`` over data segments (regressors never cross a segment).

    Each segment is a mapping with arrays ``y``, ``u`` and optionally ``r``.
    """
    rows, targets = [], []
    for seg in segments:
        Phi, z = physics.regressor(np.asarray(seg["y"], dtype=np.float64),
                                   np.asarray(seg["u"], dtype=np.float64),
                                   None if "r" not in seg else np.asarray(seg["r"], dtype=np.float64))
        rows.append(Phi)
        targets.append(z)
    return solve_scaled(np.vstack(rows), np.concatenate(targets))


def decimated_rows(x: np.ndarray, decimation: int = 10, trim: int = 50) -> np.ndarray:
    """The rows of the filtered least squares from samples x (columns along axis 0): ``scipy.signal.decimate``
    (zero phase) by ``decimation``, then ``trim // decimation`` rows (at least 1) dropped at each end; row i
    is sample (i + that) · decimation."""
    if decimation > 1:
        x = signal.decimate(x, int(decimation), axis=0, zero_phase=True)
    k = max(1, trim // max(decimation, 1))
    return x[k:-k]
