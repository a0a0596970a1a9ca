"""Shared fixtures: an isolated cache + MLflow store per test, and Hydra's compose API."""
from __future__ import annotations

import atexit
import copy
import functools
import hashlib
import os
import shutil
import sqlite3
import tempfile
from pathlib import Path

import pipeline  # noqa: F401  (first: it pins the code paths before numpy, torch and numba load; issue 52)
import pytest
from hydra import compose, initialize_config_dir
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import OverrideType

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"

from pipeline import schema  # noqa: E402
from pipeline.export import package as _package  # noqa: E402

schema.register()   # every key's default for Hydra's compose (as pipeline/__main__.py does)

_compile_harness = _package.compile_harness
_HARNESSES = Path(tempfile.mkdtemp(prefix="pgnn-harness-"))   # this test process's built harnesses
atexit.register(shutil.rmtree, _HARNESSES, True)


def _built_once(folder: Path, name: str, cc: str) -> Path:
    """``compile_harness`` once per content: some of the suite's harnesses are built from C sources it has
    already compiled (a package exported, then run on other references, or exported again in another folder:
    28 of the 260 compiler runs of the C-heavy files); the executable of the same compiler, flags,
    ``main_<name>.c``, ``<name>.c`` and headers is copied instead of compiled again (~0.35 s of gcc each)."""
    folder = Path(folder)
    parts = [cc.encode(), " ".join(_package.CFLAGS).encode(), name.encode()]
    for f in [folder / f"main_{name}.c", folder / f"{name}.c", *sorted(folder.glob("*.h"))]:
        parts += [f.name.encode(), f.read_bytes()]
    kept = _HARNESSES / hashlib.sha256(b"\0".join(parts)).hexdigest()
    exe = folder / f"main_{name}"
    if kept.exists():
        shutil.copy2(kept, exe)
        return exe
    exe = _compile_harness(folder, name, cc)
    shutil.copy2(exe, kept.with_suffix(".tmp"))
    os.replace(kept.with_suffix(".tmp"), kept)
    return exe


_package.compile_harness = _built_once   # before the test modules import it (write_package calls it too)

#: a short two-mass training set: one [K] out-and-back move (~0.9 s)
SHORT_TWO_MASS = [
    "experiment=physics_two_mass",
    "data.references=[{name:short,kind:out_and_back,distance:0.02,v_max:0.05,a_max:5,j_max:200}]",
    "evaluate.references=[{name:held,kind:out_and_back,distance:0.03,v_max:0.05,a_max:5,j_max:200}]",
]


@pytest.fixture(scope="session")
def empty_mlflow_db(tmp_path_factory) -> Path:
    """One empty MLflow SQLite store per test process, its schema made once: MLflow creates a store by
    running every one of its schema migrations (~3 s a store, measured: 23 in-process stores took 74 s of
    the suite); a test's store starts as a copy of this one (:func:`copy_empty_mlflow_db`)."""
    import mlflow   # lazy: only tests with a store pay MLflow's import
    db = tmp_path_factory.mktemp("mlflow-empty") / "mlflow.db"
    mlflow.MlflowClient(f"sqlite:///{db}").search_experiments()   # creates the tables, migrates, closes
    return db


def copy_empty_mlflow_db(template: Path, folder: Path) -> Path:
    """``folder/mlflow.db``: a copy of the migrated empty store, as MLflow would create it there (its
    ``Default`` experiment's artifacts in ``folder/mlruns/0``, not beside the template)."""
    db = folder / "mlflow.db"
    shutil.copyfile(template, db)
    with sqlite3.connect(db) as con:
        con.execute("UPDATE experiments SET artifact_location = ? WHERE experiment_id = 0",
                    (str(folder / "mlruns" / "0"),))
    con.close()
    return db


@pytest.fixture
def fresh_store(tmp_path, monkeypatch):
    """Point the stage cache and the MLflow store at a temporary folder; MLflow creates the store there."""
    monkeypatch.setenv("PIPELINE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(tmp_path / "cache.key"))
    return tmp_path


@pytest.fixture
def store(fresh_store, empty_mlflow_db):
    """:func:`fresh_store` with the MLflow store made beforehand (a copy of the empty one)."""
    copy_empty_mlflow_db(empty_mlflow_db, fresh_store)
    return fresh_store


def hydra_compose(*overrides, hydra: bool = False):
    """Hydra's own compose of conf/ with ``overrides``, afresh (``hydra``: with the ``hydra`` node, which
    also holds the working directory: :func:`hydra_config` keeps those)."""
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            return compose(config_name="config", overrides=list(overrides), return_hydra_config=hydra)
    finally:
        GlobalHydra.instance().clear()


@functools.lru_cache(maxsize=None)
def _composed(overrides: tuple[str, ...], hydra: bool = False, cwd: str = ""):
    return hydra_compose(*overrides, hydra=hydra)


def hydra_config(*overrides):
    """:func:`hydra_compose` with the ``hydra`` node (a sweep's params), composed once per test process and
    working directory; a copy."""
    return copy.deepcopy(_composed(tuple(overrides), True, os.getcwd()))


def _is_group(key: str) -> bool:
    return key.startswith(("hydra", "_params")) or (CONF / key.replace(".", "/")).is_dir()


def compose_config(*overrides):
    """The config the CLI composes from ``overrides`` (without the ``hydra`` node), as
    :func:`hydra_compose` gives it, for less: the suite composes ~300 times at ~0.3 s of CPU each, a
    quarter of its CPU. The defaults tree of the leading overrides is composed once per test process;
    the trailing plain ``key=value`` overrides (no group, no ``+``/``~``, no sweep) are applied to a copy
    by the function Hydra's compose applies them with after the defaults list
    (``ConfigLoaderImpl._apply_overrides_to_config``), in their order, with its errors.
    tests/test_config_schema.py checks both give the same config and the same errors."""
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    n = composed_prefix(parsed)
    cfg = copy.deepcopy(_composed(tuple(overrides[:n])))
    ConfigLoaderImpl._apply_overrides_to_config(parsed[n:], cfg)
    return cfg


def composed_prefix(parsed: list) -> int:
    """How many of the parsed overrides :func:`compose_config` composes (the rest it applies)."""
    n = len(parsed)
    while n and parsed[n - 1].type == OverrideType.CHANGE and parsed[n - 1].package is None \
            and not parsed[n - 1].is_sweep_override() and not _is_group(parsed[n - 1].key_or_group):
        n -= 1
    return n


@pytest.fixture
def cfg_of():
    """``cfg_of(*overrides)`` composes the real config tree like the CLI does (:func:`compose_config`)."""
    yield compose_config
    GlobalHydra.instance().clear()
