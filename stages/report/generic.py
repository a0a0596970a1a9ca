"""Generic report section: one table row per run with its evaluation and baseline metrics."""
from __future__ import annotations

from pathlib import Path

import pandas as pd

from stages.report._figures import copy_figure

EXPERIMENTS = ("physics_baseline",)


def section(experiment: str, runs: pd.DataFrame, figdir: Path):
    rows, lines = [], [f"## {experiment}", ""]
    metric_cols = [c for c in runs.columns if c.startswith("metrics.") and
                   (c.startswith("metrics.evaluate/") or c.startswith("metrics.baseline/"))
                   and not c.endswith("seconds_per_sample")]
    for _, run in runs.iterrows():
        variant = run["tags.mlflow.runName"]
        lines += [f"### {variant}", "", "| metric | value |", "| --- | --- |"]
        for c in sorted(metric_cols):
            if pd.notna(run[c]):
                metric = c[len("metrics."):]
                rows.append({"experiment": experiment, "claim": "", "variant": variant,
                             "metric": metric, "value": float(run[c]), "paper_value": None,
                             "claim_holds": None})
                lines.append(f"| {metric} | {run[c]:.6g} |")
        lines.append("")
        fig = copy_figure(run["run_id"], "figures/tracking_error.png", figdir,
                          f"{experiment}-{variant}-tracking_error.png")
        if fig:
            lines += [f"![tracking error]({fig})", ""]
    return rows, "\n".join(lines)
