"""Common interface of the simulated plants (SPEC §2).

Every plant is a :class:`System`: a true simulator hidden from identification, its sample
time, its feedback controller (or none), its noise model and the nominal physics model
structure a user would derive (:class:`PhysicsModel`).  All signals are float64 1-D arrays
of one length N (SPEC §0); past signals are zero (rest) before k = 0.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, fields

import numpy as np


@dataclass
class SimResult:
    """One closed- (or open-) loop simulation, the columns of the dataset contract (DESIGN).

    t [s], r [m] reference, u [N] applied input = u_fb + u_ff (+ excitation du),
    y [m] measured output = y_clean + v, u_ff [N], u_fb [N], y_clean [m], v [m] noise.
    """

    t: np.ndarray
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    u_ff: np.ndarray
    u_fb: np.ndarray
    y_clean: np.ndarray
    v: np.ndarray

    def as_dict(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def check_signal(name: str, x, n: int | None = None) -> np.ndarray:
    """Return ``x`` as a float64 1-D array; raise a clear error on wrong shape or NaN/inf."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"signal '{name}' must be 1-D (one sample per entry), got shape {a.shape}; "
                         "pass one reference at a time or flatten it")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"signal '{name}' has {a.shape[0]} samples but the reference has {n}; "
                         "give every signal the length of the reference")
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.isfinite(a))[0])
        raise ValueError(f"signal '{name}' contains NaN/inf (first at sample {bad}); "
                         "clean or drop those samples before using it")
    return a


def check_limits(r: np.ndarray, Ts: float, r_limit: float, v_limit: float,
                 r_limit_name: str = "r_limit") -> np.ndarray:
    """Raise ValueError if |r| > r_limit [m] or the backward-difference velocity |δr| >
    v_limit [m/s] (the past is at rest at 0, so r must start near 0); return r as float64."""
    r = check_signal("r", r)
    k = int(np.argmax(np.abs(r)))
    if abs(r[k]) > r_limit:
        raise ValueError(f"reference out of range: |r| = {abs(r[k]):.4g} m at sample {k} > "
                         f"{r_limit_name} = {r_limit} m; scale the reference down")
    vel = np.abs(np.diff(r, prepend=0.0)) / Ts
    k = int(np.argmax(vel))
    if vel[k] > v_limit:
        raise ValueError(f"reference too fast: |δr| = {vel[k]:.4g} m/s at sample {k} > "
                         f"v_limit = {v_limit} m/s; lower v_max or start r at 0 (the past is at rest)")
    return r


def loop_signals(r, u_ff=None, du=None, v=None) -> tuple[np.ndarray, ...]:
    """(r, u_ff, du, v) as checked float64 arrays of one length; None becomes zeros."""
    r = check_signal("r", r)
    n = r.shape[0]
    return (r,) + tuple(np.zeros(n) if x is None else check_signal(name, x, n)
                        for name, x in (("u_ff", u_ff), ("du", du), ("v", v)))


class PhysicsModel(ABC):
    """Nominal physics model, linear in its parameters (SPEC §3 item 1).

    Forward one-step form: ``z(k) = Φ(k) θ`` where ``z`` and ``Φ`` are built from measured
    y and u by :meth:`regressor`; ``feedforward`` is its analytic inverse (SPEC §6).
    """

    #: names of θ, in order
    param_names: tuple[str, ...] = ()
    #: the physics feedforward law the exporter ships for this model (pipeline.export.law:
    #: "linear_motor" [B1] (8), "rigid_body" a measured rigid body); None: not exported
    physics_law: str | None = None
    #: NARX orders of the model (SPEC §3 item 3)
    n_a: int = 0
    n_b: int = 0
    n_k: int = 0

    @abstractmethod
    def regressor(self, y: np.ndarray, u: np.ndarray, r: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Return (Φ [N, p], z [N]) for least squares z ≈ Φ θ (rows before the orders allow
        are dropped or zero-padded, as documented by the implementation)."""

    @abstractmethod
    def feedforward(self, theta: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Analytic inverse of the physics model: the input that makes it track ``r``."""

    def physical(self, theta: np.ndarray) -> dict[str, float]:
        """Physical parameters (m, f_v, ...) from θ; identity naming by default."""
        return {n: float(v) for n, v in zip(self.param_names, theta)}


class System(ABC):
    """A simulated plant (SPEC §2)."""

    name: str = ""
    Ts: float = 1.0
    #: a recording of a real machine (no true plant to simulate: evaluated in the recorded loop)
    measured: bool = False

    @abstractmethod
    def simulate(self, r: np.ndarray, u_ff: np.ndarray | None = None,
                 du: np.ndarray | None = None, v: np.ndarray | None = None) -> SimResult:
        """Simulate the true plant in its loop: ``u = C(q)(r - y_clean - v) + u_ff + du``
        (no computational delay, ZOH on u, SPEC §0), or open loop ``u = u_ff + du`` when the
        plant has no controller.  ``v`` is the measurement-noise realisation (zeros if None)."""

    @abstractmethod
    def noise(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw the measurement-noise realisation v of length n from the plant's noise model."""

    def controller(self):
        """The discrete feedback controller as a ``control.TransferFunction`` (dt = Ts), or None."""
        return None

    def exact_inverse(self, r: np.ndarray) -> np.ndarray:
        """The input that makes the true plant track r exactly (only where the simulator knows it)."""
        raise NotImplementedError(
            f"system '{self.name}' has no exact inverse; use data.source=ilc to learn the optimal input")

    def learning_model(self):
        """Discrete LTI model of the linear part seen by the feedforward (u_ff -> y): the process
        sensitivity P S in closed loop, the plant itself in open loop (the ILC model, SPEC §4)."""
        raise NotImplementedError(
            f"system '{self.name}' has no linear learning model; ILC needs one")

    def check_reference(self, r: np.ndarray) -> None:
        """Raise ValueError naming the violated limit if r is outside the plant's validity range."""

    @property
    @abstractmethod
    def physics(self) -> PhysicsModel:
        """The nominal physics model structure a user would derive for this plant."""


def lfilter(b, a, x, axis: int = -1):
    """``scipy.signal.lfilter``, imported on first use: scipy.signal is 0.6 s of a cached job's
    start-up, which never filters (issue 19)."""
    from scipy.signal import lfilter as _lfilter  # lazy: saves 1.1 s of start-up (scipy.signal)
    return _lfilter(b, a, x, axis=axis)
