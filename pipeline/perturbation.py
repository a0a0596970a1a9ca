"""Same numbers on another machine? Compare a perturbed ``make reproduce`` with the reference one.

``make reproduce-check`` reruns every experiment with ``PIPELINE_PERTURB`` set: every LM step's
normal equations JᵀJ and Jᵀr are multiplied by (1 + ε u), u uniform in [-1, 1] and seeded per step
(:func:`pipeline.identify.lm._perturb_normal_equations`), which emulates another BLAS summation
order on a second machine (ε = 1e-13: a few hundred ulps, larger than any machine difference).
A fit that stopped on a tolerance lands where the reference landed; a fit that stopped on a slope
(an iteration cap, an unresolved choice between restarts) lands elsewhere, and its values move.

    python -m pipeline.perturbation REFERENCE.csv PERTURBED.csv [--out DIR] [--rtol 0.02] [--check perturb|tighten]

``make reproduce-check CHECK=tighten`` does the same with every LM and SK tolerance divided by 10
(``PIPELINE_TIGHTEN``): a converged fit's values must not move (by more than 1 %).

writes ``DIR/check-<check>.csv`` (per summary key: both values and the relative change) and
``DIR/check-<check>.md`` (per experiment: values compared, the largest relative change and its key,
how many moved by more than ``rtol``, the claim verdicts that changed (a claim holds when all its
rows hold) and the claim rows whose verdict changed).  Timings are left out.

A check of a subset (``EXPERIMENTS=...``) replaces its experiments' rows and keeps the others':
``DIR/check-<check>.json`` records, per experiment, the sha256 of the reference rows it compared
(:func:`experiment_digests`), so the report shows an experiment's check only while its reference
rows are unchanged and names the others stale.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd

KEY = ["experiment", "claim", "variant", "metric"]
#: a value below this fraction of the largest |value| of its metric for its model (the variant's first
#: part) in its experiment is *tiny*: its relative change is measured against that floor (a tracking
#: error of 1e-12 where the same model's error on another reference is 1e-6); one that still moves
#: is reported as ill-determined, with its spread (both values), not counted as moved
SCALE_FLOOR = 1e-3
#: the summary row of a trained model's training cost (what its fit minimised); a value row belongs to
#: the fit whose variant is its longest '/'-prefix (``equation/sigma1e-08/direct`` for
#: ``equation/sigma1e-08/direct/v0.05``)
FIT_METRIC = "fit_cost"
#: two fits whose training costs agree to this fraction are equally good fits of the same data: a value
#: computed from them that still moves is not determined by the data (the nonconvex fit has several
#: parameter vectors of that cost: different tracking errors at one training error), reported as
#: ill-determined with its spread. A fit whose cost moved more than this landed somewhere else: its
#: values count as moved
FIT_RTOL = 1e-3
#: the summary row saying whether a trained model's fit stopped on a cap (1) or on a tolerance (0). A fit
#: that stopped on a tolerance on both sides but at training costs further apart than FIT_RTOL converged to
#: two different local minima of its nonconvex criterion: which one a machine reaches is decided by
#: rounding along thousands of steps (measured on [B2] n1 = 16: four restarts run to their stops end at
#: 1.2e-8 to 2.9e-8, another draw at 7e-10). Its values are ill-determined (*other minimum*), spread
#: given; a fit that stopped on a cap on either side landed on a slope: its values count as moved
FIT_CAP_METRIC = "fit_stopped_on_cap"
#: metrics that measure the machine, not the result
_TIMING = ("seconds", "time", "wall", "_ms", "per_sample_ns", "ns_per_sample")
#: metrics that describe the solver's path, not its result: iteration counts, the last step's size, the
#: tolerance itself (a setting: tightened on purpose), which SK rule stopped a fit whose result is its best
#: iterate either way (``sk_stopped_on_tol``: its fixed-point test or the stall), a check LM's remaining gain,
#: and rounding-level differences of the exported C/Python laws from the study (1e-15 -> 2e-15 is not a
#: result moving) and of exact identities ([B2] Lemmas 5.1/5.2, B2e: 6.9e-17 -> 9.2e-16 between two CPUs;
#: the claim's verdict on them, <= 1e-8, is still compared)
_SOLVER_PATH = ("iterations", "rel_change", "sk_tol", "sk_stopped_on_tol", "oe_check_max_iter", "oe_check_improvement",
                "c_max_rel_diff", "python_max_rel_diff", "relative_difference")


#: the categories of values the data (tiny, equal_fit) or the landscape (other_minimum) do not determine
ILL_DETERMINED = ("tiny", "equal_fit", "other_minimum")
#: a ratio of two fits named after both, variant ``A_over_B/...`` and metric ``S_ratio`` (K2's
#: ``none_over_orthogonal`` spread ratio), is computed from the rows of metric S of fits A and B (a fit
#: whose variant is A or ends in ``_A``). To first order its relative change is at most the sum of its
#: inputs' largest changes; one that moved within that bound while an input is ill-determined is
#: ill-determined like that input (its spread: both values)
RATIO_SEP, RATIO_SUFFIX = "_over_", "_ratio"


def is_timing(metric: str) -> bool:
    m = metric.lower()
    return any(t in m for t in _TIMING)


def _is_solver_path(metric: str) -> bool:
    return any(t in metric for t in _SOLVER_PATH)


def _fit_of(variants: pd.Series, fits: set[str]) -> list[str]:
    """Per variant, the longest '/'-prefix of it that is a fit's variant ('' if none)."""
    out = []
    for v in variants:
        parts, hit = str(v).split("/"), ""
        for n in range(len(parts), 0, -1):
            if "/".join(parts[:n]) in fits:
                hit = "/".join(parts[:n])
                break
        out.append(hit)
    return out


def _ratio_sides(variant: str, metric: str, fits: set[str]) -> tuple[list[str], list[str]] | None:
    """The fits of a ratio row named after both (``A_over_B/...``, metric ``S_ratio``), or None."""
    head = variant.split("/")[0]
    if not metric.endswith(RATIO_SUFFIX) or RATIO_SEP not in head:
        return None
    sides = [[f for f in sorted(fits) if f == n or f.endswith("_" + n)] for n in head.split(RATIO_SEP, 1)]
    return (sides[0], sides[1]) if all(sides) else None


def _inherit_from_inputs(m: pd.DataFrame, cat: np.ndarray) -> np.ndarray:
    """Moved ratio rows of two fits (RATIO_SEP) that their inputs' changes explain, with an ill-determined
    input: that input's category (the one of the largest change)."""
    cat = pd.Series(cat, index=m.index)
    for _, g in m.groupby("experiment", sort=False):
        fits = set(g["fit"]) - {""}
        for ix, row in g[(cat[g.index] == "moved") & (g["fit"] == "")].iterrows():
            sides = _ratio_sides(str(row["variant"]), str(row["metric"]), fits)
            if sides is None:
                continue
            stem = str(row["metric"])[: -len(RATIO_SUFFIX)]
            inputs = [g[(g["metric"] == stem) & g["fit"].isin(side)] for side in sides]
            if any(i.empty for i in inputs):
                continue
            bound = sum(float(i["rel_change"].max()) for i in inputs)   # first order, for a quotient
            both = pd.concat(inputs)
            ill = both[cat[both.index].isin(ILL_DETERMINED)]
            if len(ill) and float(row["rel_change"]) <= bound * (1 + 1e-9):
                cat[ix] = cat[ill["rel_change"].idxmax()]
    return cat.to_numpy()


def compare(reference: pd.DataFrame, perturbed: pd.DataFrame, rtol: float = 0.02) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per key (reference value, perturbed value, relative change, category) and per experiment a summary.

    The relative change is |a - b| / max(|a|, |b|, floor) (0 when both are 0, 1 when one is NaN and
    the other not), floor = SCALE_FLOOR × the largest |reference value| of the same metric for the
    same model (first part of the variant) in the same experiment.  Categories: ``solver_path``
    (iterations, step sizes, tolerances: listed, not compared); ``tiny`` (within ``rtol`` of the floor,
    not of itself: ill-determined); ``equal_fit`` (moved by more than ``rtol``, but the fit it comes
    from reached the same training cost to FIT_RTOL on both sides: ill-determined by the data);
    ``other_minimum`` (moved; its fit's cost moved by more than FIT_RTOL, but that fit stopped on a
    tolerance on both sides: two local minima, FIT_CAP_METRIC); ``moved``; ``same``.  Keys on one
    side only are counted per experiment (``keys_on_one_side``),
    not compared; only the experiments of ``perturbed`` are compared (a check of a subset)."""
    b = perturbed.copy()
    a = reference[reference["experiment"].isin(set(b["experiment"]))].copy()   # a subset rerun: its experiments
    for d in (a, b):
        d[KEY] = d[KEY].astype(object).fillna("")
    m = a.merge(b, on=KEY, how="outer", suffixes=("_ref", "_pert"), indicator=True)
    m = m[~m["metric"].map(is_timing)]
    va = pd.to_numeric(m["value_ref"], errors="coerce").to_numpy(float)
    vb = pd.to_numeric(m["value_pert"], errors="coerce").to_numpy(float)
    model = m["variant"].fillna("").astype(str).str.split("/").str[0].to_numpy()   # the model (or system) of the row
    scale = pd.Series(np.abs(va)).groupby([m["experiment"].to_numpy(), model, m["metric"].to_numpy()]).transform("max")
    floor = SCALE_FLOOR * np.nan_to_num(scale.to_numpy(float))
    with np.errstate(invalid="ignore", divide="ignore"):
        big = np.maximum(np.abs(va), np.abs(vb))
        den = np.maximum(big, floor)
        rel = np.where(den > 0, np.abs(va - vb) / den, 0.0)
        rel_raw = np.where(big > 0, np.abs(va - vb) / big, 0.0)
    both_nan = np.isnan(va) & np.isnan(vb)
    rel = np.where(both_nan, 0.0, np.where(np.isnan(va) | np.isnan(vb), 1.0, rel))
    one_side = m["_merge"].to_numpy() != "both"
    m = m.assign(rel_change=np.where(one_side, np.nan, rel), rel_raw=rel_raw)
    missing = m[one_side].groupby("experiment").size()
    m = m[~one_side].copy()
    # the fit each value comes from, and how far that fit's training cost moved
    fit_rows = m[m["metric"] == FIT_METRIC]
    fit_change = {(e, v): c for e, v, c in zip(fit_rows["experiment"], fit_rows["variant"], fit_rows["rel_change"])}
    m["fit"] = ""
    for exp, g in m.groupby("experiment", sort=False):
        fits = {v for (e, v) in fit_change if e == exp}
        m.loc[g.index, "fit"] = _fit_of(g["variant"], fits) if fits else ""
    m["fit_rel_change"] = [fit_change.get((e, f), np.nan) if f else np.nan
                           for e, f in zip(m["experiment"], m["fit"])]
    r, rr = m["rel_change"].to_numpy(float), m["rel_raw"].to_numpy(float)
    nan_one = m["value_ref"].isna().to_numpy() | m["value_pert"].isna().to_numpy()
    cat = np.where(r > rtol, "moved", np.where((rr > rtol) & ~nan_one, "tiny", "same"))
    equal_fit = (cat == "moved") & (m["fit_rel_change"].to_numpy(float) <= FIT_RTOL) & (m["metric"] != FIT_METRIC)
    cat = np.where(equal_fit, "equal_fit", cat)
    # both sides' fits stopped on a tolerance, in different minima (FIT_CAP_METRIC); unknown: not classified
    caps = m[m["metric"] == FIT_CAP_METRIC]
    converged = {(e, v) for e, v, a, b in zip(caps["experiment"], caps["variant"], caps["value_ref"],
                                              caps["value_pert"]) if float(a) == 0.0 and float(b) == 0.0}
    other_min = (cat == "moved") & (m["fit_rel_change"].to_numpy(float) > FIT_RTOL) & \
        np.array([(e, f) in converged for e, f in zip(m["experiment"], m["fit"])], dtype=bool)
    cat = np.where(other_min, "other_minimum", cat)
    cat = _inherit_from_inputs(m, cat)
    cat = np.where(m["metric"].map(_is_solver_path).to_numpy(bool), "solver_path", cat)
    m["category"] = cat
    m["ill_determined"] = np.isin(cat, ILL_DETERMINED)
    cols = KEY + ["value_ref", "value_pert", "rel_change", "category", "ill_determined", "fit", "fit_rel_change",
                  "claim_holds_ref", "claim_holds_pert"]
    keys = m[cols]
    return keys, summarise(keys, rtol, missing.to_dict())


def summarise(keys: pd.DataFrame, rtol: float, one_side: dict | None = None) -> pd.DataFrame:
    """Per experiment, from :func:`compare`'s keys (or check-<check>.csv): result values compared, the
    largest relative change among them and its key, how many moved, how many are ill-determined (tiny,
    equal fits, other minimum), how many fits landed elsewhere (training cost moved > FIT_RTOL), claim
    verdicts changed (a claim holds when every one of its rows holds) and claim rows changed."""
    one_side = one_side or {}
    rows = []
    for exp, g in keys.groupby("experiment", sort=False):
        cat = g["category"].astype(str)
        res = g[cat != "solver_path"]
        counted = res[cat[res.index] == "moved"]
        pool = counted if len(counted) else res
        worst = pool.sort_values("rel_change", kind="stable").iloc[-1] if len(pool) else None
        fits = g[g["metric"] == FIT_METRIC]
        verdicts = claim_verdicts(g)
        claims_changed = int((verdicts["holds_ref"] != verdicts["holds_pert"]).sum())
        rows.append({"experiment": exp, "values": len(res),
                     "max_rel_change": float(pool["rel_change"].max()) if len(pool) else 0.0,
                     "worst_key": "" if worst is None else
                     "|".join(str(x) for x in (worst["claim"], worst["variant"], worst["metric"])
                              if isinstance(x, str) and x),
                     "n_above_rtol": int(len(counted)),
                     "n_ill_determined": int((cat == "tiny").sum()),
                     "n_equal_fit": int((cat == "equal_fit").sum()),
                     "n_other_minimum": int((cat == "other_minimum").sum()),
                     "fits_moved": f"{int((fits['rel_change'] > FIT_RTOL).sum())} of {len(fits)}",
                     "n_solver_path": int((cat == "solver_path").sum()),
                     "verdicts_changed": claims_changed,
                     "claim_rows_changed": int(verdicts["rows_changed"].map(len).sum()),
                     "keys_on_one_side": int(one_side.get(exp, 0))})
    return pd.DataFrame(rows)


def claim_verdicts(keys: pd.DataFrame) -> pd.DataFrame:
    """Per (experiment, claim) of :func:`compare`'s keys: the verdict on both sides (a claim holds when every
    one of its rows holds) and the claim rows whose verdict changed (``rows_changed``: a list of key rows)."""
    cols = ["experiment", "claim", "holds_ref", "holds_pert", "rows_changed"]
    if "claim_holds_ref" not in keys:
        return pd.DataFrame(columns=cols)
    claimed = keys[keys["claim"].fillna("").astype(str) != ""]
    rows = []
    for (exp, claim), g in claimed.groupby(["experiment", "claim"], sort=False):
        ref, pert = (g[f"claim_holds_{s}"].astype(str).str.lower() == "true" for s in ("ref", "pert"))
        rows.append({"experiment": exp, "claim": claim, "holds_ref": bool(ref.all()), "holds_pert": bool(pert.all()),
                     "rows_changed": [r for _, r in g[ref != pert].iterrows()]})
    return pd.DataFrame(rows, columns=cols)


def capped_fits(keys: pd.DataFrame) -> pd.DataFrame:
    """Per fit that stopped on its cap in the reference run (``fit_stopped_on_cap`` 1): its training
    cost on both sides and the largest relative change of its result values (solver-path values left
    out). In the tightening check (caps times CAPS) this is how far the capped fit still had to go."""
    rows = []
    flags = keys[(keys["metric"] == FIT_CAP_METRIC) & (pd.to_numeric(keys["value_ref"], errors="coerce") == 1)]
    for exp, fit in zip(flags["experiment"], flags["variant"]):
        g = keys[(keys["experiment"] == exp) & (keys["fit"] == fit)]
        cost = g[g["metric"] == FIT_METRIC]
        vals = g[~g["metric"].isin((FIT_METRIC, FIT_CAP_METRIC)) & (g["category"].astype(str) != "solver_path")]
        pert_flag = g.loc[g["metric"] == FIT_CAP_METRIC, "value_pert"]
        rows.append({"experiment": exp, "fit": fit,
                     "cost_ref": float(cost["value_ref"].iloc[0]) if len(cost) else np.nan,
                     "cost_pert": float(cost["value_pert"].iloc[0]) if len(cost) else np.nan,
                     "still_capped": bool(len(pert_flag) and float(pert_flag.iloc[0]) == 1),
                     "n_values": len(vals), "max_value_change": float(vals["rel_change"].max()) if len(vals) else 0.0})
    return pd.DataFrame(rows, columns=["experiment", "fit", "cost_ref", "cost_pert", "still_capped", "n_values",
                                       "max_value_change"])


def capped_lines(keys: pd.DataFrame, check: str) -> list[str]:
    """The paragraph on the fits that stopped on their cap (empty without one)."""
    c = capped_fits(keys)
    if c.empty:
        return []
    what = "run on with their caps raised" if check == "tighten" else "rerun"
    items = [f"`{r.experiment}` `{r.fit}`: training cost {r.cost_ref:.4g} → {r.cost_pert:.4g}"
             f"{' (on its cap again)' if r.still_capped else ''}, its {r.n_values} values move by up to "
             f"{r.max_value_change:.2%}" for r in c.itertuples()]
    return ["", f"Fits that stopped on their iteration cap in the reference run, {what}: " + "; ".join(items) + "."]


def table_lines(summary: pd.DataFrame) -> list[str]:
    """The per-experiment table of a check (check-<check>.md and REPORT.md show the same one)."""
    lines = ["| experiment | values | largest relative change (of the moved values; of all where none moved) "
             "| at | moved > rtol "
             "| ill-determined: tiny | ill-determined: equal fits | ill-determined: other minimum "
             "| fits moved > 0.1 % | claim verdicts changed (claim rows) | solver-path values (not compared) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in summary.itertuples():
        other = getattr(r, "n_other_minimum", 0)   # a csv written before the category: none
        other = 0 if pd.isna(other) else int(other)
        lines.append(f"| {r.experiment} | {r.values} | {r.max_rel_change:.3g} | `{r.worst_key}` | "
                     f"{r.n_above_rtol} | {r.n_ill_determined} | {r.n_equal_fit} | {other} | "
                     f"{r.fits_moved} | {r.verdicts_changed} ({getattr(r, 'claim_rows_changed', 0)}) | "
                     f"{r.n_solver_path} |")
    return lines


EXPLAIN = (f"A value below {SCALE_FLOOR:g} of the largest value of its metric for its model in its experiment is "
           "compared against that floor: where it moves only relative to itself it is *ill-determined: tiny* (a "
           "tracking error of 1e-12 where the same model errs by 1e-6 on another reference). A value that moves "
           f"although the fit it comes from reached the same training cost (`{FIT_METRIC}` rows, to "
           f"{FIT_RTOL:.1%}) is *ill-determined: equal fits*: the data do not determine it (the nonconvex fit has "
           "several parameter vectors of that cost, with different tracking); its spread is both values in the "
           "csv. A value that moves because its fit landed in another local minimum, although that fit stopped "
           f"on its tolerance on both sides (`{FIT_CAP_METRIC}` rows 0), is *ill-determined: other minimum*: the "
           "nonconvex criterion has several minima and rounding decides which one a machine reaches; its spread is "
           "both values. *Fits moved*: trained models whose training cost moved by more than that, i.e. landed "
           "elsewhere; values of a fit that stopped on a cap on either side count as moved. Solver-path values "
           "(iteration counts, the last step's size, "
           "the tolerance itself, a check LM's remaining gain, rounding-level C/Python differences and residues of "
           "exact identities) are listed, not compared. Ratios of two fits are attached to the first; one named after "
           f"both (`A{RATIO_SEP}B`) that moved no more than its inputs' changes add up to, with an ill-determined "
           "input, is ill-determined like that input.")


_WHAT = {"perturb": ("Perturbation check (a second machine, emulated)",
                    "every LM step's normal equations perturbed at relative rounding level"),
         "tighten": ("Tightening check (are the tolerances adequate?)",
                     "every LM and SK tolerance divided by the factor and the restarts' iteration caps "
                     "multiplied by CAPS"),
         "isa": ("Code-path check (another instruction set)",
                 "every job under another PIPELINE_ISA than the default AVX2 pin (the setting is named below)")}


def markdown(summary: pd.DataFrame, rtol: float, check: str, setting: str,
             keys: pd.DataFrame | None = None, per: dict | None = None) -> str:
    """check-<check>.md; ``per``: the json's per-experiment entries (when each experiment was checked)."""
    title, what = _WHAT[check]
    lines = [f"# {title}", "",
             f"The whole `make reproduce` rerun with {what} (`{setting}`); values compared key by "
             f"key with the reference `summary.csv` (timings left out). A value that moves by more "
             f"than {rtol:.0%} comes from a fit that its tolerance does not pin down. " + EXPLAIN, ""]
    if per:
        lines += ["Checked (each experiment against its rows of the reference summary.csv; a subset run "
                  "replaces only its own): " + "; ".join(f"{e} {v.get('checked_at', '?')}" for e, v in per.items()
                                                          if not v.get("stale")) + ".", ""]
        lines += status_lines([e for e, v in per.items() if v.get("stale")], partial_of(per))
    lines += table_lines(summary) + ([] if keys is None else capped_lines(keys, check))
    return "\n".join(lines) + "\n"


def summary_digest(path: Path) -> str:
    """sha256 of a summary.csv's content (rows sorted by key, values as text, timings left out as
    in :func:`compare`), not of its bytes: a rerun with the same results keeps the digest."""
    t = pd.read_csv(path, dtype=str, keep_default_na=False)
    t = t[~t["metric"].map(is_timing)]
    t = t.sort_values([c for c in KEY if c in t.columns], kind="stable").reset_index(drop=True)
    return hashlib.sha256(t.to_csv(index=False).encode()).hexdigest()


def experiment_digests(path: Path) -> dict[str, str]:
    """Per experiment, the sha256 of its rows of a summary.csv (as :func:`summary_digest`): a check made
    against these rows still holds for a later summary whose rows of that experiment have this digest."""
    try:
        t = pd.read_csv(path, dtype=str, keep_default_na=False)
    except pd.errors.EmptyDataError:
        return {}
    if t.empty or not {"experiment", "metric"} <= set(t.columns):   # a report without rows
        return {}
    t = t[~t["metric"].map(is_timing)]
    return {str(e): hashlib.sha256(g.sort_values([c for c in KEY if c in g.columns], kind="stable")
                                   .reset_index(drop=True).to_csv(index=False).encode()).hexdigest()
            for e, g in t.groupby("experiment", sort=True)}


def kept_experiments(meta: dict, digests: dict[str, str]) -> tuple[list[str], list[str]]:
    """From a check-<check>.json: the experiments whose check was made against the reference rows now in
    the summary (``digests``: :func:`experiment_digests`), and the stale ones (their rows changed since).
    A json written before the per-experiment digests (one ``reference_sha256`` of the whole summary) has
    none it can vouch for one by one: its experiments are all stale. An entry marked ``stale`` (kept, without
    its rows, by a later subset check) stays stale."""
    per = meta.get("experiments", {})
    valid = sorted(e for e, info in per.items()
                   if not info.get("stale") and digests.get(e) == info.get("reference_sha256"))
    stale = sorted(set(per) - set(valid))
    return valid, stale


def partial_of(per: dict, shown=None) -> list[str]:
    """From check-<check>.json's entries: the checked experiments (of ``shown``, default all) whose rerun lacked
    reference keys (a subset that left out an experiment file reporting into the same experiment, e.g.
    emps_narx of emps), with how many."""
    return [f"{e} ({v['keys_on_one_side']} keys)" for e, v in per.items()
            if not v.get("stale") and v.get("keys_on_one_side", 0) and (shown is None or e in shown)]


def status_lines(stale: list[str], partial: list[str], unchecked: list[str] = ()) -> list[str]:
    """The line naming a check's stale, unchecked and partial experiments (check-<check>.md and REPORT.md)."""
    out = []
    if stale:
        out.append(f"Stale (their rows of summary.csv changed since they were checked; rerun with "
                   f"`EXPERIMENTS=...`): {', '.join(stale)}.")
    if unchecked:
        out.append(f"Not checked: {', '.join(unchecked)}.")
    if partial:
        out.append("Partial (the rerun lacked keys of the reference: rerun every experiment file that reports into "
                   f"it): {', '.join(partial)}.")
    return [" ".join(out), ""] if out else []


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reference")
    ap.add_argument("perturbed")
    ap.add_argument("--out", default="results")
    ap.add_argument("--rtol", type=float, default=0.02)
    ap.add_argument("--check", choices=sorted(_WHAT), default="perturb")
    ap.add_argument("--setting", default="PIPELINE_PERTURB=1e-13")
    args = ap.parse_args(argv)
    for f in (args.reference, args.perturbed):
        if not Path(f).is_file():
            raise SystemExit(f"error: {f} does not exist: run `make reproduce` (reference) and the "
                             "perturbed reproduce first (`make reproduce-check` runs both)")
    keys, summary = compare(pd.read_csv(args.reference), pd.read_csv(args.perturbed), args.rtol)
    if keys.empty:
        raise SystemExit(f"error: {args.perturbed} and {args.reference} have no experiment in common to compare")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    digests = experiment_digests(Path(args.reference))
    stamp = {"setting": args.setting, "checked_at": pd.Timestamp.now(tz="UTC").strftime("%Y-%m-%d %H:%M UTC")}
    per = {r.experiment: {"reference_sha256": digests.get(r.experiment, ""), "keys_on_one_side": r.keys_on_one_side,
                          **stamp} for r in summary.itertuples()}
    # a subset rerun: keep the other experiments' rows of the previous check while their reference rows are
    # unchanged; the stale ones stay named (without rows) until a check reruns them
    meta_path, csv_path = out / f"check-{args.check}.json", out / f"check-{args.check}.csv"
    if meta_path.exists() and csv_path.exists():
        old_meta = json.loads(meta_path.read_text())
        if float(old_meta.get("rtol", args.rtol)) != args.rtol:
            print(f"note: the previous {csv_path.name} was made at rtol {old_meta.get('rtol')}, not {args.rtol}: "
                  "its experiments are not kept")
        else:
            valid, stale = kept_experiments(old_meta, digests)
            keep = [e for e in valid if e not in per]
            if keep:
                old = pd.read_csv(csv_path, dtype={"claim": str, "variant": str, "metric": str})
                for c in ("claim", "variant", "fit"):
                    old[c] = old[c].astype(object).fillna("")
                keys = pd.concat([keys, old[old["experiment"].isin(keep)]], ignore_index=True)
                per.update({e: old_meta["experiments"][e] for e in keep})
            per.update({e: {**old_meta["experiments"][e], "stale": True} for e in stale if e not in per})
    per = {e: per[e] for e in sorted(per)}
    keys = keys.sort_values("experiment", kind="stable")
    summary = summarise(keys, args.rtol, {e: v.get("keys_on_one_side", 0) for e, v in per.items()})
    settings = sorted({v.get("setting", "") for v in per.values() if not v.get("stale")})
    md = markdown(summary, args.rtol, args.check, " / ".join(settings), keys, per)
    _atomic_write(csv_path, keys.to_csv(index=False))
    _atomic_write(out / f"check-{args.check}.md", md)
    _atomic_write(meta_path, json.dumps({   # the report shows each experiment's check while its rows are unchanged
        "rtol": args.rtol, "experiments": per}, indent=1) + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
