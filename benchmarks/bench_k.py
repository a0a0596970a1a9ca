"""Benchmark of the [K] library: wall and CPU time per SK iteration (SPEC §5, §7 cost).

On the nine [K] training references of the two-mass Stribeck plant (SPEC §2.1, exact optimal
inputs, 21,167 samples) prints, per SK iteration (j ≥ 1):

- the rational transfer function (N_a = 10, N_b = 9; closed-form weighted least squares);
- the PGNN with shared AR dynamics (N_a = 5, N_b = 2, MLP 5-10-10-1, orthogonal regulariser):
  one SK iteration = ``--lm-iter`` LM iterations of the variable-projection step; the time per
  LM iteration and the split of one LM iteration (Jacobian of g_φ, filtering by 1/B, projection,
  the normal equations JᵀJ) are printed too.

CPU time (``time.process_time``) is shown beside wall time: on a shared machine wall time
includes waiting for a core.

Usage: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_k.py [--sk-iter 3] [--lm-iter 20]``
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np
import torch

from pipeline.identify.sk import SKNotConvergedWarning, prepare_data, sk_iterations
from pipeline.models.rational import RationalFeedforward, filter_segments
from pipeline.models.shared_ar import ReferenceWindow, SharedARPGNN, make_approximator
from pipeline.references import K_TRAINING_MOVES, out_and_back
from pipeline.systems.two_mass_stribeck import TwoMassStribeck


def training_data():
    """The nine [K] training references and their exact optimal inputs (SPEC §2.1)."""
    plant = TwoMassStribeck()
    rs = [out_and_back(d, v, 5.0, 200.0, plant.Ts).r for d, v in K_TRAINING_MOVES]
    return plant, rs, [plant.exact_inverse(r) for r in rs]


class Clock:
    def __init__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def lap(self) -> tuple[float, float]:
        w, c = time.perf_counter(), time.process_time()
        out = (w - self.wall, c - self.cpu)
        self.wall, self.cpu = w, c
        return out


def report(name: str, res, clock_total: tuple[float, float]) -> None:
    secs = [it.seconds for it in res.iterates[1:]]
    print(f"{name}: {len(secs)} SK iterations, wall per iteration median {np.median(secs):.3f} s "
          f"(min {min(secs):.3f}, max {max(secs):.3f}); whole run wall {clock_total[0]:.2f} s, "
          f"CPU {clock_total[1]:.2f} s; J_OE best {min(res.J_OE):.4g} N²")


def lm_iteration_split(model, rs, fs, repeats: int = 3) -> None:
    """Time the pieces of one LM iteration of the PGNN step (median of ``repeats``)."""
    d = prepare_data(model, rs, fs)
    den, seg = model.denominator(), d["segments"]
    parts = {"jacobian of g": [], "filter by 1/B": [], "projection": [], "JᵀJ": []}
    U1 = np.linalg.qr(filter_segments(d["M"], [1.0], den, seg))[0]
    for _ in range(repeats):
        t = time.process_time()
        _, Jg = model.g_and_jacobian(d["inputs"])
        parts["jacobian of g"].append(time.process_time() - t)
        t = time.process_time()
        WJ = filter_segments(Jg.numpy(), [1.0], den, seg)
        parts["filter by 1/B"].append(time.process_time() - t)
        t = time.process_time()
        J = U1 @ (U1.T @ WJ) - WJ
        parts["projection"].append(time.process_time() - t)
        t = time.process_time()
        Jt = torch.from_numpy(J)
        _ = Jt.T @ Jt
        parts["JᵀJ"].append(time.process_time() - t)
    print(f"  one LM iteration, CPU s ({J.shape[0]} residuals × {J.shape[1]} parameters): "
          + ", ".join(f"{k} {np.median(v):.3f}" for k, v in parts.items()))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sk-iter", type=int, default=3, help="SK iterations per model")
    ap.add_argument("--lm-iter", type=int, default=20, help="LM iterations per PGNN SK iteration")
    a = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", SKNotConvergedWarning)

    plant, rs, fs = training_data()
    print(f"data: {len(rs)} references, {sum(r.size for r in rs)} samples, Ts = {plant.Ts} s")

    clock = Clock()
    res = sk_iterations(RationalFeedforward(10, 9, basis="delta", Ts=plant.Ts), rs, fs,
                        max_iter=a.sk_iter, tol=0.0)
    report("rational N_a=10, N_b=9 (delta basis)", res, clock.lap())

    win = ReferenceWindow(4, "delta", plant.Ts).fit(rs)
    pgnn = SharedARPGNN(5, 2, make_approximator("mlp", 5, seed=0), win, basis="delta", Ts=plant.Ts)
    clock = Clock()
    res = sk_iterations(pgnn, rs, fs, max_iter=a.sk_iter, tol=0.0, regularizer="orthogonal",
                        lam=1.0, lm_max_iter=a.lm_iter)
    report(f"PGNN N_a=5, N_b=2, MLP 5-10-10-1, orthogonal, {a.lm_iter} LM iterations/SK iteration",
           res, clock.lap())
    n_lm = sum(it.lm_iter for it in res.iterates[1:])
    print(f"  wall per LM iteration {sum(it.seconds for it in res.iterates[1:]) / max(n_lm, 1):.3f} s")
    lm_iteration_split(res.model, rs, fs)


if __name__ == "__main__":
    main()
