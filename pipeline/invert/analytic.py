"""Analytic inversion: the physics feedforward [B1] (8) and the invertible PGNN [B1] (27).

For a forward-layout model whose output is affine in the most recent input,
ŷ(φ) = a(φ) + ψ(φ) u(t-n_k-1) with the NN blind to u(t-n_k-1) ([B1] (26)), the feedforward
solves r(t+n_k+1) = ŷ(φ_ff(t+n_k+1)) exactly:

    u_ff(t) = (r(t+n_k+1) - f_phy(θ̂_phy, φ_ff|u=0) - f_NN(θ̂_NN, φ_ff)) / ψ(θ̂_phy, φ_ff)      [B1] (27)

with φ_ff(t+n_k+1) = [r(t+n_k), …, r(t+n_k+1-n_a), u_ff(t), …, u_ff(t-n_b+1)], recursive in
u_ff.  The physics feedforward (8) is the same with the NN off and θ = θ*_phy ([B1] (7));
for a direct-inverse layout it is the inverse physics model evaluated on φ'_ff.  Reference
held at r(0) before the start and at r(N-1) after the end; past inputs zero (at rest).
"""
from __future__ import annotations

import numba
import numpy as np
import torch

from pipeline.invert.direct import initial_state, reference_regressor, resolve_fast
from pipeline.models.fast_pgnn import (
    fast_build_phi,
    fast_nn_affine,
    fast_physics_affine,
    fast_physics_value,
    fast_push_input,
    fast_push_reference,
    padded_reference,
)
from pipeline.models.pgnn import PGNN

__all__ = ["analytic_feedforward", "physics_feedforward", "analytic_step", "physics_step",
           "analytic_solve"]


@numba.njit(cache=True)
def analytic_solve(blob, meta, phi, r_next, use_start, with_nn):
    """u with r_next = a + ψ u + f_NN for one regressor (u slot ignored); NaN if ψ = 0."""
    a, psi = fast_physics_affine(blob, meta, phi, use_start)
    nn = fast_nn_affine(blob, meta, phi)[0] if with_nn else 0.0
    if psi == 0.0:
        return np.nan
    return (r_next - a - nn) / psi


@numba.njit(cache=True)
def analytic_step(blob, meta, state, r_new):
    """One sample of [B1] (27): push r(t+n_k+1), return u_ff(t)."""
    fast_push_reference(state, meta, r_new)
    phi = fast_build_phi(state, meta, False)
    u = analytic_solve(blob, meta, phi, r_new, False, True)
    fast_push_input(state, meta, u)
    return u


@numba.njit(cache=True)
def physics_step(blob, meta, state, r_new, inverse_layout):
    """One sample of the physics feedforward [B1] (8) with the start parameters θ*_phy."""
    fast_push_reference(state, meta, r_new)
    phi = fast_build_phi(state, meta, inverse_layout)
    if inverse_layout:
        u = fast_physics_value(blob, meta, phi, True)
    else:
        u = analytic_solve(blob, meta, phi, r_new, True, False)
    fast_push_input(state, meta, u)
    return u


@numba.njit(cache=True)
def _run(blob, meta, state, r_ext, N, physics_only, inverse_layout):
    n_a, n_k = meta[7], meta[9]
    u = np.empty(N)
    for t in range(N):
        rn = r_ext[t + n_k + 1 + n_a]
        if physics_only:
            u[t] = physics_step(blob, meta, state, rn, inverse_layout)
        else:
            u[t] = analytic_step(blob, meta, state, rn)
    return u


def _check_psi(u, model):
    if not np.all(np.isfinite(u)):
        bad = int(np.flatnonzero(~np.isfinite(u))[0])
        raise ValueError(f"analytic inversion failed at sample {bad}: the input gain ψ of the "
                         f"physics model is zero there (θ_phy = "
                         f"{model.theta_phy.detach().numpy()}); the model cannot be inverted")
    return u


def analytic_feedforward(model: PGNN, r, *, fast: bool | None = None) -> np.ndarray:
    """Feedforward u_ff [N] of an analytically invertible PGNN ([B1] (26), (27)).

    Raises
    ------
    ValueError
        If the model's NN sees u(t-n_k-1) (use Newton inversion) or its physics is not
        affine in that input.
    """
    if not model.analytically_invertible:
        raise ValueError(
            f"analytic inversion ([B1] (27)) needs a forward-layout model whose NN does not see "
            f"u(t-n_k-1) (structure='invertible', [B1] (26)) or a physics-only model, with "
            f"physics affine in that input; got structure={model.structure!r}, "
            f"use_nn={model.use_nn}, use_physics={model.use_physics}. Use newton_feedforward "
            "for a forward PGNN")
    r_ext = padded_reference(r, model.n_a, model.n_k)
    N = r_ext.shape[0] - model.n_a - model.n_k - 1
    fm = resolve_fast(model, fast)
    if fm is not None:
        return _check_psi(_run(fm.blob, fm.meta, initial_state(fm, r_ext), r_ext, N, False, False),
                          model)
    u = np.full(N, np.nan)
    with torch.no_grad():
        for t in range(N):
            phi = reference_regressor(model, r_ext, u, t)
            a, psi = model.physics_affine(phi)
            psi = float(psi[0])
            if psi == 0.0:
                break
            rn = r_ext[t + model.n_k + 1 + model.n_a]
            u[t] = (rn - float(a[0]) - float(model.nn_part(phi)[0])) / psi  # [B1] (27)
    return _check_psi(u, model)


def physics_feedforward(model: PGNN, r, *, theta=None, fast: bool | None = None) -> np.ndarray:
    """Physics feedforward [B1] (8): the analytic inverse of the model's physics part with
    θ = ``theta`` (default θ*_phy of [B1] (7) when known, else the model's θ_phy).

    For a direct-inverse layout (``structure='inverse'``) the physics part is already an
    inverse model and is evaluated on φ'_ff.
    """
    if not model.use_physics:
        raise ValueError("physics feedforward needs a model with a physics part")
    if theta is None:
        star = model.theta_phy_star.detach().numpy()
        theta = star if np.all(np.isfinite(star)) else model.theta_phy.detach().numpy()
    theta = np.asarray(theta, dtype=float)
    inverse_layout = model.structure == "inverse"
    if not inverse_layout and not model.physics.affine_in_latest_input:
        raise ValueError("the physics map is not affine in u(t-n_k-1); its inverse has no "
                         "closed form here")
    r_ext = padded_reference(r, model.n_a, model.n_k)
    N = r_ext.shape[0] - model.n_a - model.n_k - 1
    fm = resolve_fast(model, fast, theta_start=theta)
    if fm is not None:
        u = _run(fm.blob, fm.meta, initial_state(fm, r_ext), r_ext, N, True, inverse_layout)
        return _check_psi(u, model)
    th = torch.as_tensor(theta)
    u = np.full(N, np.nan)
    with torch.no_grad():
        for t in range(N):
            phi = reference_regressor(model, r_ext, u, t)
            if inverse_layout:
                u[t] = float(model.physics_part(phi, th))
                continue
            a, psi = model.physics_affine(phi, th)
            psi = float(psi[0])
            if psi == 0.0:
                break
            u[t] = (r_ext[t + model.n_k + 1 + model.n_a] - float(a[0])) / psi  # [B1] (8)
    return _check_psi(u, model)
