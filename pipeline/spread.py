"""Claim rows judged on a statistic over restarts, not on the rounding (issue 52 item 2).

A nonconvex fit (a PGNN from random initial weights, best of its restarts) has several minima of about the
same training cost; which one a machine reaches can be decided by the last bit of a sum, so a value computed
from it is *ill-determined* (``make reproduce-check``: other minimum, equal fits) and a claim row judged on it
can flip on another CPU. ``make reproduce-spread`` reruns the experiments whose fits decide claim rows with
``init_seed = 1..S``: the same data, scored under the same noise, each fit from other initial weights and
restarts (:func:`stages.train.init_seed`). With the default run as ``init_seed = 0`` that gives S + 1 values of
every summary key, and per key:

- the statistic: the **median** of the S + 1 values; the **spread**: their range [min, max];
- every claim row judged again on the medians (:func:`stages.report.claims.judge`, the same thresholds), and
  *decided* when the verdict is the same at the minimum, the median and the maximum: a row whose threshold lies
  inside its spread is not decided by these fits, whatever one machine's rounding says.

    python -m pipeline.spread build SEED0.csv SEED1.csv ... [--out results] [--name spread] [--setting TEXT]
        [--keep results/spread.csv]
    python -m pipeline.spread check results/spread.csv OTHER_SPREAD.csv --name perturb|isa [--out results]
        [--keep results/spread-check-isa.csv] [--confirm FRESH_CHECK.csv]

``build`` writes ``<name>.csv`` (per key: n, median, min, max, the values; for claim rows the verdict on the
median and whether it is decided), ``<name>.md`` and ``<name>.json`` (per experiment the sha256 of the seed-0
rows it was built on, so the report shows it only while those rows are current). ``check`` compares another
machine's (or a perturbed run's) statistics with these: every claim row's median must land inside the
reference's spread and keep its verdict; it writes ``spread-check-<name>.md/.csv/.json``. ``--keep`` adds the rows of
an earlier spread for the experiments these summaries do not rerun (the same init_seeds), so the experiments can
be spread one at a time (``make reproduce-spread SPREAD_EXPERIMENTS=b2_rot_trans``); ``check --keep`` likewise keeps
an earlier check's rows (the same setting) for the experiments this check does not cover.

A separated row is the exact Mann-Whitney test at U = 0 (0.8 % with 5 draws against 5), but a check has tens
of claim rows that move, so an equivalent machine separates one of them in about a third of its checks: the
check states that family chance (``claim_rows_separated_by_chance``, ``p_any_separated_by_chance``).
``--confirm`` takes a check of *fresh* draws of both sides (other init_seeds, the rows' own jobs only: a
``check`` of two spreads built from them): a separated row whose fresh draws are separated again on the same
side is *confirmed* (chance 0.8 % × 0.8 %, whatever the number of rows); one whose fresh draws overlap was the
family's chance and is not counted against the check. Timings are left out,
as in :mod:`pipeline.perturbation`; solver-path values (iteration counts, stop flags) stay, since claims such as
K3 are judged on them.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.atomic import replace_file
from pipeline.perturbation import KEY, experiment_digests, is_timing
from stages.report.claims import claim_statistics, judge

__all__ = ["build", "check", "judge_statistic", "ABS_TOL", "REL_TOL"]

#: a value equal to the spread's end to this relative amount (or ABS_TOL absolute: residues of exact identities
#: at 1e-15) is inside it: a deterministic value (no fit behind it, min = max) may differ in its last bits
REL_TOL, ABS_TOL = 1e-9, 1e-12
#: a value's identity across runs (its claim id is the report's label of it)
_ID = [k for k in KEY if k != "claim"]


def _rows(path: str | Path) -> pd.DataFrame:
    """A spread's, a check's or a summary's rows as written (claim and variant '' where empty)."""
    t = pd.read_csv(path, dtype={"claim": str, "variant": str, "metric": str})
    t[["claim", "variant"]] = t[["claim", "variant"]].fillna("")
    return t


def _read(path: str | Path) -> pd.DataFrame:
    t = _rows(path)
    t = t[~t["metric"].map(is_timing)]      # solver-path rows stay: K3 judges its fits' stop reasons on them
    return t


def judge_statistic(stat: pd.DataFrame, column: str) -> pd.Series:
    """Each row's claim verdict with ``column``'s values in place of the run's (claim table of the report,
    per experiment, as the report judges), indexed as ``stat``; NaN where no condition names the row."""
    out = pd.Series(np.nan, index=stat.index, dtype=object)
    for _, g in stat.groupby("experiment", sort=False):
        rows = [{"experiment": r.experiment, "claim": "", "variant": r.variant, "metric": r.metric,
                 "value": float(getattr(r, column)), "paper_value": r.paper_value, "claim_holds": None}
                for r in g.itertuples()]
        judge(rows)
        for i, r in zip(g.index, rows):
            if r["claim"]:
                out[i] = bool(r["claim_holds"])
    return out


def build(summaries: list[pd.DataFrame], labels: list[str]) -> pd.DataFrame:
    """Per key of the first summary (seed 0) that every other summary has too: the values, n, median, min and
    max; claim rows judged on the median and, to say whether that verdict is decided, on the min and max."""
    if len(summaries) < 2:
        raise ValueError("a spread needs at least two runs (init_seed 0 and one more): give more summaries")
    ref = summaries[0]
    covered = set.intersection(*(set(s["experiment"]) for s in summaries[1:]))
    base = ref[ref["experiment"].isin(covered)][KEY + ["value", "paper_value", "claim_holds"]].copy()
    vals = []
    for lab, s in zip(labels, summaries):
        v = base[_ID].merge(s[_ID + ["value"]], on=_ID, how="left")["value"].to_numpy(np.float64)
        vals.append(v)
        base[f"value_{lab}"] = v
    V = np.vstack(vals)
    keep = np.isfinite(V).all(axis=0)            # a key every run has, finite in every one
    base, V = base[keep].reset_index(drop=True), V[:, keep]
    base["n"] = V.shape[0]
    base["median"], base["min"], base["max"] = np.median(V, axis=0), V.min(axis=0), V.max(axis=0)
    for col in ("median", "min", "max"):
        base[f"holds_{col}"] = judge_statistic(base, col)
    claimed = base["holds_median"].notna()
    same = (base["holds_min"] == base["holds_median"]) & (base["holds_max"] == base["holds_median"])
    base["decided"] = pd.Series([bool(x) if c else None for x, c in zip(same, claimed)], dtype=object)
    # range over |median|: inf where a zero median has a range (a count of 0 in most draws), 0 where neither moves
    width, mid = (base["max"] - base["min"]).to_numpy(), np.abs(base["median"].to_numpy())
    base["rel_spread"] = np.divide(width, mid, out=np.where(width > 0, np.inf, 0.0), where=mid > 0)
    return base


def _earlier(path: Path, field: str, want, what: str, fix: str, drop) -> tuple[pd.DataFrame, dict]:
    """The rows of the earlier file ``path`` of the experiments not in ``drop``, and its ``.json``; refused in one
    line (naming ``fix``) where its ``field`` (init_seeds, setting) is not ``want``."""
    meta_path = path.with_suffix(".json")
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    if meta.get(field) != want:
        raise SystemExit(f"error: {path} is {what} {meta.get(field)!r}, this one {want!r}: rerun its experiments "
                         f"{fix}, or drop --keep")
    old = _rows(path)
    return old[~old["experiment"].isin(set(drop))], meta


def keep_earlier(stat: pd.DataFrame, experiments: dict, labels: list[str], path: Path) -> tuple[pd.DataFrame, dict]:
    """``stat`` with the rows of the earlier spread ``path`` (and its ``.json``'s digests) for the experiments
    ``stat`` lacks; refused in one line where that spread was built over other init_seeds."""
    old, meta = _earlier(path, "seeds", labels, "over init_seeds", "with the same SEEDS", stat["experiment"])
    kept = {e: v for e, v in meta.get("experiments", {}).items() if e in set(old["experiment"])}
    both = pd.concat([old, stat], ignore_index=True)[stat.columns]
    return both, dict(sorted({**kept, **experiments}.items()))


def keep_earlier_check(m: pd.DataFrame, setting: str, path: Path, reference: pd.DataFrame,
                       determined: pd.DataFrame | None = None, confirm: pd.DataFrame | None = None) -> pd.DataFrame:
    """``m`` with the other run's statistics of the earlier check ``path`` for the experiments ``m`` lacks, judged
    against ``reference`` by the same rule (:func:`check`; their confirmation by fresh draws from ``confirm``, else
    as that check had it); refused in one line where that check ran under another setting."""
    old, _ = _earlier(path, "setting", setting, "checked under", "under the same setting", m["experiment"])
    if old.empty:
        return m
    kept = check(reference, old, determined, confirm)
    if confirm is None and "confirmed" in old:
        earlier = kept[_ID].merge(old[_ID + ["confirmed"]].drop_duplicates(_ID), on=_ID, how="left")["confirmed"]
        kept["confirmed"] = pd.Series([_bool(v) if sep else np.nan for v, sep in zip(earlier, kept["separated"])],
                                      index=kept.index, dtype=object)
    return pd.concat([kept, m], ignore_index=True)[m.columns]


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def markdown(stat: pd.DataFrame, labels: list[str], setting: str) -> str:
    """The spread's report: per claim the verdict on the medians, then every claim row with its statistic."""
    seeds = ", ".join(labels)
    lines = [f"# Claim rows over restarts (`make reproduce-spread`, init_seed {seeds})", "",
             f"Each experiment below rerun with `init_seed` = {seeds} (`{setting}`): the same data and evaluation "
             "noise, every network fit from other initial weights and restarts. Per summary key the **median** of "
             f"the {len(labels)} values is the statistic and their range [min, max] the **spread**; a claim row is "
             "judged on the median and is *decided* when its verdict is the same at the min, the median and the max. "
             "Per key: results/spread.csv.", "",
             "| experiment | keys | keys spread > 2 % | claim | rows | holds (init_seed 0) | holds (median) "
             "| rows not decided by the spread |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    per = claim_statistics(stat)
    for e, g in stat.groupby("experiment", sort=False):
        wide = int((g["rel_spread"] > 0.02).sum())
        for r in per[per["experiment"] == e].itertuples():
            lines.append(f"| {e} | {len(g)} | {wide} | {r.claim} | {r.rows} | {'yes' if r.holds_seed0 else 'no'} | "
                         f"{'yes' if r.holds_median else 'no'} | {r.rows_undecided} |")
    lines += ["", "| experiment | claim | variant | metric | init_seed 0 | median | [min, max] | holds on median "
              "| decided |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in stat[stat["holds_median"].notna()].itertuples():
        lines.append(f"| {r.experiment} | {r.claim} | `{r.variant}` | {r.metric} | {_fmt(r.value)} | "
                     f"{_fmt(r.median)} | "
                     f"[{_fmt(r.min)}, {_fmt(r.max)}] | {'yes' if r.holds_median else 'no'} | "
                     f"{'yes' if r.decided else '**no**'} |")
    return "\n".join(lines) + "\n"


def inside(x, lo, hi, rel: float = REL_TOL) -> np.ndarray:
    """x within [lo, hi] up to ``rel`` relative or ABS_TOL absolute (last bits of deterministic values)."""
    x, lo, hi = (np.asarray(a, np.float64) for a in (x, lo, hi))
    tol = np.maximum(rel * np.maximum(np.abs(lo), np.abs(hi)), ABS_TOL)
    return (x >= lo - tol) & (x <= hi + tol)


def chance_outside(n: int, m: int) -> float:
    """P(the median of m draws lies outside the range [min, max] of n draws) when all n + m come from one
    continuous distribution (an equivalent machine: exchangeable ranks): exact for odd m, an upper bound for even
    m. Below the min needs the k = (m+1)/2 smallest of the m first among all n + m: C(n+m-k, m-k)/C(n+m, m)
    (5 against 5: 21/252, so 1/6 for both sides)."""
    if n < 1 or m < 1:
        return math.nan
    k = (m + 1) // 2 if m % 2 else m // 2
    return min(1.0, 2.0 * math.comb(n + m - k, m - k) / math.comb(n + m, m))


def chance_separated(n: int, m: int) -> float:
    """P(all m draws lie on one side of all n draws) for one continuous distribution: 2/C(n+m, m), the exact
    two-sided p-value of the Mann-Whitney U = 0 (5 against 5: 2/252, 0.8 %)."""
    if n < 1 or m < 1:
        return math.nan
    return min(1.0, 2.0 / math.comb(n + m, m))


def determination(tighten: pd.DataFrame | None) -> pd.DataFrame:
    """Per key how far its value moved when its fits' tolerances were tightened 10x (a tightening check's rows,
    ``make reproduce-check CHECK=tighten``): the value is determined by its fits only to that amount."""
    if tighten is None or tighten.empty:
        return pd.DataFrame(columns=_ID + ["determination"])
    d = tighten[_ID].copy()
    d["determination"] = (pd.to_numeric(tighten["value_pert"], errors="coerce")
                          - pd.to_numeric(tighten["value_ref"], errors="coerce")).abs().fillna(0.0)
    return d.drop_duplicates(_ID)


_OTHER = ["median", "min", "max", "holds_median", "n"]


def check(reference: pd.DataFrame, other: pd.DataFrame, determined: pd.DataFrame | None = None,
          confirm: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per key both: the other run's median inside the reference's spread, the other run's draws separated from
    it, the claim verdict on the median the same (:func:`judge_check`). ``other`` is a spread (its columns
    median, min, max, holds_median, n) or an earlier check's rows (the same with the suffix ``_other``)."""
    if "median_other" in other:         # an earlier check's rows: its other run's columns
        other = other[_ID + [f"{c}_other" for c in _OTHER if f"{c}_other" in other]]
        other = other.rename(columns={f"{c}_other": c for c in _OTHER})
    other = other.assign(**{c: np.nan for c in _OTHER if c not in other})
    ref = reference.assign(**({} if "n" in reference else {"n": np.nan}))
    m = ref[KEY + ["n", "median", "min", "max", "holds_median", "decided"]].merge(
        other[_ID + _OTHER], on=_ID, suffixes=("", "_other"))
    return judge_check(m, determined, confirm)


def _bool(v):
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else str(v).lower() in ("true", "1", "1.0")


def judge_check(m: pd.DataFrame, determined: pd.DataFrame | None = None,
                confirm: pd.DataFrame | None = None) -> pd.DataFrame:
    """The check's judgement of each key, from the medians and ranges of both runs (so kept rows of an earlier
    check are judged by the same rule):

    - ``tol``: a key that does not move with the restarts (min = max: no random fit behind it) is stated to its
      ``determined`` amount (how far it moves when its fits' tolerances are tightened), at least its last bits
      (REL_TOL, ABS_TOL); a key that moves is stated by its spread;
    - ``inside``: the other run's median within [min - tol, max + tol]. An equivalent machine misses this by
      chance on :func:`chance_outside` of the keys that move (1/6 with 5 draws each), so it is counted, not
      required;
    - ``separated``: every draw of the other run beyond the stated spread on one side (chance
      :func:`chance_separated`, 0.8 % with 5 draws each, the column ``chance_separated`` for the keys that
      move): the other code path lands elsewhere; ``side`` +1 above, -1 below;
    - ``confirmed``: for a separated key, whether ``confirm`` (a check of fresh draws of both sides) separates it
      again on the same side (NaN where it has no fresh draws of it);
    - ``verdict_same``: the claim verdict on the other median equals the reference's, where the reference decides
      it (the same at its min, median and max); a row the reference's spread does not decide has no verdict to
      flip (NaN; ``undecided_read_otherwise`` says where its other median reads the other way)."""
    m = m.copy()
    for c in ("holds_median", "holds_median_other", "decided"):
        m[c] = pd.Series([_bool(v) for v in m[c]], index=m.index, dtype=object)
    lo, hi = m["min"].to_numpy(np.float64), m["max"].to_numpy(np.float64)
    tol = np.maximum(REL_TOL * np.maximum(np.abs(lo), np.abs(hi)), ABS_TOL)
    if determined is not None and not determined.empty:
        d = m[_ID].merge(determined, on=_ID, how="left")["determination"].fillna(0.0).to_numpy(np.float64)
        tol = np.where(lo == hi, np.maximum(tol, d), tol)
    m["tol"] = tol
    m["inside"] = inside(m["median_other"], lo - tol, hi + tol, 0.0)
    above = m["min_other"].to_numpy(np.float64) > hi + tol
    below = m["max_other"].to_numpy(np.float64) < lo - tol
    m["separated"] = above | below
    m["side"] = np.where(above, 1, np.where(below, -1, 0))
    claimed = m["holds_median"].notna()
    decided = claimed & (m["decided"] == True)                        # noqa: E712 - object column
    same = m["holds_median"] == m["holds_median_other"]
    m["verdict_same"] = pd.Series([bool(x) if d_ else np.nan for x, d_ in zip(same, decided)], index=m.index,
                                  dtype=object)
    m["undecided_read_otherwise"] = claimed & ~decided & ~same
    n = pd.to_numeric(m.get("n", np.nan), errors="coerce")
    n_other = pd.to_numeric(m.get("n_other", np.nan), errors="coerce")
    draws = [(int(a), int(b)) if a > 0 and b > 0 and lo_ < hi_ else None     # None: the key does not move
             for a, b, lo_, hi_ in zip(np.nan_to_num(n), np.nan_to_num(n_other), lo, hi)]
    m["chance_outside"] = [np.nan if d is None else chance_outside(*d) for d in draws]
    m["chance_separated"] = [np.nan if d is None else chance_separated(*d) for d in draws]
    again = [np.nan] * len(m)                                       # separated again on the fresh draws' same side
    if confirm is not None and not confirm.empty:
        fresh = m[_ID].merge(confirm[_ID + ["separated", "side"]].drop_duplicates(_ID), on=_ID, how="left")
        again = [np.nan if pd.isna(f) else bool(_bool(f)) and int(fs) == int(side)
                 for f, fs, side in zip(fresh["separated"], fresh["side"].fillna(0), m["side"])]
    # a separated key that does not move (no random fit behind it) is no chance event: it stands as separated
    m["confirmed"] = pd.Series([(True if d is None else a) if sep else np.nan
                                for d, a, sep in zip(draws, again, m["separated"])], index=m.index, dtype=object)
    return m


def check_summary(m: pd.DataFrame, setting: str) -> dict:
    """The check's counts over its claim rows; ``ok`` when no decided verdict flips and no claim row is separated
    from its stated spread, except a separated row whose fresh draws overlap (``confirmed`` False: the family's
    chance, :func:`judge_check`). The medians outside are compared with their chance count, not required to be 0;
    the separated rows likewise with theirs (the sum, and the chance of at least one)."""
    c = m[m["holds_median"].notna()]
    p_sep = pd.to_numeric(c.get("chance_separated", pd.Series(dtype=float)), errors="coerce").dropna()
    confirmed = c.get("confirmed", pd.Series(np.nan, index=c.index))
    sep = c["separated"].astype(bool)
    s = {"setting": setting, "keys": len(m), "inside": int(m["inside"].sum()), "claim_rows": len(c),
         "claim_rows_inside": int(c["inside"].sum()),
         "claim_rows_outside_by_chance": round(float(np.nansum(c["chance_outside"])), 1),
         "claim_rows_separated": int(sep.sum()),
         "claim_rows_separated_by_chance": round(float(p_sep.sum()), 2),
         "p_any_separated_by_chance": round(float(1.0 - np.prod(1.0 - p_sep.to_numpy())), 2),
         "claim_rows_separated_confirmed": int((sep & (confirmed == True)).sum()),               # noqa: E712
         "claim_rows_separated_not_confirmed": int((sep & (confirmed == False)).sum()),          # noqa: E712
         "claim_rows_flipped": int((c["verdict_same"] == False).sum()),                       # noqa: E712
         "claim_rows_undecided_read_otherwise": int(c["undecided_read_otherwise"].sum())}
    s["ok"] = (s["claim_rows_separated"] == s["claim_rows_separated_not_confirmed"]
               and s["claim_rows_flipped"] == 0)
    return s


def _chance(c: pd.DataFrame) -> str:
    """The rows' summed chance of a median outside; – where the draws were not recorded (an older check)."""
    if c["n_other"].isna().all():
        return "–"
    return f"{np.nansum(c['chance_outside']):.1f}"


def _chance_sep(c: pd.DataFrame) -> str:
    """The rows' summed chance of a separation; – where the draws were not recorded (an older check)."""
    if "chance_separated" not in c or c["n_other"].isna().all():
        return "–"
    return f"{np.nansum(c['chance_separated']):.2f}"


def _confirmed(c: pd.DataFrame) -> str:
    """Separated rows confirmed by fresh draws / tested; – where none was separated."""
    sep = c[c["separated"].astype(bool)]
    if sep.empty:
        return "–"
    conf = sep.get("confirmed", pd.Series(np.nan, index=sep.index))
    tested = conf.notna()
    return f"{int((conf[tested] == True).sum())} of {int(tested.sum())} tested"                # noqa: E712


def _confirm_text(confirmed, chance: float) -> str:
    if isinstance(chance, float) and math.isnan(chance):
        return " (a value that does not move with the restarts: no chance event)"
    if confirmed is None or (isinstance(confirmed, float) and math.isnan(confirmed)):
        return " (not tested on fresh draws: `--confirm`)"
    return (", **confirmed** by fresh draws (separated again on the same side)" if _bool(confirmed)
            else "; fresh draws overlap: not confirmed (the family's chance)")


def check_markdown(m: pd.DataFrame, name: str, setting: str, summary: dict | None = None) -> str:
    lines = [f"# Claim-row statistics on another code path (`{name}`: `{setting}`)", "",
             "Per key the other run's draws against this run's spread [min, max] (results/spread.csv; a key that does "
             "not move with the restarts is stated to the amount it moved when its fits' tolerances were tightened "
             "10x, results/check-tighten.csv, at least its last bits). Per key: "
             f"results/spread-check-{name}.csv.", "",
             "- *median inside*: the other median within the spread. An equivalent machine misses this by chance on "
             "a share of the keys that move: 1/6 with 5 draws on each side, 3/14 with 3 against 5 (exact, from the "
             "ranks: `chance_outside`; an upper bound for an even number of other draws); the column *by chance* sums "
             "that share over the claim rows.",
             "- *separated*: every draw of the other run beyond the spread on one side, i.e. the other code path lands "
             "elsewhere (chance 2/C(n+m, m): 0.8 % with 5 against 5, the exact Mann-Whitney p of U = 0). Over the "
             "claim rows that move an equivalent machine separates some by chance: the column *by chance* beside "
             "it sums that chance (P(at least one) below). A separated row is *confirmed* when fresh draws of both "
             "sides (other init_seeds, `--confirm`) are separated again on the same side; where they overlap it was "
             "the family's chance. The check passes when no decided verdict flips and no separated claim row is "
             "confirmed or left untested.",
             "- *flipped*: a claim row whose verdict the spread decides (the same at its min, median and max) reads "
             "otherwise on the other median. A row the spread does not decide has no verdict to flip; where its "
             "other median reads otherwise it is counted as *undecided, read otherwise*.", "",
             "| experiment | draws (init_seeds) | keys | medians inside | claim rows | claim-row medians inside "
             "| outside by chance | separated | by chance | confirmed | verdicts flipped | undecided, read otherwise |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for e, g in m.groupby("experiment", sort=False):
        c = g[g["holds_median"].notna()]
        n = g["n_other"].max() if "n_other" in g else float("nan")     # a check made before draws were recorded: –
        lines.append(f"| {e} | {'–' if pd.isna(n) else int(n)} | {len(g)} | {int(g['inside'].sum())} | {len(c)} | "
                     f"{int(c['inside'].sum())} | {_chance(c)} | {int(c['separated'].sum())} | {_chance_sep(c)} "
                     f"| {_confirmed(c)} | {int((c['verdict_same'] == False).sum())} "                        # noqa: E712
                     f"| {int(c['undecided_read_otherwise'].sum())} |")
    s = summary or check_summary(m, setting)
    lines += ["", "Over all claim rows an equivalent machine separates "
              f"~{s['claim_rows_separated_by_chance']} by chance (P(at least one) = "
              f"{s['p_any_separated_by_chance']:.2f}); {s['claim_rows_separated']} separated, "
              f"{s['claim_rows_separated_confirmed']} standing (fresh draws separated again, or a value that does "
              f"not move), {s['claim_rows_separated_not_confirmed']} not confirmed (their fresh draws overlap)."]
    out = m[m["holds_median"].notna() & (~m["inside"] | m["separated"] | (m["verdict_same"] == False)     # noqa: E712
                                         | m["undecided_read_otherwise"])]
    if len(out):
        lines += ["", "Claim rows outside the spread, separated from it, flipped or read otherwise:", ""]
        lines += [f"- {r.experiment} {r.claim} `{r.variant}` {r.metric}: median {_fmt(r.median_other)} "
                  f"(draws [{_fmt(r.min_other)}, {_fmt(r.max_other)}]) against [{_fmt(r.min)}, {_fmt(r.max)}]"
                  + (f" ± {_fmt(r.tol)}" if r.min == r.max else "")
                  + (", **separated**" if r.separated else "")
                  + (_confirm_text(r.confirmed, r.chance_separated) if r.separated else "")
                  + (", **verdict flipped**" if r.verdict_same == False else "")                   # noqa: E712
                  + (", not decided by the spread, read otherwise" if r.undecided_read_otherwise else "")
                  for r in out.itertuples()]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="the statistic of several runs' summary.csv (the first: init_seed 0)")
    b.add_argument("summaries", nargs="+")
    b.add_argument("--labels", default="", help="comma-separated init_seed of each summary (default 0,1,...)")
    b.add_argument("--keep", default=None, help="an earlier spread.csv: its experiments these summaries do not rerun "
                                                "stay (same init_seeds)")
    c = sub.add_parser("check", help="another code path's spread.csv against this one's")
    c.add_argument("reference")
    c.add_argument("other")
    c.add_argument("--keep", default=None, help="an earlier spread-check-<name>.csv: its experiments this check does "
                                                "not cover stay (same setting)")
    c.add_argument("--confirm", action="append", default=[],
                   help="a check of fresh draws of both sides (spread-check csv of two spreads built from other "
                        "init_seeds; repeat it for several rows' jobs): a separated row separated again on the same "
                        "side is confirmed")
    c.add_argument("--determination", default=None,
                   help="a tightening check's csv (results/check-tighten.csv): keys that do not move with the restarts "
                        "are stated to the amount they moved there")
    for p in (b, c):
        p.add_argument("--out", default="results")
        p.add_argument("--name", default="spread")
        p.add_argument("--setting", default="")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    if a.cmd == "build":
        missing = [s for s in a.summaries if not Path(s).is_file()]
        if missing:
            raise SystemExit(f"error: no summary {missing[0]}: run `make reproduce-spread` (one per init_seed)")
        labels = a.labels.split(",") if a.labels else [str(i) for i in range(len(a.summaries))]
        if len(labels) != len(a.summaries):
            raise SystemExit(f"error: --labels gives {len(labels)} init_seeds for {len(a.summaries)} summaries")
        try:
            stat = build([_read(s) for s in a.summaries], labels)
        except ValueError as exc:
            raise SystemExit(f"error: {exc}") from None
        if stat.empty:
            raise SystemExit("error: the summaries share no experiment; run the same EXPERIMENTS for every init_seed")
        digests = experiment_digests(Path(a.summaries[0]))
        experiments = {e: {"reference_sha256": digests.get(e)} for e in sorted(set(stat["experiment"]))}
        if a.keep and Path(a.keep).is_file():
            stat, experiments = keep_earlier(stat, experiments, labels, Path(a.keep))
        meta = {"seeds": labels, "setting": a.setting, "made": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "experiments": experiments}
        replace_file(out / f"{a.name}.csv", stat.to_csv(index=False).encode())
        replace_file(out / f"{a.name}.md", markdown(stat, labels, a.setting).encode())
        replace_file(out / f"{a.name}.json", json.dumps(meta, indent=1).encode())
        per = claim_statistics(stat)
        print(f"{a.name}: {len(stat)} keys of {stat['experiment'].nunique()} experiments over {len(labels)} runs; "
              f"claims on the median: " + ", ".join(f"{r.claim} {'holds' if r.holds_median else 'does not hold'}"
                                                   + (f" ({r.rows_undecided} rows undecided)" if r.rows_undecided
                                                      else "") for r in per.itertuples()))
        return 0
    ref = _rows(a.reference)
    determined = determination(_rows(a.determination)) if a.determination and Path(a.determination).is_file() else None
    confirm = []
    for path in a.confirm:
        if not Path(path).is_file():
            raise SystemExit(f"error: no confirming check {path}: make it with `make reproduce-confirm` (or "
                             "`python -m pipeline.spread check FRESH_REFERENCE_SPREAD.csv FRESH_OTHER_SPREAD.csv`)")
        confirm.append(_rows(path))
        if not {"separated", "side"} <= set(confirm[-1].columns):
            raise SystemExit(f"error: {path} is not a spread check's csv (no separated/side columns); "
                             "make it with `python -m pipeline.spread check`")
    confirm = pd.concat(confirm, ignore_index=True) if confirm else None
    m = check(ref, _rows(a.other), determined, confirm)
    if a.keep and Path(a.keep).is_file():
        m = keep_earlier_check(m, a.setting, Path(a.keep), ref, determined, confirm)
    replace_file(out / f"spread-check-{a.name}.csv", m.to_csv(index=False).encode())
    summary = check_summary(m, a.setting)
    replace_file(out / f"spread-check-{a.name}.md", check_markdown(m, a.name, a.setting, summary).encode())
    replace_file(out / f"spread-check-{a.name}.json", json.dumps(summary, indent=1).encode())
    print(f"spread check {a.name}: {summary['claim_rows_inside']} of {summary['claim_rows']} claim-row medians inside "
          f"the spread (~{summary['claim_rows_outside_by_chance']} outside by chance), "
          f"{summary['claim_rows_separated']} separated from it (~{summary['claim_rows_separated_by_chance']} by "
          f"chance; {summary['claim_rows_separated_confirmed']} confirmed by fresh draws, "
          f"{summary['claim_rows_separated_not_confirmed']} not), {summary['claim_rows_flipped']} decided verdicts "
          f"flipped; all keys {summary['inside']} of {len(m)}")
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
