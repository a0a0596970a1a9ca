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
how many moved by more than ``rtol``, and the claim verdicts that changed).  Timings are left out.
"""
from __future__ import annotations

import argparse
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
#: metrics that measure the machine, not the result
_TIMING = ("seconds", "time", "wall", "_ms", "per_sample_ns", "ns_per_sample")


def _is_timing(metric: str) -> bool:
    m = metric.lower()
    return any(t in m for t in _TIMING)


def compare(reference: pd.DataFrame, perturbed: pd.DataFrame, rtol: float = 0.02) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per key (reference value, perturbed value, relative change) and per experiment a summary.

    The relative change is |a - b| / max(|a|, |b|, floor) (0 when both are 0, 1 when one is NaN and
    the other not), floor = SCALE_FLOOR × the largest |reference value| of the same metric for the
    same model (first part of the variant) in the same experiment; a value whose change exceeds
    ``rtol`` only because it is below that floor is ``ill_determined`` (its spread is the two
    values), not counted in ``n_above_rtol``.  Keys on one side only are counted per experiment
    (``keys_on_one_side``), not compared; only the experiments of ``perturbed`` are compared (a check of a subset)."""
    b = perturbed.copy()
    a = reference[reference["experiment"].isin(set(b["experiment"]))].copy()   # a subset rerun: its experiments
    for d in (a, b):
        d[KEY] = d[KEY].fillna("")
    m = a.merge(b, on=KEY, how="outer", suffixes=("_ref", "_pert"), indicator=True)
    m = m[~m["metric"].map(_is_timing)]
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
    m = m.assign(rel_change=np.where(one_side, np.nan, rel),
                 ill_determined=~one_side & (rel <= rtol) & (rel_raw > rtol) & ~np.isnan(va) & ~np.isnan(vb))
    missing = m[one_side].groupby("experiment").size()
    m = m[~one_side]
    rows = []
    for exp, g in m.groupby("experiment", sort=False):
        i = int(np.argmax(g["rel_change"].to_numpy()))
        worst = g.iloc[i]
        verdicts = g[g["claim_holds_ref"].astype(str) != g["claim_holds_pert"].astype(str)]
        verdicts = verdicts[verdicts["claim"] != ""]
        rows.append({"experiment": exp, "values": len(g), "max_rel_change": float(worst["rel_change"]),
                     "worst_key": f"{worst['claim']}|{worst['variant']}|{worst['metric']}".strip("|"),
                     "n_above_rtol": int((g["rel_change"] > rtol).sum()),
                     "n_ill_determined": int(g["ill_determined"].sum()),
                     "verdicts_changed": int(verdicts["claim"].nunique()),
                     "keys_on_one_side": int(missing.get(exp, 0))})
    cols = KEY + ["value_ref", "value_pert", "rel_change", "ill_determined"]
    return m[cols], pd.DataFrame(rows)


_WHAT = {"perturb": ("Perturbation check (a second machine, emulated)",
                    "every LM step's normal equations perturbed at relative rounding level"),
         "tighten": ("Tightening check (are the tolerances adequate?)",
                     "every LM and SK tolerance divided by the factor")}


def markdown(summary: pd.DataFrame, rtol: float, check: str, setting: str) -> str:
    title, what = _WHAT[check]
    lines = [f"# {title}", "",
             f"The whole `make reproduce` rerun with {what} (`{setting}`); values compared key by "
             f"key with the reference `summary.csv` (timings left out). A value that moves by more "
             f"than {rtol:.0%} comes from a fit that its tolerance does not pin down. A value below "
             f"{SCALE_FLOOR:g} of the largest value of its metric for its model in its experiment is "
             "compared against that floor: where it moves only relative to itself it is counted as "
             "*ill-determined* (e.g. a tracking error of 1e-12 where the same model errs by 1e-6 on "
             "another reference), its spread in the csv.", "",
             "| experiment | values | largest relative change | at | moved > rtol | ill-determined (tiny) "
             "| claim verdicts changed | keys on one side only |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in summary.itertuples():
        lines.append(f"| {r.experiment} | {r.values} | {r.max_rel_change:.3g} | `{r.worst_key}` | "
                     f"{r.n_above_rtol} | {r.n_ill_determined} | {r.verdicts_changed} | {r.keys_on_one_side} |")
    return "\n".join(lines) + "\n"


def summary_digest(path: Path) -> str:
    """sha256 of a summary.csv's content (rows sorted by key, values as text, timings left out as
    in :func:`compare`), not of its bytes: a rerun with the same results keeps the digest."""
    import hashlib
    t = pd.read_csv(path, dtype=str, keep_default_na=False)
    t = t[~t["metric"].map(_is_timing)]
    t = t.sort_values([c for c in KEY if c in t.columns], kind="stable").reset_index(drop=True)
    return hashlib.sha256(t.to_csv(index=False).encode()).hexdigest()


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
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(summary, args.rtol, args.check, args.setting)
    _atomic_write(out / f"check-{args.check}.csv", keys.to_csv(index=False))
    _atomic_write(out / f"check-{args.check}.md", md)
    import json
    _atomic_write(out / f"check-{args.check}.json", json.dumps({   # the report shows the check of this summary only
        "reference_sha256": summary_digest(Path(args.reference)),
        "setting": args.setting, "rtol": args.rtol}, indent=1) + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
