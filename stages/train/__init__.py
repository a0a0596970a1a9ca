"""train: identify a (PGNN) model, chosen by ``identify.kind`` (SPEC §3, §5).

Implementations: ``stages/train/<kind>.py`` exposing ``fit(ctx) -> dict`` (at least ``model``)
and optionally ``check(cfg, system)``.  ``identify.kind=none`` trains nothing: the physics
baseline is the model.
"""
from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from omegaconf import OmegaConf

from pipeline.errors import ConfigError
from pipeline.params import is_number, schema, spec
from pipeline.runner import implementation
from stages._common import baseline_lag


@schema
class RegularizerNone:
    name: Literal["none"]


def _lam_rule(v) -> str | None:
    """regularizer.lam of physics_l2: a number or a list (diag Λ) of numbers, finite, >= 0."""
    vals = v if isinstance(v, list) else [v]
    if not vals or not all(is_number(x) and math.isfinite(x) and 0 <= x <= 1e12 for x in vals):
        return "give a finite number >= 0 and <= 1e12, or a list of them (diag Λ)"
    return None


@schema
class PhysicsL2:
    name: Literal["physics_l2"]
    # Λ = lam · I ([B1] §VI: 0.01); a list gives diag(Λ)
    lam: Any = spec(0.01, check=_lam_rule)


@schema
class Orthogonal:
    name: Literal["orthogonal"]
    # λ, dimensionless: with column scaling R is the energy [N²] of the model contributions g_φ would take over ([K]
    # (20)), so λ = 1 prices it like misfit energy. A sweep (1e-3 … 1, REPORT k_two_mass) trades J_OE (~1e-3 → ~1.5
    # N²) for the share of W g_φ in im(W M) (~0.057 → ~0.02)
    lam: float = spec(1.0, ge=0, le=1e12)


UPSTREAM = ("generate", "baseline")
DEPENDS = ("model", "identify", "regularizer", "seed", "init_seed")
VERSION = 3   # 2: stop reasons (stop_reason tags, stopped_on_cap) in every fit's record; 3: numpy's tanh in the
              # forward passes (pipeline/models/activations.py, issue 19)
KIND_KEY = "identify.kind"


def validate(cfg, system) -> None:
    impl = implementation("train", str(cfg.identify.kind))
    if hasattr(impl, "check"):
        impl.check(cfg, system)


def run(ctx) -> dict:
    from pipeline.models.activations import IMPLEMENTATION  # lazy: saves 1.1 s of start-up (torch)
    ctx.tag("tanh", IMPLEMENTATION)          # numpy's or torch's on this machine (the last bits of every NN fit)
    baseline_lag(ctx)
    return implementation("train", str(ctx.cfg.identify.kind)).fit(ctx)


def init_seed(cfg) -> int:
    """The seed of the networks' initial weights and of their restarts (issue 52 item 2): ``seed`` itself at
    ``init_seed: 0`` (the default: every published number), else one drawn from (seed, init_seed), so
    ``make reproduce-spread`` fits the same data, scored under the same noise, from other starting points."""
    k = int(cfg.init_seed)
    if k == 0:
        return int(cfg.seed)
    return int(np.random.SeedSequence([int(cfg.seed), k]).generate_state(1)[0] % (2**31 - 1))


def init_purpose(cfg, purpose: str) -> str:
    """``ctx.rng``'s purpose of an initial draw: itself at ``init_seed: 0``, else tagged with it."""
    k = int(cfg.init_seed)
    return purpose if k == 0 else f"{purpose}/init{k}"


def check_rows(model, n_samples: int, val_fraction: float) -> None:
    """Refuse (before the first LM step) a model with more parameters than the fit has equations: LM's
    Jacobian (equations x parameters) cannot determine them, and 7 998 rows for 600 005 parameters
    raised in train (issue 51). The equations are at most the training share of the samples."""
    rows = int((1.0 - val_fraction) * n_samples)
    if model.n_params > rows:
        raise ConfigError(f"the model has {model.n_params} parameters but the training data give at most {rows} "
                          f"equations ({n_samples} samples, identify.val_fraction={val_fraction:g}): the fit cannot "
                          "determine them; give a smaller network (model.hidden, e.g. [16]) or a longer recording")


def l2_lam(cfg):
    """Λ of the physics-L2 regulariser ([B1] (12), [B2] (16)): ``regularizer.lam``, a number or a
    list (diag Λ); regularizer=none has no λ: 0, no regularisation."""
    lam = cfg.regularizer.get("lam")
    if lam is None:
        return 0.0
    return OmegaConf.to_container(lam, resolve=True) if OmegaConf.is_list(lam) else float(lam)


def restart_options(ident, measured: bool = False) -> dict:
    """The LM and restart options of ``identify`` that every LM fit with restarts takes (narx,
    sim_error simulated and measured; :func:`pipeline.identify.narx.best_of_restarts` and
    :func:`pipeline.identify.lm.levenberg_marquardt`), read in one place so that no path drops one
    (the measured sim_error path once ignored ``screen_iter``). ``identify.stat_promise=auto`` is
    ``damped`` on a measured system (``measured``), ``gauss_newton`` on a simulated one."""
    promise = str(ident.stat_promise)
    if promise == "auto":
        promise = "damped" if measured else "gauss_newton"
    return dict(n_restarts=int(ident.n_restarts), max_iter=int(ident.max_iter), ftol=float(ident.ftol),
                gtol=float(ident.gtol), mu0=float(ident.mu0), geodesic=bool(ident.geodesic),
                stat_window=int(ident.stat_window), stat_tol=float(ident.stat_tol),
                stat_frac=float(ident.stat_frac), screen_iter=int(ident.screen_iter), stat_promise=promise)


def lm_progress(ctx, desc: str = "LM restarts") -> dict:
    """``progress`` and ``on_iteration`` for :func:`pipeline.identify.narx.best_of_restarts`: one bar
    over the restarts whose postfix shows the running restart's LM step and cost."""
    bar = {}

    def progress(iterable):
        items = list(iterable)
        bar["bar"] = b = ctx.progress(None, desc=desc, total=len(items))   # manual: its count is current

        def advance():
            for x in items:
                yield x
                b.update(1)
            b.close()
        return advance()

    def on_iteration(i, it, cost):
        if "bar" in bar and it % 10 == 0:
            bar["bar"].set_postfix(step=it, cost=f"{cost:.4e}")
    return {"progress": progress, "on_iteration": on_iteration}


def restart_memo(ctx):
    """``memo(i, budget, compute)`` for :func:`pipeline.identify.narx.best_of_restarts`: restart i
    on an LM budget, cached on the train key without ``identify.n_restarts``, ``max_iter`` and
    ``screen_iter`` (its seed is (seed, i) whatever the count; its budget is in the label)."""
    return lambda i, budget, compute: ctx.memo(
        f"restart{i}/max_iter{budget}", compute,
        exclude=("identify.n_restarts", "identify.max_iter", "identify.screen_iter"))


def log_restarts(ctx, restarts, best: int) -> None:
    """The loss curve (and validation curve) of every LM restart, and its cost, time and iterations."""
    for i, rr in enumerate(restarts):
        for step, c in enumerate(rr.history):
            ctx.metric(f"loss/restart{i}", c, step=step)
        for step, c in enumerate(rr.val_history):
            ctx.metric(f"val_loss/restart{i}", c, step=step)
        ctx.metric("restart_cost", rr.cost, step=i)
        ctx.metric("restart_seconds", rr.seconds, step=i)
        ctx.metric("restart_iterations", rr.n_iter, step=i)
        ctx.tag(f"stop_reason.restart{i}", rr.message)       # why it stopped: a tolerance or CAPS
    ctx.tag("stop_reason", restarts[best].message)
    ctx.metric("stopped_on_cap", float(restarts[best].message in CAPS))     # the report flags these


#: LM stop reasons that are a budget, not convergence (pipeline.identify.lm)
CAPS = ("max_iter",)
