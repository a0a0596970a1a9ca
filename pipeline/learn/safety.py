"""Safety and convergence of a learning campaign (issue 50 item 3): checked, not assumed.

**Before the campaign** (:func:`convergence_check`): the trial-to-trial map of the error is
``Q (1 - α L G_true)`` (Bristow et al. 2006, eq. (9); |·| < 1 on every frequency is monotonic convergence
of the long-trial limit). With the true plant G_true = G (1 + Δ), |Δ(ω)| ≤ δ(ω) (the model's uncertainty,
``safety.uncertainty``: the relative identification residual, growing as δ₀ √(1 + (f/f_δ)²) above
``uncertainty_hz``), the worst case over that set is

    ρ(ω) = |Q(ω)| (|1 - α L G(ω)| + α |L G(ω)| δ(ω))   < 1

checked on a grid up to the Nyquist frequency; a failure names the band where ρ ≥ 1. A law whose trial map
differs gives its own (:meth:`pipeline.learn.update.Update.rho`: IL-FHOFC's is |Q| L G (|1 - α| + α δ)).

**Every trial** (:func:`limited`, :func:`decide`): the next feedforward within ±u_max and the slew rate
(the export's default limits: 1.5 × the largest |u - (C_r - C_y) r| and its largest slew of the first
recording, ``stages.export.data_limits``), flagged as the exported laws flag (SATURATED, RATE_LIMITED);
an error that grows beyond ``rollback_factor`` × the best trial's rolls back to the best trial's feedforward
and halves the learning gain; from the second trial on, the convergence condition is checked against the plant
the last two trials measured (:func:`measured_rho`) and a band with ρ̂ ≥ 1 halves the gain ('slow'), or sets
it to half the bound the measured bands allow where halving is not enough; the
campaign stops when the error reaches the recording's noise floor (:func:`noise_floor`, from its standstill
samples): noise is not learned.
"""
from __future__ import annotations

import math

import numpy as np

from pipeline.export.guard import FLAG

__all__ = ["uncertainty", "convergence_check", "noise_floor", "limited", "decide", "rms"]


def rms(x) -> float:
    x = np.asarray(x, np.float64)
    return float(np.sqrt(np.mean(x * x)))


def uncertainty(f_hz, delta0: float, growth_hz: float | None) -> np.ndarray:
    """δ(f) = δ₀ √(1 + (f/f_δ)²) (δ₀ flat without f_δ)."""
    f = np.asarray(f_hz, np.float64)
    return delta0 * (np.ones_like(f) if growth_hz is None else np.sqrt(1.0 + (f / growth_hz) ** 2))


def convergence_check(update, gain: float, delta0: float, growth_hz: float | None = None,
                      n: int = 4000) -> dict:
    """ρ(f) on a grid (module docstring): {f_hz, rho, ok, band (f_lo, f_hi) of the first failing stretch,
    rho_max, message}."""
    Ts = update.model.Ts
    f = np.linspace(0.0, 0.5 / Ts, n + 1)[1:]
    w = 2 * math.pi * f
    rho = update.rho(w, gain, uncertainty(f, delta0, growth_hz))
    bad = rho >= 1.0
    out = {"f_hz": f, "rho": rho, "ok": not bool(bad.any()), "rho_max": float(rho.max()),
           "f_at_max": float(f[int(np.argmax(rho))]), "band": None, "message": ""}
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        j = i
        while j + 1 < f.size and bad[j + 1]:
            j += 1
        out["band"] = (float(f[i]), float(f[j]))
        cut = f", lower learn.q_cutoff_hz below {f[i]:.3g} Hz" if i > 0 else ""
        out["message"] = (f"the learning does not converge on {f[i]:.3g}-{f[j]:.3g} Hz: |Q(1 - α L G)| with the "
                          f"model's uncertainty δ = {delta0:g} reaches {rho[i:j + 1].max():.3g} ≥ 1 there (learning "
                          f"gain α = {gain:g}); lower learn.gain (ρ ≈ |1 - α| + α δ where Q ≈ 1){cut}, or identify "
                          "the model better (safety.uncertainty); --force runs it anyway, guarded by the rollback and "
                          "the check measured on the trials")
    return out


def standstill(r, settle: int) -> np.ndarray:
    """Samples where r has not changed for the last ``settle`` samples (the axis at rest)."""
    r = np.asarray(r, np.float64)
    moving = np.concatenate([[False], np.diff(r) != 0.0])
    last = np.maximum.accumulate(np.where(moving, np.arange(r.size), -settle - 1))
    return np.arange(r.size) - last > settle


def noise_floor(r, e, settle: int) -> float:
    """The error's noise level [m] on the standstill samples: rms of the sample-to-sample difference / √2 (a
    white measurement noise of std σ gives σ; slow residual error drops out of the difference). NaN when
    fewer than 100 standstill samples exist."""
    still = standstill(r, settle)
    pair = still[1:] & still[:-1]
    if pair.sum() < 100:
        return math.nan
    d = np.diff(np.asarray(e, np.float64))[pair]
    return float(np.sqrt(np.mean(d * d) / 2.0))


def limited(u: np.ndarray, u_max: float, rate: float, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """(u clipped to ±u_max, then slew-limited to rate·Ts per sample from u(0), flags) (the guard's
    SATURATED and RATE_LIMITED bits, :data:`pipeline.export.guard.FLAG`)."""
    u = np.asarray(u, np.float64)
    out = np.clip(u, -u_max, u_max)
    flags = np.where(out != u, FLAG["SATURATED"], 0).astype(np.int64)
    step = rate * Ts
    if math.isfinite(step):
        d = np.diff(out)
        if np.any(np.abs(d) > step):
            y = out.copy()
            for k in range(1, y.size):   # a forward pass: only where the slew is exceeded
                dk = out[k] - y[k - 1]
                if abs(dk) > step:
                    y[k] = y[k - 1] + math.copysign(step, dk)
                    flags[k] |= FLAG["RATE_LIMITED"]
            out = y
    return out, flags


def decide(history: list[dict], err: float, floor: float, rollback_factor: float, stop_factor: float) -> str:
    """What the campaign does after a trial of rms error ``err``: 'stop' (at the noise floor), 'rollback'
    (worse than rollback_factor × the best trial before it) or 'learn'. ``history``: the earlier trials'
    entries with 'rms'."""
    best = min((h["rms"] for h in history), default=math.inf)
    if math.isfinite(floor) and err <= stop_factor * floor:
        return "stop"
    if err > rollback_factor * best:
        return "rollback"
    return "learn"


#: a band of the measured check needs this many frequency bins: a band of one or two bins is not averaged, its
#: Ĝ is a ratio of two noisy numbers (a held-out trial's 2 s trials: 0.5-10 Hz bands of 0-4 bins halved α 9 times)
MIN_BINS = 4
#: ... and this coherence |Σ ΔY ΔΦ*|² / (Σ|ΔΦ|² Σ|ΔY|²) over its bins: where Δy is not a linear response to Δφ
#: (friction near a stop, noise) Ĝ is not the loop's, and its ρ̂ would slow a learning that converges
COHERENCE = 0.8


def unmeasured() -> dict:
    """:func:`measured_rho`'s findings where nothing was measured (the first trial, no change of φ)."""
    return {"rho_max": math.nan, "band": None, "gain_max": math.inf, "uncured": [], "ratio": math.nan, "failing": []}


def slower(gain: float, gain_max: float) -> float:
    """The gain after a trial that failed the measured check or rolled back: half, or half the measured bound
    ``gain_max`` where halving is not enough (a model far off: one trial, not ten)."""
    return gain / 2.0 if gain / 2.0 < gain_max else gain_max / 2.0


def measured_rho(update, gain: float, dphi: np.ndarray, dy: np.ndarray, noise: float = 0.0, nbands: int = 30,
                 snr: float = 10.0) -> dict:
    """The convergence condition against the plant the recordings measured: two trials' differences give the
    loop's response Ĝ = ΔY ΔΦ* / |ΔΦ|² (cross-spectrum over log-spaced bands: the measurement noise in Δy
    averages out), and ρ̂ = |Q| |1 - α L Ĝ| per band, L = (L G)/G of the model (:meth:`Update.learning`). Bands
    with fewer than :data:`MIN_BINS` frequency bins, a coherence of Δy with Δφ under :data:`COHERENCE` (Δy
    not a linear response: nonlinear friction, noise), where Δφ has under 1e-6 of its largest band's energy,
    |Q| < 0.01, or Δy under ``snr`` times the energy of the two recordings' white noise (std ``noise`` each:
    2 noise² n per frequency bin) are left out: near the floor Δy is noise and Ĝ means nothing.

    Which gain cures a band with ρ̂ ≥ 1: q |1 - α λ| < 1 (λ = L Ĝ, q = |Q|) holds for 0 < α < α_max =
    (Re λ + √(Re² λ + |λ|² (1/q² - 1))) / |λ|²; where Re λ ≤ 0 (the plant's phase more than 90° from the
    model's) no useful gain does. Returns {f_lo, f_hi, rho (NaN where left out), rho_max, band (f_lo, f_hi) of
    the worst band, or None, gain_max: the largest gain every failing band with Re λ > 0 contracts at (inf when
    none), uncured: the failing bands with Re λ ≤ 0, ratio: |λ| of the worst band (the plant's response over the
    model's there), failing: every band with ρ̂ ≥ 1}."""
    Ts = update.model.Ts
    n = dphi.size
    X, Y = np.fft.rfft(dphi), np.fft.rfft(dy)
    f = np.fft.rfftfreq(n, Ts)
    w = 2 * math.pi * f
    with np.errstate(divide="ignore", invalid="ignore"):
        lin = update.learning(w[1:]) / update.model.response(w[1:])
    X, Y, f, q = X[1:], Y[1:], f[1:], update.q(w[1:])
    edges = np.geomspace(f[0], f[-1] * (1 + 1e-12), nbands + 1)
    idx = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, nbands - 1)
    sxx = np.bincount(idx, np.abs(X) ** 2, nbands)
    def band_sum(z):      # a complex spectrum summed over each band's bins
        return np.bincount(idx, z.real, nbands) + 1j * np.bincount(idx, z.imag, nbands)
    lg = band_sum(lin * Y * np.conj(X))
    qb = np.bincount(idx, q * np.abs(X) ** 2, nbands)
    syy = np.bincount(idx, np.abs(Y) ** 2, nbands)
    nbins = np.bincount(idx, None, nbands)
    noise = noise if math.isfinite(noise) else 0.0
    sxy = band_sum(Y * np.conj(X))
    with np.errstate(divide="ignore", invalid="ignore"):
        coherence = np.abs(sxy) ** 2 / (sxx * syy)
    ok = (nbins >= MIN_BINS) & (sxx > 1e-6 * sxx.max()) & (syy > snr * nbins * 2.0 * noise ** 2 * n) \
        & (coherence >= COHERENCE)
    with np.errstate(divide="ignore", invalid="ignore"):
        qb, lg = qb / sxx, lg / sxx
    rho = np.where(ok & (qb >= 0.01), qb * np.abs(1.0 - gain * lg), np.nan)
    out = {"f_lo": edges[:-1], "f_hi": edges[1:], "rho": rho, **unmeasured()}
    if not np.any(np.isfinite(rho)):
        return out
    k = int(np.nanargmax(rho))
    out.update(rho_max=float(rho[k]), band=(float(edges[k]), float(edges[k + 1])), ratio=float(abs(lg[k])))
    for b in np.flatnonzero(np.nan_to_num(rho, nan=0.0) >= 1.0):
        out["failing"].append((float(edges[b]), float(edges[b + 1])))
        lam, qq = lg[b], min(float(qb[b]), 1.0)
        if lam.real <= 0.0:
            out["uncured"].append((float(edges[b]), float(edges[b + 1])))
        else:
            a2 = abs(lam) ** 2
            out["gain_max"] = min(out["gain_max"], (lam.real + math.sqrt(lam.real ** 2 + a2 * (1 / qq ** 2 - 1))) / a2)
    return out
