"""The summary.csv row and a run's metrics, shared by every section provider (DESIGN contracts)."""
from __future__ import annotations

import pandas as pd

from pipeline.perturbation import FIT_CAP_METRIC, FIT_METRIC


def row(experiment, variant, metric, value, *, paper=None) -> dict:
    """One summary.csv row, without a verdict: the claim table (stages/report/claims.py, ``judge``)
    gives the rows it names their SPEC §8 id, ``claim_holds`` and paper value."""
    return {"experiment": experiment, "claim": "", "variant": variant, "metric": metric,
            "value": float(value), "paper_value": paper, "claim_holds": None}


def run_metrics(run: pd.Series) -> dict[str, float]:
    """``{<stage>/<name>: value}`` of the run's logged metrics (missing ones left out)."""
    return {c[len("metrics."):]: float(run[c]) for c in run.index
            if c.startswith("metrics.") and pd.notna(run[c])}


def fit_cost_row(experiment, variant, metrics: dict, key: str = "train/cost") -> list[dict]:
    """The ``fit_cost`` row of a trained model (its training cost; [] if the run has none) and, where
    the run logged it, its ``fit_stopped_on_cap`` row: the reproduce checks (pipeline/perturbation.py)
    tell from them whether a fit landed elsewhere, and whether it had converged where it landed."""
    v = metrics.get(key)
    if v is None:
        return []
    capped = metrics.get("train/stopped_on_cap")     # 1: the kept fit stopped on a cap, not a tolerance
    return [row(experiment, variant, FIT_METRIC, v)] + \
        ([] if capped is None else [row(experiment, variant, FIT_CAP_METRIC, capped)])
