"""Two-mass-spring-damper plant with a Stribeck-like damper, [K] Section VI (SPEC §2.1).

Mass ``m1`` is tied to the world by the spring ``k1`` and the nonlinear damper ``d_NL``; mass
``m2`` is tied to ``m1`` by the spring ``k2`` and the damper ``d2``.  The force ``f`` [N] acts on
``m1`` and the output ``y`` [m] is the position of ``m1`` (collocated).  The plant is discrete
by definition, [K] (31) with the backward difference ``δ = (1 - q^-1)/Ts``::

    Σ_{i=0..2} b_i δ^i f(k) = Σ_{i=0..4} a_i δ^i y(k) + Σ_{i=0..2} b_i δ^i d_NL(δy(k))
    b0 = k2, b1 = d2, b2 = m2
    a0 = k1 k2, a1 = k1 d2, a2 = m1 k2 + m2 k1 + m2 k2, a3 = (m1 + m2) d2, a4 = m1 m2
    d_NL(v) = c1 v + (c2 - c1) sech(α v) v                                       [K] (32)

(a2 and a3 follow from Newton's law; the paper misprints them, SPEC §2.1.)

Two equivalent, well-conditioned computations are used (never the polynomial in q^-1 whose
coefficients reach ~1e12 at Ts = 1e-3):

- forward ``y = J(f)``: replacing s by δ in the physical state-space model
  ``x = [x1, v1, x2, v2]`` is the implicit (backward) Euler scheme
  ``x(k) = x(k-1) + Ts (A_c x(k) + B_c (f(k) - n(v1(k))))`` with ``v1(k) = δ x1(k)`` and
  ``n(v) = d_NL(v) - c1 v`` the nonlinear remainder; the only implicit unknown is the scalar
  ``v1(k)``, found by Newton per sample (numba);
- inverse ``f̂ = (A(q)/B(q)) r + d_NL(δr)``: ``A(δ) r`` from repeated differences of r, then the
  AR filter ``1/B(q)`` with B normalised monic in q^-1 ([K] (6)), stable for every physical
  m2, d2, k2 > 0 because δ maps the open left half plane inside the unit circle.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:   # annotations only; imported where used (start-up, issue 19)
    import control

from collections.abc import Mapping
from dataclasses import field

import numpy as np
from numba import njit

from pipeline.params import DAMP_MAX, MASS_MAX, NOISE_MAX, STIFF_MAX, TS_MAX, schema, spec
from pipeline.systems.base import PhysicsModel, SimResult, System, check_signal, lfilter


@schema
class Noise:
    # [m] std of white measurement noise on y; 0 = noise-free (SPEC §2.1 default)
    std: float = spec(0.0, ge=0, lt=NOISE_MAX, unit="m")


@schema
class Params:
    _target_: str
    name: str = "two_mass_stribeck"
    # [kg] mass carrying the force f and the sensor y (collocated), [K] §VI
    m1: float = spec(1.0, gt=0, le=MASS_MAX, unit="kg")
    # [kg] second mass, tied to m1 by k2 and d2, [K] §VI
    m2: float = spec(2.0, gt=0, le=MASS_MAX, unit="kg")
    # [N/m] spring from m1 to the world, [K] §VI
    k1: float = spec(1.0, ge=0, le=STIFF_MAX, unit="N/m")
    # [N/m] stiff spring m1-m2 (flexible mode ~150 rad/s), [K] §VI
    k2: float = spec(15000.0, gt=0, le=STIFF_MAX, unit="N/m")
    # [N s/m] damper m1-m2, [K] §VI
    d2: float = spec(50.0, ge=0, le=DAMP_MAX, unit="N s/m")
    # [N s/m] damping of d_NL away from standstill (viscous region), [K] (32)
    c1: float = spec(1.0, ge=0, le=DAMP_MAX, unit="N s/m")
    # [N s/m] damping of d_NL at standstill (Stribeck region), [K] (32)
    c2: float = spec(20.0, ge=0, le=DAMP_MAX, unit="N s/m")
    # [s/m] Stribeck velocity scale: d_NL = c1 v + (c2 - c1) sech(alpha v) v, [K] (32)
    alpha: float = spec(20.0, ge=0, le=1e9, unit="s/m")
    # [s] sample time of the δ-operator model, SPEC §2.1
    Ts: float = spec(1e-3, gt=0, le=TS_MAX, unit="s")
    noise: Noise = field(default_factory=Noise)


#: min over x of sech(x) (1 - x tanh x): the most negative slope of v ↦ sech(αv) v, per unit
_MIN_SECH_SLOPE = -0.2511478713708375


# --------------------------------------------------------------------------------------------
# building blocks
# --------------------------------------------------------------------------------------------
def sech(x):
    """Hyperbolic secant ``1/cosh(x)`` without overflow (SPEC §0): ``2 e^-|x| / (1 + e^-2|x|)``."""
    e = np.exp(-np.abs(np.asarray(x, dtype=np.float64)))
    return 2.0 * e / (1.0 + e * e)


def stribeck_damper(v, c1: float, c2: float, alpha: float):
    """Stribeck-like damper force [N] at velocity ``v`` [m/s], [K] (32).

    ``d_NL(v) = c1 v + (c2 - c1) sech(α v) v``: damping ``c2`` [N s/m] near standstill, ``c1``
    for ``|v| >> 1/α`` (α [s/m]).
    """
    v = np.asarray(v, dtype=np.float64)
    return c1 * v + (c2 - c1) * sech(alpha * v) * v


def delta_powers(x: np.ndarray, Ts: float, order: int) -> np.ndarray:
    """Backward differences ``[x, δx, …, δ^order x]`` (shape ``(order+1, N)``), ``δ = (1 - q^-1)/Ts``.

    Signals are at rest before k = 0 (SPEC §0), so ``δx(0) = x(0)/Ts``.
    """
    out = np.empty((order + 1, x.shape[-1]))
    out[0] = x
    for i in range(1, order + 1):
        out[i] = np.diff(out[i - 1], prepend=0.0) / Ts
    return out


def delta_to_monic_shift(a_delta, b_delta, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalise ``B(δ) f = A(δ) y`` to [K] (6): ``(1 + Σ β_i q^-i) f = Σ ā_i δ^i y``.

    Parameters
    ----------
    a_delta, b_delta : array_like
        Coefficients of A and B in powers of δ, lowest first.
    Ts : float
        Sample time [s].

    Returns
    -------
    a_bar : ndarray
        ``a_delta / β0`` where ``β0`` is the q^0 coefficient of B(δ) expanded in q^-1.
    beta : ndarray
        ``[β_1, …, β_nb]``, the remaining q^-i coefficients of B divided by β0.
    """
    b_delta = np.asarray(b_delta, dtype=np.float64)
    # δ^i = Ts^-i (1 - q^-1)^i: add the binomial expansions, lowest power of q^-1 first
    b_shift = np.zeros(b_delta.size)
    for i, bi in enumerate(b_delta):
        b_shift[: i + 1] += bi * Ts ** -i * np.polynomial.polynomial.polypow([1.0, -1.0], i)
    beta0 = b_shift[0]
    return np.asarray(a_delta, dtype=np.float64) / beta0, b_shift[1:] / beta0


def monic_shift_to_delta(beta, Ts: float) -> np.ndarray:
    """Inverse map of the B-part of :func:`delta_to_monic_shift`: ``1 + Σ β_i q^-i`` in powers of δ.

    Uses ``q^-1 = 1 - Ts δ``; returns the δ-coefficients (lowest first) of the same polynomial.
    """
    beta = np.asarray(beta, dtype=np.float64)
    out = np.zeros(beta.size + 1)
    out[0] = 1.0
    for i, bi in enumerate(beta, start=1):
        out[: i + 1] += bi * np.polynomial.polynomial.polypow([1.0, -Ts], i)
    return out


def ar_roots(beta) -> np.ndarray:
    """Roots in z of the AR polynomial ``B(q) = 1 + Σ β_i q^-i`` (stable iff all |z| < 1)."""
    return np.roots(np.r_[1.0, np.asarray(beta, dtype=np.float64)])


def rational_feedforward(a_bar, beta, r: np.ndarray, Ts: float) -> np.ndarray:
    """Run the rational feedforward filter ``f = (1/B(q)) Σ ā_i δ^i r`` ([K] (2), (6)).

    Parameters
    ----------
    a_bar : array_like
        Coefficients of A in powers of δ (lowest first), units N s^i/m.
    beta : array_like
        ``[β_1, …]`` of ``B(q) = 1 + Σ β_i q^-i`` (dimensionless).
    r : ndarray
        Reference [m], at rest before k = 0; 1-D or 2-D (batch, N).
    Ts : float
        Sample time [s].

    Raises
    ------
    ValueError
        If B has a root on or outside the unit circle (the filter would be unstable).
    """
    beta = np.asarray(beta, dtype=np.float64)
    roots = ar_roots(beta)
    if roots.size and np.max(np.abs(roots)) >= 1.0:
        raise ValueError(f"the AR polynomial B(q) = 1 + {beta.tolist()} q^-i has roots {roots} "
                         f"(max |z| = {np.max(np.abs(roots)):.6g} >= 1): the feedforward filter 1/B "
                         "is unstable; reflect the roots inside the unit circle or re-identify B")
    r = np.asarray(r, dtype=np.float64)
    a_bar = np.asarray(a_bar, dtype=np.float64)
    if r.ndim == 1:
        ar = a_bar @ delta_powers(r, Ts, a_bar.size - 1)
    else:
        ar = np.stack([a_bar @ delta_powers(ri, Ts, a_bar.size - 1) for ri in r])
    return lfilter([1.0], np.r_[1.0, beta], ar, axis=-1)


@njit(cache=True)
def _forward_newton(Phi, Gamma, f, dc, alpha):  # pragma: no cover - compiled
    """Implicit-Euler two-mass simulation with a scalar Newton solve per sample.

    ``x(k) = Phi x(k-1) + Gamma (f(k) - n(v1(k)))``, ``n(v) = dc sech(αv) v``; returns
    (x1 = y, the largest number of Newton steps used in one sample).
    """
    nb, N = f.shape
    y = np.empty((nb, N))
    g = Gamma[1]
    maxit = 0
    for b in range(nb):
        x = np.zeros(4)
        p = np.empty(4)
        for k in range(N):
            for i in range(4):
                p[i] = Phi[i, 0] * x[0] + Phi[i, 1] * x[1] + Phi[i, 2] * x[2] + Phi[i, 3] * x[3] \
                    + Gamma[i] * f[b, k]
            # solve h(v) = v + g n(v) - p1 = 0; h' >= 1 - g dc 0.2511 > 0 (checked), so unique
            v = p[1]
            nv = 0.0
            it = 0
            while it < 60:
                av = alpha * v
                e = np.exp(-abs(av))
                s = 2.0 * e / (1.0 + e * e)
                nv = dc * s * v
                dn = dc * s * (1.0 - av * np.tanh(av))
                step = (v + g * nv - p[1]) / (1.0 + g * dn)
                v -= step
                it += 1
                if abs(step) <= 1e-14 * abs(v) or step == 0.0:
                    break
            av = alpha * v
            e = np.exp(-abs(av))
            nv = dc * (2.0 * e / (1.0 + e * e)) * v
            if it > maxit:
                maxit = it
            for i in range(4):
                x[i] = p[i] - Gamma[i] * nv
            x[1] = v  # exact root (p1 - g n(v) equals v up to rounding)
            y[b, k] = x[0]
    return y, maxit


# --------------------------------------------------------------------------------------------
# nominal physics model: the linear rational model B(q) f = A(δ) y  ([K] (2), (6))
# --------------------------------------------------------------------------------------------
class TwoMassRationalModel(PhysicsModel):
    """Linear rational model of the two-mass structure, [K] (6) without g_φ, LIP in θ.

    ``(1 + β1 q^-1 + β2 q^-2) f(k) = Σ_{i=0..4} ā_i δ^i y(k)``, ``θ = [ā0, ā1, ā2, ā3, ā4, β1, β2]``.

    Normalisation (removes the scale ambiguity of ``B(δ) f = A(δ) y``): B is monic in q^-1, as in
    [K] (6), i.e. the equation is divided by ``β0 = b0 + b1/Ts + b2/Ts²``.  The true plant with a
    linear damper c (c1 = c2 = c) is inside the class with ``Ã(δ) = A(δ) + c δ B(δ)``
    (:meth:`TwoMassStribeck.physics_theta`).  The forward form has direct feedthrough
    (``n_k = -1``: f(k) acts on y(k)); ``n_a = 4`` past outputs, ``n_b = 3`` inputs f(k..k-2).
    """

    param_names = ("a0", "a1", "a2", "a3", "a4", "beta1", "beta2")
    n_a = 4
    n_b = 3
    n_k = -1

    def __init__(self, Ts: float):
        if not Ts > 0:
            raise ValueError(f"Ts must be > 0 s, got {Ts}")
        self.Ts = float(Ts)

    def regressor(self, y, u, r=None):
        """Equation-error regression ``z(k) = f(k) = Φ(k) θ`` over all N samples.

        ``Φ(k) = [y, δy, δ²y, δ³y, δ⁴y, -f(k-1), -f(k-2)](k)``; samples before k = 0 are zero
        (rest, SPEC §0), so no row is dropped — valid for data that start at rest.  Columns
        differ by up to ~Ts^-4 in scale: column-scale Φ before least squares.
        """
        y = check_signal("y", y)
        u = check_signal("u", u, y.size)
        dy = delta_powers(y, self.Ts, 4)
        u1 = np.r_[0.0, u[:-1]]
        u2 = np.r_[0.0, 0.0, u[:-2]]
        return np.column_stack([dy.T, -u1, -u2]), u.copy()

    def feedforward(self, theta, r):
        """``f = (1/B(q)) Σ ā_i δ^i r`` [N] for reference r [m]; raises if B is unstable."""
        theta = self._check_theta(theta)
        r = check_signal("r", r)
        return rational_feedforward(theta[:5], theta[5:], r, self.Ts)

    def physical(self, theta):
        """Physical parameters from θ (exact when the plant is in the class, c1 = c2 = c).

        From ``B ∝ k2 + d2 δ + m2 δ²`` and ``Ã = A + c δ B``: ``k1 = ã0/b0``, ``m1 = ã4/b2``,
        ``c = ã1/b0 - k1 d2/k2``, ``m2 = ã2/b0 - m1 - k1 m2/k2 - c d2/k2`` (m2/k2 known), then
        ``k2 = m2/(m2/k2)``, ``d2 = k2 (d2/k2)``.  Units: kg, N/m, N s/m.
        """
        theta = self._check_theta(theta)
        bd = monic_shift_to_delta(theta[5:], self.Ts)   # ∝ [k2, d2, m2]
        ad = theta[:5] / bd[0]                           # Ã/b0
        rho_d, rho_m = bd[1] / bd[0], bd[2] / bd[0]      # d2/k2, m2/k2 [s], [s²]
        k1 = ad[0]
        m1 = ad[4] / rho_m
        c = ad[1] - k1 * rho_d
        m2 = ad[2] - m1 - k1 * rho_m - c * rho_d
        k2 = m2 / rho_m
        return {"m1": float(m1), "m2": float(m2), "k1": float(k1), "k2": float(k2),
                "d2": float(rho_d * k2), "c": float(c)}

    @staticmethod
    def _check_theta(theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64).ravel()
        if theta.size != 7 or not np.all(np.isfinite(theta)):
            raise ValueError(f"θ must hold 7 finite numbers [ā0..ā4, β1, β2], got {theta}")
        return theta


# --------------------------------------------------------------------------------------------
# the plant
# --------------------------------------------------------------------------------------------
class TwoMassStribeck(System):
    """Open-loop two-mass plant with Stribeck damper, [K] Section VI (SPEC §2.1).

    Parameters
    ----------
    m1, m2 : float
        Masses [kg] (m1 carries the force and the sensor).
    k1, k2 : float
        Springs [N/m]: m1 to the world, m2 to m1.
    d2 : float
        Damper between the masses [N s/m].
    c1, c2 : float
        Damping of d_NL far from standstill and at standstill [N s/m], [K] (32).
    alpha : float
        Stribeck velocity scale [s/m] of ``sech(α v)``.
    Ts : float
        Sample time [s] of the δ-operator model.
    noise : mapping, optional
        ``{"std": σ}``: white measurement noise of std σ [m] added to y (default 0: none).
    """

    name = "two_mass_stribeck"

    def __init__(self, m1: float = Params.m1, m2: float = Params.m2, k1: float = Params.k1, k2: float = Params.k2,
                 d2: float = Params.d2, c1: float = Params.c1, c2: float = Params.c2, alpha: float = Params.alpha,
                 Ts: float = Params.Ts, noise: Mapping | None = None, name: str | None = None):
        for key, val in dict(m1=m1, m2=m2, k2=k2, Ts=Ts).items():
            if not float(val) > 0:
                raise ValueError(f"two_mass_stribeck: {key} must be > 0, got {val}")
        for key, val in dict(k1=k1, d2=d2, c1=c1, c2=c2, alpha=alpha).items():
            if not float(val) >= 0:
                raise ValueError(f"two_mass_stribeck: {key} must be >= 0, got {val}")
        self.m1, self.m2, self.k1, self.k2, self.d2 = map(float, (m1, m2, k1, k2, d2))
        self.c1, self.c2, self.alpha, self.Ts = map(float, (c1, c2, alpha, Ts))
        noise = dict(noise or {})
        unknown = set(noise) - {"std"}
        if unknown:
            raise ValueError(f"two_mass_stribeck: unknown noise keys {sorted(unknown)}; "
                             "the noise model takes only 'std' (white measurement noise [m])")
        self.noise_std = float(noise.get("std", 0.0))
        if not self.noise_std >= 0:
            raise ValueError(f"two_mass_stribeck: noise.std must be >= 0 m, got {self.noise_std}")
        if name:
            self.name = name
        # implicit-Euler matrices of the linear part with damping c1 (n(v) is the remainder)
        self._Phi, self._Gamma = self._backward_euler(self.c1)
        self._dc = self.c2 - self.c1
        # n'(v) = dc sech(αv)(1 - αv tanh αv) lies in [dc·(-0.2511), dc] (dc >= 0) or [dc, ...]
        min_dn = self._dc * _MIN_SECH_SLOPE if self._dc >= 0 else self._dc
        slope = 1.0 + self._Gamma[1] * min_dn
        if not slope > 0.05:
            raise ValueError(f"two_mass_stribeck: Ts = {Ts} s is too large for c2 - c1 = {self._dc}: "
                             "the per-sample equation for δy(k) is no longer monotone "
                             f"(min slope {slope:.3g}); reduce Ts")
        self._physics = TwoMassRationalModel(self.Ts)

    # ---- model pieces ----------------------------------------------------------------------
    def continuous_linear_model(self, damping: float | None = None) -> control.StateSpace:
        """Continuous physical model with a linear damper ``damping`` [N s/m] (default c1).

        States ``[x1, v1, x2, v2]`` [m, m/s, m, m/s], input f [N], output x1 [m].
        """
        import control  # lazy: saves 1.9 s of start-up (python-control)
        c = self.c1 if damping is None else float(damping)
        m1, m2, k1, k2, d2 = self.m1, self.m2, self.k1, self.k2, self.d2
        A = np.array([[0.0, 1.0, 0.0, 0.0],
                      [-(k1 + k2) / m1, -(c + d2) / m1, k2 / m1, d2 / m1],
                      [0.0, 0.0, 0.0, 1.0],
                      [k2 / m2, d2 / m2, -k2 / m2, -d2 / m2]])
        return control.ss(A, [[0.0], [1.0 / m1], [0.0], [0.0]], [[1.0, 0.0, 0.0, 0.0]], [[0.0]])

    def _backward_euler(self, c: float) -> tuple[np.ndarray, np.ndarray]:
        sysc = self.continuous_linear_model(c)
        M = np.eye(4) - self.Ts * sysc.A
        return np.linalg.solve(M, np.eye(4)), np.linalg.solve(M, self.Ts * sysc.B).ravel()

    def linear_model(self, damping: float | None = None) -> control.StateSpace:
        """Discrete linear part ``f -> y`` with linear damper ``damping`` (default c1), dt = Ts.

        ``s -> δ`` (backward Euler) of :meth:`continuous_linear_model`: ``ξ(k) = x(k-1)``,
        ``ξ(k+1) = Φ ξ(k) + Γ f(k)``, ``y(k) = C Φ ξ(k) + C Γ f(k)``.  This is the model for
        norm-optimal ILC (SPEC §2.1: use damping c1).
        """
        import control  # lazy: saves 1.9 s of start-up (python-control)
        Phi, Gamma = self._backward_euler(self.c1 if damping is None else float(damping))
        C = np.array([[1.0, 0.0, 0.0, 0.0]])
        return control.ss(Phi, Gamma[:, None], C @ Phi, C @ Gamma[:, None], self.Ts)

    def delta_coefficients(self, damping: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``(a, b)``: coefficients in powers of δ of ``Ã(δ) = A(δ) + damping·δ B(δ)`` and ``B(δ)``.

        ``damping = 0`` gives the A, B of SPEC §2.1 (the d_NL term is separate).
        """
        m1, m2, k1, k2, d2 = self.m1, self.m2, self.k1, self.k2, self.d2
        b = np.array([k2, d2, m2])
        a = np.array([k1 * k2, k1 * d2, m1 * k2 + m2 * k1 + m2 * k2, (m1 + m2) * d2, m1 * m2])
        a[1:4] += damping * b
        return a, b

    def physics_theta(self, damping: float | None = None) -> np.ndarray:
        """θ of :class:`TwoMassRationalModel` for this plant with linear damper ``damping``
        (default c1; the plant is inside the model class when c1 = c2 = damping)."""
        a, b = self.delta_coefficients(self.c1 if damping is None else float(damping))
        a_bar, beta = delta_to_monic_shift(a, b, self.Ts)
        return np.r_[a_bar, beta]

    # ---- System interface -------------------------------------------------------------------
    @property
    def physics(self) -> TwoMassRationalModel:
        return self._physics

    def learning_model(self) -> control.StateSpace:
        """The ILC model: the open-loop linear part with damping c1 (SPEC §2.1: one linearised at
        c2 converges far slower)."""
        return self.linear_model(self.c1)

    def d_nl(self, v):
        """The Stribeck damper force d_NL(v) [N] of this plant, [K] (32)."""
        return stribeck_damper(v, self.c1, self.c2, self.alpha)

    def forward(self, f: np.ndarray) -> np.ndarray:
        """Noise-free output ``y = J(f)`` [m] for input f [N] from rest; 1-D or 2-D (batch, N)."""
        f = np.asarray(f, dtype=np.float64)
        if f.ndim not in (1, 2) or not np.all(np.isfinite(f)):
            raise ValueError(f"input f must be a finite 1-D signal or a (batch, N) array, "
                             f"got shape {f.shape}")
        y, _ = _forward_newton(self._Phi, self._Gamma, np.atleast_2d(f), self._dc, self.alpha)
        return y[0] if f.ndim == 1 else y

    def exact_inverse(self, r: np.ndarray) -> np.ndarray:
        """Optimal input ``f̂ = (A(q)/B(q)) r + d_NL(δr)`` [N] (y = r exactly), SPEC §2.1."""
        r = check_signal("r", r)
        a, b = self.delta_coefficients(0.0)
        a_bar, beta = delta_to_monic_shift(a, b, self.Ts)
        return rational_feedforward(a_bar, beta, r, self.Ts) + self.d_nl(np.diff(r, prepend=0.0) / self.Ts)

    def noise(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """White measurement noise of std ``noise.std`` [m] (zeros when the std is 0)."""
        if self.noise_std == 0.0:
            return np.zeros(int(n))
        return rng.normal(0.0, self.noise_std, int(n))

    def simulate(self, r, u_ff=None, du=None, v=None) -> SimResult:
        """Open loop: ``u = u_ff + du``, ``y_clean = J(u)``, ``y = y_clean + v`` (SPEC §2.1)."""
        r = check_signal("r", r)
        n = r.size
        u_ff = np.zeros(n) if u_ff is None else check_signal("u_ff", u_ff, n)
        du = np.zeros(n) if du is None else check_signal("du", du, n)
        v = np.zeros(n) if v is None else check_signal("v", v, n)
        u = u_ff + du
        y_clean = self.forward(u)
        return SimResult(t=np.arange(n) * self.Ts, r=r, u=u, y=y_clean + v, u_ff=u_ff,
                         u_fb=np.zeros(n), y_clean=y_clean, v=v)

    def check_reference(self, r) -> None:
        check_signal("r", r)
