"""identify.kind=inverse_bias: [B1] §II-C consistency study on the ARX system (SPEC §2.4, §8 B1a).

For every N in ``identify.sample_sizes`` and ``identify.n_seeds`` data sets (white u, white
equation noise, drawn by the system), the forward least squares [B1] (7) and the direct-inverse
least squares [B1] (16)-(17) (both the physics-only PGNN with ARX features, closed form) are
computed; their parameter errors ‖θ̂ - θ0‖ and ‖θ̂' - θ0'‖ are averaged over seeds and
compared with the closed-form asymptotic bias (18) (:func:`arx_inverse_asymptotics`).

Metrics: ``train/forward_error/N<N>``, ``train/inverse_error/N<N>`` (means over seeds),
``train/forward_slope`` (log-log slope of the mean forward error over N),
``train/inverse_to_forward`` (ratio at the largest N), ``train/bias_norm`` (‖(18)‖),
``train/inverse_bias_deviation`` (‖mean θ̂' - θ0' - (18)‖ / ‖(18)‖ at the largest N).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from omegaconf import OmegaConf

from pipeline.errors import ConfigError
from pipeline.identify.narx import arx_inverse_asymptotics, forward_regressor, inverse_regressor, physics_least_squares
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import LinearFeatures
from pipeline.params import COUNT_MAX, schema, spec
from pipeline.plots import pyplot


@schema
class Params:
    kind: Literal["inverse_bias"]
    name: str = "inverse_bias"
    # N [samples] per data set
    sample_sizes: list[int] = spec([1000, 10000, 100000], ge=10, le=10**8, min_len=2,
                                   rule="give at least two sizes >= 10 (and <= 1e8)")
    # data sets per N (SPEC: >= 20)
    n_seeds: int = spec(20, ge=2, le=COUNT_MAX)


def check(cfg, system) -> None:
    if system is not None and not hasattr(system, "generate"):
        raise ConfigError(f"identify.kind=inverse_bias needs the arx_bias system (it draws its own "
                          f"data sets), got system '{getattr(system, 'name', system)}'")
    # identify.sample_sizes (>= 2 sizes >= 10), identify.n_seeds (>= 2): pipeline.schema


def fit(ctx) -> dict:
    system = ctx.system
    sizes = [int(n) for n in OmegaConf.to_container(ctx.cfg.identify.sample_sizes, resolve=True)]
    n_seeds = int(ctx.cfg.identify.n_seeds)
    n_a, n_b = system.a.size, system.b.size
    theta0 = system.theta0
    theta_inv, bias, _ = arx_inverse_asymptotics(system.a, system.b, system.u_std, system.std)
    fwd = PGNN(n_a, n_b, 0, structure="forward", physics=LinearFeatures(n_a + n_b), use_nn=False)
    inv = PGNN(n_a, n_b, 0, structure="inverse", physics=LinearFeatures(n_a + n_b), use_nn=False)
    err_f, err_i, dev = {}, {}, {}
    for N in ctx.progress(sizes, desc="sample sizes"):
        ef, ei, di = [], [], []
        for s in range(n_seeds):
            sim = system.generate(N, ctx.rng(f"inverse_bias/N{N}/seed{s}"))
            rf = forward_regressor(sim.y, sim.u, n_a, n_b, 0)
            ri = inverse_regressor(sim.y, sim.u, n_a, n_b, 0)
            th = physics_least_squares(fwd, rf.phi, rf.target)  # [B1] (7)
            thi = physics_least_squares(inv, ri.phi, ri.target)  # [B1] (17)
            ef.append(np.linalg.norm(th - theta0))
            ei.append(np.linalg.norm(thi - theta_inv))
            di.append(thi - theta_inv)
        err_f[N], err_i[N], dev[N] = float(np.mean(ef)), float(np.mean(ei)), np.mean(di, axis=0)
        ctx.metric(f"forward_error/N{N}", err_f[N])
        ctx.metric(f"inverse_error/N{N}", err_i[N])
        ctx.metric(f"forward_error_std/N{N}", float(np.std(ef)))
        ctx.metric(f"inverse_error_std/N{N}", float(np.std(ei)))
    slope = float(np.polyfit(np.log10(sizes), np.log10([err_f[n] for n in sizes]), 1)[0])
    n_max = max(sizes)
    bias_norm = float(np.linalg.norm(bias))
    deviation = float(np.linalg.norm(dev[n_max] - bias) / bias_norm)
    ctx.metric("forward_slope", slope)
    ctx.metric("inverse_to_forward", err_i[n_max] / err_f[n_max])
    ctx.metric("bias_norm", bias_norm)
    ctx.metric("inverse_error_to_bias", err_i[n_max] / bias_norm)
    ctx.metric("inverse_bias_deviation", deviation)
    ctx.metric("n_seeds", n_seeds)
    ctx.figure(_figure(sizes, err_f, err_i, bias_norm), "consistency.png")
    return {"model": None, "sizes": sizes, "forward_error": err_f, "inverse_error": err_i,
            "bias": bias, "theta_inv": theta_inv, "mean_inverse_deviation": dev}


def _figure(sizes, err_f, err_i, bias_norm):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.loglog(sizes, [err_f[n] for n in sizes], "o-", label="forward ‖θ̂ - θ0‖ ([B1] (7))")
    ax.loglog(sizes, [err_i[n] for n in sizes], "s-", label="direct inverse ‖θ̂' - θ0'‖ ([B1] (17))")
    ax.axhline(bias_norm, color="k", ls="--", lw=0.8, label="‖asymptotic bias (18)‖")
    ref = err_f[sizes[0]] * (np.asarray(sizes) / sizes[0]) ** -0.5
    ax.loglog(sizes, ref, ":", color="gray", label="slope -1/2")
    ax.set_xlabel("N [samples]")
    ax.set_ylabel("mean parameter error")
    ax.legend(fontsize=7)
    ax.set_title("[B1] §II-C: forward consistent, direct inverse biased", fontsize=9)
    return fig
