"""Third-order (jerk-limited) point-to-point reference trajectories (SPEC §1).

A move from rest to rest over a distance ``D`` with bounds ``v_max, a_max, j_max`` is the
classic 7-segment profile: the jerk is piecewise constant ``+j, 0, -j, 0, -j, 0, +j`` with
durations ``t_j, t_a, t_j, t_v, t_j, t_a, t_j``; position, velocity and acceleration follow by
integrating it three times, in closed form per segment.  The segment times are computed
analytically (:func:`move_times`): a long move reaches ``v_max`` (cruise ``t_v > 0``), a short
one never does (``t_v = 0``), and a move that cannot build up ``a_max`` before it must ramp the
acceleration down again is jerk-limited below ``a_max`` (``t_a = 0``), as [B2]'s reference R
(peak acceleration 2 m/s² with ``a_max = 4``).

Sampling evaluates the continuous profile at ``t_k = k Ts`` exactly (no numerical
integration), so no bound is exceeded (beyond rounding, ~1e-16 relative) and every move lands
exactly on its target: the second half of a move is evaluated through the profile's point
symmetry ``p(t) = D - p(T - t)`` from the target backwards.

A reference is a sequence of steps (:class:`Rest`, :class:`MoveTo`, absolute target positions)
sampled by :func:`sequence`; :func:`from_spec` builds one from a config dict.  Helpers give
the papers' named references: [K] §VI out-and-back moves (:func:`out_and_back`,
:data:`K_TRAINING_MOVES`), [B1] §VI oscillating references (:func:`b1_training_reference`,
:func:`b1_evaluation_reference`) and [B2] §VI reference R (:func:`b2_reference`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = [
    "MoveTimes", "Rest", "MoveTo", "Reference", "move_times", "move", "sequence",
    "out_and_back", "oscillating", "b1_training_reference", "b1_evaluation_reference",
    "b2_reference", "b2_training_reference", "from_spec", "profile_from_spec", "KINDS",
    "K_TRAINING_MOVES", "K_HELDOUT_MOVES", "K_STRIBECK_MOVE", "B1_EVAL_VMAX",
]

# [K] §VI / SPEC §2.1: (distance [m], v_max [m/s]) with a_max = 5 m/s², j_max = 200 m/s³
K_TRAINING_MOVES: tuple[tuple[float, float], ...] = (
    (0.02, 0.02), (0.05, 0.05), (0.05, 0.1), (0.1, 0.1), (0.1, 0.2), (0.2, 0.3),
    (0.03, 0.03), (0.15, 0.15), (0.08, 0.25))
K_HELDOUT_MOVES: tuple[tuple[float, float], ...] = (
    (0.06, 0.07), (0.12, 0.18), (0.04, 0.12), (0.03, 0.05))
K_STRIBECK_MOVE: tuple[float, float] = (0.03, 0.05)   # the Stribeck-dominated held-out move
# [B1] §VI / SPEC §2.2: evaluation velocities [m/s] (0.15 m/s is [B1] Fig. 3)
B1_EVAL_VMAX: tuple[float, ...] = (0.05, 0.10, 0.15, 0.20)

_EPS_T = 1e-9   # relative slack [-] when counting samples in a duration (rounding of sums)


def _positive(name: str, x) -> float:
    v = _finite(name, x)
    if not v > 0.0:
        raise ValueError(f"{name} must be positive, got {x!r}; give a bound > 0")
    return v


def _nonnegative(name: str, x) -> float:
    v = _finite(name, x)
    if v < 0.0:
        raise ValueError(f"{name} must be >= 0, got {x!r}")
    return v


#: longest reference built (10^7 samples: 80 MB per signal, 2.8 h at 1 kHz); a longer one is a
#: typo (a rest of 1e9 s) that would end in a memory error deep inside a stage
MAX_SAMPLES = 10**7


def _count(n: int, what: str, Ts: float) -> int:
    if n > MAX_SAMPLES:
        raise ValueError(f"{what} has {n:.3g} samples at Ts={Ts:g} s, more than {MAX_SAMPLES:.0e} "
                         "(80 MB per signal): shorten it (durations, repeats, n_samples) or raise Ts")
    return n


def _finite(name: str, x) -> float:
    if isinstance(x, bool):   # YAML's true is not a length of 1 m
        raise ValueError(f"{name} must be a number, got {x!r}")
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {x!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {x!r}")
    return v


# --------------------------------------------------------------------------- one move
@dataclass(frozen=True)
class MoveTimes:
    """Segment durations [s] and peak values of one rest-to-rest move of length ``distance``.

    Jerk ``+j, 0, -j, 0, -j, 0, +j`` over ``t_j, t_a, t_j, t_v, t_j, t_a, t_j``.
    ``v_peak`` [m/s] and ``a_peak`` [m/s²] are the reached maxima (≤ the bounds);
    ``velocity_limited`` / ``acceleration_limited`` say whether v_max / a_max are reached.
    """

    distance: float      # |D| [m]
    j: float             # jerk magnitude [m/s³] (= j_max)
    t_j: float
    t_a: float
    t_v: float
    v_peak: float
    a_peak: float
    velocity_limited: bool
    acceleration_limited: bool

    @property
    def duration(self) -> float:
        """Total move time T = 4 t_j + 2 t_a + t_v [s]."""
        return 4.0 * self.t_j + 2.0 * self.t_a + self.t_v

    @property
    def boundaries(self) -> np.ndarray:
        """End times [s] of the 7 jerk segments (zero-length segments give repeated times)."""
        return np.cumsum([self.t_j, self.t_a, self.t_j, self.t_v, self.t_j, self.t_a, self.t_j])


def move_times(distance: float, v_max: float, a_max: float, j_max: float) -> MoveTimes:
    """Segment times of the time-optimal jerk-limited rest-to-rest move (SPEC §1).

    Parameters
    ----------
    distance : float
        Move length [m]; its sign is ignored (the profile of |distance|).
    v_max, a_max, j_max : float
        Bounds on |velocity| [m/s], |acceleration| [m/s²], |jerk| [m/s³], all > 0.

    Returns
    -------
    MoveTimes
        Durations and reached peaks.  Cases: if ``v_max j_max >= a_max²`` the acceleration
        phase to v_max reaches a_max (``t_j = a/j, t_a = v/a - t_j``), else it is jerk-limited
        (``t_j = sqrt(v/j), t_a = 0``).  If the move is too short to cruise, the peak velocity
        solves ``D = v (2 t_j + t_a)``: ``t_j = (D/(2j))^(1/3)`` when ``D <= 2 a³/j²``, else
        ``t_j = a/j`` and ``t_a = (-3 t_j + sqrt(t_j² + 4D/a))/2``.
    """
    D = abs(_finite("distance", distance))
    v = _positive("v_max", v_max)
    a = _positive("a_max", a_max)
    j = _positive("j_max", j_max)
    if D == 0.0:
        return MoveTimes(0.0, j, 0.0, 0.0, 0.0, 0.0, 0.0, False, False)
    # acceleration phase that reaches v_max
    if v * j >= a * a:
        t_j, t_a = a / j, max(v / a - a / j, 0.0)
    else:
        t_j, t_a = math.sqrt(v / j), 0.0
    d_acc = 0.5 * v * (2.0 * t_j + t_a)      # distance covered while accelerating to v_max
    if 2.0 * d_acc <= D:
        t_v = (D - 2.0 * d_acc) / v
        v_peak = v
    else:                                    # v_max is not reached: no cruise phase
        t_v = 0.0
        if D <= 2.0 * a ** 3 / j ** 2:       # jerk-limited below a_max
            t_j, t_a = (D / (2.0 * j)) ** (1.0 / 3.0), 0.0
        else:
            t_j = a / j
            t_a = max(0.5 * (-3.0 * t_j + math.sqrt(t_j * t_j + 4.0 * D / a)), 0.0)
        v_peak = min(j * t_j * t_j + j * t_j * t_a, v)
    a_peak = min(j * t_j, a)
    return MoveTimes(D, j, t_j, t_a, t_v, v_peak, a_peak,
                     velocity_limited=t_v > 0.0 or math.isclose(v_peak, v, rel_tol=1e-12),
                     acceleration_limited=t_a > 0.0 or math.isclose(a_peak, a, rel_tol=1e-12))


def _first_half(mt: MoveTimes, tau: np.ndarray):
    """Closed-form p, v, a of the accelerating half (jerk segments 1–3 + half the cruise),
    for 0 <= tau <= T/2, for a move of positive length."""
    j, t_j, t_a = mt.j, mt.t_j, mt.t_a
    a1 = j * t_j                                   # plateau acceleration
    v1, p1 = 0.5 * j * t_j ** 2, j * t_j ** 3 / 6.0
    v2, p2 = v1 + a1 * t_a, p1 + v1 * t_a + 0.5 * a1 * t_a ** 2
    v3 = v2 + a1 * t_j - 0.5 * j * t_j ** 2
    p3 = p2 + v2 * t_j + 0.5 * a1 * t_j ** 2 - j * t_j ** 3 / 6.0
    p, v, a = np.empty_like(tau), np.empty_like(tau), np.empty_like(tau)
    b1, b2, b3 = t_j, t_j + t_a, 2.0 * t_j + t_a
    s1 = tau < b1
    s2 = (tau >= b1) & (tau < b2)
    s3 = (tau >= b2) & (tau < b3)
    s4 = tau >= b3
    x = tau[s1]                                    # jerk +j from rest
    p[s1], v[s1], a[s1] = j * x ** 3 / 6.0, 0.5 * j * x ** 2, j * x
    x = tau[s2] - b1                               # constant acceleration a1
    p[s2], v[s2], a[s2] = p1 + v1 * x + 0.5 * a1 * x ** 2, v1 + a1 * x, a1
    x = tau[s3] - b2                               # jerk -j down to zero acceleration
    p[s3] = p2 + v2 * x + 0.5 * a1 * x ** 2 - j * x ** 3 / 6.0
    v[s3] = v2 + a1 * x - 0.5 * j * x ** 2
    a[s3] = a1 - j * x
    x = tau[s4] - b3                               # cruise at v3 (≤ v_max)
    p[s4], v[s4], a[s4] = p3 + v3 * x, v3, 0.0
    return p, v, a


def _eval_move(mt: MoveTimes, start: float, target: float, tau: np.ndarray):
    """p, v, a, j of the move start -> target at local times tau (clipped to [0, T])."""
    T = mt.duration
    sgn = 1.0 if target >= start else -1.0
    tau = np.clip(tau, 0.0, T)
    half = tau <= 0.5 * T
    p, v, a, jerk = (np.empty_like(tau) for _ in range(4))
    ph, vh, ah = _first_half(mt, tau[half])
    p[half], v[half], a[half] = start + sgn * ph, sgn * vh, sgn * ah
    # point symmetry about (T/2, D/2): p(t) = D - p(T - t) -> lands exactly on the target
    ph, vh, ah = _first_half(mt, T - tau[~half])
    p[~half], v[~half], a[~half] = target - sgn * ph, sgn * vh, -sgn * ah
    seg = np.searchsorted(mt.boundaries, tau, side="right")      # right-continuous jerk
    jerk[:] = sgn * np.array([1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0, 0.0])[seg] * mt.j
    jerk[tau >= T] = 0.0
    return p, v, a, jerk


# --------------------------------------------------------------------------- sequences
@dataclass(frozen=True)
class Rest:
    """Stand still for ``duration`` [s]."""

    duration: float


@dataclass(frozen=True)
class MoveTo:
    """Jerk-limited move to the absolute ``position`` [m] with bounds [m/s, m/s², m/s³]."""

    position: float
    v_max: float
    a_max: float
    j_max: float


@dataclass(frozen=True)
class Reference:
    """A sampled reference and its analytic derivatives at ``t = k Ts``.

    t [s], r [m], v [m/s], a [m/s²], j [m/s³] (jerk right-continuous at segment switches),
    all float64 of one length N; Ts [s].
    """

    t: np.ndarray
    r: np.ndarray
    v: np.ndarray
    a: np.ndarray
    j: np.ndarray
    Ts: float

    def __len__(self) -> int:
        return self.r.shape[0]

    def repeat(self, n: int) -> "Reference":
        """The reference played ``n`` times back to back (e.g. [B2] R^d = 15 × R)."""
        n = int(n)
        if n < 1:
            raise ValueError(f"repeat count must be >= 1, got {n}")
        if n == 1:
            return self
        if self.r[0] != self.r[-1] or self.v[-1] != 0.0 or self.a[-1] != 0.0:
            raise ValueError("only a reference that ends at rest at its start position can be "
                             f"repeated seamlessly (r[0]={self.r[0]}, r[-1]={self.r[-1]}, "
                             f"v[-1]={self.v[-1]}); end the sequence with a move back")
        N = _count(len(self) * n, f"the reference repeated {n} times", self.Ts)
        return Reference(np.arange(N) * self.Ts, np.tile(self.r, n), np.tile(self.v, n),
                         np.tile(self.a, n), np.tile(self.j, n), self.Ts)


def sequence(steps: Sequence[Rest | MoveTo], Ts: float, start: float = 0.0,
             n_samples: int | None = None) -> Reference:
    """Sample a sequence of rests and moves at ``t_k = k Ts`` (SPEC §1).

    Parameters
    ----------
    steps : sequence of Rest | MoveTo
        Played in order from ``start`` [m] at t = 0.
    Ts : float
        Sample time [s].
    start : float
        Initial position [m] (SPEC §0: at rest).
    n_samples : int, optional
        Number of samples.  Default: the samples in ``[0, T)`` with T the total duration,
        plus one if the last step is a move (so the final position is always sampled).  A
        longer record holds the final position; a shorter one that cuts a move raises.

    Returns
    -------
    Reference
    """
    Ts = _positive("Ts", Ts)
    pos = _finite("start", start)
    plan = []                  # (t_start, duration, start_pos, target, MoveTimes | None)
    t = 0.0
    t_last_move_end = 0.0
    for i, s in enumerate(steps):
        if isinstance(s, Rest):
            d = _nonnegative(f"steps[{i}].duration", s.duration)
            plan.append((t, d, pos, pos, None))
        elif isinstance(s, MoveTo):
            target = _finite(f"steps[{i}].position", s.position)
            mt = move_times(target - pos, s.v_max, s.a_max, s.j_max)
            d = mt.duration
            plan.append((t, d, pos, target, mt))
            pos = target
            t_last_move_end = t + d
        else:
            raise TypeError(f"steps[{i}] is {type(s).__name__}; use Rest(duration) or "
                            "MoveTo(position, v_max, a_max, j_max)")
        t += d
    T = t
    n_min = int(math.floor(t_last_move_end / Ts * (1.0 - _EPS_T) + _EPS_T)) + 1 \
        if any(p[4] is not None and p[4].distance > 0 for p in plan) else 1
    if n_samples is None:
        n = max(int(math.ceil(T / Ts * (1.0 - _EPS_T))), 1)
        if (n - 1) * Ts < t_last_move_end * (1.0 - _EPS_T):
            n += 1
    else:
        n = int(n_samples)
        if n < n_min:
            raise ValueError(f"n_samples={n} cuts the last move, which ends at "
                             f"t={t_last_move_end:.6g} s; use n_samples >= {n_min}")
    _count(n, "the reference", Ts)
    tk = np.arange(n) * Ts
    r, v, a, jk = np.full(n, pos), np.zeros(n), np.zeros(n), np.zeros(n)
    starts = np.array([p[0] for p in plan] + [np.inf])
    for i, (t0, d, p0, p1, mt) in enumerate(plan):
        lo = int(np.searchsorted(tk, t0, side="left"))
        hi = int(np.searchsorted(tk, starts[i + 1], side="left")) if i + 1 < len(plan) else n
        if hi <= lo:
            continue
        if mt is None or mt.distance == 0.0:
            r[lo:hi] = p0
            continue
        r[lo:hi], v[lo:hi], a[lo:hi], jk[lo:hi] = _eval_move(mt, p0, p1, tk[lo:hi] - t0)
    return Reference(tk, r, v, a, jk, Ts)


def move(distance: float, v_max: float, a_max: float, j_max: float, Ts: float) -> Reference:
    """One rest-to-rest move 0 -> ``distance`` [m], sampled on [0, T] (last sample at target)."""
    return sequence([MoveTo(distance, v_max, a_max, j_max)], Ts)


def out_and_back(distance: float, v_max: float, a_max: float, j_max: float, Ts: float,
                 rest_start: float = 0.1, dwell: float = 0.1, rest_end: float = 0.5,
                 repeats: int = 1, n_samples: int | None = None) -> Reference:
    """Rest, move to ``distance``, dwell, move back to 0, rest; repeated ``repeats`` times.

    Defaults are [K] §VI (SPEC §2.1): 0.1 s rest, 0.1 s dwell, 0.5 s final rest
    (use ``a_max=5, j_max=200``).  ``n_samples`` fixes the length of one period.
    """
    steps = [Rest(rest_start), MoveTo(distance, v_max, a_max, j_max), Rest(dwell),
             MoveTo(0.0, v_max, a_max, j_max), Rest(rest_end)]
    return sequence(steps, Ts, n_samples=n_samples).repeat(repeats)


def oscillating(amplitude: float, v_max: float, a_max: float, j_max: float, Ts: float,
                duration: float | None = None, n_strokes: int | None = None,
                rest: float = 0.5, dwell: float = 0.5) -> Reference:
    """Reference oscillating in [-amplitude, amplitude] ([B1] §VI).

    ``rest`` at 0, move to +A, then ``n_strokes`` full strokes (±A -> ∓A) each after a
    ``dwell``, a dwell, the move back to 0, and rest.  Give either ``n_strokes`` (the final
    rest lasts ``rest``) or ``duration`` [s] (as many strokes as fit with at least ``dwell``
    of final rest; the record is then exactly ``round(duration/Ts)`` samples).
    """
    A = _positive("amplitude", amplitude)
    half = move_times(A, v_max, a_max, j_max).duration
    full = move_times(2 * A, v_max, a_max, j_max).duration
    rest, dwell = _nonnegative("rest", rest), _nonnegative("dwell", dwell)
    if (duration is None) == (n_strokes is None):
        raise ValueError("give exactly one of duration [s] or n_strokes")
    n_samples = None
    if duration is not None:
        duration = _positive("duration", duration)
        fixed = rest + half + dwell + half + dwell
        n_strokes = int(math.floor((duration - fixed) / (dwell + full)))
        if n_strokes < 0:
            raise ValueError(f"duration={duration} s is shorter than one out-and-back "
                             f"({fixed:.4g} s at these bounds); lengthen it")
        n_samples = int(round(duration / Ts))
    n_strokes = int(n_strokes)
    if n_strokes < 0:
        raise ValueError(f"n_strokes must be >= 0, got {n_strokes}")
    total = rest + half + dwell + half + (dwell + full) * n_strokes + (rest if duration is None else 0.0)
    _count(int(total / _positive("Ts", Ts)), "the oscillating reference", Ts)   # before a step per stroke
    steps: list[Rest | MoveTo] = [Rest(rest), MoveTo(A, v_max, a_max, j_max)]
    for i in range(n_strokes):
        steps += [Rest(dwell), MoveTo(-A if i % 2 == 0 else A, v_max, a_max, j_max)]
    steps += [Rest(dwell), MoveTo(0.0, v_max, a_max, j_max), Rest(rest if duration is None else 0.0)]
    return sequence(steps, Ts, n_samples=n_samples)


def b1_training_reference(Ts: float = 1e-3, duration: float = 120.0, amplitude: float = 0.1,
                          v_max: float = 0.05, a_max: float = 4.0, j_max: float = 1000.0,
                          rest: float = 0.5, dwell: float = 0.5) -> Reference:
    """[B1] §VI training reference: 120 s in [-0.1, 0.1] m, v 0.05, a 4, j 1000 (SPEC §2.2).
    The dwell and rest times (0.5 s) are our choice; the paper does not give them."""
    return oscillating(amplitude, v_max, a_max, j_max, Ts, duration=duration, rest=rest,
                       dwell=dwell)


def b1_evaluation_reference(v_max: float, Ts: float = 1e-3, amplitude: float = 0.1,
                            a_max: float = 4.0, j_max: float = 1000.0, rest: float = 0.5,
                            dwell: float = 0.5) -> Reference:
    """[B1] §VI evaluation reference: one cycle 0 -> +A -> -A -> 0 at ``v_max`` [m/s]
    (SPEC §2.2: v_max in :data:`B1_EVAL_VMAX`; 0.15 m/s is [B1] Fig. 3)."""
    return oscillating(amplitude, v_max, a_max, j_max, Ts, n_strokes=1, rest=rest, dwell=dwell)


def b2_reference(Ts: float = 0.01) -> Reference:
    """[B2] §VI reference R (SPEC §2.3): 300 samples (3 s): rest to 0.5 s, +0.1 m (1.1 s),
    0.2 s dwell, back to 0 (1.1 s), rest to 3 s; |v| ≤ 0.1, |a| ≤ 4 (reaches 2), |j| ≤ 40."""
    return out_and_back(0.1, 0.1, 4.0, 40.0, Ts, rest_start=0.5, dwell=0.2, rest_end=0.1,
                        n_samples=int(round(3.0 / Ts)))


def b2_training_reference(Ts: float = 0.01, repeats: int = 15) -> Reference:
    """[B2] §VI training reference R^d: R repeated 15 times (45 s)."""
    return b2_reference(Ts).repeat(repeats)


# --------------------------------------------------------------------------- config specs
_SPEC_ARGS = {
    "move": ({"distance", "v_max", "a_max", "j_max"}, set()),
    "out_and_back": ({"distance", "v_max", "a_max", "j_max"},
                     {"rest_start", "dwell", "rest_end", "repeats", "n_samples"}),
    "oscillating": ({"amplitude", "v_max", "a_max", "j_max"},
                    {"duration", "n_strokes", "rest", "dwell"}),
    "b1_training": (set(), {"duration", "amplitude", "v_max", "a_max", "j_max", "rest", "dwell"}),
    "b1_evaluation": ({"v_max"}, {"amplitude", "a_max", "j_max", "rest", "dwell"}),
    "b2_R": (set(), {"repeats"}),
    "sequence": ({"steps"}, {"start", "n_samples", "repeats"}),
}
#: reference kinds accepted by :func:`from_spec`
KINDS: tuple[str, ...] = tuple(_SPEC_ARGS)


def profile_from_spec(spec, Ts: float) -> Reference:
    """Build a :class:`Reference` from a config mapping ``{kind: ..., <arguments>}``.

    Kinds (:data:`KINDS`) and their arguments (units as in the functions they call):
    ``move`` (:func:`move`), ``out_and_back`` (:func:`out_and_back`), ``oscillating``
    (:func:`oscillating`), ``b1_training``, ``b1_evaluation`` (v_max), ``b2_R`` (optional
    ``repeats``: 15 gives [B2]'s R^d), ``sequence`` (``steps``: a list of ``{rest: s}`` or
    ``{to: m, v_max, a_max, j_max}``).  The keys ``name`` and ``kind`` are not arguments.
    """
    spec = dict(spec)
    kind = spec.pop("kind", None)
    spec.pop("name", None)
    if kind not in _SPEC_ARGS:
        raise ValueError(f"unknown reference kind {kind!r}; use one of {KINDS}, or 'measured' (a recorded file: "
                         "{name: test, kind: measured, file: <file in data.path>}, with data=measured)")
    required, optional = _SPEC_ARGS[kind]
    missing = required - set(spec)
    unknown = set(spec) - required - optional
    if missing:
        raise ValueError(f"reference kind '{kind}' needs {sorted(missing)}; got {sorted(spec)}")
    if unknown:
        raise ValueError(f"reference kind '{kind}' does not take {sorted(unknown)}; "
                         f"allowed: {sorted(required | optional)}")
    if kind == "move":
        return move(Ts=Ts, **spec)
    if kind == "out_and_back":
        return out_and_back(Ts=Ts, **spec)
    if kind == "oscillating":
        return oscillating(Ts=Ts, **spec)
    if kind == "b1_training":
        return b1_training_reference(Ts=Ts, **spec)
    if kind == "b1_evaluation":
        return b1_evaluation_reference(Ts=Ts, **spec)
    if kind == "b2_R":
        return b2_reference(Ts).repeat(spec.get("repeats", 1))
    steps = []
    for i, st in enumerate(spec["steps"]):
        st = dict(st)
        if set(st) == {"rest"}:
            steps.append(Rest(st["rest"]))
        elif set(st) == {"to", "v_max", "a_max", "j_max"}:
            steps.append(MoveTo(st["to"], st["v_max"], st["a_max"], st["j_max"]))
        else:
            raise ValueError(f"sequence step {i} is {st}; use {{rest: <s>}} or "
                             "{to: <m>, v_max: <m/s>, a_max: <m/s²>, j_max: <m/s³>}")
    ref = sequence(steps, Ts, start=spec.get("start", 0.0), n_samples=spec.get("n_samples"))
    return ref.repeat(spec.get("repeats", 1))


def from_spec(spec, Ts: float) -> np.ndarray:
    """The sampled position r [m] of :func:`profile_from_spec` (what the stages simulate)."""
    return profile_from_spec(spec, Ts).r
