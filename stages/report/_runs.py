"""An experiment's runs as the report reads them: the latest finished run per run name, keyed by
its stable name, and the side studies split off (shared by stages.report and its section providers)."""
from __future__ import annotations

import pandas as pd

from pipeline import tracking


def latest_runs(experiment: str) -> tuple[pd.DataFrame, list[str]]:
    """Latest finished run per run name (sweep parents excluded), and the run names whose
    finished runs carry more than one config hash (the report uses the latest; say so)."""
    df = _identity(tracking.search_runs(experiment))
    if df.empty:
        return df, []
    if "tags.sweep" in df:
        df = df[df["tags.sweep"] != "parent"]
    mixed = []
    if "tags.config_hash" in df:
        n = df.groupby("tags.mlflow.runName")["tags.config_hash"].nunique()
        mixed = sorted(n[n > 1].index)
    return df.drop_duplicates("tags.mlflow.runName", keep="first").reset_index(drop=True), mixed


def _identity(df: pd.DataFrame) -> pd.DataFrame:
    """Runs keyed by their ``run_key`` tag (the stable name; issue 23), their MLflow run name kept as
    ``tags.display_name``: the sections and summary.csv keys read ``tags.mlflow.runName`` as before.
    Runs made before the tag keep their MLflow name as key."""
    if df.empty or "tags.run_key" not in df:
        return df
    df = df.copy()
    df["tags.display_name"] = df["tags.mlflow.runName"]
    df["tags.mlflow.runName"] = df["tags.run_key"].where(df["tags.run_key"].notna(), df["tags.mlflow.runName"])
    return df


#: side studies inside an experiment, reported beside its claims but not in them (their own rows):
#: experiment -> (column, value) of the side runs
SIDE = {"b1_linear_motor": ("tags.regularizer", "none")}


def split_side(experiment: str, runs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(headline runs, side-study runs) of an experiment (:data:`SIDE`)."""
    col, val = SIDE.get(experiment, (None, None))
    if col is None or runs.empty or col not in runs:
        return runs, runs.iloc[0:0]
    side = runs[col].astype(object) == val
    return runs[~side].reset_index(drop=True), runs[side].reset_index(drop=True)
