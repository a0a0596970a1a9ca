"""identify.kind=sim_error: closed-loop simulation-error identification of the [B2] PGNN (30).

The model is the forward PGNN with ARX physics (``LinearFeatures`` on the plant's ARX
physics model, n_a = n_b = 4, n_k = 0 for rot_trans_nmp) and ``model.hidden = [n1]`` tanh
neurons (``[]``: the linear model alone), simulated in closed loop with the plant's known
controller, [B2] (8); criterion [B2] (16) with Λ = ``regularizer.lam`` [I, 0] toward θ*_phy
(``identify.theta_star``: the linear model identified first), normalised as SPEC §5.

Logged: the LM loss curve (``train/loss/restart<i>``), the identification error
‖Y^d - Ŷ^d‖/sqrt(N_d) (``train/identification_error``, [B2] (15)), seconds, θ*_phy, θ̂_phy.
Returns the module, its array export (``arx``) and the identification signals Y^d, Ŷ^d
(the bound terms of the invert stage need them).
"""
from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf

from pipeline.identify.sim_error import DiscreteController, closed_loop_exogenous, identify_sim_error
from pipeline.models.pgnn import PGNN, LinearFeatures
from pipeline.runner import ConfigError
from stages.train import log_restarts
from pipeline.systems.arx_bias import ARXPhysics

THETA_STAR = ("arx", "sim_error")


def check(cfg, system) -> None:
    m = cfg.model
    if m.get("structure") != "forward":
        raise ConfigError(f"identify.kind=sim_error simulates a forward PGNN; model.structure="
                          f"{m.get('structure')!r} (set invert.model_structure: forward)")
    if len(m.get("hidden") or []) > 1 or m.get("activation", "tanh") != "tanh":
        raise ConfigError(f"identify.kind=sim_error needs the [B2] PGNN (30): one tanh hidden layer "
                          f"(model.hidden=[n1] or []), got hidden={list(m.get('hidden') or [])}, "
                          f"activation={m.get('activation')!r}")
    if not m.get("use_physics", True):
        raise ConfigError("identify.kind=sim_error needs the ARX physics part (model.use_physics=true)")
    ident = cfg.identify
    ts = ident.get("theta_star")
    if ts not in THETA_STAR:
        raise ConfigError(f"identify.theta_star={ts!r}; choose one of {THETA_STAR}")
    if int(ident.n_restarts) < 1 or int(ident.max_iter) < 0:
        raise ConfigError(f"identify.n_restarts={ident.n_restarts} (>= 1) / max_iter={ident.max_iter} (>= 0)")
    if not 0.0 <= float(ident.val_fraction) < 0.5:
        raise ConfigError(f"identify.val_fraction={ident.val_fraction}; give a value in [0, 0.5)")
    if system is not None:
        if not isinstance(system.physics, ARXPhysics):
            raise ConfigError(f"identify.kind=sim_error needs an ARX physics model ([B2] (30)); system "
                              f"'{system.name}' has {type(system.physics).__name__}")
        if (system.physics.n_a, system.physics.n_b, system.physics.n_k) != (m.n_a, m.n_b, m.n_k):
            raise ConfigError(f"model orders n_a={m.n_a}, n_b={m.n_b}, n_k={m.n_k} differ from the plant's "
                              f"ARX physics ({system.physics.n_a}, {system.physics.n_b}, {system.physics.n_k})")
        if system.controller() is None:
            raise ConfigError(f"identify.kind=sim_error simulates the closed loop; system '{system.name}' "
                              "has no feedback controller")


def build_model(cfg, system) -> PGNN:
    """The PGNN (30) of the config: ARX physics + ``model.hidden`` tanh neurons."""
    m = cfg.model
    hidden = tuple(int(h) for h in (m.get("hidden") or ()))
    return PGNN(int(m.n_a), int(m.n_b), int(m.n_k), structure="forward",
                physics=LinearFeatures(int(m.n_a) + int(m.n_b), system.physics.param_names),
                hidden=hidden, activation="tanh", use_nn=bool(hidden) and bool(m.get("use_nn", True)),
                input_transform=str(m.get("input_transform", "raw")),
                out_init_scale=float(m.get("out_init_scale", 1.0)), out_init=str(m.get("out_init", "mirrored")),
                seed=int(cfg.seed))


def fit(ctx) -> dict:
    cfg, system = ctx.cfg, ctx.system
    ds = ctx.inputs["generate"]["dataset"]
    segs = list(ds.segments())
    if len(segs) != 1:
        raise ConfigError(f"identify.kind=sim_error simulates one closed-loop record; the data have "
                          f"{len(segs)} segments (give one reference, e.g. R repeated 15 times)")
    seg = segs[0]
    r, y, u, u_fb = (seg[c].to_numpy(np.float64) for c in ("r", "y", "u", "u_fb"))
    u_ex = closed_loop_exogenous(u, u_fb)            # U_ff^d: feedforward + excitation
    ctrl = DiscreteController.from_tf(system.controller())
    model = build_model(cfg, system)
    ident = cfg.identify
    lam = OmegaConf.to_container(cfg.regularizer.lam, resolve=True) \
        if OmegaConf.is_list(cfg.regularizer.get("lam")) else float(cfg.regularizer.get("lam", 0.0))
    fit_ = identify_sim_error(model, ctrl, r, u_ex, y, u, lam=lam, theta_star=str(ident.theta_star),
                              n_restarts=int(ident.n_restarts), seed=int(cfg.seed),
                              val_fraction=float(ident.val_fraction), max_iter=int(ident.max_iter),
                              ftol=float(ident.ftol), gtol=float(ident.gtol), mu0=float(ident.mu0),
                              patience=int(ident.patience), linear_max_iter=int(ident.linear_max_iter),
                              progress=lambda it: ctx.progress(it, desc="LM restarts"))
    log_restarts(ctx, fit_.restarts)
    best = fit_.restarts[fit_.best]
    ctx.metric("cost", best.cost)
    ctx.metric("seconds", best.seconds)
    ctx.metric("iterations", best.n_iter)
    ctx.metric("identification_error", fit_.identification_error)      # [B2] (15)
    ctx.metric("n_params", model.n_params)
    ctx.metric("n1", fit_.arx.n1)
    ctx.tag("lm_stop", best.message)
    physical = system.physics.physical(fit_.arx.theta_phy)
    for k, v in physical.items():
        ctx.metric(f"theta_phy/{k}", v)
    for k, v in system.physics.physical(fit_.theta_phy_star).items():
        ctx.metric(f"theta_phy_star/{k}", v)
    ctx.figure(_figure(fit_, r, y, system.Ts), "identification.png")
    model.eval()
    return {"model": model, "arx": fit_.arx, "theta_phy_star": fit_.theta_phy_star, "physical": physical,
            "y_d": y, "y_hat_d": fit_.y_hat, "identification_error": fit_.identification_error,
            "sigma": fit_.sigma}


def _figure(fit_, r, y, Ts):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(7, 5))
    for i, rr in enumerate(fit_.restarts):
        a0.semilogy(rr.history, lw=2.0 if i == fit_.best else 0.8)
    a0.set_xlabel("accepted LM step")
    a0.set_ylabel("normalised cost (16)")
    a0.set_title(f"closed-loop simulation-error LM, n1 = {fit_.arx.n1}", fontsize=9)
    t = np.arange(y.size) * Ts
    a1.plot(t, y - fit_.y_hat, lw=0.6)
    a1.set_xlabel("t [s]")
    a1.set_ylabel("Y^d - Ŷ^d [m]")
    a1.set_title(f"identification error, rms {fit_.identification_error:.3g} m", fontsize=9)
    fig.tight_layout()
    return fig
