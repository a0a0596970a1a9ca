"""Actuator lag: the drive's current loop as a first-order lag on the force (issue 49 item 3).

    τ Ḟ + F = u                 u the commanded force (held over each sample), F the applied one

sampled exactly per sample (a = exp(-Ts/τ), x = Ts/τ): F(k+1) = a F(k) + (1 - a) u(k).

**Model input of the rigid body** (what replaces ū of the averaged input, SPEC §2.2).  The mass
integrates F: y(k+1) - 2y(k) + y(k-1) = Ts²/M · w(k) with w(k) the triangle-weighted mean of F
over [(k-1)Ts, (k+1)Ts]; with F the lag's exact response to the held u::

    w(k) = (½ - c1) u(k) + (½ - c2) u(k-1) + c1 F(k) + c2 F(k-1),
    c1 = (x - 1 + a)/x²,   c2 = (1 - a - x a)/x²

i.e. w = B(q⁻¹)/(1 - a q⁻¹) u with B of degree 2, unit DC gain (τ → 0: B → [½, ½], ū).

**Inverse** (:meth:`ActuatorLag.applied_input`): B = b0 (1 - z_s q⁻¹)(1 - z_u q⁻¹) has one zero
z_s in (-0.27, 0) and one z_u in (-3.7, -1) (the sampled mass-and-lag's zero outside the unit
circle): 1/(1 - z_u q⁻¹) is replaced by the zero-phase-error approximation (Tomizuka's ZPETC)
(1 - z_u q)/(1 - z_u)², one sample of preview, the rest inverted exactly::

    p(k) = (w(k) - z_u w(k+1))/(1 - z_u)²,     b0 (u(k) - z_s u(k-1)) = p(k) - a p(k-1)

(τ → 0: u(k) = (w(k) + w(k+1))/2, the averaged input's inverse).  Stable: its pole is z_s.

**Identification** (:func:`identify_tau`): τ minimises the residual of the filtered inverse-model
least squares whose target is the lagged force B/(1 - a q⁻¹) u, filtered like the position
(a 1-D search over τ); its standard uncertainty is the delete-one-block jackknife of the
linearised fit (10 contiguous blocks of the rows).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize, signal

from pipeline.params import schema, spec

#: τ/Ts bounds of a lag the sampled model represents (beyond: no lag at this rate, or a drive far slower than the loop)
TAU_OVER_TS_MIN, TAU_OVER_TS_MAX = 1e-3, 1e3
#: blocks of the delete-one-block jackknife of τ
JACKKNIFE_BLOCKS = 10


def _tau_rule(v) -> str | None:
    if v is None or v == "auto" or (not isinstance(v, bool) and isinstance(v, (int, float))):
        return None     # a number: its range is checked by the schema (0 < τ <= 1 s)
    return "give the lag's time constant in s (e.g. 0.0004), 'auto' (identified from the recordings) or null"


@schema
class Params:
    """system.actuator of a measured system (pipeline.systems.actuator_lag)."""
    # [s] current-loop lag τ of τ Ḟ + F = u on the force; 'auto' = identified from the training recordings; null = none
    lag_tau: Any = spec(None, gt=0, le=1.0, unit="s", check=_tau_rule, example=0.0004)


@dataclass(frozen=True)
class ActuatorLag:
    """First-order force lag τ at sample time Ts (module docstring)."""

    tau: float
    Ts: float

    def __post_init__(self):
        if not (isinstance(self.tau, (int, float)) and math.isfinite(self.tau) and self.tau > 0):
            raise ValueError(f"lag_tau={self.tau!r} must be a positive time constant in s (or null: no lag)")
        x = self.Ts / self.tau
        if not 1.0 / TAU_OVER_TS_MAX <= x <= 1.0 / TAU_OVER_TS_MIN:
            raise ValueError(f"lag_tau={self.tau:g} s is {1 / x:.3g} samples of Ts={self.Ts:g} s: a lag must lie "
                             f"between {TAU_OVER_TS_MIN:g} and {TAU_OVER_TS_MAX:g} samples (shorter: set null)")

    @property
    def a(self) -> float:
        """Pole of the sampled lag, exp(-Ts/τ)."""
        return math.exp(-self.Ts / self.tau)

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(B, A) of w = B(q⁻¹)/A(q⁻¹) u (module docstring; A = [1, -a])."""
        x = self.Ts / self.tau
        em = math.expm1(-x)                       # a - 1, accurate for small x
        a = 1.0 + em
        c1 = (x + em) / x ** 2
        c2 = (-em - x * a) / x ** 2
        B = np.convolve([0.5 - c1, 0.5 - c2], [1.0, -a]) + (-em) * np.array([0.0, c1, c2])
        return B, np.array([1.0, -a])

    def zeros(self) -> tuple[float, float]:
        """(z_s, z_u): the zeros of B inside and outside the unit circle."""
        B, _ = self.coefficients()
        z = np.roots(B)
        if np.max(np.abs(z.imag)) > 1e-9 or not (abs(z.real).min() < 1.0 < abs(z.real).max()):
            raise ValueError(f"lag_tau={self.tau:g} s: unexpected zeros {z} of the sampled lag")
        z = z.real[np.argsort(np.abs(z.real))]
        return float(z[0]), float(z[1])

    def model_input(self, u) -> np.ndarray:
        """w = B/A u from rest (u(-1) = 0, F(0) = 0)."""
        B, A = self.coefficients()
        return signal.lfilter(B, A, np.asarray(u, dtype=np.float64))

    def applied_input(self, w, w_end: float | None = None) -> np.ndarray:
        """The command u whose lagged force gives the model input w (module docstring): w(N) = ``w_end``
        (the law's next sample on the held reference), default w(N-1); from rest."""
        w = np.asarray(w, dtype=np.float64)
        end = w[-1:] if w_end is None else np.array([float(w_end)])
        zs, zu = self.zeros()
        B, A = self.coefficients()
        p = (w - zu * np.concatenate([w[1:], end])) / (1.0 - zu) ** 2      # ZPETC of (1 - z_u q⁻¹)
        return signal.lfilter(A, B[0] * np.array([1.0, -zs]), p)

    def inverse_coefficients(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(preview FIR on [w(k), w(k+1)], IIR numerator, IIR denominator) of :meth:`applied_input`
        (the exported law's filter stage)."""
        zs, zu = self.zeros()
        B, A = self.coefficients()
        return (np.array([1.0, -zu]) / (1.0 - zu) ** 2, A.copy(), B[0] * np.array([1.0, -zs]))


def identify_tau(physics, ys, us, *, n_grid: int = 25, **filt) -> dict:
    """τ [s] of the lag and its standard uncertainty from the training recordings (module docstring).

    ``physics``: a :class:`pipeline.systems.measured.RigidBodyPhysics` (averaged input); ``ys``, ``us``:
    lists of position [m] and commanded-force [N] records; ``filt``: its filtered least squares'
    settings (idim).  Returns {"tau", "tau_std", "rss", "rss_no_lag", "at_bound"} (rss: the residual's
    energy at τ and at τ = Ts/100, i.e. without a lag; at_bound: the search ended at an end of its grid)."""
    Ts = physics.Ts
    X0 = physics.with_lag(None).stacked_regression(ys, us, **filt)[0]     # the same for every τ

    def rows(tau):
        p = physics.with_lag(None if tau is None else ActuatorLag(float(tau), Ts))
        return X0, np.concatenate([p.filtered_target(u, **filt) for u in us])

    def rss(tau):
        X, z = rows(tau)
        coef, *_ = np.linalg.lstsq(X / np.linalg.norm(X, axis=0), z, rcond=None)
        e = z - (X / np.linalg.norm(X, axis=0)) @ coef
        return float(e @ e)

    lo, hi = TAU_OVER_TS_MIN * 10 * Ts, 30.0 * Ts
    grid = np.geomspace(lo, hi, n_grid)
    prof = np.array([rss(t) for t in grid])
    i = int(np.argmin(prof))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    res = optimize.minimize_scalar(rss, bounds=(a, b), method="bounded", options={"xatol": 1e-4 * grid[i]})
    tau = float(res.x)
    # jackknife of the linearised fit: z_τ ≈ X p - δτ ∂z/∂τ
    h = 1e-3 * tau
    X, z = rows(tau)
    g = (rows(tau + h)[1] - rows(tau - h)[1]) / (2 * h)
    Xg = np.column_stack([X, -g])
    sc = np.linalg.norm(Xg, axis=0)
    blocks = np.array_split(np.arange(z.size), JACKKNIFE_BLOCKS)
    d = []
    for blk in blocks:
        keep = np.ones(z.size, bool)
        keep[blk] = False
        c, *_ = np.linalg.lstsq(Xg[keep] / sc, z[keep], rcond=None)
        d.append(c[-1] / sc[-1])
    d = np.array(d)
    K = JACKKNIFE_BLOCKS
    std = float(math.sqrt((K - 1) / K * np.sum((d - d.mean()) ** 2)))
    return {"tau": tau, "tau_std": std, "rss": float(res.fun), "rss_no_lag": float(prof[0]),
            "at_bound": bool(i in (0, n_grid - 1))}
