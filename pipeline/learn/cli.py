"""``pgnn-ff learn``: a learning campaign from the command line (README "Learn on the machine").

    pgnn-ff learn init CAMPAIGN --config campaign.yaml --reference ref.csv [--u-ff0 u_ff.csv] [--force]
    pgnn-ff learn init CAMPAIGN --run RUN_ID --reference ref.csv [--config learn.yaml]  # the model of a run
    pgnn-ff learn CAMPAIGN --recording trial_<j>.csv --out u_ff_<j+1>.csv
    pgnn-ff learn run CAMPAIGN --machine sim:<module>:<function> [--trials 10]
    pgnn-ff learn refit CAMPAIGN [--physics-only] [--trials j,k] [--campaign-only] [--restarts N] [--terms a,b]
                                                      # the physics, and the run's PGNN, on the trials
    pgnn-ff learn feedforward CAMPAIGN --reference new.csv --out u_ff.csv [--campaign-model] [--physics]
    pgnn-ff learn export CAMPAIGN --out DIR [--trial j] [--cc CC]   # the u_ff as C99 (the table family)
    pgnn-ff learn export CAMPAIGN --out DIR --model   # the refitted PGNN's law (pgnn-ff export of the refit run)

Bad input (a recording of another reference or feedforward, a diverging gain, …) is one line on stderr and
exit code 2.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import ConfigError, ExportError
from pipeline.learn import campaign, machine


def _line(h: dict) -> str:
    meas = h.get("measured_rho")
    warn = ""
    if meas is not None and meas >= 1.0:   # two trials measured the loop
        lo, hi = h["measured_band"]
        ratio = h.get("measured_ratio")
        warn = f"; WARNING: the last two trials measure |Q(1 - α L G)| = {meas:.3g} ≥ 1 on {lo:.3g}-{hi:.3g} Hz"
        if ratio is not None and not 0.5 <= ratio <= 2.0:
            warn += (f", where the plant responds {ratio:.3g}x what the model predicts: check the model's "
                     "parameters (M, F_v, K) or refit them (learn refit)")
        for a, b in h.get("uncured_bands") or []:
            warn += (f"; on {a:.3g}-{b:.3g} Hz the plant's phase is more than 90° from the model's and no learning "
                     "gain converges: lower learn.q_cutoff_hz below it or refit the model (the rollback guards the "
                     "trials)")
    if h.get("stalled"):
        warn += ("; STALLED: the gain is below 1/64 of learn.gain, so the trials hardly learn: the model is off "
                 "where the warnings say; refit it (learn refit) and start a new campaign from the best trial's u_ff "
                 "(--u-ff0)")
    sol = h.get("solve")
    if sol:    # norm_optimal: how its solve stopped
        sol = (f"; solve {sol['stop']} (residual {sol['residual']:.2g}" + ("" if sol["stop"] == "converged" else
               f" > learn.rtol {sol['rtol']:g}: WARNING, raise learn.max_sweeps, or learn.rtol if that is rounding")
               + ")")
    return (f"trial {h['trial']}: rms {h['rms']:.4g} m, MAE {h['mae']:.4g} m, max {h['max']:.4g} m, noise floor "
            f"{h['noise_floor']:.3g} m -> {h['decision']} (gain {h['gain']:g}"
            + (f", Q's cutoff lowered to {h['q_cutoff_hz']:.4g} Hz below the failing band" if h["decision"] == "filter"
               else "") + ")" + (sol or "") + warn)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv[:1] == ["init"]:
            p = argparse.ArgumentParser(prog="pgnn-ff learn init")
            p.add_argument("campaign")
            p.add_argument("--config", default=None, help="the campaign config (YAML/JSON: Ts, controller, model, "
                           "learn, safety; with --run: learn, safety)")
            p.add_argument("--run", default=None, help="MLflow run id of a finished pipeline run of a measured "
                           "system: Ts, controller, model and force limits from it")
            p.add_argument("--reference", required=True, help="CSV with t, r: the motion the machine repeats")
            p.add_argument("--u-ff0", default=None, help="CSV with u_ff: the first trial's feedforward (default 0)")
            p.add_argument("--force", action="store_true", help="start even if the convergence check fails")
            p.add_argument("--no-mlflow", action="store_true", help="log nothing to MLflow")
            a = p.parse_args(argv[1:])
            c = campaign.init(a.campaign, a.config and Path(a.config), Path(a.reference), a.u_ff0 and Path(a.u_ff0),
                              a.force, not a.no_mlflow, a.run)
            conv = c.state["convergence"]
            if a.run:
                m, src = c.config["model"], c.state["source_run"]
                print(f"model of run {a.run}: M {m['M']:.6g} kg, F_v {m['F_v']:.6g} N s/m, K {m['K']:.6g} N/m, "
                      f"F_c {m['F_c']:.6g} N (width {m['coulomb_width']:.3g} m/s)"
                      + (f"; not in the campaign's model: {', '.join(src['dropped'])}" if src["dropped"] else ""))
            print(f"campaign {a.campaign}: convergence check {'passed' if conv['ok'] else 'FAILED (forced)'} "
                  f"(max ρ {conv['rho_max']:.3g} at {conv['f_at_max']:.3g} Hz); apply {c.u_ff_path(0)} in trial 0")
        elif argv[:1] == ["run"]:
            p = argparse.ArgumentParser(prog="pgnn-ff learn run")
            p.add_argument("campaign")
            p.add_argument("--machine", required=True, help="sim:<module>:<function> (r, u_ff) -> {u, y}")
            p.add_argument("--trials", type=int, default=10)
            a = p.parse_args(argv[1:])
            log = machine.run(a.campaign, a.machine, a.trials)
            for h in log:
                print(_line(h), flush=True)
            c = campaign.load(a.campaign)
            if c.state["stopped"]:
                last = c.state["trials"][-1]
                best = c.best()
                print(f"campaign {a.campaign} {'stopped' if log else 'had stopped'} after trial {last['trial']} "
                      f"({last['decision']}): the best is trial {best['trial']} (rms {best['rms']:.4g} m); "
                      f"`learn export {a.campaign} --out DIR` ships it", flush=True)
        elif argv[:1] == ["refit"]:
            p = argparse.ArgumentParser(prog="pgnn-ff learn refit")
            p.add_argument("campaign")
            p.add_argument("--physics-only", action="store_true", help="refit the physics only, not the run's PGNN")
            p.add_argument("--trials", default=None, help="the PGNN's refit data: trials j,k,… or all (default: the "
                           "first and the best)")
            p.add_argument("--campaign-only", action="store_true", help="the PGNN on the trials' recordings only, "
                           "not with the run's training files")
            p.add_argument("--restarts", type=int, default=None, help="the PGNN's LM restarts (default: the run's "
                           "identify.n_restarts)")
            p.add_argument("--terms", default=None, help="the PGNN's physics force terms, e.g. viscous,coulomb,offset,"
                           "spring (default: the run's)")
            a = p.parse_args(argv[1:])
            try:
                trials = a.trials if a.trials in (None, "all") else [int(x) for x in a.trials.split(",")]
            except ValueError:
                raise ConfigError(f"--trials {a.trials!r}: give trial numbers separated by commas, e.g. 0,3, "
                                  "or all") from None
            f = campaign.refit_model(a.campaign, not a.physics_only, trials, not a.campaign_only, a.restarts,
                                     a.terms and a.terms.split(","))
            print(f"refit on {f['recordings']} recordings: M {f['M']:.6g} kg, F_v {f['F_v']:.6g} N s/m, K {f['K']:.6g} "
                  f"N/m, F_c {f['F_c']:.6g} N" + (f", lag τ {1e3 * f['lag_tau']:.4g} ms kept" if f["lag_tau"] else "")
                  + f" (filter {f['cutoff_hz']:.4g} Hz, force residual {100 * f['residual']:.3g} %); "
                  f"{Path(a.campaign) / 'model_refit.yaml'}")
            g = f.get("pgnn")
            if g:
                phys = ", ".join(f"{k} {v:.5g}" for k, v in g["physical"].items())
                val = g["val_force_rel_error"]
                print(f"PGNN refit (run {g['run_id']}) on trials {g['trials']} + {g['training_files']} training files, "
                      f"{g['restarts']} restarts, terms {','.join(g['terms'])}: "
                      f"stop {g['stop_reason']} ({'converged' if g['converged'] else 'NOT converged: on its cap'}) "
                      f"after {g['iterations']:g} LM steps, {g['seconds']:.0f} s; validation force error "
                      f"{'-' if val is None else format(val, '.4g')} %; "
                      f"physics {phys}; its law {Path(a.campaign) / 'refit' / 'after'}")
        elif argv[:1] == ["export"]:
            p = argparse.ArgumentParser(prog="pgnn-ff learn export")
            p.add_argument("campaign")
            p.add_argument("--out", required=True)
            p.add_argument("--trial", type=int, default=None,
                           help="default: the best trial the machine ran (lowest rms error)")
            p.add_argument("--cc", default="cc")
            p.add_argument("--model", action="store_true", help="the refitted PGNN's law (any reference) instead")
            a = p.parse_args(argv[1:])
            if a.model:
                campaign.export(a.campaign, Path(a.out), cc=a.cc, model=True)   # export_run prints each package
                return 0
            man = campaign.export(a.campaign, Path(a.out), a.trial, a.cc)
            print(f"{Path(a.out) / man['name']}: {man['law']} table of {len(campaign.load(a.campaign).reference)} "
                  f"samples ({'compiled and checked' if man.get('compiled') else 'not compiled'})")
        elif argv[:1] == ["feedforward"]:
            p = argparse.ArgumentParser(prog="pgnn-ff learn feedforward")
            p.add_argument("campaign")
            p.add_argument("--reference", required=True, help="CSV with t, r (a motion the campaign never ran)")
            p.add_argument("--out", required=True)
            p.add_argument("--campaign-model", action="store_true", help="the model before the campaign, not the refit")
            p.add_argument("--physics", action="store_true", help="the physics, also where a PGNN was refitted")
            a = p.parse_args(argv[1:])
            print(campaign.feedforward_for(a.campaign, Path(a.reference), Path(a.out), not a.campaign_model,
                                           a.physics))
        else:
            p = argparse.ArgumentParser(prog="pgnn-ff learn", description="One trial of a learning campaign "
                                        "(README \"Learn on the machine\"); also: learn init, learn run")
            p.add_argument("campaign")
            p.add_argument("--recording", required=True, help="the trial's recording: t, r, u, y, u_ff")
            p.add_argument("--out", default=None, help="also write the next u_ff here")
            a = p.parse_args(argv)
            h = campaign.step(a.campaign, Path(a.recording), a.out and Path(a.out))
            print(_line(h) + f"; next: {campaign.load(a.campaign).u_ff_path(h['trial'] + 1)}")
    except (ConfigError, ExportError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
