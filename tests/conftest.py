"""Shared fixtures: an isolated cache + MLflow store per test, and Hydra's compose API."""
from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pipeline  # noqa: F401  (first: it pins the code paths before numpy, torch and numba load; issue 52)
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"

from pipeline import schema  # noqa: E402

schema.register()   # every key's default for Hydra's compose (as pipeline/__main__.py does)

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


@pytest.fixture
def cfg_of():
    """``cfg_of(*overrides)`` composes the real config tree like the CLI does."""
    def make(*overrides):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            return compose(config_name="config", overrides=list(overrides))
    yield make
    GlobalHydra.instance().clear()
