"""Report section of experiment ``b2_rot_trans``: claims B2a–B2e of SPEC §8 ([B2] §V–VI).

Reads the FHOFC sweep (``invert.kind=fhofc``: n1 × γ, bound terms ``invert/R/bound/*``) and the
IL-FHOFC runs (``invert.kind=il_fhofc``: ``invert/R/trial_rms`` per trial) of the MLflow
experiment; the Lemma 5.1/5.2 checks (B2e) are computed here with the library on the
rot_trans_nmp linear part (N_k = 30) and on a minimum-phase ARX loop (they take < 1 s and are
also unit tests).  Figures: [B2] Fig. 4 (errors vs n1) and Fig. 5 (error per trial).
"""
from __future__ import annotations

import ast
import functools
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline import tracking
from pipeline.plots import pyplot
from stages.report import claims
from stages.report._figures import copy_figures
from stages.report._rows import fit_cost_row, row

EXPERIMENTS = ("b2_rot_trans",)
REF = "R"                           # the evaluation reference of the experiment
PAPER_LINEAR_TRIAL6 = 1.14e-8       # [B2] Fig. 5: the linear model's IL-FHOFC rms at trial 6 [m]
BOUND = ("identification_error", "inversion_error", "tracking_error", "epsilon", "model_error")


_row = functools.partial(row, EXPERIMENTS[0])


def _n1(run) -> int:
    hidden = run.get("params.model.hidden")
    h = ast.literal_eval(hidden) if isinstance(hidden, str) else []
    return int(h[0]) if h else 0


def _metric(run, key):
    v = run.get(f"metrics.{key}")
    return None if v is None or pd.isna(v) else float(v)


def _history(run_id, key) -> np.ndarray:
    hist = tracking.client().get_metric_history(run_id, key)
    return np.array([m.value for m in sorted(hist, key=lambda m: m.step)])


def sweep_table(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per FHOFC run: n1, γ and the (15) terms, seconds."""
    rows = []
    for _, run in runs[runs.get("params.invert.kind") == "fhofc"].iterrows():
        d = {"n1": _n1(run), "gamma": float(run["params.invert.gamma"]), "run_id": run["run_id"],
             "name": run["tags.mlflow.runName"]}
        for k in BOUND + ("bound_holds",):
            d[k] = _metric(run, f"invert/{REF}/bound/{k}")
        d["fhofc_seconds"] = _metric(run, f"invert/{REF}/fhofc_seconds")
        d["train_seconds"] = _metric(run, "train/seconds")
        d["train_iterations"] = _metric(run, "train/iterations")
        d["train_cost"] = _metric(run, "train/cost")
        d["train_capped"] = _metric(run, "train/stopped_on_cap")
        d["max_iter"] = float(run.get("params.identify.max_iter", "nan"))
        d["n_restarts"] = float(run.get("params.identify.n_restarts", "nan"))
        rows.append(d)
    return pd.DataFrame(rows).sort_values(["gamma", "n1"]).reset_index(drop=True) if rows else pd.DataFrame()


def lemma_checks() -> dict[str, float]:
    """B2e: Lemma 5.1 and 5.2 gaps on rot_trans_nmp's linear part (N_k = 30) and a
    minimum-phase loop (the ARX of SPEC §2.4 with a lead controller)."""
    import control  # lazy: saves 1.9 s of start-up (python-control)

    from pipeline.invert.fhofc import (  # lazy: saves 0.6 s of start-up (numba kernels, [B2] lemmas)
        lemma_5_1_gap,
        lemma_5_2_gap,
    )
    from pipeline.models.closed_loop import (  # lazy: saves 0.9 s of start-up (numba kernels, [B2] lemmas)
        ArxPGNN,
        DiscreteController,
        arx_from_tf,
        simulate_closed_loop,
    )
    from pipeline.systems.rot_trans_nmp import RotTransNMP  # lazy: saves 0.2 s of start-up (numba kernels, [B2] lemmas)

    plant = RotTransNMP(noise={"structure": "output", "std": 0.0})
    cases = {"rot_trans_nmp": (plant.linear_plant(), plant.controller(), 30, 1e-3),
             "minimum_phase": (control.tf([1.0, 0.5], [1.0, -1.5, 0.7], 0.01),
                               control.tf([0.3, -0.2], [1.0, -0.5], 0.01), 60, 1.0)}
    out = {}
    for name, (G, C, N, amp) in cases.items():
        theta, orders = arx_from_tf(G)
        model, ctrl = ArxPGNN(*orders, theta), DiscreteController.from_tf(C)
        r = amp * (1 - np.cos(np.pi * np.arange(N) / (N - 1))) / 2
        true = ArxPGNN(*orders, theta * np.r_[np.ones(orders[0]), np.full(orders[1], 1.05)])
        out[f"lemma_5_1/{name}"] = lemma_5_1_gap(model, ctrl, r)
        out[f"lemma_5_2/{name}"] = lemma_5_2_gap(model, ctrl, r,
                                                 lambda u, t=true, c=ctrl, rr=r: simulate_closed_loop(t, c, rr, u)[0])
    return out


def _fig4(tab: pd.DataFrame, path: Path) -> None:
    plt = pyplot()
    gammas = sorted(tab["gamma"].unique())
    fig, axes = plt.subplots(1, len(gammas), figsize=(5 * len(gammas), 3.6), sharey=True, squeeze=False)
    for ax, g in zip(axes[0], gammas):
        t = tab[tab["gamma"] == g].sort_values("n1")
        x = t["n1"].to_numpy()
        for k, lab in (("identification_error", "identification ‖Y^d-Ŷ^d‖/√N_d"),
                       ("inversion_error", "inversion ‖R-Ŷ‖/√N_k"), ("tracking_error", "tracking ‖R-Y‖/√N_k")):
            ax.semilogy(x, t[k].to_numpy(), "o-", label=lab)
        ax.set_xlabel("neurons n1 (0 = linear model)")
        ax.set_title(f"γ = {g:g}", fontsize=9)
        ax.grid(True, which="both", lw=0.3)
    axes[0][0].set_ylabel("normalised 2-norm [m]")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("[B2] Fig. 4 on rot_trans_nmp", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fig5(curves: dict, path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), squeeze=False)
    for ax, noise in zip(axes[0], (True, False)):
        for (n1, nz, est), c in sorted(curves.items()):
            if nz != noise:
                continue
            label = ("linear" if n1 == 0 else f"PGNN n1={n1}") + ("" if est == "sim_error" else f" ({est})")
            ax.semilogy(np.arange(c["trial_rms"].size), c["trial_rms"], "o-" if est != "oracle" else "s--",
                        label=label)
            if c.get("ideal_rms") is not None and c["ideal_rms"].size:
                ax.semilogy(np.arange(c["ideal_rms"].size), c["ideal_rms"], "k:", lw=0.8)
        ax.set_title("v ~ N(0, 1e-12)" if noise else "v = 0", fontsize=9)
        ax.set_xlabel("trial i")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("rms(R - Y) [m]")
    fig.suptitle("[B2] Fig. 5: IL-FHOFC, α = 1, γ = 1e-8 (dotted: ideal feedforward)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def section(experiment: str, runs: pd.DataFrame, figdir: Path):
    rows, md = [], [f"## {experiment}", "",
                    "[B2] §VI on `rot_trans_nmp`: closed-loop simulation-error identification (16) of "
                    "the PGNN (30) with n1 tanh neurons (n1 = 0: the linear model), FHOFC (17) on the "
                    "300-sample reference R, the bound (15) on the measured output, and IL-FHOFC (22).", ""]
    tab = sweep_table(runs)
    if not tab.empty:
        md += _sweep_section(tab, rows, figdir)
    il = runs[runs.get("params.invert.kind") == "il_fhofc"] if "params.invert.kind" in runs else runs.iloc[:0]
    if not il.empty:
        md += _il_section(il, rows, figdir)
    md += _lemma_section(rows)
    return rows, "\n".join(md)


def _sweep_section(tab, rows, figdir) -> list[str]:
    caps = tab["train_iterations"].dropna()
    budget = (f"{tab['n_restarts'].dropna().max():.0f} restarts × up to {tab['max_iter'].dropna().max():.0f} LM steps; "
              f"{int((caps >= tab['max_iter']).sum())} of {len(caps)} runs' fits stopped on that cap")
    md = ["### Bound terms vs neurons (B2a, B2b, B2d)", "",
          "| n1 | γ | identification | inversion | tracking | ε | ε/tracking | (15) | FHOFC [s] | train [s] |",
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for _, t in tab.iterrows():
        ratio = t["epsilon"] / t["tracking_error"]
        md.append(f"| {t['n1']} | {t['gamma']:g} | {t['identification_error']:.3g} | {t['inversion_error']:.3g} | "
                  f"{t['tracking_error']:.3g} | {t['epsilon']:.3g} | {ratio:.2f} | "
                  f"{'holds' if t['bound_holds'] else 'VIOLATED'} | {t['fhofc_seconds']:.3f} | "
                  f"{t['train_seconds'] or 0:.1f} |")
        v = f"n1={t['n1']}/gamma={t['gamma']:g}"
        if t["gamma"] == tab["gamma"].min() and pd.notna(t["train_cost"]):   # one fit per n1, shared by the γ runs
            capped = {} if pd.isna(t["train_capped"]) else {"train/stopped_on_cap": t["train_capped"]}
            rows += fit_cost_row(EXPERIMENTS[0], f"n1={t['n1']}", {"train/cost": t["train_cost"]} | capped)
        for k in BOUND:
            rows.append(_row(v, k, t[k]))
        # B2a: (15) holds on every run; |ε| ≤ 0.25 tracking for n1 ≥ 8 with γ = 1e-6
        rows.append(_row(v, "bound_15_holds", t["bound_holds"]))
        if t["n1"] >= 8 and np.isclose(t["gamma"], 1e-6):
            rows.append(_row(v, "abs_epsilon_over_tracking", abs(ratio)))
    md.append("")
    # B2b
    g_lo = tab[np.isclose(tab["gamma"], 1e-6)].set_index("n1")
    g_hi = tab[np.isclose(tab["gamma"], 5e-5)].set_index("n1")
    if 1 in g_lo.index and 48 in g_lo.index:
        q = g_lo.loc[48, "identification_error"] / g_lo.loc[1, "identification_error"]
        # the ratio of two fits belongs to the first (its variant): the perturbation check attaches it to n1 = 48
        rows.append(_row("n1=48/gamma=1e-06", "identification_error_n48_over_n1", q))
    for n1, t in g_hi.iterrows():
        if n1 >= 24:
            q = t["inversion_error"] / t["identification_error"]
            rows.append(_row(f"n1={n1}/gamma=5e-05", "inversion_over_identification", q))
    for n1, t in g_lo.iterrows():
        q = t["identification_error"] / t["inversion_error"]
        rows.append(_row(f"n1={n1}/gamma=1e-06", "identification_over_inversion", q))
    # B2d: FHOFC solve time for n1 = 32 (one core: the Makefile sets OMP_NUM_THREADS=1)
    for g, sub in ((1e-6, g_lo), (5e-5, g_hi)):
        if 32 in sub.index:
            sec = float(sub.loc[32, "fhofc_seconds"])
            rows.append(_row(f"n1=32/gamma={g:g}", "fhofc_seconds", sec))
    claims.judge(rows)
    holds_b = [h for _, h, _ in claims.verdicts(rows, "B2b")]
    eps_ok = [r["claim_holds"] for r in rows if r["metric"] == "abs_epsilon_over_tracking"]
    name = "b2_rot_trans-fig4.png"
    _fig4(tab, figdir / name)
    md += [f"![errors vs neurons](figures/{name})", "",
           f"(15) holds on {int(tab['bound_holds'].sum())}/{len(tab)} runs (it is the triangle inequality); "
           f"|ε| {claims.rule('B2a', 'abs_epsilon_over_tracking')}·tracking on {sum(eps_ok)}/{len(eps_ok)} runs "
           "with n1 ≥ 8, γ = 1e-6; the B2b orderings "
           f"hold on {sum(holds_b)}/{len(holds_b)} conditions. FHOFC (N_k = 300) solves in "
           f"{tab['fhofc_seconds'].median():.3f} s median (paper: {claims.paper('B2d', 'fhofc_seconds'):g} s in "
           "MATLAB).", ""]
    if not all(eps_ok):
        md += ["**Why B2a's ε condition fails** (investigated, not tuned): the identification error is "
               "the rms over the whole 45 s record, which is dominated by the excited window [10, 40] s, "
               "while tracking is scored on R without excitation. For well-fitted models ε is therefore negative "
               "(the bound is loose, as (15) allows); where a model "
               "generalises worse to the feedforward's operating point it is positive. |ε| ≤ 0.25·tracking is a "
               "property of this split of the data, not of the method; (15) itself holds on every run. With the "
               "converged stops the fits with n1 ≥ 16 land either on a plateau far above the noise floor or at "
               "it, and "
               "a rounding-level perturbation decides which (results/check-perturb.md): the per-n1 verdicts of "
               "this condition are not pinned down, the count above is one draw.", ""]
    if not all(holds_b):
        md += ["**B2b** rests on one trained model per n1: the orderings move with the random "
               "initialisation and with rounding (results/check-perturb.md), so a failing condition here says "
               f"the training budget ({budget}) does not "
               "reach the same optimum every time.", ""]
    return md


#: the linear model's estimator (identify.theta_star) -> its label; B2c's own linear model is
#: closed-loop output error, chosen before the IL-FHOFC results (conf/experiment/b2_rot_trans_il.yaml)
ESTIMATORS = {"sim_error": "output error", "arx": "one-step ARX", "oracle": "ORACLE: true linear part",
              "sim_error/nn_outputs": "output error; NN of the outputs only (remedy)"}


def _il_curves(il) -> dict:
    """{(n1, noise, estimator): {trial_rms, ideal_rms, zeros, stop}} of the IL-FHOFC runs."""
    curves = {}
    for _, run in il.iterrows():
        nz = str(run.get("params.invert.trial_noise")) == "True"
        est = str(run.get("params.identify.theta_star") or "sim_error")
        if _n1(run) and str(run.get("params.model.nn_inputs") or "all") == "outputs":
            est += "/nn_outputs"      # the remedy: an NN of the output window only
        elif not _n1(run) and str(run.get("params.model.nn_inputs") or "all") == "outputs":
            continue                  # the linear model again (no NN)
        curves[(_n1(run), nz, est)] = {
            "trial_rms": _history(run["run_id"], f"invert/{REF}/trial_rms"),
            "ideal_rms": _history(run["run_id"], f"invert/{REF}/ideal_rms") if nz else None,
            "zeros": run.get("tags.zeros") or "", "stop": run.get("tags.stop_reason") or "?",
            "iterations": _metric(run, "train/iterations"),
            "ident": _metric(run, "train/identification_error"),
            "metrics": {k: v for k in ("train/cost", "train/stopped_on_cap") if (v := _metric(run, k)) is not None}}
    return curves


def b2c_rows(pg: np.ndarray, li: np.ndarray, floor: float) -> list[dict]:
    """SPEC §8 B2c with v = 0, the quantities its conditions judge (stages/report/claims.py): PGNN rms
    minus linear rms at every trial i = 1..6 until both are within 10 % of the γ-floor; PGNN rms at
    i = 6 and its ratio to the floor."""
    out = []
    for i in range(1, min(pg.size, li.size, 7)):
        if pg[i] <= 1.1 * floor and li[i] <= 1.1 * floor:
            break
        out.append(_row(f"trial={i}/noise=False", "pgnn_rms_minus_linear_rms", pg[i] - li[i]))
    if pg.size > 6:
        out.append(_row("n1=32/noise=False/trial=6", "trial_rms_final", pg[6]))
        out.append(_row("n1=32/noise=False/trial=6", "trial_rms_over_floor", pg[6] / floor))
    return out


def _il_section(il, rows, figdir) -> list[str]:
    curves = _il_curves(il)
    md = ["### IL-FHOFC (B2c)", "",
          "Trial i = 0 is the FHOFC feedforward of the identified model. Linear models (n1 = 0) by three "
          "estimators, their B(z) zeros beside the true ones (2.25, −0.773, 0.734); B2c uses the "
          "closed-loop **output-error** estimate, chosen before the IL-FHOFC results on principle "
          "(it is [B2]'s criterion (16), the one that also trains the PGNN, and it is consistent under "
          "the training data's output noise; one-step ARX is not). The ORACLE row uses the plant's true "
          "linear part, which a user does not have: it measures the floor Γ = γΔ puts under IL-FHOFC (22) "
          "(Γ penalises U_ff itself, not its change).", "",
          "| model | estimator | zeros of B(z) | training stop | noise | rms per trial i = 0, 1, … [m] |",
          "| --- | --- | --- | --- | --- | --- |"]
    for (n1, nz, est), c in sorted(curves.items(), key=lambda kv: (kv[0][1], kv[0][0], kv[0][2])):
        stop = c["stop"] + (f" ({c['iterations']:.0f} it.)" if c["iterations"] else "")
        if c["stop"] == "max_iter":
            stop = f"**CAP** {stop}"
        md.append(f"| {'linear' if n1 == 0 else f'PGNN n1={n1}'} | {ESTIMATORS.get(est, est)} | {c['zeros']} | "
                  f"{stop} | {'yes' if nz else 'v = 0'} | " + ", ".join(f"{v:.3g}" for v in c["trial_rms"]) + " |")
        if not nz:                     # one fit per (n1, estimator): the noise only enters the trials
            rows += fit_cost_row(EXPERIMENTS[0], f"n1={n1}/{est}", c["metrics"])
        for i, v in enumerate(c["trial_rms"]):
            rows.append(_row(f"n1={n1}/{est}/noise={nz}/trial={i}", "trial_rms", v,
                             paper={(32, 6): claims.paper("B2c", "trial_rms_final"),
                                    (0, 6): PAPER_LINEAR_TRIAL6}.get((n1, i)) if est == "sim_error" and not nz
                             else None))
    md.append("")
    pg, li = curves.get((32, False, "sim_error")), curves.get((0, False, "sim_error"))
    oracle = curves.get((0, False, "oracle"))
    floor = float(oracle["trial_rms"][-1]) if oracle is not None else None
    if floor is not None:
        rows.append(_row("oracle/noise=False", "gamma_floor", floor))
    if pg is not None and li is not None and floor is not None:
        rows += b2c_rows(pg["trial_rms"], li["trial_rms"], floor)
        md += [f"γ-floor (oracle, trial {oracle['trial_rms'].size - 1}): {floor:.3g} m. PGNN at i = 6: "
               f"{pg['trial_rms'][-1]:.3g} m ({pg['trial_rms'][-1] / floor:.2f} × the floor; paper "
               f"{claims.paper('B2c', 'trial_rms_final'):.3g}); "
               f"linear (output error) at i = 6: {li['trial_rms'][-1]:.3g} m (paper {PAPER_LINEAR_TRIAL6:.3g}).", ""]
    for n1 in (0, 32):
        c = curves.get((n1, True, "sim_error"))
        if c is not None and c["ideal_rms"] is not None and c["ideal_rms"].size:
            i = c["trial_rms"].size - 1
            q = c["trial_rms"][i] / c["ideal_rms"][i]
            rows.append(_row(f"n1={n1}/noise=True/trial={i}", "rms_over_ideal_rms", q))
    rem, rem_n = curves.get((32, False, "sim_error/nn_outputs")), curves.get((32, True, "sim_error/nn_outputs"))
    if rem is not None and rem_n is not None and rem_n["ideal_rms"] is not None and rem_n["ideal_rms"].size:
        q = rem_n["trial_rms"][-1] / rem_n["ideal_rms"][-1]
        rows.append(_row("n1=32/nn_outputs/noise=True", "rms_over_ideal_rms", q))
        full = curves.get((32, True, "sim_error"))
        q_full = full["trial_rms"][-1] / full["ideal_rms"][-1] if full is not None else float("nan")
        lin_n = curves.get((0, True, "sim_error"))
        q_lin = lin_n["trial_rms"][-1] / lin_n["ideal_rms"][-1] if lin_n is not None else float("nan")
        md += ["**Why the noisy B2c row fails, and a remedy tried** (reported whatever it showed): with noise "
               f"the PGNN ends at {q_full:.2f} × the ideal feedforward's rms under the same noise, the linear "
               f"model at {q_lin:.2f} ×: IL-FHOFC inverts the model on targets that carry the trial's noise, and the "
               "NN's input path adds a response of its own that this noise excites. An NN that sees the "
               "output window only (`model.nn_inputs=outputs`) cannot add an input-to-output response of its "
               f"own; it ends at {q:.2f} × (criterion {claims.threshold('B2c', 'rms_over_ideal_rms'):g} ×), but it "
               "fits the cogging far worse (identification "
               f"error {rem['ident'] or float('nan'):.3g} m vs {pg['ident'] if pg else float('nan'):.3g} m) and "
               f"reaches only {rem['trial_rms'][-1]:.3g} m at i = 6 without noise: the cogging of this plant is "
               "not a function of the output window alone, so the remedy trades the noise-free accuracy B2c "
               "is about for noise robustness. B2c's rows use the NN of [B2] (30) (all regressors).", ""]
    capped = [f"n1={k[0]} ({ESTIMATORS.get(k[2], k[2])})" for k, c in curves.items() if c["stop"] == "max_iter"]
    if capped:
        md += [f"**Stopped on the LM cap** (flag): {', '.join(sorted(set(capped)))}; see the loss curves.", ""]
    b2c = [h for _, h, _ in claims.verdicts(claims.judge(rows), "B2c")]
    if b2c and not all(b2c):
        md += [f"**B2c holds on {sum(b2c)}/{len(b2c)} conditions.** The failing rows are listed in "
               "summary.csv; with noise, the comparison is to the ideal feedforward under the same noise.", ""]
    name = "b2_rot_trans-fig5.png"
    _fig5(curves, figdir / name)
    md += [f"![IL-FHOFC per trial](figures/{name})", ""]
    for _, run in il.iterrows():
        copy_figures(run["run_id"], figdir, f"b2_rot_trans-{run['tags.mlflow.runName']}")
    return md


def _lemma_section(rows) -> list[str]:
    gaps = lemma_checks()
    md = ["### Recovery of inverse-model feedforward and ILC (B2e)", "",
          "| check | relative difference |", "| --- | --- |"]
    for k, v in gaps.items():
        md.append(f"| {k} | {v:.2e} |")
        rows.append(_row(k, "relative_difference", v))
    claims.judge(rows)
    md += ["", "Lemma 5.1: receding-horizon FHOFC (h = n_k + 1, Γ = 0) vs the inverse-model feedforward (20); "
           "Lemma 5.2: IL-FHOFC with the linear model and Γ = 0 vs the ILC update (23), 4 trials on a "
           "mismatched plant; N_k = 30 on rot_trans_nmp (its lifted matrix has condition ~1e19 at 300).", ""]
    return md
