"""Wall time of each stage for each plant's physics experiment (fresh cache, one process each).

Run: `make bench` (or `.venv/bin/python benchmarks/bench_stages.py`). Prints a table; asserts nothing.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ["physics_arx", "physics_linear_motor", "physics_rot_trans", "physics_two_mass",
               "ilc_rot_trans"]


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PIPELINE_CACHE": f"{tmp}/cache", "OMP_NUM_THREADS": "1",
               "MLFLOW_TRACKING_URI": f"sqlite:///{tmp}/mlflow.db"}
        print(f"{'experiment':24s} {'stage':10s} {'seconds':>9s}")
        for exp in EXPERIMENTS:
            out = subprocess.run([sys.executable, "-m", "pipeline", f"experiment={exp}"], cwd=ROOT,
                                 env=env, capture_output=True, text=True)
            if out.returncode:
                print(f"{exp}: failed\n{out.stderr[-2000:]}")
                continue
            for stage_dir in sorted(Path(tmp, "cache").iterdir()):
                for rec in stage_dir.glob("*/record.json"):
                    if rec.stat().st_mtime_ns and not rec.with_name(".seen").exists():
                        sec = json.loads(rec.read_text())["seconds"]
                        print(f"{exp:24s} {stage_dir.name:10s} {sec:9.3f}")
                        rec.with_name(".seen").touch()
                        extra = [m for m in json.loads(rec.read_text())["metrics"]
                                 if m[0].endswith("/rms") and m[0].startswith("generate/ilc")]
                        if extra:
                            print(f"{'':24s} {'ILC':10s} {sec / len(extra):9.3f} s per trial "
                                  f"(incl. update), {len(extra)} trials")


if __name__ == "__main__":
    main()
