"""The guard around every exported feedforward law (issue 22): what the law may be fed and what it
may send to the actuator, the same in C and in Python, flag for flag.

Per sample t, around the law's own step (which is unchanged: on clean input inside the limits the
guarded u_ff is the study's to the bit):

1. **Input sanitation.** A non-finite reference sample r(t+i) of the preview window is replaced by
   the last finite one (the forward-filled reference r_c; before t = 0 the rest value r0, itself 0
   if non-finite) and the sample is flagged ``NONFINITE_INPUT``. The law never sees a NaN, so its
   state (recursions, filters) stays finite.
2. **Training envelope.** The regressors x = [r_c(n), δr_c(n), δ²r_c(n)] (position, first and
   second backward difference / Ts, Ts²: what every law's φ is built from, the reference standing in
   for the identified output y) at every n = t .. t + P, i.e. over the whole window r(t-2) .. r(t+P)
   the law is fed, must lie in [lo, hi] per component, the range of the same quantities over the
   identification data's y widened by a margin of the range on each side. Outside: ``OUT_OF_RANGE``
   (only flagged by default; with ``envelope_action = fallback`` it also triggers the fallback).
   Checking the newest sample only let a step's kick through unflagged once the step had left it
   (a 1 mm step: +2506 N flagged, then -2498 N not). A recursive law (Newton's model state, a
   filter) carries an excursion's effect past the window: the flag marks the samples whose own
   input left the envelope, not that memory.
3. **Fallback** on an invalid sample (``NONFINITE_INPUT``, a non-finite law output, or
   ``OUT_OF_RANGE`` with ``envelope_action = fallback``), flagged ``FALLBACK``:
   ``hold``: the last output of a valid sample; ``ramp``: that output times max(0, 1 - m Ts /
   ramp_time) on the m-th invalid sample in a row (to 0 N over ramp_time, never a step);
   ``physics``: the rigid-body law M δ²r + F_v δr + F_c sign δr on the regressors (a finite,
   out-of-range reference); on a non-finite reference there is no trustworthy reference to feed
   it, so it holds as ``hold`` does.
4. **Saturation** to [u_min, u_max] (``SATURATED``), then the **slew limit**
   |u(t) - u(t-1)| <= rate · Ts (``RATE_LIMITED``), from u(-1) = 0 (the actuator at rest).

Defaults (no limits: ±inf; envelope flagging only; fallback hold) leave every clean sample's u_ff
untouched. The flags (one bit each, :data:`FLAGS`) are shared by all laws; the low bits are the
laws' own (Newton's ``BOUNDS``/``SINGULAR``/``DIVERGED``, a table's ``OTHER_REFERENCE``/``PAST_END``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import ExportError

__all__ = ["FLAGS", "FLAG", "FALLBACKS", "Guard", "envelope_of", "run_guard", "regressors"]

#: (name, bit, meaning) of every status flag of an exported law
FLAGS = (
    ("BOUNDS", 1, "Newton: the start or an update left [u_min, u_max] of invert (the best iterate is returned)"),
    ("SINGULAR", 2, "Newton: a zero/non-finite derivative or prediction (the best iterate is returned); any "
                    "law: a non-finite output (an overflow), replaced by the fallback until init"),
    ("DIVERGED", 4, "Newton: the last |V_R| exceeds the first"),
    ("OTHER_REFERENCE", 8, "table: r(t) differs from the reference the table was made for"),
    ("PAST_END", 16, "table: past the end of the table, its last value is held"),
    ("SATURATED", 32, "u_ff was clipped to [u_min, u_max] (export.limits)"),
    ("RATE_LIMITED", 64, "|u_ff(t) - u_ff(t-1)| was limited to rate * Ts (export.limits.rate)"),
    ("OUT_OF_RANGE", 128, "r, dr/dt or d2r/dt2 somewhere in the law's window r(t-2) .. r(t+P) left the training "
                          "envelope"),
    ("NONFINITE_INPUT", 256, "a preview sample was NaN/inf: the last finite sample was used instead"),
    ("FALLBACK", 512, "u_ff is the fallback (hold, physics or ramp), not the law's"),
)
FLAG = {n: b for n, b, _ in FLAGS}
#: the laws' own flags, by family
CORE_FLAGS = {"pgnn": ("BOUNDS", "SINGULAR", "DIVERGED"), "k_filter": ("SINGULAR",),
              "rigid_body": ("SINGULAR",), "table": ("OTHER_REFERENCE", "PAST_END")}
GUARD_FLAGS = ("SATURATED", "RATE_LIMITED", "OUT_OF_RANGE", "NONFINITE_INPUT", "FALLBACK")
FALLBACKS = ("hold", "physics", "ramp")
REGRESSORS = ("r", "dr", "d2r")


@dataclass
class Guard:
    """Limits, envelope and fallback of a law (module docstring); ±inf: no limit."""

    u_min: float = -math.inf                 # [N]
    u_max: float = math.inf                  # [N]
    rate: float = math.inf                   # [N/s]
    env_lo: list = field(default_factory=lambda: [-math.inf] * 3)    # r [m], δr [m/s], δ²r [m/s²]
    env_hi: list = field(default_factory=lambda: [math.inf] * 3)
    envelope_action: str = "flag"            # flag | fallback
    fallback: str = "hold"                   # hold | physics | ramp
    ramp_time: float = 0.1                   # [s]
    physics: list = field(default_factory=lambda: [0.0, 0.0, 0.0])   # [M, F_v, F_c] of the physics fallback

    def __post_init__(self):
        for k in ("u_min", "u_max", "rate", "ramp_time"):
            setattr(self, k, float(getattr(self, k)))
        self.env_lo = [float(v) for v in self.env_lo]
        self.env_hi = [float(v) for v in self.env_hi]
        self.physics = [float(v) for v in self.physics]
        if self.fallback not in FALLBACKS:
            raise ExportError(f"fallback must be one of {FALLBACKS}, got {self.fallback!r}")
        if self.envelope_action not in ("flag", "fallback"):
            raise ExportError(f"envelope_action must be 'flag' or 'fallback', got {self.envelope_action!r}")
        if not (self.u_min < self.u_max and self.rate > 0 and self.ramp_time > 0):
            raise ExportError(f"limits need u_min < u_max, rate > 0 and ramp_time > 0; got u_min={self.u_min}, "
                              f"u_max={self.u_max}, rate={self.rate}, ramp_time={self.ramp_time}")
        if len(self.env_lo) != 3 or len(self.env_hi) != 3 or any(math.isnan(v) for v in self.env_lo + self.env_hi):
            raise ExportError("the envelope needs 3 lower and 3 upper bounds (r, dr, d2r), none NaN")
        if not all(math.isfinite(v) for v in self.physics):
            raise ExportError(f"the physics fallback's [M, F_v, F_c] must be finite, got {self.physics}")

    def du_max(self, Ts: float) -> float:
        """Largest |u(t) - u(t-1)| [N]: rate · Ts."""
        return self.rate * float(Ts)

    def ramp_n(self, Ts: float) -> float:
        """Samples of the ramp to zero: ramp_time / Ts."""
        return self.ramp_time / float(Ts)


def _diff(x: np.ndarray, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    return (x[2:] - x[1:-1]) / Ts, (x[2:] - 2.0 * x[1:-1] + x[:-2]) / (Ts * Ts)


def envelope_of(segments, Ts: float, margin: float) -> tuple[list, list]:
    """[lo], [hi] of (r, δr, δ²r) over the signals ``segments`` (the identification data's y, one
    array per experiment: no difference across a boundary), each widened by ``margin`` × its range."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for y in segments:
        y = np.asarray(y, dtype=np.float64)
        if y.size < 3:
            continue
        v, a = _diff(y, Ts)
        for i, x in enumerate((y, v, a)):
            lo[i], hi[i] = min(lo[i], float(np.min(x))), max(hi[i], float(np.max(x)))
    if not np.all(np.isfinite(lo)):
        return [-math.inf] * 3, [math.inf] * 3
    width = hi - lo
    return list(lo - margin * width), list(hi + margin * width)


def sanitized(r: np.ndarray, r0: float) -> tuple[np.ndarray, np.ndarray]:
    """(r_c, finite): r forward-filled from the rest value r0 over its non-finite samples."""
    finite = np.isfinite(r)
    idx = np.where(finite, np.arange(r.size), -1)
    np.maximum.accumulate(idx, out=idx)
    r_c = np.where(idx >= 0, r[np.maximum(idx, 0)], r0)
    return r_c, finite


def _regressors_all(r_c: np.ndarray, r0: float, preview: int, Ts: float) -> np.ndarray:
    """[N + P, 3]: r_c(n), δr_c(n), δ²r_c(n) at every n = 0 .. N - 1 + P (held after the end; r0 before 0),
    as the C computes them from its window ext = [r(t-2), r(t-1), r(t) .. r(t+P)]."""
    ext = np.concatenate([[r0, r0], r_c, np.full(preview, r_c[-1])])
    x0, x1, x2 = ext[2:], ext[1:-1], ext[:-2]
    with np.errstate(over="ignore", invalid="ignore"):     # an absurd reference: inf, flagged OUT_OF_RANGE
        return np.stack([x0, (x0 - x1) / Ts, (x0 - 2.0 * x1 + x2) / (Ts * Ts)], axis=1)


def regressors(r_c: np.ndarray, r0: float, preview: int, Ts: float) -> np.ndarray:
    """[N, 3]: the regressors at the newest sample n = t + P of every t."""
    return _regressors_all(r_c, r0, preview, Ts)[preview:]


def run_guard(g: Guard, Ts: float, preview: int, r: np.ndarray, r0: float, core,
              u_start: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(u_ff, flags) of a guarded law on the whole reference r: ``core(r_c) -> (u, flags)`` is the
    law itself on the sanitized reference. The sequential part (fallback, limits) runs sample by
    sample in the C's order of operations, so both give the same doubles."""
    r0 = r0 if math.isfinite(r0) else 0.0
    r_c, finite = sanitized(r, r0)
    N, P = r.size, preview
    u_core, flags = core(r_c)
    flags = np.asarray(flags, dtype=np.int64).copy()
    bad = ~finite
    if P:                             # any non-finite sample in r(t) .. r(t+P) (the end held)
        bad_ext = np.concatenate([bad, np.full(P, bad[-1])])
        bad = np.lib.stride_tricks.sliding_window_view(bad_ext, P + 1).any(axis=1)
    flags |= np.where(bad, FLAG["NONFINITE_INPUT"], 0)
    x_all = _regressors_all(r_c, r0, P, Ts)
    x = x_all[P:]                     # the newest, n = t + P: the physics fallback's regressors
    ok = ((np.asarray(g.env_lo) <= x_all) & (x_all <= np.asarray(g.env_hi))).all(axis=1)
    inside = np.lib.stride_tricks.sliding_window_view(ok, P + 1).all(axis=1)   # every n = t .. t + P (the C's loop)
    flags |= np.where(inside, 0, FLAG["OUT_OF_RANGE"])
    invalid = bad | ~np.isfinite(u_core)
    if g.envelope_action == "fallback":
        invalid |= ~inside
    unlimited = g.u_min == -math.inf and g.u_max == math.inf and g.rate == math.inf
    if unlimited and not invalid.any():
        return u_core, flags          # the law's own numbers, untouched
    u = np.empty(N)
    du, ramp_n = g.du_max(Ts), g.ramp_n(Ts)
    M, Fv, Fc = g.physics
    u_prev = u_hold = float(u_start)   # the output before t = 0: the law at rest (0 N: the actuator at rest)
    m = 0
    for t in range(N):
        f = int(flags[t])
        v = float(u_core[t])
        if invalid[t]:
            f |= FLAG["FALLBACK"]
            m += 1
            if g.fallback == "ramp":
                k = 1.0 - m / ramp_n
                v = u_hold * (k if k > 0.0 else 0.0)
            elif g.fallback == "physics" and not bad[t]:
                vel, acc = float(x[t, 1]), float(x[t, 2])
                sg = 1.0 if vel > 0 else (-1.0 if vel < 0 else 0.0)
                v = M * acc + Fv * vel + Fc * sg
                if not math.isfinite(v):
                    v = u_hold
            else:
                v = u_hold
        else:
            m = 0
        if v > g.u_max:
            v, f = g.u_max, f | FLAG["SATURATED"]
        elif v < g.u_min:
            v, f = g.u_min, f | FLAG["SATURATED"]
        if v - u_prev > du:
            v, f = u_prev + du, f | FLAG["RATE_LIMITED"]
        elif u_prev - v > du:
            v, f = u_prev - du, f | FLAG["RATE_LIMITED"]
        if not invalid[t]:
            u_hold = v
        u_prev = v
        u[t], flags[t] = v, f
    return u, flags
