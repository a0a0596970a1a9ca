"""Issue 14: every README command marked ``# quick`` runs as written on a fresh store."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def quick_commands() -> list[str]:
    """The indented README commands with a ``# quick`` comment (the comment removed)."""
    out = []
    for line in (ROOT / "README.md").read_text().splitlines():
        m = re.match(r"^    (\.venv/bin/python .*?)\s+# quick\b", line)
        if m:
            out.append(m.group(1))
    return out


def test_the_readme_marks_its_tour_commands_quick():
    cmds = quick_commands()
    assert len(cmds) >= 3 and all(c.startswith(".venv/bin/python -m pipeline") for c in cmds)


@pytest.mark.slow
def test_readme_quick_commands_run_as_written_on_a_fresh_store(tmp_path):
    env = dict(os.environ, PIPELINE_CACHE=str(tmp_path / "cache"), PIPELINE_CACHE_KEY_FILE=str(tmp_path / "key"),
               MLFLOW_TRACKING_URI=f"sqlite:///{tmp_path / 'mlflow.db'}")
    total = 0.0
    for cmd in quick_commands():
        argv = shlex.split(cmd)
        argv[0] = sys.executable     # .venv/bin/python of this checkout
        t0 = time.perf_counter()
        out = subprocess.run(argv + [f"hydra.run.dir={tmp_path}/h", f"hydra.sweep.dir={tmp_path}/m"], cwd=ROOT,
                             env=env, capture_output=True, text=True, timeout=900)
        total += time.perf_counter() - t0
        assert out.returncode == 0, f"{cmd}\n{out.stderr[-3000:]}"
    assert total < 300, f"the quick tour took {total:.0f} s"   # the 'five-minute tour'
