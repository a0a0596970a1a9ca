"""One experiment's runs compared by the factors they vary (issue 23); no MLflow here.

:func:`comparison` takes the runs as MLflow's ``search_runs`` frame (columns ``tags.*``, ``params.*``,
``metrics.*``) and returns a table: one row per run, the factors that vary across the runs (structure,
inversion, regulariser, noise, ...) and the claim-relevant metrics in units that read (µm for positions),
sorted by the factors; and findings: every factor across which some runs give identical numbers, with
the reason. :func:`figure` draws the table; :func:`markdown` prints it. The sweep's parent run logs them
(``compare/comparison.csv|md|png``, :func:`pipeline.tracking.log_comparison`) and REPORT.md shows them.
"""
from __future__ import annotations

import fnmatch
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.plots import pyplot

#: candidate factors: (column, label), in the order they group the table
FACTORS = (("tags.invert", "inversion"), ("tags.model", "structure"), ("tags.regularizer", "regulariser"),
           ("params.system.noise.structure", "noise"), ("params.system.noise.std", "σ [m]"),
           ("params.regularizer.lam", "λ"), ("params.model.hidden", "hidden"), ("params.invert.gamma", "γ"),
           ("params.model.nn_inputs", "NN inputs"), ("params.invert.trial_noise", "trial noise"),
           ("params.identify.theta_star", "θ*"), ("tags.identify", "identification"), ("params.seed", "seed"))
#: the factor whose levels a figure shows side by side, coloured, with a legend
REGULARISER = "tags.regularizer"
#: why a factor leaves runs identical, where the stages know it: (factor column, where column, where
#: value, reason); checked against the numbers, never assumed
REASONS = (
    ("tags.regularizer", "tags.invert", "physics",
     "the physics feedforward (8) uses the baseline least-squares θ*_phy only: no trained model, so no "
     "regulariser acts"),
    ("tags.regularizer", "tags.model", "rational",
     "the orthogonal regulariser ([K] (29)-(30)) penalises the PGNN's approximator g_φ; the rational model has "
     "none, so SK solves the same problem with and without it"),
)
#: metric leaves in metres whose display twin is in µm (:func:`display_metrics`)
LENGTH_LEAVES = ("mae", "max_abs", "rms")
#: systems whose output is not a length (the ARX system of [B1] §II-C is dimensionless)
UNITLESS_SYSTEMS = ("arx_bias",)


def display_metrics(metrics: list[tuple[str, float, int | None]], system: str) -> list[tuple[str, float, int | None]]:
    """Twins of the metrics in units that read in the MLflow UI, the unit in the name: tracking errors
    in metres ``evaluate/<ref>/mae`` → ``evaluate/<ref>/mae_um`` [µm] (also ``max_abs``, ``rms``,
    ``max_abs_<phase>``), seconds per sample ``…/sample_seconds_<stat>`` → ``…/sample_seconds_<stat>_us`` [µs].
    The SI metrics stay (the report reads them)."""
    out = []
    for k, v, step in metrics:
        leaf = k.rsplit("/", 1)[-1]
        if (k.startswith("evaluate/") and system not in UNITLESS_SYSTEMS
                and (leaf in LENGTH_LEAVES or leaf.startswith("max_abs_"))):
            out.append((f"{k}_um", 1e6 * float(v), step))
        elif "/sample_seconds_" in k:   # the name keeps "seconds": timings stay recognisable as timings
            out.append((f"{k}_us", 1e6 * float(v), step))
    return out


def metric_columns(runs: pd.DataFrame, patterns: list[str]) -> list[str]:
    """The ``metrics.*`` columns matching ``patterns`` (globs on the metric name), in pattern order,
    each shown in its display unit (``_um``) where the runs have that twin."""
    names = [c[len("metrics."):] for c in runs.columns if c.startswith("metrics.")]
    out = []
    for p in patterns:
        for n in sorted(fnmatch.filter(names, p)):
            shown = f"{n}_um" if f"{n}_um" in names else n
            if f"metrics.{shown}" not in out and runs[f"metrics.{shown}"].notna().any():
                out.append(f"metrics.{shown}")
    return out


def _text(col: pd.Series) -> pd.Series:
    """A column as plain strings, a missing value as '' (pandas' ``astype(str)`` may keep NaN)."""
    return col.map(lambda v: "" if v is None or (isinstance(v, float) and np.isnan(v)) else str(v)).astype(object)


def varying_factors(runs: pd.DataFrame) -> list[tuple[str, str]]:
    """The candidate factors with more than one value across the runs; a param that only follows an
    earlier factor (``regularizer.lam`` with ``regularizer``) is left out."""
    out, seen = [], []
    for c, lbl in FACTORS:
        if c not in runs or _text(runs[c]).nunique(dropna=False) < 2:
            continue
        codes = tuple(pd.factorize(_text(runs[c]))[0])
        if c.startswith("params.") and any(codes == s for s in seen):
            continue
        seen.append(codes)
        out.append((c, lbl))
    return out


def _std_key(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("inf")


def comparison(runs: pd.DataFrame, patterns: list[str]) -> tuple[pd.DataFrame, list[str]]:
    """(table, findings): one row per run, its name, the varying factors and the matching metrics."""
    runs = runs.reset_index(drop=True)
    factors = varying_factors(runs)
    metrics = metric_columns(runs, patterns)
    name_col = "tags.mlflow.runName" if "tags.mlflow.runName" in runs else None
    table = pd.DataFrame({lbl: _text(runs[c]) for c, lbl in factors})
    if name_col:
        table.insert(0, "run", _text(runs[name_col]))
    for c in metrics:
        table[c[len("metrics."):]] = runs[c].astype(float)
    # the regulariser sorts last: a regularised run beside its unregularised twin (issue 52)
    keys = sorted(factors, key=lambda f: f[0] == REGULARISER)
    order = sorted(range(len(runs)), key=lambda i: tuple(
        (_std_key(runs.at[i, c]), "") if c.startswith("params.") and _std_key(runs.at[i, c]) != float("inf")
        else (0.0, str(runs.at[i, c])) for c, _ in keys))
    table = table.iloc[order].reset_index(drop=True)
    return table, identical(runs, factors, metrics)


def identical(runs: pd.DataFrame, factors: list[tuple[str, str]], metrics: list[str]) -> list[str]:
    """Findings: for each factor, the groups of runs (all other factors equal) whose metrics are equal
    to the bit across that factor's values, with the reason where the stages give one."""
    out = []
    metrics = [m for m in metrics if m.startswith("metrics.evaluate/")] or metrics   # the feedforward's numbers
    if not metrics:
        return out
    for col, lbl in factors:
        others = [c for c, _ in factors if c != col]
        same, differ = [], 0
        groups = runs.groupby([_text(runs[c]) for c in others], dropna=False) if others else [((), runs)]
        for key, g in groups:
            if _text(g[col]).nunique() < 2:
                continue
            vals = g[metrics].to_numpy(dtype=float)
            if np.all(np.isnan(vals) | (vals == vals[0])) and not np.isnan(vals).all():
                key = key if isinstance(key, tuple) else (key,)
                same.append(dict(zip(others, key)))
            else:
                differ += 1
        if not same:
            continue
        where = "; ".join(", ".join(f"{dict(FACTORS).get(c, c)} = {v}" for c, v in s.items()) or "all runs"
                          for s in same)
        reasons = sorted({why for f, wc, wv, why in REASONS if f == col
                          and all(str(s.get(wc)) == wv for s in same)})
        if not reasons:
            hashes = [runs.loc[(runs[others].apply(_text) == pd.Series(s)).all(axis=1), "tags.config_hash"]
                      for s in same] if "tags.config_hash" in runs and others else []
            reasons = ["the runs have the same config hash: the factor enters none of their stages"
                       if hashes and all(h.nunique() == 1 for h in hashes) else
                       "no stage records why: the factor does not change these numbers"]
        out.append(f"Identical across {lbl} ({', '.join(sorted(_text(runs[col]).unique()))}) where {where}"
                   f" ({len(same)} group(s); {differ} other group(s) differ): {'; '.join(reasons)}.")
    return out


def _fmt(v) -> str:
    if isinstance(v, (float, np.floating)):
        return "" if np.isnan(v) else f"{v:.4g}"
    return str(v)


def markdown(table: pd.DataFrame, findings: list[str]) -> str:
    """The table as markdown (metric columns named with their unit), then the findings."""
    cols = list(table.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
    for _, r in table.iterrows():
        lines.append("| " + " | ".join(_fmt(r[c]).replace("|", "\\|") for c in cols) + " |")
    if findings:
        lines += [""] + [f"- {f}" for f in findings]
    return "\n".join(lines) + "\n"


def figure(table: pd.DataFrame, path: Path, title: str = "") -> Path | None:
    """One panel per metric: a horizontal bar per run (labelled by its name, the varying part first), its
    value written at the bar's end, on a log scale where the values span more than a decade. Bars are
    coloured by the regulariser where it varies (its twins sit side by side, :func:`comparison`), else by
    the first factor, with a legend (issue 52)."""
    plt = pyplot()
    metrics = [c for c in table.columns if pd.api.types.is_float_dtype(table[c])]
    if not metrics or table.empty:
        return None
    labels = table["run"].str.split(" | ", regex=False).str[0] if "run" in table else table.index.astype(str)
    n = len(table)
    fig, axes = plt.subplots(1, len(metrics), figsize=(2.6 + 3.0 * len(metrics), 1.4 + 0.26 * n),
                             sharey=True, squeeze=False)
    y = np.arange(n)
    first = [c for c in table.columns if c not in metrics and c != "run"]
    by = "regulariser" if "regulariser" in first else (first[0] if first else None)
    colour_by = table[by] if by else pd.Series([""] * n)
    palette = {v: f"C{i % 10}" for i, v in enumerate(dict.fromkeys(colour_by))}
    for ax, m in zip(axes[0], metrics):
        vals = table[m].to_numpy(dtype=float)
        bars = ax.barh(y, np.where(np.isnan(vals), 0, vals), color=[palette[v] for v in colour_by])
        ax.bar_label(bars, labels=["" if np.isnan(v) else f"{v:.3g}" for v in vals], fontsize=6, padding=2)
        pos = vals[np.isfinite(vals) & (vals > 0)]
        if pos.size and pos.max() / pos.min() > 10:
            ax.set_xscale("log")
        ax.margins(x=0.25)   # room for the values
        ax.set_title(m.replace("_um", " [µm]").replace("_us", " [µs]"), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    axes[0, 0].set_yticks(y, labels, fontsize=7)
    axes[0, 0].invert_yaxis()
    if by and len(palette) > 1:
        handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in palette.values()]
        fig.legend(handles, [str(v) for v in palette], title=by, fontsize=7, title_fontsize=7,
                   loc="upper right", ncol=min(len(palette), 4), frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    with warnings.catch_warnings():   # long run names: matplotlib says it could not shrink further
        warnings.simplefilter("ignore", UserWarning)
        fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path


def loss_overlay(curves: dict[str, list[float]], path: Path, title: str = "") -> Path:
    """One sweep's training losses on one log-scale axes (issue 52): per run the curve of its best restart,
    against the accepted step, labelled by its name's varying part, the legend in the sort order of
    :func:`natural_key`."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 4.8))
    for name in sorted(curves, key=natural_key):
        v = np.asarray(curves[name], dtype=float)
        ax.plot(np.arange(v.size), v, lw=1.2, label=name.split(" | ")[0])
    ax.set_yscale("log")
    ax.set_xlabel("accepted step")
    ax.set_ylabel("training loss (best restart)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=6, ncol=2 if len(curves) > 12 else 1, loc="center left", bbox_to_anchor=(1.01, 0.5))
    if title:
        ax.set_title(title, fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def natural_key(text: str) -> tuple:
    """Sort key that reads numbers as numbers: n1 < n8 < n16 < n32, σ1e-7 < σ1e-6 (issue 52)."""
    parts = re.split(r"(\d+(?:\.\d+)?(?:e[+-]?\d+)?)", str(text))
    return tuple((0, float(p), "") if i % 2 else (1, 0.0, p) for i, p in enumerate(parts))
