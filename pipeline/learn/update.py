"""The update laws of a learning campaign (issue 50 item 2): the next trial's feedforward from the last
trial's recorded error.

**The loop's learning path.** On the measured system's loop (README "Your own machine's data")
``A v = B_r r - B_y y``, ``u(k) = gtau sat(v + u_ff/gtau)(k - D)``, the feedforward u_ff [N] reaches the
position through the process sensitivity

    G = P' / (1 + gtau C_y P'),   P' = z^-D P_zoh,   P(s) = 1 / (M s² + F_v s + K)

(:class:`LoopModel`): the linear part of the identified physics (mass, viscous friction, a position spring)
with the controller's measurement path C_y = B_y/A. A smooth Coulomb force F_c tanh(q̇/w) of the model is
taken along the trajectories instead (:meth:`Update.along`): near standstill its slope F_c/w is a damping
hundreds of times the viscous one, which turns P from a mass (-180°) into a damper (-90°) for a while, and
an LTI L then pushes a stop's creep later and later in every trial (measured on tests/heldout_axis.py: the
error stalls at 0.7 µm MAE and grows). Stribeck and cogging forces are repeated disturbances the learning
removes; their effect on G is in the uncertainty (:mod:`pipeline.learn.safety`).

**What is learned.** With u_ff = φ - gtau (C_r - C_y) r the command is c = C_y e + φ/gtau: the loop is error
feedback driven by the force φ, and G is the map φ → y as well. The controller term is known exactly (the
config), so the laws learn φ, the force the plant needs, and Q filters φ only: a D-term on y makes
(C_r - C_y) r kN-large and rich in high frequencies, which Q must not cut.

**Model-based ILC** (``law: model_ilc``; Bristow, Tharayil, Alleyne 2006, IEEE CSM 26(3), eq. (7))::

    φ_{j+1} = Q (φ_j + α L e_j),   L = |Q| G^-1,   G^-1 = z^D / P_zoh + gtau C_y

Q is a zero-phase Butterworth low-pass (:func:`scipy.signal.sosfiltfilt`, ``|Q| = |H|²``, cutoff
``q_cutoff_hz``). G^-1 grows like M ω² and has a pole at z = -1, so L carries Q's magnitude once more
before it makes a signal; L is non-causal, and the recording is offline: it is applied in the frequency
domain (:func:`apply_response`, zero-padded FFT). The learning gain α ≤ 1 weighs each trial's correction.

**Norm-optimal ILC** (``law: norm_optimal``; [B2] (22)-(23), :class:`pipeline.invert.ilc.MatrixFreeUpdate`
on G as a state-space model)::

    Δφ = argmin ‖e_j - G Δφ‖² + w ‖φ_j + Δφ‖² + w_Δ ‖Δφ‖²,   φ_{j+1} = Q (φ_j + α Δφ)

with w = ``w_f`` max|G|², w_Δ = ``w_df`` max|G|² (max|G| over frequency ≈ σ_max of the lifted G).

For both laws the learned part of one trial is ``α L G`` in the frequency domain (:meth:`Update.learning`):
L G = |Q| for model-based ILC, |G|² / (|G|² + w + w_Δ) for norm-optimal ILC (the long-trial limit of the
lifted solution); the convergence check of :mod:`pipeline.learn.safety` uses it.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import fft, signal

from pipeline.invert.ilc import MatrixFreeUpdate, process_sensitivity
from pipeline.systems.controller import LTIController

__all__ = ["LoopModel", "Update", "ModelILC", "NormOptimalILC", "make_update", "apply_response", "applied_disturbance",
           "LAWS"]

LAWS = ("model_ilc", "norm_optimal")


@dataclass(frozen=True, eq=False)
class LoopModel:
    """The identified loop: linear physics (M [kg], F_v [N s/m], K [N/m]) under the controller ``ctrl``."""

    Ts: float
    M: float
    F_v: float
    K: float
    ctrl: LTIController
    F_c: float = 0.0              # smooth Coulomb friction F_c tanh(q̇/w) [N] ...
    coulomb_width: float = 0.0    # ... its width w [m/s] (0: not in the linearisation)

    def __post_init__(self):
        if not (self.M > 0 and self.F_v >= 0 and self.K >= 0 and self.Ts > 0 and self.F_c >= 0
                and self.coulomb_width >= 0):
            raise ValueError(f"the learning model needs M > 0, F_v, K, F_c, coulomb_width >= 0 and Ts > 0; got "
                             f"M={self.M}, F_v={self.F_v}, K={self.K}, F_c={self.F_c}, "
                             f"coulomb_width={self.coulomb_width}, Ts={self.Ts}")

    def coulomb(self, x: np.ndarray) -> np.ndarray:
        """F_c tanh(ẋ/w) [N] with ẋ(k) = (x(k+D+1) - x(k+D))/Ts: the velocity over the ZOH interval the force of
        sample k acts on (D: the controller's delay); zero without a width."""
        if self.F_c == 0.0 or self.coulomb_width == 0.0:
            return np.zeros(np.size(x))
        D = self.ctrl.delay
        x = np.asarray(x, np.float64)
        v = np.diff(np.concatenate([x, np.full(D + 1, x[-1])]))[D:D + x.size] / self.Ts
        return self.F_c * np.tanh(v / self.coulomb_width)

    def _plant_zpk(self):
        """P_zoh's zeros, poles, gain (exact ZOH of 1/(M s² + F_v s + K) in state space)."""
        A = np.array([[0.0, 1.0], [-self.K / self.M, -self.F_v / self.M]])
        Ad, Bd, Cd, Dd, _ = signal.cont2discrete((A, np.array([[0.0], [1.0 / self.M]]), np.array([[1.0, 0.0]]),
                                                   np.zeros((1, 1))), self.Ts)
        with warnings.catch_warnings():   # the leading numerator coefficient is 0 (strictly proper): not an issue
            warnings.simplefilter("ignore", signal.BadCoefficients)
            return signal.ss2zpk(Ad, Bd, Cd, Dd)

    def plant(self, w) -> np.ndarray:
        """P'(e^{jωTs}) = z^-D P_zoh [m/N] at ω [rad/s] (factored: the poles near z = 1 keep their digits)."""
        z = np.exp(1j * np.asarray(w, dtype=np.float64) * self.Ts)
        zeros, poles, k = self._plant_zpk()
        num = k * np.prod([z - q for q in np.atleast_1d(zeros)], axis=0) if np.size(zeros) else k * np.ones_like(z)
        den = np.prod([z - p for p in poles], axis=0)
        return num / den * z ** (-self.ctrl.delay)

    def plant_inverse(self, w) -> np.ndarray:
        """1/P' [N/m]; 0 where P' = 0 (the ZOH zero at z = -1 of a pure double integrator)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            out = 1.0 / self.plant(w)
        return np.where(np.isfinite(out), out, 0.0)

    def controller(self, w) -> np.ndarray:
        """gtau C_y(e^{jωTs}) [N/m]."""
        zi = np.exp(-1j * np.asarray(w, dtype=np.float64) * self.Ts)
        return self.ctrl.gtau * np.polyval(self.ctrl.b_y[::-1], zi) / np.polyval(self.ctrl.a[::-1], zi)

    def response(self, w) -> np.ndarray:
        """G(e^{jωTs}) = P' / (1 + gtau C_y P') [m/N]: u_ff → y."""
        p = self.plant(w)
        return p / (1.0 + self.controller(w) * p)

    def controller_from_rest(self, e: np.ndarray) -> np.ndarray:
        """gtau C_y e [N], causal from rest (lifted: lower triangular Toeplitz; the loop at rest before k = 0 saw
        e = 0): what the feedback made of the error."""
        return self.ctrl.gtau * signal.lfilter(self.ctrl.b_y, self.ctrl.a, np.asarray(e, np.float64))

    def state_space(self):
        """G as a discrete python-control state-space model (norm-optimal ILC's filters)."""
        import control  # lazy: saves 1.9 s of start-up (python-control)
        zeros, poles, k = self._plant_zpk()
        p = control.zpk(np.atleast_1d(zeros), poles, k, self.Ts)
        if self.ctrl.delay:
            p = p * control.tf([1.0], [1.0] + [0.0] * self.ctrl.delay, self.Ts)
        c = self.ctrl.transfer_functions(self.Ts)[1] * self.ctrl.gtau
        return process_sensitivity(p, c)


def applied_disturbance(ctrl: LTIController, u_ff: np.ndarray) -> np.ndarray:
    """The applied u_ff as the measured format's disturbance column d [controller units]: u = gtau (sat(v + u_ff/gtau)
    (k - D)) is u = gtau (v(k - D) + d) with d(k) = u_ff(k - D)/gtau off the limit (u_ff(0) before the trial)."""
    u_ff = np.asarray(u_ff, np.float64)
    return np.concatenate([np.full(ctrl.delay, u_ff[0]), u_ff[:u_ff.size - ctrl.delay]]) / ctrl.gtau


def apply_response(x: np.ndarray, response, Ts: float, pad: int) -> np.ndarray:
    """Y(ω) = H(ω) X(ω) for a non-causal H [its values at ω, rad/s], on x zero-padded by ``pad`` samples
    (circular: what H moves before sample 0 wraps into the padding, not into the signal)."""
    n = fft.next_fast_len(x.size + pad)
    w = 2 * math.pi * fft.rfftfreq(n, Ts)
    return fft.irfft(fft.rfft(x, n) * response(w), n)[:x.size]


class Update:
    """f_{j+1} = Q(f_j + α ·learned(e_j, f_j)) with a zero-phase Butterworth Q (module docstring)."""

    law = ""

    def __init__(self, model: LoopModel, q_cutoff_hz: float, q_order: int = 2, pad_seconds: float = 0.5):
        nyq = 0.5 / model.Ts
        if not 0 < q_cutoff_hz < nyq:
            raise ValueError(f"learn.q_cutoff_hz={q_cutoff_hz} must lie in (0, {nyq:g}) Hz (the Nyquist frequency "
                             f"at Ts = {model.Ts:g} s); e.g. 2-3x the loop's bandwidth")
        self.model = model
        self.q_sos = signal.butter(int(q_order), q_cutoff_hz, fs=1.0 / model.Ts, output="sos")
        self.pad = int(round(pad_seconds / model.Ts))
        self.reference = None

    def along(self, r) -> "Update":
        """Take the model's Coulomb force along the trajectories: its difference between the reference r and the
        recorded y joins L e (model-based ILC; module docstring)."""
        self.reference = np.asarray(r, np.float64) if self.model.F_c and self.model.coulomb_width else None
        return self

    def q(self, w) -> np.ndarray:
        """|Q(e^{jωTs})| = |H|² (filtfilt: the filter forwards and backwards, no phase)."""
        return np.abs(signal.sosfreqz(self.q_sos, worN=np.asarray(w) * self.model.Ts)[1]) ** 2

    def learning(self, w) -> np.ndarray:
        """L G at ω (module docstring)."""
        raise NotImplementedError

    def correction(self, e: np.ndarray, f: np.ndarray) -> np.ndarray:
        """The learned change before Q and α [N]."""
        raise NotImplementedError

    def next(self, e, f, gain: float, offset=None) -> np.ndarray:
        """f_{j+1} [N] from the error e_j [m] of the feedforward f_j [N]. ``offset``: the controller term
        (C_r - C_y) r gtau (:meth:`LTIController.reference_force`); Q then acts on the force f + offset the
        plant needs, never on the controller's own (exactly known) reference path (module docstring)."""
        e, f = np.asarray(e, np.float64), np.asarray(f, np.float64)
        k = 0.0 if offset is None else np.asarray(offset, np.float64)
        phi = f + k
        return signal.sosfiltfilt(self.q_sos, phi + gain * self.correction(e, phi)) - k


class ModelILC(Update):
    """L = G^-1 (module docstring); its Nyquist-side growth cut by |Q| before it is a signal."""

    law = "model_ilc"

    def learning(self, w):
        return self.q(w)

    def correction(self, e, f):
        inv_p = apply_response(e, lambda w: self.q(w) * self.model.plant_inverse(w), self.model.Ts, self.pad)
        fb = self.model.controller_from_rest(e)
        if self.reference is not None:   # the Coulomb force's difference F_c (tanh(ṙ/w) - tanh(ẏ/w)), y smoothed by Q
            y = signal.sosfiltfilt(self.q_sos, self.reference - e)
            fb = fb + self.model.coulomb(self.reference) - self.model.coulomb(y)
        return inv_p + signal.sosfiltfilt(self.q_sos, fb)


class NormOptimalILC(Update):
    """[B2]'s norm-optimal step through :class:`pipeline.invert.ilc.MatrixFreeUpdate` (module docstring)."""

    law = "norm_optimal"

    def __init__(self, model, q_cutoff_hz, q_order=2, pad_seconds=0.5, w_f: float = 0.0, w_df: float = 1e-4,
                 maxiter: int = 300, rtol: float = 1e-8):
        super().__init__(model, q_cutoff_hz, q_order, pad_seconds)
        w = np.linspace(0.0, math.pi / model.Ts, 20001)[1:]
        self.g2 = float(np.max(np.abs(model.response(w)))) ** 2
        self.w, self.w_delta = w_f * self.g2, w_df * self.g2
        if self.w + self.w_delta <= 0:
            raise ValueError("learn.w_f + learn.w_df must be > 0 for norm-optimal ILC (the model has a delay: no "
                             "exact inverse); e.g. learn.w_df=1e-4")
        self.maxiter, self.rtol = int(maxiter), float(rtol)
        self._solver: MatrixFreeUpdate | None = None

    def learning(self, w):
        g2 = np.abs(self.model.response(w)) ** 2
        return g2 / (g2 + self.w + self.w_delta)

    def correction(self, e, f):
        if self._solver is None or self._solver.N != e.size:
            self._solver = MatrixFreeUpdate(self.model.state_space(), e.size, w=self.w, w_delta=self.w_delta,
                                            preconditioner="none", rtol=self.rtol, maxiter=self.maxiter)
        return self._solver.step(e, f)


def make_update(model: LoopModel, law: str, q_cutoff_hz: float, q_order: int = 2, **weights) -> Update:
    """The update law named ``law`` (:data:`LAWS`)."""
    if law == "model_ilc":
        return ModelILC(model, q_cutoff_hz, q_order)
    if law == "norm_optimal":
        return NormOptimalILC(model, q_cutoff_hz, q_order, **weights)
    raise ValueError(f"learn.law={law!r}; choose one of {LAWS}")
