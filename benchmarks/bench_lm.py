"""Benchmark: one Levenberg–Marquardt iteration of the [B1] PGNN against the machine's floor.

The dominant cost of an LM iteration on a tall problem is forming JᵀJ (BLAS syrk, M·P² flops)
and the Jacobian J itself.  This prints, for the linear-motor PGNN of ``conf/model/pgnn.yaml``
(forward, 16 tanh neurons, 84 parameters) on ``--rows`` training rows (the record is sized so that
80 % of it gives that many rows; default 120,000 × 84, the acceptance shape of issue 10 item 1):

- ms per LM iteration (median over the accepted iterations of ``--iters`` damped solves of one
  restart, ftol = gtol = 0);
- the floor: the measured time of numpy's ``J.T @ J`` (syrk) on a random array of the same shape
  (median of 7 before and 7 after the fit, so a drift of the machine's speed shows in both), and
  the ratio iteration / floor;
- the peak resident memory of the process.

Usage: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_lm.py [--rows 120000] [--iters 30]``
"""
from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np
import torch

from pipeline.identify.narx import identify_pgnn
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import RigidBodyForward

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from bench_b1 import motor_data  # noqa: E402


def syrk_seconds(J: np.ndarray) -> float:
    t0 = time.perf_counter()
    J.T @ J  # numpy: BLAS syrk
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=120_000, help="training rows (80 %% of the record)")
    ap.add_argument("--iters", type=int, default=30, help="timed LM iterations")
    ap.add_argument("--hidden", type=int, default=16)
    a = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(1)
    m = PGNN(2, 1, 0, structure="forward", physics=RigidBodyForward(1e-3), hidden=(a.hidden,),
             input_transform="raw", out_init="mirrored", out_init_scale=1.0)
    r, y, u = motor_data(round((a.rows + m.n_a) / 0.8))  # n_a samples start the regressor
    J = np.random.default_rng(0).standard_normal((a.rows, m.n_params))
    ts = [syrk_seconds(J) for _ in range(7)]
    stamps = []
    fit = identify_pgnn(m, y, u, n_restarts=1, val_fraction=0.2, max_iter=a.iters, ftol=0.0, gtol=0.0,
                        patience=10 ** 6, on_iteration=lambda i, it, c: stamps.append(time.perf_counter()))
    rr = fit.restarts[0]
    per_iter = np.diff(stamps) if len(stamps) > 2 else np.array([rr.seconds / max(rr.n_iter, 1)])
    M, P = fit.n_train, m.n_params
    if J.shape != (M, P):
        raise RuntimeError(f"the fit has {M} x {P}, the floor was timed at {J.shape}")
    ts += [syrk_seconds(J) for _ in range(7)]
    floor = float(np.median(ts))
    it = float(np.median(per_iter))
    print(f"LM on {M} rows x {P} parameters: {it * 1e3:.1f} ms per accepted iteration (median of "
          f"{per_iter.size}; {rr.n_iter} damped solves in {rr.seconds:.2f} s)")
    print(f"floor: syrk JᵀJ {floor * 1e3:.1f} ms (median of {len(ts)}); ratio {it / floor:.2f}x")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
