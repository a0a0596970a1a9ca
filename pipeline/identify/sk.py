"""Sanathanan–Koerner iterations for output-error identification ([K] Alg. 5 and 19, SPEC §5).

The output-error criterion ([K] (7))

    J_OE = Σ_k ( f̂(k) − (A(r(k)) + g_φ(r(k))) / B(q) )²

is minimised by iterating, with the weighting 1/B^{j-1}(q) fixed ([K] (10), (27), (30)),

    θ^j, φ^j = argmin ‖W^{j-1} (f̂ − M θ − g_φ(r))‖² + λ R^{j-1}(φ),   M = [R, −F̂] ([K] (14)).

W^{j-1} is a recursive filter (never an N×N matrix).  Within an iteration θ enters linearly:
for the rational model the step is closed-form least squares on the column-scaled W M; for
the PGNN θ is eliminated in closed form (variable projection, Golub–Pereyra)

    θ(φ) = (W M)^+ W (f̂ − g_φ),   cost(φ) = ‖(I − U1 U1ᵀ) W (f̂ − g_φ)‖² + λ R(φ),

which has exactly the minimisers of [K] (30) (the θ-block of [K] (23) is zeroed), and φ is
found by Levenberg–Marquardt with the exact Jacobian −W ∂g/∂φ (per-sample gradients filtered
column by column).  Initialisation per [K]: a, b from the best linear approximation (equation
error, B^0 = 1), φ as constructed (Glorot).  After every step roots of B outside the unit circle
are reflected inside (SPEC §5, reported in :attr:`SKResult.reflected`), the true J_OE is
logged, and the best iterate by J_OE is returned.

Stopping (SPEC §8 K3, "stop on convergence, not on a cap"): the outer loop stops with reason
``'tol'`` when the relative parameter change of a step is below ``tol`` *and* that step's inner
LM stopped on its own tolerance (ftol/gtol/mu_max, not its iteration cap); ``max_iter`` is only
a safety cap (reason ``'max_iter'``, :class:`SKNotConvergedWarning`).  Every iterate records
its inner LM's stop message (:attr:`SKIterate.lm_message`, :attr:`SKIterate.lm_converged`).

:func:`output_error_lm` minimises (7) directly by LM from a given model (SPEC §8 K3 check); with
``lam > 0`` and a frozen ``weighting`` it minimises J_OE + λR ([K] (30)) with R frozen at that
weighting (the check for the regularised PGNN, which does not minimise (7)).
"""
from __future__ import annotations

import copy
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from pipeline.identify.lm import TIGHTEN, LMResult, levenberg_marquardt
from pipeline.identify.orthogonal import ModelSubspace, model_subspace, orthogonal_regularizer
from pipeline.models.rational import RationalFeedforward, Segments, filter_segments

__all__ = ["REGULARIZERS", "SKIterate", "SKResult", "SKNotConvergedWarning", "sk_iterations", "sk_restarts",
           "oe_cost", "output_error_lm", "output_error_problem", "OEResult", "prepare_data",
           "frozen_regularizer"]

#: relative size below which a projected Jacobian column is rounding noise (see _varpro_step)
_FLAT_RTOL = 1e-11
#: squared projected/full column norm below which the normal equations' G_ii − ‖C_i‖² (which
#: loses ~N·eps of G_ii to cancellation) is recomputed from the explicit projected column
_CANCEL_RTOL2 = 1e-8
#: regularisers of the SK step ([K] Alg. 5 = 'none', Alg. 19 = 'orthogonal')
REGULARIZERS = ("none", "orthogonal")


class SKNotConvergedWarning(UserWarning):
    """SK stopped at max_iter before the parameter change fell below the tolerance."""


@dataclass
class SKIterate:
    """One SK iterate (j = 0 is the initialisation).

    Attributes
    ----------
    j : int
    theta : np.ndarray
        col(a, b) after the step (and after a root reflection, if any).
    phi : np.ndarray or None
        Approximator parameters (None for the rational model).
    g_gain : float
        Approximator output gain (changes only when a root reflection happened).
    J_OE : float
        True output-error cost [K] (7) of this iterate [N²].
    J_weighted : float
        Weighted cost J^j ([K] (10)) at the step's optimum, plus λR for 'orthogonal' [N²].
    regularizer : float
        R^{j-1}(φ^j) ([K] (29)) [N²] (0 without approximator; at j = 0 with W = 1, only
        computed with λ > 0).
    change : float
        Relative parameter change from the previous iterate (column-scaled θ, and φ).
    output_change : float
        Change of the model's output on the training data from the previous iterate, relative to
        this iterate's output error: ‖F^j(r) − F^{j-1}(r)‖ / ‖f̂ − F^j(r)‖ = ‖Δŷ‖ / √J_OE.
    n_reflected : int
        Roots of B reflected into the unit circle after this step.
    condition : float
        Condition number of the column-scaled W^{j-1} M (over the kept directions).
    n_truncated : int
        Numerically singular directions of W^{j-1} M dropped (``weighted_rank='truncate'``).
    lm_iter : int
        LM iterations of the step (0 for closed form).
    lm_message : str
        Why the inner LM stopped ('ftol', 'gtol', 'mu_max', 'max_iter', …; 'closed form' for the
        rational model's least-squares step, 'initialisation' for j = 0).
    lm_converged : bool
        The inner solve stopped on its tolerance (not on its iteration cap).
    weighting : np.ndarray
        q^{-1} coefficients of B^{j-1}, the denominator of the weighting W^{j-1} = 1/B^{j-1} of
        this step (and of the regulariser R^{j-1}); [1.0] for j = 0.
    seconds : float
        Wall time of the step [s].
    """

    j: int
    theta: np.ndarray
    phi: np.ndarray | None
    g_gain: float
    J_OE: float
    J_weighted: float = math.nan
    regularizer: float = 0.0
    change: float = math.inf
    output_change: float = math.inf
    n_reflected: int = 0
    condition: float = math.nan
    n_truncated: int = 0
    lm_iter: int = 0
    lm_message: str = ""
    lm_converged: bool = True
    weighting: np.ndarray = field(default_factory=lambda: np.ones(1))
    seconds: float = 0.0


@dataclass
class SKResult:
    """Outcome of :func:`sk_iterations`.

    Attributes
    ----------
    model : RationalFeedforward
        The model at the best iterate (lowest J_OE, or J_OE + λR^{j-1}(φ^j) with the
        regulariser: :attr:`cost`); the input model is not modified.
    best : int
        Index j of that iterate.
    iterates : list of SKIterate
        Every iterate, j = 0 (initialisation) … last.
    converged : bool
        True when the parameter change fell below ``tol`` (or the criterion's change below
        ``cost_tol``) after an inner solve that converged.
    message : str
        Outer stop reason: 'tol', 'cost_tol', 'stalled' (no fixed point, the best criterion
        stopped improving; ``converged`` stays False) or 'max_iter'.
    reflected : list of int
        Iterations after which roots of B were reflected (SPEC §5: tag the run).
    tol : float
        The outer tolerance used.
    lam : float
        λ of the regulariser (0 without).
    """

    model: RationalFeedforward
    best: int
    iterates: list[SKIterate]
    converged: bool
    message: str
    reflected: list[int] = field(default_factory=list)
    tol: float = math.nan
    lam: float = 0.0

    @property
    def cost(self) -> list[float]:
        """The criterion the iterates are ranked by: J_OE + λR^{j-1}(φ^j), j = 0 … last."""
        return [it.J_OE + self.lam * it.regularizer for it in self.iterates]

    @property
    def stop_reason(self) -> str:
        """Outer stop reason ('tol', 'cost_tol', 'stalled' or 'max_iter')."""
        return self.message

    @property
    def inner_converged(self) -> bool:
        """Every inner solve (j ≥ 1) stopped on its tolerance, none on its cap."""
        return all(it.lm_converged for it in self.iterates[1:])

    @property
    def n_inner_capped(self) -> int:
        """Number of inner solves that stopped on their iteration cap."""
        return sum(not it.lm_converged for it in self.iterates[1:])

    @property
    def n_lm_iter(self) -> int:
        """Inner LM iterations summed over the SK steps."""
        return sum(it.lm_iter for it in self.iterates[1:])

    def summary(self) -> str:
        """One line: outer reason, iterations, inner stop messages (counts), last change."""
        msgs: dict[str, int] = {}
        for it in self.iterates[1:]:
            msgs[it.lm_message] = msgs.get(it.lm_message, 0) + 1
        inner = ", ".join(f"{k}×{v}" for k, v in msgs.items()) or "none"
        return (f"{self.message} after {len(self.iterates) - 1} SK iterations (last change "
                f"{self.iterates[-1].change:.2e}, tol {self.tol:.1e}); inner: {inner}")

    @property
    def J_OE(self) -> list[float]:
        """J_OE per iterate ([K] (7)), j = 0 … last."""
        return [it.J_OE for it in self.iterates]

    @property
    def seconds_per_iter(self) -> float:
        """Mean wall time of the SK steps j ≥ 1 [s]."""
        t = [it.seconds for it in self.iterates[1:]]
        return float(np.mean(t)) if t else 0.0


# ----------------------------------------------------------------------------- helpers
def prepare_data(model: RationalFeedforward, r, f_hat) -> dict:
    """Concatenate the references and optimal inputs and build everything SK needs once:
    the model inputs, f̂ and M = [R, −F̂] ([K] (14))."""
    r_cat, seg = Segments.concat(r, "reference")
    f_cat, seg_f = Segments.concat(f_hat, "optimal input f̂")
    if seg_f != seg:
        raise ValueError(f"references and optimal inputs have different lengths {seg.lengths} vs "
                         f"{seg_f.lengths}; pair every reference with its own f̂")
    inp = model.inputs(r_cat, seg)
    M = np.hstack([inp["R"], -model.ar_regressors(f_cat, seg)])
    names = [f"a{i + 1}" for i in range(model.n_a)] + [f"b{i + 1}" for i in range(model.n_b)]
    return {"inputs": inp, "segments": seg, "f": f_cat, "M": M, "names": names}


def _has_approximator(model) -> bool:
    return hasattr(model, "g_and_jacobian")


def _oe_output(model: RationalFeedforward, data: dict) -> np.ndarray | None:
    """F_θ,φ(r), the model's output on the training references; None when B is unstable."""
    if not model.is_stable():
        return None
    with torch.no_grad():
        return model.simulate(data["inputs"]).numpy()


def oe_cost(model: RationalFeedforward, data: dict, output: np.ndarray | None = None) -> float:
    """J_OE = ‖f̂ − F_θ,φ(r)‖² ([K] (7)) [N²]; inf when B is unstable."""
    f = _oe_output(model, data) if output is None else output
    if f is None:
        return math.inf
    e = data["f"] - f
    c = float(e @ e)
    return c if math.isfinite(c) else math.inf


def _snapshot(model) -> tuple:
    phi = model.phi.numpy().copy() if _has_approximator(model) else None
    gain = float(model.g_gain) if _has_approximator(model) else 1.0
    return model.theta.copy(), phi, gain


def _restore(model, theta, phi, gain) -> None:
    model.set_theta(theta)
    if phi is not None:
        model.set_phi(torch.from_numpy(phi.copy()))
        with torch.no_grad():
            model.g_gain.fill_(gain)


# ----------------------------------------------------------------------------- SK step
class _LastForward:
    """g_φ(r) of a tanh MLP at the last φ evaluated, with its layer outputs (SharedARPGNN.g_forward: the
    bits of g_value), so that W ∂g/∂φ at that φ (filtered_jacobian[_gram], g_jvp, g_vjp) reuses them."""

    def __init__(self, model, inputs: dict):
        self.model, self.inputs = model, inputs
        self.key, self.g, self.acts = None, None, None

    def __call__(self, phi: torch.Tensor) -> torch.Tensor:
        key = phi.numpy().tobytes()
        if key != self.key:
            self.g, self.acts = self.model.g_forward(self.inputs, phi)
            self.key = key
        return self.g

    def at(self, phi: torch.Tensor):
        """The layer outputs at ``phi`` if it is the last φ evaluated, else None."""
        return self.acts if self.key == phi.numpy().tobytes() else None


def _varpro_step(model, data: dict, sub: ModelSubspace, Wf: np.ndarray, den: np.ndarray,
                 lam: float, lm_kw: dict) -> tuple[torch.Tensor, LMResult]:
    """φ^j of [K] (30) with θ eliminated (variable projection), by LM with exact Jacobian."""
    seg, inp = data["segments"], data["inputs"]
    U1 = np.ascontiguousarray(sub.U1)
    Wf_perp = sub.project_out(Wf)
    sq = math.sqrt(lam)
    # a tanh MLP g_φ: the residual keeps its layer outputs, and W ∂g/∂φ is formed from them in closed
    # form and filtered in one numba pass (SharedARPGNN.filtered_jacobian[_gram]); otherwise ∂g/∂φ by
    # per-sample backpropagation (torch) and filter_segments column by column
    closed = bool(getattr(model, "closed_form_jacobian", False))
    fwd = _LastForward(model, inp) if closed else None

    def residual(phi: torch.Tensor) -> torch.Tensor:
        g = fwd(phi) if closed else model.g_value(inp, phi)
        Wg = filter_segments(g.numpy(), [1.0], den, seg)
        res = Wf_perp - sub.project_out(Wg)                    # (I − U1U1ᵀ) W (f̂ − g)
        if lam > 0:   # [K] (23): extra rows √λ (ΣVᵀ)^{-1} U1ᵀ W g_φ
            res = np.concatenate([res, sq * sub.coordinates(Wg)])
        return torch.from_numpy(res)

    last: dict = {}     # the filtered Jacobian of g (and J) at the last φ asked for
    zeroed: dict = {}   # the flat columns normal_equations zeroed, and at which φ

    def filtered(phi: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        key = phi.numpy().tobytes()
        if last.get("key") != key:
            last.clear()
            if closed:
                WJ = model.filtered_jacobian(inp, phi, [1.0], den, seg, fwd.at(phi))
            else:
                _, Jg = model.g_and_jacobian(inp, phi)
                WJ = filter_segments(Jg.numpy(), [1.0], den, seg)     # W ∂g/∂φ, column by column
            last.update(key=key, WJ_C=(WJ, U1.T @ WJ))            # and U1ᵀ W ∂g/∂φ  [p, n_φ]
        return last["WJ_C"]

    def jacobian(phi: torch.Tensor) -> torch.Tensor:
        WJ, C = filtered(phi)
        J = U1 @ C - WJ                                       # −(I − U1U1ᵀ) W ∂g/∂φ
        # a φ_i that moves g only inside im(W M) is flat in the reduced cost (θ absorbs it,
        # [K] Corollary 14); its projected column is rounding noise, which LM's scale-
        # invariant damping would turn into a huge step: make it exactly zero
        flat = np.linalg.norm(J, axis=0) <= _FLAT_RTOL * np.linalg.norm(WJ, axis=0)
        if np.any(flat):
            J[:, flat] = 0.0
        if lam > 0:
            J = np.vstack([J, sq * sub.coordinates(C, projected=True)])
        return torch.from_numpy(J)

    def normal_equations(phi: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(JᵀJ, Jᵀr) of :func:`jacobian` without forming J (the LM uses this; ~2× cheaper):
        with J = U1 C − WJ and U1ᵀU1 = I, JᵀJ = WJᵀWJ − CᵀC and Jᵀr = Cᵀ U1ᵀr − WJᵀr.  The
        subtraction loses ~N·eps of ‖WJ_i‖² to cancellation, so columns whose projected norm is
        below √_CANCEL_RTOL2 of the full one are recomputed from the explicit projected column
        (and tested for flatness exactly as :func:`jacobian` does)."""
        rn = r.numpy()
        n = seg.n
        r1 = rn[:n]
        key = phi.numpy().tobytes()
        if closed and last.get("key") != key:
            # G, C and WJᵀr block by block while the filtered rows are in cache (WJ is not stored)
            G, C, WJr = model.filtered_jacobian_gram(inp, phi, [1.0], den, seg, U1, r1, fwd.at(phi))
        else:
            WJ, C = filtered(phi)
            G = WJ.T @ WJ                                     # syrk
            WJr = WJ.T @ r1
        A = G - C.T @ C
        g = C.T @ (U1.T @ r1) - WJr
        full2 = np.diag(G).copy()
        sus = np.flatnonzero(np.diag(A) <= _CANCEL_RTOL2 * full2)
        zeroed.update(key=key, flat=sus[:0], acts=fwd.at(phi) if closed else None)
        if sus.size:
            WJ = filtered(phi)[0]                             # the explicit columns (rare)
            WJt = WJ.T
            J_s = U1 @ C[:, sus] - WJ[:, sus]                 # explicit projected columns
            A_s = C.T @ (U1.T @ J_s) - WJt @ J_s              # Jᵀ J_s, no cancellation
            A[:, sus] = A_s
            A[sus, :] = A_s.T
            flat = sus[np.linalg.norm(J_s, axis=0) <= _FLAT_RTOL * np.sqrt(full2[sus])]
            if flat.size:
                A[:, flat] = 0.0
                A[flat, :] = 0.0
                g[flat] = 0.0
                zeroed["flat"] = flat
        if lam > 0:
            K = sq * sub.coordinates(C, projected=True)       # [p, n_φ] regulariser rows
            A = A + K.T @ K
            g = g + K.T @ rn[n:]
        return torch.from_numpy(A), torch.from_numpy(g)

    def explicit(phi: torch.Tensor) -> torch.Tensor:          # J at φ, formed once per φ
        filtered(phi)
        if "J" not in last:
            last["J"] = jacobian(phi)
        return last["J"]

    # J v and Jᵀ w for the geodesic acceleration (lm.py), J never formed: one directional derivative
    # of g and one filtering pass instead of the n_φ columns of W ∂g/∂φ.  With J = −(I − U1U1ᵀ) W ∂g/∂φ
    # (flat columns zeroed, as normal_equations did at this φ) over the regulariser rows
    # K = √λ V Σ⁻¹ U1ᵀ W ∂g/∂φ ([K] (23)):
    #   J v  = [−(I − U1U1ᵀ) W ∂g/∂φ v_nf ;  √λ V Σ⁻¹ U1ᵀ W ∂g/∂φ v]                 (v_nf: v, flat zeroed)
    #   Jᵀ w = zero_flat(∂g/∂φᵀ Wᵀ (−(I − U1U1ᵀ) w1)) + ∂g/∂φᵀ Wᵀ U1 √λ Σ⁻¹ Vᵀ w2   (Wᵀ: the time-reversed filter)
    def flat_at(phi: torch.Tensor):
        return zeroed["flat"] if zeroed.get("key") == phi.numpy().tobytes() else None

    def jvp(phi: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        flat = flat_at(phi)
        if flat is None:
            return explicit(phi) @ v
        v_nf = v.clone()
        v_nf[flat] = 0.0
        acts = zeroed["acts"]
        u = filter_segments(model.g_jvp(inp, phi, v_nf, acts).numpy(), [1.0], den, seg)
        out = -sub.project_out(u)
        if lam > 0:
            u_full = u if flat.size == 0 else filter_segments(model.g_jvp(inp, phi, v, acts).numpy(), [1.0],
                                                              den, seg)
            out = np.concatenate([out, sq * sub.coordinates(U1.T @ u_full, projected=True)])
        return torch.from_numpy(out)

    def vjp(phi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        flat = flat_at(phi)
        if flat is None:
            return explicit(phi).T @ w
        wn = w.numpy()
        n = seg.n

        def pull(y):                                          # ∂g/∂φᵀ Wᵀ y
            return model.g_vjp(inp, phi, filter_segments(y, [1.0], den, seg, reverse=True), zeroed["acts"])

        y = -sub.project_out(wn[:n])
        y_reg = U1 @ (sq * (sub.Vt @ wn[n:]) / sub.s) if lam > 0 else None
        if flat.size == 0:
            return pull(y if y_reg is None else y + y_reg)
        out = pull(y)
        out[flat] = 0.0
        return out if y_reg is None else out + pull(y_reg)

    jacobian.normal_equations = normal_equations              # type: ignore[attr-defined]
    jacobian.jvp, jacobian.vjp = jvp, vjp                     # type: ignore[attr-defined]  (geodesic LM)
    res = levenberg_marquardt(residual, model.phi, jacobian=jacobian, **lm_kw)
    return res.theta, res


def sk_iterations(model: RationalFeedforward, r, f_hat, *, max_iter: int = 20, tol: float = 1e-8,
                  regularizer: str = "orthogonal", lam: float = 1.0, column_scale: bool = True,
                  init: str = "equation_error", lm_max_iter: int = 100, lm_ftol: float = 1e-10,
                  lm_gtol: float = 1e-10, geodesic: bool = False, cost_tol: float = 0.0,
                  stall_window: int = 0, stall_tol: float = 1e-3, output_tol: float = 0.0,
                  rank_rtol: float | None = None, weighted_rank: str = "truncate",
                  callback: Callable[[SKIterate], None] | None = None) -> SKResult:
    """Identify a [K] feedforward by SK iterations ([K] Alg. 5; Alg. 19 with the regulariser).

    Parameters
    ----------
    model : RationalFeedforward or SharedARPGNN
        Model structure and initial φ (copied; the input is not modified).
    r, f_hat : array or list of arrays
        Training references [m] and their optimal inputs f̂ [N] (one array per reference).
    max_iter : int
        Safety cap on the number of SK iterations (the run stops there with a warning and
        reason 'max_iter').
    tol : float
        Stop (reason 'tol') when the relative parameter change (column-scaled θ, and φ) of a
        step is below ``tol`` and that step's inner LM converged (stopped on ftol/gtol/mu_max).
    cost_tol : float
        Stop (reason 'cost_tol') when the SK criterion J_OE (+ λR, [K] (30)) of a step differs
        from the previous step's by at most ``cost_tol`` of it and that step's inner LM
        converged: the fixed point in cost where the parameters are not unique (the
        unregularised PGNN, [K] K2: g_φ and θ trade along directions that leave the fit
        unchanged, so a parameter-change test never passes).  0 = off.
    output_tol : float
        With ``output_tol > 0`` the 'tol' and 'cost_tol' stops also need the step's output change
        ‖Δŷ‖/√J_OE (:attr:`SKIterate.output_change`) at most ``output_tol``: the model's output
        moved by a small fraction of its own error, so what is computed from it (a tracking error,
        which is that error propagated) has settled to about that fraction (issue 19: parameters
        changing by 1e-6 still moved the regularised PGNN's held-out tracking by 6 %).
    stall_window, stall_tol : int, float
        Stop (reason 'stalled') when the best criterion over the iterates has not fallen by more
        than ``stall_tol`` of itself for ``stall_window`` iterations whose inner solves converged:
        SK without a fixed point (the rational model, whose roots of B are reflected at every
        step, SPEC §5) has searched to its end; the best iterate is kept, as always, and
        ``converged`` stays False (it is not a fixed point).  Also when the criterion is out of
        reach of that: three or more iterates after the best, falling (if at all) too slowly at the
        pace of its last two steps to come within ``stall_tol`` of the best before ``max_iter``
        (the regularised PGNN crawling along a valley, thousands of LM steps per SK step); and when
        the last iterate is the best, falling at a steady pace (its last fall at least half the
        one before) at which the next ``stall_window`` iterations would gain less than
        ``stall_tol`` of it (the window rule's verdict, foreseen: the same PGNN setting a new best
        by ~1e-5 at every step).  0 = off.
    regularizer : {'orthogonal', 'none'}
        Orthogonal projection-based regulariser [K] (29) or none ([K] Alg. 5).  Ignored for
        the rational model (no approximator).
    lam : float
        λ of [K] (30) (dimensionless: R is in column-scaled coefficients, units N²).
    column_scale : bool
        Scale the columns of W M to unit norm before least squares / SVD (SPEC §5).
    init : {'equation_error', 'model'}
        θ^0 from the equation-error linear fit (B^0 = 1, [K]) or the model's current θ.
    lm_max_iter, lm_ftol, lm_gtol : int, float, float
        LM settings of each PGNN step (:func:`pipeline.identify.lm.levenberg_marquardt`): the
        inner solve converges on ``lm_ftol``/``lm_gtol``; ``lm_max_iter`` is its safety cap.
    geodesic : bool
        Geodesic acceleration in the PGNN's inner LM solves (:mod:`pipeline.identify.lm`).
    rank_rtol : float, optional
        Rank tolerance of [K] Assumption 10 (see :func:`model_subspace`).
    weighted_rank : {'truncate', 'raise'}
        Policy when the *weighted* W^{j-1} M (j ≥ 1) is numerically rank deficient although
        M itself is not (overparametrised rational models: weighting by 1/B smooths the
        columns): minimum-norm solution over the kept directions (reported per iterate in
        ``n_truncated``) or raise.  M itself (j = 0) must always have full rank.
    callback : callable, optional
        Called with every :class:`SKIterate` (e.g. to log J_OE per iteration).

    Returns
    -------
    SKResult

    Raises
    ------
    RankDeficientModelError
        If W M is rank deficient at some iteration.
    """
    if regularizer not in REGULARIZERS:
        raise ValueError(f"unknown regularizer '{regularizer}'; choose one of {REGULARIZERS}")
    if init not in ("equation_error", "model"):
        raise ValueError(f"unknown init '{init}'; choose 'equation_error' or 'model'")
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if lam < 0:
        raise ValueError(f"λ must be >= 0, got {lam}")
    model = copy.deepcopy(model)
    has_g = _has_approximator(model)
    lam_eff = lam if (has_g and regularizer == "orthogonal") else 0.0
    data = prepare_data(model, r, f_hat)
    seg, M, f = data["segments"], data["M"], data["f"]
    lm_kw = dict(max_iter=lm_max_iter, ftol=lm_ftol, gtol=lm_gtol, geodesic=geodesic)
    tol, cost_tol = tol / TIGHTEN, cost_tol / TIGHTEN   # make reproduce-check CHECK=tighten (lm.TIGHTEN)
    output_tol = output_tol / TIGHTEN
    if not output_tol >= 0:
        raise ValueError(f"output_tol must be >= 0, got {output_tol}")
    stall_tol = stall_tol / TIGHTEN
    if int(stall_window) < 0 or not stall_tol >= 0:
        raise ValueError(f"stall_window must be >= 0 and stall_tol >= 0, got {stall_window}, {stall_tol}")
    if cost_tol < 0:
        raise ValueError(f"cost_tol must be >= 0, got {cost_tol}")

    # j = 0: best linear approximation by equation error, B^0 = 1 ([K] Alg. 5, Remark 7)
    t0 = time.perf_counter()
    sub0 = model_subspace(M, column_scale=column_scale, rtol=rank_rtol, names=data["names"])
    if init == "equation_error":                                   # [K] Assumption 10 on M
        model.set_theta(sub0.solve(f))
    n_ref = model.reflect_unstable()
    snap = _snapshot(model)
    reg0 = 0.0
    if lam_eff > 0:                                # R^0 with the weighting of j = 0 (B^0 = 1)
        with torch.no_grad():
            reg0 = float(orthogonal_regularizer(sub0, model.exogenous_extra(data["inputs"]).numpy()))
    y_prev = _oe_output(model, data)
    iterates = [SKIterate(j=0, theta=snap[0], phi=snap[1], g_gain=snap[2], J_OE=oe_cost(model, data, y_prev),
                          regularizer=reg0, n_reflected=n_ref, lm_message="initialisation",
                          seconds=time.perf_counter() - t0)]
    reflected = [0] if n_ref else []
    if callback is not None:
        callback(iterates[0])

    converged, message = False, "max_iter"
    for j in range(1, int(max_iter) + 1):
        t0 = time.perf_counter()
        den = model.denominator()                                  # B^{j-1}(q)
        WM = filter_segments(M, [1.0], den, seg)                   # [K] (27), as a filter
        Wf = filter_segments(f, [1.0], den, seg)
        sub = model_subspace(WM, column_scale=column_scale, rtol=rank_rtol, names=data["names"],
                             rank_deficient=weighted_rank)
        lm_iter, lm_msg, lm_conv, reg = 0, "closed form", True, 0.0
        if has_g:
            phi, lmres = _varpro_step(model, data, sub, Wf, den, lam_eff, lm_kw)
            model.set_phi(phi)
            with torch.no_grad():
                g = model.exogenous_extra(data["inputs"]).numpy()
            Wg = filter_segments(g, [1.0], den, seg)
            theta = sub.solve(Wf - Wg)                             # θ(φ) = (WM)^+ W (f̂ − g)
            reg = float(orthogonal_regularizer(sub, Wg))
            lm_iter, lm_msg, lm_conv = lmres.n_iter, lmres.message, lmres.converged   # 'ftol'/… or 'max_iter'
        else:
            Wg = 0.0
            theta = sub.solve(Wf)                                  # closed-form LS
        model.set_theta(theta)
        e_w = Wf - WM @ theta - Wg
        J_w = float(e_w @ e_w) + lam_eff * reg
        n_ref = model.reflect_unstable()                           # SPEC §5
        if n_ref:
            reflected.append(j)
        snap = _snapshot(model)
        prev = iterates[-1]
        d_theta = (snap[0] - prev.theta) / sub.scale
        change = float(np.linalg.norm(d_theta) / max(np.linalg.norm(snap[0] / sub.scale), 1e-300))
        if has_g:
            change = max(change, float(np.linalg.norm(snap[1] - prev.phi)
                                       / max(np.linalg.norm(snap[1]), 1e-300)))
        y_now = _oe_output(model, data)
        J_OE = oe_cost(model, data, y_now)
        out_change = math.inf if y_now is None or y_prev is None or not J_OE > 0 else \
            float(np.linalg.norm(y_now - y_prev) / math.sqrt(J_OE))
        y_prev = y_now
        it = SKIterate(j=j, theta=snap[0], phi=snap[1], g_gain=snap[2], J_OE=J_OE,
                       J_weighted=J_w, regularizer=reg, change=change, output_change=out_change,
                       n_reflected=n_ref,
                       condition=sub.condition, n_truncated=sub.n_truncated, lm_iter=lm_iter,
                       lm_message=lm_msg, lm_converged=lm_conv, weighting=den.copy(),
                       seconds=time.perf_counter() - t0)
        iterates.append(it)
        if callback is not None:
            callback(it)
        # converged: the parameters stopped moving *and* this step's inner solve converged (a
        # small change from an LM stopped on its cap is not a fixed point of the SK map)
        settled = output_tol <= 0 or out_change <= output_tol
        if change < tol and it.lm_converged and settled:
            converged, message = True, "tol"
            break
        # ... or the criterion stopped moving ([K] (30): J_OE + λR; cost_tol > 0 only)
        J_prev, J_now = prev.J_OE + lam_eff * prev.regularizer, it.J_OE + lam_eff * it.regularizer
        if cost_tol > 0 and it.lm_converged and settled and abs(J_now - J_prev) <= cost_tol * abs(J_prev):
            converged, message = True, "cost_tol"
            break
        # ... or, without a fixed point, the best criterion stopped improving (stall_window > 0 only)
        if stall_window > 0 and _stalled([x.J_OE + lam_eff * x.regularizer for x in iterates],
                                         [x.lm_converged for x in iterates], int(stall_window), stall_tol,
                                         max_iter=int(max_iter)):
            message = "stalled"
            break

    if message == "max_iter":
        n_cap = sum(not it.lm_converged for it in iterates[1:])
        warnings.warn(f"SK iterations did not converge in {max_iter} iterations (last relative "
                      f"parameter change {iterates[-1].change:.2e}, tol {tol:.1e}; {n_cap} inner "
                      "solves stopped on their LM cap); returning the best iterate by J_OE (+ λR). Raise "
                      "max_iter / lm_max_iter or loosen tol if this is expected.",
                      SKNotConvergedWarning, stacklevel=2)
    # the best iterate by the criterion SK minimises: J_OE ([K] (7)), plus λR^{j-1}(φ^j) with
    # the regulariser ([K] (30)) — an early iterate with a lower J_OE but g_φ inside the model
    # subspace is not the regularised solution
    J = np.array([it.J_OE + lam_eff * it.regularizer for it in iterates])
    best = int(np.argmin(J)) if np.any(np.isfinite(J)) else len(iterates) - 1
    b = iterates[best]
    _restore(model, b.theta, b.phi, b.g_gain)
    return SKResult(model=model, best=best, iterates=iterates, converged=converged,
                    message=message, reflected=reflected, tol=float(tol), lam=lam_eff)


def _stalled(J: list, inner_ok: list, window: int, tol: float, max_iter: int | None = None) -> bool:
    """The last ``window`` iterates (inner solves converged) did not lower the best J by more
    than ``tol`` of the best before them; or (``max_iter`` given) that verdict is foreseen from
    the pace of the last two steps (the larger fall of the two, none if J rose), the last inner
    solve converged and j >= 3:

    - out of reach: at least three iterates after the best, and the iterations left to
      ``max_iter`` cannot bring J below ``(1 − tol)`` of the best at that pace;
    - a slow crawl: the last iterate is the best, its last fall at least half the one before
      (a steady pace, not a fixed point approached at a contraction of 1/2 or faster, which
      the parameter test is about to catch), and at that pace the next ``window`` iterations
      would lower it by less than ``tol`` of itself (the window rule, foreseen).

    A crawl along a valley with no fixed point: whichever rule stops it, the best iterate is
    the result."""
    if len(J) > window and all(inner_ok[-window:]) and not min(J[-window:]) < min(J[:-window]) * (1.0 - tol):
        return True
    if max_iter is None or len(J) < 4 or not inner_ok[-1]:
        return False
    pace = max(0.0, J[-3] - J[-2], J[-2] - J[-1])        # fall per SK iteration, recent
    b = int(np.argmin(J))
    if b == len(J) - 1:                                 # a new best: is it still worth a window?
        steady = J[-2] - J[-1] >= 0.5 * (J[-3] - J[-2]) > 0
        return steady and window * pace < tol * J[-1]
    if len(J) - 1 - b < 3:
        return False
    left = int(max_iter) - (len(J) - 1)                 # iterations still allowed (J[0] is j = 0)
    return left * pace < J[-1] - J[b] * (1.0 - tol)


def _sk_restart(job: tuple) -> tuple[SKResult, float, bool]:
    """One SK run for :func:`sk_restarts` (module level: picklable for a process pool)."""
    model, r, f_hat, kw = job
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SKNotConvergedWarning)
        res = sk_iterations(model, r, f_hat, **kw)
    warned = any(issubclass(w.category, SKNotConvergedWarning) for w in caught)
    return res, time.perf_counter() - t0, warned


def sk_restarts(models, r, f_hat, *, n_jobs: int = 1, progress: Callable | None = None,
                **kw) -> list[tuple[SKResult, float, bool]]:
    """:func:`sk_iterations` from several initial models (random restarts, SPEC §5).

    Parameters
    ----------
    models : sequence of RationalFeedforward
        One initial model per restart (e.g. g_φ initialised from different seeds).
    r, f_hat
        Training data, as :func:`sk_iterations`.
    n_jobs : int
        Worker processes (joblib, loky backend); 1 runs the restarts in this process.
    progress : callable, optional
        ``progress(iterable, total)`` wraps the results as they arrive, in order (a progress bar).
    **kw
        Passed to :func:`sk_iterations`.

    Returns
    -------
    list of (SKResult, seconds, not_converged)
        In the order of ``models``; ``not_converged`` is True when the run stopped at
        ``max_iter`` (its :class:`SKNotConvergedWarning` is captured, not re-raised).
    """
    jobs = [(m, r, f_hat, kw) for m in models]
    if int(n_jobs) <= 1 or len(jobs) == 1:
        out = (_sk_restart(j) for j in jobs)
    else:
        # joblib's loky processes (never fork a process that holds torch threads); inside a worker of
        # Hydra's joblib launcher joblib itself decides how far to nest; results in order as they end
        from joblib import Parallel, delayed  # lazy: saves 0.1 s of start-up (joblib: parallel restarts only)
        out = Parallel(n_jobs=min(int(n_jobs), len(jobs)), backend="loky",
                       return_as="generator")(delayed(_sk_restart)(j) for j in jobs)
    return list(progress(out, len(jobs)) if progress is not None else out)


# ----------------------------------------------------------------------------- direct OE
@dataclass
class OEResult:
    """Outcome of :func:`output_error_lm`.

    ``J_before``/``J_after`` are the minimised cost: J_OE ([K] (7)) for ``lam = 0``, else
    J_OE + λR with R frozen at the given weighting ([K] (30)); ``J_OE_*`` and ``R_*`` are its
    parts [N²].
    """

    model: RationalFeedforward
    J_before: float
    J_after: float
    lm: LMResult
    lam: float = 0.0
    J_OE_before: float = math.nan
    J_OE_after: float = math.nan
    R_before: float = 0.0
    R_after: float = 0.0

    @property
    def improvement(self) -> float:
        """Relative decrease of the minimised cost, (J_before − J_after)/J_before."""
        return (self.J_before - self.J_after) / self.J_before if self.J_before > 0 else 0.0

    @property
    def oe_improvement(self) -> float:
        """Relative decrease of J_OE alone."""
        b, a = self.J_OE_before, self.J_OE_after
        return (b - a) / b if b > 0 else 0.0

    @property
    def stop_reason(self) -> str:
        """The LM's stop message ('ftol', 'gtol', 'mu_max', 'max_iter', …)."""
        return self.lm.message

    @property
    def converged(self) -> bool:
        return self.lm.converged


def _frozen_subspace(model, data: dict, weighting, *, column_scale: bool = True,
                     rank_rtol: float | None = None) -> ModelSubspace:
    """SVD of W M for W = 1/B_w with B_w's q^{-1} coefficients ``weighting`` (frozen)."""
    WM = filter_segments(data["M"], [1.0], np.asarray(weighting, dtype=np.float64), data["segments"])
    return model_subspace(WM, column_scale=column_scale, rtol=rank_rtol, names=data["names"],
                          rank_deficient="truncate")


def frozen_regularizer(model, r, f_hat, weighting, *, column_scale: bool = True,
                       rank_rtol: float | None = None) -> float:
    """R(φ) = ‖(ΣVᵀ)^{-1} U1ᵀ W g_φ(r)‖² ([K] (29)) of ``model``'s approximator with the
    weighting W = 1/B_w frozen (``weighting``: q^{-1} coefficients of B_w, e.g.
    :attr:`SKIterate.weighting`); 0 without approximator [N²]."""
    if not _has_approximator(model):
        return 0.0
    data = prepare_data(model, r, f_hat)
    sub = _frozen_subspace(model, data, weighting, column_scale=column_scale, rank_rtol=rank_rtol)
    with torch.no_grad():
        g = model.exogenous_extra(data["inputs"]).numpy()
    Wg = filter_segments(g, [1.0], np.asarray(weighting, dtype=np.float64), data["segments"])
    return float(orthogonal_regularizer(sub, Wg))


def output_error_problem(model: RationalFeedforward, data: dict, *, lam: float = 0.0,
                         sub: ModelSubspace | None = None, weighting=None):
    """Residual and exact Jacobian of J_OE ([K] (7)) over x = col(a, b, φ), optionally plus
    λR with R frozen ([K] (30)).

    With f = (R a + g)/B and e = f̂ − f: ∂e/∂a = −R/B, ∂e/∂b_i = ψ_i(f)/B,
    ∂e/∂φ = −(∂g/∂φ)/B, all computed by filtering.  The residual is +inf when B is
    unstable (LM then rejects the step).  With ``lam > 0`` (approximator models only) the
    residual has p more rows √λ (ΣVᵀ)^{-1} U1ᵀ W_w g_φ(r) (``sub``: SVD of W_w M, ``weighting``:
    the q^{-1} coefficients of B_w; both frozen, independent of x), so ‖residual‖² =
    J_OE + λR.

    Returns
    -------
    residual, jacobian : callable
        ``residual(x) -> e`` [N (+p)], ``jacobian(x) -> ∂e/∂x`` [N (+p), n_x] (torch float64).
    x0 : torch.Tensor
        The model's current x.
    """
    seg, inp, f_hat_c = data["segments"], data["inputs"], data["f"]
    R = inp["R"]
    has_g = _has_approximator(model)
    n_th = model.n_a + model.n_b
    reg = lam > 0 and has_g
    if reg and (sub is None or weighting is None):
        raise ValueError("lam > 0 needs the frozen subspace `sub` and `weighting` of the regulariser")
    sq = math.sqrt(lam) if reg else 0.0
    w_den = np.asarray(weighting, dtype=np.float64) if reg else None

    # a tanh MLP g_φ: the residual keeps its layer outputs (g_forward: the bits of g_value), and
    # W ∂g/∂φ is formed from them in one numba pass per filter (SharedARPGNN.filtered_jacobian)
    # instead of torch's per-sample Jacobian filtered column by column by lfilter
    closed = has_g and bool(getattr(model, "closed_form_jacobian", False))
    fwd = _LastForward(model, inp) if closed else None

    def split(x: torch.Tensor):
        xn = x.detach().numpy()
        trial = RationalFeedforward(model.n_a, model.n_b, model.basis, model.Ts, b=xn[model.n_a:n_th])
        u = R @ xn[:model.n_a]
        g = None
        if has_g:
            g = (fwd(x[n_th:]) if closed else model.g_value(inp, x[n_th:])).numpy()
            u = u + g
        return trial, u, g

    def residual(x: torch.Tensor) -> torch.Tensor:
        trial, u, g = split(x)
        n_extra = sub.p if reg else 0
        if not trial.is_stable():
            return torch.full((seg.n + n_extra,), math.inf, dtype=torch.float64)
        e = f_hat_c - filter_segments(u, [1.0], trial.denominator(), seg)
        if reg:
            e = np.concatenate([e, sq * sub.coordinates(filter_segments(g, [1.0], w_den, seg))])
        return torch.from_numpy(e)

    def jacobian(x: torch.Tensor) -> torch.Tensor:
        trial, u, _ = split(x)
        den = trial.denominator()
        fsim = filter_segments(u, [1.0], den, seg)
        J = np.empty((seg.n + (sub.p if reg else 0), x.numel()))
        J[:seg.n, :n_th] = filter_segments(np.hstack([-R, trial.ar_regressors(fsim, seg)]), [1.0], den, seg)
        if has_g:
            # (1/D)(q) ∂g/∂φ for a filter denominator D: closed form from the layer outputs split kept,
            # else torch's per-sample ∂g/∂φ filtered column by column
            phi = x[n_th:]
            if closed:
                a = fwd.at(phi)
                filtered = lambda d: model.filtered_jacobian(inp, phi, [1.0], d, seg, a)   # noqa: E731
            else:
                Jg = model.g_and_jacobian(inp, phi)[1].numpy()
                filtered = lambda d: filter_segments(Jg, [1.0], d, seg)                    # noqa: E731
            J[:seg.n, n_th:] = filtered(den)
            np.negative(J[:seg.n, n_th:], out=J[:seg.n, n_th:])   # ∂e/∂φ = −(∂g/∂φ)/B
            if reg:                                               # R's rows: φ only, [p, n_φ]
                J[seg.n:, :n_th] = 0.0
                J[seg.n:, n_th:] = sq * sub.coordinates(filtered(w_den))
        return torch.from_numpy(J)

    x0 = [torch.from_numpy(model.theta)]
    if has_g:
        x0.append(model.phi)
    return residual, jacobian, torch.cat(x0)


def output_error_lm(model: RationalFeedforward, r, f_hat, *, max_iter: int = 50,
                    ftol: float = 1e-12, gtol: float = 1e-12, lam: float = 0.0, weighting=None,
                    column_scale: bool = True, rank_rtol: float | None = None) -> OEResult:
    """Minimise J_OE ([K] (7)) directly by LM over (a, b, φ), starting from ``model``.

    Exact Jacobian by filtering (:func:`output_error_problem`); steps that make B unstable
    are rejected, so the result stays stable.  Used to check that SK reached the
    output-error optimum (SPEC §8 K3).  The input model is not modified.

    With ``lam > 0`` (a model with approximator) the cost is J_OE + λR, R the orthogonal
    regulariser ([K] (29)) frozen at the weighting W = 1/B_w, ``weighting`` the q^{-1}
    coefficients of B_w (for an SK result: ``iterates[-1].weighting``, the weighting of the last
    SK step): the criterion the regularised SK minimises ([K] (30)), SPEC §8 K3.

    ``max_iter`` is a safety cap; the LM stops on ``ftol``/``gtol`` (see
    :attr:`OEResult.stop_reason`).
    """
    model = copy.deepcopy(model)
    model.check_stable()
    data = prepare_data(model, r, f_hat)
    reg = lam > 0 and _has_approximator(model)
    sub = None
    if reg:
        if weighting is None:
            raise ValueError("lam > 0 needs the frozen weighting (q^{-1} coefficients of B_w)")
        sub = _frozen_subspace(model, data, weighting, column_scale=column_scale, rank_rtol=rank_rtol)
    residual, jacobian, x0 = output_error_problem(model, data, lam=lam if reg else 0.0, sub=sub,
                                                  weighting=weighting)
    n = data["segments"].n

    def parts(x: torch.Tensor) -> tuple[float, float]:
        e = residual(x).numpy()
        return float(e[:n] @ e[:n]), (float(e[n:] @ e[n:]) / lam if reg else 0.0)

    J0, R0 = parts(x0)
    res = levenberg_marquardt(residual, x0, jacobian=jacobian, max_iter=max_iter, ftol=ftol, gtol=gtol)
    J1, R1 = parts(res.theta)
    n_th = model.n_a + model.n_b
    model.set_theta(res.theta[:n_th].numpy())
    if _has_approximator(model):
        model.set_phi(res.theta[n_th:])
    lam_eff = lam if reg else 0.0
    return OEResult(model=model, J_before=J0 + lam_eff * R0, J_after=J1 + lam_eff * R1, lm=res,
                    lam=lam_eff, J_OE_before=J0, J_OE_after=J1, R_before=R0, R_after=R1)
