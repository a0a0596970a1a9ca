"""Hydra entry point: ``python -m pipeline [experiment=NAME] [key=value ...] [-m]``; and
``python -m pipeline export RUN_ID [--out DIR]`` (:mod:`pipeline.export.cli`)."""
from __future__ import annotations

import signal
import sys

import hydra
from omegaconf import DictConfig

from pipeline.runner import ConfigError, run_job, run_name_with_overrides


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def _main(cfg: DictConfig) -> None:
    try:
        from hydra.core.hydra_config import HydraConfig
        hc = HydraConfig.get()
        cfg.run_name = run_name_with_overrides(cfg, hc.overrides.task, hc.sweeper.get("params"))
        run_job(cfg)
    except ConfigError as exc:  # bad input: one clear line, no traceback, exit code 2
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


def _terminate(signum, frame) -> None:  # `kill`: unwind like Ctrl-C (runs end FAILED, temps removed)
    raise SystemExit(128 + signum)


def main() -> None:
    signal.signal(signal.SIGTERM, _terminate)
    if len(sys.argv) > 1 and sys.argv[1] == "export":   # pgnn-ff export RUN_ID [--out DIR]
        from pipeline.export.cli import main as export_main
        sys.exit(export_main(sys.argv[2:]))
    _main()


if __name__ == "__main__":
    main()
