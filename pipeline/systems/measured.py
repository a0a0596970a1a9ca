"""Measured systems: a recorded experiment, not a simulator (SPEC §2.5, DESIGN "Measured systems").

A :class:`Recording` has what a user knows about a real machine, and nothing more:

- the **physics model** of a prismatic rigid-body axis, :class:`RigidBodyPhysics`::

      M q̈ = τ - F_v q̇ - F_c sign(q̇) - OF                      (EMPS reference model)

  linear in θ = [1/M, F_v/M, F_c/M, OF/M] in its one-step (NARX) form;
- the **known controller** as config, :class:`pipeline.systems.controller.LTIController`: any
  discrete LTI C(z), error feedback or 2-DOF, with gain, limit and delay (the EMPS position/velocity
  cascade ``vir = sat±v_sat(kv (kp (r - q) - q̇f))``, force ``τ = gtau · vir``, is one instance);
- the sample time (from the data, checked against the config) and the units of the signals.

It has no true plant: :meth:`Recording.simulate` refuses, so no stage can score a model of
measured data on a simulator by accident.  Evaluation simulates the *identified* model inside
the known controller (``pipeline.identify.measured_loop``) and compares with the recording.
"""
from __future__ import annotations

import math
from dataclasses import field
from typing import Literal, Optional

import numpy as np
from scipy import signal

from pipeline.identify.least_squares import solve_scaled
from pipeline.params import DAMP_MAX, FORCE_MAX, FREQ_MAX, MASS_MAX, TS_MAX, schema, spec
from pipeline.systems.actuator_lag import ActuatorLag, identify_tau
from pipeline.systems.actuator_lag import Params as ActuatorParams
from pipeline.systems.base import System, check_signal
from pipeline.systems.controller import LTIController
from pipeline.systems.controller import Params as ControllerParams
from pipeline.systems.force_terms import ForceTerms
from pipeline.systems.force_terms import Params as ForceTermsParams
from pipeline.systems.linear_motor import LinearMotorPhysics


@schema
class Published:
    M: float = spec(gt=0, le=MASS_MAX, unit="kg", example=95.1)
    F_v: float = spec(ge=-DAMP_MAX, le=DAMP_MAX, unit="N s/m", example=203.5)
    F_c: float = spec(ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=20.4)
    OF: float = spec(ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-3.2)


@schema
class Idim:
    # (system/emps.yaml) Butterworth low-pass of q before differentiating [Hz] (~2.5x the 20 Hz loop bandwidth)
    # (system/measured.yaml) low-pass before differentiating [Hz]: a few times the loop bandwidth
    cutoff_hz: float = spec(50.0, gt=0, le=FREQ_MAX, unit="Hz")
    # Butterworth order (filtfilt: zero phase, effective order 8)
    order: int = spec(4, ge=1, le=20)
    # parallel decimation of τ and the regressors (scipy.signal.decimate, zero phase)
    decimation: int = spec(10, ge=1, le=10_000)
    # samples dropped at each end (filter transients)
    trim: int = spec(50, ge=0, le=10**8)


@schema
class Params:
    _target_: str
    name: str = "measured"
    # (system/emps.yaml) sample time [s]; the data's own t must step this (checked before any work)
    # (system/measured.yaml) sample time [s]; must equal the data's own (t column or sidecar Ts)
    Ts: float = spec(1e-3, gt=0, le=TS_MAX, unit="s")
    controller: ControllerParams = spec(example="{kp:160.18,kv:243.45}")
    # (system/emps.yaml) one-step physics input: averaged ū(t-1) (exact ZOH of a mass, SPEC §2.2) | direct u(t-1) (the
    # benchmark authors' semi-implicit Euler); the published model is always replayed direct
    # (system/measured.yaml) averaged ū(t-1) (exact ZOH) | direct u(t-1)
    physics_input: Literal["averaged", "direct"] = "averaged"
    # M q̈ = τ - Σ terms (pipeline/systems/force_terms.py): viscous F_v q̇, coulomb F_c sign(q̇)
    force_terms: ForceTermsParams = field(default_factory=lambda: ForceTermsParams())
    # the drive: lag_tau of its current loop τ Ḟ + F = u [s], 'auto' or null (pipeline/systems/actuator_lag.py)
    actuator: ActuatorParams = field(default_factory=ActuatorParams)
    # name of the measured disturbance column in your files (loaded as d), or null
    disturbance: Optional[str] = None
    # {M, F_v, F_c, OF} from a datasheet or an earlier identification, or null
    published: Optional[Published] = None
    # (system/emps.yaml) filtered inverse-model LS (the benchmark's method), scipy.signal
    # (system/measured.yaml) filtered inverse-model least squares of the physics baseline
    idim: Idim = field(default_factory=Idim)


# --------------------------------------------------------------------------- physics model
class RigidBodyPhysics(LinearMotorPhysics):
    """Rigid body with composable force terms (:mod:`pipeline.systems.force_terms`; EMPS: viscous,
    Coulomb and a constant offset, SPEC §2.5)::

        M q̈ = τ - Σ_j p_j T_j(q, q̇)

    One-step form (the [B1] (32) rigid body of :class:`LinearMotorPhysics` with the terms)::

        y(t) = 2y(t-1) - y(t-2) + Ts² (w(t-1) - Σ_j p_j T_j(y(t-1), δy(t-1))) / M

    θ = [1/M, p_1/M, …]; w = u (``averaged_input=False``: the semi-implicit Euler step of the
    benchmark authors' script) or ū(t-1) = (u(t-1) + u(t-2))/2 (``averaged_input=True``: the
    exact ZOH sampling of a mass, whose zero sits at z = -1, SPEC §2.2 pitfall).
    """

    physics_law = "rigid_body"     # exported by pipeline.export.law.from_measured_physics

    input_gain_index = 0

    def __init__(self, Ts: float = 1e-3, averaged_input: bool = True, terms: ForceTerms | None = None,
                 lag: ActuatorLag | None = None):
        super().__init__(Ts, averaged_input)
        self.terms = terms if terms is not None else ForceTerms()
        self.param_names = ("inv_m",) + self.terms.param_names
        if lag is not None and not self.averaged_input:
            raise ValueError("an actuator lag (system.actuator.lag_tau) needs physics_input: averaged (the exact "
                             "sampling of the mass the lag's model extends); set physics_input: averaged")
        self.lag = lag      # None: the force is the command (pipeline.systems.actuator_lag)
        self.input_lag = None   # with_direct_input: the lag that made its input w

    def with_lag(self, lag: ActuatorLag | None) -> "RigidBodyPhysics":
        """The same physics with the force lag ``lag`` (None: none)."""
        return RigidBodyPhysics(self.Ts, self.averaged_input, self.terms, lag)

    def model_input(self, u) -> np.ndarray:
        """w of the command u: ū, or with a lag its exact sampling B/(1 - a q⁻¹) u (actuator_lag)."""
        if self.lag is None:
            return super().model_input(u)
        return self.lag.model_input(check_signal("u", u))

    def applied_input(self, w, w_end: float | None = None) -> np.ndarray:
        """The command for a model input w: (w(t) + w(t+1))/2, or with a lag its inverse (actuator_lag)."""
        if self.lag is None:
            return super().applied_input(w, w_end)
        return self.lag.applied_input(check_signal("w", w), w_end)

    @property
    def has_offset(self) -> bool:
        return "offset" in self.terms.names

    def with_direct_input(self) -> "RigidBodyPhysics":
        """The same physics on an input that is already the model input w (no averaging); ``input_lag``
        remembers the actuator lag that made w (the loop kernel and the exported law apply it to u)."""
        p = RigidBodyPhysics(self.Ts, averaged_input=False, terms=self.terms)
        p.input_lag = self.lag
        return p

    def theta_from_physical(self, physical: dict) -> np.ndarray:
        """θ from {M [kg], F_v, F_c, …}; a term the dict does not give is 0 (a datasheet that
        knows M, F_v, F_c only)."""
        m = physical.get("M")
        if m is None or not m > 0:
            raise ValueError(f"mass must be positive, got M={m!r}")
        return np.array([1.0 / m] + [float(physical.get(n, 0.0)) / m for n in self.terms.physical_names])

    def _check_theta(self, theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        p = len(self.param_names)
        if theta.shape != (p,) or not np.all(np.isfinite(theta)):
            raise ValueError(f"θ must be {p} finite numbers {self.param_names}, got {theta}")
        return theta

    def physical(self, theta) -> dict[str, float]:
        """{M [kg], then each term's parameter (F_v [N s/m], F_c [N], …)} from θ."""
        t = self._check_theta(theta)
        names = self.terms.physical_names
        if t[0] == 0.0:
            return {"M": math.inf, **{n: math.nan for n in names}}
        return {"M": 1.0 / t[0], **{n: t[1 + i] / t[0] for i, n in enumerate(names)}}

    def inverse_theta(self, theta) -> np.ndarray:
        """θ' = [M, p_1, …] of the inverse form."""
        t = self._check_theta(theta)
        if not t[0] > 0.0:
            raise ValueError(f"θ[0] = 1/M = {t[0]} is not positive: no physical mass, the model cannot "
                             "be inverted; check the identification (sign of u and y)")
        return np.concatenate([[1.0], t[1:]]) / t[0]

    def features(self, phi):
        """Ts² [w(t-1), -T_1, -T_2, …] at (y(t-1), δy(t-1)) (numpy or torch)."""
        Ts = self.Ts
        w = 0.5 * (phi[..., 2] + phi[..., 3]) if self.averaged_input else phi[..., 2]
        dy = (phi[..., 0] - phi[..., 1]) / Ts
        cols = [Ts * Ts * w] + [-Ts * Ts * c for c in self.terms.columns(phi[..., 0], dy)]
        return _stack(cols, phi)

    def inverse_features(self, phi_inv):
        """[δ²y(k+1), T_1, T_2, …] at (y(k), δy(k)) (numpy or torch): w(k) = inverse_features θ'."""
        Ts = self.Ts
        d2 = (phi_inv[..., 0] - 2.0 * phi_inv[..., 1] + phi_inv[..., 2]) / Ts ** 2
        dy = (phi_inv[..., 1] - phi_inv[..., 2]) / Ts
        return _stack([d2] + self.terms.columns(phi_inv[..., 1], dy), phi_inv)

    def inverse_force(self, theta, r) -> np.ndarray:
        """w(k) = M δ²r(k+1) + Σ p_j T_j(r(k), δr(k)), k = 0 .. N, with r(-1) = 0 and r held after the end
        (an overflow of an absurd reference is kept: the exported law flags it)."""
        p = self.inverse_theta(theta)
        r = check_signal("r", r)
        rp = np.concatenate([[0.0], r, r[-1:], r[-1:]])            # r(-1) .. r(N+1)
        phi_inv = np.stack([rp[2:], rp[1:-1], rp[:-2]], axis=1)    # k = 0 .. N
        with np.errstate(over="ignore", invalid="ignore"):
            return self.inverse_features(phi_inv) @ p              # w(0) .. w(N)

    def feedforward(self, theta, r) -> np.ndarray:
        """:meth:`inverse_force` w(0) .. w(N-1), then :meth:`applied_input` [N] (the analytic inverse, SPEC §6)."""
        w = self.inverse_force(theta, r)
        return self.applied_input(w[:-1], w_end=w[-1])

    def kernel_terms(self) -> tuple[np.ndarray, np.ndarray]:
        """The terms' kernel codes and constants (``pipeline.identify.measured_loop``)."""
        return self.terms.kernel()

    @staticmethod
    def min_samples(decimation: int = 10, trim: int = 50) -> int:
        """Shortest record :meth:`fit_filtered` accepts: the trimmed ends plus 20 decimated rows."""
        return 2 * int(trim) + 20 * max(int(decimation), 1)

    def butterworth(self, cutoff_hz: float = 50.0, order: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """The IDIM-LS prefilter: Butterworth low-pass in transfer-function form (b, a), as the EMPS
        benchmark filters.  Refused where that form is inaccurate (high order, or a cutoff far below
        Nyquist: the coefficients of a cancel to rounding): its response must match the
        second-order-sections design to 1e-6 and its poles lie inside the unit circle."""
        nyq = 0.5 / self.Ts
        if not 0.0 < cutoff_hz < nyq:
            raise ValueError(f"idim.cutoff_hz={cutoff_hz} must lie in (0, {nyq:g}) Hz (Nyquist at Ts={self.Ts} s)")
        b, a = signal.butter(int(order), cutoff_hz / nyq)
        w = np.linspace(0.0, np.pi, 512)
        h_ba = signal.freqz(b, a, w)[1]
        h_sos = signal.sosfreqz(signal.butter(int(order), cutoff_hz / nyq, output="sos"), w)[1]
        if not (np.max(np.abs(np.roots(a))) < 1.0 and np.max(np.abs(h_ba - h_sos)) <= 1e-6):
            raise ValueError(f"idim.order={order} with idim.cutoff_hz={cutoff_hz} Hz at Ts={self.Ts} s gives a "
                             f"Butterworth filter that is inaccurate in (b, a) form (response off by "
                             f"{np.max(np.abs(h_ba - h_sos)):.2g}): lower idim.order (4 is the EMPS benchmark's) "
                             "or raise idim.cutoff_hz")
        return b, a

    def filtered_regression(self, y, u, cutoff_hz: float = 50.0, order: int = 4, decimation: int = 10,
                            trim: int = 50):
        """The rows of the filtered inverse-model least squares (IDIM-LS, the EMPS benchmark's
        method): Butterworth ``filtfilt`` of q, central-difference q̇, q̈, then parallel decimation
        (``scipy.signal.decimate``, zero phase) of τ and of every regressor column; ``trim``
        samples at each end are dropped (filter transients).  Returns (X = [q̈, T_1, …], τ, q, q̇)
        on the kept rows."""
        y = check_signal("y", y)
        u = check_signal("u", u, y.shape[0])
        if y.shape[0] < self.min_samples(decimation, trim):
            raise ValueError(f"{y.shape[0]} samples are too few for the filtered least squares "
                             f"(trim={trim}, decimation={decimation}); give a longer record")
        b, a = self.butterworth(cutoff_hz, order)
        qf = signal.filtfilt(b, a, y)
        v = np.gradient(qf, self.Ts)
        acc = np.gradient(v, self.Ts)
        X = np.stack([acc] + self.terms.columns(qf, v) + [qf, v], axis=1)   # [q̈, T_1(q, q̇), …, q, q̇]
        X = _rows(X, decimation, trim)
        return X[:, :-2], self.filtered_target(u, cutoff_hz, order, decimation, trim), X[:, -2], X[:, -1]

    def filtered_target(self, u, cutoff_hz: float = 50.0, order: int = 4, decimation: int = 10,
                        trim: int = 50) -> np.ndarray:
        """The force rows of :meth:`filtered_regression`: u, or with a lag the force the mass sees
        (actuator_lag), filtered like q (zero phase, as q̈)."""
        if self.lag is not None:
            b, a = self.butterworth(cutoff_hz, order)
            u = signal.filtfilt(b, a, self.lag.model_input(u))
        return _rows(u, decimation, trim)

    def stacked_regression(self, y, u, **filt):
        """:meth:`filtered_regression` of one record (arrays) or of several (lists of arrays, one
        per recording: each filtered on its own, the rows stacked)."""
        if isinstance(y, np.ndarray) and y.ndim == 1:
            return self.filtered_regression(y, u, **filt)
        if len(y) != len(u) or not len(y):
            raise ValueError(f"give as many position records as force records (got {len(y)} and {len(u)})")
        rows = [self.filtered_regression(a, b, **filt) for a, b in zip(y, u)]
        return tuple(np.concatenate([r[i] for r in rows]) for i in range(4))

    def fit_filtered(self, y, u, cutoff_hz: float = 50.0, order: int = 4, decimation: int = 10,
                     trim: int = 50) -> np.ndarray:
        """θ by least squares on the rows of :meth:`stacked_regression` (y, u: one record's
        arrays, or lists of them, one per recording).

        Returns the forward θ ([1/M, p_1/M, …]) of the inverse fit [M, p_1, …].
        """
        X, z, _, _ = self.stacked_regression(y, u, cutoff_hz=cutoff_hz, order=order, decimation=decimation, trim=trim)
        p = solve_scaled(X, z)     # [M, p_1, …]
        if p[0] == 0:
            raise ValueError("the filtered least squares gives a zero mass: the data do not excite the "
                             "acceleration; check that y moves and that u is the force")
        return np.concatenate([[1.0], p[1:]]) / p[0]   # M < 0 comes back as is: the baseline warns

    def residual_diagnostics(self, y, u, **filt) -> dict:
        """What the configured terms leave in the force (issue 20 item 2): on the rows of the
        filtered least squares, the residual r = τ - X p and, for each term the config does *not*
        have, the share of ‖r‖² it would explain (its column made orthogonal to X, then fitted to
        r): ``viscous`` (q̇), ``coulomb`` (sign q̇), ``offset`` (1) and ``cogging`` (cos, sin of
        2πq/P at the best period P between 4 row spacings and a third of the travel, scanned on a
        log grid).  Returns {"residual_rel": ‖r‖/‖τ‖, "<term>": share, "cogging_period": P}."""
        X, z, q, v = self.stacked_regression(y, u, **filt)
        Q, _ = np.linalg.qr(X / np.maximum(np.linalg.norm(X, axis=0), 1e-300))
        res = z - Q @ (Q.T @ z)
        rr = float(res @ res)
        out = {"residual_rel": float(np.sqrt(rr) / np.linalg.norm(z))}

        def share(cols):
            C = np.stack(cols, axis=1)
            C = C - Q @ (Q.T @ C)                                  # orthogonal to the configured terms
            keep = np.linalg.norm(C, axis=0) > 1e-9 * np.sqrt(len(z))
            if not keep.any() or rr == 0:
                return 0.0
            coef, *_ = np.linalg.lstsq(C[:, keep], res, rcond=None)
            fit = C[:, keep] @ coef
            return float(fit @ fit / rr)

        have = set(self.terms.names)
        for name, col in (("viscous", v), ("coulomb", np.sign(v)), ("offset", np.ones_like(v))):
            if name not in have:
                out[name] = share([col])
        if "cogging" not in have:
            travel = float(q.max() - q.min())
            # the 99.5th percentile, not the max: the jumps between stacked records are not steps
            step = float(np.percentile(np.abs(np.diff(q)), 99.5)) if q.size > 1 else 0.0
            lo, hi = 4 * step, travel / 3
            if travel > 0 and 0 < lo < hi:
                best = (0.0, math.nan)
                for P in np.geomspace(lo, hi, 400):
                    a = 2 * np.pi * q / P
                    best = max(best, (share([np.cos(a), np.sin(a)]), float(P)))
                out["cogging"], out["cogging_period"] = best
        return out


def _rows(x, decimation: int, trim: int) -> np.ndarray:
    """Parallel decimation (``scipy.signal.decimate``, zero phase) of the regression's columns, then
    ``trim`` samples dropped at each end (filter transients)."""
    if decimation > 1:
        x = signal.decimate(x, int(decimation), axis=0, zero_phase=True)
    k = max(1, trim // max(decimation, 1))
    return x[k:-k]


#: a term the config lacks that would explain this share of the residual's energy is missing (warning)
MISSING_TERM_SHARE = 0.2


def _stack(cols, like):
    if isinstance(like, np.ndarray):
        return np.stack(cols, axis=-1)
    import torch  # lazy: saves 2.0 s of start-up (torch)
    return torch.stack(cols, dim=-1)


# --------------------------------------------------------------------------- the recording
class Recording(System):
    """A measured system (SPEC §2.5): physics model, known controller, sample time; no plant.

    Parameters
    ----------
    name : str
        System name (run tags, report).
    Ts : float
        Sample time [s]; the data's own sample time must equal it (checked before any work).
    controller : dict
        :meth:`LTIController.from_config` arguments: ``kind: cascade`` (kp, kv, gtau, v_sat) or
        ``kind: lti`` (num, den, num_r, gtau, v_sat, delay).
    physics_input : {'averaged', 'direct'}
        Input of the one-step physics model: ū(t-1) (exact ZOH, default) or u(t-1).
    force_terms : dict or None
        :class:`pipeline.systems.force_terms.ForceTerms` arguments: ``terms`` (the force terms of
        ``M q̈ = τ - Σ``: viscous, coulomb, stribeck, offset, cogging) and their shape constants
        (coulomb_width, stribeck_velocity, cogging_period, cogging_harmonics).  Default: EMPS's
        viscous, Coulomb (sign) and offset.
    disturbance : str or None
        Column of the data holding a measured disturbance [V] added after the saturation
        (EMPS test file: ``pulses_N``), zero when absent.
    published : dict or None
        Published physical parameters {M, F_v, F_c, OF, …} (the report compares with them; a term
        it does not give is 0).
    idim : dict or None
        Settings of the filtered inverse-model least squares (:meth:`RigidBodyPhysics.fit_filtered`:
        cutoff_hz, order, decimation, trim).
    actuator : dict or None
        ``lag_tau``: the drive's force lag τ [s] (τ Ḟ + F = u, :mod:`pipeline.systems.actuator_lag`),
        ``'auto'`` (identified by :meth:`fit_physics` from the training records) or None (no lag).
    """

    measured = True

    def __init__(self, name: str = Params.name, Ts: float = Params.Ts, controller: dict | None = None,
                 physics_input: str = Params.physics_input, force_terms: dict | None = None,
                 disturbance: str | None = Params.disturbance,
                 published: dict | None = Params.published, idim: dict | None = None,
                 actuator: dict | None = None):
        if not (isinstance(Ts, (int, float)) and math.isfinite(Ts) and Ts > 0):
            raise ValueError(f"Ts={Ts!r} must be a positive sample time in s")
        if physics_input not in ("averaged", "direct"):
            raise ValueError(f"physics_input={physics_input!r}; use 'averaged' (exact ZOH) or 'direct'")
        if controller is None:
            raise ValueError("a measured system needs its controller (system.controller: kind cascade with kp, "
                             "kv, gtau, or kind lti with num, den)")
        self.name, self.Ts = str(name), float(Ts)
        self.ctrl = LTIController.from_config(dict(controller), self.Ts)
        self.disturbance = disturbance or None
        self.published = dict(published) if published else None
        self.idim = dict(idim or {})
        unknown = set(self.idim) - {"cutoff_hz", "order", "decimation", "trim"}
        if unknown:
            raise ValueError(f"unknown idim key(s) {sorted(unknown)}; allowed: cutoff_hz, order, decimation, trim")
        ft = dict(force_terms or {})
        terms = ForceTerms(tuple(ft.pop("terms", ForceTerms.names)), **ft)
        self._physics = RigidBodyPhysics(self.Ts, averaged_input=physics_input == "averaged", terms=terms)
        act = dict(actuator or {})
        unknown = set(act) - {"lag_tau"}
        if unknown:
            raise ValueError(f"unknown actuator key(s) {sorted(unknown)}; allowed: lag_tau")
        self.lag_tau = act.get("lag_tau")          # None | τ [s] | 'auto' (set by fit_physics)
        if self.lag_tau is not None:
            if self.lag_tau != "auto":
                self.use_lag(self.lag_tau)
            elif physics_input != "averaged":
                raise ValueError("actuator.lag_tau: auto needs physics_input: averaged (the exact sampling of the "
                                 "mass the lag's model extends); set physics_input: averaged")
        self._physics.butterworth(**{k: self.idim[k] for k in ("cutoff_hz", "order") if k in self.idim})

    @property
    def physics(self) -> RigidBodyPhysics:
        return self._physics

    def simulate(self, r, u_ff=None, du=None, v=None):
        raise RuntimeError(f"system '{self.name}' is a recording of a real machine: it has no true plant to "
                           "simulate. Evaluate the identified model inside the known controller "
                           "(evaluate references of kind 'measured') instead")

    def noise(self, n, rng):
        raise RuntimeError(f"system '{self.name}' is measured: its noise is in the data, not in a model")

    def published_theta(self) -> np.ndarray | None:
        """θ of the published physical parameters (None if not given)."""
        if not self.published:
            return None
        return self.physics.theta_from_physical(self.published)

    def min_samples(self) -> int:
        """Shortest training record the physics baseline (``idim`` settings) can use."""
        return self.physics.min_samples(**{k: v for k, v in self.idim.items() if k in ("decimation", "trim")})

    def use_lag(self, tau: float | None) -> None:
        """Model the force lag τ [s] (None: none) from now on (physics, replay, inverse, export)."""
        self._physics = self._physics.with_lag(None if tau is None else ActuatorLag(float(tau), self.Ts))

    def identify_lag(self, y, u) -> dict:
        """τ of the force lag from the training records (lists), with its standard uncertainty
        (:func:`pipeline.systems.actuator_lag.identify_tau`); the physics uses it from then on."""
        ys, us = ([y], [u]) if isinstance(y, np.ndarray) and y.ndim == 1 else (list(y), list(u))
        out = identify_tau(self._physics.with_lag(None), ys, us, **self.idim)
        self.use_lag(out["tau"])
        return out

    def fit_physics(self, y, u) -> np.ndarray:
        """θ of the physics model from one record (arrays) or several (lists), by the filtered
        inverse-model least squares (with ``lag_tau: auto``, τ identified first: :meth:`identify_lag`)."""
        if self.lag_tau == "auto":
            self.lag_fit = self.identify_lag(y, u)
        return self.physics.fit_filtered(y, u, **self.idim)

    def missing_terms(self, y, u) -> tuple[dict, list[str]]:
        """(:meth:`RigidBodyPhysics.residual_diagnostics` on this record, a sentence per force term
        the config lacks that would explain ≥ MISSING_TERM_SHARE of the residual's energy)."""
        diag = self.physics.residual_diagnostics(y, u, **self.idim)
        hints = {"viscous": "add 'viscous' to system.force_terms.terms",
                 "coulomb": "add 'coulomb' (sign, or smooth with coulomb_width)",
                 "offset": "add 'offset' (gravity, cable force)",
                 "cogging": f"add 'cogging' with cogging_period ≈ {diag.get('cogging_period', math.nan):.4g} m"}
        found = [f"{k} would explain {100 * diag[k]:.0f} % of the residual force: {hints[k]}"
                 for k in hints if diag.get(k, 0.0) >= MISSING_TERM_SHARE]
        return diag, found

    def check_reference(self, r) -> None:
        check_signal("r", r)
