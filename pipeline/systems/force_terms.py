"""Composable rigid-body physics: the force terms of ``M q̈ = τ - Σ_j p_j T_j(q, q̇)`` (issue 20).

Every term is linear in its parameter p_j [N per unit of T_j], so the physics stays linear in
θ = [1/M, p_1/M, …] (one-step form, [B1] (10)) and in θ' = [M, p_1, …] (inverse form, the
filtered least squares of the EMPS benchmark).  The terms, by config name:

==========  ==============================================  ===========================
name        T(q, q̇)                                         parameter (physical name)
==========  ==============================================  ===========================
viscous     q̇                                               F_v [N s/m]
coulomb     sign(q̇), or tanh(q̇/w) with ``coulomb_width`` w   F_c [N]
stribeck    sign(q̇) exp(-(q̇/v_s)²), ``stribeck_velocity``    F_s [N] (static minus Coulomb)
offset      1                                                OF [N] (gravity, cable force)
cogging     cos(2π h q/P), sin(2π h q/P), h = 1..H            C_cos<h>, C_sin<h> [N]
            (``cogging_period`` P = the pole pitch, ``cogging_harmonics`` H)
spring      q (with ``offset``: K q + OF = K (q - q0),         K [N/m] (cable carrier,
            q0 = -OF/K the rest position)                    gravity-compensation spring)
position_   (q/L)^k, k = 2..N (``position_order`` N,           P<k> [N] (the force at q = L)
poly        ``position_scale`` L)
drag        q̇ |q̇|                                            F_d [N s²/m²] (air, fluid)
==========  ==============================================  ===========================

A user term: add a name to :data:`TERMS` with its code in :func:`term` (numba) and
:func:`columns` (numpy/torch), one line each.  :func:`term` returns T and its partial
derivatives, which the closed-loop kernel (``pipeline.identify.measured_loop``) needs for the
exact sensitivities.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Optional

import numba
import numpy as np

from pipeline.params import LENGTH_MAX, SPEED_MAX, is_number, schema, spec


#: the configurable terms (the mass is always in)
TERMS = ("viscous", "coulomb", "stribeck", "offset", "cogging", "spring", "position_poly", "drag")
# kernel codes of the expanded columns; POWER + k - 1 is (q/p)^k (k = 1, p = 1: the spring's q)
VISCOUS, SIGN, TANH, STRIBECK, OFFSET, COS, SIN, DRAG, POWER = range(9)
SPRING = POWER
#: the highest power of the position_poly term, and the highest kernel code
POSITION_ORDER_MAX = 8
MAX_CODE = POWER + POSITION_ORDER_MAX - 1


def _width_rule(v) -> str | None:
    if v == "auto" or (is_number(v) and math.isfinite(v)):
        return None
    return "is not a width: give a positive velocity [m/s], auto (chosen from the data) or null (sign)"


def _terms_rule(v) -> str | None:
    bad = [t for t in v if t not in TERMS]
    return f"unknown term(s) {bad}; choose from {list(TERMS)} (the mass is always in)" if bad else None


@schema
class Params:
    """system.force_terms of a measured system (pipeline.systems.force_terms)."""
    # (or tanh(q̇/coulomb_width)), stribeck, offset OF, cogging (cos/sin of 2π h q/P), spring K q,
    # position_poly (q/L)^2 .. (q/L)^N, drag q̇|q̇|
    terms: list[str] = spec(["viscous", "coulomb", "offset"], check=_terms_rule,
                            example=["viscous", "coulomb", "cogging"])
    # [m/s] null = sign(q̇); a width = the smooth tanh(q̇/width); auto = the width chosen from the data
    # (the baseline's held-out force error on the training records' tail)
    coulomb_width: Any = spec(None, gt=0, le=SPEED_MAX, unit="m/s", check=_width_rule, example=0.002,
                              rule="give a positive width [m/s], auto, or null (sign)")
    # [m/s] v_s of the stribeck term F_s sign(q̇) exp(-(q̇/v_s)²)
    stribeck_velocity: float = spec(0.01, gt=0, le=SPEED_MAX, unit="m/s")
    # [m] position period P of the cogging force (the pole pitch); needed by the cogging term
    # (>= 0.1 mm: the finest pole pitches are millimetres; 1e-9 fitted noise as cogging, issue 51)
    cogging_period: Optional[float] = spec(None, ge=1e-4, le=LENGTH_MAX, unit="m", example=0.03)
    # H: cos and sin of 2π h q/P for h = 1..H
    cogging_harmonics: int = spec(1, ge=1, le=20)
    # N: the position_poly term's highest power (q/L)^2 .. (q/L)^N
    position_order: int = spec(3, ge=2, le=POSITION_ORDER_MAX)
    # [m] L of the position_poly term (e.g. half the stroke: P<k> is then the force at q = L); needed by it
    position_scale: Optional[float] = spec(None, gt=0, le=LENGTH_MAX, unit="m", example=0.1)


@dataclass(frozen=True)
class ForceTerms:
    """The configured terms and their shape constants (module docstring).  ``coulomb_width='auto'``:
    a tanh Coulomb term whose width the baseline chooses from the data (:meth:`with_coulomb_width`);
    until then its columns and kernel are refused."""

    names: tuple = ("viscous", "coulomb", "offset")
    coulomb_width: float | str | None = None
    stribeck_velocity: float = 0.01
    cogging_period: float | None = None
    cogging_harmonics: int = 1
    position_order: int = 3
    position_scale: float | None = None

    def __post_init__(self):
        names = tuple(self.names)
        object.__setattr__(self, "names", names)
        bad = [n for n in names if n not in TERMS]
        if bad:
            raise ValueError(f"unknown physics term(s) {bad}; choose from {list(TERMS)} (the mass is always in)")
        if len(set(names)) != len(names):
            raise ValueError(f"physics terms {list(names)} name a term twice")
        w = self.coulomb_width
        if w == "auto":
            if "coulomb" not in names:
                raise ValueError("coulomb_width: auto chooses the width of the coulomb term, which the terms lack: "
                                 "add 'coulomb' to system.force_terms.terms or drop coulomb_width")
        elif w is not None and not (is_number(w) and math.isfinite(w) and w > 0):
            raise ValueError(f"coulomb_width={w!r} must be a positive velocity [m/s], auto (chosen from the data) "
                             "or null (sign)")
        if not (math.isfinite(self.stribeck_velocity) and self.stribeck_velocity > 0):
            raise ValueError(f"stribeck_velocity={self.stribeck_velocity} must be a positive velocity [m/s]")
        if "cogging" in names:
            if self.cogging_period is None or not (math.isfinite(self.cogging_period) and self.cogging_period > 0):
                raise ValueError("the cogging term needs cogging_period: the position period of the cogging force "
                                 "[m] (the pole pitch of the motor), e.g. cogging_period: 0.03")
            if int(self.cogging_harmonics) != self.cogging_harmonics or not 1 <= self.cogging_harmonics <= 20:
                raise ValueError(f"cogging_harmonics={self.cogging_harmonics} must be a whole number in 1..20")
        if "position_poly" in names:
            L = self.position_scale
            if L is None or not (math.isfinite(L) and L > 0):
                raise ValueError("the position_poly term needs position_scale: the length L [m] of (q/L)^k (e.g. "
                                 "half the stroke), e.g. position_scale: 0.1")
            if int(self.position_order) != self.position_order or not 2 <= self.position_order <= POSITION_ORDER_MAX:
                raise ValueError(f"position_order={self.position_order} must be a whole number in "
                                 f"2..{POSITION_ORDER_MAX} (the highest power of (q/L)^k)")

    @property
    def auto_width(self) -> bool:
        """The Coulomb width is still to be chosen from the data (``coulomb_width: auto``)."""
        return self.coulomb_width == "auto"

    def with_coulomb_width(self, width: float | None) -> "ForceTerms":
        """The same terms with Coulomb width ``width`` [m/s] (None: sign)."""
        return replace(self, coulomb_width=None if width is None else float(width))

    def expanded(self) -> list[tuple[str, str, int, float]]:
        """One (θ name, physical name, kernel code, shape constant) per parameter, in θ order (an
        unchosen auto width has the constant NaN: :meth:`kernel` and :meth:`columns` refuse it)."""
        out = []
        for n in self.names:
            if n == "viscous":
                out.append(("fv_over_m", "F_v", VISCOUS, 0.0))
            elif n == "coulomb":
                w = self.coulomb_width
                out.append(("fc_over_m", "F_c", SIGN if w is None else TANH,
                            0.0 if w is None else (math.nan if w == "auto" else float(w))))
            elif n == "stribeck":
                out.append(("fs_over_m", "F_s", STRIBECK, float(self.stribeck_velocity)))
            elif n == "offset":
                out.append(("of_over_m", "OF", OFFSET, 0.0))
            elif n == "spring":
                out.append(("k_over_m", "K", SPRING, 1.0))
            elif n == "position_poly":
                for k in range(2, int(self.position_order) + 1):
                    out.append((f"p{k}_over_m", f"P{k}", POWER + k - 1, float(self.position_scale)))
            elif n == "drag":
                out.append(("fd_over_m", "F_d", DRAG, 0.0))
            else:
                for h in range(1, int(self.cogging_harmonics) + 1):
                    k = 2.0 * math.pi * h / float(self.cogging_period)
                    out.append((f"ccos{h}_over_m", f"C_cos{h}", COS, k))
                    out.append((f"csin{h}_over_m", f"C_sin{h}", SIN, k))
        return out

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(e[0] for e in self.expanded())

    @property
    def physical_names(self) -> tuple[str, ...]:
        return tuple(e[1] for e in self.expanded())

    def _chosen(self) -> list[tuple[str, str, int, float]]:
        if self.auto_width:
            raise ValueError("coulomb_width: auto is not chosen yet: the baseline stage chooses it from the "
                             "training data (run the baseline first, or give a width in m/s)")
        return self.expanded()

    def kernel(self) -> tuple[np.ndarray, np.ndarray]:
        """(codes int64, shape constants float64) for :func:`term`."""
        e = self._chosen()
        return np.array([x[2] for x in e], dtype=np.int64), np.array([x[3] for x in e], dtype=np.float64)

    def columns(self, q, v) -> list:
        """[T_j(q, q̇)] as numpy arrays or torch tensors (the type of q and v)."""
        torch_in = not isinstance(v, np.ndarray) and hasattr(v, "sign")
        if torch_in:
            import torch as xp  # lazy: saves 1.8 s of start-up (torch: the terms evaluate on numpy arrays too)
        else:
            xp = np
        cols = []
        for _, _, code, p in self._chosen():
            if code == VISCOUS:
                cols.append(v)
            elif code == SIGN:
                cols.append(xp.sign(v))
            elif code == TANH:
                cols.append(xp.tanh(v / p))
            elif code == STRIBECK:
                cols.append(xp.sign(v) * xp.exp(-(v / p) ** 2))
            elif code == OFFSET:
                cols.append(v * 0.0 + 1.0)
            elif code == COS:
                cols.append(xp.cos(p * q))
            elif code == SIN:
                cols.append(xp.sin(p * q))
            elif code == DRAG:
                cols.append(v * xp.abs(v))
            else:
                cols.append(_power(q / p, code - POWER + 1))
        return cols


def _power(x, k: int):
    """x^k by k - 1 products, in the order :func:`term` and the C's force_term multiply (same bits)."""
    t = x
    for _ in range(k - 1):
        t = t * x
    return t


@numba.njit(cache=True)
def term(code, p, q, v):
    """(T, ∂T/∂q, ∂T/∂q̇) of one expanded column (codes of :class:`ForceTerms`)."""
    if code == 0:      # viscous
        return v, 0.0, 1.0
    if code == 1:      # sign
        return (1.0 if v > 0 else (-1.0 if v < 0 else 0.0)), 0.0, 0.0
    if code == 2:      # smooth Coulomb
        t = math.tanh(v / p)
        return t, 0.0, (1.0 - t * t) / p
    if code == 3:      # Stribeck
        s = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
        e = math.exp(-(v / p) ** 2)
        return s * e, 0.0, s * e * (-2.0 * v / (p * p))
    if code == 4:      # offset
        return 1.0, 0.0, 0.0
    if code == 5:      # cogging cos
        return math.cos(p * q), -p * math.sin(p * q), 0.0
    if code == 6:      # cogging sin
        return math.sin(p * q), p * math.cos(p * q), 0.0
    if code == 7:      # drag q̇|q̇|
        return v * abs(v), 0.0, 2.0 * abs(v)
    # position power (q/p)^k, k = code - 7 (the spring: k = 1, p = 1); ∂/∂q = k (q/p)^(k-1) / p
    k = code - 7
    x = q / p
    lower = 1.0
    for _ in range(k - 1):
        lower = lower * x
    return lower * x if k > 1 else x, k * lower / p, 0.0
