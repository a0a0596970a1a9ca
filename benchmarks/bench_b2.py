"""Benchmark of the [B2] library on one CPU core (SPEC §8 B2d and the training-time target).

1. Closed-loop simulation-error training ([B2] (16)) of the PGNN (30) with n1 = 32 on the
   4,500-sample rot_trans_nmp data set (R × 15, white U_ff^d of 20 N in [10, 40] s, noise
   1e-6 m): wall time, LM iterations, identification error.
2. FHOFC ([B2] (17)) for N_k = 300, n1 = 32, γ = 1e-6 (and 5e-5, 1e-8): median solve time
   over repeats after a warm-up.

Usage: ``python benchmarks/bench_b2.py [--max-iter 300] [--repeats 5] [--json out.json]``.
Numbers depend on the machine's load; run it alone.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from pipeline.identify.sim_error import closed_loop_exogenous, identify_sim_error  # noqa: E402
from pipeline.models.closed_loop import DiscreteController  # noqa: E402
from pipeline.invert.fhofc import fhofc  # noqa: E402
from pipeline.models.pgnn import PGNN  # noqa: E402
from pipeline.models.physics_maps import LinearFeatures  # noqa: E402
from pipeline.references import b2_reference, b2_training_reference  # noqa: E402
from pipeline.systems.rot_trans_nmp import RotTransNMP  # noqa: E402


def training_data(seed: int = 0):
    """[B2] §VI data: R repeated 15 times, white excitation (std 20 N) in [10, 40] s, noise 1e-6 m."""
    plant = RotTransNMP()
    r = b2_training_reference(plant.Ts).r
    rng = np.random.default_rng(seed)
    t = np.arange(r.size) * plant.Ts
    du = np.where((t >= 10.0) & (t < 40.0), 20.0 * rng.standard_normal(r.size), 0.0)
    v = plant.noise(r.size, rng)
    return plant, plant.simulate(r, du=du, v=v)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n1", type=int, default=32)
    ap.add_argument("--max-iter", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    plant, sim = training_data()
    ctrl = DiscreteController.from_tf(plant.controller())
    u_ex = closed_loop_exogenous(sim.u, sim.u_fb)
    out = {"n1": args.n1, "N_d": int(sim.y.size)}

    # warm-up: numba compilation (cached on disk after the first run)
    warm = PGNN(4, 4, 0, physics=LinearFeatures(8), hidden=(2,), input_transform="raw")
    identify_sim_error(warm, ctrl, sim.r[:600], u_ex[:600], sim.y[:600], sim.u[:600], max_iter=2)

    t0 = time.perf_counter()
    lin = identify_sim_error(PGNN(4, 4, 0, physics=LinearFeatures(8), use_nn=False), ctrl, sim.r, u_ex,
                             sim.y, sim.u, theta_star="sim_error", max_iter=50)
    out["linear_train_s"] = time.perf_counter() - t0
    out["linear_identification_error"] = lin.identification_error

    # the experiment's model: raw regressor ([B2] (30)), mirrored output init (conf/model/pgnn.yaml)
    model = PGNN(4, 4, 0, physics=LinearFeatures(8), hidden=(args.n1,), input_transform="raw",
                 out_init="mirrored", out_init_scale=1.0)
    t0 = time.perf_counter()
    fit = identify_sim_error(model, ctrl, sim.r, u_ex, sim.y, sim.u, theta_star=lin.theta_phy_star,
                             max_iter=args.max_iter, seed=0)
    out["pgnn_train_s"] = time.perf_counter() - t0
    rr = fit.restarts[fit.best]
    out["pgnn_lm_iterations"] = rr.n_iter
    out["pgnn_lm_message"] = rr.message
    out["pgnn_train_s_per_iteration"] = out["pgnn_train_s"] / max(rr.n_iter, 1)
    out["pgnn_identification_error"] = fit.identification_error

    r = b2_reference(plant.Ts).r
    for gamma in (1e-6, 5e-5, 1e-8):
        fhofc(fit.arx, ctrl, r, gamma=gamma)                    # warm-up
        times, res = [], None
        for _ in range(args.repeats):
            res = fhofc(fit.arx, ctrl, r, gamma=gamma)
            times.append(res.time_s)
        key = f"fhofc_gamma{gamma:g}"
        out[f"{key}_median_s"] = float(np.median(times))
        out[f"{key}_iterations"] = res.n_iter
        out[f"{key}_inversion_error"] = res.inversion_error
        out[f"{key}_converged"] = res.converged
    for k, v in out.items():
        print(f"{k:40s} {v}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
