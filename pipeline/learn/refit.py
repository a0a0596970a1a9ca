"""The model learns too (issue 50 item 4): the campaign's recordings extend the identification data.

After a campaign its trials' recordings (t, r, u, y: the commanded force and the measured motion, on the
machine, near and far from the reference) refit the physics the update inverts, by the filtered inverse-model
least squares of the measured systems (``RigidBodyPhysics.stacked_regression``: zero-phase Butterworth on y,
central differences, zero-phase decimation, each recording on its own) with the viscous, smooth Coulomb (the
model's width), offset and spring terms:

    F = M q̈ + F_v q̇ + F_c tanh(q̇/w) + K q + OF,     τ Ḟ + F = u

The filter's cutoff is chosen from the recordings' noise (:func:`choose_cutoff`): as high as the measurement noise
in q̈ allows, since a velocity filtered below the motion's stops biases the Coulomb column (held-out axis B at the
baseline's 50 Hz: F_v 6.56 N s/m for 6.0; the refit tracked new references 1.5x *worse* than the model before).

Where the model has the drive's lag (``lag_tau`` > 0) the force rows are the lagged force of u, with the model's τ
kept: the run identified it from recordings made for identification, and the campaign's repeat one reference
(held-out axis B, τ = 0.35 ms: the run's τ 0.351 ms; identified again from the 10 trials 0.42 ms at 50 Hz and
0.32 ms at 566 Hz, each with a jackknife σ of ~1 µs: biased, not uncertain; kept, the new references track 2.46x
and 2.09x better than the model before the campaign, re-identified 2.24x and 2.02x). A model without a lag
regresses u itself. Dropping a lag the model had throws its structure away: on axis B the lag-free refit tracked
a new reference only 1.1-1.2x better than the model before.

:func:`feedforward` is the model's feedforward for any reference, started at rest at r(0) with an
integrating controller holding the static load (README "Where the feedforward starts"): the force
F̂(r) - F̂(r(0)) through the lifted inverse of the ZOH plant (its lag included) with the controller's delay
(with |Q|, the same as the update's) minus the controller term (C_r - C_y) r; a reference never run on the
machine then starts from the refitted model instead of the campaign's first guess.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import signal

from pipeline.identify.least_squares import solve_scaled
from pipeline.learn.update import LoopModel, Update, apply_response
from pipeline.systems.actuator_lag import ActuatorLag
from pipeline.systems.force_terms import ForceTerms
from pipeline.systems.measured import RigidBodyPhysics

__all__ = ["refit", "feedforward", "choose_cutoff", "noise_share"]


#: the filter's cutoff is the highest at which the measurement noise in the q̈ column stays below this share of its
#: energy (errors in the regressor bias M low by about that share)
NOISE_SHARE = 1e-3
#: the cutoffs tried [Hz]: 25 Hz · √2^k up to 0.4 × Nyquist
CUTOFF_MIN, CUTOFF_STEP = 25.0, math.sqrt(2.0)
DEFAULT_CUTOFF_HZ = 50.0


def _decimation(cutoff_hz: float, Ts: float) -> int:
    return max(1, int(round(1.0 / (8 * cutoff_hz * Ts))))


def noise_share(phys: RigidBodyPhysics, ys: list[np.ndarray], noise: float, cutoff_hz: float) -> float:
    """The share of the filtered q̈ column's energy that a white measurement noise of std ``noise`` [m] makes:
    σ² Σ h² (h the impulse response of the zero-phase Butterworth and the central differences,
    ``RigidBodyPhysics.filtered_states``) over the column's mean square on the recordings."""
    n = int(min(max(40.0 / (cutoff_hz * phys.Ts), 200), 200_000))
    impulse = np.zeros(2 * n + 1)
    impulse[n] = 1.0
    gain = float(np.sum(phys.filtered_states(impulse, cutoff_hz)[2] ** 2))
    acc = np.concatenate([phys.filtered_states(y, cutoff_hz)[2] for y in ys])
    return noise ** 2 * gain / float(np.mean(acc ** 2))


def choose_cutoff(phys: RigidBodyPhysics, ys: list[np.ndarray], noise: float | None) -> tuple[float, float]:
    """(the filtered least squares' cutoff [Hz], its noise share: NaN where the noise is unknown): the highest of
    25 Hz · √2^k (≤ 0.4 × Nyquist) whose noise share
    (:func:`noise_share`) stays ≤ :data:`NOISE_SHARE`; :data:`DEFAULT_CUTOFF_HZ` (the baseline's) where the noise is
    unknown. Why as high as the noise allows: the Coulomb column tanh(q̇/w) of a velocity filtered below the motion's
    stops is biased (held-out axis B, 10 trials, τ kept: F_v 6.56, 6.21, 6.06 N s/m at 50, 100, 200 Hz, truth 6.0);
    why not higher: the noise in q̈ biases M low (held-out axis A, 50 nm at 4 kHz: M -4.5 % at 450 Hz)."""
    if noise is None or not math.isfinite(noise) or noise <= 0:
        return DEFAULT_CUTOFF_HZ, math.nan
    top = 0.4 * 0.5 / phys.Ts
    grid = CUTOFF_MIN * CUTOFF_STEP ** np.arange(int(math.log(top / CUTOFF_MIN) / math.log(CUTOFF_STEP)) + 1)
    shares = [(float(f), noise_share(phys, ys, noise, float(f))) for f in grid]
    ok = [fs for fs in shares if fs[1] <= NOISE_SHARE]
    return max(ok) if ok else shares[0]


def refit(model: LoopModel, recordings: list[dict], cutoff_hz: float | None = None,
          noise: float | None = None) -> tuple[LoopModel, dict]:
    """(the model with M, F_v, F_c, K refitted on the recordings' u, y (its width and lag kept); {residual: the
    relative force residual, cutoff_hz, noise_share}). ``cutoff_hz`` None: :func:`choose_cutoff` from the
    measurement noise's std ``noise`` [m]."""
    width = model.coulomb_width or None
    terms = ForceTerms(("viscous", "coulomb", "offset", "spring"), coulomb_width=width)
    phys = RigidBodyPhysics(model.Ts, terms=terms)
    ys = [np.asarray(r["y"], np.float64) for r in recordings]
    us = [np.asarray(r["u"], np.float64) for r in recordings]
    if cutoff_hz is None:
        cutoff_hz, share = choose_cutoff(phys, ys, noise)
    else:
        share = noise_share(phys, ys, noise, cutoff_hz) if noise and math.isfinite(noise) else math.nan
    filt = {"cutoff_hz": cutoff_hz, "decimation": _decimation(cutoff_hz, model.Ts)}
    fit = {"cutoff_hz": float(cutoff_hz), "decimation": filt["decimation"], "noise_share": share}
    if model.lag_tau:            # the model's τ, kept (module docstring): the force rows are the lagged force
        phys = phys.with_lag(ActuatorLag(model.lag_tau, model.Ts))
    X, z, _, _ = phys.stacked_regression(ys, us, **filt)      # [q̈, q̇, tanh(q̇/w), 1, q]
    p = solve_scaled(X, z)
    M, F_v, F_c, _offset, K = (float(x) for x in p)
    fit["residual"] = float(np.linalg.norm(z - X @ p) / np.linalg.norm(z - np.mean(z)))
    if M <= 0:
        raise ValueError(f"the refit gives a mass of {M:.3g} kg: the recordings do not excite the acceleration")
    return dataclasses.replace(model, M=M, F_v=max(F_v, 0.0), K=max(K, 0.0), F_c=max(F_c, 0.0)), fit


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
