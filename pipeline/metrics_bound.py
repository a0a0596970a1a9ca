"""The tracking-error bound of [B2] Lemma 4.1: identification, inversion and ε terms (SPEC §7).

For the p-norm normalised by the signal length, ‖x‖_p / N^(1/p) ([B2]'s "normalised
norm"; p = 2 gives the rms):

- identification error ([B2] (13)):  ‖Y^d - Ŷ^d‖ / N_d^(1/p)
- inversion error:                   ‖R - Ŷ‖ / N_k^(1/p),      Ŷ = Φ̂(θ̂, x0, R, U_ff)
- model error:                       ‖Y - Ŷ‖ / N_k^(1/p)
- ε ([B2] (14)):                     model error - identification error
- tracking error:                    ‖R - Y‖ / N_k^(1/p)

and (15): tracking ≤ inversion + identification + ε, which is the triangle inequality
‖R - Y‖ ≤ ‖R - Ŷ‖ + ‖Ŷ - Y‖ after substituting ε ([B2] (11), (12)).  Y is the measured
output (SPEC §8 B2a).  Pure functions of arrays.
"""
from __future__ import annotations

import numpy as np

__all__ = ["normalised_norm", "identification_error", "inversion_error", "model_error",
           "tracking_error", "epsilon", "bound_terms", "bound_holds"]


def _pair(name_a: str, a, name_b: str, b) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 1 or a.shape != b.shape or a.size == 0:
        raise ValueError(f"{name_a} and {name_b} must be non-empty 1-D signals of one length, got shapes "
                         f"{a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError(f"{name_a} or {name_b} contains NaN/inf")
    return a, b


def normalised_norm(x, p: float = 2) -> float:
    """‖x‖_p / N^(1/p) (p = 2: rms; p = inf: max |x|)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("normalised_norm of an empty signal")
    if not p >= 1:
        raise ValueError(f"p must be >= 1, got {p}")
    if np.isinf(p):
        return float(np.max(np.abs(x)))
    return float(np.linalg.norm(x, ord=p) / x.size ** (1.0 / p))


def identification_error(y_d, y_hat_d, p: float = 2) -> float:
    """‖Y^d - Ŷ^d‖_p / N_d^(1/p) [m] ([B2] (13), (15))."""
    a, b = _pair("Y^d", y_d, "Ŷ^d", y_hat_d)
    return normalised_norm(a - b, p)


def inversion_error(r, y_hat, p: float = 2) -> float:
    """‖R - Ŷ‖_p / N_k^(1/p) [m] ([B2] (15))."""
    a, b = _pair("R", r, "Ŷ", y_hat)
    return normalised_norm(a - b, p)


def model_error(y, y_hat, p: float = 2) -> float:
    """‖Y - Ŷ‖_p / N_k^(1/p) [m] ([B2] (11))."""
    a, b = _pair("Y", y, "Ŷ", y_hat)
    return normalised_norm(a - b, p)


def tracking_error(r, y, p: float = 2) -> float:
    """‖R - Y‖_p / N_k^(1/p) [m]."""
    a, b = _pair("R", r, "Y", y)
    return normalised_norm(a - b, p)


def epsilon(y, y_hat, y_d, y_hat_d, p: float = 2) -> float:
    """ε of [B2] (14): ‖Y - Ŷ‖/N_k^(1/p) - ‖Y^d - Ŷ^d‖/N_d^(1/p) [m] (data informativity)."""
    return model_error(y, y_hat, p) - identification_error(y_d, y_hat_d, p)


def bound_terms(r, y, y_hat, y_d, y_hat_d, p: float = 2, rtol: float = 1e-12) -> dict[str, float | bool]:
    """All terms of [B2] (15) and whether it holds.

    Parameters
    ----------
    r : array [m]
        Reference R (N_k samples).
    y : array [m]
        Measured output Y of the true system with the feedforward applied.
    y_hat : array [m]
        Model prediction Ŷ = Φ̂(θ̂, x0, R, U_ff) for that feedforward.
    y_d, y_hat_d : array [m]
        Identification data Y^d and its closed-loop simulation Ŷ^d (N_d samples).
    p : float
        Norm (2 in [B2] §VI).
    rtol : float
        Rounding allowance of the check, relative to the right-hand side.

    Returns
    -------
    dict with ``identification_error``, ``inversion_error``, ``model_error``,
    ``tracking_error``, ``epsilon``, ``bound`` (right-hand side of (15)), ``slack``
    (bound - tracking) and ``bound_holds`` (bool).
    """
    ident = identification_error(y_d, y_hat_d, p)
    inv = inversion_error(r, y_hat, p)
    mod = model_error(y, y_hat, p)
    trk = tracking_error(r, y, p)
    eps = mod - ident
    bound = inv + ident + eps
    return {"identification_error": ident, "inversion_error": inv, "model_error": mod,
            "tracking_error": trk, "epsilon": eps, "bound": bound, "slack": bound - trk,
            "bound_holds": bool(bound_holds(trk, inv, ident, eps, rtol))}


def bound_holds(tracking: float, inversion: float, identification: float, eps: float,
                rtol: float = 1e-12) -> bool:
    """[B2] (15): tracking ≤ inversion + identification + ε (up to ``rtol`` rounding)."""
    rhs = inversion + identification + eps
    return bool(tracking <= rhs + rtol * max(abs(rhs), abs(tracking)))
