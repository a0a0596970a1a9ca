"""report: results/summary.csv and results/REPORT.md from the tracking store (DESIGN contracts).

For every experiment in ``report.experiments`` the latest finished run of each run name is
read from MLflow and handed to a *section provider*: a module in ``stages/report/`` whose
``EXPERIMENTS`` tuple names the experiment, exposing

    section(experiment: str, runs: pandas.DataFrame, figdir: pathlib.Path) -> (rows, markdown)

``rows``: dicts with the summary.csv columns (``claim`` a SPEC §8 id or "", ``claim_holds``
True/False on claim rows, None elsewhere); ``markdown``: the REPORT.md section (the paper's
claim, our numbers, figures saved into ``figdir`` and linked as ``figures/<file>``, and a
sentence on what matched).  Experiments without a provider get the generic table.

``report.update=true`` rebuilds only the sections of the ``report.experiments`` that have runs in
the store and keeps every other section of the existing REPORT.md, its summary.csv rows and its
figures (a subset of experiments rerun does not erase the others' results; ``make reproduce
EXPERIMENTS=...`` uses it); the header says which sections were rebuilt.
"""
from __future__ import annotations

import ast
import importlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import mlflow
import pandas as pd

from pipeline import compare, owned, tracking
from pipeline.atomic import replace_file, umask
from pipeline.cache import UntrustedCache, cache_dir, copy_signed
from pipeline.export.law import strict_json
from pipeline.perturbation import (EXPLAIN, capped_fits, capped_lines, claim_verdicts, experiment_digests,
                                   is_timing, kept_experiments, partial_of, status_lines, summarise, summary_digest,
                                   table_lines)
from pipeline.runner import ROOT
from stages.report import claims
from stages.report._rows import row, run_metrics
from stages.report._runs import latest_runs, split_side

UPSTREAM = ()
DEPENDS = ()
CACHE = False
COLUMNS = ["experiment", "claim", "variant", "metric", "value", "paper_value", "claim_holds"]
KEY = ["experiment", "claim", "variant", "metric"]     # unique in summary.csv
#: what the report replaces under paths.results (pipeline.owned: only if it wrote them)
OUTPUTS = ("REPORT.md", "summary.csv", "figures", "export")


def _results(cfg) -> Path:
    return Path(cfg.paths.results) if cfg.paths.get("results") else ROOT / "results"


def validate(cfg, system) -> None:
    """Refuse (before any work) a results folder where the report would replace a user's file."""
    owned.refuse_foreign(_results(cfg), OUTPUTS, "paths.results")


def providers() -> dict[str, object]:
    out = {}
    for p in sorted(Path(__file__).parent.glob("*.py")):
        if p.stem.startswith("_"):
            continue
        mod = importlib.import_module(f"stages.report.{p.stem}")
        for e in getattr(mod, "EXPERIMENTS", ()):
            out[e] = mod
    return out


def _fmt_holds(v) -> str:
    return "" if v is None or (isinstance(v, float) and pd.isna(v)) else ("true" if v else "false")


def run(ctx) -> dict:
    cfg = ctx.cfg
    results = _results(cfg)
    results.mkdir(parents=True, exist_ok=True)
    figdir = Path(tempfile.mkdtemp(prefix=".figures-tmp-", dir=results))  # swapped in when complete
    try:
        update = bool(cfg.report["update"])   # ["update"]: .update is the mapping method
        table, text, built = _build(cfg, figdir, skip_empty=update)
        if update:
            table, text = _merge(results, table, text, built, figdir)
        _write(results / "summary.csv", table.to_csv(index=False))
        text = _with_checks(text, results, table)
        text = _with_champions(text, [(e, _champion_or_warn(e)) for e in built])
        if update and not built:    # nothing rerun (make reproduce-spread): the registry's champions are as they were
            text = _in_head(text, _registry_paragraph(results / "REPORT.md"))
        old = Path(tempfile.mkdtemp(prefix=".figures-old-", dir=results))
        if (results / "figures").exists():
            os.replace(results / "figures", old / "figures")
        owned.allow(results, "figures", figdir)
        os.chmod(figdir, 0o777 & ~umask())      # private (mkdtemp) while filled; readable as usual once whole
        os.replace(figdir, results / "figures")  # the figures first, then the report that links them
        shutil.rmtree(old, ignore_errors=True)
        _write(results / "REPORT.md", text)
        if not update or SHIPPED[0] in built:
            _ship(results / "export", SHIPPED, cache_dir(cfg))
        owned.record(results, OUTPUTS)
    finally:
        shutil.rmtree(figdir, ignore_errors=True)
    ctx.metric("n_rows", len(table))
    return {}


def _with_checks(text: str, results: Path, table: pd.DataFrame | None = None) -> str:
    """REPORT.md with a section per reproduce-check (pipeline/perturbation.py): the experiments whose check was
    made against their rows of this very summary.csv (per-experiment sha256 in check-<check>.json); the
    experiments checked against other rows are named stale, those never checked are named too.  Before them,
    the claim table of ``table`` (summary.csv's rows), each capped fit with its current tightening check."""
    digest, digests = summary_digest(results / "summary.csv"), experiment_digests(results / "summary.csv")
    out, tightened, verdicts = [], {}, {}
    for check, title in (("perturb", "a second machine, emulated"), ("tighten", "tolerances tightened 10x")):
        meta, csv = results / f"check-{check}.json", results / f"check-{check}.csv"
        if not (meta.exists() and csv.exists()):
            continue
        info = json.loads(meta.read_text())
        if "experiments" not in info:   # one digest of the whole summary (a check written before the merge)
            valid = [] if info.get("reference_sha256") != digest else None
            stale = sorted(info.get("keys_on_one_side", {})) if valid == [] else []
        else:
            valid, stale = kept_experiments(info, digests)
        if valid == []:
            out += [f"`make reproduce-check CHECK={check}` ({title}): results/check-{check}.md compares another "
                    "summary.csv than this one (stale); rerun it.", ""]
            continue
        k = pd.read_csv(csv, dtype={"claim": str, "variant": str, "metric": str})
        rtol = float(info.get("rtol", 0.02))
        if "category" not in k:
            out += [f"`make reproduce-check CHECK={check}`: results/check-{check}.csv was written by an older "
                    "version of the check (no categories); rerun it.", ""]
            continue
        k[["claim", "variant"]] = k[["claim", "variant"]].fillna("")
        per = info.get("experiments", {})
        if valid is not None:
            k = k[k["experiment"].isin(valid)]
        keys_one_side = {e: v.get("keys_on_one_side", 0) for e, v in per.items()} or info.get("keys_on_one_side", {})
        settings = sorted({v.get("setting", "") for v in per.values()} or {info.get("setting", "")})
        unchecked = sorted(set(digests) - set(k["experiment"]) - set(stale))
        out += [f"### Same numbers on {title} (`make reproduce-check CHECK={check}`, `{' / '.join(settings)}`)", "",
                f"Per experiment, the largest relative change of a summary value between this run and the "
                f"rerun, and how many moved by more than {rtol:.0%}. " + EXPLAIN +
                f" Per key: results/check-{check}.csv.", ""]
        out += status_lines(stale, partial_of(per, set(k["experiment"])), unchecked)
        out += table_lines(summarise(k, rtol, keys_one_side)) + capped_lines(k, check)
        out.append("")
        verdicts[check] = {(r.experiment, r.claim): r for r in claim_verdicts(k).itertuples()}
        if check == "tighten":
            tightened = {(r.experiment, r.fit): r for r in capped_fits(k).itertuples()}
    spread, spread_lines = _spread(results, digests)
    out += spread_lines
    if table is not None:
        out = _claim_table(table, tightened, verdicts, spread) + out
    if not out:
        return text
    head, rest = text.split("\n## ", 1) if "\n## " in text else (text, "")
    return head.rstrip("\n") + "\n\n" + "\n".join(out) + ("\n## " + rest if rest else "")


def _build(cfg, figdir: Path, skip_empty: bool = False) -> tuple[pd.DataFrame, str, list[str]]:
    """summary.csv as a table, REPORT.md as text and the experiments built; the sections' figures
    go to ``figdir``.  ``skip_empty``: experiments without runs get no section (update mode keeps theirs)."""
    provs = providers()
    rows, sections, built = [], [], []
    for exp in cfg.report.experiments:
        runs, mixed = latest_runs(str(exp))
        if runs.empty and skip_empty:
            continue
        built.append(str(exp))
        if runs.empty:
            sections.append(f"## {exp}\n\nNo finished runs in the tracking store "
                            f"({tracking.tracking_uri()}); run `make reproduce`.\n")
            continue
        mod = provs.get(str(exp)) or importlib.import_module("stages.report.generic")
        every = runs
        runs, side = split_side(str(exp), runs)
        r, md = mod.section(str(exp), runs, figdir)
        rows += claims.judge(r)     # the claim table gives every verdict (idempotent on judged rows)
        if not side.empty and hasattr(mod, "side_section"):
            r, extra = mod.side_section(str(exp), runs, side, figdir)
            rows += r
            md += extra
        for extra in (_stop_reasons(str(exp), runs), _exports(str(exp), every), _comparison(str(exp), every, figdir)):
            if extra:
                rows += extra[0]
                md += extra[1]
        if mixed:
            md += (f"\n\n> Note: run name(s) {', '.join(mixed)} have finished runs with different "
                   "configs in the store; this section uses the latest of each. Run `make reproduce` "
                   "on a clean store (`make clean`) to report one configuration only.\n")
        sections.append(md)
    table = pd.DataFrame(rows, columns=COLUMNS)
    table["claim"] = table["claim"].fillna("")
    dup = table.duplicated(KEY, keep=False)
    if dup.any():   # one number per key: a provider that repeats one is a bug, not a result
        raise RuntimeError(f"summary.csv would repeat keys {sorted(set(map(tuple, table.loc[dup, KEY].values)))}")
    table["claim_holds"] = table["claim_holds"].map(_fmt_holds)
    head = ["# Results", "",
            "Generated by `make reproduce` from the MLflow runs "
            f"(store: `{tracking.tracking_uri().replace(str(ROOT), '<repo>')}`; runs made at git "
            f"{_shas(cfg.report.experiments)}, report at "
            f"`{tracking.git_sha()[:12]}`). One section per experiment; every number is also a row "
            "of `summary.csv`.", ""]
    return table, "\n".join(head + sections) + "\n", built


#: the runs whose exported packages results/export/<law>/ holds: experiment, (logged param, value), and
#: the reference whose CSVs are kept there (the [B1] Fig. 3 one; the run's artifacts have every reference)
SHIPPED = ("b1_linear_motor", ("system.noise.structure", "equation"), "v0_15")


def _exports(experiment: str, runs: pd.DataFrame):
    """summary.csv rows and a REPORT.md table of the feedforwards the export stage shipped
    (issue 12): per package, the C code's and the Python law's max|Δu|/max|u| against the study,
    ns per sample in C, flops, parameters and the MISRA C:2012 findings of cppcheck's addon (issue 22;
    n/a where cppcheck is not installed: the package README lists them per rule with the reasons)."""
    col = "metrics.export/max_rel_diff"
    if col not in runs or runs[col].isna().all():
        return None
    rows = []
    lines = ["", "", "Exported feedforward (the `export` stage; C99 compiled with `cc -std=c99 -O2 -Wall -Wextra "
             "-Werror`, run by its harness on every evaluation reference; Δu against the study's u_ff):", "",
             "| run | package | C max Δu / max u | Python max Δu / max u | C ns/sample | flops/sample | parameters "
             "| MISRA findings |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for _, r in runs[runs[col].notna()].sort_values("tags.mlflow.runName").iterrows():
        m = run_metrics(r)
        for pkg in sorted({k.split("/")[1] for k in m if k.startswith("export/ff_")}):
            get = {k.split("/")[-1]: v for k, v in m.items() if k.startswith(f"export/{pkg}/")}
            name = r["tags.mlflow.runName"]
            for k in ("c_max_rel_diff", "python_max_rel_diff", "c_ns_per_sample", "misra_findings"):
                if k in get:
                    rows.append(row(experiment, f"export/{name}/{pkg}", k, get[k]))
            fmt = lambda k, f: format(get[k], f) if k in get else "n/a"   # noqa: E731
            lines.append(f"| `{name}` | `{pkg}` | {fmt('c_max_rel_diff', '.2g')} | {fmt('python_max_rel_diff', '.2g')} "
                         f"| {fmt('c_ns_per_sample', '.0f')} | {fmt('flops', '.0f')} | {fmt('parameters', '.0f')} "
                         f"| {fmt('misra_findings', '.0f')} |")
    if experiment == SHIPPED[0]:
        lines += ["", f"The packages of the `{SHIPPED[1][0]}={SHIPPED[1][1]}` runs are in `results/export/<package>/`, "
                  f"with the reference `{SHIPPED[2].replace('_', '.')}` (README: Deploy the feedforward)."]
    return rows, "\n".join(lines) + "\n"


def _ship(dest: Path, which: tuple[str, tuple[str, str], str], store: Path) -> None:
    """Copy the export packages of the runs of experiment ``which[0]`` whose param ``which[1][0]`` is
    ``which[1][1]`` into ``dest/<package>/`` (swapped in whole), with the CSVs of reference ``which[2]``.
    They come from each run's signed export entry in the stage cache ``store`` (its tag
    ``cache_entry.export``), every file hashed as it is copied, never from the artifact store (issue 51
    item 2: a line appended there was shipped); a run without a trusted entry is named and not shipped."""
    runs, _ = latest_runs(which[0])
    col = "metrics.export/max_rel_diff"
    if runs.empty or col not in runs:
        return
    tmp = Path(tempfile.mkdtemp(prefix=".export-tmp-", dir=dest.parent))
    try:
        got = tmp / "export"
        got.mkdir()
        runs, _ = split_side(which[0], runs)   # the headline runs' packages (one per package name)
        param = runs.get(f"params.{which[1][0]}", pd.Series("", index=runs.index)).astype(str)
        for _, r in runs[runs[col].notna() & (param == which[1][1])].iterrows():
            where = r.get("tags.cache_entry.export")
            try:
                if not isinstance(where, str) or not re.fullmatch(r"export/[0-9a-f]{20}", where):
                    raise UntrustedCache(f"run {r['run_id']} names no export cache entry (made before the tag "
                                         "cache_entry.export existed; rerun it)")
                copy_signed(store / where, "artifacts", got)     # got/<package>/...
            except (UntrustedCache, OSError) as exc:
                print(f"warning: {which[0]}: {exc}; its packages are not shipped to {dest}", flush=True)
        for f in got.iterdir():     # a package is a folder: a loose artifact file is not one
            if f.is_file():
                f.unlink()
        if not any(got.iterdir()):
            print(f"warning: no export packages in the {which[0]} runs: results/export not updated", flush=True)
            return
        for f in got.glob("*/*.csv"):   # one reference; the test vectors stay (the package README lists them)
            if not f.stem.endswith(f"_{which[2]}") and not f.stem.startswith("vectors_"):
                f.unlink()
        for path in got.glob("*/manifest.json"):   # the manifest lists exactly what is shipped
            man, pkg = json.loads(path.read_text()), path.parent
            man["verified_on"] = sorted(man["references"])
            man["references"] = {k: v for k, v in man["references"].items() if (pkg / v["file"]).exists()}
            man["files"] = sorted(p.name for p in pkg.iterdir() if p.name != "manifest.json")
            path.write_text(strict_json(man))
        old = Path(tempfile.mkdtemp(prefix=".export-old-", dir=dest.parent))
        if dest.exists():
            os.replace(dest, old / "export")
        owned.allow(dest.parent, dest.name, got)
        os.replace(got, dest)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _with_champions(text: str, champions: list) -> str:
    """REPORT.md with the Model Registry's champions (one per experiment with a logged feedforward) in
    its header: `models:/<name>@champion` serves it (README: Browse and compare)."""
    got = [(e, c) for e, c in champions if c]
    if not got:
        return text
    lines = ["Model Registry: each experiment's chosen feedforward (lowest first `compare_metrics` value among its "
             "headline runs) is the version with alias `champion` of `<experiment>-feedforward`, the run's metrics "
             "as version tags: " + "; ".join(f"`models:/{n}@champion` (version {v})" for _, (n, v) in got) + "."
             + (" No logged feedforward model (no `export` stage), so none registered: "
                + ", ".join(f"`{e}`" for e, c in champions if not c) + "." if len(got) < len(champions) else ""), ""]
    return _in_head(text, lines)


def _in_head(text: str, lines: list[str]) -> str:
    """``text`` with ``lines`` at the end of its header (before the first ``## `` section)."""
    if not lines:
        return text
    head, rest = text.split("\n## ", 1) if "\n## " in text else (text, "")
    return head.rstrip("\n") + "\n\n" + "\n".join(lines) + ("\n## " + rest if rest else "")


def _registry_paragraph(report: Path) -> list[str]:
    """The header's Model Registry paragraph of an existing REPORT.md (as :func:`_with_champions` wrote it)."""
    md = report.read_text() if report.exists() else ""
    head = md.split("\n## ", 1)[0]
    return [p + "\n" for p in head.split("\n\n") if p.startswith("Model Registry: ")][:1]


def _champion_or_warn(experiment: str):
    """:func:`champion`, or None with a warning when the registry refuses (the report is written anyway)."""
    try:
        return champion(experiment)
    except mlflow.exceptions.MlflowException as exc:
        print(f"warning: {experiment}: no champion registered: {exc}", flush=True)
        return None


def champion(experiment: str) -> tuple[str, str] | None:
    """Register the experiment's chosen feedforward (issues 23, 52): among ALL its runs with a logged model
    (headline and side studies: regularised or not, every inversion), the lowest value of the first metric
    of its ``compare_metrics``; the model whose name holds the run's inversion (else its first). Alias
    ``champion``; the version's description states that rule and what the run is; version tags name its
    inversion, model, regulariser and noise, and its tracking metrics in µm."""
    runs = latest_runs(experiment)[0]
    models = tracking.logged_models(experiment)
    runs = runs[runs["run_id"].isin(models)] if not runs.empty else runs
    if runs.empty:
        return None
    cols = [c for c in compare.metric_columns(runs, compare_patterns(runs)) if runs[c].notna().any()]
    if not cols:
        return None
    metric = cols[0].removeprefix("metrics.").removesuffix("_um")
    col = f"metrics.{metric}" if f"metrics.{metric}" in runs else cols[0]
    best = runs.loc[runs[col].astype(float).idxmin()]
    mods = sorted(models[best["run_id"]], key=lambda m: m.name)
    model = next((m for m in mods if str(best.get("tags.invert", "")) in m.name), mods[0])
    shown = {k[len("metrics."):]: v for k, v in best.items() if k.startswith("metrics.evaluate/") and pd.notna(v)}
    # each tracking metric once, in the unit that reads (µm where the run has that twin)
    tags = {k: f"{float(v):.6g}" for k, v in shown.items()
            if k.rsplit("/", 1)[-1] in ("mae_um", "max_abs_um", "rms_um", "sq_norm2")
            or (k.rsplit("/", 1)[-1] in ("mae", "max_abs", "rms") and f"{k}_um" not in shown)}
    factors = {"inversion": "tags.invert", "model": "tags.model", "regularizer": "tags.regularizer",
               "noise_structure": "params.system.noise.structure", "noise_std": "params.system.noise.std"}
    tags |= {k: str(best[c]) for k, c in factors.items() if c in best and pd.notna(best[c])}
    name = best.get("tags.display_name", best["tags.mlflow.runName"])
    tags |= {"run_id": best["run_id"], "run_key": best["tags.mlflow.runName"], "chosen_by": f"min {metric}",
             "run_name": name}
    value = float(best[col])
    rule = (f"Lowest `{col.removeprefix('metrics.')}` ({value:.4g}) among all {len(runs)} runs of `{experiment}` "
            f"with a logged feedforward (every inversion, model and regulariser): `{name}` "
            f"({', '.join(f'{k} {tags[k]}' for k in factors if k in tags)}).")
    desc = tracking.client().get_experiment_by_name(experiment).tags.get(tracking.NOTE, "")
    return tracking.register_champion(experiment, best["run_id"], model, rule, tags, desc)


def compare_patterns(runs: pd.DataFrame) -> list[str]:
    """The experiment's ``compare_metrics`` as its runs logged them (a param), else every ``evaluate/*/mae``."""
    col = "params.compare_metrics"
    vals = runs[col].dropna() if col in runs else []
    for v in vals:
        try:
            got = ast.literal_eval(str(v))
        except (ValueError, SyntaxError):
            continue
        if isinstance(got, list) and got:
            return [str(x) for x in got]
    return ["evaluate/*/mae"]


def _comparison(experiment: str, runs: pd.DataFrame, figdir: Path):
    """summary rows (none) and a REPORT.md part: the sweep's runs side by side by the factors they vary,
    the sweep parents' ``compare/`` artifacts computed again from the runs reported here (issue 23)."""
    if runs.empty or "tags.mlflow.parentRunId" not in runs or runs["tags.mlflow.parentRunId"].isna().all():
        return None
    swept = runs[runs["tags.mlflow.parentRunId"].notna()].copy()
    if len(swept) < 2:
        return None
    if "tags.display_name" in swept:
        swept["tags.mlflow.runName"] = swept["tags.display_name"].where(swept["tags.display_name"].notna(),
                                                                        swept["tags.mlflow.runName"])
    table, findings = compare.comparison(swept, compare_patterns(swept))
    if table.empty or len(table.columns) < 2:
        return None
    fig = compare.figure(table, figdir / f"{experiment}-comparison.png", f"{experiment}: runs side by side")
    md = ["", "", f"### Comparison of the {len(table)} swept runs (the sweep parent's `compare/` artifacts)", "",
          "Every run by the factors its sweep varies, metrics in the units of the name (`_um`: µm); "
          "the MLflow run names lead with the same factors.", "", compare.markdown(table, findings)]
    if fig is not None:
        md += [f"![comparison]({'figures/' + fig.name})", ""]
    return [], "\n".join(md)


def _stop_reasons(experiment: str, runs: pd.DataFrame):
    """summary.csv rows (fits with a stop reason, fits stopped on a cap) and a REPORT.md paragraph
    naming the runs whose training stopped on an iteration cap (train convergence, issue 11)."""
    if "tags.stop_reason" not in runs or runs["tags.stop_reason"].isna().all():
        return None
    fits = runs[runs["tags.stop_reason"].notna()]
    capped = sorted(fits.loc[fits["tags.stop_reason"].str.startswith("max_iter"), "tags.mlflow.runName"])
    rows = [row(experiment, "training", "fits_with_stop_reason", len(fits)),
            row(experiment, "training", "fits_stopped_on_cap", len(capped))]
    counts = ", ".join(f"{k}: {v}" for k, v in fits["tags.stop_reason"].value_counts().sort_index().items())
    md = f"\n\nTraining stop reasons of the {len(fits)} runs ({counts})."
    if capped:
        md += (f" **Flag: {len(capped)} stopped on an iteration cap, not on a tolerance** "
               f"({', '.join(f'`{n}`' for n in capped)}): their numbers are of a fit that was still improving.")
    return rows, md + "\n"


def _spread(results: Path, digests: dict[str, str]) -> tuple[dict, list[str]]:
    """The claims' statistics over restarts (``make reproduce-spread``, :mod:`pipeline.spread`) of the experiments
    whose init_seed-0 rows are this summary's ((experiment, claim) -> its :func:`claim_statistics` row), and the
    report's lines on it and on its checks (another code path's medians against the spread)."""
    meta, csv = results / "spread.json", results / "spread.csv"
    if not (meta.exists() and csv.exists()):
        return {}, []
    info = json.loads(meta.read_text())
    valid, stale = kept_experiments(info, digests)
    lines = []
    if stale:
        lines += [f"`make reproduce-spread`: results/spread.md was built on other rows of {', '.join(stale)} than "
                  "these (stale); rerun it.", ""]
    if not valid:
        return {}, lines
    stat = pd.read_csv(csv, dtype={"claim": str, "variant": str, "metric": str})
    stat[["claim", "variant"]] = stat[["claim", "variant"]].fillna("")
    stat = stat[stat["experiment"].isin(valid)]
    for c in ("holds_median", "holds_min", "holds_max", "decided"):
        stat[c] = stat[c].map(lambda v: None if pd.isna(v) else str(v).lower() in ("true", "1", "1.0"))
    per = claims.claim_statistics(stat)
    lines += [f"### Claim rows over restarts (`make reproduce-spread`, init_seed {', '.join(info['seeds'])})", "",
              f"{', '.join(valid)} rerun with other initial weights and restarts (same data and noise): the claim "
              "table's *holds* is judged on each row's median over the runs; rows whose verdict differs at the "
              "spread's min or max are not decided by these fits. Per claim row: results/spread.md.", ""]
    for check in ("perturb", "isa"):
        f = results / f"spread-check-{check}.json"
        if f.exists():
            j = json.loads(f.read_text())
            if "claim_rows_separated" not in j:
                lines += [f"- `make reproduce-spread SPREAD_CHECK={check}`: results/spread-check-{check}.json was "
                          "judged by an older rule; rerun the check."]
                continue
            read = j["claim_rows_undecided_read_otherwise"]
            sep = ""
            if "claim_rows_separated_by_chance" in j:         # the family's chance and the fresh draws' verdict
                sep = (f" (an equivalent machine separates ~{j['claim_rows_separated_by_chance']:g} by chance, at "
                       f"least one with P = {j['p_any_separated_by_chance']:.2f}"
                       + (f"; fresh draws (`make reproduce-confirm`): {j['claim_rows_separated_confirmed']} "
                          f"confirmed, {j['claim_rows_separated_not_confirmed']} not"
                          if j["claim_rows_separated"] else "") + ")")
            lines += [f"- `make reproduce-spread SPREAD_CHECK={check}` (`{j.get('setting', '')}`): "
                      f"{j['claim_rows_separated']} of {j['claim_rows']} claim rows separated from the spread{sep}, "
                      f"{j['claim_rows_flipped']} decided verdicts flipped"
                      + (f" ({read} rows the spread does not decide read otherwise on the median)" if read else "")
                      + f"; {j['claim_rows_inside']} of {j['claim_rows']} claim-row medians inside the spread, "
                      f"where an equivalent machine leaves ~{j['claim_rows_outside_by_chance']:g} outside by chance "
                      f"(results/spread-check-{check}.md)."]
    return {(r.experiment, r.claim): r for r in per.itertuples()}, lines + [""]


def _claim_table(table: pd.DataFrame, tightened: dict | None = None, verdicts: dict | None = None,
                 spread: dict | None = None) -> list[str]:
    """The header's claim table: a claim holds when every one of its rows holds; beside it, how many
    of the experiment's fits stopped on an iteration cap, the fits named, each with its tightening check
    (``tightened``: (experiment, fit) -> its :func:`pipeline.perturbation.capped_fits` row) where one is current,
    and the verdict in each current check (``verdicts``: check -> (experiment, claim) -> its
    :func:`pipeline.perturbation.claim_verdicts` row): a verdict a check flips is not pinned down by the fits."""
    claimed = table[table["claim"] != ""]
    if claimed.empty:
        return []
    fits = table[table["variant"] == "training"].set_index(["experiment", "metric"])["value"]
    flag = table[table["metric"] == "fit_stopped_on_cap"]          # one row per fit (a fit may feed several runs)
    capped = flag[pd.to_numeric(flag["value"], errors="coerce") == 1].groupby("experiment")["variant"].agg(list)
    out = ["| claim | experiment | holds | in the checks (second machine, emulated; tolerances tightened 10x) "
           "| its experiment's kept fits stopped on a cap (an inner solve or a discarded restart on its cap: "
           "flagged in the experiment's section) |", "| --- | --- | --- | --- | --- |"]
    for (c, e), g in claimed.groupby(["claim", "experiment"], sort=False):
        cap = (f"{float(fits[(e, 'fits_stopped_on_cap')]):.0f} of {float(fits[(e, 'fits_with_stop_reason')]):.0f}"
               if (e, "fits_stopped_on_cap") in fits.index and c not in claims.CLAIMS_WITHOUT_FITS else "")
        if cap and not cap.startswith("0 "):
            named = "; ".join(_capped_fit(e, v, (tightened or {}).get((e, v))) for v in capped.get(e, []))
            cap = f"**{cap}**" + (f" ({named})" if named else "")
        holds = (g["claim_holds"] == "true").all()
        checks = ("a timing: the checks do not compare it" if g["metric"].map(is_timing).all() else
                  _verdict_in_checks(holds, {k: v.get((e, c)) for k, v in (verdicts or {}).items()}))
        st = (spread or {}).get((e, c))
        shown = 'yes' if holds else 'no'
        if st is not None:      # judged on the medians over restarts (issue 52 item 2)
            shown = (f"{'yes' if st.holds_median else 'no'} (median of the restarts"
                     + ("" if st.holds_median == holds else f"; init_seed 0 alone: {'yes' if holds else 'no'}")
                     + (f"; {st.rows_undecided} of {st.rows} rows not decided by the spread" if st.rows_undecided
                        else "") + ")")
        out.append(f"| {c} | {e} | {shown} | {checks} | {cap} |")
    return out + [""]


def _verdict_in_checks(holds: bool, per_check: dict) -> str:
    """A claim's verdict in each current check: the same, or flipped with the claim rows that flipped it
    (their values on both sides and the fit behind them, with its category in the check)."""
    names = {"perturb": "second machine", "tighten": "tightened"}
    parts = []
    for check in ("perturb", "tighten"):
        v = per_check.get(check)
        if v is None:
            parts.append(f"{names[check]}: not checked")
        elif v.holds_pert == holds:
            n = len(v.rows_changed)
            parts.append(f"{names[check]}: same" + (f" ({n} of its rows flip{'s' if n == 1 else ''})" if n else ""))
        else:
            rows = "; ".join(
                f"`{r['variant']}` {r['metric']} {float(r['value_ref']):.3g} → {float(r['value_pert']):.3g}"
                + (f", fit `{r['fit']}` {str(r['category']).replace('_', ' ')}"
                   if isinstance(r["fit"], str) and r["fit"] else "")
                for r in v.rows_changed)
            parts.append(f"**{names[check]}: {'yes' if v.holds_pert else 'no'}** ({rows})")
    return "; ".join(parts)


def _capped_fit(experiment: str, fit: str, t) -> str:
    """A capped fit in the claim table, with what its caps raised (the tightening check) did to it."""
    if t is None:
        return f"fit `{fit}`: no current tightening check (`make reproduce-check CHECK=tighten`)"
    return (f"fit `{fit}`, caps raised in the tightening check: training cost {t.cost_ref:.3g} → {t.cost_pert:.3g}"
            f"{', on its cap again' if t.still_capped else ', stopped on its tolerance'}, its values move by up to "
            f"{t.max_value_change:.0%}")


def _write(path: Path, data: str) -> None:
    """``path`` replaced by ``data`` (:func:`pipeline.atomic.replace_file`: no link followed, no guessable
    name), its hash listed first: known as ours even if the job stops right after the swap."""
    replace_file(path, data, before=lambda blob: owned.allow(path.parent, path.name, blob))


def _shas(experiments) -> str:
    """The git commits the experiments' reported runs were made at (their ``git_sha`` tags)."""
    shas = set()
    for exp in experiments:
        runs, _ = latest_runs(str(exp))
        if "tags.git_sha" in runs:
            shas |= set(runs["tags.git_sha"].dropna())
    return ", ".join(f"`{x[:12]}`" for x in sorted(shas)) or "unknown"


def _sections(md: str) -> tuple[str, dict[str, str]]:
    """REPORT.md split into its header and its ``## <experiment>`` sections (in order)."""
    parts = re.split(r"(?m)^(?=## )", md)
    head, out = parts[0], {}
    for p in parts[1:]:
        out[p.split("\n", 1)[0][3:].strip()] = p.rstrip() + "\n"
    return head, out


def _merge(results: Path, table: pd.DataFrame, text: str, rebuilt: list[str], figdir: Path):
    """``report.update``: the rebuilt sections (and rows, figures) replace theirs in the existing
    report; every other section, row and figure is kept."""
    old_md = (results / "REPORT.md").read_text() if (results / "REPORT.md").exists() else ""
    _, old = _sections(old_md)
    _, new = _sections(text)
    merged = {k: (new[k] if k in new else v) for k, v in old.items()}
    merged |= {k: v for k, v in new.items() if k not in merged}
    if (results / "summary.csv").exists():
        prev = pd.read_csv(results / "summary.csv", dtype=str, keep_default_na=False)
        prev = prev[~prev["experiment"].isin(rebuilt)]
        table = pd.concat([prev, table.astype(str).replace({"None": "", "nan": ""})], ignore_index=True)
    if (results / "figures").exists():
        for f in (results / "figures").iterdir():
            if not any(f.name.startswith(f"{e}-") for e in rebuilt) and not (figdir / f.name).exists():
                shutil.copyfile(f, figdir / f.name)
    kept = [k for k in merged if k not in rebuilt]
    if not rebuilt and old_md.startswith("# Results\n\n"):   # nothing rerun (e.g. make reproduce-spread): its header
        return table, "\n\n".join(old_md.split("\n\n")[:2]) + "\n\n" + "\n".join(merged.values())
    head = ["# Results", "",
            f"Generated by `make reproduce` from the MLflow runs; sections {', '.join(f'`{e}`' for e in rebuilt)} "
            f"rebuilt by `report.update` (runs made at git {_shas(rebuilt)}, report at "
            f"`{tracking.git_sha()[:12]}`), the others kept from the previous report (their runs in this store made "
            f"at git {_shas(kept)}). One section per experiment; every number is also a row of `summary.csv`.", ""]
    return table, "\n".join(head) + "\n" + "\n".join(merged.values())
