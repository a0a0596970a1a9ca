"""Measured systems: a recorded experiment, not a simulator (SPEC §2.5, DESIGN "Measured systems").

A :class:`Recording` has what a user knows about a real machine, and nothing more:

- the **physics model** of a prismatic rigid-body axis, :class:`RigidBodyPhysics`::

      M q̈ = τ - F_v q̇ - F_c sign(q̇) - OF                      (EMPS reference model)

  linear in θ = [1/M, F_v/M, F_c/M, OF/M] in its one-step (NARX) form;
- the **known controller** as config, :class:`CascadeController` (the EMPS position/velocity
  cascade ``vir = sat±v_sat(kv (kp (r - q) - q̇f))``, force ``τ = gtau · vir``);
- the sample time (from the data, checked against the config) and the units of the signals.

It has no true plant: :meth:`Recording.simulate` refuses, so no stage can score a model of
measured data on a simulator by accident.  Evaluation simulates the *identified* model inside
the known controller (``pipeline.identify.measured_loop``) and compares with the recording.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal

from pipeline.systems.base import System, check_signal
from pipeline.systems.linear_motor import LinearMotorPhysics


# --------------------------------------------------------------------------- physics model
class RigidBodyPhysics(LinearMotorPhysics):
    """Rigid body with viscous, Coulomb friction and a constant force offset (EMPS, SPEC §2.5).

    One-step form (the [B1] (32) rigid body of :class:`LinearMotorPhysics` plus the offset)::

        y(t) = 2y(t-1) - y(t-2) + Ts² (w(t-1) - F_v δy(t-1) - F_c sign(δy(t-1)) - OF) / M

    θ = [1/M, F_v/M, F_c/M, OF/M]; w = u (``averaged_input=False``: the semi-implicit Euler step
    of the benchmark authors' script) or ū(t-1) = (u(t-1) + u(t-2))/2 (``averaged_input=True``:
    the exact ZOH sampling of a mass, whose zero sits at z = -1, SPEC §2.2 pitfall).
    ``offset=False`` drops OF (θ has 3 entries, as the linear motor).
    """

    input_gain_index = 0

    def __init__(self, Ts: float = 1e-3, averaged_input: bool = True, offset: bool = True):
        super().__init__(Ts, averaged_input)
        self.has_offset = bool(offset)
        self.param_names = ("inv_m", "fv_over_m", "fc_over_m") + (("of_over_m",) if offset else ())

    def with_direct_input(self) -> "RigidBodyPhysics":
        """The same physics on an input that is already the model input w (no averaging)."""
        return RigidBodyPhysics(self.Ts, averaged_input=False, offset=self.has_offset)

    @staticmethod
    def theta_from_physical(m: float, f_v: float, f_c: float, of: float | None = 0.0) -> np.ndarray:
        """θ from M [kg], F_v [N s/m], F_c [N], OF [N] (``of=None``: no offset entry)."""
        if not m > 0:
            raise ValueError(f"mass must be positive, got M={m!r}")
        th = [1.0 / m, f_v / m, f_c / m] + ([] if of is None else [of / m])
        return np.array(th)

    def _check_theta(self, theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        p = len(self.param_names)
        if theta.shape != (p,) or not np.all(np.isfinite(theta)):
            raise ValueError(f"θ must be {p} finite numbers {self.param_names}, got {theta}")
        return theta

    def physical(self, theta) -> dict[str, float]:
        """{M [kg], F_v [N s/m], F_c [N], OF [N]} from θ."""
        t = self._check_theta(theta)
        if t[0] == 0.0:
            return {"M": math.inf, "F_v": math.nan, "F_c": math.nan, **({"OF": math.nan} if self.has_offset else {})}
        out = {"M": 1.0 / t[0], "F_v": t[1] / t[0], "F_c": t[2] / t[0]}
        if self.has_offset:
            out["OF"] = t[3] / t[0]
        return out

    def inverse_theta(self, theta) -> np.ndarray:
        """θ' = [M, F_v, F_c(, OF)] of the inverse form."""
        t = self._check_theta(theta)
        if not t[0] > 0.0:
            raise ValueError(f"θ[0] = 1/M = {t[0]} is not positive: no physical mass, the model cannot "
                             "be inverted; check the identification (sign of u and y)")
        return np.concatenate([[1.0], t[1:]]) / t[0]

    def features(self, phi):
        cols = super().features(phi)
        if not self.has_offset:
            return cols
        ones = -self.Ts ** 2 * (phi[..., 0] * 0.0 + 1.0)
        if isinstance(cols, np.ndarray):
            return np.concatenate([cols, ones[..., None]], axis=-1)
        import torch
        return torch.cat([cols, ones.unsqueeze(-1)], dim=-1)

    def inverse_features(self, phi_inv):
        cols = super().inverse_features(phi_inv)
        if not self.has_offset:
            return cols
        ones = phi_inv[..., 0] * 0.0 + 1.0
        if isinstance(cols, np.ndarray):
            return np.concatenate([cols, ones[..., None]], axis=-1)
        import torch
        return torch.cat([cols, ones.unsqueeze(-1)], dim=-1)

    def feedforward(self, theta, r) -> np.ndarray:
        """w(k) = M δ²r(k+1) + F_v δr(k) + F_c sign(δr(k)) + OF, then :meth:`applied_input` [N]."""
        p = self.inverse_theta(theta)
        of = p[3] if self.has_offset else 0.0
        base = LinearMotorPhysics(self.Ts, self.averaged_input)
        return base.feedforward(np.array([1.0, p[1], p[2]]) / p[0], r) + of

    @staticmethod
    def min_samples(decimation: int = 10, trim: int = 50) -> int:
        """Shortest record :meth:`fit_filtered` accepts: the trimmed ends plus 20 decimated rows."""
        return 2 * int(trim) + 20 * max(int(decimation), 1)

    def fit_filtered(self, y, u, cutoff_hz: float = 50.0, order: int = 4, decimation: int = 10,
                     trim: int = 50) -> np.ndarray:
        """θ by least squares on the inverse model with zero-phase filtered derivatives (IDIM-LS,
        the EMPS benchmark's method): Butterworth ``filtfilt`` of q, central-difference q̇, q̈,
        then parallel decimation (``scipy.signal.decimate``, zero phase) of τ and of every
        regressor column; ``trim`` samples at each end are dropped (filter transients).

        Returns the forward θ ([1/M, F_v/M, F_c/M(, OF/M)]) of the inverse fit [M, F_v, F_c, OF].
        """
        y = check_signal("y", y)
        u = check_signal("u", u, y.shape[0])
        nyq = 0.5 / self.Ts
        if not 0.0 < cutoff_hz < nyq:
            raise ValueError(f"cutoff_hz={cutoff_hz} must lie in (0, {nyq}) Hz (Nyquist at Ts={self.Ts} s)")
        if y.shape[0] < self.min_samples(decimation, trim):
            raise ValueError(f"{y.shape[0]} samples are too few for the filtered least squares "
                             f"(trim={trim}, decimation={decimation}); give a longer record")
        b, a = signal.butter(int(order), cutoff_hz / nyq)
        qf = signal.filtfilt(b, a, y)
        v = np.gradient(qf, self.Ts)
        acc = np.gradient(v, self.Ts)
        X = np.stack([acc, v, np.sign(v)] + ([np.ones_like(v)] if self.has_offset else []), axis=1)
        z = u
        if decimation > 1:
            X = signal.decimate(X, int(decimation), axis=0, zero_phase=True)
            z = signal.decimate(u, int(decimation), zero_phase=True)
        k = max(1, trim // max(decimation, 1))
        from pipeline.identify.least_squares import solve_scaled
        p = solve_scaled(X[k:-k], z[k:-k])     # [M, F_v, F_c(, OF)]
        if p[0] == 0:
            raise ValueError("the filtered least squares gives a zero mass: the data do not excite the "
                             "acceleration; check that y moves and that u is the force")
        return np.concatenate([[1.0], p[1:]]) / p[0]   # M < 0 comes back as is: the baseline warns


# --------------------------------------------------------------------------- controller
@dataclass(frozen=True)
class CascadeController:
    """The known position/velocity cascade of a measured axis (EMPS README)::

        v(k)   = kv (kp (r(k) - q(k)) - q̇f(k)),    q̇f(k) = (q(k) - q(k-2)) / (2 Ts)
        vir(k) = sat±v_sat(v(k)) (+ measured disturbance d(k) after the saturation)
        τ(k)   = gtau · vir(k)   [N]

    q̇f is the backward difference of the two-sample-averaged position.  No computational
    delay: vir(k) uses q(k) of the same sample (SPEC §0; checked on the data by
    :meth:`residual`).
    """

    kp: float           # position gain [1/s]
    kv: float           # velocity gain [V/(m/s)]
    gtau: float         # force per volt [N/V]
    v_sat: float = 10.0  # controller output limit [V]

    def __post_init__(self):
        for k in ("kp", "kv", "gtau", "v_sat"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"controller.{k}={v!r} must be a finite positive number")

    def law(self, r, q, Ts: float, saturate: bool = True) -> np.ndarray:
        """Controller output vir [V] for position samples q (past at q[0]), vectorised."""
        q = np.asarray(q, dtype=np.float64)
        q2 = np.concatenate([np.full(2, q[0]), q[:-2]])
        v = self.kv * (self.kp * (np.asarray(r) - q) - (q - q2) / (2.0 * Ts))
        return np.clip(v, -self.v_sat, self.v_sat) if saturate else v

    def force_on_reference(self, r, Ts: float) -> np.ndarray:
        """τ [N] of the feedback law when the axis follows r exactly (q = r): -gtau kv ṙf, before
        the limit.  The velocity loop feeds back q̇, not the error, so a force feedforward (added to
        the command before the drive's limit) that makes q = r is the model's inverse force *minus*
        this: it cancels the velocity feedback on the reference."""
        return self.gtau * self.law(r, r, Ts, saturate=False)

    def residual(self, r, q, u, d, Ts: float) -> float:
        """rms of (measured force - law on the measured position) over rms force: a check that
        the recording is this loop (signs, units, gains, sample time) before any fitting."""
        vir = np.asarray(u) / self.gtau
        res = vir - self.law(r, q, Ts) - np.asarray(d)
        return float(np.sqrt(np.mean(res[2:] ** 2)) / max(np.sqrt(np.mean(vir ** 2)), 1e-300))


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
        :class:`CascadeController` arguments (kp, kv, gtau, v_sat).
    physics_input : {'averaged', 'direct'}
        Input of the one-step physics model: ū(t-1) (exact ZOH, default) or u(t-1).
    offset : bool
        Whether the physics has the constant force offset OF.
    disturbance : str or None
        Column of the data holding a measured disturbance [V] added after the saturation
        (EMPS test file: ``pulses_N``), zero when absent.
    published : dict or None
        Published physical parameters {M, F_v, F_c, OF} (the report compares with them).
    idim : dict or None
        Settings of the filtered inverse-model least squares (:meth:`RigidBodyPhysics.fit_filtered`:
        cutoff_hz, order, decimation, trim).
    """

    def __init__(self, name: str = "measured", Ts: float = 1e-3, controller: dict | None = None,
                 physics_input: str = "averaged", offset: bool = True, disturbance: str | None = None,
                 published: dict | None = None, idim: dict | None = None):
        if not (isinstance(Ts, (int, float)) and math.isfinite(Ts) and Ts > 0):
            raise ValueError(f"Ts={Ts!r} must be a positive sample time in s")
        if physics_input not in ("averaged", "direct"):
            raise ValueError(f"physics_input={physics_input!r}; use 'averaged' (exact ZOH) or 'direct'")
        if controller is None:
            raise ValueError("a measured system needs its controller (system.controller: kp, kv, gtau)")
        self.name, self.Ts = str(name), float(Ts)
        self.ctrl = CascadeController(**dict(controller))
        self.disturbance = disturbance or None
        self.published = dict(published) if published else None
        self.idim = dict(idim or {})
        unknown = set(self.idim) - {"cutoff_hz", "order", "decimation", "trim"}
        if unknown:
            raise ValueError(f"unknown idim key(s) {sorted(unknown)}; allowed: cutoff_hz, order, decimation, trim")
        self._physics = RigidBodyPhysics(self.Ts, averaged_input=physics_input == "averaged", offset=offset)

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
        p = self.published
        return self.physics.theta_from_physical(p["M"], p["F_v"], p["F_c"],
                                                p.get("OF", 0.0) if self.physics.has_offset else None)

    def min_samples(self) -> int:
        """Shortest training record the physics baseline (``idim`` settings) can use."""
        return self.physics.min_samples(**{k: v for k, v in self.idim.items() if k in ("decimation", "trim")})

    def fit_physics(self, y, u) -> np.ndarray:
        """θ of the physics model from one record, by the filtered inverse-model least squares."""
        return self.physics.fit_filtered(y, u, **self.idim)

    def check_reference(self, r) -> None:
        check_signal("r", r)
