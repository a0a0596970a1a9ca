"""The model learns too (issue 50 item 4): the campaign's recordings extend the identification data.

After a campaign its trials' recordings (t, r, u, y: the commanded force and the measured motion, on the
machine, near and far from the reference) refit the physics the update inverts, by the filtered inverse-model
least squares of the measured systems (``RigidBodyPhysics.stacked_regression``: zero-phase Butterworth on y,
central differences, zero-phase decimation, each recording on its own) with the viscous, smooth Coulomb (the
model's width), offset and spring terms:

    F = M q̈ + F_v q̇ + F_c tanh(q̇/w) + K q + OF,     τ Ḟ + F = u

Where the model has the drive's lag (``lag_tau`` > 0: the run identified one), τ is identified again from the
recordings first (:func:`pipeline.systems.actuator_lag.identify_tau`, the baseline's ``lag_tau: auto``; kept at the
model's where the search ends on its grid) and the force rows are the lagged force of u; a model without a lag
regresses u itself. Dropping a lag the model had throws its structure away: on held-out axis B (τ = 0.35 ms) the
lag-free refit tracked a new reference only 1.1-1.2x better than the model before.

:func:`feedforward` is the model's feedforward for any reference, started at rest at r(0) with an
integrating controller holding the static load (README "Where the feedforward starts"): the force
F̂(r) - F̂(r(0)) through the lifted inverse of the ZOH plant (its lag included) with the controller's delay
(with |Q|, the same as the update's) minus the controller term (C_r - C_y) r; a reference never run on the
machine then starts from the refitted model instead of the campaign's first guess.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy import signal

from pipeline.identify.least_squares import solve_scaled
from pipeline.learn.update import LoopModel, Update, apply_response
from pipeline.systems.actuator_lag import ActuatorLag, identify_tau
from pipeline.systems.force_terms import ForceTerms
from pipeline.systems.measured import RigidBodyPhysics

__all__ = ["refit", "feedforward"]


def refit(model: LoopModel, recordings: list[dict], cutoff_hz: float = 50.0) -> tuple[LoopModel, float, dict]:
    """(the model with M, F_v, F_c, K (and τ) refitted on the recordings' u, y; the relative force residual; the
    lag's identification {tau, tau_std, at_bound, …}, {} without a lag)."""
    width = model.coulomb_width or None
    terms = ForceTerms(("viscous", "coulomb", "offset", "spring"), coulomb_width=width)
    phys = RigidBodyPhysics(model.Ts, terms=terms)
    filt = {"cutoff_hz": cutoff_hz, "decimation": max(1, int(round(1.0 / (8 * cutoff_hz * model.Ts))))}
    ys = [np.asarray(r["y"], np.float64) for r in recordings]
    us = [np.asarray(r["u"], np.float64) for r in recordings]
    lag, tau = {}, 0.0
    if model.lag_tau:
        lag = identify_tau(phys, ys, us, **filt)
        tau = model.lag_tau if lag["at_bound"] else lag["tau"]
        phys = phys.with_lag(ActuatorLag(tau, model.Ts))
    X, z, _, _ = phys.stacked_regression(ys, us, **filt)      # [q̈, q̇, tanh(q̇/w), 1, q]
    p = solve_scaled(X, z)
    M, F_v, F_c, _offset, K = (float(x) for x in p)
    res = float(np.linalg.norm(z - X @ p) / np.linalg.norm(z - np.mean(z)))
    if M <= 0:
        raise ValueError(f"the refit gives a mass of {M:.3g} kg: the recordings do not excite the acceleration")
    return (dataclasses.replace(model, M=M, F_v=max(F_v, 0.0), K=max(K, 0.0), F_c=max(F_c, 0.0), lag_tau=tau),
            res, lag)


def feedforward(update: Update, r: np.ndarray) -> np.ndarray:
    """u_ff [N] of ``update.model`` for the reference r from rest at r(0) (module docstring), static load excluded
    (the controller integrates)."""
    model = update.model
    r = np.asarray(r, np.float64)
    n = update.pad // 2
    ext = np.concatenate([np.full(n, r[0]), r, np.full(n, r[-1])]) - r[0]   # at rest before and after
    inv = lambda w: update.q(w) * model.plant_inverse(w)                     # noqa: E731 - |Q| P'^-1
    force = apply_response(ext, inv, model.Ts, n)[n:n + r.size]
    coulomb = model.command_for(model.coulomb(r) - model.coulomb(np.full(r.size, r[0])))   # through the lag
    force = force + signal.sosfiltfilt(update.q_sos, coulomb)
    return force - model.ctrl.reference_force(r, float(r[0]))
