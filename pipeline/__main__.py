"""Hydra entry point: ``python -m pipeline [experiment=NAME] [key=value ...] [-m]``; and
``python -m pipeline export RUN_ID [--out DIR]`` (:mod:`pipeline.export.cli`); ``python -m pipeline learn …``
(:mod:`pipeline.learn.cli`)."""
from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pipeline import interrupts, resources, runner, schema
from pipeline.runner import ConfigError, run_job, run_name_with_overrides
from pipeline.tracking import VARYING_ENV

schema.register()   # every key's default for Hydra (before it composes; a launcher's workers get the store)


# an absolute path: the `pgnn-ff` console script imports this module from outside the package folder
@hydra.main(version_base="1.3", config_path=str(Path(__file__).resolve().parent.parent / "conf"), config_name="config")
def _main(cfg: DictConfig) -> dict:
    try:
        hc = HydraConfig.get()
        cfg.run_name = run_name_with_overrides(cfg, hc.overrides.task, hc.sweeper.get("params"))
        t0 = time.perf_counter()
        run_job(cfg, varying=[k for k in os.environ.get(VARYING_ENV, "").split(",") if k])
        # the job's own time, waits for another job's identical entry left out (hydra/sweeper=queue
        # orders by it: the waiting job is short next time and runs after the one it waited for)
        return {"seconds": time.perf_counter() - t0 - runner.WAITED}
    except ConfigError as exc:  # bad input: one clear line, no traceback, exit code 2
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except Exception as exc:  # disk full, read-only or forbidden folder, tracking server down: one line
        line = resources.describe(exc, cfg)
        if line is None:      # anything else is a bug: its traceback
            raise
        print(line, file=sys.stderr)
        sys.exit(1)


def main() -> None:
    # Ctrl-C (SIGINT) and `kill` (SIGTERM) raise interrupts.Interrupted in the main thread: the stage's
    # temporary directory is removed, the run ends KILLED; a watchdog ends the process if that takes long
    interrupts.install()
    try:
        if len(sys.argv) > 1 and sys.argv[1] == "export":   # pgnn-ff export RUN_ID [--out DIR]
            from pipeline.export.cli import main as export_main  # lazy: saves 0.1 s of start-up (pipeline.export)
            sys.exit(export_main(sys.argv[2:]))
        if len(sys.argv) > 1 and sys.argv[1] == "learn":    # pgnn-ff learn … (README "Learn on the machine")
            from pipeline.learn.cli import main as learn_main  # lazy: saves 0.3 s of start-up (pipeline.learn)
            sys.exit(learn_main(sys.argv[2:]))
        _main()
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", None) or interrupts.received() or signal.SIGINT
        took = interrupts.seconds_since_signal()
        print(f"interrupted ({signal.Signals(signum).name}"
              + (f", stopped in {took:.1f} s" if took is not None else "")
              + "): an unfinished run is marked KILLED and its temporary files removed; rerun the same "
              "command to resume from the cache", file=sys.stderr, flush=True)
        interrupts.exit_now(128 + signum)


if __name__ == "__main__":
    main()
