"""Norm-optimal iterative learning control (SPEC §4, §2.1, §2.3; [B2] (22)-(23)).

Each trial j runs the true system with the input f_j and measures the tracking error e_j.
The next input minimises the predicted error of a linear model G (lifted, N×N, lower
triangular Toeplitz of its impulse response)::

    f_{j+1} = f_j + L Δf,   Δf = argmin ‖e_j - G Δf‖² + w ‖f_j + Δf‖² + w_Δ ‖Δf‖²
            ⇒ (GᵀG + (w + w_Δ) I) Δf = Gᵀ e_j - w f_j

with learning gain L.  G is the linear part of the plant seen by the feedforward: the process
sensitivity P S = P/(1 + P C) for a closed loop, the plant itself in open loop (for the
two-mass plant: its linear part with damping c1, SPEC §2.1).

Two back-ends with one interface (:class:`NormOptimalUpdate`):

- :class:`LiftedUpdate` — dense G from the impulse response, solved through its SVD
  ``G = U S Vᵀ``: ``Δf = V (S Uᵀ e - w Vᵀ f) / (S² + w + w_Δ)``.  Exact to rounding even at
  condition numbers ~1e19 (never forms GᵀG); for short references (N ≲ 1000).
- :class:`MatrixFreeUpdate` — G and Gᵀ applied as filters (Gᵀ is the time-reversed filter: a
  lower triangular Toeplitz T satisfies Tᵀ = J T J, J the flip), the normal equations solved by
  conjugate gradients (:func:`scipy.sparse.linalg.cg` on a LinearOperator), optionally
  preconditioned with the model inverse ``(GᵀG)^-1 = G^-1 G^-T`` (exact for a lifted
  lower triangular Toeplitz G with nonzero diagonal; needs a stable inverse, i.e. a
  minimum-phase model with direct feedthrough).  Never builds an N×N matrix.

Which weight: SPEC §2.3's numbers for rot_trans_nmp (rms < 1e-9 m in about 7 trials at
1e-10 σ_max², a stall near 1e-7 m at 7e-7 σ_max²) are those of the weight on the input
*change*, ``w_delta`` (measured: 4.7e-10 m at trial 6; 9.9e-8 m after 12 trials).  A weight
``w`` on f itself biases the fixed point (Gᵀ e∞ = w f∞): 1.55e-9 m at 1e-10 σ_max², 5.2e-7 m at
7e-7 σ_max² (the closed-form Tikhonov residual); below ~1e-12 σ_max² that bias is negligible.
For the invertible two-mass model use w = 0 (or w ≲ σ_min² ≈ 6e-14 m²/N²).

The filters are state-space recursions (numba), not ``lfilter`` on transfer-function
polynomials: at Ts = 1e-3 the q^-1 polynomials of the two-mass model have roots clustered at
z ≈ 1 and lose ~8 digits (SPEC §2.1).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:   # annotations only; imported where used (start-up, issue 19)
    import control

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.linalg import toeplitz
from scipy.sparse.linalg import LinearOperator, cg, svds
from tqdm.auto import tqdm

from pipeline.systems._statespace import ss_step

__all__ = [
    "impulse_response", "lifted_matrix", "process_sensitivity", "LTIFilter",
    "NormOptimalUpdate", "LiftedUpdate", "MatrixFreeUpdate", "make_update", "ILCResult",
    "norm_optimal_ilc", "system_trial", "rms",
]


def rms(x: np.ndarray) -> float:
    """Root mean square ``‖x‖₂/√N`` ([B2]'s normalised 2-norm)."""
    x = np.asarray(x, dtype=np.float64)
    return float(np.linalg.norm(x) / np.sqrt(x.size))


# --------------------------------------------------------------------------------------------
# linear model as a filter
# --------------------------------------------------------------------------------------------
@njit(cache=True)
def _ss_filter(A, B, C, D, u):  # pragma: no cover - compiled
    """y(k) = C x(k) + D u(k), x(k+1) = A x(k) + B u(k), x(0) = 0, SISO; u shape (m, N)."""
    n = A.shape[0]
    m, N = u.shape
    y = np.empty((m, N))
    x = np.zeros(n)
    xn = np.zeros(n)
    for b in range(m):
        for i in range(n):
            x[i] = 0.0
        for k in range(N):
            y[b, k] = ss_step(A, B, C, D, x, xn, u[b, k])
    return y


def ss_filter(A, B, C, D, u) -> np.ndarray:
    """:func:`_ss_filter` of u (N,) or (m, N), passed as C-contiguous rows: one compiled specialisation for
    every caller (a strided u, e.g. an adjoint's time-reversed view, compiled another; same operations)."""
    return _ss_filter(A, B, C, D, np.ascontiguousarray(np.atleast_2d(np.asarray(u, dtype=np.float64))))


def _as_discrete_siso_ss(sys) -> control.StateSpace:
    import control  # lazy: saves 1.9 s of start-up (python-control)
    if not isinstance(sys, (control.StateSpace, control.TransferFunction)):
        raise TypeError(f"the ILC model must be a python-control StateSpace or TransferFunction, "
                        f"got {type(sys).__name__}")
    if not sys.isdtime(strict=True):
        raise ValueError("the ILC model must be discrete time (dt = Ts > 0); discretise it with "
                         "control.c2d first")
    if sys.ninputs != 1 or sys.noutputs != 1:
        raise ValueError(f"the ILC model must be SISO, got {sys.noutputs}x{sys.ninputs}")
    return control.ss(sys)


class LTIFilter:
    """A discrete SISO LTI system applied to signals from rest: ``y = G u`` (and ``Gᵀ``).

    Parameters
    ----------
    sys : control.StateSpace | control.TransferFunction
        Discrete-time SISO model (dt > 0).  Prefer a state-space realisation: TF polynomials
        with clustered poles are ill-conditioned.
    """

    def __init__(self, sys):
        ss = _as_discrete_siso_ss(sys)
        self.sys = ss
        self.dt = float(ss.dt) if ss.dt is not True else 1.0
        self._A = np.ascontiguousarray(ss.A, dtype=np.float64)
        self._B = np.ascontiguousarray(ss.B, dtype=np.float64).ravel()
        self._C = np.ascontiguousarray(ss.C, dtype=np.float64).ravel()
        self._D = float(np.asarray(ss.D).ravel()[0])

    def apply(self, u: np.ndarray) -> np.ndarray:
        """``G u`` for u of shape (N,) or (batch, N) (lifted: lower triangular Toeplitz × u)."""
        y = ss_filter(self._A, self._B, self._C, self._D, u)
        return y[0] if np.ndim(u) == 1 else y

    def adjoint(self, v: np.ndarray) -> np.ndarray:
        """``Gᵀ v``: the filter run on the time-reversed signal, reversed back (Tᵀ = J T J)."""
        v = np.asarray(v, dtype=np.float64)
        return self.apply(v[..., ::-1])[..., ::-1]

    def inverse(self) -> "LTIFilter":
        """The causal inverse G^-1 (needs D ≠ 0); raises if it is unstable (non-minimum phase)."""
        import control  # lazy: saves 1.9 s of start-up (python-control)
        if self._D == 0.0:
            raise ValueError("the model has no direct feedthrough (D = 0): its lifted matrix has "
                             "a zero diagonal and no causal inverse; use preconditioner='none'")
        A = self._A - np.outer(self._B, self._C) / self._D
        rho = float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0
        if rho >= 1.0:
            raise ValueError(f"the model inverse is unstable (largest |pole| {rho:.6g} >= 1: a "
                             "zero outside the unit circle, non-minimum phase); use "
                             "preconditioner='none' or the lifted back-end")
        inv = control.ss(A, self._B[:, None] / self._D, -self._C[None, :] / self._D,
                         [[1.0 / self._D]], self.sys.dt)
        return LTIFilter(inv)


def impulse_response(sys, N: int) -> np.ndarray:
    """First N Markov parameters h(0..N-1) of a discrete SISO system (unit pulse at k = 0)."""
    N = _check_n(N)
    e0 = np.zeros(N)
    e0[0] = 1.0
    return LTIFilter(sys).apply(e0)


def lifted_matrix(sys_discrete, N: int) -> np.ndarray:
    """Lifted (finite-time) matrix of a discrete SISO system: ``G[i, j] = h(i - j)`` for i ≥ j.

    Parameters
    ----------
    sys_discrete : control.StateSpace | control.TransferFunction
        Discrete-time SISO system (dt > 0), e.g. the process sensitivity P S.
    N : int
        Number of samples.

    Returns
    -------
    ndarray, shape (N, N)
        Lower triangular Toeplitz matrix with ``y = G u`` for signals starting from rest.
    """
    h = impulse_response(sys_discrete, N)
    return toeplitz(h, np.zeros(N))


def process_sensitivity(P, C) -> control.StateSpace:
    """``P S = P / (1 + P C)``: the map from feedforward to output in the loop of SPEC §2.

    Both discrete with one dt; returned as a state-space model (u = C(r - y) + u_ff).
    """
    import control  # lazy: saves 1.9 s of start-up (python-control)
    return control.ss(control.feedback(control.ss(P), control.ss(C), sign=-1))


def _check_n(N) -> int:
    N = int(N)
    if N < 1:
        raise ValueError(f"number of samples N must be >= 1, got {N}")
    return N


# --------------------------------------------------------------------------------------------
# the norm-optimal update, two back-ends
# --------------------------------------------------------------------------------------------
class NormOptimalUpdate(ABC):
    """Solves ``Δf = argmin ‖e - G Δf‖² + w ‖f + Δf‖² + w_Δ ‖Δf‖²`` for one reference length.

    ``w`` [m²/N²] weighs the input itself (a bias toward small inputs at convergence: the
    fixed point satisfies Gᵀ e = w f), ``w_Δ`` [m²/N²] the change of input (slows learning,
    damps noise, no bias).
    """

    N: int
    w: float
    w_delta: float

    def set_weights(self, w: float, w_delta: float) -> None:
        """Set the weights [m²/N²] of ‖f‖² and ‖Δf‖² (used at each step; no rebuild needed)."""
        self.w, self.w_delta = _check_weights(w, w_delta)

    @abstractmethod
    def step(self, e: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Return Δf [N] for the measured error e [m] of the input f [N]."""

    @property
    @abstractmethod
    def sigma_max(self) -> float:
        """Largest singular value of the lifted G [m/N]."""

    def _check(self, e, f) -> tuple[np.ndarray, np.ndarray]:
        e = np.asarray(e, dtype=np.float64)
        f = np.asarray(f, dtype=np.float64)
        if e.shape != (self.N,) or f.shape != (self.N,):
            raise ValueError(f"ILC update built for N = {self.N} samples, got error shape {e.shape} "
                             f"and input shape {f.shape}")
        return e, f


def _check_weights(w, w_delta) -> tuple[float, float]:
    w, w_delta = float(w), float(w_delta)
    if not (w >= 0 and w_delta >= 0 and np.isfinite(w) and np.isfinite(w_delta)):
        raise ValueError(f"ILC weights must be finite and >= 0, got w = {w}, w_delta = {w_delta}")
    return w, w_delta


class LiftedUpdate(NormOptimalUpdate):
    """Dense lifted back-end: SVD of G once, each update O(N²) (short references).

    Parameters
    ----------
    G : ndarray (N, N) | control LTI
        The lifted model, or a discrete SISO model to lift with :func:`lifted_matrix`.
    N : int, optional
        Needed when G is a model.
    w, w_delta : float
        Weights [m²/N²] of ‖f‖² and ‖Δf‖².  With w = w_Δ = 0 the update is the minimum-norm
        least-squares solution (singular values below N·eps·σ_max are dropped).
    """

    def __init__(self, G, N: int | None = None, w: float = 0.0, w_delta: float = 0.0):
        if not isinstance(G, np.ndarray):
            if N is None:
                raise ValueError("LiftedUpdate: give N (samples) when G is a model, not a matrix")
            G = lifted_matrix(G, N)
        G = np.asarray(G, dtype=np.float64)
        if G.ndim != 2 or G.shape[0] != G.shape[1]:
            raise ValueError(f"the lifted matrix must be square N×N, got shape {G.shape}")
        self.N = G.shape[0]
        self.w, self.w_delta = _check_weights(w, w_delta)
        self.U, self.s, self.Vt = np.linalg.svd(G)
        self.G = G

    @property
    def sigma_max(self) -> float:
        return float(self.s[0])

    def step(self, e, f):
        e, f = self._check(e, f)
        lam = self.w + self.w_delta
        num = self.s * (self.U.T @ e) - self.w * (self.Vt @ f)
        den = self.s ** 2 + lam
        if lam == 0.0:   # pseudo-inverse: drop numerically zero singular values
            keep = self.s > self.N * np.finfo(float).eps * self.s[0]
            x = np.where(keep, num / np.where(keep, den, 1.0), 0.0)
        else:
            x = num / den
        return self.Vt.T @ x


class MatrixFreeUpdate(NormOptimalUpdate):
    """Matrix-free back-end: G, Gᵀ as (time-reversed) filters, CG on the normal equations.

    Parameters
    ----------
    model : control.StateSpace | control.TransferFunction
        Discrete SISO model of the linear part.
    N : int
        Samples per trial.
    w, w_delta : float
        Weights [m²/N²] of ‖f‖² and ‖Δf‖²; w + w_Δ > 0 keeps the system positive definite.
    preconditioner : {"auto", "inverse", "none"}
        ``inverse``: PCG with ``M = G^-1 G^-T`` (the exact (GᵀG)^-1; needs a minimum-phase model
        with feedthrough), turning the ~σ_max²/σ_min² condition number into 1 + (w+w_Δ)/σ_min².
        ``auto``: inverse when the model allows it, else none.
    rtol : float
        CG relative residual tolerance.
    maxiter : int, optional
        CG iteration cap per trial (default 1000 for ``none``, 500 for ``inverse``).
    """

    def __init__(self, model, N: int, w: float = 0.0, w_delta: float = 0.0,
                 preconditioner: str = "auto", rtol: float = 1e-12, maxiter: int | None = None):
        self.N = _check_n(N)
        self.w, self.w_delta = _check_weights(w, w_delta)
        self.G = LTIFilter(model)
        if preconditioner not in ("auto", "inverse", "none"):
            raise ValueError(f"preconditioner must be 'auto', 'inverse' or 'none', "
                             f"got {preconditioner!r}")
        self.Ginv = None
        if preconditioner in ("auto", "inverse"):
            try:
                self.Ginv = self.G.inverse()
            except ValueError:
                if preconditioner == "inverse":
                    raise
        self.preconditioner = "inverse" if self.Ginv is not None else "none"
        self.rtol = float(rtol)
        self.maxiter = int(maxiter) if maxiter is not None else (
            500 if self.Ginv is not None else 1000)
        self._sigma_max: float | None = None
        self.cg_iterations: list[int] = []
        n = self.N
        self.op = LinearOperator((n, n), matvec=lambda x: self.G.apply(np.ravel(x)),
                                 rmatvec=lambda x: self.G.adjoint(np.ravel(x)), dtype=np.float64)

    def normal_matvec(self, x: np.ndarray) -> np.ndarray:
        """``(GᵀG + (w + w_Δ) I) x`` via two filter passes."""
        x = np.asarray(x, dtype=np.float64).ravel()
        return self.G.adjoint(self.G.apply(x)) + (self.w + self.w_delta) * x

    @property
    def sigma_max(self) -> float:
        if self._sigma_max is None:
            if self.N <= 2:
                self._sigma_max = float(np.linalg.norm(lifted_matrix(self.G.sys, self.N), 2))
            else:
                self._sigma_max = float(svds(self.op, k=1, return_singular_vectors=False,
                                             random_state=0)[0])
        return self._sigma_max

    def step(self, e, f):
        e, f = self._check(e, f)
        if self.w + self.w_delta == 0.0 and self.Ginv is None:
            raise ValueError("the matrix-free update needs w + w_delta > 0 (CG on the singular "
                             "normal equations) unless the model inverse preconditioner is used")
        b = self.G.adjoint(e) - self.w * f
        A = LinearOperator((self.N, self.N), matvec=self.normal_matvec, dtype=np.float64)
        M = None
        if self.Ginv is not None:
            Ginv = self.Ginv
            M = LinearOperator((self.N, self.N), dtype=np.float64,
                               matvec=lambda x: Ginv.apply(Ginv.adjoint(np.ravel(x))))
        count = [0]

        def _cb(_):
            count[0] += 1

        x, info = cg(A, b, rtol=self.rtol, atol=0.0, maxiter=self.maxiter, M=M, callback=_cb)
        self.cg_iterations.append(count[0])
        if info < 0:
            raise RuntimeError(f"CG failed in the ILC update (info = {info})")
        return x


def make_update(model, N: int, w: float = 0.0, w_delta: float = 0.0, backend: str = "auto",
                **matrix_free_kw) -> NormOptimalUpdate:
    """Build the update of the chosen back-end: ``lifted``, ``matrix_free`` or ``auto``
    (lifted for N ≤ 1000, matrix-free above)."""
    N = _check_n(N)
    if backend == "auto":
        backend = "lifted" if N <= 1000 else "matrix_free"
    if backend == "lifted":
        return LiftedUpdate(model, N, w=w, w_delta=w_delta)
    if backend == "matrix_free":
        return MatrixFreeUpdate(model, N, w=w, w_delta=w_delta, **matrix_free_kw)
    raise ValueError(f"unknown ILC backend {backend!r}; use 'lifted', 'matrix_free' or 'auto'")


# --------------------------------------------------------------------------------------------
# the ILC loop
# --------------------------------------------------------------------------------------------
@dataclass
class ILCResult:
    """History of an ILC run: ``inputs[j]`` [N] was applied in trial j and gave ``rms[j]`` [m].

    ``error`` is the last trial's measured error [m]; ``converged`` says whether the tolerance
    was reached; ``w`` the absolute input weight used [m²/N²].
    """

    inputs: np.ndarray
    rms: np.ndarray
    error: np.ndarray
    converged: bool
    w: float
    w_delta: float
    extras: dict = field(default_factory=dict)

    @property
    def f(self) -> np.ndarray:
        """The input of the last trial [N]."""
        return self.inputs[-1]

    @property
    def n_trials(self) -> int:
        return int(self.rms.size)


def norm_optimal_ilc(run_trial: Callable[[np.ndarray], np.ndarray], model, N: int | None = None,
                     *, f0: np.ndarray | None = None, gain: float = 1.0, w: float | None = None,
                     w_rel: float | None = None, w_delta: float = 0.0, n_trials: int = 10,
                     tol: float = 0.0, backend: str = "auto", update: NormOptimalUpdate | None = None,
                     progress: bool = False, **matrix_free_kw) -> ILCResult:
    """Norm-optimal ILC (SPEC §4): run, measure, update, repeat.

    Parameters
    ----------
    run_trial : callable
        ``e = run_trial(f)``: apply input f [N] to the true system (any plant, e.g. through
        :func:`system_trial`) and return the measured tracking error r - y [m].
    model : control LTI
        Discrete SISO model of the linear part seen by f (P S in closed loop, the plant in
        open loop).  Ignored when ``update`` is given.
    N : int, optional
        Samples per trial (default: the length of ``f0``).
    f0 : ndarray, optional
        Input of the first trial [N] (default zeros).
    gain : float
        Learning gain L in (0, 2): ``f_{j+1} = f_j + L Δf``.
    w, w_rel : float, optional
        Weight of ‖f‖² [m²/N²], either absolute (``w``) or relative to σ_max(G)²
        (``w = w_rel σ_max²``, the SPEC §2.3 scale); default 0.
    w_delta : float
        Weight of ‖Δf‖² [m²/N²].
    n_trials : int
        Maximum number of trials (runs of the true system).
    tol : float
        Stop after the first trial whose rms error is ≤ tol [m].
    backend : str
        ``lifted``, ``matrix_free`` or ``auto`` (see :func:`make_update`).
    update : NormOptimalUpdate, optional
        A prebuilt update (reuse its SVD / preconditioner across runs); its weights are used.
    progress : bool
        Show a tqdm progress bar.
    **matrix_free_kw
        ``preconditioner``, ``rtol``, ``maxiter`` of :class:`MatrixFreeUpdate`.

    Returns
    -------
    ILCResult
        Every trial's input and rms error (trial 0 uses f0).
    """
    if f0 is None:
        if N is None:
            raise ValueError("give N (samples per trial) or an initial input f0")
        f = np.zeros(_check_n(N))
    else:
        f = np.array(f0, dtype=np.float64)
        if f.ndim != 1 or (N is not None and f.size != int(N)):
            raise ValueError(f"f0 must be 1-D with N = {N} samples, got shape {f.shape}")
    N = f.size
    if not 0.0 < gain < 2.0:
        raise ValueError(f"learning gain must lie in (0, 2), got {gain}")
    n_trials = int(n_trials)
    if n_trials < 1:
        raise ValueError(f"n_trials must be >= 1, got {n_trials}")
    if update is None:
        if w is not None and w_rel is not None:
            raise ValueError("give the input weight as w (absolute) or w_rel (× σ_max²), not both")
        update = make_update(model, N, w=0.0, w_delta=w_delta, backend=backend, **matrix_free_kw)
        if w_rel is not None:
            update.set_weights(float(w_rel) * update.sigma_max ** 2, update.w_delta)
        elif w is not None:
            update.set_weights(w, update.w_delta)
    else:
        if w is not None or w_rel is not None:
            raise ValueError("give the weights to the prebuilt update (update.w, update.w_delta), "
                             "not to norm_optimal_ilc")
        if update.N != N:
            raise ValueError(f"the given update is built for N = {update.N}, the input has {N} "
                             "samples")
    inputs, rms_hist = [], []
    converged = False
    bar = tqdm(total=n_trials, desc="ILC trials", disable=not progress, leave=False)
    e = np.zeros(N)
    for j in range(n_trials):
        e = np.asarray(run_trial(f), dtype=np.float64)
        if e.shape != (N,) or not np.all(np.isfinite(e)):
            raise ValueError(f"run_trial must return a finite error of shape ({N},), got shape "
                             f"{e.shape} (trial {j})")
        inputs.append(f.copy())
        rms_hist.append(rms(e))
        bar.set_postfix(rms=f"{rms_hist[-1]:.3e}", refresh=False)
        bar.update(1)             # the count advances with each trial (a manual bar: n is current)
        if rms_hist[-1] <= tol:
            converged = True
            break
        if j < n_trials - 1:
            f = f + gain * update.step(e, f)
    bar.close()
    extras = {}
    if isinstance(update, MatrixFreeUpdate):
        extras["cg_iterations"] = list(update.cg_iterations)
    return ILCResult(np.array(inputs), np.array(rms_hist), e, converged, update.w,
                     update.w_delta, extras)


def system_trial(system, r: np.ndarray, rng: np.random.Generator | None = None
                 ) -> Callable[[np.ndarray], np.ndarray]:
    """A ``run_trial`` for :func:`norm_optimal_ilc`: simulate ``system`` with feedforward f.

    Each call draws a fresh noise realisation from the system's noise model with ``rng``
    (noise-free when rng is None) and returns the measured error r - y [m].
    """
    r = np.asarray(r, dtype=np.float64)

    def run(f: np.ndarray) -> np.ndarray:
        v = system.noise(r.size, rng) if rng is not None else None
        return r - system.simulate(r, u_ff=f, v=v).y

    return run
