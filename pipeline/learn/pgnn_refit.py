"""The PGNN learns too (issue 50 item 4): a campaign started from a PGNN run refits that PGNN on its recordings.

A campaign made by ``learn init --run RUN_ID`` of a measured axis whose run identified a PGNN (``identify.kind``
not ``none``) and designed its feedforward with it (``invert.kind`` direct, analytic or newton) is refitted by
the pipeline itself: the run's config is composed again as ``pgnn-ff export RUN_ID`` does
(:func:`pipeline.export.cli.run_config`), its training data become the campaign's trials' recordings (and,
unless left out, the run's own training files), and the stages generate, baseline, train, invert and export run
as one new MLflow run beside the source run (same experiment; tags ``learn_campaign``, ``learn_source_run``).
So the refit is the run's own identification on more data: the physics least squares (the baseline, θ*_phy),
then the PGNN by the closed-loop simulation error on the recorded force with its restarts, its tolerances and its
logged stop reason (``stop_reason``: ftol, gtol, the statistical rule, or the cap ``max_iter``, which is
reported as not converged), then the run's inversion and its exported law.

A trial's recording enters as the measured-data format the pipeline reads: t, r, u, y and the feedforward the
campaign applied as the disturbance column d = u_ff(k - D)/gtau (the loop u = gtau (sat(v + u_ff/gtau)(k - D)),
no sample of a learned trial at the limit: :func:`pipeline.learn.update.applied_disturbance`), written to
``<campaign>/refit/data/trial_<j>.csv``.

The feedforward for a reference the machine never ran is the exported law's (``pipeline.export.law.guarded``:
started at rest at r(0), the static load left to the integrator, the guard's limits and flags), i.e. exactly what
``pgnn-ff export`` ships; the law of the run before the campaign is exported beside it
(``<campaign>/refit/before/``, ``after/``), so "before" and "after" are the same code path.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline import runner, tracking
from pipeline.errors import ConfigError
from pipeline.export.cli import export_run, run_config, stored_run
from pipeline.export.law import Law, guarded
from pipeline.learn.update import applied_disturbance
from stages.generate.measured import DisturbanceShareWarning, _target, training_files
from stages.train import CAPS

__all__ = ["PGNN_INVERSIONS", "has_pgnn", "refit", "feedforward", "law_folder"]

#: the inversions of a PGNN a campaign's refit reproduces (stages/invert/<kind>.py)
PGNN_INVERSIONS = ("direct", "analytic", "newton")
#: the stages the refit job runs (the export ships the refitted law)
STAGES = ["generate", "baseline", "train", "invert", "export"]


def has_pgnn(run_id: str) -> bool:
    """Whether the run identified a PGNN and inverted it (module docstring)."""
    run = stored_run(run_id)
    stages = [s for s in run.data.tags.get("stages", "").split(",") if s]
    return ("train" in stages and "invert" in stages and run.data.tags.get("identify", "none") != "none"
            and run.data.tags.get("invert", "") in PGNN_INVERSIONS)


def _write_trial(c, j: int, folder: Path) -> str:
    """Trial j's recording as a measured-data file (t, r, u, y, d) in ``folder``; its file name."""
    frame = pd.read_csv(c.folder / "recordings" / f"trial_{j}.csv")
    u_ff = frame["u_ff"].to_numpy(np.float64)
    out = pd.DataFrame({"t": np.arange(len(frame)) * c.Ts, "r": frame["r"], "u": frame["u"], "y": frame["y"],
                        "d": applied_disturbance(c.controller(), u_ff)})
    name = f"trial_{j}.csv"
    out.to_csv(folder / name, index=False, float_format="%.17g")
    return name


def default_trials(c) -> list[int]:
    """The first trial and the best (lowest rms error): the same motion with the force all feedback, then all
    feedforward; the trials between repeat it (the refit's time grows with its samples, not its information)."""
    best = min(c.state["trials"], key=lambda h: h["rms"])["trial"]
    return sorted({c.state["trials"][0]["trial"], best})


def refit(c, trials: list[int] | str | None = None, training: bool = True, restarts: int | None = None,
          terms: list[str] | None = None) -> dict:
    """Refit the source run's PGNN on the campaign ``c``'s recordings (``trials``: their indices, 'all', or None:
    :func:`default_trials`) plus, with ``training``, the run's own training files, with ``restarts`` LM restarts
    (None: the run's ``identify.n_restarts``; each costs its screening steps) and the physics' force ``terms``
    (None: the run's ``system.force_terms.terms``; e.g. a spring the physics refit found); returns the state's
    ``refit_pgnn`` entry."""
    src = c.state["source_run"]["run_id"]
    run = stored_run(src)
    cfg = run_config(run)
    done = [h["trial"] for h in c.state["trials"]]
    trials = done if trials == "all" else default_trials(c) if trials is None else list(trials)
    bad = [j for j in trials if j not in done]
    if bad or not trials:
        raise ConfigError(f"--trials {trials}: the campaign has recorded trials {done}; give some of them")
    data_dir = (c.folder / "refit" / "data").resolve()
    data_dir.mkdir(parents=True, exist_ok=True)
    files = [_write_trial(c, j, data_dir) for j in trials]
    if training:
        if str(cfg.data.format) != "table":
            raise ConfigError(f"run {src}'s training data are data.format={cfg.data.format} files, the campaign's "
                              "recordings tables: refit on the recordings alone (learn refit --campaign-only)")
        files += [str(_target(cfg, f).resolve()) for f in training_files(cfg)]   # absolute: read where they are
    cfg.data.path = str(data_dir)
    cfg.data.file = None
    cfg.data.files = files
    cfg.evaluate.references = [{"name": "campaign", "kind": "measured", "file": files[0]}]
    cfg.stages = STAGES
    if restarts is not None:
        if restarts < 1:
            raise ConfigError(f"--restarts {restarts}: give at least 1 (the LM fits from that many initialisations)")
        cfg.identify.n_restarts = int(restarts)
    if terms is not None:
        cfg.system.force_terms.terms = list(terms)      # checked by the job's schema before any work
    name = f"{run.data.tags.get('run_key', src)}-refit-{c.folder.resolve().name}"
    cfg.run_name = name
    with warnings.catch_warnings():   # d is the campaign's own feedforward, not a controller hidden in d
        warnings.simplefilter("ignore", DisturbanceShareWarning)
        results = runner.run_job(cfg)
    exp = str(cfg.experiment_name)
    runs = tracking.search_runs(exp)
    refit_id = str(runs[runs["tags.run_key"] == name].iloc[0]["run_id"])
    client = tracking.client()
    for k, v in (("learn_campaign", str(c.folder.resolve())), ("learn_source_run", src), ("kind", "learn_refit")):
        client.set_tag(refit_id, k, v)
    tags, metrics = client.get_run(refit_id).data.tags, client.get_run(refit_id).data.metrics
    stop = tags.get("stop_reason", "?")
    before = export_run(src, c.folder / "refit" / "before")
    after = export_run(refit_id, c.folder / "refit" / "after")
    loop = results["train"].get("loop")
    entry = {"run_id": refit_id, "source_run": src, "trials": trials, "training_files": len(files) - len(trials),
             "restarts": int(cfg.identify.n_restarts), "terms": list(cfg.system.force_terms.terms),
             "stop_reason": stop, "converged": stop not in CAPS, "iterations": metrics.get("train/iterations"),
             "seconds": metrics.get("train/seconds"), "val_force_rel_error": metrics.get("train/val_force_rel_error"),
             "physical": {k: float(v) for k, v in results["train"]["physical"].items()},
             "physical_before": physics_of(src),
             "n1": None if loop is None else int(loop.n1), "before": sorted(before), "after": sorted(after)}
    if not entry["converged"]:
        warnings.warn(f"the PGNN refit stopped on its cap ({stop}) after {entry['iterations']:g} LM steps, not on a "
                      "tolerance: raise identify.max_iter in the source run's config", stacklevel=2)
    return entry


def physics_of(run_id: str) -> dict:
    """The physics part θ_phy of a run's PGNN as physical parameters (its metrics ``train/theta_phy/<name>``)."""
    pre = "train/theta_phy/"
    return {k[len(pre):]: float(v) for k, v in sorted(tracking.client().get_run(run_id).data.metrics.items())
            if k.startswith(pre)}


def law_folder(c, which: str) -> Path:
    """The exported law of the PGNN ``which`` ('before': the source run's, 'after': the refit's)."""
    info = c.state.get("refit_pgnn")
    if info is None:
        raise ConfigError(f"{c.folder}: no PGNN refit yet; run `pgnn-ff learn refit {c.folder}` first")
    names = info[which]
    if len(names) != 1:
        raise ConfigError(f"{c.folder}: the {which} run exported {names}; expected one PGNN law")
    return c.folder / "refit" / which / names[0] / "law"


def feedforward(c, which: str, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u_ff, guard flags) of the PGNN ``which`` for the reference r: the exported law as shipped."""
    return guarded(Law.load(law_folder(c, which)), np.asarray(r, np.float64))
