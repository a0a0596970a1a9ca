"""The guard around every exported feedforward law (issue 22): what the law may be fed and what it
may send to the actuator, the same in C and in Python, flag for flag.

Per sample t, around the law's own step (which is unchanged: on clean input inside the limits the
guarded u_ff is the study's to the bit):

1. **Input sanitation.** A non-finite reference sample r(t+i) of the preview window is replaced by
   the last finite one (the forward-filled reference r_c; before t = 0 the rest value r0, itself 0
   if non-finite). The law never sees a NaN, so its state (recursions, filters) stays finite.
   ``NONFINITE_INPUT`` marks every sample whose window r(t-2) .. r(t+P) (the regressors below) holds
   a replaced sample: the forward-filled value is a step in the law's differences (one NaN in motion:
   M δ²r = 3 kN on the samples after it), so those samples are invalid too.
2. **Training envelope.** The regressors x = [r_c(n), δr_c(n), δ²r_c(n)] (position, first and
   second backward difference / Ts, Ts²: what every law's φ is built from, the reference standing in
   for the identified output y) at every n = t .. t + P, i.e. over the whole window r(t-2) .. r(t+P)
   the law is fed, must lie in [lo, hi] per component, the range of the same quantities over the
   identification data's y widened by a margin of the range on each side. Outside: ``OUT_OF_RANGE``
   (only flagged by default; with ``envelope_action = fallback`` it also triggers the fallback).
   Checking the newest sample only let a step's kick through unflagged once the step had left it
   (a 1 mm step: +2506 N flagged, then -2498 N not). A recursive law (Newton's model state, a
   filter) carries an excursion's effect past the window: the flag marks the samples whose own
   input left the envelope, not that memory. A non-finite regressor (an absurd reference, e.g.
   1e306 m: its differences overflow) is outside any envelope and always invalid.
3. **Fallback** on an invalid sample, flagged ``FALLBACK``: ``NONFINITE_INPUT``; an overflow (a
   non-finite regressor, a non-finite law output, or the law's ``SINGULAR``: Newton's start or
   iteration overflowed and it returned 0 N or its last finite iterate); ``OUT_OF_RANGE`` with
   ``envelope_action = fallback``. ``hold``: the last output of a valid sample; ``ramp``: that
   output times max(0, 1 - m Ts / ramp_time) on the m-th invalid sample in a row (to 0 N over
   ramp_time, never a step); ``physics``: the rigid-body law M δ²r + Σ_j p_j T_j(r, δr) with every
   force term of the system (viscous, Coulomb, Stribeck, offset (gravity), cogging:
   :data:`pipeline.systems.force_terms.TERMS`) on the newest regressors (a finite, out-of-range
   reference); on a non-finite reference there is no trustworthy reference to feed it, so it holds
   as ``hold`` does.
   **Latch.** A non-finite law output means the law's state (its recursion, a filter register) may
   hold inf/NaN and cannot be trusted again: the fallback is latched until init (``SINGULAR`` and
   ``FALLBACK`` on every later sample). Every other invalid sample recovers when the input is valid.
   **Return.** After a fallback the output goes back to the law's linearly over ramp_time
   (u = u_from + (u_law - u_from) m/(ramp_time/Ts) on the m-th valid sample, ``FALLBACK`` still set),
   so the return never steps even with no slew limit: a recursive law's state has seen the held
   samples, and its first outputs after them may still carry that.
4. **Saturation** to [u_min, u_max] (``SATURATED``), then the **slew limit**
   |u(t) - u(t-1)| <= rate · Ts (``RATE_LIMITED``), from u(-1) = the law at rest (0 N: the actuator at
   rest). With finite limits no sample leaves [u_min, u_max] and no step exceeds rate · Ts, on any
   path (a fallback, its return, a glitch), as long as u(-1) lies in [u_min, u_max].

Under ``export.target_rate`` the zero-order hold (:func:`zoh_loop`, ``templates/zoh.c``) also ramps
its held output at the slew limit per loop sample, |Δu| <= rate · Ts / N.

Defaults (no limits: ±inf; envelope flagging only; fallback hold) leave every clean sample's u_ff
untouched. The flags (one bit each, :data:`FLAGS`) are shared by all laws; the low bits are the
laws' own (Newton's ``BOUNDS``/``SINGULAR``/``DIVERGED``, a table's ``OTHER_REFERENCE``/``PAST_END``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import ExportError

__all__ = ["FLAGS", "FLAG", "FALLBACKS", "Guard", "envelope_of", "run_guard", "regressors", "physics_force",
           "zoh_loop"]

#: (name, bit, meaning) of every status flag of an exported law
FLAGS = (
    ("BOUNDS", 1, "Newton: the start or an update left [u_min, u_max] of invert (the best iterate is returned)"),
    ("SINGULAR", 2, "an overflow: Newton's zero/non-finite derivative or prediction, or a non-finite output of "
                    "any law; the sample falls back, and after a non-finite output every sample until the next "
                    "init (latched: the law's state is not trusted again)"),
    ("DIVERGED", 4, "Newton: the last |V_R| exceeds the first"),
    ("OTHER_REFERENCE", 8, "table: r(t) differs from the reference the table was made for"),
    ("PAST_END", 16, "table: past the end of the table, its last value is held"),
    ("SATURATED", 32, "u_ff was clipped to [u_min, u_max] (export.limits)"),
    ("RATE_LIMITED", 64, "|u_ff(t) - u_ff(t-1)| was limited to rate * Ts (export.limits.rate)"),
    ("OUT_OF_RANGE", 128, "r, dr/dt or d2r/dt2 somewhere in the law's window r(t-2) .. r(t+P) left the training "
                          "envelope or is non-finite (an overflow: then also FALLBACK)"),
    ("NONFINITE_INPUT", 256, "a sample of the window r(t-2) .. r(t+P) was NaN/inf: the last finite sample was used "
                             "instead, and the sample falls back"),
    ("FALLBACK", 512, "u_ff is the fallback (hold, physics or ramp), or still ramping back from it to the law's "
                      "over ramp_time, not the law's own"),
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
    # the physics fallback M δ²r + Σ_j p_j T_j(r, δr): physics = [M, p_1, ..., p_n] (θ' of the inverse form),
    # physics_codes = the n kernel codes of T_j, physics_consts = their shape constants
    # (pipeline.systems.force_terms.ForceTerms.kernel); the default codes [viscous, sign] make
    # [M, F_v, F_c] the linear motor's (8)
    physics: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    physics_codes: list = field(default_factory=lambda: [0, 1])
    physics_consts: list = field(default_factory=lambda: [0.0, 0.0])

    def __post_init__(self):
        for k in ("u_min", "u_max", "rate", "ramp_time"):
            setattr(self, k, float(getattr(self, k)))
        self.env_lo = [float(v) for v in self.env_lo]
        self.env_hi = [float(v) for v in self.env_hi]
        self.physics = [float(v) for v in self.physics]
        self.physics_codes = [int(c) for c in self.physics_codes]
        self.physics_consts = [float(v) for v in self.physics_consts]
        if self.fallback not in FALLBACKS:
            raise ExportError(f"fallback must be one of {FALLBACKS}, got {self.fallback!r}")
        if self.envelope_action not in ("flag", "fallback"):
            raise ExportError(f"envelope_action must be 'flag' or 'fallback', got {self.envelope_action!r}")
        if not (self.u_min < self.u_max and self.rate > 0 and self.ramp_time > 0):
            raise ExportError(f"limits need u_min < u_max, rate > 0 and ramp_time > 0; got u_min={self.u_min}, "
                              f"u_max={self.u_max}, rate={self.rate}, ramp_time={self.ramp_time}")
        if len(self.env_lo) != 3 or len(self.env_hi) != 3 or any(math.isnan(v) for v in self.env_lo + self.env_hi):
            raise ExportError("the envelope needs 3 lower and 3 upper bounds (r, dr, d2r), none NaN")
        if not all(math.isfinite(v) for v in self.physics + self.physics_consts):
            raise ExportError(f"the physics fallback's [M, p_1, ...] and shape constants must be finite, got "
                              f"{self.physics}, {self.physics_consts}")
        from pipeline.systems.force_terms import MAX_CODE  # lazy: saves 0.6 s of start-up (numba kernels)
        n = len(self.physics) - 1
        if n < 0 or len(self.physics_codes) != n or len(self.physics_consts) != n or \
                not all(0 <= c <= MAX_CODE for c in self.physics_codes):
            raise ExportError(f"the physics fallback needs [M, p_1 .. p_n], n kernel codes in 0..{MAX_CODE} and n "
                              f"shape constants (force_terms.ForceTerms.kernel); got {self.physics}, "
                              f"{self.physics_codes}, {self.physics_consts}")

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
    # NONFINITE_INPUT: a replaced sample anywhere in r(t-2) .. r(t+P) (the end held): the law's differences
    # see the forward-filled value as a step on the samples after a NaN too
    bad_ext = np.concatenate([[False, False], ~finite, np.full(P, not finite[-1])])
    bad = np.lib.stride_tricks.sliding_window_view(bad_ext, P + 3).any(axis=1)
    flags |= np.where(bad, FLAG["NONFINITE_INPUT"], 0)
    x_all = _regressors_all(r_c, r0, P, Ts)
    x = x_all[P:]                     # the newest, n = t + P: the physics fallback's regressors
    fin = np.isfinite(x_all).all(axis=1)
    ok = fin & ((np.asarray(g.env_lo) <= x_all) & (x_all <= np.asarray(g.env_hi))).all(axis=1)
    every = lambda a: np.lib.stride_tricks.sliding_window_view(a, P + 1).all(axis=1)   # noqa: E731  n = t .. t + P
    inside, overflow = every(ok), ~every(fin)                     # (the C's loop)
    flags |= np.where(inside, 0, FLAG["OUT_OF_RANGE"])
    # invalid: a replaced input, an overflow (inf regressor, non-finite output, the law's SINGULAR: Newton
    # returns 0 N or its last finite iterate when it overflows), out of the envelope when that falls back
    invalid = bad | overflow | ~np.isfinite(u_core) | ((flags & FLAG["SINGULAR"]) != 0)
    if g.envelope_action == "fallback":
        invalid |= ~inside
    unlimited = g.u_min == -math.inf and g.u_max == math.inf and g.rate == math.inf
    if unlimited and not invalid.any():
        return u_core, flags          # the law's own numbers, untouched
    u = np.empty(N)
    du, ramp_n = g.du_max(Ts), g.ramp_n(Ts)
    u_prev = u_hold = float(u_start)   # the output before t = 0: the law at rest (0 N: the actuator at rest)
    u_from = 0.0                       # the output the return from a fallback ramps from
    m = back = 0                       # invalid samples in a row; valid samples since a fallback (0: none)
    latched = False                    # a non-finite law output: the fallback until init
    for t in range(N):
        f = int(flags[t])
        v = float(u_core[t])
        if not math.isfinite(v):
            latched = True
        if latched:
            f |= FLAG["SINGULAR"]
        if invalid[t] or latched:
            f |= FLAG["FALLBACK"]
            m += 1
            back = 0
            if g.fallback == "ramp":
                k = 1.0 - m / ramp_n
                v = u_hold * (k if k > 0.0 else 0.0)
            elif g.fallback == "physics" and not bad[t]:
                v = physics_force(g, float(x[t, 0]), float(x[t, 1]), float(x[t, 2]))
                if not math.isfinite(v):
                    v = u_hold
            else:
                v = u_hold
        else:
            if m > 0:                  # the first valid sample after a fallback: ramp back from its output
                u_from, back = u_prev, 1
            elif back > 0:
                back += 1
            m = 0
            if back > 0:
                k = back / ramp_n
                if k < 1.0:
                    v = u_from + (v - u_from) * k
                    f |= FLAG["FALLBACK"]
                else:
                    back = 0
        if v > g.u_max:
            v, f = g.u_max, f | FLAG["SATURATED"]
        elif v < g.u_min:
            v, f = g.u_min, f | FLAG["SATURATED"]
        if v - u_prev > du:
            v, f = u_prev + du, f | FLAG["RATE_LIMITED"]
        elif u_prev - v > du:
            v, f = u_prev - du, f | FLAG["RATE_LIMITED"]
        if not (invalid[t] or latched):
            u_hold = v
        u_prev = v
        u[t], flags[t] = v, f
    return u, flags


def _term(code: int, p: float, q: float, v: float) -> float:
    """T(q, q̇) of one force term, as templates/force_term.c's force_term (force_terms.term, the C library's
    tanh/exp/cos/sin through math, so C and Python agree to the bit)."""
    sg = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
    if code == 0:
        return v
    if code == 1:
        return sg
    if code == 2:
        return math.tanh(v / p)
    if code == 3:
        x = v / p
        return sg * math.exp(-(x * x))
    if code == 4:
        return 1.0
    if code == 7:
        return v * abs(v)
    if code > 7:                      # (q/p)^k, k = code - 7, by the C's products
        x = q / p
        t = x
        for _ in range(code - 8):
            t = t * x
        return t
    a = p * q
    if not math.isfinite(a):          # C's cos/sin(±inf) is NaN (math's raise)
        return math.nan
    return math.cos(a) if code == 5 else math.sin(a)


def physics_force(g: Guard, q: float, vel: float, acc: float) -> float:
    """The physics fallback M δ²r + Σ_j p_j T_j(r, δr) on the regressors (q, vel, acc), in the C's order."""
    v = g.physics[0] * acc
    for p, code, c in zip(g.physics[1:], g.physics_codes, g.physics_consts):
        v += p * _term(code, c, q, vel)
    return v


def zoh_loop(u_law, n: int, du_loop: float, u0: float = 0.0) -> np.ndarray:
    """The zero-order-hold wrapper's output at the loop rate n / Ts (templates/zoh.c, same operations): the
    law's u_ff(k) is the target from loop sample k n on, reached from the wrapper's last output (u0 before the
    first) in steps of at most du_loop = rate · Ts / n, so a law step of up to rate · Ts (the guard's slew
    limit) takes at most n loop samples; du_loop = inf: the plain hold."""
    held = np.repeat(np.asarray(u_law, dtype=np.float64), int(n))
    if not du_loop < math.inf:
        return held
    out = np.empty_like(held)
    u = float(u0)
    for i, target in enumerate(held):
        if target - u > du_loop:
            u = u + du_loop
        elif u - target > du_loop:
            u = u - du_loop
        else:
            u = float(target)
        out[i] = u
    return out
