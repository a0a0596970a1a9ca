"""Norm-optimal ILC solved exactly in O(N): the finite-horizon LQ tracking problem (issue 50).

The norm-optimal update ([B2] (22)-(23); Amann, Owens, Rogers 1996, IEE Proc. Control Theory Appl. 143(2))::

    Δ = argmin ‖e - G Δ‖² + w ‖f + Δ‖² + w_Δ ‖Δ‖²   ⇔   (GᵀG + λ I) Δ = Gᵀ e - w f,   λ = w + w_Δ

with G the lifted (lower triangular Toeplitz) matrix of a causal SISO model x(k+1) = A x + B u,
z = C x + D u from rest, is a linear-quadratic tracking problem over the trial's N samples: stage cost
(e_k - C x_k - D u_k)² + λ u_k² - 2 c_k u_k (c = -w f), no terminal cost, x_0 = 0. Its minimiser is
exact in one backward and one forward sweep (Bryson & Ho 1975, ch. 5; the standard implementation of
norm-optimal ILC, e.g. Barton & Alleyne 2011, IEEE TCST 19(1)):

    Riccati (data-free, once per N and λ), P_N = 0, k = N-1 … 0:
        H_k = D² + λ + Bᵀ P B,   K_k = (D C + Bᵀ P A) / H_k,
        P_k = (A - B K_k)ᵀ P (A - B K_k) + (C - D K_k)ᵀ (C - D K_k) + λ K_kᵀ K_k      (Joseph form: PSD)
    adjoint (per trial), p_N = 0:  g_k = -D e_k - c_k + Bᵀ p_{k+1},
        p_k = -Cᵀ e_k + Aᵀ p_{k+1} - K_kᵀ g_k
    forward, x_0 = 0:  u_k = -K_k x_k - g_k / H_k,   x_{k+1} = A x_k + B u_k

(P = P_{k+1}, p = p_{k+1} on the right). The cost is divided by λ first (C, D, e by √λ): the Riccati
then sees G/√λ, never the model's units. Cost O(N n³) for the gains, O(N n²) per trial; n the model's
order. No N×N matrix, no iteration cap: the stop reason of a solve is its residual on the normal
equations, measured with two filter passes (G, then Gᵀ as the time-reversed filter) and refined
(Δ += solve(residual), at most ``max_sweeps`` times) until ``rtol``; a solve that stays above it
says ``cap`` (:class:`SolveReport`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.sparse.linalg import LinearOperator, svds

from pipeline.invert.ilc import NormOptimalUpdate, _as_discrete_siso_ss, _check_n, _check_weights, ss_filter

__all__ = ["RiccatiUpdate", "SolveReport"]


@njit(cache=True)
def _gains(A, B, C, D, lam, N):  # pragma: no cover - compiled
    """K_k (N, n) and H_k (N,) of the backward Riccati sweep (module docstring), λ already 1 after scaling
    when called from :class:`RiccatiUpdate`."""
    n = A.shape[0]
    K = np.empty((N, n))
    H = np.empty(N)
    P = np.zeros((n, n))
    Acl = np.empty((n, n))
    Ccl = np.empty(n)
    for k in range(N - 1, -1, -1):
        PB = P @ B
        h = D * D + lam + B @ PB
        Kk = (D * C + PB @ A) / h          # Bᵀ P A = (P B)ᵀ A, P symmetric
        for i in range(n):
            Ccl[i] = C[i] - D * Kk[i]
            for j in range(n):
                Acl[i, j] = A[i, j] - B[i] * Kk[j]
        P = Acl.T @ P @ Acl + np.outer(Ccl, Ccl) + lam * np.outer(Kk, Kk)
        P = 0.5 * (P + P.T)
        K[k] = Kk
        H[k] = h
    return K, H


@njit(cache=True)
def _sweeps(A, B, C, D, K, H, e, c):  # pragma: no cover - compiled
    """The minimiser u of Σ (e_k - z_k)² + λ u_k² - 2 c_k u_k: adjoint backward, state forward."""
    N, n = K.shape
    g = np.empty(N)
    p = np.zeros(n)
    for k in range(N - 1, -1, -1):
        gk = -D * e[k] - c[k] + B @ p
        p = -C * e[k] + A.T @ p - K[k] * gk
        g[k] = gk
    u = np.empty(N)
    x = np.zeros(n)
    for k in range(N):
        uk = -(K[k] @ x) - g[k] / H[k]
        u[k] = uk
        x = A @ x + B * uk
    return u


@dataclass(frozen=True)
class SolveReport:
    """How one norm-optimal solve ended: ``residual`` = ‖b - (GᵀG + λI)Δ‖ / ‖b‖ with b = Gᵀe - w f (0 when
    b = 0), ``sweeps`` refinements after the direct solve, ``stop`` 'converged' (residual ≤ rtol) or 'cap'."""

    method: str
    residual: float
    rtol: float
    sweeps: int
    stop: str

    def as_dict(self) -> dict:
        return {"method": self.method, "residual": self.residual, "rtol": self.rtol, "sweeps": self.sweeps,
                "stop": self.stop}


class RiccatiUpdate(NormOptimalUpdate):
    """The exact norm-optimal update by the LQ sweeps (module docstring).

    Parameters
    ----------
    model : tuple (A, B, C, D) | control.StateSpace | control.TransferFunction
        Discrete SISO model of the map input → output (A (n, n), B, C (n,), D scalar).
    N : int
        Samples per trial.
    w, w_delta : float
        Weights [m²/N²] of ‖f + Δ‖² and ‖Δ‖²; w + w_Δ > 0 (the LQ problem's input weight λ).
    rtol : float
        Relative residual of the normal equations a solve must reach (SolveReport).
    max_sweeps : int
        Refinement sweeps at most (each one adjoint and one forward sweep plus the residual's two filters).
    """

    method = "riccati"

    def __init__(self, model, N: int, w: float = 0.0, w_delta: float = 0.0, rtol: float = 1e-9,
                 max_sweeps: int = 3):
        self.N = _check_n(N)
        self.w, self.w_delta = _check_weights(w, w_delta)
        if isinstance(model, tuple):
            A, B, C, D = model
        else:
            ss = _as_discrete_siso_ss(model)
            A, B, C, D = ss.A, ss.B, ss.C, ss.D
        self.A = np.ascontiguousarray(np.atleast_2d(np.asarray(A, np.float64)))
        self.B = np.ascontiguousarray(np.asarray(B, np.float64).ravel())
        self.C = np.ascontiguousarray(np.asarray(C, np.float64).ravel())
        self.D = float(np.asarray(D, np.float64).ravel()[0])
        n = self.A.shape[0]
        if self.A.shape != (n, n) or self.B.size != n or self.C.size != n:
            raise ValueError(f"the ILC model must be (A (n, n), B (n,), C (n,), D); got shapes {self.A.shape}, "
                             f"{self.B.shape}, {self.C.shape}")
        if not (np.all(np.isfinite(self.A)) and np.all(np.isfinite(self.B)) and np.all(np.isfinite(self.C))
                and np.isfinite(self.D)):
            raise ValueError("the ILC model's matrices must be finite")
        if not 0 < rtol < 1 or int(max_sweeps) < 0:
            raise ValueError(f"rtol={rtol} must lie in (0, 1) and max_sweeps={max_sweeps} be >= 0")
        self.rtol, self.max_sweeps = float(rtol), int(max_sweeps)
        self._gain_cache: tuple[float, np.ndarray, np.ndarray] | None = None
        self._sigma_max: float | None = None
        self.reports: list[SolveReport] = []

    # ---- G, Gᵀ as filters ------------------------------------------------------------------------
    def apply(self, u: np.ndarray) -> np.ndarray:
        """G u from rest."""
        return ss_filter(self.A, self.B, self.C, self.D, u)[0]

    def adjoint(self, v: np.ndarray) -> np.ndarray:
        """Gᵀ v: the filter on the time-reversed signal, reversed back (Tᵀ = J T J)."""
        return self.apply(np.asarray(v, np.float64)[::-1])[::-1]

    def normal_matvec(self, x: np.ndarray) -> np.ndarray:
        """(GᵀG + λ I) x."""
        return self.adjoint(self.apply(x)) + (self.w + self.w_delta) * np.asarray(x, np.float64)

    @property
    def sigma_max(self) -> float:
        """Largest singular value of the lifted G (dense for N ≤ 50, else scipy's svds on the filters)."""
        if self._sigma_max is None:
            if self.N <= 50:
                G = np.column_stack([self.apply(col) for col in np.eye(self.N)])
                self._sigma_max = float(np.linalg.norm(G, 2))
            else:
                op = LinearOperator((self.N, self.N), matvec=lambda x: self.apply(np.ravel(x)),
                                    rmatvec=lambda x: self.adjoint(np.ravel(x)), dtype=np.float64)
                self._sigma_max = float(svds(op, k=1, return_singular_vectors=False, random_state=0)[0])
        return self._sigma_max

    # ---- the solve ---------------------------------------------------------------------------------
    def _scaled_gains(self):
        lam = self.w + self.w_delta
        if lam <= 0:
            raise ValueError("the LQ norm-optimal update needs w + w_delta > 0 (the model has no causal inverse "
                             "to fall back on); e.g. w_delta = 1e-4 sigma_max²")
        if self._gain_cache is None or self._gain_cache[0] != lam:
            s = 1.0 / np.sqrt(lam)
            self._gain_cache = (lam, *_gains(self.A, self.B, self.C * s, self.D * s, 1.0, self.N))
        return self._gain_cache

    def _solve(self, e: np.ndarray, c: np.ndarray) -> np.ndarray:
        """argmin ‖e - G Δ‖² + λ ‖Δ‖² - 2 cᵀΔ, i.e. (GᵀG + λI) Δ = Gᵀe + c (cost divided by λ)."""
        lam, K, H = self._scaled_gains()
        s = 1.0 / np.sqrt(lam)
        return _sweeps(self.A, self.B, self.C * s, self.D * s, K, H, e * s, c / lam)

    def step(self, e, f):
        e, f = self._check(e, f)
        b = self.adjoint(e) - self.w * f
        x = self._solve(e, -self.w * f)
        nb = float(np.linalg.norm(b))
        res = b - self.normal_matvec(x)
        rel = float(np.linalg.norm(res)) / nb if nb > 0 else 0.0
        sweeps = 0
        while rel > self.rtol and sweeps < self.max_sweeps:      # iterative refinement: Δ += A⁻¹ (b - A Δ)
            x = x + self._solve(np.zeros(self.N), res)
            res = b - self.normal_matvec(x)
            rel = float(np.linalg.norm(res)) / nb
            sweeps += 1
        self.reports.append(SolveReport(self.method, rel, self.rtol, sweeps,
                                        "converged" if rel <= self.rtol else "cap"))
        return x
