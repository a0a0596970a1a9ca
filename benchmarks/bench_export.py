"""Benchmark of the exported feedforward laws (issue 12): ns per sample in C beside numba.

For each law: the generated C99 (compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror``, timed
by its harness: median over ``--repeats`` runs of the whole reference, per sample), the numba
per-sample kernel called from Python once per sample (dispatch included, what a Python loop
pays), the numba whole-trajectory run / N, and [B1] Table I (MATLAB, per sample).  Models have
the shapes of the paper experiments (random weights: the cost does not depend on their values):
[B1] PGNNs with 16 tanh neurons on the 0.15 m/s reference, the [K] rational TF (n_a = 10,
n_b = 9) and shared-AR PGNN (5-10-10-1) on 3 s of motion.

Usage: ``.venv/bin/python benchmarks/bench_export.py [--repeats 51]``
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.export.law import from_k_filter, from_pgnn
from pipeline.export.package import find_compiler, write_package
from pipeline.invert.analytic import analytic_feedforward, analytic_step
from pipeline.invert.direct import direct_feedforward, direct_step, per_sample_seconds
from pipeline.invert.newton import newton_feedforward, newton_step
from pipeline.invert.rational_filter import rational_feedforward
from pipeline.models.fast_pgnn import fast_pgnn
from pipeline.models.pgnn import PGNN
from pipeline.models.physics_maps import RigidBodyForward, RigidBodyInverse
from pipeline.models.rational import RationalFeedforward
from pipeline.models.shared_ar import ReferenceWindow, SharedARPGNN, make_approximator
from pipeline.references import b1_evaluation_reference

TABLE_I = {"newton": 128e3, "direct": 0.42e3, "analytic": 0.38e3}   # [B1] Table I, ns per sample (MATLAB)


def _pgnn(structure, physics, theta):
    m = PGNN(2, 1, 0, structure=structure, physics=physics, hidden=(16,), seed=0, out_init_scale=0.3)
    m.set_physics_estimate(theta)
    m.fit_normalisation(torch.as_tensor(np.random.default_rng(0).standard_normal((100, 3)) * 1e-2))
    return m


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=51)
    a = ap.parse_args()
    if find_compiler("cc") is None:
        raise SystemExit("no C compiler 'cc': nothing to time")
    Ts = 1e-3
    r = b1_evaluation_reference(0.15, Ts=Ts).r
    fwd, inv = (1 / 5.0, 10 / 5.0, 2 / 5.0), (5.0, 10.0, 2.0)
    cases = [("newton", _pgnn("forward", RigidBodyForward(Ts), fwd), newton_step, (5, -np.inf, np.inf),
              lambda m, r: newton_feedforward(m, r, k=5).u_ff),
             ("direct", _pgnn("inverse", RigidBodyInverse(Ts), inv), direct_step, (), direct_feedforward),
             ("analytic", _pgnn("invertible", RigidBodyForward(Ts), fwd), analytic_step, (), analytic_feedforward)]
    print(f"{'law':<26}{'C ns/sample':>13}{'numba step ns':>15}{'numba run ns':>14}{'[B1] Table I':>14}  C vs study")
    with tempfile.TemporaryDirectory() as tmp:
        for law, m, step, args, run in cases:
            u = run(m, r)
            man = write_package(from_pgnn(m, law, Ts, k=5), f"ff_{law}", Path(tmp), {"v0.15": (r, u)},
                                source={}, timing_repeats=a.repeats)
            step_ns = float(np.median(per_sample_seconds(step, fast_pgnn(m), r, *args))) * 1e9
            t0 = time.perf_counter()
            for _ in range(5):
                run(m, r)
            run_ns = (time.perf_counter() - t0) / 5 / r.size * 1e9
            print(f"{law + ' (H = 16)':<26}{man['c_ns_per_sample']:>13.0f}{step_ns:>15.0f}{run_ns:>14.0f}"
                  f"{TABLE_I[law]:>14.0f}  {man['c_max_rel_diff']:.1g}")
        rk = np.concatenate([r[:3000], np.full(200, r[2999])])
        g = make_approximator("mlp", 5, seed=0, hidden=(10, 10), activation="tanh")
        k_models = [("rational (10/9)", RationalFeedforward(10, 9, basis="delta", Ts=Ts, a=np.linspace(1, 2, 10) * 1e-3,
                                                            b=np.r_[2e-3, 1e-6, np.zeros(7)])),
                    ("pgnn_shared_ar (5-10-10-1)", SharedARPGNN(5, 2, g, ReferenceWindow(4, "delta", Ts).fit(rk),
                                                                basis="delta", Ts=Ts, a=[0.1, 2, 3e-3, 1e-6, 1e-9],
                                                                b=[2e-3, 1e-6]))]
        for label, m in k_models:
            t0 = time.perf_counter()
            u = rational_feedforward(m, rk).f
            run_ns = (time.perf_counter() - t0) / rk.size * 1e9
            man = write_package(from_k_filter(m), "ff_k", Path(tmp), {"r": (rk, u)}, source={},
                                timing_repeats=a.repeats)
            print(f"{label:<26}{man['c_ns_per_sample']:>13.0f}{'-':>15}{run_ns:>14.0f}{'-':>14}  "
                  f"{man['c_max_rel_diff']:.1g}")
    print("numba run: whole trajectory / N (torch + scipy for [K]); C: median of the harness over the reference")


if __name__ == "__main__":
    main()
