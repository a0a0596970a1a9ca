"""tanh of the networks' forward passes, one source for the PGNN ([B1] (10)) and g_φ ([K] (6)).

torch's float64 tanh (SLEEF) takes 4.9 ns per value on the project's CPUs. numpy's float64 tanh runs a
vectorised loop where numpy dispatches its AVX-512 target (X86_V4, formerly AVX512_SKX): 1.7 ns per
value on an AVX-512 EPYC (0.22 vs 0.65 ms per 131k values; in the [B1] NARX LM iteration the residual
went from 14.1 to 7.9 ms, benchmarks/bench_iterations.py); without AVX-512 it is libm's scalar tanh,
2.2x slower than torch's (27.8 vs 12.4 ms on a 2-core EPYC without AVX-512, README). So
:data:`IMPLEMENTATION` is numpy's where numpy's tanh dispatches AVX-512, torch's otherwise: fixed per
machine and numpy build (never by a timing, which would make the bits depend on the load). Both are
within 1 ulp of tanh and differ from each other in the last bit of ~20 % of values; the train stage
logs which one ran (tag ``tanh``), so two machines' results can be told apart.

Where autograd or a torch.func transform traces the tensor (a tensor that requires grad, or a
functorch wrapper without storage), ``.numpy()`` refuses and torch's tanh runs: derivatives are
always torch's, values there agree to 1 ulp.
"""
from __future__ import annotations

import numpy as np
import torch
from numpy.lib.introspect import opt_func_info
from torch import nn

__all__ = ["IMPLEMENTATION", "tanh", "tanh_", "Tanh"]

#: numpy targets with a vectorised float64 tanh loop (AVX-512; X86_V4 is numpy ≥ 2.4's name)
_SIMD_TARGETS = ("X86_V4", "AVX512_SKX", "AVX512_ICL", "AVX512_SPR")


def _numpy_target() -> str | None:
    """The target numpy's float64 tanh dispatches on this machine (numpy.lib.introspect), or None."""
    try:
        return str(opt_func_info(func_name="^tanh$", signature="^d")["tanh"]["dd"]["current"])
    except (KeyError, TypeError, ValueError):
        return None


_TARGET = _numpy_target()
#: which tanh the plain forward passes use on this machine: "numpy (<target>)" or "torch"
IMPLEMENTATION = f"numpy ({_TARGET})" if _TARGET in _SIMD_TARGETS else "torch"
_NUMPY = IMPLEMENTATION != "torch"


def _plain(z: torch.Tensor) -> np.ndarray | None:
    """z's data as numpy where numpy's tanh runs (None: torch's, on this machine or where autograd /
    torch.func traces z)."""
    if not _NUMPY:
        return None
    try:
        return z.numpy()
    except (RuntimeError, TypeError):
        return None


def tanh(z: torch.Tensor) -> torch.Tensor:
    """tanh(z): :data:`IMPLEMENTATION`'s on plain data, torch's where z is traced."""
    a = _plain(z)
    if a is None:
        return torch.tanh(z)
    out = np.empty_like(a)                  # an array also for a 0-d z (np.tanh of one returns a scalar)
    np.tanh(a, out=out)
    return torch.from_numpy(out)


def tanh_(z: torch.Tensor) -> torch.Tensor:
    """tanh(z) in place (z returned): :data:`IMPLEMENTATION`'s on plain data, torch's where z is traced."""
    a = _plain(z)
    if a is None:
        return z.tanh_()
    np.tanh(a, out=a)
    return z


class Tanh(nn.Tanh):
    """nn.Tanh by :func:`tanh` (an approximator's hidden activation)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return tanh(x)
