"""``pgnn-ff export RUN_ID [--out DIR]`` (or ``python -m pipeline export …``): export the
feedforward of an existing MLflow run (issue 12).

The run's config, composed again from this code's ``conf/`` and the run's own overrides (its tag
``overrides``; a run made before it: its stored ``<run id>.yaml``, checked as data), is rerun with the
stages up to ``invert`` plus ``export``: the upstream stages load from the cache (or are recomputed,
bit-identical for the config), the packages and MLflow models are logged to that run, and the packages
are copied from the signed cache entry to ``DIR/<package>/`` (default ``export/``), each appearing
whole or not at all.

Never trusted from the stored run (issue 51): a module name (``_target_``), a path (``paths``), an
interpolation, and the C compiler.  It is ``--cc`` when given, else the default of
``conf/config.yaml`` (``cc``): a shared store must not be a way to run a command on a colleague's
machine.  ``DIR`` must not be inside the source tree, and a package folder there is replaced only
if this command wrote it (:mod:`pipeline.owned`): a file of the user's in it stops the export
before any work.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import mlflow
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline import owned, runner, schema, tracking
from pipeline.cache import UntrustedCache, cache_dir, copy_signed
from pipeline.export.law import ExportError
from pipeline.export.package import replace_dir
from pipeline.runner import ORDER, ROOT, ConfigError

__all__ = ["main", "export_run", "stored_run", "run_config"]


def _writable(out: Path) -> None:
    """``out`` is (or can be made) a folder this user writes to, outside the source tree."""
    owned.refuse_foreign(out, [], "--out")     # not /, home or the source tree; not a file
    try:
        out.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=out).close()
    except OSError as exc:
        raise ConfigError(f"cannot write to --out {out} ({exc.strerror}); give a folder you can write to") from None


def _targets(node, at: str = ""):
    """Every ``_target_`` of a config tree: (dotted key, value)."""
    if isinstance(node, DictConfig):
        for k in node.keys():
            key = f"{at}.{k}" if at else str(k)
            if k == "_target_":
                yield key, node._get_node(k)._value()
            else:
                yield from _targets(node._get_node(k), key)
    elif isinstance(node, ListConfig):
        for i, v in enumerate(node._iter_ex(resolve=False)):
            yield from _targets(v, f"{at}[{i}]")


def plant_targets() -> set[str]:
    """The plants' classes the current code's config tree names (``conf/system/*.yaml`` ``_target_``),
    read as text: nothing is imported."""
    out = set()
    for f in sorted((ROOT / "conf" / "system").glob("*.yaml")):
        node = OmegaConf.load(f)
        if isinstance(node, DictConfig) and isinstance(node.get("_target_"), str):
            out.add(node["_target_"])
    return out


#: overrides of a stored run that are never re-applied: where this user's files go, Hydra's own settings,
#: the compiler (``--cc`` chooses it)
_NOT_REAPPLIED = ("paths", "hydra", "export.cc")


def recomposed(run_id: str, overrides: str | None, stored: DictConfig) -> DictConfig | None:
    """The run's config composed again from the current ``conf/`` and the run's own overrides (its tag
    ``overrides``, issue 51 finding 5): what a stored config names is never imported or used as a path. An
    override of a ``_target_`` is refused; those of ``paths``, ``hydra`` and ``export.cc`` are dropped (yours
    apply). None for a run made before the tag existed (:func:`stored_as_data` then)."""
    if not overrides:
        return None
    try:
        given = json.loads(overrides)
    except ValueError:
        given = None
    if not (isinstance(given, list) and all(isinstance(o, str) for o in given)):
        raise ConfigError(f"run {run_id}'s tag overrides is not a JSON list of overrides: the run was altered or "
                          "not made by this pipeline")
    kept = []
    for o in given:
        key = o.lstrip("+~").split("=", 1)[0].strip()
        if "_target_" in key or "${" in o:    # a module name, or a resolver (${oc.env:...}) reading this machine
            raise ConfigError(f"run {run_id} was made with the override {o!r}: a stored module name or "
                              "interpolation is never used; export a run made with this code's configs")
        if not any(key == k or key.startswith(f"{k}.") or key.startswith(f"{k}/") for k in _NOT_REAPPLIED):
            kept.append(o)
    schema.register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            cfg = compose(config_name="config", overrides=kept)
    except Exception as exc:  # noqa: BLE001 — Hydra raises several types for an override it cannot apply
        raise ConfigError(f"run {run_id}'s overrides {kept} do not compose with this code's conf/ "
                          f"({str(exc).splitlines()[0]}): export it with the code it was made with") from None
    finally:
        GlobalHydra.instance().clear()
    if isinstance(stored.get("run_name"), str) and "${" not in stored.run_name:
        cfg.run_name = stored.run_name          # a name (the schema checks it), as __main__ set it for the job
    return cfg


def stored_as_data(cfg: DictConfig, run_id: str) -> DictConfig:
    """A run's stored config (from a store others may write) made data (issue 51 finding 5): its only
    ``_target_`` may be ``system._target_`` and must be a plant class of the current code's
    ``conf/system/`` (checked before anything imports it; the schema then checks every key as for a new
    job); ``paths`` are this user's (the defaults: ``$PIPELINE_CACHE``, ``<repo>/results``), never the
    stored ones; ``export.cc`` is replaced by the caller."""
    allowed = plant_targets()
    if "${" in OmegaConf.to_yaml(cfg, resolve=False):   # stored resolved: an interpolation was put there since
        raise ConfigError(f"run {run_id}'s stored config holds an interpolation (${{...}}), which a resolved config "
                          "never does: the run was altered; a stored interpolation is never resolved here")
    for key, value in _targets(cfg):
        if key != "system._target_" or value not in allowed:
            raise ConfigError(f"run {run_id}'s stored config sets {key}={value!r}, which is not a plant of this "
                              f"code's conf/system/ ({', '.join(sorted(allowed))}); a stored module name is never "
                              "imported: export a run made with this code's configs")
    stored = OmegaConf.select(cfg, "paths", default=None)
    cfg.paths = OmegaConf.create(schema.defaults(schema.Paths))
    if isinstance(stored, DictConfig) and any(stored.get(k) not in (None, cfg.paths[k]) for k in cfg.paths):
        print(f"note: run {run_id} was made with paths {OmegaConf.to_container(stored)}; exporting with this "
              f"user's cache ({cache_dir(cfg)}), never a stored path", file=sys.stderr)
    return cfg


def stored_run(run_id: str):
    """The MLflow run ``run_id`` of the tracking store (not a sweep's parent), or a one-line ConfigError."""
    client = tracking.client()
    try:
        run = client.get_run(run_id)
    except mlflow.exceptions.MlflowException as exc:
        raise ConfigError(f"no run {run_id!r} in the tracking store {tracking.tracking_uri()} "
                          "(set MLFLOW_TRACKING_URI to the store the run is in)") from exc
    if run.data.tags.get("sweep") == "parent":
        raise ConfigError(f"run {run_id} is the parent of a sweep; give one of its children (make ui lists them)")
    return run


def run_config(run) -> DictConfig:
    """The config of a stored run, composed again from this code's ``conf/`` and the run's tag ``overrides``
    (:func:`recomposed`), or its stored ``<run id>.yaml`` checked as data (:func:`stored_as_data`)."""
    run_id = run.info.run_id
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=f"{run_id}.yaml", dst_path=tmp)
        except (mlflow.exceptions.MlflowException, OSError) as exc:
            raise ConfigError(f"run {run_id} has no resolved config artifact ({run_id}.yaml): it was not made by "
                              "this pipeline") from exc
        try:
            cfg = OmegaConf.load(path)
        except Exception as exc:  # noqa: BLE001 — YAML and OmegaConf raise several types
            raise ConfigError(f"run {run_id}'s config artifact {run_id}.yaml is not a config ({type(exc).__name__}): "
                              "the run was altered or not made by this pipeline") from None
    if not isinstance(cfg, DictConfig):
        raise ConfigError(f"run {run_id}'s config artifact {run_id}.yaml is not a mapping: the run was altered or "
                          "not made by this pipeline")
    return recomposed(run_id, run.data.tags.get("overrides"), cfg) or stored_as_data(cfg, run_id)


def export_run(run_id: str, out: Path, *, register: bool = False, compile: bool = True,
               cc: str | None = None) -> dict:
    """Export the feedforward of run ``run_id`` to ``out``; returns {package: manifest}.  ``cc``:
    the C compiler (None: the default of conf/config.yaml, never the one stored with the run)."""
    out = Path(out)
    _writable(out)
    run = stored_run(run_id)
    stages = [s for s in run.data.tags.get("stages", "").split(",") if s]
    if "invert" not in stages:
        raise ConfigError(f"run {run_id} designed no feedforward (stages={stages}): export needs a run with the "
                          "invert stage")
    cfg = run_config(run)
    kind = str(OmegaConf.select(cfg, "invert.kind", default=""))
    if kind not in runner.exportable():
        raise ConfigError(f"run {run_id} has invert.kind={kind!r}, which has no feedforward law to ship; "
                          f"export covers {runner.exportable()}")
    default = OmegaConf.create(schema.defaults(schema.owned_class("export")))   # stages/export.py Params
    if "export" not in cfg:   # a run made before the export stage existed
        cfg.export = default
    stored, cfg.export.cc = str(cfg.export.get("cc")), str(cc or default.cc)
    if compile and stored != cfg.export.cc:
        print(f"note: run {run_id} was exported with export.cc={stored!r}; compiling with {cfg.export.cc!r} "
              "(a stored command is never run: pass --cc to choose the compiler)", file=sys.stderr)
    # the packages this run can write (stages/export.py names them ff_<kind>[_<reference>]): none of
    # them may hold a file of the user's
    prefix = "ff_" if kind == "rational_filter" else f"ff_{kind}"
    owned.refuse_foreign(out, [d.name for d in out.iterdir() if d.name.startswith(prefix)], "--out")
    cfg.export.register = bool(register)
    cfg.export.compile = bool(compile)
    cfg.stages = [s for s in ORDER if s in ("generate", "baseline", "train", "invert", "export")]
    results = runner.run_job(cfg, run=tracking.JobRun.resume(run_id))
    packages = results["export"]["packages"]
    owned.refuse_foreign(out, list(packages), "--out")
    # the packages are copied from the signed cache entry the job just loaded or wrote, never from the
    # tracking store's artifact folder (anyone with write access to a shared store could plant a file
    # there); each file's bytes are hashed as they are read and written only if signed (no check-then-copy)
    names, _, modules = runner.validate(cfg)
    entry = cache_dir(cfg) / "export" / runner.plan(cfg, names, modules)["export"][:20]
    for name in packages:
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{name}-", dir=out))
        try:
            got = tmp / name
            try:
                if not copy_signed(entry, f"artifacts/{name}", got):
                    raise UntrustedCache(f"{entry} holds no package {name}")
            except (UntrustedCache, OSError) as exc:
                raise ConfigError(f"the export's cache entry changed while it was copied: {exc}; rerun") from None
            final = out / name
            owned.allow(out, name, got)     # known as ours even if stopped right after the swap
            replace_dir(got, final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        owned.record(out, [name])
        man = packages[name]
        c = f"C max|Δu|/max|u| = {man['c_max_rel_diff']:.2g}, {man['c_ns_per_sample']:.0f} ns/sample" \
            if man["compiled"] else "C not compiled (no compiler)"
        model = tracking.JobRun.resume(run_id).model_name(name)
        print(f"{final}: {man['law']} ({c}); MLflow model runs:/{run_id}/{model}")
    return packages


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pgnn-ff export", description="Export the feedforward of an MLflow run "
                                "to C99 code, an MLflow pyfunc model and a manifest (README: Deploy the feedforward).")
    p.add_argument("run_id", help="the MLflow run id (make ui shows it)")
    p.add_argument("--out", default="export", help="folder of the packages (default: ./export)")
    p.add_argument("--register", action="store_true", help="also register the model in the MLflow Model Registry")
    p.add_argument("--no-compile", action="store_true", help="write the C source without compiling or verifying it")
    p.add_argument("--cc", default=None, help="the C compiler to run (default: cc; the one stored with the run "
                   "is never used)")
    args = p.parse_args(argv)
    if not args.out.strip():
        print("error: --out is empty; give the folder of the packages (default ./export)", file=sys.stderr)
        return 2
    try:
        export_run(args.run_id, Path(args.out), register=args.register, compile=not args.no_compile, cc=args.cc)
    except (ConfigError, ExportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
