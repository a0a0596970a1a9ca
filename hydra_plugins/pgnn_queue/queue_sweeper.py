"""``hydra/sweeper=queue``: every job of several experiments in one launch, longest first.

``make reproduce`` runs ``python -m pipeline -m hydra/sweeper=queue hydra.sweeper.experiments=[a,b,...]
hydra/launcher=local``: each experiment's own sweep (its ``hydra.sweeper.params``, expanded exactly as
Hydra's basic sweeper expands them, a single job where it has none) becomes part of one job list,
ordered longest first by the job times of the previous run (``hydra.sweeper.timings``; jobs without
one first, in experiment order), and handed to the configured launcher in one call: a core idles only
at the very end of the whole reproduction, not at the end of every experiment, and the Python and
MLflow start-up is paid once per launcher worker instead of once per experiment.  The launcher
(joblib locally, submitit on SLURM) does the running; this only decides the order.

Each experiment that is a sweep gets its MLflow parent run as before (the ``mlflow_parent`` callback
is told of it through ``on_multirun_start`` with that experiment's config).  The job times are written
back to ``hydra.sweeper.timings`` (experiment, job, wall_seconds, git_sha; atomically).
"""

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, RunMode, TaskFunction
from omegaconf import DictConfig, OmegaConf


@dataclass
class QueueSweeperConf:
    _target_: str = "hydra_plugins.pgnn_queue.queue_sweeper.QueueSweeper"
    experiments: List[str] = field(default_factory=list)   # conf/experiment/<name>.yaml, in report order
    timings: Optional[str] = None     # csv of the previous run's job times (read for the order, rewritten)
    params: Optional[Dict[str, str]] = None   # an experiment's own sweep lands here when it is composed
    dry_run: bool = False             # print the ordered jobs (with their estimated seconds), run nothing


ConfigStore.instance().store(group="hydra/sweeper", name="queue", node=QueueSweeperConf, provider="pgnn")


class QueueSweeper(Sweeper):
    def __init__(self, experiments: List[str], timings: Optional[str] = None,
                 params: Optional[Dict[str, str]] = None, dry_run: bool = False) -> None:
        super().__init__()
        self.experiments = list(experiments)
        self.timings = timings
        self.dry_run = dry_run
        self.hydra_context: Optional[HydraContext] = None
        self.config: Optional[DictConfig] = None
        self.launcher = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        from hydra.core.plugins import Plugins
        self.hydra_context, self.config = hydra_context, config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config)

    def _experiment_config(self, name: str, arguments: List[str]) -> DictConfig:
        """The experiment's own composition (its hydra.sweeper.params)."""
        assert self.config is not None and self.hydra_context is not None
        return self.hydra_context.config_loader.load_configuration(
            config_name=self.config.hydra.job.config_name,
            overrides=list(self.config.hydra.overrides.hydra) + [f"experiment={name}"] + list(arguments),
            run_mode=RunMode.MULTIRUN)

    def sweep(self, arguments: List[str]) -> Any:
        from pathlib import Path

        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser

        from pipeline import job_queue
        if not self.experiments:
            from hydra.errors import ConfigCompositionException   # Hydra prints its message, one line
            raise ConfigCompositionException("hydra/sweeper=queue needs hydra.sweeper.experiments=[name,...] "
                             "(conf/experiment/<name>.yaml)")
        assert self.hydra_context is not None and self.launcher is not None and self.config is not None
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        jobs, composed = [], []
        for name in self.experiments:
            cfg = self._experiment_config(name, arguments)
            params = OmegaConf.to_container(cfg.hydra.sweeper.params, resolve=False) \
                if cfg.hydra.sweeper.get("params") else {}
            # as Hydra's basic sweeper does: the sweep's params first, then the command line
            spec = [f"{k}={v}" for k, v in params.items()] + [f"experiment={name}"] + list(arguments)
            (batch,) = BasicSweeper.split_arguments(parser.parse_overrides(spec), None)
            jobs += [job_queue.Job(name, tuple(ov)) for ov in batch]
            composed.append((name, cfg, params))
        if not self.dry_run:   # every data file every job reads, before any job or MLflow run (issue 51)
            from hydra.errors import ConfigCompositionException   # Hydra prints its message, one line

            from pipeline import preflight
            from pipeline.errors import ConfigError
            try:
                preflight.check([(name, cfg) for name, cfg, _ in composed])
            except ConfigError as exc:
                raise ConfigCompositionException(f"pre-flight: {exc}") from None
        for name, cfg, params in composed:
            if params and not self.dry_run:              # a sweep: its MLflow parent run, as before
                self.hydra_context.callbacks.on_multirun_start(config=cfg)
        previous = job_queue.read_timings(Path(self.timings)) if self.timings else None
        ordered = job_queue.longest_first(jobs, previous)
        est = job_queue.estimates(ordered, previous)
        print(job_queue.plan_line(ordered, est, int(self.config.hydra.launcher.get("n_jobs") or 1)), flush=True)
        if self.dry_run:
            for job, sec in zip(ordered, est):
                print(f"{'?' if sec is None else f'{sec:.1f}'}\t{job.experiment}\t{job.key}", flush=True)
            return []
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        batch = [list(j.overrides) for j in ordered]
        self.validate_batch_is_legal(batch)
        results = self.launcher.launch(batch, initial_job_idx=0)
        for r in results:
            _ = r.return_value             # a failed job raises here, as with the basic sweeper
        if self.timings:
            seconds = [r.return_value.get("seconds") if isinstance(r.return_value, dict) else None
                       for r in results]
            job_queue.write_timings(Path(self.timings), ordered, seconds, previous)
        return [results]
