"""Benchmark: one Levenberg–Marquardt iteration of the [B2] simulation-error fit against its floor.

The B2 case of ``benchmarks/bench_b2.py``: the PGNN (30) with ``--n1`` (32) tanh neurons on the
4,500-sample rot_trans_nmp training record (R × 15, white U_ff^d in [10, 40] s), θ*_phy from the
closed-loop simulation-error linear fit, then ``--fit-iter`` LM iterations of the PGNN fit so that
θ is a realistic iterate (not the initialisation).  At that θ it prints the CPU time
(``time.process_time``, one call per item, median over ``--repeats`` repeats; the items are
interleaved in every repeat, so a drift of the machine's speed shows in all of them) of

- ``simulation``: one closed-loop model simulation (:func:`simulate_closed_loop`);
- ``residual``: the criterion's residual (``sim_error_criterion``; one simulation);
- ``jacobian_theta``: the public kernel ∂Ŷ/∂θ (its own simulation included);
- ``criterion jacobian``: ``sim_error_criterion``'s ``jacobian`` at the θ of the last residual,
  as LM calls it (the sensitivities; scaled rows and the regulariser rows included);
- ``syrk``: JᵀJ of the criterion's N×p Jacobian by ``scipy.linalg.blas.dsyrk``, and numpy's
  ``J.T @ J`` (``pipeline.identify.lm``'s path, also syrk);
- ``LM iteration``: the work of one accepted iteration of
  :func:`pipeline.identify.lm.levenberg_marquardt`, with its torch/numpy calls: the residual at
  the trial point, the Jacobian, JᵀJ, Jᵀr, the scaled damped normal equations by Cholesky;
- the floor = syrk + simulation, and two ratios: the whole LM iteration / floor, and
  (syrk + criterion jacobian + simulation) / floor, the iteration without LM's own small p×p and
  Jᵀr work (the target of the kernel: ≤ 1.3).

``--impl PATH`` times another single-file copy of the closed-loop simulation and criterion (e.g. before
they were split into ``pipeline/models/closed_loop.py`` and ``pipeline/identify/sim_error.py``:
``git show ec882d3:pipeline/identify/sim_error.py > /tmp/sim_error_head.py``); the data, the model
and the warm-up fit always use the installed one.

Usage: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_floors.py [--n1 32] [--repeats 21]
[--impl PATH] [--json out.json]``.  Numbers depend on the machine's load; run it alone.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.linalg.blas import dsyrk  # noqa: E402

from bench_b2 import training_data  # noqa: E402
from types import SimpleNamespace  # noqa: E402

from pipeline.identify import sim_error as _criterion  # noqa: E402
from pipeline.models import closed_loop  # noqa: E402

# the installed code as one namespace: the closed-loop simulation (pipeline/models/closed_loop.py) and the
# criterion and fit (pipeline/identify/sim_error.py), as a single-file copy given by --impl has them
sim_error = SimpleNamespace(**{**vars(closed_loop), **vars(_criterion)})
from pipeline.identify.lm import _gram  # noqa: E402
from pipeline.models.pgnn import PGNN  # noqa: E402
from pipeline.models.physics_maps import LinearFeatures  # noqa: E402


def cpu_ms(fn) -> float:
    """CPU time of one call ``fn()`` [ms]."""
    t0 = time.process_time()
    fn()
    return (time.process_time() - t0) * 1e3


def lm_iteration(residual, jacobian, theta: np.ndarray, mu: float = 1e-3):
    """The work of one accepted LM iteration with ``lm.py``'s calls: residual (at the trial point,
    where LM then evaluates the Jacobian), Jacobian, JᵀJ, Jᵀr, scaled damped Cholesky solve."""
    th = torch.from_numpy(theta)
    r = torch.from_numpy(residual(theta))
    J = torch.from_numpy(jacobian(theta)).detach()
    A = _gram(J)
    g = J.T @ r
    diag = torch.diagonal(A).clone()
    d = torch.where(diag > 0, diag, torch.ones_like(diag))
    s = 1.0 / torch.sqrt(d)
    A_s = A * s[:, None] * s[None, :]
    g_s = g * s
    L, _ = torch.linalg.cholesky_ex(A_s + mu * torch.eye(theta.size, dtype=torch.float64))
    return th - torch.cholesky_solve(g_s[:, None], L)[:, 0] * s


def load_impl(path: str | None):
    """The sim_error module to time: the installed one, or a copy of it at ``path``."""
    if path is None:
        return sim_error
    spec = importlib.util.spec_from_file_location("sim_error_impl", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod                         # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n1", type=int, default=32)
    ap.add_argument("--fit-iter", type=int, default=12, help="LM iterations of the warm-up PGNN fit")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--impl", type=str, default=None, help="time this copy of sim_error.py instead")
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(1)

    plant, sim = training_data()
    ctrl = sim_error.DiscreteController.from_tf(plant.controller())
    u_ex = sim_error.closed_loop_exogenous(sim.u, sim.u_fb)
    r, y = sim.r, sim.y
    N = y.size
    lin = sim_error.identify_sim_error(PGNN(4, 4, 0, physics=LinearFeatures(8), use_nn=False), ctrl, r, u_ex, y,
                                       sim.u, theta_star="sim_error", max_iter=50)
    model = PGNN(4, 4, 0, physics=LinearFeatures(8), hidden=(args.n1,), input_transform="raw",
                 out_init="mirrored", out_init_scale=1.0)
    stamps = []
    fit = sim_error.identify_sim_error(model, ctrl, r, u_ex, y, sim.u, theta_star=lin.theta_phy_star,
                                       max_iter=args.fit_iter, seed=0,
                                       on_iteration=lambda i, it, c: stamps.append(time.process_time()))

    impl = load_impl(args.impl)
    arx = impl.ArxPGNN(**{f.name: getattr(fit.arx, f.name) for f in dataclasses.fields(fit.arx)})
    ctrl = impl.DiscreteController(ctrl.A, ctrl.B, ctrl.C, ctrl.D, ctrl.dt)
    theta = arx.theta()
    residual, jacobian = impl.sim_error_criterion(arx, ctrl, r, u_ex, y, fit.theta_phy_star, 1.0, slice(0, N),
                                                  fit.sigma)
    Jc = jacobian(theta)
    M, P = Jc.shape
    JT = Jc.T                                            # F-ordered P×M view: syrk 'N' gives JᵀJ

    def criterion_jacobian():                            # at the θ of the last residual, as in LM
        jacobian(theta)

    fns = {"simulation": lambda: impl.simulate_closed_loop(arx, ctrl, r, u_ex),
           "residual (criterion)": lambda: residual(theta),
           "jacobian_theta (simulation + sensitivities)": lambda: impl.jacobian_theta(arx, ctrl, r, u_ex),
           "criterion jacobian (sensitivities, as LM calls it)": criterion_jacobian,
           "syrk JᵀJ (scipy dsyrk)": lambda: dsyrk(1.0, JT, trans=0, lower=1),
           "numpy J.T @ J (lm._gram)": lambda: Jc.T @ Jc,
           "LM iteration (residual + jacobian + JᵀJ + Jᵀr + solve)": lambda: lm_iteration(residual, jacobian,
                                                                                         theta)}
    for f in fns.values():                               # warm-up (numba compiled, caches)
        f()
    times = {k: [] for k in fns}
    for _ in range(args.repeats):
        for k, f in fns.items():
            if k.startswith("criterion jacobian"):
                residual(theta)                          # LM's order: the residual, then the Jacobian
            times[k].append(cpu_ms(f))
    med = {k: float(np.median(v)) for k, v in times.items()}
    syrk = med["syrk JᵀJ (scipy dsyrk)"]
    floor = syrk + med["simulation"]
    sens = med["criterion jacobian (sensitivities, as LM calls it)"]
    out = {"implementation": args.impl or "installed", "n1": args.n1, "N": N, "rows": M, "params": P,
           **{f"{k} [ms]": v for k, v in med.items()},
           "floor = syrk + simulation [ms]": floor,
           "ratio LM iteration / floor": med["LM iteration (residual + jacobian + JᵀJ + Jᵀr + solve)"] / floor,
           "ratio (syrk + sensitivities + simulation) / floor": (syrk + sens + med["simulation"]) / floor,
           "syrk rate [GFlop/s]": M * P * (P + 1) / (syrk * 1e-3) / 1e9}
    if len(stamps) > 2:
        out["warm-up fit (installed sim_error), ms per accepted LM iteration"] = float(np.median(np.diff(stamps))
                                                                                       * 1e3)
    print(f"B2 PGNN n1 = {args.n1}: N = {N} samples, J {M} × {P}; CPU ms, median of {args.repeats}")
    for k, v in out.items():
        print(f"  {k:58s} {v:.3f}" if isinstance(v, float) else f"  {k:58s} {v}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
