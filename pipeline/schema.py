"""The strict checker of the composed config: what every key may hold, checked before any work.

Each option owns its parameters: one strict dataclass (:data:`schema`) next to its code, named
``Params``: a plant's in its module of pipeline/systems/ (found by ``system._target_``), a data /
identify / invert option's in its stage implementation stages/<stage>/<kind>.py (found by ``kind``,
as the runner finds the stage), a model's in its pipeline/models/ module (``KIND`` or the module's
name), the regularizers' in stages/train/__init__.py (by ``name``), the export stage's in
stages/export.py; sub-nodes next to the code using them (the controller's in
pipeline/systems/controller.py). This module keeps the top level (:class:`Config`, ``paths``,
``report``, ``evaluate``), the checker and the magnitude bounds; it imports no option module (they
import it) and finds a class with importlib: no registry. A field's annotation is its type
(``bool``, ``int``, ``float``, ``str``, ``Literal[...]`` for an enumeration, ``list[...]``,
``Optional[...]`` for null, a nested dataclass for a sub-node, ``Any`` for what a library checks
itself, e.g. reference specs); its metadata (:func:`spec`) gives the range
(``gt``/``ge``/``lt``/``le``, on every item of a list), the unit, a list's shortest length, and
the rule and example quoted in the message. Every ``float`` must be finite, and every physical
quantity has an upper bound that rules out implausible magnitudes (``system.noise.std=1e300``).

A key's default is stated once, in its class: :func:`register` gives Hydra every class's defaults
before it composes (conf/config.yaml merges ``_params/<group>/<option>`` under each group), so the
YAML files hold only values that differ and every key can still be set on the command line.

:func:`check` validates the resolved config against these classes: an unknown key, a missing
mandatory value (``???``), a value of the wrong type, outside its range or not one of its choices
raises :class:`pipeline.runner.ConfigError` with one line naming the key, the value, what is allowed
and an example, e.g. ``model.hidden=[-3]: widths must be positive integers (e.g.
model.hidden=[16])``. Types are strict: nothing is coerced (``true``/``false`` only for a bool, not
``maybe``, ``yes`` or 1; an integer for an int, not 1.5 or '3'); this is why the check walks the
annotations itself instead of merging into ``OmegaConf.structured`` (which converts 'yes' and 1 to
True and '3' to 3), and why Hydra gets the defaults as plain values, not as typed structured configs.
Keys a config still leaves out are set to their defaults. Checks across keys or against the plant
(orders against the physics model, bounds lower < upper, references within the plant's limits) stay
in the stages' ``validate`` / ``check`` functions, which run after this one.

Adding a plant: its module pipeline/systems/<plant>.py (the System and its ``Params``) and
conf/system/<plant>.yaml. Adding a method: stages/<stage>/<kind>.py (with its ``Params``) and its
conf/<group>/<kind>.yaml (tests/test_config_schema.py checks that every implementation declares one).
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import math
import typing
from dataclasses import MISSING, field
from pathlib import Path
from typing import Any, Literal, Optional, Union

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf, open_dict

from pipeline import source_digest
from pipeline.atomic import replace_file
from pipeline.errors import ORDER, SAFE_NAME, ConfigError
from pipeline.params import is_number, references_rule, schema, spec

__all__ = ["check", "options", "option_class", "defaults", "register", "Config", "Evaluate"]


def _stages_rule(v) -> str | None:
    unknown = [s for s in v if s not in ORDER]
    if unknown:
        return f"unknown stage(s) {unknown}; choose from {list(ORDER)}"
    return None


def _name_rule(v) -> str | None:
    if not SAFE_NAME.fullmatch(v):
        return ("is not a name: use letters, digits, '.', '_' and '-' (it names the MLflow experiment and its "
                "artifact folder)")
    return None


# ------------------------------------------------------------------------------------------------
# top level
# ------------------------------------------------------------------------------------------------
@schema
class Paths:
    cache: Optional[str] = None      # stage output store; null = <repo>/.cache (or $PIPELINE_CACHE)
    results: Optional[str] = None    # report output; null = <repo>/results


@schema
class Report:
    # MLflow experiments summarised, in order
    experiments: list[str] = spec(["physics_baseline", "b1_arx_bias", "b1_linear_motor", "b1_noise_sweep", "k_two_mass",
                                   "b2_rot_trans", "emps"], min_len=1)
    # true: rebuild only these experiments' sections, keep the rest of results/
    update: bool = False


@schema
class Config:
    """The top level; each group (system, data, ...) is checked by its option's own class."""
    # seeds every random draw of the job (SPEC §0)
    seed: int = spec(0, ge=0)
    # the networks' initial weights and restarts only (issue 52 item 2; `make reproduce-spread`): 0 draws
    # them from `seed` (every published number); k > 0 from (seed, k): other restarts on the same data
    init_seed: int = spec(0, ge=0)
    # MLflow experiment (one per paper experiment)
    experiment_name: str = spec("default", check=_name_rule, example="my_study")
    run_name: str = "default"
    description: str = ""            # the experiment's MLflow note: what it compares, which tags/metrics to read
    compare_metrics: list[str] = spec(["evaluate/*/mae"])   # metric globs of the sweep's comparison (issue 23)
    # subset of generate,baseline,train,invert,evaluate,export,report
    stages: list[str] = spec(["generate", "baseline", "train", "invert", "evaluate"], min_len=1,
                             check=_stages_rule, example=["generate", "baseline"],
                             rule=f"give a non-empty list of stages from {list(ORDER)}")
    paths: Paths = field(default_factory=Paths)
    # the export stage (stages=[..., export]): C99 code + MLflow model of the feedforward
    export: Any = None               # stages/export.py Params
    # where every feedforward law starts and what it gives at switch-on (pipeline/invert/start.py Params)
    start: Any = None
    report: Report = field(default_factory=Report)
    system: Any = None
    data: Any = None
    model: Any = None
    identify: Any = None
    regularizer: Any = None
    invert: Any = None
    evaluate: Any = None


# ------------------------------------------------------------------------------------------------
# data (by kind; stages/generate/<kind>.py)
# ------------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------------
# model (by kind; pgnn when it has a structure, else the physics model)
# ------------------------------------------------------------------------------------------------


def _model_option(node: dict) -> str:
    """model.kind where given; else the physics model (model=physics) or a NARX PGNN (model=pgnn)."""
    if "kind" in node:
        return node["kind"]
    return "physics" if node.get("name") == "physics" else "pgnn"


# ------------------------------------------------------------------------------------------------
# identify (by kind; stages/train/<kind>.py)
# ------------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------------
# regularizer (by name)
# ------------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------------
# invert (by kind; stages/invert/<kind>.py)
# ------------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------------
# evaluate (one layout; convention and validation_tail matter for measured systems)
# ------------------------------------------------------------------------------------------------
@schema
class Evaluate:
    # reference specs (pipeline.references.from_spec), scored one by one
    references: Any = spec([], check=references_rule, example="[{name:R,kind:b2_R}]")
    # (evaluate/default.yaml) false: noise-free evaluation runs; true: the plant's noise model (seeded)
    # (evaluate/k_heldout.yaml) the two-mass plant is noise-free
    # (evaluate/measured.yaml) measured data carry their own noise; nothing is added
    noise: bool = False
    # a model identified on measured data (data=measured) is scored on a simulator only if true (the run is tagged
    # evaluated_on): it says nothing about the machine the data came from
    allow_simulator: bool = False
    # data: as recorded (default) | published: the EMPS authors' script (one more sample of delay on the controller
    # output, time base t(10) - t(9)); both are logged, this one is plotted
    convention: Literal["data", "published"] = "data"   # = pipeline.identify.measured_loop.CONVENTIONS
    # last share of a record scored separately (training file: the held-out block)
    validation_tail: float = spec(0.2, ge=0, lt=1)


# ------------------------------------------------------------------------------------------------
# where an option's class lives (found like the runner finds a stage implementation: no registry)
# ------------------------------------------------------------------------------------------------
#: group -> the key choosing its option
CHOOSER = {"system": "_target_", "data": "kind", "model": "kind", "identify": "kind", "regularizer": "name",
           "invert": "kind"}
#: group -> the stage whose ``stages/<stage>/<kind>.py`` implements (and declares the ``Params`` of) an option
STAGE = {"data": "generate", "identify": "train", "invert": "invert"}
#: top-level nodes a stage owns: their class is that stage module's ``Params``
OWNED = {"export": "stages.export", "start": "pipeline.invert.start"}
_ROOT = Path(__file__).resolve().parent.parent
#: where :func:`register` keeps the options' defaults per content hash (beside this package's bytecode)
DEFAULTS_CACHE = Path(__file__).resolve().parent / "__pycache__"


def owned_class(key: str) -> type:
    """The class of a top-level node a stage owns (``export``: stages/export.py ``Params``)."""
    return importlib.import_module(OWNED[key]).Params


def _modules(package: str) -> list[str]:
    """The public modules of a package folder (``stages.train`` -> its ``<kind>.py``)."""
    folder = _ROOT.joinpath(*package.split("."))
    return sorted(p.stem for p in folder.glob("*.py") if not p.stem.startswith("_"))


def _model_option(node: dict) -> str:
    """model.kind where given; else the physics model (model=physics) or a NARX PGNN (model=pgnn)."""
    if "kind" in node:
        return node["kind"]
    return "physics" if node.get("name") == "physics" else "pgnn"


def _literal(cls: type, key: str) -> Any:
    args = typing.get_args(typing.get_type_hints(cls).get(key, Any))
    return args[0] if len(args) == 1 else None


def options(group: str) -> dict[str, type]:
    """Every option of ``group`` and its class, found where the options live: a system module's
    ``Params`` (pipeline/systems/<plant>.py), a stage implementation's ``Params``
    (stages/<stage>/<kind>.py), a model module's ``Params`` (pipeline/models/<module>.py, option
    ``KIND`` or the module's name), the regularizer classes of the train stage (stages/train/__init__.py,
    option their ``name``)."""
    if group == "system":
        out = {}
        for stem in _modules("pipeline.systems"):
            mod = importlib.import_module(f"pipeline.systems.{stem}")
            if hasattr(mod, "Params"):
                base = importlib.import_module("pipeline.systems.base").System
                for obj in vars(mod).values():
                    if isinstance(obj, type) and issubclass(obj, base) and obj.__module__ == mod.__name__:
                        out[f"{mod.__name__}.{obj.__name__}"] = mod.Params
        return out
    if group in STAGE:
        pkg = f"stages.{STAGE[group]}"
        return {k: importlib.import_module(f"{pkg}.{k}").Params for k in _modules(pkg)}
    if group == "model":
        out = {}
        for stem in _modules("pipeline.models"):
            mod = importlib.import_module(f"pipeline.models.{stem}")
            if hasattr(mod, "Params"):
                out[getattr(mod, "KIND", stem)] = mod.Params
        return out
    if group == "regularizer":
        mod = importlib.import_module("stages.train")
        return {_literal(c, "name"): c for c in vars(mod).values()
                if dataclasses.is_dataclass(c) and isinstance(c, type) and _literal(c, "name")}
    raise KeyError(group)


def option_class(group: str, node: dict) -> tuple[str, type]:
    """(the option, its class) of a group's node; ConfigError naming the choices for an unknown one."""
    by = CHOOSER[group]
    option = _model_option(node) if group == "model" else node.get(by)
    cls = None
    if group == "system" and isinstance(option, str) and "." in option:
        try:   # the plant's own module (any importable module, not only pipeline/systems/)
            cls = getattr(importlib.import_module(option.rsplit(".", 1)[0]), "Params", None)
        except ImportError:
            cls = None
    elif group in STAGE and isinstance(option, str) and option in _modules(f"stages.{STAGE[group]}"):
        cls = importlib.import_module(f"stages.{STAGE[group]}.{option}").Params
    elif group not in ("system",) and group not in STAGE:
        cls = options(group).get(option)
    if cls is None:
        where = f"no '{STAGE[group]}' implementation" if group in STAGE else "no parameter class"
        hint = (" (a new plant is its module, e.g. pipeline/systems/<plant>.py, with a `Params` dataclass "
                "next to the System class its _target_ names)") if group == "system" else ""
        choices = sorted(options(group))
        raise ConfigError(f"{group}.{by}={_show(option)}: {where} for {by} {option!r}; choose one of "
                          f"{choices}{hint}")
    return option, cls


def defaults(cls: type) -> dict:
    """The class's defaults as a config node (a mandatory value: ``???``)."""
    out = {}
    for f in dataclasses.fields(cls):
        if not f.metadata.get("fill", True):
            continue
        if f.default is MISSING and f.default_factory is MISSING:
            tp, _ = _optional(typing.get_type_hints(cls)[f.name])
            out[f.name] = defaults(tp) if dataclasses.is_dataclass(tp) else "???"
        else:
            out[f.name] = _default(f)
    return out


def _selector(folder: Path, stem: str, seen: tuple = ()) -> dict:
    """The keys choosing an option file's class (kind, _target_, name), following its ``defaults``
    within its group (conf/data/inverse.yaml -> closed_loop.yaml)."""
    path = folder / f"{stem}.yaml"
    if not path.exists() or stem in seen:
        return {}
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}
    out = {}
    for d in node.get("defaults") or []:
        if isinstance(d, str) and d != "_self_" and "/" not in d:
            out.update(_selector(folder, d, (*seen, stem)))
    out.update({k: node[k] for k in ("kind", "_target_", "name") if k in node})
    return out


def register(conf: Path | None = None) -> None:
    """Give Hydra every key's default before it composes, so that any key can be overridden on the
    command line (``identify.patience=0``) while conf/ holds only the values that differ: for every
    option file conf/<group>/<option>.yaml the defaults of its class as ``_params/<group>/<option>``
    (conf/config.yaml puts ``_params/<group>@<group>: ${<group>}`` before the group), and the top
    level's as ``_params_config``. Call before composing (pipeline/__main__.py, tests/conftest.py)."""
    conf = Path(conf or _ROOT / "conf")
    store = ConfigStore.instance()
    nodes = _cached_defaults(conf)
    for name, node in nodes.items():
        group, _, stem = name.rpartition("/")
        store.store(group=group or None, name=stem, node=node)


def _all_defaults(conf: Path) -> dict[str, dict]:
    """{store name: node} of :func:`register` (imports every option's module)."""
    top = {k: v for k, v in defaults(Config).items() if k not in CHOOSER and k != "evaluate"}
    for key in OWNED:
        top[key] = defaults(owned_class(key))
    out = {"_params_config": top}
    for group in (*CHOOSER, "evaluate"):
        for path in sorted((conf / group).glob("*.yaml")):
            node = {}
            try:
                cls = Evaluate if group == "evaluate" else option_class(group, _selector(path.parent, path.stem))[1]
                node = defaults(cls)
            except ConfigError:   # an option without a class: schema.check names the choices
                pass
            out[f"_params/{group}/{path.stem}"] = node
    return out


def _cached_defaults(conf: Path) -> dict[str, dict]:
    """:func:`_all_defaults`, kept beside the bytecode (:data:`DEFAULTS_CACHE`) under the SHA-256 of every
    source and config file it depends on (pipeline/, stages/, conf/): importing every option's module
    (torch, numba, python-control) costs ~3.7 s of start-up per process, reading the file ~10 ms. Any
    edit of those files gives a new hash, so the defaults are recomputed (a compiled form of the code,
    like a .pyc, not a second statement of the defaults; never in a run's cache or results); an
    unwritable folder only loses the saving."""
    digest = source_digest((f.relative_to(base.parent).as_posix(), f.read_bytes())
                           for base, pattern in ((_ROOT / "pipeline", "*.py"), (_ROOT / "stages", "*.py"),
                                                 (conf, "*.yaml"))
                           for f in sorted(base.rglob(pattern)))
    where = DEFAULTS_CACHE / f"params-defaults-{digest[:20]}.json"
    try:
        return json.loads(where.read_text())
    except (OSError, ValueError):
        pass
    nodes = _all_defaults(conf)
    try:
        where.parent.mkdir(parents=True, exist_ok=True)
        replace_file(where, json.dumps(nodes))
    except OSError:
        pass
    return nodes


# ------------------------------------------------------------------------------------------------
# the check
# ------------------------------------------------------------------------------------------------
def check(cfg) -> list[str]:
    """Validate the composed config against the schema; ConfigError (one line) on the first problem.
    Then every key left out is set to its schema default in ``cfg`` (the one place a default is
    stated: stages read every key without a default of their own); returns the keys set."""
    try:  # every interpolation resolves (a typo in ${...} fails here, not after hours of work)
        raw = OmegaConf.to_container(cfg, resolve=True)
    except Exception as exc:  # noqa: BLE001 — OmegaConf raises several error types
        raise ConfigError(f"config does not resolve: {str(exc).splitlines()[0]}") from exc
    raw.pop("hydra", None)
    _DEFAULTED.clear()
    _check_nodes(raw)
    filled = list(_DEFAULTED)
    with open_dict(cfg):
        for key, value in filled:
            OmegaConf.update(cfg, key, value, force_add=True)
    return [k for k, _ in filled]


#: (dotted key, default) of the keys the last check found left out
_DEFAULTED: list[tuple[str, Any]] = []


def _default(f: dataclasses.Field) -> Any:
    v = f.default if f.default is not MISSING else f.default_factory()
    return dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v


def _check_nodes(raw: dict) -> None:
    _check_node(Config, raw, "", "the config")
    for key in OWNED:
        node = raw.get(key)
        _check_node(owned_class(key), {} if node is None else node, key, key)
    for group in CHOOSER:
        node = raw.get(group)
        if node is None:
            continue
        if not isinstance(node, dict):
            raise ConfigError(f"{group}={_show(node)} is not a config group: choose an option, e.g. "
                              f"{group}=<name of a file in conf/{group}/>")
        option, cls = option_class(group, node)
        label = f"{group} {option!r}" if group != "system" else f"system '{node.get('name', option)}'"
        _check_node(cls, node, group, label)
    if raw.get("evaluate") is not None:
        _check_node(Evaluate, raw["evaluate"], "evaluate", "evaluate")


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _check_node(cls: type, node: Any, prefix: str, label: str) -> None:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if not isinstance(node, dict):
        raise ConfigError(f"{prefix}={_show(node)} is not a mapping: give the keys {', '.join(fields)}")
    unknown = [k for k in node if k not in fields]
    if unknown:
        raise ConfigError(f"{_join(prefix, str(unknown[0]))}: unknown key of {label}; allowed keys: "
                          f"{', '.join(fields)}")
    hints = typing.get_type_hints(cls)
    for name, f in fields.items():
        key = _join(prefix, name)
        value = node.get(name, MISSING)
        if value is MISSING and (f.default is not MISSING or f.default_factory is not MISSING):
            default = _default(f)
            if default is not None:   # left out: its default, set by check() (None: read with .get)
                _DEFAULTED.append((key, default))
            continue
        if value is MISSING or value == "???":
            raise ConfigError(f"{key} is not set: {_rule(hints[name], f)} (e.g. {key}={_example(f)})")
        _check_value(hints[name], value, f, key, label)


def _optional(tp) -> tuple[Any, bool]:
    """(inner type, True) for Optional[inner], else (tp, False)."""
    if typing.get_origin(tp) is Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def _is(tp, x) -> bool:
    """x has type tp, strictly (no conversion)."""
    if tp is Any:
        return True
    if tp is bool:
        return isinstance(x, bool)
    if tp is int:
        return isinstance(x, int) and not isinstance(x, bool)
    if tp is float:
        return is_number(x)
    if tp is str:
        return isinstance(x, str)
    if typing.get_origin(tp) is Literal:
        return any(type(x) is type(a) and x == a for a in typing.get_args(tp))
    return False


def _desc(tp) -> str:
    if typing.get_origin(tp) is list:
        return {int: "a list of integers", float: "a list of finite numbers", str: "a list of strings"}.get(
            typing.get_args(tp)[0], "a list")
    return {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}.get(tp, "a value")


def _bounds(meta) -> str:
    parts = [f"{op} {meta[k]:g}" for k, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))
             if meta.get(k) is not None]
    return " and ".join(parts)


def _rule(tp, f) -> str:
    """What the field accepts, for the message."""
    meta = f.metadata
    if meta.get("rule"):
        return meta["rule"]
    tp, nullable = _optional(tp)
    if typing.get_origin(tp) is Literal:
        return f"choose one of {typing.get_args(tp)}"
    text = f"give {_desc(tp)}"
    b = _bounds(meta)
    if b:
        text += (" with items " if typing.get_origin(tp) is list else " ") + b
    if meta.get("unit"):
        text += f" [{meta['unit']}]"
    if meta.get("min_len"):
        text += f", at least {meta['min_len']}"
    return text + (", or null" if nullable else "")


def _example(f) -> str:
    ex = f.metadata.get("example", MISSING)
    if ex is MISSING:
        ex = f.default if f.default is not MISSING else (
            f.default_factory() if f.default_factory is not MISSING else None)
    return ex if isinstance(ex, str) else _override(ex)


def _override(v) -> str:
    """A value as a command-line override writes it."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_override(x) for x in v) + "]"
    if dataclasses.is_dataclass(v):
        return "{" + ",".join(f"{k}:{_override(x)}" for k, x in dataclasses.asdict(v).items()) + "}"
    return str(v)


def _show(v) -> str:
    """A bad value as the message quotes it (strings quoted: 'abc')."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, list):
        return "[" + ",".join(_show(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ",".join(f"{k}:{_show(x)}" for k, x in v.items()) + "}"
    return repr(v)


def _in_range(meta, x) -> bool:
    return not ((meta.get("gt") is not None and not x > meta["gt"])
                or (meta.get("ge") is not None and not x >= meta["ge"])
                or (meta.get("lt") is not None and not x < meta["lt"])
                or (meta.get("le") is not None and not x <= meta["le"]))


def _why(meta, items) -> str:
    """'not finite; ' or 'implausible magnitude; ' (above the key's upper bound) where that is the
    problem, else ''."""
    nums = [x for x in items if is_number(x)]
    if not all(math.isfinite(x) for x in nums):
        return "not finite; "
    upper = {k: meta.get(k) for k in ("lt", "le")}
    if not meta.get("rule") and any(not _in_range(upper, x) for x in nums):   # a rule says it itself
        return "implausible magnitude; "
    return ""


def _check_value(tp, value, f, key: str, label: str) -> None:
    meta = f.metadata
    inner, nullable = _optional(tp)
    if value is None:
        if nullable or inner is Any:
            return
        raise ConfigError(f"{key}=null: {_rule(tp, f)} (e.g. {key}={_example(f)})")
    if dataclasses.is_dataclass(inner):
        _check_node(inner, value, key, label)
        return
    if typing.get_origin(inner) is Literal:
        if not _is(inner, value):
            raise ConfigError(f"{key}={_show(value)}; choose one of {typing.get_args(inner)} "
                              f"(e.g. {key}={_example(f)})")
        return
    is_list = typing.get_origin(inner) is list
    item = typing.get_args(inner)[0] if is_list else inner
    items = value if is_list and isinstance(value, list) else [value]
    if (is_list and not isinstance(value, list)) or not all(_is(item, x) for x in items):
        raise ConfigError(f"{key}={_show(value)} is not {_desc(inner)}: {_rule(tp, f)} (e.g. {key}={_example(f)})")
    bad = is_list and len(value) < meta.get("min_len", 0)
    if item is float and not all(math.isfinite(x) for x in items):
        bad = True
    if is_number(items[0] if items else 0) and not all(_in_range(meta, x) for x in items):
        bad = True
    if bad:
        raise ConfigError(f"{key}={_show(value)}: {_why(meta, items)}{_rule(tp, f)} (e.g. {key}={_example(f)})")
    why = meta.get("check") and meta["check"](value)
    if why:
        sep = " " if why.startswith("is not") else ": "
        raise ConfigError(f"{key}={_show(value)}{sep}{why} (e.g. {key}={_example(f)})")
