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
==========  ==============================================  ===========================

A user term: add a name to :data:`TERMS` with its code in :func:`term` (numba) and
:func:`columns` (numpy/torch), one line each.  :func:`term` returns T and its partial
derivatives, which the closed-loop kernel (``pipeline.identify.measured_loop``) needs for the
exact sensitivities.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numba
import numpy as np

from pipeline.params import LENGTH_MAX, SPEED_MAX, schema, spec


def _terms_rule(v) -> str | None:
    bad = [t for t in v if t not in TERMS]
    return f"unknown term(s) {bad}; choose from {list(TERMS)} (the mass is always in)" if bad else None


@schema
class Params:
    """system.force_terms of a measured system (pipeline.systems.force_terms)."""
    # (or tanh(q̇/coulomb_width)), stribeck, offset OF, cogging (cos/sin of 2π h q/P)
    terms: list[str] = spec(["viscous", "coulomb", "offset"], check=_terms_rule,
                            example=["viscous", "coulomb", "cogging"])
    # [m/s] null = sign(q̇); a width = the smooth tanh(q̇/width)
    coulomb_width: Optional[float] = spec(None, gt=0, le=SPEED_MAX, unit="m/s", example=0.002)
    # [m/s] v_s of the stribeck term F_s sign(q̇) exp(-(q̇/v_s)²)
    stribeck_velocity: float = spec(0.01, gt=0, le=SPEED_MAX, unit="m/s")
    # [m] position period P of the cogging force (the pole pitch); needed by the cogging term
    # (>= 0.1 mm: the finest pole pitches are millimetres; 1e-9 fitted noise as cogging, issue 51)
    cogging_period: Optional[float] = spec(None, ge=1e-4, le=LENGTH_MAX, unit="m", example=0.03)
    # H: cos and sin of 2π h q/P for h = 1..H
    cogging_harmonics: int = spec(1, ge=1, le=20)


#: the configurable terms (the mass is always in)
TERMS = ("viscous", "coulomb", "stribeck", "offset", "cogging")
# kernel codes of the expanded columns
VISCOUS, SIGN, TANH, STRIBECK, OFFSET, COS, SIN = range(7)


@dataclass(frozen=True)
class ForceTerms:
    """The configured terms and their shape constants (module docstring)."""

    names: tuple = ("viscous", "coulomb", "offset")
    coulomb_width: float | None = None
    stribeck_velocity: float = 0.01
    cogging_period: float | None = None
    cogging_harmonics: int = 1

    def __post_init__(self):
        names = tuple(self.names)
        object.__setattr__(self, "names", names)
        bad = [n for n in names if n not in TERMS]
        if bad:
            raise ValueError(f"unknown physics term(s) {bad}; choose from {list(TERMS)} (the mass is always in)")
        if len(set(names)) != len(names):
            raise ValueError(f"physics terms {list(names)} name a term twice")
        if self.coulomb_width is not None and not (math.isfinite(self.coulomb_width) and self.coulomb_width > 0):
            raise ValueError(f"coulomb_width={self.coulomb_width} must be a positive velocity [m/s] (or null: sign)")
        if not (math.isfinite(self.stribeck_velocity) and self.stribeck_velocity > 0):
            raise ValueError(f"stribeck_velocity={self.stribeck_velocity} must be a positive velocity [m/s]")
        if "cogging" in names:
            if self.cogging_period is None or not (math.isfinite(self.cogging_period) and self.cogging_period > 0):
                raise ValueError("the cogging term needs cogging_period: the position period of the cogging force "
                                 "[m] (the pole pitch of the motor), e.g. cogging_period: 0.03")
            if int(self.cogging_harmonics) != self.cogging_harmonics or not 1 <= self.cogging_harmonics <= 20:
                raise ValueError(f"cogging_harmonics={self.cogging_harmonics} must be a whole number in 1..20")

    def expanded(self) -> list[tuple[str, str, int, float]]:
        """One (θ name, physical name, kernel code, shape constant) per parameter, in θ order."""
        out = []
        for n in self.names:
            if n == "viscous":
                out.append(("fv_over_m", "F_v", VISCOUS, 0.0))
            elif n == "coulomb":
                w = self.coulomb_width
                out.append(("fc_over_m", "F_c", SIGN if w is None else TANH, 0.0 if w is None else float(w)))
            elif n == "stribeck":
                out.append(("fs_over_m", "F_s", STRIBECK, float(self.stribeck_velocity)))
            elif n == "offset":
                out.append(("of_over_m", "OF", OFFSET, 0.0))
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

    def kernel(self) -> tuple[np.ndarray, np.ndarray]:
        """(codes int64, shape constants float64) for :func:`term`."""
        e = self.expanded()
        return np.array([x[2] for x in e], dtype=np.int64), np.array([x[3] for x in e], dtype=np.float64)

    def columns(self, q, v) -> list:
        """[T_j(q, q̇)] as numpy arrays or torch tensors (the type of q and v)."""
        torch_in = not isinstance(v, np.ndarray) and hasattr(v, "sign")
        if torch_in:
            import torch as xp  # lazy: saves 1.8 s of start-up (torch: the terms evaluate on numpy arrays too)
        else:
            xp = np
        cols = []
        for _, _, code, p in self.expanded():
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
            else:
                cols.append(xp.sin(p * q))
        return cols


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
    return math.sin(p * q), p * math.cos(p * q), 0.0
