"""Benchmark of the [B1] library (SPEC §7 cost, claim B1c).

Prints
- LM time per restart (one restart, ``--max-iter`` iterations) for a forward PGNN with 16
  tanh neurons on a 120,000-sample linear-motor data set (SPEC §2.2 'equation' noise), and the
  peak resident memory of the process (``resource.getrusage``: it includes torch's buffers,
  which tracemalloc does not see);
- per-sample feedforward times (median over the samples of a 0.15 m/s evaluation reference,
  after a warm-up) of the direct inverse, Newton k = 5 ([B1] Alg. 1) and analytic ([B1] (27))
  inversions: each sample is one call of the numba per-sample kernel from Python (call
  overhead included, what a sample-by-sample loop pays), plus the whole-trajectory time / N.

Usage: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_b1.py [--n 120000] [--max-iter 200]``
"""
from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np
import torch

from pipeline.identify.narx import identify_pgnn
from pipeline.invert.analytic import analytic_feedforward, analytic_step
from pipeline.invert.direct import direct_feedforward, direct_step, per_sample_seconds
from pipeline.invert.newton import newton_feedforward, newton_step
from pipeline.models.fast_pgnn import fast_pgnn
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import RigidBodyForward, RigidBodyInverse
from pipeline.references import b1_evaluation_reference, b1_training_reference
from pipeline.systems.linear_motor import LinearMotor


def motor_data(n: int, seed: int = 0):
    """Closed-loop data of the 'equation' linear motor (SPEC §2.2): the [B1] §VI training
    reference (cut or repeated to n samples) plus Δu ~ N(0, 50²) N."""
    rng = np.random.default_rng(seed)
    sys_ = LinearMotor(noise={"structure": "equation", "std": 1e-6})
    r = b1_training_reference(sys_.Ts).r
    r = np.tile(r, int(np.ceil(n / r.shape[0])))[:n]
    res = sys_.simulate(r, du=50.0 * rng.standard_normal(n), v=sys_.noise(n, rng))
    return res.r, res.y, res.u


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=120_000, help="training samples")
    ap.add_argument("--max-iter", type=int, default=200,
                    help="LM iterations of the timed restart (conf/identify/narx.yaml: 200)")
    ap.add_argument("--hidden", type=int, default=16)
    a = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(1)

    t0 = time.perf_counter()
    r, y, u = motor_data(a.n)
    print(f"data: {a.n} samples simulated in {time.perf_counter() - t0:.1f} s")
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    models = {}
    for struct, phys in [("forward", RigidBodyForward(1e-3)), ("invertible", RigidBodyForward(1e-3)),
                         ("inverse", RigidBodyInverse(1e-3))]:
        m = PGNN(2, 1, 0, structure=struct, physics=phys, hidden=(a.hidden,),
                 input_transform="raw", out_init="mirrored", out_init_scale=1.0)  # conf/model/pgnn
        fit = identify_pgnn(m, y, u, n_restarts=1, val_fraction=0.0, max_iter=a.max_iter,
                            ftol=0.0, gtol=0.0)
        rr = fit.restarts[0]
        print(f"LM {struct:10s}: {rr.seconds:7.2f} s per restart ({rr.n_iter} iterations, "
              f"{rr.seconds / max(rr.n_iter, 1) * 1e3:.0f} ms/iteration, {m.n_params} parameters, "
              f"{fit.n_train} rows, stop: {rr.message})")
        models[struct] = m
        if struct == "forward" and a.max_iter > 20:
            a.max_iter = 20  # the other two only need to be trained a little for timing
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS: {rss:.0f} MB (before identification {rss0:.0f} MB)")

    r_ev = b1_evaluation_reference(0.15, 1e-3).r
    print(f"feedforward on a {r_ev.shape[0]}-sample reference (median per sample, after warm-up):")
    rows = [("direct", "inverse", direct_step, (), lambda m: direct_feedforward(m, r_ev)),
            ("Newton k=5", "forward", newton_step, (5, -np.inf, np.inf),
             lambda m: newton_feedforward(m, r_ev, k=5)),
            ("analytic", "invertible", analytic_step, (), lambda m: analytic_feedforward(m, r_ev))]
    for name, struct, step, args, whole in rows:
        m = models[struct]
        fm = fast_pgnn(m)
        whole(m)  # warm-up / compile
        ts = per_sample_seconds(step, fm, r_ev, *args)
        t0 = time.perf_counter()
        whole(m)
        tw = (time.perf_counter() - t0) / r_ev.shape[0]
        print(f"  {name:11s}: median {np.median(ts) * 1e6:6.3f} µs/sample (p99 "
              f"{np.percentile(ts, 99) * 1e6:6.3f} µs, {ts.size} samples); whole trajectory "
              f"{tw * 1e6:6.3f} µs/sample")


if __name__ == "__main__":
    main()
