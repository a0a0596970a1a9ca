"""Benchmark of one learning trial (issue 50): ``pipeline.learn.campaign.step`` on a 48 000-sample recording of
the held-out vertical axis (tests/heldout_axis.py, its 12 s test reference at 4 kHz): reading and checking the
recording, the update, the limits, writing the next u_ff and the plot (MLflow off), per update law; and the
update alone (norm_optimal: with its solve's stop and residual). Goal: ≤ 10 s on 2 cores.

Usage: ``.venv/bin/python benchmarks/bench_learn.py [--repeat 3] [--laws model_ilc norm_optimal il_fhofc]``
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import pipeline  # noqa: F401  (before numpy: its one BLAS thread per process, as the pgnn-ff CLI runs)
import numpy as np
import pandas as pd
import yaml

from pipeline.learn import campaign
from pipeline.learn.update import LAWS

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import heldout_axis as ha  # noqa: E402  (the held-out axis lives with the tests)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--laws", nargs="+", default=list(LAWS), choices=LAWS)
    a = p.parse_args()
    b_r, b_y, den, D = ha.controller()
    r = ha.eval_reference()
    rec = ha.simulate(r, np.zeros(r.size), seed=1)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        pd.DataFrame({"t": rec["t"], "r": r}).to_csv(tmp / "ref.csv", index=False, float_format="%.17g")
        pd.DataFrame({"t": rec["t"], "r": r, "u": rec["u"], "y": rec["y"], "u_ff": np.zeros(r.size)}).to_csv(
            tmp / "trial_0.csv", index=False, float_format="%.17g")
        for law in a.laws:
            cfg = {"Ts": ha.TS, "controller": {"kind": "lti", "num": b_y, "den": den, "num_r": b_r, "delay": D,
                                               "v_sat": 60.0},
                   "model": {"M": 2.67, "F_v": 10.0, "F_c": 4.0, "coulomb_width": 1e-3},
                   "learn": {"law": law, "q_cutoff_hz": 150.0}}
            (tmp / "c.yaml").write_text(yaml.safe_dump(cfg))
            steps, updates, cpu = [], [], []
            for i in range(a.repeat):
                folder = tmp / f"{law}{i}"
                c = campaign.init(folder, tmp / "c.yaml", tmp / "ref.csv", tracking=False)
                t0 = time.perf_counter()
                campaign.step(folder, tmp / "trial_0.csv")
                steps.append(time.perf_counter() - t0)
                upd, kr = c.update(), c.controller_term()
                t0, c0 = time.perf_counter(), time.process_time()
                upd.next(r - rec["y"], np.zeros(r.size), 1.0, kr)
                updates.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            solve = upd.diagnostics().get("solve")     # norm_optimal: how the exact solve stopped
            how = f"; solve {solve['stop']}, residual {solve['residual']:.2g}" if solve else ""
            print(f"{law}: one trial (step: read, check, update, write) {np.median(steps):.2f} s wall "
                  f"[{min(steps):.2f}-{max(steps):.2f}], the update alone {np.median(updates):.2f} s wall, "
                  f"{np.median(cpu):.2f} s CPU (median of {a.repeat}, N = {r.size}{how})", flush=True)


if __name__ == "__main__":
    main()
