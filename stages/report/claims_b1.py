"""Report sections of the [B1] experiments: ``b1_arx_bias`` (claim B1a), ``b1_linear_motor``
(claims B1b, B1c), SPEC §8, and the ``b1_noise_sweep`` noise study (issue 3)."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.metrics import motion_phases
from pipeline.plots import pyplot
from stages.report import _runs, claims
from stages.report._figures import copy_figures, load_errors
from stages.report._rows import fit_cost_row, row, run_metrics

EXPERIMENTS = ("b1_arx_bias", "b1_linear_motor", "b1_noise_sweep")
METHODS = ("physics", "direct", "newton", "analytic")
LABEL = {"physics": "physics (8)", "direct": "direct inverse (13)-(14)",
         "newton": "Newton k=5 (Alg. 1)", "analytic": "analytic (27)"}
PAPER_SECONDS = {"direct": 4.18e-7, "newton": 1.28e-4, "analytic": 3.84e-7}  # [B1] Table I



def section(experiment: str, runs: pd.DataFrame, figdir: Path):
    if experiment == "b1_arx_bias":
        return _arx_bias(experiment, runs, figdir)
    if experiment == "b1_noise_sweep":
        return _noise_sweep(experiment, runs, figdir)
    return _linear_motor(experiment, runs, figdir)


# ---------------------------------------------------------------------------------- B1a
def _arx_bias(experiment, runs, figdir):
    run = runs.iloc[0]
    m = run_metrics(run)
    rows = []
    sizes = sorted(int(k.split("/N")[1]) for k in m if k.startswith("train/forward_error/N"))
    lines = [f"## {experiment}", "",
             "**Claim B1a** ([B1] §II-C): direct inverse identification is biased under noise, "
             "forward identification is consistent. SPEC §2.4 ARX system, white u, equation noise "
             f"σ_v = 0.1, mean parameter error over {int(m.get('train/n_seeds', 0))} data sets per N; "
             "both estimates are the closed-form least squares of the physics-only PGNN "
             "([B1] (7) and (16)-(17)).", "",
             "| N | forward ‖θ̂ - θ0‖ | direct inverse ‖θ̂' - θ0'‖ |", "| --- | --- | --- |"]
    for n in sizes:
        ef, ei = m[f"train/forward_error/N{n}"], m[f"train/inverse_error/N{n}"]
        lines.append(f"| {n} | {ef:.3g} | {ei:.3g} |")
        rows += [row(experiment, f"N{n}", "forward_error", ef),
                 row(experiment, f"N{n}", "inverse_error", ei)]
    slope = m["train/forward_slope"]
    ratio = m["train/inverse_to_forward"]
    dev = m["train/inverse_bias_deviation"]
    rows += claims.judge([
        row(experiment, "forward", "loglog_slope", slope),
        row(experiment, f"N{sizes[-1]}", "inverse_to_forward_error", ratio),
        row(experiment, f"N{sizes[-1]}", "inverse_deviation_from_bias18_rel", dev),
        row(experiment, "asymptotic", "bias18_norm", m["train/bias_norm"]),
    ])
    ok = [h for _, h, _ in claims.verdicts(rows, "B1a")]
    lines += ["", f"- forward error slope on log-log: **{slope:.3f}** (claim: {claims.rule('B1a', 'loglog_slope')}) — "
              f"{'holds' if ok[0] else 'does not hold'};",
              f"- at N = {sizes[-1]}: inverse error / forward error = **{ratio:.1f}** (claim "
              f"{claims.rule('B1a', 'inverse_to_forward_error')}) — {'holds' if ok[1] else 'does not hold'};",
              f"- ‖mean θ̂' - θ0' - bias(18)‖ / ‖bias(18)‖ = **{dev:.3f}** (claim "
              f"{claims.rule('B1a', 'inverse_deviation_from_bias18_rel')}; ‖bias(18)‖ = "
              f"{m['train/bias_norm']:.4g}, closed form from the stationary covariance) — "
              f"{'holds' if ok[2] else 'does not hold'}.", ""]
    for fig in copy_figures(run["run_id"], figdir, experiment):
        lines += [f"![{Path(fig).stem}]({fig})", ""]
    lines.append("The direct-inverse error stays at the predicted bias while the forward error "
                 "falls like N^-1/2, as [B1] (18) and Proposition 4.1 say." if all(ok) else
                 "See the numbers above for which condition failed.")
    return rows, "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------- B1b, B1c
def _variant(run) -> tuple[str, str]:
    """(noise structure, inversion) of a run, from its logged param and tag (never from its name)."""
    return str(run.get("params.system.noise.structure")), str(run.get("tags.invert"))


def _linear_motor(experiment, runs, figdir):
    table: dict[tuple[str, str], dict] = {}
    ids = {}
    for _, run in runs.iterrows():
        noise, method = _variant(run)
        if method in METHODS:
            table[(noise, method)] = run_metrics(run)
            ids[(noise, method)] = run["run_id"]
    rows, lines = [], [f"## {experiment}", "",
                       "**Claims B1b, B1c** ([B1] §VI on the simulated linear motor, SPEC §2.2): the "
                       "indirect PGNN feedforwards (forward PGNN + Newton, [B1] Alg. 1 with k = 5; "
                       "invertible PGNN + analytic inverse (27)) beat the direct-inverse PGNN; all "
                       "PGNNs beat the physics feedforward; per-sample cost table. PGNNs: 16 tanh "
                       "neurons, LM, Λ = 0.01 I (normalised units), best of 10 restarts; training: "
                       "120 s closed loop with Δu ~ N(0, 50²) N; evaluation runs noise-free.", ""]
    refs = sorted({k.split("/")[1] for m in table.values() for k in m
                   if k.startswith("evaluate/") and k.endswith("/mae")},
                  key=lambda s: float(s.lstrip("v")) if s.lstrip("v").replace(".", "").isdigit() else 0)
    for noise in ("equation", "output"):
        have = [mt for mt in METHODS if (noise, mt) in table]
        if not have:
            continue
        lines += [f"### noise structure `{noise}`" + (" (claim B1b)" if noise == "equation"
                                                      else " (reported side by side)"), "",
                  "| method | " + " | ".join(f"MAE {r}" for r in refs) + " | peak v0.15 |",
                  "| --- |" + " --- |" * (len(refs) + 1)]
        for mt in have:
            m = table[(noise, mt)]
            rows += fit_cost_row(experiment, f"{noise}/{mt}", m)
            vals = [m.get(f"evaluate/{r}/mae") for r in refs]
            peak = m.get("evaluate/v0.15/max_abs")
            lines.append(f"| {LABEL[mt]} | " + " | ".join("" if v is None else f"{v:.3g}" for v in vals)
                         + f" | {'' if peak is None else f'{peak:.3g}'} |")
            for r, v in zip(refs, vals):
                if v is not None:
                    rows.append(row(experiment, f"{noise}/{mt}/{r}", "mae", v))
                    rows.append(row(experiment, f"{noise}/{mt}/{r}", "max_abs",
                                     m[f"evaluate/{r}/max_abs"]))
        lines.append("")
        d = table.get((noise, "direct"))
        p = table.get((noise, "physics"))
        for mt in ("newton", "analytic"):
            m = table.get((noise, mt))
            if m is None or d is None:
                continue
            for r in refs:
                rows.append(row(experiment, f"{noise}/{mt}/{r}", "mae_over_direct",
                                m[f"evaluate/{r}/mae"] / d[f"evaluate/{r}/mae"]))
            if "evaluate/v0.15/max_abs" in m:
                rows.append(row(experiment, f"{noise}/{mt}/v0.15", "peak_over_direct",
                                m["evaluate/v0.15/max_abs"] / d["evaluate/v0.15/max_abs"],
                                paper=claims.paper("B1b", "peak_over_direct")))
        for mt in ("direct", "newton", "analytic"):
            m = table.get((noise, mt))
            if m is None or p is None:
                continue
            for r in refs:
                rows.append(row(experiment, f"{noise}/{mt}/{r}", "mae_over_physics",
                                m[f"evaluate/{r}/mae"] / p[f"evaluate/{r}/mae"]))
        # B1c: per-sample cost (median over the samples of the 0.15 m/s reference)
        cost = {mt: table[(noise, mt)].get("invert/v0.15/sample_seconds_median")
                for mt in ("direct", "newton", "analytic") if (noise, mt) in table}
        if noise == "equation" and any(v is not None for v in cost.values()):
            lines += ["| per-sample cost [s] | ours (median, numba kernel called per sample) | "
                      "[B1] Table I (MATLAB, mean) |", "| --- | --- | --- |"]
            for mt, v in cost.items():
                if v is None:
                    continue
                lines.append(f"| {LABEL[mt]} | {v:.3g} | {PAPER_SECONDS[mt]:.3g} |")
                rows.append(row(experiment, f"equation/{mt}/v0.15", "sample_seconds_median", v,
                                paper=PAPER_SECONDS[mt]))
            lines.append("")
        diag = []
        r2 = {mt: table[(noise, mt)].get("invert/nn_r2_unmodelled") for mt in ("newton", "analytic")
              if (noise, mt) in table}
        if any(v is not None for v in r2.values()):
            diag.append("share of the true unmodelled one-step dynamics explained by f_NN on the "
                        "training rows (R²): " + ", ".join(f"{LABEL[k]} {v:.2f}" for k, v in r2.items()
                                                          if v is not None))
        vr = []
        for mt in have:  # the same for every PGNN run (same data, same references)
            vr = [(r, table[(noise, mt)].get(f"invert/{r}/velocity_over_training")) for r in refs]
            vr = [(r, v) for r, v in vr if v is not None]
            if vr:
                break
        if vr:
            diag.append("max reference velocity / max training velocity ([B1] Def. 6: above 1 the NN "
                        "extrapolates): " + ", ".join(f"{r} {v:.2f}" for r, v in vr))
        if diag:
            lines += ["Diagnostics: " + "; ".join(diag) + ".", ""]
        if noise == "equation":
            fig = _mae_figure(table, noise, refs, figdir / f"{experiment}-{noise}-mae.png")
            if fig:
                lines += [f"![MAE vs v_max]({fig})", ""]
    # every `equation` run's evaluate/errors.npz, read once: Fig. 3, the MAE by phase, the peaks' lags
    errors = {mt: z for mt in METHODS if ("equation", mt) in ids
              and (z := load_errors(ids[("equation", mt)])) is not None}
    fig = _fig3(errors, figdir / f"{experiment}-equation-fig3.png")
    if fig:
        lines += [f"![tracking error at 0.15 m/s, every method]({fig})", ""]
    for key in (("equation", "direct"), ("equation", "newton"), ("equation", "analytic")):
        if key in ids:
            for fig in copy_figures(ids[key], figdir, f"{experiment}-{key[0]}-{key[1]}", only=("loss",)):
                lines += [f"![{Path(fig).stem}]({fig})", ""]
    claims.judge(rows)
    verdicts = claims.verdicts(rows, "B1b") + claims.verdicts(rows, "B1c")
    if verdicts:
        failed = [v for v in verdicts if not v[1]]
        lines += [f"B1b/B1c conditions (`equation` noise): {len(verdicts) - len(failed)} of "
                  f"{len(verdicts)} hold."]
        if failed:
            lines += ["Failed: " + "; ".join(f"{t} (value {x:.3g})" for t, _, x in failed) + ".", ""]
            lines += _mae_diagnosis(failed, table, refs, _phase_mae(errors, refs))
            if any("peak" in t for t, _, _ in failed):
                lines += _peak_diagnosis(table, rows, experiment,
                                         failing=[mt for mt in METHODS if any(t.startswith(f"{mt} peak")
                                                                             for t, _, _ in failed)],
                                         m_true=_first_param(runs, "system.m"), lags=_peak_lags(errors))
        lines.append("")
    return rows, "\n".join(lines) + "\n"


def side_section(experiment, runs, side, figdir):
    """Regularised vs not (issue 23): the headline runs (physics-L2 Λ, [B1] §VI) against the same jobs
    with ``regularizer=none``: MAE per reference and the PGNN's mass side by side, and the B1b
    conditions evaluated on the unregularised PGNNs (rows ``regularizer=none/...``, no claim)."""
    head = {(_variant(r)): run_metrics(r) for _, r in runs.iterrows()}
    free = {(_variant(r)): run_metrics(r) for _, r in side.iterrows()}
    with tempfile.TemporaryDirectory() as tmp:     # its figures are not shown: the headline's are
        side_rows, _ = _linear_motor(experiment, side, Path(tmp))
    rows = [dict(r, variant=f"regularizer=none/{r['variant']}", claim="", claim_holds=None) for r in side_rows]
    held = [r for r in side_rows if r["claim"] == "B1b"]    # the conditions judged on the side runs
    held_head = []
    with tempfile.TemporaryDirectory() as tmp:
        held_head = [r for r in _linear_motor(experiment, runs, Path(tmp))[0] if r["claim"] == "B1b"]
    refs = sorted({k.split("/")[1] for m in free.values() for k in m
                   if k.startswith("evaluate/") and k.endswith("/mae")})
    lines = ["", "### Regularised vs not ([B1] (12), (14): Λ = 0.01 I against Λ = 0)", "",
             "The same jobs without the physics regulariser (`regularizer=none`); MAE in µm, the PGNN's mass in kg "
             "(true: the system's m). Ratio = without / with.", "",
             "| noise | method | " + " | ".join(f"MAE {r} with / without / ratio" for r in refs)
             + " | mass with / without |",
             "| --- | --- |" + " --- |" * (len(refs) + 1)]
    changes = []
    for key in sorted(free, key=lambda k: (k[0], METHODS.index(k[1]) if k[1] in METHODS else 9)):
        if key[1] not in METHODS or key not in head:
            continue
        a, b = head[key], free[key]
        cells = []
        for r in refs:
            x, y = a.get(f"evaluate/{r}/mae"), b.get(f"evaluate/{r}/mae")
            if x is None or y is None:
                cells.append("")
                continue
            cells.append(f"{1e6 * x:.3g} / {1e6 * y:.3g} / {y / x:.3f}")
            rows.append(row(experiment, f"regularizer=none/{key[0]}/{key[1]}/{r}", "mae_over_regularised", y / x))
            changes.append((abs(y / x - 1), key, r, y / x))
        ma, mb = a.get("train/theta_phy/m"), b.get("train/theta_phy/m")
        mass = f"{ma:.3f} / {mb:.3f}" if ma is not None and mb is not None and key[1] != "physics" else ""
        lines.append(f"| {key[0]} | {LABEL[key[1]]} | " + " | ".join(cells) + f" | {mass} |")
    lines.append("")
    if changes:
        big = max(changes)
        same = [c for c in changes if c[0] == 0]
        lines.append(f"Effect: the largest change of an MAE is {100 * (big[3] - 1):+.1f}% "
                     f"({big[1][0]}/{LABEL[big[1][1]]} at {big[2]}); {len(same)} of {len(changes)} MAEs are "
                     "identical to the bit"
                     + (" (the physics feedforward (8) uses only the baseline θ*_phy: no regulariser acts on it)"
                        if any(c[1][1] == "physics" for c in same) else "") + ".")
    if held and held_head:
        n, nh = sum(bool(r["claim_holds"]) for r in held), sum(bool(r["claim_holds"]) for r in held_head)
        lines.append(f"B1b conditions (`equation` noise) with the unregularised PGNNs: {n} of {len(held)} hold "
                     f"(regularised: {nh} of {len(held_head)}); the claim is stated for the regularised ones.")
    return rows, "\n".join(lines) + "\n"


PHASE_LABEL = {"accel": "accelerating", "constvel": "constant velocity", "standstill": "standstill"}


def _ratio(a, b) -> float:
    return a / b if b else float("nan")


def _phase_mae(errors, refs) -> dict[tuple[str, str], dict[str, tuple[float, float]]]:
    """{(method, ref): {phase: (share of the samples, its part of the MAE: Σ_phase |e| / N)}} of the
    `equation` runs, from their evaluate/errors.npz (``errors``: {method: arrays}): which motion phase an
    MAE comes from."""
    out = {}
    for mt, z in errors.items():
        for r in refs:
            if f"{r}/e" not in z:
                continue
            e = np.abs(z[f"{r}/e"])
            out[(mt, r)] = {k: (float(m.mean()), float(e[m].sum()) / e.size)
                            for k, m in motion_phases(z[f"{r}/r"]).items()}
    return out


def _phase_clause(mt, ref, parts, table) -> str | None:
    """Why ``mt``'s MAE at ``ref`` is not 0.8x the direct inverse's: the phase where its part of the MAE
    exceeds the direct's most, when that excess outweighs what it gains in the other phases (None else)."""
    a, d = parts.get((mt, ref)), parts.get(("direct", ref))
    if not a or not d:
        return None
    excess = {k: a[k][1] - d[k][1] for k in PHASE_LABEL}
    worst = max(excess, key=excess.get)
    gain = -sum(v for k, v in excess.items() if k != worst)
    if excess[worst] <= 0 or excess[worst] <= gain:
        return None
    ff = [table.get(("equation", m), {}).get(f"evaluate/{ref}/ff_rms_{worst}") for m in (mt, "direct")]
    return (f"{LABEL[mt]} at {ref}: {a[worst][0]:.0%} of its samples are {PHASE_LABEL[worst]}, where its errors add "
            f"{1e6 * a[worst][1]:.2f} µm to the MAE against the direct inverse's {1e6 * d[worst][1]:.2f} µm"
            + (f" (force error {ff[0]:.2f} against {ff[1]:.2f} N rms)" if None not in ff else "")
            + (f"; it gains only {1e6 * gain:.2f} µm in the other phases" if gain >= 0 else
               f"; it loses {1e6 * -gain:.2f} µm more in the other phases"))


def _mae_diagnosis(failed, table, refs, parts=None) -> list[str]:
    """Why the failed MAE conditions of B1b fail, from the run diagnostics (computed, not written in):
    how much of the unmodelled dynamics each NN explains, how far each reference leaves the
    training range ([B1] Def. 6), and (``parts``: :func:`_phase_mae`) which motion phase decides the MAE."""
    why = []
    r2 = {mt: table.get(("equation", mt), {}).get("invert/nn_r2_unmodelled") for mt in ("newton", "analytic")}
    if any(t.startswith("analytic MAE") for t, _, _ in failed) and r2.get("analytic") is not None:
        why.append(f"the invertible PGNN's NN explains R² = {r2['analytic']:.2f} of the true unmodelled one-step "
                   f"dynamics on the training rows (the forward PGNN's: {r2.get('newton') or float('nan'):.2f}), "
                   "so its analytic inverse stays close to the physics feedforward and does not reach 0.8× the "
                   "direct inverse's error")
    vr = {}
    for mt in METHODS:   # the same for every PGNN run (same data, same references); physics has none
        vr = {r: v for r in refs
              if (v := table.get(("equation", mt), {}).get(f"invert/{r}/velocity_over_training")) is not None}
        if vr:
            break
    lost = [t.rsplit(" at ", 1)[1] for t, _, _ in failed if t.startswith("direct MAE < physics")]
    if lost and all(vr.get(r) is not None for r in lost):
        why.append("the direct-inverse PGNN loses to the physics feedforward at " + ", ".join(
            f"{r} (reference velocity {vr[r]:.2f}× the training maximum)" for r in lost)
            + ": where the reference leaves the training range its NN extrapolates ([B1] Def. 6)")
    for t, _, _ in failed:   # which motion phase decides each failed MAE ratio
        mt, _, rest = t.partition(" MAE ≤ 0.8× direct at ")
        if rest and (c := _phase_clause(mt, rest, parts or {}, table)):
            why.append(c)
    if not why:
        return []
    return ["**Why** (from the diagnostics above, not tuned): " + "; ".join(why) + ". Whether these fits are "
            "pinned by their tolerances is measured by the checks at the top of this report.", ""]


def _peak_diagnosis(table, rows, experiment, failing=("newton", "analytic"), m_true=float("nan"),
                    lags=None) -> list[str]:
    """Why the peak condition fails, read from the runs: the peak error per motion phase at
    0.15 m/s (evaluate/<ref>/max_abs_<phase>), the feedforward's force error against the exact
    optimal input per phase (evaluate/<ref>/ff_rms_<phase>, the equation plant's inverse) and
    ``lags`` {method: s from the end of the last acceleration phase to the peak}. Every sentence
    is printed only when the numbers it states were checked."""
    ref = "v0.15"
    get = lambda mt, key: table.get(("equation", mt), {}).get(key)  # noqa: E731
    have = [mt for mt in METHODS if all(get(mt, f"evaluate/{ref}/max_abs_{k}") is not None for k in PHASE_LABEL)]
    if "direct" not in have:
        return ["(No per-phase metrics in these runs: rerun `make reproduce` to get them.)"]
    out = ["| peak error at 0.15 m/s [m] (phases of the reference) | " + " | ".join(PHASE_LABEL.values()) + " |",
           "| --- |" + " --- |" * len(PHASE_LABEL)]
    for mt in have:
        out.append(f"| {LABEL[mt]} | " + " | ".join(f"{get(mt, f'evaluate/{ref}/max_abs_{k}'):.3g}"
                                                   for k in PHASE_LABEL) + " |")
        if mt in ("newton", "analytic"):
            for k in PHASE_LABEL:
                v = _ratio(get(mt, f"evaluate/{ref}/max_abs_{k}"), get("direct", f"evaluate/{ref}/max_abs_{k}"))
                rows.append(row(experiment, f"equation/{mt}/{ref}", f"peak_over_direct_{k}", v))
    out.append("")
    ind = [mt for mt in ("newton", "analytic") if mt in failing and mt in have]
    keys = [(r, k) for r in ("v0.05", ref) for k in ("accel", "constvel")]
    ff = {(mt, r, k): get(mt, f"evaluate/{r}/ff_rms_{k}") for mt in have for r, k in keys}
    if not ind or any(ff[(mt, r, k)] is None for mt in ind + ["direct"] for r, k in keys):
        return out
    out += ["Feedforward force error u_ff - f̂ against the exact optimal input f̂ (rms per phase) [N]:", "",
            "| method | accelerating 0.05 m/s | constant velocity 0.05 m/s | accelerating 0.15 m/s | "
            "constant velocity 0.15 m/s |", "| --- | --- | --- | --- | --- |"]
    for mt in have:
        if all(ff[(mt, r, k)] is not None for r, k in keys):
            out.append(f"| {LABEL[mt]} | " + " | ".join(f"{ff[(mt, r, k)]:.2f}" for r, k in keys) + " |")
    out.append("")
    acc = {mt: _ratio(ff[("direct", ref, "accel")], ff[(mt, ref, "accel")]) for mt in ind}
    grow = {mt: _ratio(ff[(mt, ref, "constvel")], ff[(mt, "v0.05", "constvel")]) for mt in ind}
    alike = {mt: _ratio(ff[("direct", ref, "constvel")], ff[(mt, ref, "constvel")]) for mt in ind}
    speed = get(ind[0], f"invert/{ref}/velocity_over_training")
    m_f, m_d = get("newton", "train/theta_phy/m"), get("direct", "train/theta_phy/m")
    names = " and ".join(LABEL[mt] for mt in ind)
    out.append("Where the reference accelerates, the direct PGNN's force error is "
               + ", ".join(f"{acc[mt]:.1f}× {LABEL[mt]}'s" for mt in ind)
               + (f" (its mass {m_d:.2f} kg, the forward PGNN's {m_f:.2f} kg, true {m_true:g} kg)"
                  if m_d and m_f and m_true == m_true else "")
               + ". At constant velocity the force error grows from 0.05 to 0.15 m/s by "
               + ", ".join(f"{grow[mt]:.1f}× ({LABEL[mt]}, to {ff[(mt, ref, 'constvel')]:.2f} N)" for mt in ind)
               + f"; the direct PGNN's is {ff[('direct', ref, 'constvel')]:.2f} N there"
               + (f", and the 0.15 m/s reference is {speed:.2f}× the fastest training velocity ([B1] Definition 6)"
                  if speed else "") + ".")
    if lags:
        out.append("Each method's peak comes " + ", ".join(f"{1e3 * v:.0f} ms ({LABEL[mt]})" for mt, v in lags.items())
                   + " after the end of the last acceleration phase before it (the figure shades them).")
    # the conclusion, per indirect PGNN whose numbers carry it: its own mass within 2 %, a force error >= 2x
    # smaller than the direct's where the reference accelerates, growing >= 2x with speed at constant
    # velocity to within +-50 % of the direct's there, and its peak in the constant-velocity phase
    peak_at = {mt: max(PHASE_LABEL, key=lambda k: get(mt, f"evaluate/{ref}/max_abs_{k}")) for mt in ind}
    mass_ok = {mt: (mass := get(mt, "train/theta_phy/m")) is not None and m_true == m_true
               and abs(mass - m_true) <= 0.02 * m_true for mt in ind}
    held = [mt for mt in ind if acc[mt] >= 2.0 and grow[mt] >= 2.0 and 0.7 <= alike[mt] <= 1.5 and mass_ok[mt]
            and peak_at[mt] == "constvel"]
    if held:
        names = " and ".join(LABEL[mt] for mt in held)
        out.append(f"So: {names} {'has' if len(held) == 1 else 'have'} the mass within 2% and, where the reference "
                   "accelerates, a force error ≥ 2× smaller than the direct PGNN's; "
                   f"{'its' if len(held) == 1 else 'their'} peak lies at constant velocity, where what remains "
                   "is the velocity-dependent force that every PGNN extrapolates alike above the training speeds "
                   "(within ±50% of the direct's there), which no inversion removes, "
                   f"so {'its' if len(held) == 1 else 'their'} peak is not 3× below the direct's.")
    return out


def _peak_lags(errors, ref: str = "v0.15") -> dict[str, float]:
    """{method: seconds from the end of the last acceleration phase before |e|'s peak to the peak}
    (0 when the peak is inside an acceleration phase), from the runs' evaluate/errors.npz (``errors``)."""
    out = {}
    for mt, z in errors.items():
        if f"{ref}/e" not in z:
            continue
        acc = np.flatnonzero(motion_phases(z[f"{ref}/r"])["accel"])
        i = int(np.argmax(np.abs(z[f"{ref}/e"])))
        before = acc[acc <= i]
        if before.size:
            out[mt] = (i - before[-1]) * float(z["Ts"])
    return out


def _fig3(errors, path: Path, ref: str = "v0.15"):
    """[B1] Fig. 3: the tracking error of every method at 0.15 m/s in one plot, accelerating
    phases shaded (from each run's evaluate/errors.npz artifact, ``errors``)."""
    plt = pyplot()

    sig = {mt: z for mt, z in errors.items() if f"{ref}/e" in z}
    if not sig:
        return None
    fig, ax = plt.subplots(figsize=(8, 3.5))
    z = next(iter(sig.values()))
    t = np.arange(z[f"{ref}/r"].size) * float(z["Ts"])
    acc = motion_phases(z[f"{ref}/r"])["accel"]
    ax.fill_between(t, 0, 1, where=acc, color="0.9", transform=ax.get_xaxis_transform(), label="accelerating")
    for mt, z in sig.items():
        ax.plot(t, 1e6 * z[f"{ref}/e"], lw=0.8, label=LABEL[mt])
    ax.set_xlabel("time [s]")
    ax.set_ylabel("e = r - y [µm]")
    ax.set_title(f"[B1] Fig. 3 analogue: tracking error at v_max = {ref.lstrip('v')} m/s "
                 "(`equation` noise in the training data)", fontsize=9)
    ax.legend(fontsize=7, ncol=5, loc="upper center")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return f"figures/{path.name}"


def _mae_figure(table, noise, refs, path: Path):
    plt = pyplot()
    v = [float(r.lstrip("v")) for r in refs]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    drawn = False
    for mt in METHODS:
        m = table.get((noise, mt))
        if m is None:
            continue
        ax.plot(v, [m.get(f"evaluate/{r}/mae", np.nan) for r in refs], "o-", label=LABEL[mt])
        drawn = True
    if not drawn:
        plt.close(fig)
        return None
    ax.set_xlabel("max reference velocity [m/s]")
    ax.set_ylabel("MAE of e = r - y [m]")
    ax.set_title(f"[B1] Fig. 4 analogue ({noise} noise in the training data)", fontsize=9)
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return f"figures/{path.name}"


# ---------------------------------------------------------------------------------- noise sweep
# estimated mass of each model: (label, job whose run carries it, metric)
MASS = (("forward LS θ*_phy (7)", "newton", "train/theta_phy_star/m"),
        ("inverse LS θ'*_phy (16)", "direct", "train/theta_phy_star/m"),
        ("forward PGNN (10)", "newton", "train/theta_phy/m"),
        ("direct-inverse PGNN (13)", "direct", "train/theta_phy/m"),
        ("invertible PGNN (26)", "analytic", "train/theta_phy/m"))
SWEEP_REFS = ("v0.05", "v0.15")  # in the tables and figure: the training speed and [B1] Fig. 3's


def _first_param(runs: pd.DataFrame, key: str) -> float:
    """The first numeric value of param ``key`` over the runs (NaN if none has it)."""
    v = pd.to_numeric(runs.get(f"params.{key}", pd.Series(dtype=float)), errors="coerce").dropna()
    return float(v.iloc[0]) if len(v) else float("nan")


def _sweep_table(runs) -> dict:
    """{(structure, σ, method): metrics}."""
    table = {}
    for _, run in runs.iterrows():
        noise, method = _variant(run)
        sigma = run.get("params.system.noise.std")
        if method in METHODS and sigma is not None and pd.notna(sigma):
            table[(noise, float(sigma), method)] = run_metrics(run)
    return table


def _noise_sweep(experiment, runs, figdir):
    table = _sweep_table(runs)
    sigmas = sorted({k[1] for k in table})
    structures = [s for s in ("equation", "output") if any(k[0] == s for k in table)]
    m_true = _first_param(runs, "system.m")
    n_restarts = _first_param(runs, "identify.n_restarts")
    rows = []
    lines = [f"## {experiment}", "",
             "**Noise study** ([B1] §II-C, Prop. 4.1, Remark 4.2 on the simulated linear motor, SPEC §2.2): "
             "the `b1_linear_motor` set-up with the training-data noise swept, for both noise "
             "structures: `equation` (NARX noise σ_v, forward identification consistent) and `output` "
             f"(measurement noise σ_y). True mass m = {m_true:g} kg. PGNNs: best of "
             f"{n_restarts:.0f} restarts (the headline uses 10; the "
             "restart seeds are the first ones of those 10). Evaluation runs are noise-free.", "",
             "Estimated mass [kg]:", "",
             "| noise | σ [m] | " + " | ".join(lbl for lbl, _, _ in MASS) + " |",
             "| --- | --- |" + " --- |" * len(MASS)]
    for s in structures:
        for sg in sigmas:
            vals = []
            for lbl, job, key in MASS:
                v = table.get((s, sg, job), {}).get(key)
                vals.append("" if v is None else f"{v:.3f}")
                if v is not None:
                    rows.append(row(experiment, f"{s}/sigma{sg:g}/{job}", key.replace("train/", ""), v))
            lines.append(f"| {s} | {sg:g} | " + " | ".join(vals) + " |")
    refs = [r for r in SWEEP_REFS if any(f"evaluate/{r}/mae" in m for m in table.values())]
    lines += ["", "MAE of e = r - y [m] on the noise-free evaluation runs (every v_max is in "
              "summary.csv):", "",
              "| noise | σ [m] | " + " | ".join(f"{LABEL[mt]} {r}" for r in refs for mt in METHODS) + " |",
              "| --- | --- |" + " --- |" * (len(refs) * len(METHODS))]
    for s in structures:
        for sg in sigmas:
            vals = []
            for r in refs:
                for mt in METHODS:
                    v = table.get((s, sg, mt), {}).get(f"evaluate/{r}/mae")
                    vals.append("" if v is None else f"{v:.3g}")
            lines.append(f"| {s} | {sg:g} | " + " | ".join(vals) + " |")
            for mt in METHODS:
                rows += fit_cost_row(experiment, f"{s}/sigma{sg:g}/{mt}", table.get((s, sg, mt), {}))
                for k, v in sorted(table.get((s, sg, mt), {}).items()):  # stable row order
                    if k.startswith("evaluate/") and k.rsplit("/", 1)[1] in ("mae", "max_abs"):
                        rows.append(row(experiment, f"{s}/sigma{sg:g}/{mt}/{k.split('/')[1]}",
                                        k.rsplit("/", 1)[1], v))
    lines += ["", "Peak error at 0.15 m/s [m] ([B1] Fig. 3's reference):", "",
              "| noise | σ [m] | " + " | ".join(LABEL[mt] for mt in METHODS) + " |",
              "| --- | --- |" + " --- |" * len(METHODS)]
    for s in structures:
        for sg in sigmas:
            vals = [table.get((s, sg, mt), {}).get("evaluate/v0.15/max_abs") for mt in METHODS]
            lines.append(f"| {s} | {sg:g} | " + " | ".join("" if v is None else f"{v:.3g}" for v in vals) + " |")
    lines.append("")
    lines += _sweep_findings(table, sigmas, structures, m_true)
    lines += _headline_check(table)
    fig = _sweep_figure(table, sigmas, structures, refs, m_true, figdir / f"{experiment}.png")
    if fig:
        lines += [f"![noise sweep]({fig})", ""]
    return rows, "\n".join(lines) + "\n"


def _sweep_findings(table, sigmas, structures, m_true) -> list[str]:
    """What the sweep shows, computed from the numbers (nothing asserted beforehand)."""
    out = []
    for s in structures:
        fwd = {sg: table.get((s, sg, "newton"), {}).get("train/theta_phy_star/m") for sg in sigmas}
        inv = {sg: table.get((s, sg, "direct"), {}).get("train/theta_phy_star/m") for sg in sigmas}
        fwd = {k: v for k, v in fwd.items() if v is not None}
        inv = {k: v for k, v in inv.items() if v is not None}
        if not fwd or not inv or not m_true == m_true:  # no estimates, or no true mass to compare with
            continue
        dev_f = max(abs(v - m_true) / m_true for v in fwd.values())
        lo, hi = min(inv), max(inv)
        out.append(f"- `{s}`: the forward LS mass stays within {100 * dev_f:.1f}% of the true mass at every σ; "
                   f"the inverse LS mass moves from {inv[lo]:.2f} (σ = {lo:g}) to {inv[hi]:.2f} kg "
                   f"(σ = {hi:g}), {100 * (inv[hi] - m_true) / m_true:+.1f}% off the true mass.")
        d, n = table.get((s, hi, "direct"), {}), table.get((s, hi, "newton"), {})
        d0, n0 = table.get((s, lo, "direct"), {}), table.get((s, lo, "newton"), {})
        both = lambda key: all(key in x for x in (d, n, d0, n0))  # noqa: E731
        if both("evaluate/v0.05/mae"):
            out.append(f"  Direct-inverse PGNN MAE at 0.05 m/s: {d0['evaluate/v0.05/mae']:.3g} m at σ = {lo:g} → "
                       f"{d['evaluate/v0.05/mae']:.3g} m at σ = {hi:g}; Newton: {n0['evaluate/v0.05/mae']:.3g} → "
                       f"{n['evaluate/v0.05/mae']:.3g} m.")
        if both("evaluate/v0.15/max_abs"):
            q0 = _ratio(n0["evaluate/v0.15/max_abs"], d0["evaluate/v0.15/max_abs"])
            q1 = _ratio(n["evaluate/v0.15/max_abs"], d["evaluate/v0.15/max_abs"])
            out.append(f"  Newton / direct peak error at 0.15 m/s: {q0:.2f} at σ = {lo:g}, {q1:.2f} at σ = {hi:g}.")
    return out + ([""] if out else [])


def _headline_check(table) -> list[str]:
    """This sweep at the headline's noise level against the b1_linear_motor headline runs (their
    noise level and restart count read from their params): how much the best-of-N training spreads."""
    head, _ = _runs.split_side("b1_linear_motor", _runs.latest_runs("b1_linear_motor")[0])
    if head.empty:
        return []
    out, rel, sig, nr = [], [], set(), set()
    for _, run in head.iterrows():
        noise, mt = _variant(run)
        sigma = pd.to_numeric(pd.Series([run.get("params.system.noise.std")]), errors="coerce").iloc[0]
        here = table.get((noise, float(sigma), mt))
        if mt not in METHODS or here is None:
            continue
        a, b = here.get("evaluate/v0.15/mae"), run_metrics(run).get("evaluate/v0.15/mae")
        if a is not None and b:
            out.append(f"{noise}/{mt} {a:.3g} vs {b:.3g}")
            rel.append(abs(a - b) / b)
            sig.add(float(sigma))
            nr.add(str(run.get("params.identify.n_restarts", "?")))
    if not out:
        return []
    return [f"Restart sensitivity: MAE at 0.15 m/s, σ = {', '.join(f'{x:g}' for x in sorted(sig))}, this sweep vs the "
            f"`b1_linear_motor` headline (best of {', '.join(sorted(nr))}): " + "; ".join(sorted(out))
            + f". They differ by up to {100 * max(rel):.0f}%: MAE differences between σ values smaller than "
            "that cannot be told apart from the spread of the non-convex training.", ""]


def _sweep_figure(table, sigmas, structures, refs, m_true, path: Path):
    plt = pyplot()
    if not table or not structures:
        return None
    x = np.arange(len(sigmas))
    fig, axes = plt.subplots(2, len(structures), figsize=(5 * len(structures), 6.5), squeeze=False,
                             sharex=True)
    for j, s in enumerate(structures):
        ax = axes[0, j]
        for i, (lbl, job, key) in enumerate(MASS):  # LS dashed over the PGNN it starts (often equal)
            style = dict(ls="--", marker="x", ms=8, zorder=3) if "LS" in lbl else dict(ls="-", marker="o")
            ax.plot(x, [table.get((s, sg, job), {}).get(key, np.nan) for sg in sigmas], color=f"C{i}",
                    label=lbl, **style)
        ax.axhline(m_true, color="k", ls=":", lw=1, label="true m")
        ax.set_ylabel("estimated mass [kg]")
        ax.set_title(f"`{s}` noise in the training data", fontsize=9)
        ax.legend(fontsize=6)
        ax = axes[1, j]
        for i, mt in enumerate(METHODS):
            for r, ls in zip(refs, ("-", "--")):
                ax.semilogy(x, [table.get((s, sg, mt), {}).get(f"evaluate/{r}/mae", np.nan) for sg in sigmas],
                            ls, marker="o", color=f"C{i}", label=f"{LABEL[mt]} {r}")
        ax.set_ylabel("MAE of e = r - y [m]")
        ax.set_xlabel("training-data noise σ [m]")
        ax.set_xticks(x, [f"{sg:g}" for sg in sigmas])
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return f"figures/{path.name}"
