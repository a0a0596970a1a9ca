"""[K] feedforward: the trained filter F_θ,φ run on a reference (SPEC §6, last item).

    f = (A(r) + g_φ(r)) / B(q) = f_M + f_C

is a stable causal filter when every root of B lies inside the unit circle; the roots are
checked and reported, and an unstable B is refused (:class:`UnstableFilterError`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.models.rational import RationalFeedforward, UnstableFilterError

__all__ = ["RationalFeedforwardOutput", "rational_feedforward", "UnstableFilterError"]


@dataclass
class RationalFeedforwardOutput:
    """Feedforward f [N] for one reference, its parts and the roots of B.

    Attributes
    ----------
    f : np.ndarray
        f = f_M + f_C [N].
    f_M : np.ndarray
        Model part A(r)/B [N] ([K] Def. 1).
    f_C : np.ndarray or None
        Approximator part g_φ(r)/B [N] ([K] Def. 2); None for the rational model.
    poles : np.ndarray
        Roots of B in z.
    """

    f: np.ndarray
    f_M: np.ndarray
    f_C: np.ndarray | None
    poles: np.ndarray

    @property
    def max_pole_abs(self) -> float:
        """Largest |root| of B (< 1: stable)."""
        return float(np.max(np.abs(self.poles))) if self.poles.size else 0.0


def rational_feedforward(model: RationalFeedforward, r) -> RationalFeedforwardOutput:
    """Run the trained [K] filter on reference ``r`` [m] (1-D, at rest before k = 0).

    Raises
    ------
    UnstableFilterError
        If B has a root on or outside the unit circle (the filter would diverge).
    """
    r = np.asarray(r, dtype=np.float64)
    if r.ndim != 1:
        raise ValueError(f"reference must be 1-D, got shape {r.shape}; run one reference at a time")
    model.check_stable()
    inp = model.inputs(r)
    with torch.no_grad():
        f_M, f_C = model.parts(inp)
    f_M = f_M.numpy()
    f_C = None if f_C is None else f_C.numpy()
    f = f_M if f_C is None else f_M + f_C
    return RationalFeedforwardOutput(f=f, f_M=f_M, f_C=f_C, poles=model.poles())
