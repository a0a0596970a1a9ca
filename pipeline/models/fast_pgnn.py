"""The numba fast path of a PGNN: flat arrays and kernels for the per-sample inversions.

:func:`fast_pgnn` exports a one-hidden-layer tanh PGNN (or one without NN) with a built-in
physics map (:mod:`pipeline.models.physics_maps`) to flat numpy arrays evaluated by numba
kernels (``fast_predict``, ``fast_physics_affine``, ``fast_nn_affine``, the feedforward
regressor window), used by the inversions of :mod:`pipeline.invert` ([B1] Alg. 1, (27)) and by
the exported law (:mod:`pipeline.export.law`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
import torch

from pipeline.systems.force_terms import term

if TYPE_CHECKING:
    from pipeline.models.pgnn import PGNN

__all__ = ["FastPGNN", "fast_pgnn", "fast_predict", "fast_physics_value", "fast_physics_affine", "fast_nn_affine",
           "fast_state", "fast_push_reference", "fast_build_phi", "fast_push_input", "padded_reference"]


# --------------------------------------------------------------------------------------------
# numba fast path (one hidden tanh layer or no NN; built-in physics maps)
# --------------------------------------------------------------------------------------------
@dataclass
class FastPGNN:
    """Flat numpy export of a PGNN for the numba inversion kernels.

    ``blob`` (float64) = [theta_phy (p), theta_phy_start (p), W (H × n_phi, the first layer
    folded with the input map), b (H), w2 (H), b2, cfg…]; ``meta`` (int64) =
    [kind, p, H, n_phi, u_index, use_phys, use_nn, n_a, n_b, n_k, n_cfg].
    """

    blob: np.ndarray
    meta: np.ndarray
    structure: str
    n_a: int
    n_b: int
    n_k: int


def fast_pgnn(model: PGNN, theta_start=None) -> FastPGNN | None:
    """Export ``model`` for the numba kernels, or None when it has no fast path (NN deeper
    than one hidden layer or not tanh, physics map without a numba kernel).

    ``theta_start`` is the θ_phy of the physics feedforward that starts Newton ([B1] Alg. 1,
    θ*_phy); default: the model's θ*_phy if known, else its θ_phy.
    """
    if model.use_nn and not (len(model.hidden) == 1 and model.activation == "tanh"):
        return None
    if model.use_physics and model.physics.fast_kind < 0:
        return None
    with torch.no_grad():
        if model.use_physics:
            th = model.theta_phy.detach().numpy().copy()
            star = model.theta_phy_star.detach().numpy()
            if theta_start is None:
                theta_start = star if np.all(np.isfinite(star)) else th
            ts = np.asarray(theta_start, dtype=float)
            cfg = model.physics.fast_config()
            kind = model.physics.fast_kind
        else:
            th = ts = np.zeros(0)
            cfg, kind = np.zeros(0), -1
        if model.use_nn:
            (l1, l2) = model.layers
            s = float(model.out_scale)
            W = (l1.weight @ model.nn_P).numpy()  # fold the input map into the first layer
            b = (l1.bias + l1.weight @ model.nn_c).numpy()
            w2 = s * l2.weight[0].numpy()
            b2 = s * float(l2.bias[0])
            H = W.shape[0]
        else:
            W, b, w2, b2, H = np.zeros((0, model.n_phi)), np.zeros(0), np.zeros(0), 0.0, 0
    blob = np.concatenate([th, ts, W.ravel(), b, w2, [b2], cfg]).astype(np.float64)
    meta = np.array([kind, th.size, H, model.n_phi, model.u_index, int(model.use_physics),
                     int(model.use_nn), model.n_a, model.n_b, model.n_k, cfg.size], dtype=np.int64)
    return FastPGNN(blob, meta, model.structure, model.n_a, model.n_b, model.n_k)


@numba.njit(cache=True)
def _fast_physics(kind, cfg, theta, phi):
    """f_phy(θ, φ) of the built-in maps (same formulas as the torch classes)."""
    if kind == 0:  # LinearFeatures
        n = int(cfg[0])
        s = 0.0
        for i in range(n):
            s += theta[i] * phi[i]
        return s
    elif kind == 1:  # RigidBodyForward
        Ts = cfg[0]
        na = int(cfg[1])
        y1, y2, u1 = phi[0], phi[1], phi[na]
        v = (y1 - y2) / Ts
        sg = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
        return 2.0 * y1 - y2 + Ts * Ts * (theta[0] * u1 - theta[1] * v - theta[2] * sg)
    elif kind == 2:  # RigidBodyInverse
        Ts = cfg[0]
        acc = (phi[0] - 2.0 * phi[1] + phi[2]) / (Ts * Ts)
        v = (phi[1] - phi[2]) / Ts
        sg = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
        return theta[0] * acc + theta[1] * v + theta[2] * sg
    elif kind == 4:  # its inverse layout: θ'₀ δ²y(t+1) + Σ_j θ'_j T_j(y(t), δy(t)) (RigidBodyPhysics.inverse_features)
        Ts = cfg[0]
        nt = int(cfg[1])
        acc = (phi[0] - 2.0 * phi[1] + phi[2]) / (Ts * Ts)
        v = (phi[1] - phi[2]) / Ts
        s = theta[0] * acc
        for j in range(nt):
            s += theta[1 + j] * term(int(cfg[2 + j]), cfg[2 + nt + j], phi[1], v)[0]
        return s
    else:  # measured rigid body with force terms (PhysicsModelFeatures of RigidBodyPhysics, direct input)
        Ts = cfg[0]
        nt = int(cfg[1])
        y1, y2 = phi[0], phi[1]
        v = (y1 - y2) / Ts
        s = Ts * Ts * phi[2] * theta[0]          # Ts² w(t-1) θ₀
        for j in range(nt):                      # - Ts² T_j(y(t-1), δy(t-1)) θ_j
            s += -Ts * Ts * term(int(cfg[2 + j]), cfg[2 + nt + j], y1, v)[0] * theta[1 + j]
        return 2.0 * y1 - y2 + s


@numba.njit(cache=True)
def _fast_physics_gain(kind, cfg, theta, u_index):
    """ψ = ∂f_phy/∂u(t-n_k-1) of the built-in forward maps, in closed form (a difference
    f(u=1) - f(u=0) would lose ~10 digits to cancellation when ψ u << f, e.g. Ts²/m)."""
    if kind == 0:  # LinearFeatures: θ of the u(t-n_k-1) column
        return theta[u_index]
    elif kind == 1 or kind == 3:  # RigidBodyForward, rigid body with terms: Ts² / m
        return cfg[0] * cfg[0] * theta[0]
    return np.nan  # inverse map: no input gain


@numba.njit(cache=True)
def _unpack(blob, meta):
    p, H, n = meta[1], meta[2], meta[3]
    i = 0
    th = blob[i:i + p]; i += p
    ts = blob[i:i + p]; i += p
    W = blob[i:i + H * n].reshape((H, n)); i += H * n
    b = blob[i:i + H]; i += H
    w2 = blob[i:i + H]; i += H
    b2 = blob[i]; i += 1
    cfg = blob[i:i + meta[10]]
    return th, ts, W, b, w2, b2, cfg


@numba.njit(cache=True)
def fast_predict(blob, meta, phi):
    """ŷ(θ, φ) for one regressor φ (numba; equals ``PGNN.forward``)."""
    th, ts, W, b, w2, b2, cfg = _unpack(blob, meta)
    out = 0.0
    if meta[5]:
        out += _fast_physics(meta[0], cfg, th, phi)
    if meta[6]:
        H, n = meta[2], meta[3]
        acc = b2
        for j in range(H):
            z = b[j]
            for i in range(n):
                z += W[j, i] * phi[i]
            acc += w2[j] * np.tanh(z)
        out += acc
    return out


@numba.njit(cache=True)
def fast_physics_value(blob, meta, phi, use_start):
    """f_phy(θ, φ) for θ_phy (``use_start`` False) or the start θ*_phy (True); 0 without physics."""
    if not meta[5]:
        return 0.0
    th, ts, W, b, w2, b2, cfg = _unpack(blob, meta)
    return _fast_physics(meta[0], cfg, ts if use_start else th, phi)


@numba.njit(cache=True)
def fast_physics_affine(blob, meta, phi, use_start):
    """(a, ψ) with f_phy(φ) = a + ψ u(t-n_k-1): physics part at u = 0 and its input gain
    (affine maps only), for θ_phy (``use_start`` False) or the start θ*_phy (True)."""
    if not meta[5]:
        return 0.0, 0.0
    th, ts, W, b, w2, b2, cfg = _unpack(blob, meta)
    theta = ts if use_start else th
    k = meta[4]
    keep = phi[k]
    phi[k] = 0.0
    a = _fast_physics(meta[0], cfg, theta, phi)
    phi[k] = keep
    return a, _fast_physics_gain(meta[0], cfg, theta, k)


@numba.njit(cache=True)
def fast_nn_affine(blob, meta, phi):
    """(f_NN(φ), ∂f_NN/∂u(t-n_k-1)) for one regressor φ (zero without NN)."""
    th, ts, W, b, w2, b2, cfg = _unpack(blob, meta)
    if not meta[6]:
        return 0.0, 0.0
    H, n, k = meta[2], meta[3], meta[4]
    val = b2
    d = 0.0
    for j in range(H):
        z = b[j]
        for i in range(n):
            z += W[j, i] * phi[i]
        h = np.tanh(z)
        val += w2[j] * h
        d += w2[j] * (1.0 - h * h) * W[j, k]
    return val, d


# ---- feedforward regressor window (numba), shared by the inversions of pipeline.invert -----
# state = [r window (n_a + 1): r(t+n_k+1), r(t+n_k), …, r(t+n_k+1-n_a);
#          input history (n_b): u_ff(t-1), …, u_ff(t-n_b);  φ scratch (n_a + n_b)]
def fast_state(fm: FastPGNN, r_past) -> np.ndarray:
    """Initial window state for a feedforward run: ``r_past`` = [r(n_k), r(n_k-1), …,
    r(n_k-n_a)] (the reference before the first new sample r(n_k+1)), zero past inputs."""
    n_a, n_b = fm.n_a, fm.n_b
    s = np.zeros(2 * (n_a + n_b) + 1)
    r_past = np.asarray(r_past, dtype=float)
    if r_past.shape != (n_a + 1,):
        raise ValueError(f"r_past must hold n_a + 1 = {n_a + 1} samples, got {r_past.shape}")
    s[:n_a + 1] = r_past  # the first push of r(n_k+1) completes the window
    return s


@numba.njit(cache=True)
def fast_push_reference(state, meta, r_new):
    """Shift the reference window and insert the newest sample r(t+n_k+1)."""
    n_y = meta[7] + 1
    for i in range(n_y - 1, 0, -1):
        state[i] = state[i - 1]
    state[0] = r_new


@numba.njit(cache=True)
def fast_build_phi(state, meta, inverse_layout):
    """φ_ff (forward layout, u(t) slot = 0) or φ'_ff (inverse layout) from the state; a view
    into the state's scratch part."""
    n_a, n_b = meta[7], meta[8]
    n_y = n_a + 1
    phi = state[n_y + n_b:]
    if inverse_layout:
        for i in range(n_y):
            phi[i] = state[i]  # r(t+n_k+1-i), i = 0..n_a
        for i in range(n_b - 1):
            phi[n_y + i] = state[n_y + i]  # u_ff(t-1-i)
    else:
        for i in range(n_a):
            phi[i] = state[1 + i]  # r(t+n_k-i)
        phi[n_a] = 0.0  # u_ff(t), the unknown
        for i in range(n_b - 1):
            phi[n_a + 1 + i] = state[n_y + i]  # u_ff(t-1-i)
    return phi


@numba.njit(cache=True)
def fast_push_input(state, meta, u):
    """Shift the input history and insert u_ff(t)."""
    n_y, n_b = meta[7] + 1, meta[8]
    for i in range(n_b - 1, 0, -1):
        state[n_y + i] = state[n_y + i - 1]
    state[n_y] = u


def padded_reference(r, n_a: int, n_k: int) -> np.ndarray:
    """r(j) for j = -n_a … N + n_k, held at r(0) before the start and at r(N-1) after the end
    (at rest), so that ``out[j + n_a] = r(j)``."""
    r = np.asarray(r, dtype=np.float64)
    if r.ndim != 1 or r.shape[0] < 1:
        raise ValueError(f"reference must be a non-empty 1-D signal, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("reference contains NaN/inf")
    N = r.shape[0]
    return r[np.clip(np.arange(-n_a, N + n_k + 1), 0, N - 1)]
