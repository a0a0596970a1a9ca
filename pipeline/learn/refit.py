"""The model learns too (issue 50 item 4): the campaign's recordings extend the identification data.

After a campaign its trials' recordings (t, r, u, y: the applied force and the measured motion, on the
machine, near and far from the reference) refit the physics the update inverts, by the filtered inverse-model
least squares of the measured systems (``RigidBodyPhysics.stacked_regression``: zero-phase Butterworth on y,
central differences, zero-phase decimation, each recording on its own) with the viscous, smooth Coulomb (the
model's width) and offset terms, plus a position spring column K q (the force library has none yet):

    u = M q̈ + F_v q̇ + F_c tanh(q̇/w) + K q + OF

:func:`feedforward` is the model's feedforward for any reference, started at rest at r(0) with an
integrating controller holding the static load (README "Where the feedforward starts"): the force
F̂(r) - F̂(r(0)) through the lifted inverse of the ZOH plant with the controller's delay (with |Q|, the same
as the update's) minus the controller term (C_r - C_y) r; a reference never run on the machine then starts
from the refitted model instead of the campaign's first guess.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy import signal

from pipeline.identify.least_squares import solve_scaled
from pipeline.learn.update import LoopModel, Update, apply_response
from pipeline.systems.force_terms import ForceTerms
from pipeline.systems.measured import RigidBodyPhysics

__all__ = ["refit", "feedforward"]


def refit(model: LoopModel, recordings: list[dict], cutoff_hz: float = 50.0) -> tuple[LoopModel, float]:
    """(the model with M, F_v, F_c, K refitted on the recordings' u, y; the relative force residual)."""
    width = model.coulomb_width or None
    terms = ForceTerms(("viscous", "coulomb", "offset"), coulomb_width=width)
    phys = RigidBodyPhysics(model.Ts, terms=terms)
    decim = max(1, int(round(1.0 / (8 * cutoff_hz * model.Ts))))
    X, z, q, _ = phys.stacked_regression([np.asarray(r["y"], np.float64) for r in recordings],
                                         [np.asarray(r["u"], np.float64) for r in recordings],
                                         cutoff_hz=cutoff_hz, decimation=decim)
    X = np.column_stack([X, q])                 # [q̈, q̇, tanh(q̇/w), 1, q]
    p = solve_scaled(X, z)
    M, F_v, F_c, _offset, K = (float(x) for x in p)
    res = float(np.linalg.norm(z - X @ p) / np.linalg.norm(z - np.mean(z)))
    if M <= 0:
        raise ValueError(f"the refit gives a mass of {M:.3g} kg: the recordings do not excite the acceleration")
    return dataclasses.replace(model, M=M, F_v=max(F_v, 0.0), K=max(K, 0.0), F_c=max(F_c, 0.0)), res


def feedforward(update: Update, r: np.ndarray) -> np.ndarray:
    """u_ff [N] of ``update.model`` for the reference r from rest at r(0) (module docstring), static load excluded
    (the controller integrates)."""
    model = update.model
    r = np.asarray(r, np.float64)
    n = update.pad // 2
    ext = np.concatenate([np.full(n, r[0]), r, np.full(n, r[-1])]) - r[0]   # at rest before and after
    inv = lambda w: update.q(w) * model.plant_inverse(w)                     # noqa: E731 - |Q| P'^-1
    force = apply_response(ext, inv, model.Ts, n)[n:n + r.size]
    force = force + signal.sosfiltfilt(update.q_sos, model.coulomb(r) - model.coulomb(np.full(r.size, r[0])))
    return force - model.ctrl.reference_force(r, float(r[0]))
