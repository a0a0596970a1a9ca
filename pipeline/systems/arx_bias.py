"""`arx_bias`: the linear ARX system of [B1] §II-C (SPEC §2.4), and the ARX physics model.

True system (open loop, equation noise)::

    y(t) = 1.5 y(t-1) - 0.7 y(t-2) + 1.0 u(t-1) + 0.5 u(t-2) + v(t),   u ~ N(0,1), v ~ N(0,0.1²)

i.e. ``A(q) y = B(q) u + v`` with ``A = 1 - 1.5 q^-1 + 0.7 q^-2``, ``B = q^-1 + 0.5 q^-2``
(n_a = n_b = 2, n_k = 0).  The physics model is the ARX regression itself,
:class:`ARXPhysics` (θ = [a1, a2, b1, b2]); forward least squares is consistent because the
noise enters as equation error, the direct inverse regression is biased ([B1] (15)-(18)).

:class:`ARXPhysics` is the generic linear-in-parameters ARX model
``y(k) = Σ a_i y(k-i) + Σ b_i u(k-n_k-i)`` (SPEC §3 item 1); :mod:`rot_trans_nmp` uses it with
n_a = n_b = 4.  :func:`least_squares` (column-scaled linear LS) is shared by the physics models.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import field
from typing import Literal

import numpy as np

from pipeline.identify.least_squares import solve_scaled as least_squares
from pipeline.params import schema, spec
from pipeline.systems.base import PhysicsModel, SimResult, System, check_signal, lfilter


@schema
class Noise:
    # white equation noise v(t) (ARX), the only structure here
    structure: Literal["equation"] = "equation"
    # std of v [-]
    std: float = spec(0.1, ge=0, le=1e3, unit="(output units)")


@schema
class Params:
    _target_: str
    name: str = "arx_bias"
    # AR coefficients a1, a2 [-]
    a: list[float] = spec([1.5, -0.7], ge=-1e3, le=1e3)
    # input coefficients b1, b2 [-] (n_k = 0)
    b: list[float] = spec([1.0, 0.5], ge=-1e6, le=1e6, min_len=1)
    noise: Noise = field(default_factory=Noise)
    # std of the white input u ~ N(0, u_std^2) used by ArxBias.generate [-]
    u_std: float = spec(1.0, ge=0, le=1e6)
    # sample time [s] (discrete system; only recorded)
    Ts: float = spec(1.0, gt=0, le=3600.0, unit="s")   # a discrete system: Ts is only recorded


def lagged(x: np.ndarray, lags) -> np.ndarray:
    """Columns ``x(k - l)`` for each l in ``lags`` (negative l = future), zero outside [0, N)
    (SPEC §0: the past is at rest); shape [N, len(lags)]."""
    x = np.asarray(x, dtype=np.float64)
    N = x.shape[0]
    out = np.zeros((N, len(lags)))
    for c, l in enumerate(lags):
        if l >= 0:
            out[l:, c] = x[:N - l] if l < N else 0.0
        else:
            out[:N + l, c] = x[-l:]
    return out


class ARXPhysics(PhysicsModel):
    """Linear ARX physics model ``y(k) = Σ_{i=1..n_a} a_i y(k-i) + Σ_{i=1..n_b} b_i u(k-n_k-i)``.

    θ = [a_1..a_{n_a}, b_1..b_{n_b}] (SPEC §3 items 1, 3).  Regressor windows
    φ(k) = [y(k-1..k-n_a), u(k-n_k-1..k-n_k-n_b)] with zero past; ``ŷ = offset(φ) +
    features(φ) θ`` with offset 0 and features = φ, so the target of the forward least
    squares is y itself.

    The inverse ([B1] (15)): ``u(k) = θ'ᵀ φ'(k)`` with φ'(k) = [y(k+n_k+1..k+n_k-n_a+1),
    u(k-1..k-n_b+1)] and θ' = :meth:`inverse_theta` (θ) = [1, -a_1..-a_{n_a}, -b_2..-b_{n_b}]/b_1;
    the target of the inverse regression is u.

    Parameters
    ----------
    n_a, n_b, n_k : int
        Orders; n_b >= 1.
    Ts : float
        Sample time [s] (only recorded).
    """

    def __init__(self, n_a: int, n_b: int, n_k: int = 0, Ts: float = 1.0):
        if n_a < 0 or n_b < 1 or n_k < 0:
            raise ValueError(f"ARX orders need n_a >= 0, n_b >= 1, n_k >= 0; got "
                             f"n_a={n_a}, n_b={n_b}, n_k={n_k}")
        self.n_a, self.n_b, self.n_k, self.Ts = int(n_a), int(n_b), int(n_k), float(Ts)
        #: index in θ of the input gain ψ = b_1 ([B1] (15), (26))
        self.input_gain_index = self.n_a
        self.param_names = tuple(f"a{i}" for i in range(1, n_a + 1)) + \
            tuple(f"b{i}" for i in range(1, n_b + 1))

    # ----- forward model (consistent least squares under equation noise)
    def phi(self, y, u) -> np.ndarray:
        """Regressor windows φ(k) [N, n_a+n_b] (zero past)."""
        y = check_signal("y", y)
        u = check_signal("u", u, y.shape[0])
        return np.hstack([lagged(y, range(1, self.n_a + 1)),
                          lagged(u, range(self.n_k + 1, self.n_k + self.n_b + 1))])

    def features(self, phi):
        """Columns multiplying θ in ŷ (numpy or torch, [..., n_a+n_b] -> same)."""
        return phi

    def offset(self, phi):
        """Part of ŷ that does not depend on θ: zero for ARX."""
        return 0.0 * phi[..., 0]

    def predict(self, theta, phi):
        """One-step prediction ŷ = offset(φ) + features(φ) θ (numpy or torch)."""
        return self.offset(phi) + self.features(phi) @ theta

    def regressor(self, y, u, r=None):
        """(Φ [N, p], z [N]) with z = y (rows from k = 0, zero past)."""
        return self.phi(y, u), check_signal("y", y)

    def fit(self, y, u) -> np.ndarray:
        """Forward least-squares estimate θ* ([B1] (7) for a LIP model)."""
        return least_squares(*self.regressor(y, u))

    # ----- inverse model ([B1] (13)-(18))
    def inverse_phi(self, y, u) -> np.ndarray:
        """φ'(k) = [y(k+n_k+1..k+n_k-n_a+1), u(k-1..k-n_b+1)], rows k = 0..N-n_k-2."""
        y = check_signal("y", y)
        u = check_signal("u", u, y.shape[0])
        h = self.n_k + 1
        cols = lagged(y, range(-h, -h + self.n_a + 1))
        if self.n_b > 1:
            cols = np.hstack([cols, lagged(u, range(1, self.n_b))])
        return cols[:y.shape[0] - h]

    def inverse_regressor(self, y, u):
        """(Φ' [N-n_k-1, n_a+n_b], z' = u(k)) for the direct inverse regression; θ' as in
        :meth:`inverse_theta`."""
        u = check_signal("u", u)
        Phi = self.inverse_phi(y, u)
        return Phi, u[:Phi.shape[0]]

    def inverse_theta(self, theta) -> np.ndarray:
        """θ' of the exact inverse of the forward model θ ([B1] (15))."""
        theta = self._check_theta(theta)
        a, b = theta[:self.n_a], theta[self.n_a:]
        if b[0] == 0.0:
            raise ValueError("b1 = 0: the model has no input at lag n_k+1 and cannot be inverted")
        return np.concatenate([[1.0], -a, -b[1:]]) / b[0]

    def _check_theta(self, theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape[0] != len(self.param_names):
            raise ValueError(f"θ has {theta.shape[0]} entries; this model has "
                             f"{len(self.param_names)}: {self.param_names}")
        if not np.all(np.isfinite(theta)):
            raise ValueError(f"θ contains NaN/inf: {theta}")
        return theta

    def input_zeros(self, theta) -> np.ndarray:
        """Zeros of B: roots of b_1 z^{n_b-1} + … + b_{n_b} (the poles of the inverse)."""
        b = self._check_theta(theta)[self.n_a:]
        return np.roots(b) if b.shape[0] > 1 else np.zeros(0)

    def feedforward(self, theta, r) -> np.ndarray:
        """Exact inverse ``u = A(q)/B(q) q^{n_k+1} r`` (y = r for the model), SPEC §6.

        Uses r(k) for k >= N held at r(N-1) (rest) and zero past.  Raises ValueError if B has
        a zero on or outside the unit circle (the inverse is unstable): use FHOFC or ILC.
        """
        theta = self._check_theta(theta)
        r = check_signal("r", r)
        zeros = self.input_zeros(theta)
        bad = zeros[np.abs(zeros) >= 1.0]
        if bad.size:
            raise ValueError(
                f"the model is nonminimum phase: B(z) has zero(s) {np.round(bad, 4).tolist()} "
                "on/outside the unit circle, so its causal inverse is unstable; compute the "
                "feedforward by optimisation instead (invert=fhofc, FHOFC [B2] (17)) or learn "
                "it on the plant (invert=ilc)")
        a, b = theta[:self.n_a], theta[self.n_a:]
        h = self.n_k + 1
        r_ext = np.concatenate([r, np.full(h, r[-1])])
        w = lfilter(np.concatenate([[1.0], -a]), [1.0], r_ext)[h:]    # A(q) r, advanced n_k+1
        return lfilter([1.0], b, w)                                   # b1 u(k) + b2 u(k-1) + …

    def physical(self, theta) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.param_names, self._check_theta(theta))}


def _noise_options(noise, allowed: tuple[str, ...], default: dict) -> tuple[str, float]:
    """Validate a ``noise: {structure, std}`` mapping; return (structure, std)."""
    opts = dict(default)
    if noise is not None:
        if not isinstance(noise, Mapping):
            raise ValueError(f"noise must be a mapping {{structure, std}}, got {noise!r}")
        unknown = set(noise) - {"structure", "std"}
        if unknown:
            raise ValueError(f"noise has unknown key(s) {sorted(unknown)}; allowed: structure, std")
        opts.update({k: noise[k] for k in noise})
    structure, std = str(opts["structure"]), float(opts["std"])
    if structure not in allowed:
        raise ValueError(f"noise.structure={structure!r} is not supported here; use one of {allowed}")
    if not (np.isfinite(std) and std >= 0.0):
        raise ValueError(f"noise.std must be >= 0 and finite, got {opts['std']!r}")
    return structure, std


class ArxBias(System):
    """[B1] §II-C ARX system (SPEC §2.4), open loop: ``u = u_ff + du``, ``r`` is only recorded.

    Parameters
    ----------
    a : sequence of float
        AR coefficients a_1, a_2 (y(t) = a1 y(t-1) + a2 y(t-2) + …).
    b : sequence of float
        Input coefficients b_1, b_2 of u(t-1), u(t-2) (n_k = 0).
    noise : mapping
        ``{structure: equation, std: 0.1}``: white equation noise v(t) [-].
    u_std : float
        Std of the white input drawn by :meth:`input` / :meth:`generate` [-].
    Ts : float
        Sample time [s] (the system is discrete; 1 by default).
    """

    name = "arx_bias"

    def __init__(self, a=(1.5, -0.7), b=(1.0, 0.5), noise=None, u_std: float = Params.u_std,
                 Ts: float = Params.Ts, name: str = Params.name):
        self.a = np.asarray(a, dtype=np.float64).reshape(-1)
        self.b = np.asarray(b, dtype=np.float64).reshape(-1)
        if self.b.size < 1 or not (np.all(np.isfinite(self.a)) and np.all(np.isfinite(self.b))):
            raise ValueError(f"a={a!r}, b={b!r}: give finite coefficients and at least one b")
        poles = np.roots(np.concatenate([[1.0], -self.a])) if self.a.size else np.zeros(0)
        if np.any(np.abs(poles) >= 1.0):
            raise ValueError(f"A(q) with a={a!r} has poles {poles} outside the unit circle; "
                             "the open-loop system would be unstable")
        self.structure, self.std = _noise_options(noise, ("equation",),
                                                  {"structure": "equation", "std": 0.1})
        self.u_std = float(u_std)
        if not (np.isfinite(self.u_std) and self.u_std >= 0.0):
            raise ValueError(f"u_std must be >= 0, got {u_std!r}")
        self.Ts = float(Ts)
        self.name = name
        self._physics = ARXPhysics(self.a.size, self.b.size, 0, self.Ts)

    @property
    def theta0(self) -> np.ndarray:
        """True parameters θ0 = [a1, a2, b1, b2] in :class:`ARXPhysics` order."""
        return np.concatenate([self.a, self.b])

    @property
    def physics(self) -> ARXPhysics:
        return self._physics

    def noise(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """White equation noise v ~ N(0, std²), length n."""
        return self.std * rng.standard_normal(int(n))

    def input(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """White input u ~ N(0, u_std²), length n (the [B1] §II-C excitation)."""
        return self.u_std * rng.standard_normal(int(n))

    def check_reference(self, r) -> None:
        check_signal("r", r)

    def simulate(self, r, u_ff=None, du=None, v=None) -> SimResult:
        """Open loop: ``A(q) y = B(q) u + v`` with ``u = u_ff + du`` (zero past).

        ``y_clean = y - v`` is the noise-free one-step part (past noise has entered y through
        the AR dynamics, as equation noise does)."""
        r = check_signal("r", r)
        n = r.shape[0]
        u_ff = np.zeros(n) if u_ff is None else check_signal("u_ff", u_ff, n)
        du = np.zeros(n) if du is None else check_signal("du", du, n)
        v = np.zeros(n) if v is None else check_signal("v", v, n)
        u = u_ff + du
        A = np.concatenate([[1.0], -self.a])
        y = lfilter(np.concatenate([[0.0], self.b]), A, u) + lfilter([1.0], A, v)
        return SimResult(t=np.arange(n) * self.Ts, r=r, u=u, y=y, u_ff=u_ff, u_fb=np.zeros(n),
                         y_clean=y - v, v=v)

    def generate(self, n: int, rng: np.random.Generator) -> SimResult:
        """The [B1] §II-C data set: u = :meth:`input` then v = :meth:`noise` from ``rng``."""
        u = self.input(n, rng)
        v = self.noise(n, rng)
        return self.simulate(np.zeros(int(n)), du=u, v=v)

    def exact_inverse(self, r) -> np.ndarray:
        """The input making y = r with v = 0 (B has its zero at -0.5: stable)."""
        return self._physics.feedforward(self.theta0, r)
