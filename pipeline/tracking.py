"""MLflow glue: the one module that knows about MLflow (DESIGN, Tracking).

- Store: ``MLFLOW_TRACKING_URI`` if set, else ``sqlite:///<repo>/mlruns/mlflow.db`` with
  artifacts under ``<repo>/mlruns/artifacts`` (absolute paths, so every working directory
  shares one store).
- One Hydra job = one run; a multirun gets a parent run (:class:`MultirunCallback`) whose id
  reaches the jobs through the environment variable ``PIPELINE_PARENT_RUN_ID``, whichever Hydra
  launcher runs them (basic, joblib, submitit).
"""
from __future__ import annotations

import atexit
import errno
import os
import re
import shutil
import subprocess
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Mapping
from urllib.parse import unquote, urlparse

import mlflow
import mlflow.data
import mlflow.models
import pandas as pd
from filelock import FileLock
from hydra.core.utils import JobStatus
from mlflow.entities import DatasetInput, InputTag, Metric, Param, RunTag
from mlflow.tracking import MlflowClient

import pipeline
from pipeline import compare, interrupts
from pipeline.cache import HOST, cache_dir, pid_alive, remove_stale_temporaries
from pipeline.errors import ConfigError
from pipeline.naming import varying_keys

ROOT = Path(__file__).resolve().parent.parent
PARENT_ENV = "PIPELINE_PARENT_RUN_ID"
#: the keys a job's sweep varies (comma-separated; they lead its run name, pipeline/naming.py)
VARYING_ENV = "PIPELINE_SWEEP_VARYING"
#: MLflow 3 opens experiments on the GenAI page unless they carry this tag (DESIGN).
EXPERIMENT_KIND = {"mlflow.experimentKind": "custom_model_development"}
#: a job run by SLURM (hydra/launcher=slurm) names its SLURM job in these run tags
SLURM_TAGS = {"SLURM_JOB_ID": "slurm.job_id", "SLURM_ARRAY_JOB_ID": "slurm.array_job_id",
              "SLURM_ARRAY_TASK_ID": "slurm.array_task_id"}


#: tracking-store URI schemes MLflow opens (a bare path is a file store)
#: rows a numeric dataset's MLflow schema is inferred from (its dtypes decide it; see ``log_dataset``)
SCHEMA_ROWS = 100
STORE_SCHEMES = ("sqlite", "http", "https", "file", "postgresql", "mysql", "mssql", "databricks")


def default_uri() -> str:
    return f"sqlite:///{ROOT / 'mlruns' / 'mlflow.db'}"


def tracking_uri() -> str:
    """The tracking URI of this process: ``MLFLOW_TRACKING_URI`` or the embedded SQLite store."""
    uri = os.environ.get("MLFLOW_TRACKING_URI") or default_uri()
    scheme = urlparse(uri).scheme.split("+")[0]
    if "://" in uri and scheme not in STORE_SCHEMES:
        raise ConfigError(f"MLFLOW_TRACKING_URI={uri}: MLflow has no store of scheme {scheme!r}; use "
                          "sqlite:///<path>/mlflow.db (one machine), http(s)://<host>:<port> (a server) or "
                          "postgresql+psycopg://… (README, Parallel sweeps)")
    if uri.startswith("sqlite:///"):
        db = Path(uri[len("sqlite:///"):])
        db.parent.mkdir(parents=True, exist_ok=True)
        if db.exists() and not db.is_file():   # MLflow would retry opening it for 2 minutes, logging each try
            raise IsADirectoryError(errno.EISDIR, "the database path is a folder, not a file", str(db))
    return uri


#: SQLite stores this process has opened (created and migrated under a file lock)
_OPENED: set[str] = set()


def client() -> MlflowClient:
    uri = tracking_uri()
    mlflow.set_tracking_uri(uri)
    if not uri.startswith("sqlite:///") or uri in _OPENED:
        return MlflowClient(uri)
    # MLflow creates and migrates a new SQLite store when a client first opens it; two processes doing
    # that at once (the first jobs of a parallel sweep on a fresh store) break it ("duplicate column
    # name", "_alembic_tmp_* already exists"). The first open of each process runs under a lock beside
    # the database: one creates it, the others find it made.
    with FileLock(uri[len("sqlite:///"):] + ".open.lock"):
        c = MlflowClient(uri)
        c.search_experiments(max_results=1)
    _OPENED.add(uri)
    return c


#: MLflow's description of an experiment or run (the UI's "Description" / note)
NOTE = "mlflow.note.content"
#: MLflow 3.x's UI opens on a global workflow type kept in the browser (default GenAI) and ignores the
#: experiment's kind tag; this query of an experiment's runs page switches it to "Model training", and
#: sorting by run name lists a sweep's children flat (MLflow nests them under the parent only when sorted
#: by start time), grouped by what their names lead with (README, Browse and compare)
ML_VIEW = "workflowType=machine_learning&orderByKey=attributes.run_name&orderByAsc=true"


def experiment_id(name: str, description: str = "") -> str:
    """Get or create the experiment ``name`` (artifacts beside the SQLite store); ``description``
    (what the experiment compares, where to look) becomes its MLflow note when given."""
    c = client()
    exp = c.get_experiment_by_name(name)
    if exp is not None:
        if description and exp.tags.get(NOTE) != description:
            c.set_experiment_tag(exp.experiment_id, NOTE, description)
        for k, v in EXPERIMENT_KIND.items():
            if exp.tags.get(k) != v:   # an experiment made before the tag (e.g. by MLflow itself)
                c.set_experiment_tag(exp.experiment_id, k, v)
        return exp.experiment_id
    location = None
    uri = tracking_uri()
    if uri.startswith("sqlite:///"):  # artifacts beside the database, whatever the working directory
        root = (Path(uri[len("sqlite:///"):]).parent / "artifacts").resolve()
        folder = (root / name).resolve()
        if folder.parent != root:     # a name that is a path would write outside the store
            raise ValueError(f"experiment name {name!r} would put artifacts outside {root}; "
                             "use letters, digits, '.', '_' and '-'")
        location = folder.as_uri()
    tags = {**EXPERIMENT_KIND, **({NOTE: description} if description else {})}
    try:
        return c.create_experiment(name, artifact_location=location, tags=tags)
    except mlflow.exceptions.MlflowException:  # created meanwhile by another process
        return c.get_experiment_by_name(name).experiment_id


def git_sha() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                             text=True, timeout=10)
        sha = out.stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return (sha or "unknown") + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = str(v)[:6000]
    return out


class JobRun:
    """One MLflow run for one pipeline job; batches what the stages record."""

    def __init__(self, experiment: str, run_name: str, tags: Mapping[str, str],
                 params: Mapping[str, Any], description: str = ""):
        self.client = client()
        exp_id = experiment_id(experiment, description)
        mark_dead_runs_killed(exp_id)
        all_tags = {"git_sha": git_sha(), "host": _host(), "pid": str(os.getpid()), "isa": pipeline.isa_setting(),
                    **slurm_tags(), **{k: str(v) for k, v in tags.items()}}
        parent = os.environ.get(PARENT_ENV)
        all_tags["sweep"] = "child" if parent else "single"
        if parent:
            all_tags["mlflow.parentRunId"] = parent
        run = self.client.create_run(exp_id, run_name=run_name, tags=all_tags)
        self.run_id = run.info.run_id
        # if Ctrl-C cannot unwind the job in time, the interrupt watchdog ends the run KILLED
        interrupts.on_abort(("run", self.run_id), lambda: self.client.set_terminated(self.run_id, "KILLED"))
        self._log_params(params)

    @classmethod
    def resume(cls, run_id: str) -> "JobRun":
        """An existing run to log more into (``pgnn-ff export RUN_ID``); its status is left alone."""
        self = cls.__new__(cls)
        self.client = client()
        self.run_id = run_id
        return self

    def _log_params(self, params: Mapping[str, Any]) -> None:
        flat = _flatten(params)
        items = [Param(k[:250], v) for k, v in sorted(flat.items())]
        for i in range(0, len(items), 100):
            self.client.log_batch(self.run_id, params=items[i:i + 100])

    def log_metrics(self, metrics: list[tuple[str, float, int | None]]) -> None:
        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, int(s or 0)) for k, v, s in metrics]
        for i in range(0, len(items), 500):
            self.client.log_batch(self.run_id, metrics=items[i:i + 500])

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        items = [RunTag(k, str(v)) for k, v in tags.items()]
        if items:
            self.client.log_batch(self.run_id, tags=items)

    def log_artifact(self, path: Path, subdir: str | None = None) -> None:
        try:   # MLflow's local store writes a hidden temporary file and renames it: never half-written
            self.client.log_artifact(self.run_id, str(path), subdir)
        except OSError as exc:
            if not exc.filename and not exc.filename2:   # a write into an open file: name the folder
                exc.filename = self._artifact_dir(subdir)
            raise

    def _artifact_dir(self, subdir: str | None) -> str:
        uri = self.client.get_run(self.run_id).info.artifact_uri
        folder = unquote(urlparse(uri).path) if uri.startswith("file:") else uri
        return f"{folder}/{subdir}" if subdir else folder

    def log_dataset(self, df, name: str, source: str, context: str = "training") -> None:
        """Log a pandas dataset as an MLflow dataset input (DESIGN: ``log_input``)."""
        with warnings.catch_warnings():  # schema hints about int columns, ambiguous local sources
            warnings.simplefilter("ignore", UserWarning)
            ds = mlflow.data.from_pandas(df, source=source, name=name)
            if all(pd.api.types.is_numeric_dtype(t) for t in df.dtypes) and not df.isna().to_numpy().any():
                # a numeric frame without NaN: its schema is its dtypes, every column required. Inferred on
                # the first rows, not value by value (1.08 M values of a [B1] record: 1.1-1.5 s per job)
                ds.schema = mlflow.models.infer_signature(df.head(SCHEMA_ROWS)).inputs
            inp = DatasetInput(ds._to_mlflow_entity(),
                               tags=[InputTag("mlflow.data.context", context)])
        for attempt in range(5):
            try:
                self.client.log_inputs(self.run_id, datasets=[inp])
                return
            except mlflow.exceptions.MlflowException as exc:
                # two parallel jobs logging one dataset race on MLflow's get-or-create (SQL UNIQUE
                # constraint: SQLite's "UNIQUE constraint failed", PostgreSQL's "duplicate key value
                # violates unique constraint"); the retry finds the row the other job created
                if "unique constraint" not in str(exc).lower() and "IntegrityError" not in str(exc) or attempt == 4:
                    raise
                time.sleep(0.2 * (attempt + 1))

    def model_name(self, package: str) -> str:
        """The logged model's name: the package and the run's key (``ff_newton-linear_motor-equation-newton-s0``),
        so the experiment's models tab tells the runs' models apart (issue 23)."""
        tags = self.client.get_run(self.run_id).data.tags
        key = re.sub(r"[^A-Za-z0-9_-]+", "_",   # MLflow refuses / : . % " ' in a model name
                      tags.get("run_key") or tags.get("mlflow.runName") or "").strip("_")
        return f"{package}-{key}"[:200] if key else package

    def log_feedforward_model(self, name: str, law_dir: Path, example_csv: Path,
                              register_as: str | None = None) -> str:
        """Log an exported feedforward (``pipeline.export``) as an MLflow pyfunc model of this run
        named :meth:`model_name` (``runs:/<run id>/<that name>``), with signature and input example;
        register it as ``register_as`` with the run's evaluation metrics as tags.  Returns the model URI."""
        import mlflow.pyfunc  # lazy: saves 0.2 s of start-up (mlflow.pyfunc: only a job that exports logs a model)

        from pipeline.export.law import Law  # lazy: saves 0.1 s of start-up (pipeline.export, export jobs only)
        from pipeline.export.package import (  # lazy: saves 0.1 s of start-up (pipeline.export, export jobs only)
            read_column,
        )
        from pipeline.export.pyfunc import (  # lazy: saves 0.1 s of start-up (pipeline.export, export jobs only)
            signature,
        )
        law = Law.load(law_dir)
        r = read_column(example_csv)
        sig, example = signature(law, r if law.family == "table" else r[:200])
        status = self.client.get_run(self.run_id).info.status
        name = self.model_name(name)
        with warnings.catch_warnings():   # MLflow's notes on environment capture and example conversion
            warnings.simplefilter("ignore")
            with mlflow.start_run(run_id=self.run_id):
                mlflow.pyfunc.log_model(name=name, loader_module="pipeline.export.pyfunc",
                                        data_path=str(law_dir), signature=sig, input_example=example,
                                        pip_requirements=["pgnn-feedforward", "numpy", "pandas", "scipy",
                                                          "numba", "torch"])
        # leaving start_run() marked the run FINISHED: back to what it was (RUNNING for a job)
        self.client.update_run(self.run_id, status=status)
        uri = f"runs:/{self.run_id}/{name}"
        if register_as:
            metrics = self.client.get_run(self.run_id).data.metrics
            version = mlflow.register_model(uri, register_as)
            for k, v in sorted(metrics.items()):
                if k.startswith("evaluate/") and k.rsplit("/", 1)[-1] in ("mae", "max_abs", "norm2", "rms"):
                    self.client.set_model_version_tag(register_as, version.version, k, f"{v:.6g}")
            self.client.set_model_version_tag(register_as, version.version, "run_id", self.run_id)
        return uri

    def end(self, status: str = "FINISHED") -> None:
        self.client.set_terminated(self.run_id, status)
        interrupts.discard(("run", self.run_id))


def slurm_tags() -> dict[str, str]:
    """The SLURM job this process runs in (``sacct -j``, ``scontrol show job``), empty outside SLURM."""
    return {tag: os.environ[var] for var, tag in SLURM_TAGS.items() if os.environ.get(var)}


def _host() -> str:
    return HOST


def mark_dead_runs_killed(exp_id: str) -> list[str]:
    """Runs of the experiment left RUNNING by a process of this machine that no longer exists
    (SIGKILL, OOM) are marked KILLED; returns their ids."""
    c = client()
    runs = c.search_runs([exp_id], filter_string=f"attributes.status = 'RUNNING' and tags.host = '{_host()}'",
                         max_results=1000)
    dead = [r.info.run_id for r in runs
            if r.data.tags.get("pid", "").isdigit() and not pid_alive(int(r.data.tags["pid"]))]
    for run_id in dead:
        c.set_terminated(run_id, "KILLED")
    return dead


def experiment_links(base_url: str = "http://127.0.0.1:5000") -> list[str]:
    """One line per experiment of the store with runs: its name, run count and the UI page that
    opens on its runs table (``make ui`` prints them before starting the server)."""
    c = client()
    lines = []
    for exp in c.search_experiments(order_by=["name ASC"]):
        n = len(c.search_runs([exp.experiment_id], max_results=1000))
        if n:
            lines.append(f"  {exp.name:<24} {n:>4} runs  {base_url}/#/experiments/{exp.experiment_id}/runs?{ML_VIEW}")
    return lines


#: the alias of each experiment's chosen feedforward in the Model Registry (issue 23)
CHAMPION = "champion"


def logged_models(experiment: str) -> dict[str, list]:
    """{run id: its logged models (MLflow 3 ``LoggedModel``)} of ``experiment``."""
    c = client()
    exp = c.get_experiment_by_name(experiment)
    out: dict[str, list] = {}
    if exp is None:
        return out
    token = None
    while True:
        page = c.search_logged_models(experiment_ids=[exp.experiment_id], page_token=token, max_results=100)
        for m in page:
            if m.source_run_id:
                out.setdefault(m.source_run_id, []).append(m)
        token = page.token
        if not token:
            return out


def register_champion(experiment: str, run_id: str, model, rule: str, tags: Mapping[str, Any],
                      description: str = "") -> tuple[str, str]:
    """Register ``model`` (a logged model of run ``run_id``) as a version of ``<experiment>-feedforward``
    with alias ``champion``, ``rule`` (how it was chosen) as the version's description and ``tags`` (the
    run's metrics, its names) as version tags; a champion that is already this model is kept (no new
    version; its description is brought up to date). Returns (registered name, version)."""
    c = client()
    name = f"{experiment}-feedforward"
    try:
        c.get_registered_model(name)
    except mlflow.exceptions.MlflowException:
        try:
            c.create_registered_model(name, description=description or None)
        except mlflow.exceptions.MlflowException:   # created meanwhile
            pass
    try:
        current = c.get_model_version_by_alias(name, CHAMPION)
    except mlflow.exceptions.MlflowException:
        current = None
    if current is not None and current.run_id == run_id and current.source == f"models:/{model.model_id}":
        version = current.version
        c.update_model_version(name, version, description=rule)
    else:
        version = c.create_model_version(name, source=f"models:/{model.model_id}", run_id=run_id,
                                         model_id=model.model_id,
                                         description=rule).version
        c.set_registered_model_alias(name, CHAMPION, version)
    for k, v in tags.items():
        c.set_model_version_tag(name, version, k, str(v))
    if description:
        c.update_registered_model(name, description=description)
    return name, str(version)


def search_runs(experiment: str):
    """All finished runs of ``experiment`` as a pandas DataFrame (empty if none)."""
    c = client()
    exp = c.get_experiment_by_name(experiment)
    if exp is None:
        return pd.DataFrame()
    return mlflow.search_runs([exp.experiment_id], filter_string="attributes.status = 'FINISHED'",
                              order_by=["attributes.start_time DESC"])


def children(run_id: str):
    """The finished child runs of the sweep parent ``run_id`` (MLflow's ``search_runs`` frame)."""
    exp = client().get_run(run_id).info.experiment_id
    return mlflow.search_runs([exp], filter_string=f"tags.mlflow.parentRunId = '{run_id}' and "
                                                   "attributes.status = 'FINISHED'", max_results=10000)


def log_comparison(run_id: str, patterns: list[str], title: str = ""):
    """Log on the sweep parent ``run_id`` its children compared (:mod:`pipeline.compare`): artifacts
    ``compare/comparison.csv``, ``.md`` and ``.png``; returns (table, findings), None if no children."""
    kids = children(run_id)
    if kids.empty:
        return None
    table, findings = compare.comparison(kids, patterns)
    folder = Path(tempfile.mkdtemp(prefix="pgnn-compare-"))
    try:
        table.to_csv(folder / "comparison.csv", index=False)
        (folder / "comparison.md").write_text(compare.markdown(table, findings))
        compare.figure(table, folder / "comparison.png", title)
        c = client()
        curves = best_loss_curves(kids)
        if curves:
            compare.loss_overlay(curves, folder / "loss_overlay.png", title)
        for f in sorted(folder.iterdir()):
            c.log_artifact(run_id, str(f), "compare")   # MLflow writes each through a temporary file
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    if findings:
        note = c.get_run(run_id).data.tags.get(NOTE, "")
        c.set_tag(run_id, NOTE, note + "\n\nFindings:\n\n" + "\n".join(f"- {x}" for x in findings))
    return table, findings


def best_loss_curves(runs) -> dict[str, list[float]]:
    """{run display name: the loss curve of its best restart} (the restart with the lowest final loss of its
    ``train/loss/restart<i>`` histories) for the runs of MLflow's ``search_runs`` frame that trained."""
    c = client()
    out = {}
    for _, r in runs.iterrows():
        keys = [k[len("metrics."):] for k in r.index if k.startswith("metrics.train/loss/restart")
                and pd.notna(r[k])]
        hist = [[m.value for m in sorted(c.get_metric_history(r["run_id"], k), key=lambda m: m.step)] for k in keys]
        hist = [h for h in hist if h]
        if hist:
            out[str(r.get("tags.mlflow.runName", r["run_id"]))] = min(hist, key=lambda h: h[-1])
    return out


try:  # the Hydra callback lives here so that tracking stays in one module
    from hydra.experimental.callback import Callback
    from omegaconf import OmegaConf

    def _sweep_key(config) -> str:
        """The sweep a job belongs to: its experiment file (several files share an MLflow experiment:
        b2_rot_trans, b2_rot_trans_il and b2_rot_trans_linear all log to b2_rot_trans), else its name."""
        return str(OmegaConf.select(config, "hydra.runtime.choices.experiment", default=None)
                   or OmegaConf.select(config, "experiment_name", default=""))

    class MultirunCallback(Callback):
        """Parent MLflow run around a Hydra multirun; jobs attach to it (DESIGN).

        Works with every launcher: the parent's id is set in the environment of the process that
        runs each job (``on_job_start`` runs there: in-process for the basic launcher, in the worker
        for joblib, on the node for submitit, which receive this callback pickled with it).  The
        parent ends FINISHED when every child finished, FAILED otherwise; if the sweep dies an
        ``atexit`` hook marks it FAILED (an exception) or KILLED (Ctrl-C, SIGTERM: with the children
        still RUNNING, whose workers the launcher killed) instead of leaving it RUNNING.

        One parent per experiment file: ``make reproduce``'s one queue of every experiment's jobs
        (``hydra/sweeper=queue``) announces each sweep with ``on_multirun_start`` and its config, and
        a job attaches to the parent of its own experiment file's sweep (:func:`_sweep_key`)."""

        def __init__(self) -> None:
            self.failed = 0
            self.parents: dict[str, str] = {}     # sweep (experiment file) -> parent run id
            self.meta: dict[str, dict] = {}       # parent run id -> description, comparison metrics
            self.varying: dict[str, str] = {}     # sweep -> the keys it varies (VARYING_ENV)
            self.cache = ""

        def _describe(self, config) -> dict:
            """What the parent's comparison needs from its sweep's config."""
            return {"description": str(OmegaConf.select(config, "description", default="") or ""),
                    "patterns": list(OmegaConf.select(config, "compare_metrics", default=None) or ["evaluate/*/mae"]),
                    "experiment": str(config.experiment_name)}

        def on_multirun_start(self, config, **kwargs) -> None:
            self.cache = str(cache_dir(config))
            choice = OmegaConf.select(config, "hydra.runtime.choices.experiment", default=None)
            if OmegaConf.select(config, "hydra.sweeper.experiments", default=None) and choice is None:
                return                        # the queue itself: it announces each experiment's sweep
            c = client()
            name = str(config.experiment_name)
            meta = self._describe(config)
            note = (f"**Sweep `{choice or name}`**: its jobs are this run's children. Comparison of the children "
                    "by the factors they vary: artifacts `compare/comparison.png`, `.md`, `.csv` (written when "
                    "the sweep ends).\n\n" + meta["description"])
            run = c.create_run(experiment_id(name, meta["description"]), run_name=f"{choice or name}-sweep",
                               tags={"git_sha": git_sha(), "experiment": name, "sweep": "parent",
                                     NOTE: note})   # one name per sweep file
            if not self.parents:
                atexit.register(self._close, "FAILED")
            self.meta[run.info.run_id] = meta
            self.varying[_sweep_key(config)] = ",".join(varying_keys(
                OmegaConf.select(config, "hydra.sweeper.params", default=None),
                OmegaConf.select(config, "hydra.overrides.task", default=None) or ()))
            self.parents[_sweep_key(config)] = run.info.run_id
            os.environ[PARENT_ENV] = run.info.run_id
            interrupts.on_abort(("run", run.info.run_id), lambda: self._close("KILLED"))

        @property
        def parent_run_id(self) -> str | None:
            """The parent of a one-experiment sweep (None before it starts or after it ends)."""
            return next(iter(self.parents.values()), None)

        def on_job_start(self, config, **kwargs) -> None:
            queue = bool(OmegaConf.select(config, "hydra.sweeper.experiments", default=None))
            # one sweep: every job is its child (even one whose experiment_name the sweep varies);
            # the queue: each job the child of its own experiment file's sweep, if that is one
            parent = self.parents.get(_sweep_key(config)) or \
                (self.parent_run_id if len(self.parents) == 1 and not queue else None)
            if parent:                        # a worker process of a parallel launcher
                os.environ[PARENT_ENV] = parent
            else:                             # a single-job experiment of the queue: no parent
                os.environ.pop(PARENT_ENV, None)
            varying = self.varying.get(_sweep_key(config)) or \
                (next(iter(self.varying.values()), "") if len(self.varying) == 1 and not queue else "")
            os.environ[VARYING_ENV] = varying

        def on_job_end(self, config, job_return, **kwargs) -> None:
            if job_return is not None and job_return.status != JobStatus.COMPLETED:
                self.failed += 1

        def on_multirun_end(self, config, **kwargs) -> None:
            for name, run_id in list(self.parents.items()):
                self._close_one(name, "FAILED" if self.failed or self._unfinished_children(run_id) else "FINISHED")
            os.environ.pop(PARENT_ENV, None)
            os.environ.pop(VARYING_ENV, None)

        def _unfinished_children(self, run_id: str) -> int:
            """Children not FINISHED (parallel launchers report job ends in their workers)."""
            runs = client().search_runs(
                [client().get_run(run_id).info.experiment_id],
                filter_string=f"tags.mlflow.parentRunId = '{run_id}'", max_results=10000)
            return sum(r.info.status != "FINISHED" for r in runs)

        def _close(self, status: str) -> None:
            for name in list(self.parents):
                self._close_one(name, status)
            os.environ.pop(PARENT_ENV, None)

        def _close_one(self, name: str, status: str) -> None:
            run_id = self.parents.pop(name, None)
            if not run_id:
                return
            interrupts.discard(("run", run_id))
            c = client()
            meta = self.meta.get(run_id)
            if meta and interrupts.received() is None:
                try:   # the children side by side; a failure here must not hide the sweep's own status
                    log_comparison(run_id, meta["patterns"], meta["experiment"] if name == meta["experiment"]
                                   else f"{meta['experiment']}: {name}")
                except Exception as exc:  # noqa: BLE001
                    print(f"warning: no comparison logged on the sweep's parent run {run_id}: {exc}", flush=True)
            if status != "FINISHED":   # a worker SIGKILLed (OOM) leaves its child RUNNING: not for long
                mark_dead_runs_killed(c.get_run(run_id).info.experiment_id)
            if status != "FINISHED" and interrupts.received() is not None:   # Ctrl-C / kill
                status = "KILLED"
                children = c.search_runs([c.get_run(run_id).info.experiment_id],
                                         filter_string=f"tags.mlflow.parentRunId = '{run_id}' and "
                                                       "attributes.status = 'RUNNING'", max_results=10000)
                for child in children:   # their workers were killed with the sweep
                    c.set_terminated(child.info.run_id, "KILLED")
                remove_stale_temporaries(Path(self.cache))   # and the stage they were computing
            c.set_terminated(run_id, status)
except ImportError:  # pragma: no cover
    pass
