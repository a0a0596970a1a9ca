"""A learning campaign driven by files (issue 50 item 1): one folder, one command per trial.

The folder holds ``campaign.json`` (the config: Ts, controller, model, learn, safety; and the state: every
trial's recording, error norms, decision, the learning gain; written atomically, so any interruption leaves
the last complete step and rerunning the same command resumes), ``reference.csv`` (t, r), ``u_ff_<j>.csv``
(t, r, u_ff, flags: what trial j must apply), ``recordings/trial_<j>.csv`` (the recordings as received),
``convergence.png`` (the check before the campaign) and ``errors.png`` (‖e_j‖ and max|e_j| per trial).
MLflow: the campaign is a parent run (experiment ``learn``), each trial a child run.

A trial's recording (the measured-data format plus the applied ``u_ff``) is checked against the campaign
before any work, each problem refused in one line: the same reference and the u_ff the campaign gave
(to 1e-6 of their largest magnitude: float32 or 7-digit logs pass), the configured controller (equation
error < 5 %, ``LTIController.check`` with the u_ff as the command's known part), no sample at the limit, finite
(``pipeline.data.load``).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
import pandas as pd

from pipeline import data
from pipeline.errors import ConfigError
from pipeline.learn import safety
from pipeline.learn.update import LoopModel, applied_disturbance, make_update
from pipeline.plots import pyplot
from pipeline.params import DAMP_MAX, FORCE_MAX, FREQ_MAX, ITER_MAX, MASS_MAX, SPEED_MAX, STIFF_MAX, TS_MAX, \
    schema, spec
from pipeline.systems.controller import LTIController

__all__ = ["Campaign", "init", "step", "load", "CONTROLLER_RTOL"]

#: a recording whose u is further than this from the controller's output (relative equation error) is refused
CONTROLLER_RTOL = 0.05
#: r and u_ff of a recording must equal the campaign's to this (relative to their largest magnitude): a log in
#: float32 (rounding <= 6e-8 of a value) or to 7 significant digits (<= 5e-7) passes, another reference or another
#: trial's u_ff (differing by far more) does not; the campaign then learns from its own exact r and u_ff
MATCH_RTOL = 1e-6
STATE = "campaign.json"
#: a campaign whose gain fell below learn.gain / STALL (six halvings) has stalled: the console says so and why
STALL = 64
#: failing bands all above FILTER × Q's cutoff (its roll-off: a mode the model lacks) lower the cutoff to 0.8 × the
#: lowest band's edge instead of halving the gain (decision 'filter'): the gain learns the rest at full speed
FILTER = 0.5


@schema
class LearnModel:
    """The identified loop the laws invert (pipeline.learn.update.LoopModel)."""
    M: float = spec(gt=0, le=MASS_MAX, unit="kg", example=3.4)
    F_v: float = spec(0.0, ge=0, le=DAMP_MAX, unit="N s/m")
    K: float = spec(0.0, ge=0, le=STIFF_MAX, unit="N/m")
    F_c: float = spec(0.0, ge=0, le=FORCE_MAX, unit="N")
    coulomb_width: float = spec(0.0, ge=0, le=SPEED_MAX, unit="m/s")
    # the drive's current-loop lag τ Ḟ + F = u (pipeline.systems.actuator_lag); 0: none
    lag_tau: float = spec(0.0, ge=0, le=1.0, unit="s")


@schema
class LearnLaw:
    """The update law (pipeline.learn.update)."""
    law: Literal["model_ilc", "norm_optimal", "il_fhofc"] = "model_ilc"
    gain: float = spec(1.0, gt=0, le=4.0)
    q_cutoff_hz: float = spec(150.0, gt=0, le=FREQ_MAX, unit="Hz")
    q_order: int = spec(2, ge=1, le=8)
    # norm_optimal's weights on φ (pulls what G cannot see, its DC, to 0) and on its change (damps noise; keeps the DC
    # of the first φ = the controller term: a 2-DOF loop's saturates; pipeline.learn.update)
    w_f: float = spec(1e-5, ge=0, le=1e6, unit="× max|G|²")
    w_df: float = spec(0.0, ge=0, le=1e6, unit="× max|G|²")
    # norm_optimal: the exact solve's relative residual on its normal equations, and its refinement sweeps at most
    # (each one O(N); the solve's stop, converged or cap, is in every trial's log)
    rtol: float = spec(1e-9, gt=0, lt=1)
    max_sweeps: int = spec(3, ge=0, le=ITER_MAX)
    # il_fhofc: Gauss–Newton iterations per window of a nonlinear model (a linear one takes one)
    maxiter: int = spec(100, ge=1, le=ITER_MAX)
    # il_fhofc: γ of Γ = γΔ ([B2] (31)); null: |G|/|Δ| at q_cutoff_hz (L G = 1/2 where |Q| = 1/2); 0: no
    # regularisation (the triangular solve: fast, but the inverse's noise gain is cut by Q alone)
    gamma: Optional[float] = spec(None, ge=0, le=1.0, unit="m/N")
    # il_fhofc: FHOFC on windows of fhofc_window samples, each looking fhofc_overlap further (the dense Jacobian)
    fhofc_window: int = spec(100, ge=1, le=5000)
    fhofc_overlap: int = spec(50, ge=1, le=5000)
    # the model's Coulomb force along r and the recorded y (model_ilc, norm_optimal; needs model.F_c, coulomb_width > 0)
    along_trajectory: bool = True


@schema
class LearnSafety:
    """The rules of pipeline.learn.safety."""
    uncertainty: float = spec(0.3, ge=0, le=100)
    uncertainty_hz: Optional[float] = spec(None, gt=0, le=FREQ_MAX, unit="Hz")
    u_max: Optional[float] = spec(None, gt=0, le=FORCE_MAX, unit="N")
    rate: Optional[float] = spec(None, gt=0, le=1e12, unit="N/s")
    data_margin: float = spec(0.5, ge=0, le=100)
    rollback_factor: float = spec(1.2, gt=1, le=100)
    stop_factor: float = spec(1.2, gt=0, le=100)
    settle_s: float = spec(0.2, gt=0, le=100, unit="s")


@schema
class CampaignConfig:
    """A campaign's config file (README "Learn on the machine")."""
    Ts: float = spec(gt=0, le=TS_MAX, unit="s", example=0.00025)
    controller: Any = spec(example={"kind": "lti", "num": [1.0], "den": [1.0]})
    model: LearnModel = spec(example={"M": 3.4})
    learn: LearnLaw = field(default_factory=LearnLaw)
    safety: LearnSafety = field(default_factory=LearnSafety)


#: the model section's keys a refit writes (model_refit.yaml; pipeline.learn.refit)
REFIT_KEYS = tuple(f.name for f in fields(LearnModel))
_SECTIONS = {"model": LearnModel, "learn": LearnLaw, "safety": LearnSafety}


def _build(cls, node: dict):
    """The config's dataclasses from its (checked) mapping."""
    return cls(**{f.name: (_build(_SECTIONS[f.name], node[f.name]) if f.name in _SECTIONS else node[f.name])
                  for f in fields(cls) if f.name in node})


#: the sections ``learn init --run`` takes from the run (pipeline.learn.from_run); a config file then gives the rest
FROM_RUN = ("Ts", "controller", "model")


def read_config(path: Path | None, base: dict | None = None) -> CampaignConfig:
    """The campaign config (YAML or JSON), every key checked (pipeline.schema) before any work. ``base``: the
    Ts, controller, model and safety limits of a run (``--run``); the file (optional then) gives learn and
    safety, its safety keys over the run's."""
    import yaml  # lazy: saves 0.1 s of start-up (only learn init reads YAML)
    from pipeline import schema as sch  # lazy: saves 0.3 s of start-up (the config schema machinery)
    node, name = {}, "the run's model"
    if path is not None:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"campaign config {path} does not exist; README \"Learn on the machine\" shows one")
        node, name = yaml.safe_load(path.read_text()), f"a campaign config ({path.name})"
    if base is not None:
        both = [k for k in FROM_RUN if isinstance(node, dict) and k in node]
        if both:
            raise ConfigError(f"{path.name}: sets {both}, which --run takes from the run; drop them from the file "
                              "(it gives learn and safety) or drop --run")
        safety = {**base.get("safety", {}), **((node or {}).get("safety") or {})}
        node = {**base, **(node or {}), **({"safety": safety} if safety else {})}
    sch._check_node(CampaignConfig, node, "", name)
    return _build(CampaignConfig, node)


@dataclass
class Campaign:
    """A campaign folder (module docstring)."""

    folder: Path
    config: dict
    reference: np.ndarray
    state: dict

    # ---- objects ----------------------------------------------------------------------------------
    @property
    def cfg(self) -> CampaignConfig:
        return _build(CampaignConfig, self.config)

    @property
    def Ts(self) -> float:
        return float(self.config["Ts"])

    def controller(self) -> LTIController:
        return LTIController.from_config(self.config["controller"], self.Ts)

    def update(self):
        c = self.cfg
        model = self.loop_model(c.model)
        L = c.learn
        weights = {"model_ilc": {}, "norm_optimal": {"w_f": L.w_f, "w_df": L.w_df, "max_sweeps": L.max_sweeps,
                                                     "rtol": L.rtol},
                   "il_fhofc": {"reference": self.reference, "gamma": L.gamma, "window": L.fhofc_window,
                                "overlap": L.fhofc_overlap, "maxiter": L.maxiter}}[L.law]
        upd = make_update(model, c.learn.law, self.q_cutoff_hz, c.learn.q_order, **weights)
        return upd.along(self.reference) if c.learn.along_trajectory else upd

    @property
    def q_cutoff_hz(self) -> float:
        """Q's cutoff: learn.q_cutoff_hz, or lower where a trial measured a band it must not learn (decision
        'filter')."""
        return float(self.state.get("q_cutoff_hz") or self.cfg.learn.q_cutoff_hz)

    def best(self) -> dict:
        """The entry of the trial with the lowest rms error (of those the machine ran)."""
        return min(self.state["trials"], key=lambda h: h["rms"])

    def loop_model(self, m: LearnModel) -> LoopModel:
        """The update's :class:`LoopModel` of a ``model`` section (the config's, or the refit's)."""
        return LoopModel(self.Ts, m.M, m.F_v, m.K, self.controller(), m.F_c, m.coulomb_width, m.lag_tau)

    def controller_term(self) -> np.ndarray:
        """gtau (C_r - C_y) r from rest at r(0) (LTIController.reference_force)."""
        return self.controller().reference_force(self.reference, float(self.reference[0]))

    # ---- files ------------------------------------------------------------------------------------
    def u_ff_path(self, j: int) -> Path:
        return self.folder / f"u_ff_{j}.csv"

    def u_ff(self, j: int) -> np.ndarray:
        return pd.read_csv(self.u_ff_path(j))["u_ff"].to_numpy(np.float64)

    def write_u_ff(self, j: int, u: np.ndarray, flags: np.ndarray, out: Path | None = None) -> Path:
        t = np.arange(self.reference.size) * self.Ts
        frame = pd.DataFrame({"t": t, "r": self.reference, "u_ff": u, "flags": flags.astype(np.int64)})
        path = self.u_ff_path(j)
        _atomic(path, lambda p: frame.to_csv(p, index=False, float_format="%.17g"))
        if out is not None and Path(out).resolve() != path.resolve():
            _atomic(Path(out), lambda p: shutil.copyfile(path, p))
        return path

    def save(self) -> None:
        body = json.dumps({"config": self.config, "state": self.state}, indent=1, default=_json)
        _atomic(self.folder / STATE, lambda p: Path(p).write_text(body))


def _json(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x).__name__)


def _atomic(path: Path, write) -> None:
    """Write through a temporary file in the same folder and rename: never half-written."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    write(tmp)
    os.replace(tmp, path)


def load(folder) -> Campaign:
    folder = Path(folder)
    state = folder / STATE
    if not state.exists():
        raise ConfigError(f"{folder} is not a learning campaign (no {STATE}); start one with "
                          f"`pgnn-ff learn init {folder} --config campaign.yaml --reference ref.csv`")
    body = json.loads(state.read_text())
    ref = pd.read_csv(folder / "reference.csv")["r"].to_numpy(np.float64)
    return Campaign(folder, body["config"], ref, body["state"])


def _limits(c: Campaign, rec: dict) -> tuple[float, float, str]:
    """(u_max, rate, where from): safety.u_max/rate, else (1 + data_margin) × the first recording's largest
    |u - (C_r - C_y) r| and its slew (the export's defaults, stages.export.data_limits)."""
    from stages.export import data_limits  # lazy: saves 0.5 s of start-up (the export stage)
    s = c.cfg.safety
    u_abs, du_abs = data_limits([(rec["u"], rec["r"])], c.Ts, c.controller(), rest=True)
    f = 1.0 + s.data_margin
    u_max = s.u_max if s.u_max is not None else f * u_abs
    rate = s.rate if s.rate is not None else f * du_abs
    return u_max, rate, ("safety.u_max/rate" if s.u_max is not None and s.rate is not None else
                         f"±{f:g} × {u_abs:.6g} N and {f:g} × {du_abs:.6g} N/s of the first recording")


def init(folder, config: Path | None, reference: Path, u_ff0: Path | None = None, force: bool = False,
         tracking: bool = True, run_id: str | None = None) -> Campaign:
    """A new campaign in ``folder``: config checked, the convergence check passed (or ``force``), u_ff_0.csv
    written (zero, or ``u_ff0``'s u_ff column). ``run_id``: Ts, controller, model and limits from that finished
    run of a measured system (pipeline.learn.from_run); ``config`` then optional (learn, safety)."""
    folder = Path(folder)
    if (folder / STATE).exists():
        raise ConfigError(f"{folder} already holds a campaign; continue it with `pgnn-ff learn {folder} "
                          "--recording …`, or give a new folder")
    if config is None and run_id is None:
        raise ConfigError("learn init needs --config campaign.yaml, or --run RUN_ID (the model of a finished run)")
    source = None
    if run_id is not None:
        from pipeline.learn import from_run  # lazy: saves 3.0 s of start-up (mlflow, hydra, the stages)
        source = from_run.model_of(run_id)
    cfg = read_config(config, source and source["config"])
    if not Path(reference).exists():
        raise ConfigError(f"reference {reference} does not exist; give a CSV with columns t, r")
    frame = pd.read_csv(reference)
    if "r" not in frame or "t" not in frame:
        raise ConfigError(f"{reference}: a reference needs columns t, r; found {list(frame.columns)[:8]}")
    r = frame["r"].to_numpy(np.float64)
    t = frame["t"].to_numpy(np.float64)
    if not np.all(np.isfinite(r)) or r.size < 100:
        raise ConfigError(f"{reference}: r must be at least 100 finite samples, got {r.size}")
    try:
        data.sample_time(t, cfg.Ts, str(reference), given_by="the campaign config's Ts")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    c = Campaign(folder, json.loads(json.dumps(asdict(cfg))), r, {"trials": [], "gain": cfg.learn.gain,
                                                                  "stopped": False, "limits": None})
    if source is not None:
        c.state["source_run"] = {"run_id": run_id, "physical": source["physical"], "dropped": source["dropped"]}
    c.controller()   # the controller config, checked before any work
    check = safety.convergence_check(c.update(), cfg.learn.gain, cfg.safety.uncertainty, cfg.safety.uncertainty_hz)
    folder.mkdir(parents=True, exist_ok=True)
    plot_check(check, folder / "convergence.png")
    if not check["ok"] and not force:
        raise ConfigError(check["message"])
    c.state["convergence"] = {"ok": check["ok"], "rho_max": check["rho_max"], "f_at_max": check["f_at_max"],
                              "band": check["band"], "forced": bool(force and not check["ok"])}
    pd.DataFrame({"t": np.arange(r.size) * cfg.Ts, "r": r}).to_csv(folder / "reference.csv", index=False,
                                                                    float_format="%.17g")
    u0 = np.zeros(r.size) if u_ff0 is None else pd.read_csv(u_ff0)["u_ff"].to_numpy(np.float64)
    if u0.shape != r.shape or not np.all(np.isfinite(u0)):
        raise ConfigError(f"{u_ff0}: its u_ff must be {r.size} finite samples (one per reference sample)")
    c.write_u_ff(0, u0, np.zeros(r.size, np.int64))
    if tracking:
        c.state["mlflow"] = _parent_run(folder, c)
    c.save()
    return c


def check_recording(c: Campaign, path: Path, j: int) -> dict:
    """The recording of trial j against the campaign (module docstring); its signals."""
    name = Path(path).name
    ds = data.load(path)
    if "u_ff" not in ds.frame:
        raise ConfigError(f"{name}: no u_ff column; a trial's recording holds t, r, u, y and the u_ff applied "
                          f"(the campaign's u_ff_{j}.csv)")
    if abs(ds.Ts - c.Ts) > data.TS_RTOL * c.Ts:
        raise ConfigError(f"{name}: sampled at Ts = {ds.Ts:.6g} s, the campaign at {c.Ts:g} s")
    rec = {k: ds[k] for k in ("t", "r", "u", "y", "u_ff")}
    if rec["r"].size != c.reference.size:
        raise ConfigError(f"{name}: {rec['r'].size} samples, the campaign's reference has {c.reference.size}: "
                          "record the whole reference")
    dr = np.abs(rec["r"] - c.reference)
    if dr.max() > MATCH_RTOL * max(np.abs(c.reference).max(), 1e-300):
        k = int(np.argmax(dr))
        raise ConfigError(f"{name}: another reference than the campaign's (r differs by {dr[k]:.3g} m at sample {k}); "
                          "run the campaign's reference.csv")
    expect = c.u_ff(j)
    du = np.abs(rec["u_ff"] - expect)
    if du.max() > MATCH_RTOL * max(np.abs(expect).max(), 1.0):
        k = int(np.argmax(du))
        raise ConfigError(f"{name}: its u_ff is not the campaign's u_ff_{j}.csv (differs by {du[k]:.3g} N at "
                          f"sample {k}); "
                          f"apply u_ff_{j}.csv for trial {j}")
    rec["r"], rec["u_ff"] = c.reference.copy(), expect      # the exact values the log rounded
    ctrl = c.controller()
    at_limit = np.abs(rec["u"] / ctrl.gtau) >= ctrl.v_sat * (1 - 1e-9)
    if at_limit.any():
        fix = ("the feedback alone saturates on this reference with u_ff_0: use a slower reference, or start from "
               "the model's feedforward (`learn feedforward CAMPAIGN --reference ref.csv --out u0.csv "
               "--campaign-model`, then `learn init … --u-ff0 u0.csv`)" if j == 0 else
               "lower learn.gain or the limits (safety.u_max, safety.rate) and rerun the best trial's u_ff")
        raise ConfigError(f"{name}: {int(at_limit.sum())} samples at the actuator limit ±{ctrl.v_sat * ctrl.gtau:g} N "
                          f"(first at sample {int(np.flatnonzero(at_limit)[0])}): not learned from; {fix}")
    rel = ctrl.check(rec["r"], rec["y"], rec["u"], applied_disturbance(ctrl, rec["u_ff"]))
    if not rel < CONTROLLER_RTOL:
        raise ConfigError(f"{name}: the recorded u is not {ctrl.describe()} plus the applied u_ff (relative equation "
                          f"error {100 * rel:.3g} % > {100 * CONTROLLER_RTOL:.0f} %); record u as the force applied "
                          "and u_ff as the feedforward added before the limit")
    rec["controller_error"] = rel
    return rec


def step(folder, recording: Path, out: Path | None = None) -> dict:
    """One trial: check the recording of the next trial, decide (learn, rollback, stop), write the next u_ff.
    Returns the trial's log entry. The same recording again (an interrupted run) returns its entry unchanged."""
    c = load(folder)
    digest = hashlib.sha256(Path(recording).read_bytes()).hexdigest()
    for h in c.state["trials"]:
        if h["sha256"] == digest:         # resumed: the step was done
            if out is not None:
                shutil.copyfile(c.u_ff_path(h["trial"] + 1), out)
            return h
    j = len(c.state["trials"])
    rec = check_recording(c, recording, j)
    s = c.cfg.safety
    if c.state["limits"] is None:
        u_max, rate, src = _limits(c, rec)
        c.state["limits"] = {"u_max": u_max, "rate": rate, "source": src}
    e = rec["r"] - rec["y"]
    err, mae, emax = safety.rms(e), float(np.mean(np.abs(e))), float(np.max(np.abs(e)))
    floor = safety.noise_floor(rec["r"], e, int(round(s.settle_s / c.Ts)))
    history = c.state["trials"]
    measured = safety.unmeasured()
    prev = c.folder / "recordings" / f"trial_{j - 1}.csv"
    if j >= 1 and prev.exists():       # the convergence condition on the plant the last two trials measured
        dphi = rec["u_ff"] - c.u_ff(j - 1)
        if np.max(np.abs(dphi)) > 0:
            y_prev = pd.read_csv(prev)["y"].to_numpy(np.float64)
            measured = safety.measured_rho(c.update(), c.state["gain"], dphi, rec["y"] - y_prev, floor)
    decision = "stop" if c.state["stopped"] else safety.decide(history, err, floor, s.rollback_factor, s.stop_factor)
    gain = c.state["gain"]
    q_cut = c.q_cutoff_hz
    lowest = min((lo for lo, _ in measured["failing"]), default=0.0)
    if decision == "learn" and lowest >= FILTER * q_cut:
        # every failing band in Q's roll-off (a mode the model lacks): Q's cutoff below it, the gain kept
        decision, q_cut = "filter", 0.8 * lowest
        c.state["q_cutoff_hz"] = q_cut
    if decision == "learn" and (measured["gain_max"] < gain or measured["uncured"]):   # the measured loop does not
        # contract (safety.slower); a band no gain cures (Re L Ĝ <= 0) slows it too, and the console names the fix
        decision, gain = "slow", safety.slower(gain, measured["gain_max"])
    best = min(history + [{"rms": err, "trial": j}], key=lambda h: h["rms"])
    kr = c.controller_term()
    diagnostics = {}
    if decision in ("learn", "slow", "filter"):
        upd = c.update()
        u_next = upd.next(e, rec["u_ff"], gain, kr)
        diagnostics = upd.diagnostics()
    elif decision == "rollback":
        gain = safety.slower(gain, measured["gain_max"])
        u_next = c.u_ff(best["trial"])
    else:   # stop: the best trial's feedforward from now on
        c.state["stopped"] = True
        u_next = c.u_ff(best["trial"])
    lim = c.state["limits"]
    u_next, flags = safety.limited(u_next, lim["u_max"], lim["rate"], c.Ts)
    (c.folder / "recordings").mkdir(exist_ok=True)
    shutil.copyfile(recording, c.folder / "recordings" / f"trial_{j}.csv")
    c.write_u_ff(j + 1, u_next, flags, out)
    entry = {"trial": j, "recording": str(recording), "sha256": digest, "rms": err, "mae": mae, "max": emax,
             "noise_floor": floor, "decision": decision, "gain": gain, "controller_error": rec["controller_error"],
             "limited_samples": int(np.count_nonzero(flags)), "max_abs_u": float(np.max(np.abs(rec["u"]))),
             "measured_rho": None if math.isnan(measured["rho_max"]) else measured["rho_max"],
             "measured_band": measured["band"], "measured_ratio": None if math.isnan(measured["ratio"]) else
             measured["ratio"], "uncured_bands": measured["uncured"],
             "stalled": bool(gain < c.cfg.learn.gain / STALL), "q_cutoff_hz": q_cut, **diagnostics}
    c.state["trials"].append(entry)
    c.state["gain"] = gain
    plot_errors(c.state["trials"], c.folder / "errors.png")
    c.save()
    if c.state.get("mlflow"):
        _log_trial(c, entry)
    return entry


# ---- plots and MLflow --------------------------------------------------------------------------------------
def plot_check(check: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.semilogx(check["f_hz"], check["rho"], label="|Q(1 - αLG)| + uncertainty")
    ax.axhline(1.0, color="r", lw=0.8, label="1: divergence")
    if check["band"]:
        ax.axvspan(*check["band"], color="r", alpha=0.15)
    _finish(fig, ax, "frequency [Hz]", "ρ", path)


def plot_errors(trials: list[dict], path: Path) -> None:
    plt = pyplot()
    j = [h["trial"] for h in trials]
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.semilogy(j, [h["rms"] for h in trials], "o-", label="‖e_j‖ (rms)")
    ax.semilogy(j, [h["max"] for h in trials], "s-", label="max|e_j|")
    floors = [h["noise_floor"] for h in trials if math.isfinite(h["noise_floor"])]
    if floors:
        ax.axhline(floors[-1], color="gray", ls="--", label="noise floor")
    for h in trials:
        if h["decision"] == "rollback":
            ax.axvline(h["trial"], color="r", alpha=0.3)
    _finish(fig, ax, "trial j", "error [m]", path)


def _finish(fig, ax, xlabel: str, ylabel: str, path: Path) -> None:
    """Label, legend and save a campaign figure, then close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    pyplot().close(fig)


def _parent_run(folder: Path, c: Campaign) -> dict:
    from pipeline import tracking  # lazy: saves 1.5 s of start-up (mlflow)
    client = tracking.client()
    exp = tracking.experiment_id("learn", "learning campaigns: a parent run per campaign, a child per trial")
    run = client.create_run(exp, run_name=folder.resolve().name, tags={"kind": "learn_campaign",
                                                                      "folder": str(folder.resolve())})
    from mlflow.entities import Param  # lazy: saves 1.5 s of start-up (mlflow)
    flat = {f"{k}.{kk}": str(vv) for k, v in c.config.items() if isinstance(v, dict) for kk, vv in v.items()}
    client.log_batch(run.info.run_id, params=[Param(k[:250], v[:6000]) for k, v in sorted(flat.items())])
    client.log_artifact(run.info.run_id, str(folder / "convergence.png"))
    client.set_terminated(run.info.run_id, "FINISHED")
    return {"experiment": exp, "parent": run.info.run_id}


def _log_trial(c: Campaign, entry: dict) -> None:
    from mlflow.entities import Metric  # lazy: saves 1.5 s of start-up (mlflow)
    from pipeline import tracking  # lazy: saves 1.5 s of start-up (mlflow)
    client = tracking.client()
    m = c.state["mlflow"]
    j = entry["trial"]
    run = client.create_run(m["experiment"], run_name=f"trial_{j}", tags={"mlflow.parentRunId": m["parent"],
                                                                         "decision": entry["decision"]})
    keys = ("rms", "mae", "max", "noise_floor", "gain", "controller_error", "limited_samples", "measured_rho")
    now = 0
    vals = [(k, float(entry[k])) for k in keys if entry[k] is not None and math.isfinite(float(entry[k]))]
    if entry.get("solve"):
        vals.append(("solve_residual", float(entry["solve"]["residual"])))
        client.set_tag(run.info.run_id, "solve_stop", entry["solve"]["stop"])
    client.log_batch(run.info.run_id, metrics=[Metric(k, v, now, j) for k, v in vals])
    client.log_batch(m["parent"], metrics=[Metric(f"trial/{k}", v, now, j) for k, v in vals])
    client.log_artifact(run.info.run_id, str(c.u_ff_path(j + 1)))
    client.set_terminated(run.info.run_id, "FINISHED")
    client.log_artifact(m["parent"], str(c.folder / "errors.png"))


# ---- the model learns (pipeline.learn.refit) ----------------------------------------------------------------
def refit_model(folder, pgnn: bool = True, trials: list[int] | str | None = None, training: bool = True,
                restarts: int | None = None, terms: list[str] | None = None) -> dict:
    """Refit the campaign's physics on every trial's recording (:func:`pipeline.learn.refit.refit`); stored in
    the state and written as ``model_refit.yaml`` (the ``model`` section of a next campaign). A campaign from a
    run with a PGNN (``learn init --run``) also refits that PGNN (:func:`pipeline.learn.pgnn_refit.refit`, on
    ``trials``: indices, 'all', default the first and the best; plus with ``training`` the run's training files)
    unless ``pgnn`` is off, with ``restarts`` LM restarts and the force ``terms`` (default the run's); its entry is
    the state's ``refit_pgnn``, returned under the key ``pgnn``."""
    import yaml  # lazy: saves 0.1 s of start-up (only learn init and refit write YAML)
    from pipeline.learn import refit  # lazy: saves 0.4 s of start-up (the measured-system physics)
    c = load(folder)
    if not c.state["trials"]:
        raise ConfigError(f"{folder}: no trial recorded yet; the refit needs the trials' recordings")
    with_pgnn = pgnn and has_pgnn(c)
    if not with_pgnn and (trials is not None or not training or restarts is not None or terms is not None):
        raise ConfigError(f"{folder}: --trials, --campaign-only, --restarts and --terms choose the PGNN's refit, and "
                          "this campaign refits no PGNN (started from a config file or a physics run, or "
                          "--physics-only); drop them: the physics refits on every trial")
    recs = []
    for h in c.state["trials"]:
        frame = pd.read_csv(c.folder / "recordings" / f"trial_{h['trial']}.csv")
        recs.append({"u": frame["u"].to_numpy(np.float64), "y": frame["y"].to_numpy(np.float64)})
    floors = [h["noise_floor"] for h in c.state["trials"] if math.isfinite(h["noise_floor"])]
    model, fit = refit.refit(c.update().model, recs, noise=float(np.median(floors)) if floors else None)
    out = {k: float(getattr(model, k)) for k in REFIT_KEYS}
    c.state["refit"] = {**out, **fit, "recordings": len(recs)}
    _atomic(c.folder / "model_refit.yaml", lambda p: Path(p).write_text(yaml.safe_dump({"model": out})))
    c.save()
    result = dict(c.state["refit"])
    if with_pgnn:
        from pipeline.learn import pgnn_refit  # lazy: saves 3.0 s of start-up (mlflow, hydra, torch, the stages)
        c.state["refit_pgnn"] = result["pgnn"] = pgnn_refit.refit(c, trials, training, restarts, terms)
        c.save()
    return result


def has_pgnn(c: Campaign) -> bool:
    """Whether the campaign came from a run whose model is a PGNN it inverted (pipeline.learn.pgnn_refit)."""
    if "source_run" not in c.state:
        return False
    from pipeline.learn import pgnn_refit  # lazy: saves 3.0 s of start-up (mlflow, hydra, torch, the stages)
    return pgnn_refit.has_pgnn(c.state["source_run"]["run_id"])


def feedforward_for(folder, reference: Path, out: Path, refitted: bool = True, physics: bool = False) -> Path:
    """The model's feedforward for a reference the campaign never ran (t, r, u_ff, flags), from the refitted
    model (or, ``refitted`` off, the one before the campaign): the PGNN's exported law when the campaign refitted
    one (pipeline.learn.pgnn_refit; ``physics`` on: the physics instead), else the physics within the limits the
    config states."""
    from pipeline.learn import refit  # lazy: saves 0.4 s of start-up (the measured-system physics)
    c = load(folder)
    cfg = c.cfg
    frame = pd.read_csv(reference)
    if "r" not in frame or "t" not in frame:
        raise ConfigError(f"{reference}: a reference needs columns t, r; found {list(frame.columns)[:8]}")
    r = frame["r"].to_numpy(np.float64)
    if not physics and "refit_pgnn" in c.state:
        from pipeline.learn import pgnn_refit  # lazy: saves 3.0 s of start-up (mlflow, hydra, torch, the stages)
        u, flags = pgnn_refit.feedforward(c, "after" if refitted else "before", r)
    else:
        m = cfg.model
        if refitted:
            if "refit" not in c.state:
                raise ConfigError(f"{folder}: not refitted yet; run `pgnn-ff learn refit {folder}` first")
            m = LearnModel(**{k: c.state["refit"][k] for k in REFIT_KEYS if k in c.state["refit"]})
        model = c.loop_model(m)
        u = refit.feedforward(make_update(model, "model_ilc", cfg.learn.q_cutoff_hz, cfg.learn.q_order), r)
        # only the limits the config states: the ones from the campaign's recordings are its reference's, and a
        # new reference may need more (a faster move); beyond them is a warning
        s = cfg.safety
        u, flags = safety.limited(u, s.u_max or math.inf, s.rate or math.inf, c.Ts)
    lim = c.state["limits"]
    peak, slew = float(np.max(np.abs(u))), float(np.max(np.abs(np.diff(u)))) / c.Ts
    if lim and (peak > lim["u_max"] or slew > lim["rate"]):
        warnings.warn(f"{Path(out).name}: u_ff reaches {peak:.4g} N and {slew:.4g} N/s, beyond the campaign's "
                      f"limits from its recordings ({lim['u_max']:.4g} N, {lim['rate']:.4g} N/s): a faster motion "
                      "than the campaign's; set safety.u_max and safety.rate to the actuator's",
                      stacklevel=2)
    frame = pd.DataFrame({"t": frame["t"], "r": r, "u_ff": u, "flags": flags})
    _atomic(Path(out), lambda p: frame.to_csv(p, index=False, float_format="%.17g"))
    return Path(out)


def export(folder, out: Path, trial: int | None = None, cc: str | None = "cc", model: bool = False) -> dict:
    """The u_ff of ``trial`` (default: the best trial the machine ran, lowest rms error) as a C99 package
    (pipeline.export): the table family, the law IL-FHOFC's tables use (a signal learned by trials for one
    reference; the manifest's law reads il_fhofc), with the campaign's force and slew limits (the ones every
    trial's u_ff was held to: safety.u_max/rate, else from the first recording), verified against the CSV and
    compiled with ``cc`` when one is found. ``model``: instead the refitted PGNN's law for any reference
    (``pgnn-ff export`` of the refit's run: {package: manifest})."""
    from pipeline.export.law import from_table  # lazy: saves 0.5 s of start-up (the exporter)
    from pipeline.export.package import write_package  # lazy: saves 0.5 s of start-up (the exporter)
    c = load(folder)
    if model:
        if "refit_pgnn" not in c.state:
            raise ConfigError(f"{folder}: no PGNN refit to export; `pgnn-ff learn refit {folder}` refits the PGNN of "
                              "a campaign started with --run RUN_ID of a PGNN run")
        from pipeline.export.cli import export_run  # lazy: saves 3.0 s of start-up (mlflow, hydra, the stages)
        return export_run(c.state["refit_pgnn"]["run_id"], Path(out), cc=cc)
    trials = c.state["trials"]
    if trial is None and not trials:
        raise ConfigError(f"{folder}: no trial has run yet, so no u_ff of it is measured: run trial 0 with "
                          "u_ff_0.csv first (or export it untried with --trial 0)")
    j = c.best()["trial"] if trial is None else int(trial)
    if not c.u_ff_path(j).exists():
        raise ConfigError(f"{folder}: no u_ff_{j}.csv; the campaign has u_ff_0 .. u_ff_{len(trials)}")
    if j >= len(trials):
        warnings.warn(f"{folder}: u_ff_{j}.csv has not run on the machine yet (trials 0 .. {len(trials) - 1} "
                      "have): its error is not measured", stacklevel=2)
    lim = c.state["limits"] or {}
    s = c.cfg.safety
    u_max, rate = lim.get("u_max", s.u_max), lim.get("rate", s.rate)
    if u_max is None or rate is None:
        raise ConfigError(f"{folder}: no force and slew limits known to ship with the table (no trial has run, and "
                          "safety.u_max or safety.rate is not set): set both in the campaign config to the actuator's")
    u = c.u_ff(j)
    law = from_table("il_fhofc", c.Ts, c.reference, u)
    law.guard = {**law.guard, "u_min": -float(u_max), "u_max": float(u_max), "rate": float(rate)}
    law.strings["limits_source"] = (f"the campaign's limits ({lim['source']})" if lim else
                                    "the campaign config's safety.u_max and safety.rate")
    return write_package(law, f"ff_learn_{j}", Path(out), {"reference": (c.reference, u)}, cc=cc,
                         source={"campaign": str(c.folder.resolve()), "trial": j})
