"""The known controller of a measured loop: any discrete LTI controller, 1- or 2-DOF (issue 20).

In z⁻¹ polynomials with a common denominator A (a[0] = 1)::

    A(z⁻¹) v(k) = B_r(z⁻¹) r(k) - B_y(z⁻¹) y(k)          C_r = B_r/A,  C_y = B_y/A

Each path may come with its own denominator, as a drive's tuning tool gives it (issue 49):
C_r = N_r/D_r, C_y = N_y/D_y.  :func:`common_denominator` writes them over the least common
multiple A = D_r D_y / G, G the common factor of D_r and D_y (shared roots, e.g. the integrator
of a PID on both paths), B_r = N_r D_y/G, B_y = N_y D_r/G: the controller's own order, no pole
twice, nothing for the user to multiply out.
    c(k) = sat±v_sat(v(k) + u_ff(k)/gtau)                 controller output [controller units]
    u(k) = gtau (c(k - D) + d(k))                         applied force [N]

- **error feedback** (``num_r`` null): C_r = C_y = C, the usual PID / lead-lag on e = r - y;
- **2-DOF**: separate reference and measurement paths, e.g. the EMPS position/velocity cascade
  ``vir = kv (kp (r - q) - q̇f)``, q̇f = (q(k) - q(k-2))/(2 Ts): B_r = [kv kp],
  B_y = [kv kp + kv/(2 Ts), 0, -kv/(2 Ts)], A = [1] (:meth:`LTIController.cascade`);
- D: an integer computational delay of the output [samples]; d: a measured disturbance added
  after the limit (controller units); u_ff: a force feedforward added before the limit.

The filter state is the unsaturated v (no anti-windup modelled).  **The feedforward that fits
the loop** (:meth:`LTIController.reference_force`): the axis follows r exactly (y = r) when the
applied force equals the model's inverse force F(r), i.e. u_ff = F(r) - (C_r - C_y) r, zero
extra term for error feedback, the velocity feedback on the reference for the EMPS cascade.

**The consistency check** (:meth:`LTIController.check`) is an equation error, so it needs no
initial controller state: ``A c_meas - B_r r + B_y y`` with c_meas(k) = u(k+D)/gtau - d(k+D),
relative to ``‖A c_meas‖``, on the samples where the limit is not reached.  When it fails,
:meth:`LTIController.diagnose` says how far the configured structure is and what fits better
(another gain or sign, another delay, error feedback vs 2-DOF).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

from pipeline.params import schema, spec


@schema
class Params:
    """system.controller (pipeline.systems.controller): kind cascade (kp, kv) or lti (num, den, num_r,
    delay); which keys a kind takes is checked by LTIController.from_config."""
    # the position/velocity cascade (a 2-DOF LTI controller, pipeline/systems/controller.py)
    kind: Literal["cascade", "lti"] = "cascade"
    kp: Optional[float] = spec(None, fill=False, gt=0, le=1e6, unit="1/s", example=160.18)
    kv: Optional[float] = spec(None, fill=False, gt=0, le=1e9, unit="controller units per m/s", example=243.45)
    num: Optional[list[float]] = spec(None, fill=False, ge=-1e15, le=1e15, min_len=1,
                                     example=[4.279e6, -8.212e6, 3.939e6])
    den: Optional[list[float]] = spec(None, fill=False, ge=-1e15, le=1e15, min_len=1, example=[1.0, -1.4361, 0.4361])
    num_r: Optional[list[float]] = spec(None, fill=False, ge=-1e15, le=1e15, min_len=1,
                                       example=[4.279e6, -8.212e6, 3.939e6])
    # C_r's own denominator (a 2-DOF controller whose paths differ); null = den (one common denominator)
    den_r: Optional[list[float]] = spec(None, fill=False, ge=-1e15, le=1e15, min_len=1, example=[1.0, -1.0])
    delay: Optional[int] = spec(None, fill=False, ge=0, le=100, unit="samples", example=1)
    # force per controller unit [N/unit]; 1 if the controller outputs newtons
    gtau: float = spec(1.0, gt=0, le=1e6, unit="N per controller unit")
    # controller output limit [units]; large = no saturation
    v_sat: float = spec(1e9, gt=0, le=1e12, unit="controller units")


KINDS = ("cascade", "lti")
#: a root of A this close to z = 1 is an integrator (a pole typed with 7-10 significant digits lands ~1e-7 off)
INTEGRATOR_TOL = 1e-6
#: roots of D_r and D_y this close (relative to max(1, |p|)) are one common pole of the two paths
COMMON_ROOT_TOL = 1e-6


def _poly(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError(f"controller.{name}={list(np.atleast_1d(v))} must be a non-empty list of finite "
                         "coefficients in powers of z⁻¹ (e.g. [4.279e6, -8.212e6, 3.939e6])")
    return a


@dataclass(frozen=True, eq=False)
class LTIController:
    """A discrete LTI controller (module docstring).  Build with :meth:`from_config`,
    :meth:`cascade` or :meth:`lti`."""

    b_r: np.ndarray          # C_r numerator in z⁻¹ (normalised by a[0])
    b_y: np.ndarray          # C_y numerator in z⁻¹
    a: np.ndarray            # common denominator, a[0] = 1
    gtau: float = 1.0        # force per controller unit [N/unit]
    v_sat: float = math.inf  # limit of the controller output [units]
    delay: int = 0           # computational delay D of the output [samples]
    structure: str = "lti"   # 'cascade' | 'error feedback' | '2-DOF' (messages, tags)
    params: tuple = ()       # the config's numbers ((name, value), …): checked against a file's constants
    given: tuple = ()        # ((N_r, D_r), (N_y, D_y)) as typed when the paths have their own denominators

    # ---- construction ---------------------------------------------------------------------------
    @classmethod
    def cascade(cls, kp: float, kv: float, gtau: float = 1.0, v_sat: float = 1e9, Ts: float = 1e-3, delay: int = 0):
        """The EMPS position/velocity cascade as a 2-DOF LTI controller (module docstring)."""
        for k, v in (("kp", kp), ("kv", kv), ("gtau", gtau), ("v_sat", v_sat)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"controller.{k}={v!r} must be a finite positive number")
        if int(delay) != delay or delay < 0:
            raise ValueError(f"controller.delay={delay} must be a whole number of samples >= 0")
        dg = kv / (2.0 * Ts)
        return cls(np.array([kv * kp]), np.array([kv * kp + dg, 0.0, -dg]), np.array([1.0]), float(gtau),
                   float(v_sat), int(delay), "cascade",
                   (("kp", float(kp)), ("kv", float(kv)), ("gtau", float(gtau)), ("v_sat", float(v_sat))))

    @classmethod
    def lti(cls, num, den=(1.0,), num_r=None, gtau: float = 1.0, v_sat: float = 1e9, delay: int = 0, den_r=None):
        """C_y = num/den and C_r = num_r/den_r (``den_r`` None: den; ``num_r`` None: error feedback,
        C_r = C_y); two denominators are written over their least common multiple
        (:func:`common_denominator`)."""
        b_y, a = _poly("num", num), _poly("den", den)
        if a[0] == 0:
            raise ValueError(f"controller.den={list(den)}: the leading coefficient (of z⁰) must not be 0")
        if den_r is not None and num_r is None:
            raise ValueError("controller.den_r is the denominator of the reference path C_r = num_r/den_r: give "
                             "num_r too (or drop den_r for error feedback on r - y)")
        b_r = b_y if num_r is None else _poly("num_r", num_r)
        given = ()
        if den_r is not None:
            a_r = _poly("den_r", den_r)
            if a_r[0] == 0:
                raise ValueError(f"controller.den_r={list(den_r)}: the leading coefficient (of z⁰) must not be 0")
            for name, p in (("den_r", a_r), ("den", a)):
                _check_stable(name, p)
            given = ((b_r / a_r[0], a_r / a_r[0]), (b_y / a[0], a / a[0]))
            b_r, b_y, a = common_denominator(b_r, a_r, b_y, a)
        if not (math.isfinite(gtau) and gtau > 0 and v_sat > 0):
            raise ValueError(f"controller.gtau={gtau} and v_sat={v_sat} must be positive")
        if int(delay) != delay or delay < 0:
            raise ValueError(f"controller.delay={delay} must be a whole number of samples >= 0")
        _check_stable("den", a)
        return cls(b_r / a[0], b_y / a[0], a / a[0], float(gtau), float(v_sat), int(delay),
                   "error feedback" if num_r is None else "2-DOF",
                   (("gtau", float(gtau)), ("v_sat", float(v_sat))), given)

    @classmethod
    def from_config(cls, cfg: dict, Ts: float) -> "LTIController":
        """From ``system.controller``: kind 'cascade' (kp, kv, gtau, v_sat, delay) or 'lti' (num,
        den, num_r, gtau, v_sat, delay); null values are absent keys."""
        cfg = {k: v for k, v in dict(cfg).items() if v is not None}
        kind = cfg.pop("kind", "cascade")
        if kind not in KINDS:
            raise ValueError(f"controller.kind={kind!r}; choose one of {KINDS}")
        keys = {"cascade": ("kp", "kv", "gtau", "v_sat", "delay"),
                "lti": ("num", "den", "num_r", "den_r", "gtau", "v_sat", "delay")}[kind]
        extra = sorted(set(cfg) - set(keys))
        if extra:
            raise ValueError(f"controller.kind={kind} takes {list(keys)}, not {extra}" +
                             ("; a C(z) is given as kind: lti" if kind == "cascade" else
                              "; the cascade's kp, kv need kind: cascade"))
        if kind == "cascade":
            missing = [k for k in ("kp", "kv") if k not in cfg]
            if missing:
                raise ValueError(f"controller.kind=cascade needs {missing} (or give C(z) as kind: lti, num, den)")
            return cls.cascade(Ts=Ts, **cfg)
        if "num" not in cfg:
            raise ValueError("controller.kind=lti needs num (C(z) numerator in powers of z⁻¹) and den")
        return cls.lti(**cfg)

    # ---- properties -----------------------------------------------------------------------------
    @property
    def order(self) -> int:
        """Longest polynomial degree: the samples of history the controller needs."""
        return max(self.a.size, self.b_r.size, self.b_y.size) - 1

    def transfer_functions(self, Ts: float):
        """(C_r, C_y) as python-control discrete transfer functions [units/m]."""
        import control  # lazy: saves 1.9 s of start-up (python-control)
        n = self.order + 1
        pad = lambda p: np.concatenate([p, np.zeros(n - p.size)])     # z⁻¹ → z: same coefficients, z^(n-1) scaled
        return (control.tf(pad(self.b_r), pad(self.a), Ts), control.tf(pad(self.b_y), pad(self.a), Ts))

    def describe(self) -> str:
        d = f", delay {self.delay}" if self.delay else ""
        if self.structure == "cascade":
            p = dict(self.params)
            return f"the position/velocity cascade (kp {p['kp']:g}, kv {p['kv']:g}, gtau {p['gtau']:g}{d})"
        if self.given:
            (n_r, d_r), (n_y, d_y) = self.given
            return (f"2-DOF C_r(z) = ({_fmt(n_r)}) / ({_fmt(d_r)}), C_y(z) = ({_fmt(n_y)}) / ({_fmt(d_y)}), "
                    f"common denominator of order {self.a.size - 1}{d}")
        return (f"{self.structure} C(z) = ({_fmt(self.b_y)}) / ({_fmt(self.a)})"
                + ("" if self.structure == "error feedback" else f", C_r num ({_fmt(self.b_r)})") + d)

    # ---- signals ---------------------------------------------------------------------------------
    def law(self, r, y) -> np.ndarray:
        """v = C_r r - C_y y [units] from rest (zero filter state), before the limit."""
        from scipy import signal  # lazy: saves 1.4 s of start-up (scipy.signal)
        r, y = np.asarray(r, np.float64), np.asarray(y, np.float64)
        return signal.lfilter(self.b_r, self.a, r) - signal.lfilter(self.b_y, self.a, y)

    def reference_filter(self) -> tuple[np.ndarray, np.ndarray]:
        """(B_r - B_y, A) padded to one length: C_r - C_y as a filter (zero numerator for error feedback). With
        integral action and the same integral weight on r and y (B_r(1) = B_y(1) to the coefficients' digits) the
        integrator cancels: both are divided by (1 - z⁻¹), their remainders (the typed digits' rounding) dropped, so
        the filter has no pole at z = 1 left to integrate that rounding into a drift."""
        db, den = self._difference()
        if np.any(db) and self.integral_action and self._same_integral(db):
            db, den = np.cumsum(db)[:-1], np.cumsum(den)[:-1]     # c(z⁻¹) / (1 - z⁻¹), ascending powers
        return db, den

    def _difference(self) -> tuple[np.ndarray, np.ndarray]:
        """(B_r - B_y, A) padded to one length, as given."""
        n = max(self.b_r.size, self.b_y.size, self.a.size)
        db, den = np.zeros(n), np.zeros(n)
        db[:self.b_r.size] += self.b_r
        db[:self.b_y.size] -= self.b_y
        den[:self.a.size] = self.a
        return db, den

    def _same_integral(self, db: np.ndarray) -> bool:
        scale = max(abs(float(np.sum(self.b_r))), abs(float(np.sum(self.b_y))), 1e-300)
        return abs(float(np.sum(db))) <= 1e-3 * scale

    @property
    def integral_action(self) -> bool:
        """A has a root at z = 1 (within INTEGRATOR_TOL: coefficients typed with 7-10 digits move it by ~1e-7): the
        controller integrates, so at rest it holds any constant load with zero error."""
        if self.a.size < 2:
            return False
        return bool(np.any(np.abs(np.roots(self.a) - 1.0) <= INTEGRATOR_TOL))

    def rest_gain(self) -> float:
        """K0 [units/m]: the controller's output (C_r - C_y)(1) r0 / r0 at rest at y = r = r0, the
        steady state of the reference filter.  With integral action the rest value is whatever the
        integrator holds (it absorbs any constant), so the feedforward's controller term counts from
        r0: K0 = 0.  A pole at z = 1 that B_r - B_y does not cancel means the integrator sees r and y
        with different weights: no rest away from r = 0 exists (ValueError)."""
        if self.integral_action:   # the same integral weight on r and y: B_r(1) = B_y(1) to the coefficients' digits
            raw = self._difference()[0]
            if np.any(raw) and not self._same_integral(raw):
                raise ValueError(f"C_r - C_y of {self.describe()} integrates (B_r(1) = {float(np.sum(self.b_r)):.6g} "
                                 f"differs from B_y(1) = {float(np.sum(self.b_y)):.6g}): the loop has no rest away "
                                 "from r = 0; check num_r, or use start.at=zero")
            return 0.0
        db, den = self.reference_filter()
        return float(np.sum(db)) / float(np.sum(den))

    def reference_force(self, r, r0: float = 0.0) -> np.ndarray:
        """(C_r - C_y) r · gtau [N]: the controller's force when the axis follows r exactly.  The
        feedforward that makes y = r is the model's inverse force minus this (module docstring).
        From rest at ``r0`` (the filter's steady state there, :meth:`rest_gain`): the filter runs on
        r - r0 from a zero state, plus K0 r0; r0 = 0 is the zero state (as before, to the bit)."""
        from scipy import signal  # lazy: saves 1.4 s of start-up (scipy.signal)
        db, den = self.reference_filter()
        if not np.any(db):                    # error feedback: exactly zero
            return np.zeros(np.shape(r))
        r = np.asarray(r, np.float64)
        if r0 == 0.0:
            return self.gtau * signal.lfilter(db, den, r)
        return self.gtau * (signal.lfilter(db, den, r - r0) + self.rest_gain() * r0)

    def recorded_output(self, u, d) -> np.ndarray:
        """c_meas(k) = u(k+D)/gtau - d(k+D) [units] (the last D samples are unknown: NaN)."""
        c = np.asarray(u, np.float64) / self.gtau - np.asarray(d, np.float64)
        if self.delay:
            c = np.concatenate([c[self.delay:], np.full(self.delay, np.nan)])
        return c

    def _equation_error(self, r, y, c) -> tuple[np.ndarray, np.ndarray]:
        """(A c, B_r r - B_y y) on the samples where every tap is known and below the limit."""
        from scipy import signal  # lazy: saves 1.4 s of start-up (scipy.signal)
        n = self.order
        Ac = signal.lfilter(self.a, [1.0], c)
        Bx = signal.lfilter(self.b_r, [1.0], r) - signal.lfilter(self.b_y, [1.0], y)
        ok = np.isfinite(c) & (np.abs(c) < self.v_sat * (1 - 1e-9))
        ok = np.convolve(ok.astype(float), np.ones(n + 1))[:c.size] > n    # the last n+1 samples all ok
        ok[:n] = False
        return Ac[ok], Bx[ok]

    def check(self, r, y, u, d) -> float:
        """Relative rms equation error ‖A c_meas - B_r r + B_y y‖ / ‖A c_meas‖ (module docstring):
        ~1e-3 for a recording of this controller, O(1) or more for another structure."""
        Ac, Bx = self._equation_error(np.asarray(r, np.float64), np.asarray(y, np.float64),
                                      self.recorded_output(u, d))
        if Ac.size < 10:
            return math.inf
        return float(np.linalg.norm(Ac - Bx) / max(np.linalg.norm(Ac), 1e-300))

    def other_delays(self, r, y, u, d) -> dict[int, float]:
        """:meth:`check` of this controller with each other delay of 0..3 samples."""
        return {D: dataclasses.replace(self, delay=D).check(r, y, u, d)
                for D in range(0, 4) if D != self.delay}

    def better_delay(self, r, y, u, d, rel: float, factor: float = 10.0) -> tuple[int, float] | None:
        """(D, its equation error) of the delay among 0..3 samples that fits the recording ``factor`` times better
        than this controller's ``rel`` (its :meth:`check`), or None: a wrong delay can stay under the check's
        tolerance (EMPS with delay 1: 3.5 % against 0.2 % at its true 0) and still bias every replay."""
        D, res = min(self.other_delays(r, y, u, d).items(), key=lambda kv: kv[1])
        return (D, res) if res * factor < rel else None

    def diagnose(self, r, y, u, d, tol: float) -> list[str]:
        """What fits the recording better than the configured structure (for the error message)."""
        r, y = np.asarray(r, np.float64), np.asarray(y, np.float64)
        hints = []
        near = [p for p in (np.roots(self.a) if self.a.size > 1 else []) if INTEGRATOR_TOL < abs(p - 1.0) <= 1e-3]
        if near:
            hints.append(f"A has a pole at z = {complex(near[0]).real:.10g}, {abs(near[0] - 1):.2g} from 1: an "
                         "integrator or a slow filter typed with too few digits moves it and changes the controller "
                         "a lot; give num, den and num_r with every digit the drive's tuning tool shows (12 or more)")
        Ac, Bx = self._equation_error(r, y, self.recorded_output(u, d))
        if Ac.size >= 10 and np.dot(Bx, Bx) > 0:
            g = float(np.dot(Ac, Bx) / np.dot(Bx, Bx))            # best scale of the law
            res = float(np.linalg.norm(Ac - g * Bx) / np.linalg.norm(Ac))
            if res < tol and abs(g - 1) > 0.01:
                why = "a sign error" if g < 0 else "check gtau and the gains"
                hints.append(f"the recording is this structure with its gain ×{g:.4g} ({why}; residual then "
                             f"{100 * res:.2g} %)")
        for D, res in self.other_delays(r, y, u, d).items():
            if res < tol:
                hints.append(f"delay {D} samples fits (residual {100 * res:.2g} %): set controller.delay={D}")
        if self.structure != "error feedback":
            ef = LTIController(self.b_y, self.b_y, self.a, self.gtau, self.v_sat, self.delay, "error feedback")
            res = ef.check(r, y, u, d)
            if res < tol:
                hints.append(f"error feedback on e = r - y with this C_y fits (residual {100 * res:.2g} %)")
        return hints


def _check_stable(name: str, a: np.ndarray) -> None:
    """A denominator with a pole outside the unit circle (beyond INTEGRATOR_TOL) is refused."""
    poles = np.roots(a / a[0]) if a.size > 1 else np.zeros(0)
    if np.any(np.abs(poles) > 1.0 + INTEGRATOR_TOL):   # an integrator typed with few digits: |z| = 1 + 1e-7
        z = float(np.abs(poles).max())
        raise ValueError(f"controller.{name}={list(a)} has poles outside the unit circle "
                         f"(|z| = {z:.10g}): an unstable controller cannot be replayed; "
                         "check the coefficient order (powers of z⁻¹, a[0] first)"
                         + ("; a pole this close to 1 is an integrator typed with too few digits: give den, num "
                            "and num_r with every digit the drive's tuning tool shows (12 or more)"
                            if z - 1.0 < 1e-3 else ""))


def _common_roots(p_r: np.ndarray, p_y: np.ndarray) -> np.ndarray:
    """The roots shared by two root sets (each used once), matched greedily nearest first within COMMON_ROOT_TOL
    relative to max(1, |p|); a complex root comes with its conjugate, so the common factor is real."""
    free = list(range(p_y.size))
    out = []
    for p in sorted(p_r, key=lambda z: (z.real, z.imag)):
        if not free:
            break
        j = min(free, key=lambda k: abs(p_y[k] - p))
        if abs(p_y[j] - p) <= COMMON_ROOT_TOL * max(1.0, abs(p)):
            out.append(1.0 + 0j if abs(p - 1.0) <= INTEGRATOR_TOL else p)    # an integrator: exactly 1
            free.remove(j)
    return np.array(out, dtype=complex)


def _deflate(a: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """A(z⁻¹) / Π (1 - p z⁻¹) for roots p of A: the quotient of the synthetic division (the remainder, the
    typed digits' rounding of a shared root, is dropped).  a[0] = 1; ascending powers of z⁻¹ are the
    descending powers of z of zⁿ A, so numpy's polynomial division applies as is."""
    g = np.real_if_close(np.poly(roots), tol=1e6) if roots.size else np.ones(1)
    if np.iscomplexobj(g):
        raise ValueError("the common poles of den and den_r are not in conjugate pairs: check the coefficients")
    q, _ = np.polydiv(a, g)
    return np.atleast_1d(q)


def common_denominator(n_r: np.ndarray, d_r: np.ndarray, n_y: np.ndarray, d_y: np.ndarray):
    """(B_r, B_y, A) of C_r = N_r/D_r, C_y = N_y/D_y over the least common multiple A = D_r · D_y/G, G the
    factor the two share (module docstring).  D_r, D_y are normalised (d[0] = 1) here."""
    n_r, d_r = n_r / d_r[0], d_r / d_r[0]
    n_y, d_y = n_y / d_y[0], d_y / d_y[0]
    if d_r.size == d_y.size and np.array_equal(d_r, d_y):
        return n_r, n_y, d_y
    roots_r = np.roots(d_r) if d_r.size > 1 else np.zeros(0, complex)
    roots_y = np.roots(d_y) if d_y.size > 1 else np.zeros(0, complex)
    shared = _common_roots(roots_r, roots_y)
    rest_y = _deflate(d_y, shared) if shared.size else d_y        # D_y / G
    rest_r = _deflate(d_r, shared) if shared.size else d_r        # D_r / G
    return np.convolve(n_r, rest_y), np.convolve(n_y, rest_r), np.convolve(d_r, rest_y)


def _fmt(p: np.ndarray) -> str:
    """'4.279e+06 - 8.212e+06 z^-1 + 3.939e+06 z^-2'"""
    terms = [(c, i) for i, c in enumerate(p) if c != 0 or i == 0]
    out = f"{terms[0][0]:.4g}" + (f" z^-{terms[0][1]}" if terms[0][1] else "")
    for c, i in terms[1:]:
        out += f" {'-' if c < 0 else '+'} {abs(c):.4g} z^-{i}"
    return out


def advanced_reference(r: np.ndarray, advance: int) -> np.ndarray:
    """r(k + D) for k = 0 … N-1, the last sample held past the end: the reference whose force a law must give at k
    when the controller delays its output D samples (``LTIController.delay``: u = gtau (sat(v + u_ff/gtau)(k - D) + d),
    so u_ff(k) acts at k + D); D = 0: r itself."""
    if not advance:
        return r
    r = np.asarray(r, dtype=np.float64)
    return np.concatenate([r[advance:], np.full(min(advance, r.size), r[-1])])
