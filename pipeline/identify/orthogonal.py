"""Orthogonal projection-based regulariser ([K] Section IV, Alg. 19; SPEC §5, §7).

At SK iteration j the weighted model matrix W^{j-1} M (columns of M per [K] (14), W^{j-1}
filtering by 1/B^{j-1}(q), applied as a filter) is factorised by a thin SVD
(:func:`model_subspace`, [K] (28))

    W M D = U1 Σ Vᵀ,          D = diag(1/‖(W M)_i‖)   (column scaling, SPEC §5)

and the approximator output is penalised in the model's output space ([K] (29))

    R(φ) = ‖(Σ Vᵀ)^{-1} U1ᵀ W g_φ(r)‖²,

i.e. the squared norm of the (column-scaled) model coefficients that would reproduce the part
of W g_φ lying in im(W M) ([K] (20)).  With column scaling the coefficients are in units of
the signal (N), so R has the units of the criterion and λ is dimensionless.

Also here: the interpretability quantities of SPEC §7 (share of f_C in the model subspace,
‖f_C‖/‖f_M‖, corr(f_M, f_C), spread over initialisations).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["RankDeficientModelError", "ModelSubspace", "model_subspace", "orthogonal_regularizer",
           "subspace_share", "spread_over_inits", "interpretability"]


class RankDeficientModelError(ValueError):
    """The (weighted) model matrix M is rank deficient ([K] Assumption 10 fails)."""


def _as_np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)


@dataclass
class ModelSubspace:
    """Thin SVD ``W M D = U1 Σ Vᵀ`` of the column-scaled weighted model matrix ([K] (28)).

    Attributes
    ----------
    U1 : np.ndarray
        [N, p] orthonormal basis of im(W M).
    s : np.ndarray
        [p] singular values σ_1 ≥ … ≥ σ_p > 0 (of the column-scaled matrix).
    Vt : np.ndarray
        [p, p] right singular vectors (rows).
    scale : np.ndarray
        [p] column scaling D (θ = D θ_s; all ones without scaling).
    n_truncated : int
        Numerically singular directions dropped (U1, s, Vt then have p − n_truncated
        columns/entries/rows; see :func:`model_subspace`).
    """

    U1: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    scale: np.ndarray
    n_truncated: int = 0

    @property
    def p(self) -> int:
        """Numerical rank (number of kept singular values)."""
        return int(self.s.size)

    @property
    def condition(self) -> float:
        """Condition number σ_1/σ_p of the column-scaled weighted model matrix."""
        return float(self.s[0] / self.s[-1])

    # -- maps (numpy or torch; first axis = time) ----------------------------------------
    def _mats(self, like):
        if isinstance(like, torch.Tensor):
            t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
            return t(self.U1), t(self.s), t(self.Vt), t(self.scale)
        return self.U1, self.s, self.Vt, self.scale

    def coordinates(self, Wx, projected: bool = False):
        """(Σ Vᵀ)^{-1} U1ᵀ W x = V Σ^{-1} U1ᵀ W x: scaled model coefficients of W x's
        projection on im(W M) ([K] (20), (29)); [p] or [p, m] for columns.  With
        ``projected=True`` the argument is already U1ᵀ W x."""
        U1, s, Vt, _ = self._mats(Wx)
        c = Wx if projected else U1.T @ Wx
        c = c / (s if c.ndim == 1 else s[:, None])
        return Vt.T @ c

    def solve(self, Wy):
        """Least squares θ = argmin ‖W y − W M θ‖² in physical units (θ = D V Σ^{-1} U1ᵀ W y)."""
        _, _, _, scale = self._mats(Wy)
        th = self.coordinates(Wy)
        return th * (scale if th.ndim == 1 else scale[:, None])

    def project(self, Wx):
        """U1 U1ᵀ W x, the part of W x inside the model's output space."""
        U1 = self._mats(Wx)[0]
        return U1 @ (U1.T @ Wx)

    def project_out(self, Wx):
        """(I − U1 U1ᵀ) W x, the part of W x the model cannot produce."""
        return Wx - self.project(Wx)


def model_subspace(WM, *, column_scale: bool = True, rtol: float | None = None,
                   names=None, rank_deficient: str = "raise") -> ModelSubspace:
    """Thin SVD of the weighted model matrix with a rank check ([K] Lemma 12, Assumption 10).

    Parameters
    ----------
    WM : array_like
        [N, p] weighted model matrix W^{j-1} M (N > p).
    column_scale : bool
        Scale every column to unit norm first (SPEC §5: "column-scale M before any least
        squares").
    rtol : float, optional
        Rank tolerance on σ_p/σ_1; default ``max(N, p) · eps`` (numpy's ``matrix_rank``).
    names : sequence of str, optional
        Column names, used in the error message.
    rank_deficient : {'raise', 'truncate'}
        What to do when σ_p ≤ rtol σ_1: raise (Assumption 10 fails), or drop the singular
        directions (U1 keeps the numerical rank; :meth:`ModelSubspace.solve` then gives the
        minimum-norm least-squares solution in column-scaled coordinates, as ``pinv``).
        ``truncate`` is for the weighted matrices of later SK iterations of an
        overparametrised model (10th-order shift basis at Ts = 1 ms: σ_p/σ_1 ~ 1e-16 after
        weighting by 1/B although M itself has full rank).

    Raises
    ------
    RankDeficientModelError
        If a column is zero, or (``raise``) σ_p ≤ rtol · σ_1, naming the smallest singular
        value and the parameters of the weakest direction.
    """
    if rank_deficient not in ("raise", "truncate"):
        raise ValueError(f"rank_deficient must be 'raise' or 'truncate', got '{rank_deficient}'")
    WM = _as_np(WM)
    if WM.ndim != 2:
        raise ValueError(f"model matrix must be 2-D [N, p], got shape {WM.shape}")
    N, p = WM.shape
    if N <= p:
        raise RankDeficientModelError(
            f"model matrix has {N} rows for {p} parameters; [K] Assumption 10 needs a tall M: "
            "use more data or fewer coefficients (n_a, n_b)")
    names = list(names) if names is not None else [f"θ{i}" for i in range(p)]
    norms = np.linalg.norm(WM, axis=0)
    if np.any(norms == 0):
        zero = [names[i] for i in np.flatnonzero(norms == 0)]
        raise RankDeficientModelError(
            f"model matrix column(s) {zero} are identically zero, smallest singular value 0: "
            "the reference does not excite them ([K] Assumption 10); use a richer reference or "
            "drop those coefficients")
    scale = 1.0 / norms if column_scale else np.ones(p)
    U1, s, Vt = np.linalg.svd(WM * scale, full_matrices=False)
    tol = max(N, p) * np.finfo(np.float64).eps if rtol is None else float(rtol)
    keep = s > tol * s[0]
    if not np.all(keep):
        if rank_deficient == "truncate":
            return ModelSubspace(U1=U1[:, keep], s=s[keep], Vt=Vt[keep], scale=scale,
                                 n_truncated=int(np.sum(~keep)))
        weak = np.argsort(-np.abs(Vt[-1]))[:3]
        raise RankDeficientModelError(
            f"model matrix M is rank deficient ([K] Assumption 10): smallest singular value "
            f"{s[-1]:.3e} vs largest {s[0]:.3e} (ratio {s[-1] / s[0]:.2e} <= tolerance {tol:.1e}); "
            f"weakest direction mostly {[names[i] for i in weak]}. The reference must have a "
            "nonzero spectrum at >= n_a + n_b frequencies: use a richer reference, fewer "
            "coefficients (n_a, n_b), or the delta basis at high sample rates")
    return ModelSubspace(U1=U1, s=s, Vt=Vt, scale=scale)


def orthogonal_regularizer(sub: ModelSubspace, Wg):
    """R(φ) = ‖(Σ Vᵀ)^{-1} U1ᵀ W g_φ‖² ([K] (22), (29)); ``Wg`` is the filtered g [N]."""
    c = sub.coordinates(Wg)
    return c @ c


def subspace_share(sub: ModelSubspace, Wx) -> float:
    """‖U1ᵀ W x‖ / ‖W x‖: the share of W x inside the model subspace (SPEC §7, K2)."""
    Wx = _as_np(Wx)
    n = np.linalg.norm(Wx)
    return float(np.linalg.norm(sub.U1.T @ Wx) / n) if n > 0 else 0.0


def spread_over_inits(signals, reference) -> float:
    """rms deviation of several runs' signals from their mean, over rms of ``reference``
    (SPEC §8 K2: spread of f_M over random initialisations, relative to rms f̂)."""
    S = np.vstack([_as_np(s) for s in signals])
    ref = _as_np(reference)
    dev = S - S.mean(axis=0)
    return float(np.sqrt(np.mean(dev ** 2)) / np.sqrt(np.mean(ref ** 2)))


def interpretability(model, r, f_hat, theta_true=None, *, column_scale: bool = True) -> dict:
    """Interpretability quantities of SPEC §7 for a trained [K] model on data (r, f̂).

    Parameters
    ----------
    model : RationalFeedforward or SharedARPGNN
        Trained feedforward (stable B).
    r, f_hat : array or list of arrays
        References [m] and optimal inputs [N].
    theta_true : array_like, optional
        True col(a, b) in the model's basis, where the model class holds them.

    Returns
    -------
    dict
        ``f_M``, ``f_C`` (per-sample arrays, concatenated), ``share_C_in_model``
        (‖U1ᵀ W g‖/‖W g‖ with W = 1/B of the model, W g = f_C), ``ratio_C_M``
        (‖f_C‖/‖f_M‖), ``corr_M_C`` (Pearson correlation of f_M and f_C), ``theta``,
        and with ``theta_true`` the relative error per coefficient ``theta_rel_err``.
    """
    from pipeline.models.rational import (  # lazy: saves 2.1 s of start-up (torch, scipy.signal)
        Segments,
        filter_segments,
    )
    r_cat, seg = Segments.concat(r, "reference")
    f_cat, seg_f = Segments.concat(f_hat, "optimal input")
    if seg_f != seg:
        raise ValueError(f"references and optimal inputs have different lengths {seg.lengths} vs "
                         f"{seg_f.lengths}; pair every reference with its own f̂")
    model.check_stable()
    inp = model.inputs(r_cat, seg)
    with torch.no_grad():
        f_M, f_C = model.parts(inp)
    f_M = f_M.numpy()
    out = {"theta": model.theta, "f_M": f_M}
    if theta_true is not None:
        tt = np.asarray(theta_true, dtype=np.float64)
        out["theta_rel_err"] = np.abs(model.theta - tt) / np.where(tt != 0, np.abs(tt), 1.0)
    if f_C is None:
        return out
    f_C = f_C.numpy()
    M = np.hstack([inp["R"], -model.ar_regressors(f_cat, seg)])
    sub = model_subspace(filter_segments(M, [1.0], model.denominator(), seg), column_scale=column_scale)
    out.update({
        "f_C": f_C,
        "share_C_in_model": subspace_share(sub, f_C),   # W g = f_C: filtered once
        "ratio_C_M": float(np.linalg.norm(f_C) / np.linalg.norm(f_M)),
        "corr_M_C": float(np.corrcoef(f_M, f_C)[0, 1]) if np.std(f_C) > 0 and np.std(f_M) > 0 else 0.0,
    })
    return out
