"""The Coulomb smoothing width chosen from the data (issue 49 item 2, ``coulomb_width: auto``).

The Coulomb term F_c tanh(q̇/w) of :mod:`pipeline.systems.force_terms` is linear in F_c for a fixed
width w, so every candidate w is one filtered least squares (the EMPS benchmark's IDIM-LS,
:meth:`~pipeline.systems.measured.RigidBodyPhysics.filtered_regression`): fitted on the head of each
training record, scored on its tail (``val_fraction`` of it, never a test file) by the held-out force
error ‖τ - X p̂(w)‖ / ‖τ‖.  The search is 1-D on log w: a log grid over four decades below the
velocity range, then ``scipy.optimize.minimize_scalar`` (bounded) between the best grid point's
neighbours.  The same search scores ``sign`` (w → 0), so a sign Coulomb term that a smooth one would
beat is hinted at (:data:`SMOOTH_SHARE`).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from pipeline.identify.least_squares import decimated_rows, solve_scaled

#: a smooth width that removes this share of the sign fit's held-out residual energy is hinted at
SMOOTH_SHARE = 0.2
#: the held-out tail of each training record when the identification sets no validation fraction
HOLD_OUT = 0.2
#: points of the log grid, and its span below the velocity range [decades]
GRID, DECADES = 41, 4.0


def _rows(physics, y, u, n_fit, cutoff_hz=50.0, order=4, decimation=10, trim=50):
    """(X with a sign Coulomb column, that column's index, the filtered q̇ (samples), τ, head mask, the
    decimation settings) of one record: the rows of ``physics.filtered_regression``, split at sample n_fit."""
    terms = physics.terms.with_coulomb_width(None)
    j = 1 + [e[0] for e in terms.expanded()].index("fc_over_m")     # its column of X = [q̈, T_1, …]
    qf, v, acc = physics.filtered_states(y, cutoff_hz, order)
    X = decimated_rows(np.stack([acc] + terms.columns(qf, v), axis=1), decimation, trim)
    k = max(1, trim // max(decimation, 1))
    sample = (np.arange(X.shape[0]) + k) * max(int(decimation), 1)
    return X, j, v, decimated_rows(u, decimation, trim), sample < n_fit, (decimation, trim)


def _column(v, w, filt):
    """tanh(q̇/w) (w = 0: sign) on the rows of the other columns."""
    return decimated_rows(np.sign(v) if w == 0 else np.tanh(v / w), *filt)


def held_out_error(parts, w: float) -> float:
    """‖τ - X p̂‖/‖τ‖ on the records' tails, p̂ the filtered LS on their heads, Coulomb width w (0: sign)."""
    Xs, zs, heads = [], [], []
    for X, j, v, z, head, filt in parts:
        X = X.copy()
        X[:, j] = _column(v, w, filt)
        Xs.append(X)
        zs.append(z)
        heads.append(head)
    X, z, head = np.concatenate(Xs), np.concatenate(zs), np.concatenate(heads)
    try:
        p = solve_scaled(X[head], z[head])
    except ValueError:            # the head does not excite every term at this width: no candidate
        return math.inf
    e = z[~head] - X[~head] @ p
    return float(np.linalg.norm(e) / np.linalg.norm(z[~head]))


def choose(physics, ys, us, val_fraction: float = HOLD_OUT, **filt) -> dict:
    """The Coulomb width [m/s] of least held-out force error on the training records ``ys``, ``us``
    (lists of arrays, one per record; the last ``val_fraction`` of each is held out).  Returns
    {"width", "error" (held out, at the width), "error_sign" (sign), "share" = 1 - error²/error_sign²
    (the share of the sign fit's held-out residual energy the width removes)}."""
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction={val_fraction} must be in (0, 1) to hold out a tail of the training data")
    parts = []
    for y, u in zip(ys, us):
        n_fit = int(round((1.0 - val_fraction) * len(y)))
        parts.append(_rows(physics, np.asarray(y, np.float64), np.asarray(u, np.float64), n_fit, **filt))
    if not all(p[4].any() and (~p[4]).any() for p in parts):
        raise ValueError(f"a training record is too short to hold out its last {val_fraction:.0%} for the Coulomb "
                         "width: give a longer record or a fixed coulomb_width")
    vmax = float(np.percentile(np.abs(np.concatenate([p[2] for p in parts])), 99))
    if not vmax > 0:
        raise ValueError("the training data do not move: no Coulomb width can be chosen; give a fixed coulomb_width")
    grid = np.geomspace(vmax * 10.0 ** -DECADES, vmax, GRID)
    errs = np.array([held_out_error(parts, w) for w in grid])
    i = int(np.argmin(errs))
    if not math.isfinite(errs[i]):
        raise ValueError("the heads of the training records do not excite every force term: no Coulomb width "
                         "can be chosen; give a fixed coulomb_width or more excitation")
    lo, hi = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, GRID - 1)])
    res = optimize.minimize_scalar(lambda s: held_out_error(parts, math.exp(s)), bounds=(lo, hi),
                                   method="bounded", options={"xatol": 1e-3})
    w, e = (math.exp(res.x), float(res.fun)) if res.fun < errs[i] else (float(grid[i]), float(errs[i]))
    e_sign = held_out_error(parts, 0.0)
    share = 1.0 - (e / e_sign) ** 2 if 0 < e_sign < math.inf else 0.0
    return {"width": w, "error": e, "error_sign": e_sign, "share": share}
