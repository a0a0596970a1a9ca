"""The update laws of a learning campaign (issue 50 item 2): the next trial's feedforward from the last
trial's recorded error.

**The loop's learning path.** On the measured system's loop (README "Your own machine's data")
``A v = B_r r - B_y y``, ``u(k) = gtau sat(v + u_ff/gtau)(k - D)``, the feedforward u_ff [N] reaches the
position through the process sensitivity

    G = P' / (1 + gtau C_y P'),   P' = z^-D P_zoh,   P(s) = 1 / ((τ s + 1)(M s² + F_v s + K))

(:class:`LoopModel`): the linear part of the identified physics (mass, viscous friction, a position spring; the
drive's current-loop lag τ where the physics has one, else τ = 0) with the controller's measurement path
C_y = B_y/A. A smooth Coulomb force F_c tanh(q̇/w) of the model is
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

**Norm-optimal ILC** (``law: norm_optimal``; [B2] (22)-(23); Amann, Owens, Rogers 1996)::

    Δφ = argmin ‖ê_j - G Δφ‖² + w ‖φ_j + Δφ‖² + w_Δ ‖Δφ‖²,   φ_{j+1} = Q (φ_j + α Δφ)
    ê_j = e_j + G δd,   δd = F_c (tanh(ṙ/w) - tanh(ẏ_j/w))

with w = ``w_f`` max|G|², w_Δ = ``w_df`` max|G|² (max|G| over frequency ≈ σ_max of the lifted G). ê_j is the
error the model predicts for the next trial: the Coulomb force is taken along the trajectories as in model-based
ILC (the same δd, y_j smoothed by Q; the next trial is to run along r), so e_{j+1} ≈ e_j - G (Δφ - δd); with
w = w_Δ = 0 the minimiser is model-based ILC's G^-1 e_j + δd. The minimiser is exact:
(GᵀG + (w + w_Δ) I) Δφ = Gᵀ ê_j - w φ_j solved as the finite-horizon LQ tracking problem of G's state space
(:meth:`LoopModel.realisation`; a backward Riccati and adjoint sweep and a forward sweep, O(N),
:class:`pipeline.invert.ilc_lq.RiccatiUpdate`), its residual on the normal equations measured and refined to
``rtol`` (at most ``max_sweeps``; :attr:`NormOptimalILC.solve` says converged or cap, the campaign logs it).

Which weight: with an integrator in C_y, G(1) = 0 (the loop rejects a constant force), so the DC part of φ never
shows in e and only the weights set it: w_Δ keeps φ_j's, w pulls it to 0. A 2-DOF controller's first φ_0 =
gtau (C_r - C_y) r is kN-large with a DC part (a set-point weight b gives -(1 - b) k_p (r - r(0))); under w_Δ alone
it stays in φ_1, and u_ff_1 = φ_1 - gtau (C_r - C_y) r carries it where r rests (measured on the held-out axis
with w_df = 1e-4: -1000 N at rest, trial 1 at the ±60 N limit from sample 1; with w_f = w_df = 1e-5 still 76
samples there). Hence the defaults w_f = 1e-5, w_df = 0: φ, the force the plant needs, is small, and the fixed
point's bias (Gᵀ ê∞ = w φ∞) stays under that axis's noise. Started from the model's own feedforward (``--u-ff0``)
φ_0 is the model's force and w_Δ alone is safe (held-out axis, w_df = 1e-4: at the floor by trial 3). For an
error-feedback controller (C_r = C_y: φ_0 = 0) a w_df = 1e-4 on top damps the noise at the fixed point
(tests/test_learn.py's machine: the stop at 1.28x the noise floor; 1.36x and rollbacks on noise with the defaults).

**IL-FHOFC** (``law: il_fhofc``; [B2] (22), :func:`pipeline.invert.fhofc.il_fhofc_step`, the method of
``invert=il_fhofc`` fed by the recording instead of a simulator)::

    R_{j+1} = Ŷ_j + α e_j,   Ŷ_j = Φ̂(R, φ_j),   φ_{j+1} = Q argmin_φ ‖R_{j+1} - Φ̂(R, φ)‖² + ‖γ Δ φ‖²

Φ̂ is [B2]'s closed-loop model: the ARX model (30) of P' (:meth:`LoopModel.arx`; with a Coulomb width a PGNN,
the force in its tanh layer) in the loop of gtau C_y (:meth:`LoopModel.loop_controller`), or any
:class:`ArxPGNN` given; FHOFC ([B2] (17)) by :func:`pipeline.invert.fhofc.fhofc` on windows
(:func:`pipeline.invert.fhofc.fhofc_windows`: the dense Jacobian of 48 000 samples would not fit). γ defaults
to |G|/|Δ| at ``q_cutoff_hz``.

For every law the learned part of one trial is ``α L G`` in the frequency domain (:meth:`Update.learning`):
L G = |Q| for model-based ILC, |G|² / (|G|² + w + w_Δ) for norm-optimal ILC (the long-trial limit of the
lifted solution), |G|² / (|G|² + γ² |1 - e^{-jωTs}|²) for IL-FHOFC (its linearisation); the convergence check
of :mod:`pipeline.learn.safety` uses it.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import fft, signal

from pipeline.invert.fhofc import il_fhofc_step
from pipeline.invert.ilc import process_sensitivity
from pipeline.invert.ilc_lq import RiccatiUpdate
from pipeline.models.closed_loop import ArxPGNN, DiscreteController
from pipeline.systems.actuator_lag import ActuatorLag
from pipeline.systems.controller import LTIController

__all__ = ["LoopModel", "Update", "ModelILC", "NormOptimalILC", "IlFhofc", "make_update", "apply_response",
           "applied_disturbance", "LAWS"]

LAWS = ("model_ilc", "norm_optimal", "il_fhofc")


@dataclass(frozen=True, eq=False)
class LoopModel:
    """The identified loop: linear physics (M [kg], F_v [N s/m], K [N/m]) under the controller ``ctrl``, the force
    behind the drive's current-loop lag τ Ḟ + F = u (``lag_tau`` [s], :mod:`pipeline.systems.actuator_lag`; 0: none)."""

    Ts: float
    M: float
    F_v: float
    K: float
    ctrl: LTIController
    F_c: float = 0.0              # smooth Coulomb friction F_c tanh(q̇/w) [N] ...
    coulomb_width: float = 0.0    # ... its width w [m/s] (0: not in the linearisation)
    lag_tau: float = 0.0          # the actuator lag τ [s] between the command u and the force F (0: none)

    def __post_init__(self):
        if not (self.M > 0 and self.F_v >= 0 and self.K >= 0 and self.Ts > 0 and self.F_c >= 0
                and self.coulomb_width >= 0 and self.lag_tau >= 0):
            raise ValueError(f"the learning model needs M > 0, F_v, K, F_c, coulomb_width, lag_tau >= 0 and Ts > 0; "
                             f"got M={self.M}, F_v={self.F_v}, K={self.K}, F_c={self.F_c}, "
                             f"coulomb_width={self.coulomb_width}, lag_tau={self.lag_tau}, Ts={self.Ts}")

    def command_for(self, force: np.ndarray) -> np.ndarray:
        """The command u [N] that makes the lagged force F follow ``force`` at the samples: the exact sampled lag
        F(k+1) = a F(k) + (1 - a) u(k), a = exp(-Ts/τ), inverted, u(k) = (F(k+1) - a F(k))/(1 - a) (one sample of
        preview: offline, the recording's). Without a lag u = F. What a force of the model that acts on the mass
        (the Coulomb force) asks of the command."""
        f = np.asarray(force, np.float64)
        if not self.lag_tau or f.size < 2:
            return f
        a = ActuatorLag(self.lag_tau, self.Ts).a
        nxt = np.concatenate([f[1:], f[-1:]])
        return (nxt - a * f) / (1.0 - a)

    def coulomb(self, x: np.ndarray) -> np.ndarray:
        """F_c tanh(ẋ/w) [N] with ẋ(k) = (x(k+D+1) - x(k+D))/Ts: the velocity over the ZOH interval the force of
        sample k acts on (D: the controller's delay); zero without a width."""
        if self.F_c == 0.0 or self.coulomb_width == 0.0:
            return np.zeros(np.size(x))
        D = self.ctrl.delay
        x = np.asarray(x, np.float64)
        v = np.diff(np.concatenate([x, np.full(D + 1, x[-1])]))[D:D + x.size] / self.Ts
        return self.F_c * np.tanh(v / self.coulomb_width)

    def _plant_ss(self):
        """P_zoh in state space (q, q̇[, F]): the exact ZOH of 1/(M s² + F_v s + K), with a lag of
        1/((τ s + 1)(M s² + F_v s + K)) (the force F a third state); its D is 0."""
        if not self.lag_tau:
            A = np.array([[0.0, 1.0], [-self.K / self.M, -self.F_v / self.M]])
            B, C = np.array([[0.0], [1.0 / self.M]]), np.array([[1.0, 0.0]])
        else:
            A = np.array([[0.0, 1.0, 0.0], [-self.K / self.M, -self.F_v / self.M, 1.0 / self.M],
                          [0.0, 0.0, -1.0 / self.lag_tau]])
            B, C = np.array([[0.0], [0.0], [1.0 / self.lag_tau]]), np.array([[1.0, 0.0, 0.0]])
        return signal.cont2discrete((A, B, C, np.zeros((1, 1))), self.Ts)[:4]

    def _plant_zpk(self):
        """P_zoh's zeros, poles, gain."""
        with warnings.catch_warnings():   # the leading numerator coefficient is 0 (strictly proper): not an issue
            warnings.simplefilter("ignore", signal.BadCoefficients)
            return signal.ss2zpk(*self._plant_ss())

    def realisation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """G = P'/(1 + gtau C_y P') as (A, B, C, D) built from its parts (norm-optimal ILC's model; numpy only).

        State [x_p (P_zoh: q, q̇[, F]), s_1 … s_D (the delay line), x_c (C_y = B_y/A in controllable form)]::

            y = C_p x_p,   c(k) = φ(k) - gtau (C_c x_c + D_c y),   u = s_D (u = c when D = 0)
            x_p⁺ = A_p x_p + B_p u,   s_1⁺ = c,  s_i⁺ = s_{i-1},   x_c⁺ = A_c x_c + B_c y

        P_zoh is strictly proper, so the loop has no algebraic loop and G's D is 0."""
        Ap, Bp, Cp, _ = (np.asarray(m, np.float64) for m in self._plant_ss())
        Bp, Cp = Bp.ravel(), Cp.ravel()
        b, a = self.ctrl.b_y, self.ctrl.a
        m = max(b.size, a.size)
        pad = lambda v: np.concatenate([v, np.zeros(m - v.size)])     # noqa: E731  z⁻¹ → z: the same coefficients
        Ac, Bc, Cc, Dc = signal.tf2ss(pad(b), pad(a))
        nc, D, g, npl = Ac.shape[0], self.ctrl.delay, self.ctrl.gtau, Ap.shape[0]
        n = npl + D + nc
        ip, ic = slice(0, npl), slice(npl + D, n)
        Cy = np.zeros(n)
        Cy[ip] = Cp
        Lc = -g * float(Dc.ravel()[0]) * Cy                         # c = Lc x + φ
        Lc[ic] -= g * Cc.ravel()
        A, B = np.zeros((n, n)), np.zeros(n)
        A[ip, ip] = Ap
        if D:
            A[ip, npl + D - 1] += Bp
            A[npl], B[npl] = Lc, 1.0
            for i in range(1, D):
                A[npl + i, npl + i - 1] = 1.0
        else:
            A[ip] += np.outer(Bp, Lc)
            B[ip] = Bp
        A[ic, ic] = Ac
        A[ic] += np.outer(Bc.ravel(), Cy)
        return A, B, Cy, 0.0

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

    def arx(self) -> ArxPGNN:
        """P' = z^-D P_zoh as [B2]'s ARX model (the PGNN (30)): ŷ(k) = -Σ a_i ŷ(k-i) + Σ b_i ĉ(k-D-i), ĉ the
        controller's command before the delay (:meth:`loop_controller` closes the loop on it). With a Coulomb
        width the force F_c tanh(q̇/w) acting over the interval [j, j+1) is the PGNN's tanh layer, one neuron per
        b_i: -b_i F_c tanh((ŷ(k-i) - ŷ(k-i-1))/(Ts w)), the velocity one interval earlier (explicit: ŷ(k) may
        not depend on itself; stable while its damping F_c Ts/(w M) < 1). With an actuator lag the Coulomb force
        goes through the lag with the command here (it acts on the mass itself): a lag of τ on a force that
        changes sign once per stop."""
        zeros, poles, k = self._plant_zpk()
        num, den = k * np.poly(np.atleast_1d(zeros)), np.poly(poles)   # descending powers of z
        n, m = den.size - 1, num.size - 1
        theta = np.concatenate([-den[1:], num]) / den[0]
        orders = (n, m + 1, n - m - 1 + self.ctrl.delay)
        if not (self.F_c and self.coulomb_width):
            return ArxPGNN(*orders, theta)
        if self.F_c * self.Ts / (self.coulomb_width * self.M) >= 1.0:
            raise ValueError(f"the model's Coulomb slope F_c/w = {self.F_c / self.coulomb_width:.4g} N s/m is too "
                             f"stiff for one explicit step at Ts = {self.Ts:g} s (F_c Ts/(w M) >= 1); learn.law="
                             "il_fhofc needs a wider model.coulomb_width or no Coulomb term")
        nb, na = m + 1, n + 1            # ŷ(k-1 .. k-n-1): the velocity of the oldest interval needs one more lag
        P = np.zeros((nb, na + nb))      # x_i = (ŷ(k-i) - ŷ(k-i-1)) / (Ts w), i = 1 .. n_b
        for i in range(nb):
            P[i, i], P[i, i + 1] = 1.0, -1.0
        P /= self.Ts * self.coulomb_width
        b = theta[n:]
        return ArxPGNN(na, nb, orders[2], np.concatenate([theta[:n], [0.0], b]), np.eye(nb), np.zeros(nb),
                       -b / abs(b[0]), 0.0, nn_P=P, out_scale=self.F_c * abs(b[0]))

    def loop_controller(self) -> DiscreteController:
        """gtau C_y as [B2]'s controller (no computational delay: :meth:`arx` holds it): the command is
        ĉ = gtau C_y (r - ŷ) + φ (module docstring)."""
        return DiscreteController.from_tf(self.ctrl.transfer_functions(self.Ts)[1] * self.ctrl.gtau)

    def state_space(self):
        """G as a discrete python-control state-space model through P_zoh's zeros and poles (python-control's
        feedback; :meth:`realisation` is the one norm-optimal ILC uses: it keeps the digits ss2zpk loses)."""
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


def apply_response(x: np.ndarray, response, Ts: float, pad: int, hold: bool = False) -> np.ndarray:
    """Y(ω) = H(ω) X(ω) for a non-causal H [its values at ω, rad/s], on x zero-padded by ``pad`` samples
    (circular: what H moves before sample 0 wraps into the padding, not into the signal). ``hold``: x held at
    its first and last values for pad/2 samples either side first, so a trial's error that ends (or starts) away
    from 0, an axis standing with a residual error, is not a step into the padding: P'^-1 of that step (M s²)
    was a force ramp over the trial's last samples, held past the end of an exported table (a held-out trial:
    -8 N at the last sample, growing from trial to trial)."""
    x = np.asarray(x, np.float64)
    m = pad // 2 if hold else 0
    if m:
        x = np.concatenate([np.full(m, x[0]), x, np.full(m, x[-1])])
    n = fft.next_fast_len(x.size + pad - 2 * m)
    w = 2 * math.pi * fft.rfftfreq(n, Ts)
    return fft.irfft(fft.rfft(x, n) * response(w), n)[m:x.size - m]


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
        """Take the model's Coulomb force along the trajectories: its difference δd between the reference r and
        the recorded y joins L e (model-based ILC) or the predicted error through G (norm-optimal; module
        docstring)."""
        self.reference = np.asarray(r, np.float64) if self.model.F_c and self.model.coulomb_width else None
        return self

    def coulomb_along(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model's Coulomb force [N] along r (where the next trial is to go) and along the recorded y = r - e
        smoothed by Q, as the commands that make them through the lag (:meth:`LoopModel.command_for`); their
        difference is δd (:meth:`along`; module docstring)."""
        y = signal.sosfiltfilt(self.q_sos, self.reference - e)
        m = self.model
        return m.command_for(m.coulomb(self.reference)), m.command_for(m.coulomb(y))

    def q(self, w) -> np.ndarray:
        """|Q(e^{jωTs})| = |H|² (filtfilt: the filter forwards and backwards, no phase)."""
        return np.abs(signal.sosfreqz(self.q_sos, worN=np.asarray(w) * self.model.Ts)[1]) ** 2

    def learning(self, w) -> np.ndarray:
        """L G at ω (module docstring)."""
        raise NotImplementedError

    def rho(self, w, gain: float, delta) -> np.ndarray:
        """The worst trial-to-trial factor |Q| (|1 - α L G| + α |L G| δ) at ω over |Δ| ≤ δ
        (:func:`pipeline.learn.safety.convergence_check`)."""
        lg = self.learning(w)
        return self.q(w) * (np.abs(1.0 - gain * lg) + gain * np.abs(lg) * delta)

    def correction(self, e: np.ndarray, f: np.ndarray) -> np.ndarray:
        """The learned change before Q and α [N]."""
        raise NotImplementedError

    def diagnostics(self) -> dict:
        """What the last :meth:`next` reports for the trial's log entry (none by default)."""
        return {}

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
        inv_p = apply_response(e, lambda w: self.q(w) * self.model.plant_inverse(w), self.model.Ts, self.pad,
                               hold=True)
        fb = self.model.controller_from_rest(e)
        if self.reference is not None:
            c_r, c_y = self.coulomb_along(e)
            fb = fb + c_r - c_y
        return inv_p + signal.sosfiltfilt(self.q_sos, fb)


class NormOptimalILC(Update):
    """[B2]'s norm-optimal step, solved exactly by :class:`pipeline.invert.ilc_lq.RiccatiUpdate` on
    :meth:`LoopModel.realisation` (module docstring); :attr:`solve` is the last solve's report (residual, stop)."""

    law = "norm_optimal"

    def __init__(self, model, q_cutoff_hz, q_order=2, pad_seconds=0.5, w_f: float = 1e-5, w_df: float = 0.0,
                 max_sweeps: int = 3, rtol: float = 1e-9):
        super().__init__(model, q_cutoff_hz, q_order, pad_seconds)
        w = np.linspace(0.0, math.pi / model.Ts, 20001)[1:]
        self.g2 = float(np.max(np.abs(model.response(w)))) ** 2
        self.w, self.w_delta = w_f * self.g2, w_df * self.g2
        if self.w + self.w_delta <= 0:
            raise ValueError("learn.w_f + learn.w_df must be > 0 for norm-optimal ILC (the model has a delay: no "
                             "exact inverse); e.g. learn.w_f=1e-5")
        self.max_sweeps, self.rtol = int(max_sweeps), float(rtol)
        self._solver: RiccatiUpdate | None = None
        self.solve: dict | None = None

    def learning(self, w):
        g2 = np.abs(self.model.response(w)) ** 2
        return g2 / (g2 + self.w + self.w_delta)

    def correction(self, e, f):
        if self._solver is None or self._solver.N != e.size:
            self._solver = RiccatiUpdate(self.model.realisation(), e.size, self.w, self.w_delta, self.rtol,
                                         self.max_sweeps)
        if self.reference is not None:   # the predicted error e_j - G (Δφ - δd): δd joins e through G
            c_r, c_y = self.coulomb_along(e)
            e = e + self._solver.apply(c_r - c_y)
        out = self._solver.step(e, f)
        self.solve = self._solver.reports[-1].as_dict()
        if self.solve["stop"] != "converged":
            warnings.warn(f"norm-optimal ILC: the solve stopped at relative residual {self.solve['residual']:.3g} > "
                          f"learn.rtol = {self.rtol:g} after {self.solve['sweeps']} refinement sweeps "
                          "(learn.max_sweeps)", RuntimeWarning, stacklevel=2)
        return out

    def diagnostics(self) -> dict:
        """The last solve's report for the trial's log entry: ``solve`` = {method, residual, rtol, sweeps, stop}."""
        return {} if self.solve is None else {"solve": self.solve}


class IlFhofc(Update):
    """[B2]'s IL-FHOFC (22) on the recorded error (:func:`pipeline.invert.fhofc.il_fhofc_step`), then Q (module
    docstring). ``arx``: the closed-loop model Φ̂ (an :class:`ArxPGNN`, e.g. a [B2] PGNN with its NN; its input
    the command ĉ before the delay, its controller ``ctrl``); default the physics' :meth:`LoopModel.arx` and
    :meth:`LoopModel.loop_controller`. The model loop runs from rest at r(0) on r - r(0) (the physics is
    linear: the static load is the integrator's, as for the other laws)."""

    law = "il_fhofc"

    def __init__(self, model, q_cutoff_hz, q_order=2, pad_seconds=0.5, *, reference, gamma: float | None = None,
                 window: int = 100, overlap: int = 50, maxiter: int = 100, arx: ArxPGNN | None = None,
                 ctrl: DiscreteController | None = None):
        super().__init__(model, q_cutoff_hz, q_order, pad_seconds)
        self.arx = model.arx() if arx is None else arx
        self.loop = model.loop_controller() if ctrl is None else ctrl
        if gamma is None:     # |G| = γ |Δ| at Q's cutoff: L G = 1/2 there, as |Q| (learning)
            wq = 2 * math.pi * q_cutoff_hz
            gamma = float(np.abs(model.response(wq)) / np.abs(1.0 - np.exp(-1j * wq * model.Ts)))
        if not (math.isfinite(gamma) and gamma >= 0):
            raise ValueError(f"learn.gamma={gamma} must be a finite number >= 0 [m/N] (Γ = γΔ of [B2] (31))")
        self.gamma, self.window, self.overlap = float(gamma), int(window), int(overlap)
        # one Gauss–Newton step solves FHOFC of a linear model exactly (a linear least squares)
        self.max_iter = 1 if self.arx.n1 == 0 else int(maxiter)
        self.r = np.asarray(reference, np.float64)
        self.last = None

    def learning(self, w):
        """L G = |G|² / (|G|² + γ² |1 - e^{-jωTs}|²): FHOFC's regularised inverse L = G* / (|G|² + γ²|Δ|²) of G,
        long-trial limit."""
        g2 = np.abs(self.model.response(w)) ** 2
        if self.gamma == 0.0:
            return np.where(g2 > 0, 1.0, 0.0)
        d2 = np.abs(1.0 - np.exp(-1j * np.asarray(w) * self.model.Ts)) ** 2
        return g2 / (g2 + self.gamma ** 2 * d2)

    def rho(self, w, gain, delta):
        """The target Ŷ_j + α e_j with Ŷ_j = G φ_j + (r's part): FHOFC's solution is L G φ_j + α L e_j, so with
        e_j = d - G (1 + Δ) φ_j the trial map is Q L G (1 - α (1 + Δ)): worst case |Q| L G (|1 - α| + α δ)
        (L G real in [0, 1]; γ's bias 1 - L G contracts too)."""
        return self.q(w) * self.learning(w) * (abs(1.0 - gain) + gain * delta)

    def next(self, e, f, gain: float, offset=None) -> np.ndarray:
        e, f = np.asarray(e, np.float64), np.asarray(f, np.float64)
        if e.shape != self.r.shape:
            raise ValueError(f"the recorded error has {e.size} samples, the reference {self.r.size}")
        k = 0.0 if offset is None else np.asarray(offset, np.float64)
        phi = f + k
        x = self.r - self.r[0]
        self.last = il_fhofc_step(self.arx, self.loop, x, phi, x - e, alpha=gain, gamma=self.gamma,
                                  window=self.window, overlap=self.overlap, max_iter=self.max_iter,
                                  check_range=False)
        return signal.sosfiltfilt(self.q_sos, self.last.u_ff) - k

    def diagnostics(self) -> dict:
        """FHOFC's inversion error ‖R_{j+1} - Ŷ‖/√N [m] ([B2] (15): how far the model reaches the target) and its
        Gauss–Newton steps, of the last :meth:`next`."""
        if self.last is None:
            return {}
        return {"fhofc_inversion_error": self.last.inversion_error, "fhofc_iterations": self.last.n_iter}


def make_update(model: LoopModel, law: str, q_cutoff_hz: float, q_order: int = 2, **weights) -> Update:
    """The update law named ``law`` (:data:`LAWS`); il_fhofc needs ``reference=r``."""
    if law == "model_ilc":
        return ModelILC(model, q_cutoff_hz, q_order)
    if law == "norm_optimal":
        return NormOptimalILC(model, q_cutoff_hz, q_order, **weights)
    if law == "il_fhofc":
        return IlFhofc(model, q_cutoff_hz, q_order, **weights)
    raise ValueError(f"learn.law={law!r}; choose one of {LAWS}")
