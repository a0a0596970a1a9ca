"""Where a feedforward starts (issue 48): the state every law takes before its first sample, and
what it gives at switch-on.

A machine switches the feedforward on with the axis at rest wherever it stands, r(0) = r0, its loop
running. Two choices say what the law assumes then (config node ``start``):

- ``start.at``: ``rest``: every state of the law (reference windows, past inputs, filter registers,
  the controller term (C_r - C_y) r) is in its steady state at r0, so a reference resting at r0
  gives a constant u_ff there, the static force at r0, and no transient; ``zero``: the papers'
  conventions as the study ran them (the physics law (8) and the [K] filters from r = 0, the [B1]
  PGNN inversions from r(0), the controller term from a zero state), for references that start at
  0 (their numbers stay equal to the bit); ``recorded``: the same conventions on a measured system, for a
  recording replayed as the study replayed it before the start was declared (the reference from r = 0, the
  controller term from a zero state); ``auto`` (default): ``rest`` on a measured system, ``zero`` on the simulators.
- ``start.static``: ``include``: u_ff(0) is the law's force at rest at r0 (gravity, a spring, an
  offset): right when the feedforward is on from power-up; ``exclude``: that constant is taken off,
  u_ff(0) = 0, right when the loop's integrator already holds the load at switch-on (else the axis
  gets the load twice); ``auto``: ``exclude`` when the controller integrates (A(1) = 0, it holds a
  constant load with zero error), ``include`` otherwise (and on the simulators).

How a law reaches its rest (:func:`started`): the law runs on the reference with ``settle + 1``
samples of r0 in front, which are dropped; ``settle`` (:func:`settle_count`) is the number of rest
samples after which the law's output no longer changes (0 for a law without memory beyond its
window, more for a recursion in its past inputs or a 1/B(q) filter). The controller term is exact
instead (``LTIController.reference_force(r, r0)``: the filter on r - r0 plus its rest value). The C
does the same at ``<p>_init(&s, r0)`` (``settle + 1`` steps at r0), so Python and C agree.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np

from pipeline.params import schema

AT = ("auto", "rest", "zero", "recorded")
STATIC = ("auto", "include", "exclude")
#: rest samples tried at most before a law is declared not to settle (a recursion that does not converge)
SETTLE_MAX = 1 << 17
#: a law has settled when its output changes by at most this × its scale from one rest sample to the next
SETTLE_RTOL = 1e-14


@schema
class Params:
    """start (pipeline/invert/start.py): the state every feedforward law starts from and its value at switch-on."""
    # auto: rest on a measured system, zero on the simulators | rest: steady state at r(0) | zero: the papers'
    # conventions | recorded: the same on a measured system (as it ran before the start was declared)
    at: Literal["auto", "rest", "zero", "recorded"] = "auto"
    # auto: exclude when the controller integrates (it holds the load at switch-on), else include
    static: Literal["auto", "include", "exclude"] = "auto"


@dataclass(frozen=True)
class Start:
    at: str        # rest | zero | recorded
    static: str    # include | exclude

    @property
    def rest(self) -> bool:
        return self.at == "rest"


def resolve(node, system) -> Start:
    """The ``start`` node with ``auto`` decided for ``system``."""
    node = node or {}
    at, static = str(node.get("at", "auto")), str(node.get("static", "auto"))
    if at not in AT or static not in STATIC:
        raise ValueError(f"start.at={at!r} must be one of {AT} and start.static={static!r} one of {STATIC}")
    measured = bool(getattr(system, "measured", False))
    if at == "auto":
        at = "rest" if measured else "zero"
    if static == "auto":
        ctrl = getattr(system, "ctrl", None) if measured else None
        static = "exclude" if (at == "rest" and ctrl is not None and ctrl.integral_action) else "include"
    if static == "exclude" and at != "rest":
        raise ValueError("start.static=exclude takes the static force at the rest position off the feedforward: "
                         "it needs start.at=rest (or auto on a measured system)")
    return Start(at, static)


def settle_count(law: Callable[[np.ndarray], np.ndarray], r0s) -> int:
    """Rest samples after which ``law`` (u_ff of a reference) is constant on a reference held at each r0 of
    ``r0s``: the first index from which every later sample is within SETTLE_RTOL × max|u| (+1e-300) of the
    last. 0 for a law with no memory beyond its window; ValueError if it has not settled by SETTLE_MAX."""
    n = 0
    for r0 in r0s:
        m = 64
        while True:
            u = np.asarray(law(np.full(m, float(r0))), dtype=np.float64)
            if not np.all(np.isfinite(u)):
                raise ValueError(f"the feedforward is not finite at rest at r0 = {r0:g}: it has no rest there")
            tol = SETTLE_RTOL * float(np.max(np.abs(u))) + 1e-300
            off = np.abs(u - u[-1]) > tol
            last = int(np.flatnonzero(off)[-1]) + 1 if off.any() else 0
            if last < m // 2:
                n = max(n, last)
                break
            if m >= SETTLE_MAX:
                raise ValueError(f"the feedforward does not settle at rest at r0 = {r0:g} within {SETTLE_MAX} "
                                 "samples (a recursion in its past inputs that does not converge: an unstable "
                                 "inverse); use start.at=zero or another inversion")
            m *= 2
    return n


def started(law: Callable[[np.ndarray], np.ndarray], r: np.ndarray, r0: float, settle: int) -> tuple[np.ndarray, float]:
    """(u_ff, u_rest) of ``law`` started at rest at r0: run on [r0] × (settle + 1) + r, the rest samples
    dropped (the law's past is r0, its preview the reference); u_rest is the law at rest, its last sample on
    [r0] × (settle + 1) (the C's last warm-up step at init, its preview r0 too)."""
    n = int(settle) + 1
    u_rest = float(np.asarray(law(np.full(n, float(r0))), dtype=np.float64)[-1])
    u = np.asarray(law(np.concatenate([np.full(n, float(r0)), r])), dtype=np.float64)
    return u[n:], u_rest
