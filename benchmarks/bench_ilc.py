"""Time per norm-optimal ILC trial, lifted vs matrix-free back-end (SPEC §4, §2.1, §2.3).

Plain script, no asserts: ``OMP_NUM_THREADS=1 python benchmarks/bench_ilc.py [--trials 10]``.
For each case it prints the one-off set-up (lifting + SVD, or building the filters and the
preconditioner), the median time of one update step and of one run of the true system, and
the rms error reached.  The lifted back-end is skipped above ``--max-lifted`` samples (a dense
N×N matrix costs 8 N² bytes and its SVD O(N³)).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.invert.ilc import make_update, norm_optimal_ilc, system_trial  # noqa: E402
from pipeline.references import b2_reference, out_and_back  # noqa: E402
from pipeline.systems.rot_trans_nmp import RotTransNMP  # noqa: E402
from pipeline.systems.two_mass_stribeck import TwoMassStribeck  # noqa: E402


def bench(name: str, system, model, r: np.ndarray, backend: str, trials: int, w_delta_rel: float,
          f_ref: np.ndarray | None = None) -> None:
    t0 = time.perf_counter()
    update = make_update(model, r.size, backend=backend)
    update.w_delta = w_delta_rel * update.sigma_max ** 2 if w_delta_rel else 0.0
    setup = time.perf_counter() - t0
    run = system_trial(system, r)
    step_times, run_times = [], []

    def timed_run(f):
        t = time.perf_counter()
        e = run(f)
        run_times.append(time.perf_counter() - t)
        return e

    class TimedUpdate:                          # wraps update.step to time it
        N, w, w_delta = update.N, update.w, update.w_delta

        @staticmethod
        def step(e, f):
            t = time.perf_counter()
            d = update.step(e, f)
            step_times.append(time.perf_counter() - t)
            return d

    res = norm_optimal_ilc(timed_run, None, r.size, n_trials=trials, update=TimedUpdate())
    extra = ""
    if f_ref is not None:
        extra = f"  ‖f-f̂‖/‖f̂‖ = {np.linalg.norm(res.f - f_ref) / np.linalg.norm(f_ref):.2e}"
    cg = getattr(update, "cg_iterations", None)
    if cg:
        extra += f"  CG its/trial = {int(np.median(cg))}"
    print(f"{name:<28} {backend:<12} N={r.size:<6} setup {setup:8.3f} s  "
          f"update {np.median(step_times) * 1e3:9.2f} ms  run {np.median(run_times) * 1e3:8.2f} ms  "
          f"rms[{res.n_trials - 1}] = {res.rms[-1]:.2e}{extra}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--max-lifted", type=int, default=3000)
    args = ap.parse_args()

    # warm up numba kernels (compilation is cached on disk, not counted)
    tm = TwoMassStribeck()
    tm.forward(np.zeros(10))
    make_update(tm.linear_model(), 10, backend="matrix_free").step(np.ones(10), np.zeros(10))
    RotTransNMP().simulate(np.zeros(10))

    rt = RotTransNMP(noise={"std": 0.0})
    r = b2_reference(rt.Ts).r
    for backend in ("lifted", "matrix_free"):
        bench("rot_trans_nmp R", rt, rt.process_sensitivity(), r, backend, args.trials, 1e-10)

    cases = {"two_mass (0.08, 0.25)": out_and_back(0.08, 0.25, 5.0, 200.0, tm.Ts).r,
             "two_mass (0.1, 0.1) ×3": out_and_back(0.1, 0.1, 5.0, 200.0, tm.Ts, repeats=3).r}
    for name, r in cases.items():
        f_hat = tm.exact_inverse(r)
        for backend in ("lifted", "matrix_free"):
            if backend == "lifted" and r.size > args.max_lifted:
                print(f"{name:<28} {backend:<12} N={r.size:<6} skipped: dense G would be "
                      f"{8 * r.size ** 2 / 1e6:.0f} MB, SVD O(N³)")
                continue
            bench(name, tm, tm.linear_model(), r, backend, max(args.trials, 30), 0.0, f_hat)


if __name__ == "__main__":
    main()
