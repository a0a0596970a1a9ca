"""Chains the stages of one job and caches their outputs by config hash (DESIGN, Stages).

A stage is a module ``stages.<name>`` with

- ``UPSTREAM``: the stages whose outputs it reads (``ctx.inputs[name]``);
- ``DEPENDS``: the dotted config keys its result depends on;
- ``VERSION``: bump it when the stage's code changes its results (``KIND_KEY`` names the config
  key choosing a ``stages/<name>/<kind>.py`` implementation, whose own ``VERSION`` counts too);
- ``run(ctx) -> dict``: the result (picklable: arrays, DataFrames, modules, numbers);
- optionally ``validate(cfg, system)``: raise before any work is done on bad input;
- optionally ``CACHE = False`` (the report reads the tracking store and always runs).

The cache key of a stage is the SHA-256 of its name, VERSION, the DEPENDS sub-configs and its
upstream keys, so changing ``invert.*`` reruns invert and evaluate but not generate or train.
A stage writes into a temporary directory that is renamed into place only when complete, so
an interrupted run leaves nothing a rerun would trust.  Concurrent jobs (a Hydra launcher running
several at once, on one machine or on a cluster sharing the cache directory) take a file lock per
key before computing: two jobs needing the same stage compute it once, the second waits and loads
it.  ``ctx.memo`` caches a part of a stage (one LM restart) on its own key, which may leave out
config keys the part does not depend on (``identify.n_restarts``): a sweep asking for the first 3
of the 10 restarts another job trained loads them.
"""
from __future__ import annotations

import hashlib
import importlib
import json
import os
import re
import shutil
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

import pipeline
from pipeline import data, interrupts, naming, owned, schema, tracking
from pipeline.atomic import replace_file
from pipeline.cache import (  # noqa: F401
    HOST,
    BadKey,
    ShortKey,
    UntrustedCache,
    _load_trusted,
    _locked,
    _signing_key,
    _tmp_name,
    _write_signed,
    cache_dir,
    cache_key_file,
    pid_alive,
    private_dir,
    remove_stale_temporaries,
)
from pipeline.compare import display_metrics
from pipeline.errors import ORDER, SAFE_NAME, ConfigError  # noqa: F401  (re-exported)
from pipeline.plots import pyplot

ROOT = tracking.ROOT
#: config groups whose chosen option is a run tag (DESIGN, Tracking)
TAG_GROUPS = ("system", "data", "model", "identify", "regularizer", "invert")


def make_system(cfg: DictConfig):
    """Instantiate ``cfg.system`` (its ``name`` key is metadata, not a constructor argument)."""
    sys_cfg = OmegaConf.to_container(cfg.system, resolve=True)
    name = sys_cfg.pop("name", None)
    try:
        system = instantiate(sys_cfg)
    except Exception as exc:  # hydra wraps constructor errors; surface the message
        cause = exc.__cause__ or exc
        raise ConfigError(f"system '{name}': {cause}") from exc
    if name and getattr(system, "name", None) != name:   # e.g. a Recording: its config names it
        system.name = str(name)
    return system


def experiment_file() -> str:
    """The experiment file this job composed (Hydra's ``experiment`` choice), "" outside a Hydra app."""
    return str(HydraConfig.get().runtime.choices.get("experiment") or "") if HydraConfig.initialized() else ""


def job_overrides() -> str:
    """This job's command-line overrides (Hydra's ``overrides.task``, the experiment file and a sweep's
    values included) as a JSON list, the run's tag ``overrides``: ``pgnn-ff export`` re-composes the run
    from them and the current ``conf/`` instead of trusting its stored config (issue 51). "" outside a
    Hydra app, or when longer than a tag holds."""
    if not HydraConfig.initialized():
        return ""
    text = json.dumps([str(o) for o in HydraConfig.get().overrides.task])
    return text if len(text) <= 5000 else ""


def choice(cfg: DictConfig, group: str) -> str:
    node = cfg.get(group)
    if isinstance(node, DictConfig):
        return str(node.get("name") or node.get("kind") or "")
    return "" if node is None else str(node)


def implementation(stage: str, kind: str):
    """The module ``stages.<stage>.<kind>`` (method-specific stage implementation)."""
    pkg = importlib.import_module(f"stages.{stage}")
    folder = Path(pkg.__file__).parent
    options = sorted(p.stem for p in folder.glob("*.py") if not p.stem.startswith("_"))
    if kind not in options:
        raise ConfigError(f"no '{stage}' implementation for kind '{kind}'; choose one of {options}")
    return importlib.import_module(f"stages.{stage}.{kind}")


def exportable() -> list[str]:
    """The invert options the exporter ships: those whose stages/invert/<kind>.py declares ``export_laws``."""
    folder = Path(importlib.import_module("stages.invert").__file__).parent
    return [k for k in sorted(p.stem for p in folder.glob("*.py") if not p.stem.startswith("_"))
            if hasattr(implementation("invert", k), "export_laws")]


@dataclass
class StageContext:
    """What a stage sees: config, upstream results, seeded randomness, and recorders."""

    cfg: DictConfig
    name: str
    inputs: dict[str, dict]
    workdir: Path
    system: Any = None
    key: str = ""               # the stage's cache key (hash of its config and inputs)
    subkey: Any = None          # subkey(exclude) -> the key with the dotted config keys ``exclude`` left out
    metrics: list = field(default_factory=list)
    tags: dict = field(default_factory=dict)
    figures: list = field(default_factory=list)
    datasets: list = field(default_factory=list)
    artifacts: list = field(default_factory=list)
    models: list = field(default_factory=list)   # MLflow models to log: {"name", "law", "example"} (export)
    run_id: str = ""            # the MLflow run this stage computes for (provenance of exports)

    def rng(self, purpose: str) -> np.random.Generator:
        """A generator seeded by (cfg.seed, purpose): same config, same draws (SPEC §0)."""
        return np.random.default_rng([int(self.cfg.seed), zlib.crc32(purpose.encode())])

    def metric(self, key: str, value: float, step: int | None = None) -> None:
        self.metrics.append((f"{self.name}/{key}", float(value), step))

    def tag(self, key: str, value: Any) -> None:
        self.tags[key] = str(value)

    def figure(self, fig, filename: str) -> Path:
        path = self.workdir / "figures" / filename
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110, bbox_inches="tight")
        pyplot().close(fig)      # the figure was drawn with it: no import here
        self.figures.append(filename)
        return path

    def artifact(self, filename: str) -> Path:
        """A file to write that is logged to the run as artifact ``<stage>/<filename>``."""
        self.artifacts.append(filename)
        return self.path(f"artifacts/{filename}")

    def path(self, filename: str) -> Path:
        """A file inside the stage's (atomic) output directory."""
        p = self.workdir / filename
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def dataset(self, ds, name: str, context: str = "training") -> Path:
        """Save a :class:`pipeline.data.Dataset` (Parquet + sidecar) and log it as an input."""
        path = data.save(ds, self.workdir / "data" / name)
        self.datasets.append([f"data/{path.name}", name, context])
        return path

    def memo(self, label: str, compute, exclude: Iterable[str] = ()):
        """``compute()``, cached on its own key: this stage's key without the config keys
        ``exclude``, plus ``label``.  For a part of a stage that does not depend on those keys
        (restart i of an LM does not depend on ``identify.n_restarts``); locked and written
        atomically like a stage."""
        key = hashlib.sha256(f"{self.subkey(tuple(exclude))}/{label}".encode()).hexdigest()[:20]
        final = cache_dir(self.cfg) / f"{self.name}.parts" / key
        with _locked(final):
            loaded = _load_trusted(final)
            if loaded is not None:
                return loaded[0]
            value = compute()
            tmp = final.with_name(_tmp_name(key))
            try:
                private_dir(tmp)
                _write_signed(tmp, value, final=final)
                os.rename(tmp, final)
            except BaseException:   # a full disk, Ctrl-C: nothing half-written stays
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        return value

    def progress(self, iterable: Iterable | None, desc: str = "", total: int | None = None):
        """A tqdm bar over ``iterable`` (None: a manual bar, advanced with ``update``) on stderr when
        it is a terminal or ``PIPELINE_PROGRESS`` is set (quiet in tests and logs)."""
        return tqdm(iterable, desc=f"{self.name}: {desc}", total=total, leave=False,
                    disable=not sys.stderr.isatty() and not os.environ.get("PIPELINE_PROGRESS"))


def _select(cfg: DictConfig, key: str):
    node = OmegaConf.select(cfg, key, default=None)
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) or \
        OmegaConf.is_list(node) else node


def _without(node, dotted: str):
    """``node`` (a plain dict) with the dotted key removed (no-op if absent)."""
    head, _, rest = dotted.partition(".")
    if not isinstance(node, dict) or head not in node:
        return node
    node = dict(node)
    if rest:
        node[head] = _without(node[head], rest)
    else:
        del node[head]
    return node


#: DEPENDS keys added after caches were written: at this value left out of the key, so those entries stay valid
_KEY_DEFAULTS = {"init_seed": 0}


def stage_key(cfg: DictConfig, name: str, mod, upstream_keys: dict[str, str],
              exclude: tuple[str, ...] = ()) -> str:
    version = [getattr(mod, "VERSION", 1)]
    impl = None
    if getattr(mod, "KIND_KEY", None):  # the chosen implementation's VERSION counts too
        impl = implementation(name, str(OmegaConf.select(cfg, mod.KIND_KEY)))
        version.append(getattr(impl, "VERSION", 1))
    config = {k: _select(cfg, k) for k in mod.DEPENDS}
    config = {k: v for k, v in config.items() if _KEY_DEFAULTS.get(k, object()) != v}
    for dotted in exclude:   # a part's key (StageContext.memo) leaves out keys it does not depend on
        config = _without(config, dotted)
    payload = {"stage": name, "version": version, "config": config,
               "upstream": {u: upstream_keys[u] for u in mod.UPSTREAM},
               "isa": pipeline.ISA}   # the code paths decide the bits (issue 52): another ISA, another entry
    contents = getattr(impl, "content_key", None)    # what it reads besides the config (a measured
    if contents is not None:                         # file's bytes: another file under one name reruns)
        payload["contents"] = contents(cfg)
    if exclude:
        payload["exclude"] = sorted(exclude)
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


#: overrides that do not change what a run computes or are already its experiment: not in its name
_NAME_SKIP = ("experiment", "hydra", "stages", "paths", "report", "export", "run_name", "experiment_name",
              "description")


def run_name_with_overrides(cfg: DictConfig, overrides: Iterable[str], fixed: dict | None = None) -> str:
    """The run name: ``cfg.run_name`` (the experiment's template, naming what its sweep varies)
    plus ``-<key>=<value>`` for every command-line override the template does not interpolate, so
    two runs of one experiment with different configs never share a name
    (``experiment=physics_linear_motor model=pgnn`` is not named like the physics run).
    ``fixed``: the experiment's own single-valued sweep parameters (one value for every job: a
    setting of the experiment, not a variation), left out."""
    node = cfg._get_node("run_name")
    template = str(node._value()) if node is not None else ""
    sweep = {k: re.sub(r"^choice\((.*)\)$", r"\1", str(v)) for k, v in (fixed or {}).items()}
    fixed = {k: v for k, v in sweep.items() if "," not in v}
    # a group the experiment sweeps without naming it in its template (b1_linear_motor's regularizer):
    # its first value is the experiment's headline setting and stays out of the key, so the headline
    # runs keep the key (and summary.csv rows) they had before the sweep was added
    headline = {k: v.split(",")[0].strip() for k, v in sweep.items()
                if "," in v and "." not in k and "${" + k + "." not in template}
    extra = []
    for ov in overrides:
        key, sep, raw = ov.lstrip("+~").partition("=")
        key = key.replace("/", ".")
        bare = ov.lstrip("+~").partition("=")[0]
        if not sep or key.split(".")[0] in _NAME_SKIP or fixed.get(bare) == raw or headline.get(bare) == raw:
            continue
        if "${" + key + "}" in template or "${" + key + "." in template:   # the name shows it already
            continue
        val = OmegaConf.select(cfg, key, default=None)
        if isinstance(val, DictConfig):   # a group option: its name
            val = val.get("name") or raw
        elif OmegaConf.is_list(val):
            val = OmegaConf.to_container(val, resolve=True)
        shown = str(raw if val is None else val)
        if len(shown) > 24:   # a list of references: a short digest, not the whole value
            shown = hashlib.sha256(shown.encode()).hexdigest()[:8]
        extra.append(f"{key.removeprefix('system.')}={shown}")
    return "-".join([str(cfg.run_name), *extra])


def selected_stages(cfg: DictConfig) -> list[str]:
    raw = cfg.stages
    names = [raw] if isinstance(raw, str) else list(raw)
    names = [n.strip() for part in names for n in str(part).split(",") if n.strip()]
    unknown = [n for n in names if n not in ORDER]
    if unknown:
        raise ConfigError(f"unknown stage(s) {unknown} in 'stages'; choose from {list(ORDER)}, "
                          "e.g. stages=[generate,baseline]")
    return [n for n in ORDER if n in names]


def validate(cfg: DictConfig) -> tuple[list[str], Any, dict]:
    """Everything that can be checked before work starts (DESIGN: validate configs early)."""
    schema.check(cfg)
    names = selected_stages(cfg)
    system = make_system(cfg) if "system" in cfg and cfg.system is not None else None
    modules = {}
    needed, todo = set(), list(names)
    while todo:  # every transitive upstream stage: its key is needed, its result loaded from cache
        n = todo.pop()
        if n not in needed:
            needed.add(n)
            todo += list(importlib.import_module(f"stages.{n}").UPSTREAM)
    for n in ORDER:
        if n in needed:
            modules[n] = importlib.import_module(f"stages.{n}")
    for n in names:
        if hasattr(modules[n], "validate"):
            modules[n].validate(cfg, system)
    cache = Path(os.path.abspath(cache_dir(cfg)))
    why = owned.unsafe_place(cache)
    if why:
        raise ConfigError(f"paths.cache={cache} is {why} (the file system's root, the home folder and the "
                          "source tree are refused); give the cache a folder of its own, e.g. paths.cache=.cache "
                          "(the default)")
    try:
        _signing_key()          # a short or empty cache signing key is bad input: named before any work
    except BadKey as exc:
        raise ConfigError(str(exc)) from None
    return names, system, modules


def _record(ctx: StageContext, seconds: float) -> dict:
    return {"metrics": ctx.metrics, "tags": ctx.tags, "figures": ctx.figures,
            "datasets": ctx.datasets, "artifacts": ctx.artifacts, "models": ctx.models, "seconds": seconds}


def _store(tmp: Path, final: Path, result: dict, ctx: StageContext, seconds: float) -> None:
    _write_signed(tmp, result, _record(ctx, seconds), final)
    try:
        os.rename(tmp, final)  # atomic: the directory appears complete or not at all
    except OSError:  # another process finished the same key first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)


def plan(cfg: DictConfig, names: list[str], modules: dict) -> dict[str, str]:
    """Cache key of every needed stage; raise (before any work) if a stage that is not selected
    has no cached result, naming every such stage."""
    keys: dict[str, str] = {}
    missing = []
    for name, mod in modules.items():
        keys[name] = stage_key(cfg, name, mod, keys)
        done = (cache_dir(cfg) / name / keys[name][:20] / "record.json").exists()
        if name not in names and not done:
            missing.append(name)
    if missing:
        raise ConfigError(f"stage(s) {missing} are needed by {names} but have no cached result for "
                          f"this config; run them too, e.g. stages=[{','.join(missing + names)}]")
    return keys


#: seconds the last :func:`run_job` of this process waited for other jobs computing its entries (the
#: job queue orders by a job's own work: a job that found its model being trained is short next time)
WAITED = 0.0


def display(cfg: DictConfig, varying: list[str] | None) -> tuple[str, str]:
    """The run's display name and note (:mod:`pipeline.naming`): what ``varying`` (the keys its sweep
    or command line varies) are for this job first, then the fixed settings."""
    values = {k: (choice(cfg, k) if k in TAG_GROUPS else _select(cfg, k)) for k in varying or []}
    system = str(OmegaConf.select(cfg, "system.name", default="") or "")
    name = naming.display_name(values, list(varying or []), system, int(cfg.seed), str(cfg.run_name),
                               choice(cfg, "model") if "model" in cfg else "")
    note = naming.run_note(name, list(varying or []), values, str(cfg.experiment_name),
                           str(OmegaConf.select(cfg, "description", default="") or ""))
    return name, note


def run_job(cfg: DictConfig, run: "tracking.JobRun | None" = None,
            varying: list[str] | None = None) -> dict[str, dict]:
    """Run the selected stages of one job; returns every stage's result by name.  ``varying``: the
    dotted keys this job's sweep varies (they lead its MLflow run name; ``cfg.run_name`` is its
    ``run_key`` tag, the report's identity of the run)."""
    global WAITED
    WAITED = 0.0
    names, system, modules = validate(cfg)
    keys = plan(cfg, names, modules)
    store = cache_dir(cfg)
    for d in remove_stale_temporaries(store):
        print(f"[{cfg.run_name}] removed {d.parent.name}/{d.name}, left by a process that died",
              file=sys.stderr, flush=True)
    own_run = run is None
    if own_run:
        name, note = display(cfg, varying)
        tags = {"experiment": cfg.experiment_name, "stages": ",".join(names),
                "config_hash": keys[names[-1]][:20],  # the last stage's key: same hash, same config
                "run_key": str(cfg.run_name), "mlflow.note.content": note,
                "experiment_file": experiment_file(),   # conf/experiment/<file>.yaml: what the report selects by
                "overrides": job_overrides(),
                **{g: choice(cfg, g) for g in TAG_GROUPS if g in cfg}}
        params = OmegaConf.to_container(cfg, resolve=True)
        params.pop("description", None)   # the experiment's note, not a parameter of the run
        run = tracking.JobRun(str(cfg.experiment_name), name, tags, params,
                              description=str(OmegaConf.select(cfg, "description", default="") or ""))
    results: dict[str, dict] = {}
    status = "FAILED"
    try:
        if own_run:
            cfg_file = store / "configs" / f"{run.run_id}.yaml"
            cfg_file.parent.mkdir(parents=True, exist_ok=True)
            replace_file(cfg_file, OmegaConf.to_yaml(cfg, resolve=True))
            run.log_artifact(cfg_file)  # the resolved config (DESIGN, Tracking)
        for name, mod in modules.items():
            key = keys[name]
            final = store / name / key[:20]
            cacheable = getattr(mod, "CACHE", True)
            lock = _locked(final) if cacheable else None
            if lock is not None and not (final / "record.json").exists():
                try:
                    lock.acquire(timeout=0)
                except TimeoutError:  # another job computes this entry now: wait for it, then load
                    print(f"[{cfg.run_name}] {name}: waiting for another job computing the same result",
                          file=sys.stderr, flush=True)
                    t_wait = time.perf_counter()
                    lock.acquire()
                    WAITED += time.perf_counter() - t_wait
            try:
                loaded = _load_trusted(final) if cacheable else None
                hit = loaded is not None
                if hit:
                    results[name], record = loaded
                else:
                    final, results[name], record = _compute(cfg, name, mod, key, keys, results, system,
                                                            store, cacheable, run.run_id)
                adopt = getattr(mod, "adopt", None)   # what a stage hands the system (baseline: the chosen width)
                if adopt is not None and system is not None:
                    adopt(system, results[name])
            finally:
                if lock is not None and lock.is_locked:
                    lock.release()
            try:
                _log_stage(run, name, record, final, hit, cfg, cacheable)
            finally:
                if not cacheable:   # its temporary directory, logged: removed whatever happens
                    shutil.rmtree(final, ignore_errors=True)
                    interrupts.discard(final)
            print(f"[{cfg.run_name}] {name}: " + ("cached" if hit else f"{record['seconds']:.1f} s"),
                  file=sys.stderr, flush=True)  # one line per stage: a log file shows progress too
        status = "FINISHED"
    except KeyboardInterrupt:   # Ctrl-C or `kill` (pipeline.interrupts): stopped, not failed
        status = "KILLED"
        raise
    finally:
        if own_run:
            run.end(status)
    return results


def _compute(cfg, name, mod, key, keys, results, system, store, cacheable, run_id=""):
    """Run one stage into a temporary directory and move it into the cache (atomic)."""
    final = store / name / key[:20]
    tmp = store / name / _tmp_name(key[:20])
    # removed on any exception, Ctrl-C included; by the interrupt watchdog if this thread cannot react
    interrupts.on_abort(tmp, lambda: shutil.rmtree(tmp, ignore_errors=True))
    try:
        private_dir(tmp)   # no one else writes (or plants a link) in it while the stage fills it
        ctx = StageContext(cfg, name, {u: results[u] for u in mod.UPSTREAM}, tmp, system, key,
                           subkey=lambda exclude: stage_key(cfg, name, mod, keys, exclude), run_id=run_id)
        _seed_everything(int(cfg.seed), name)
        t0 = time.perf_counter()
        result = mod.run(ctx) or {}
        seconds = time.perf_counter() - t0
        if cacheable:
            _store(tmp, final, result, ctx, seconds)
        else:
            final = tmp
            (tmp / "record.json").write_text(json.dumps(_record(ctx, seconds)))
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)   # nothing half-written stays (a full disk, Ctrl-C)
        interrupts.discard(tmp)
        if isinstance(exc, OSError) and not exc.filename:   # a write into an open file: name the entry
            exc.filename = str(tmp)
        raise
    if cacheable:
        interrupts.discard(tmp)    # renamed into place (the non-cacheable one: run_job removes it)
    return final, result, json.loads((final / "record.json").read_text())


def _seed_everything(seed: int, stage: str) -> None:
    import torch  # lazy: saves 2.6 s of start-up (torch: a cached job never seeds)
    s = (seed * 1_000_003 + zlib.crc32(stage.encode())) % 2**31
    np.random.seed(s)
    torch.manual_seed(s)


def _log_stage(run, name: str, record: dict, stage_dir: Path, hit: bool, cfg=None, cacheable: bool = False) -> None:
    """Log one stage's metrics, tags and artifacts to ``run``; a cached stage's entry is named in the tag
    ``cache_entry.<stage>`` (``<stage>/<key>``): the report ships exported packages from that signed entry,
    never from the artifact store (issue 51 item 2)."""
    metrics = [tuple(m) for m in record["metrics"]]
    metrics.append((f"time/{name}_s", record["seconds"], None))
    system = str(OmegaConf.select(cfg, "system.name", default="") or "") if cfg is not None else ""
    metrics += display_metrics(metrics, system)   # µm, µs twins: the UI's charts read (issue 23)
    run.log_metrics(metrics)
    run.set_tags({**record["tags"], f"cache.{name}": "hit" if hit else "miss",
                  **({f"cache_entry.{name}": f"{name}/{stage_dir.name}"} if cacheable else {})})
    for fig in record["figures"]:
        run.log_artifact(stage_dir / "figures" / fig, "figures")
    for rel in record.get("artifacts", []):   # <stage>/<rel>, sub-folders kept
        parent = Path(rel).parent
        run.log_artifact(stage_dir / "artifacts" / rel, name if parent == Path(".") else f"{name}/{parent.as_posix()}")
    for rel, ds_name, context in record.get("datasets", []):
        path = stage_dir / rel
        run.log_dataset(pd.read_parquet(path), ds_name, str(path), context)
    register = bool(OmegaConf.select(cfg, "export.register", default=False)) if cfg is not None else False
    for m in record.get("models", []):   # the exported feedforwards as MLflow pyfunc models
        run.log_feedforward_model(m["name"], stage_dir / m["law"], stage_dir / m["example"],
                                  f"{cfg.experiment_name}-{m['name']}" if register else None)
