"""tanh of the networks' forward passes, one source for the PGNN ([B1] (10)) and g_φ ([K] (6)).

torch's float64 tanh is a third as fast as numpy's vectorised one on this project's CPUs (AVX-512:
0.65 vs 0.22 ms per 131k values; in a [B1] NARX LM iteration it was 9.6 of 14.1 ms of the residual,
benchmarks/bench_iterations.py). Both are within 1 ulp of tanh and differ from each other in the
last bit of ~20 % of values; which one a model uses is fixed here, so every plain forward pass of a
model (training residual, its kept activations, g_value) has the same bits.

Where autograd or a torch.func transform traces the tensor (a tensor that requires grad, or a
functorch wrapper without storage), ``.numpy()`` refuses and torch's tanh runs instead: derivatives
are always torch's, values there agree to 1 ulp.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

__all__ = ["tanh", "tanh_", "Tanh"]


def _plain(z: torch.Tensor) -> np.ndarray | None:
    """z's data as numpy, or None when autograd / torch.func traces z."""
    try:
        return z.numpy()
    except (RuntimeError, TypeError):
        return None


def tanh(z: torch.Tensor) -> torch.Tensor:
    """tanh(z): numpy's on plain data, torch's where z is traced."""
    a = _plain(z)
    return torch.tanh(z) if a is None else torch.from_numpy(np.tanh(a))


def tanh_(z: torch.Tensor) -> torch.Tensor:
    """tanh(z) in place (z returned): numpy's on plain data, torch's where z is traced."""
    a = _plain(z)
    if a is None:
        return z.tanh_()
    np.tanh(a, out=a)
    return z


class Tanh(nn.Tanh):
    """nn.Tanh by :func:`tanh` (an approximator's hidden activation)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return tanh(x)
