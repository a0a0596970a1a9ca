"""Generic report section: per run, the identified physical parameters, the tracking metrics per
evaluation reference, ILC results, and the run's figures."""
from __future__ import annotations

from pathlib import Path

import pandas as pd

from stages.report._figures import copy_figures
from stages.report._rows import row, run_metrics

EXPERIMENTS = ("physics_baseline",)
EVAL_METRICS = ("mae", "max_abs", "rms", "sq_norm2", "ff_error_rel")


def section(experiment: str, runs: pd.DataFrame, figdir: Path):
    rows, lines = [], [f"## {experiment}", "",
                       "Physics baselines of every plant (SPEC §2–§4): closed-form least squares of "
                       "the nominal physics model, its feedforward scored on the true plant "
                       "(noise-free evaluation runs), and ILC where configured.", ""]
    for _, run in runs.sort_values("tags.mlflow.runName").iterrows():
        variant = run["tags.mlflow.runName"]
        m = run_metrics(run)
        lines += [f"### {variant}", ""]
        for tag in ("physics_warning", "reference_warning", "envelope_warning"):
            warn = run.get(f"tags.{tag}")
            if isinstance(warn, str) and warn:
                lines += [f"> Warning: {warn}", ""]
        params = {k.split("/", 1)[1]: v for k, v in sorted(m.items())
                  if k.startswith("baseline/") and not k.startswith("baseline/rel_error")}
        if params:
            lines += ["| parameter | " + " | ".join(params) + " |",
                      "| --- |" + " --- |" * len(params),
                      "| estimate | " + " | ".join(f"{v:.5g}" for v in params.values()) + " |", ""]
            rows += [row(experiment, variant, f"baseline/{k}", v) for k, v in params.items()]
        refs = sorted({k.split("/")[1] for k in m if k.startswith("evaluate/")})
        if refs:
            present = [x for x in EVAL_METRICS if any(f"evaluate/{r}/{x}" in m for r in refs)]
            lines += ["| reference | " + " | ".join(present) + " |",
                      "| --- |" + " --- |" * len(present)]
            for r in refs:
                vals = [m.get(f"evaluate/{r}/{x}") for x in present]
                lines.append(f"| {r} | " + " | ".join("" if v is None else f"{v:.4g}" for v in vals) + " |")
                rows += [row(experiment, f"{variant}/{r}", x, v) for x, v in zip(present, vals)
                         if v is not None]
            lines.append("")
        ilc = {k.split("/")[2]: v for k, v in m.items()
               if k.startswith("generate/ilc/") and k.endswith("/final_rms")}
        for ref, v in ilc.items():
            lines.append(f"ILC on `{ref}`: final rms error {v:.3g} m "
                         f"(per-trial curve: metric `generate/ilc/{ref}/rms`).")
            rows.append(row(experiment, f"{variant}/{ref}", "ilc_final_rms", v))
        for fig in copy_figures(run["run_id"], figdir, f"{experiment}-{variant}"):
            lines += ["", f"![{Path(fig).stem}]({fig})"]
        lines.append("")
    return rows, "\n".join(lines)
