"""Run names and notes that explain themselves in the MLflow UI (issue 23); no MLflow here.

A run has two names:

- its **key** (tag ``run_key``): ``cfg.run_name``, the experiment's template plus ``-<key>=<value>`` for
  what the template does not show (:func:`pipeline.runner.run_name_with_overrides`); stable, the
  report's identity of a run (summary.csv rows are keyed by it);
- its **display name** (MLflow's run name, :func:`display_name`): what varies inside its experiment
  first, short, joined by ``·`` (``direct·inv·eq·σ1e-7``), then `` | `` and the fixed settings
  (system, seed), so the visible start of the runs table's name column tells the runs apart.
"""
from __future__ import annotations

import re
from typing import Any, Iterable, Mapping

#: the order in which varying keys lead a display name (others follow in their override order)
LEAD = ("invert", "model", "system.noise.structure", "system.noise.std", "regularizer", "regularizer.lam",
        "model.hidden", "invert.gamma", "model.nn_inputs", "invert.trial_noise", "identify.theta_star")
#: short forms of values (per key, then for any key)
SHORT = {"system.noise.structure": {"equation": "eq", "output": "out"},
         "regularizer": {"physics_l2": "L2", "none": "noreg", "orthogonal": "orth"},
         "invert.trial_noise": {"True": "trialnoise", "False": "noiseless"}}
#: symbols that prefix a numeric value of a key
PREFIX = {"system.noise.std": "σ", "regularizer.lam": "λ", "invert.gamma": "γ", "model.hidden": "n",
          "seed": "s", "init_seed": "init", "data.n_samples": "N", "identify.theta_star": "θ*",
          "model.nn_inputs": "nn_"}
#: inversions of a PGNN: the display name adds which identification they use ([B1]: fwd = forward PGNN (10),
#: inv = direct-inverse PGNN (13), invt = invertible PGNN (26)), short so that the name column shows it
PGNN_INVERSIONS = ("direct", "newton", "analytic")
PGNN_SHORT = {"forward": "fwd", "inverse": "inv", "invertible": "invt"}
#: integer values zero-padded to this many digits in a name, so that text order is numeric order
PADDED = {"model.hidden": 2}
#: overrides that are not a variation of what a run computes
SKIP = ("experiment", "hydra", "stages", "paths", "report", "export", "run_name", "experiment_name", "description")


def _num(v: Any) -> str:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if f != int(f) or abs(f) >= 1e5:   # 1e-07 -> 1e-7: every character counts in the name column
        return re.sub(r"e([+-])0*(\d)", lambda m: "e" + m.group(1).replace("+", "") + m.group(2), f"{f:g}")
    return str(int(f))


def short_value(key: str, value: Any, model_name: str = "") -> str:
    """One key's value as it reads in a display name."""
    if isinstance(value, (list, tuple)):
        value = "-".join(_num(x) for x in value) if value else "0"
    if key in PADDED:   # n00 < n01 < … < n16 < n48 also where the UI sorts names as text (issue 52)
        return PREFIX.get(key, "") + re.sub(r"\d+", lambda m: m.group(0).zfill(PADDED[key]), str(value))
    s = str(value)
    if key in SHORT and s in SHORT[key]:
        return SHORT[key][s]
    if key == "invert" and s in PGNN_INVERSIONS and model_name.startswith("pgnn-"):
        kind = model_name.removeprefix("pgnn-")
        return f"{s}·{PGNN_SHORT.get(kind, kind)}"   # direct·inv, newton·fwd, analytic·invt
    if key in PREFIX:
        return PREFIX[key] + _num(value)
    if isinstance(value, bool) or s in ("True", "False", "true", "false"):
        leaf = key.rsplit(".", 1)[-1]
        return leaf if s.lower() == "true" else f"no_{leaf}"
    if "." in key and key.split(".")[0] not in ("invert", "model", "regularizer"):
        return f"{key.rsplit('.', 1)[-1]}={s}"
    return s


def _sweeps(value: str) -> bool:
    """Whether a Hydra override value lists several values (``a,b``, ``choice(..)``, ``range(..)``)."""
    v = str(value).strip()
    m = re.fullmatch(r"(choice|range|glob)\((.*)\)", v)
    if m:
        if m.group(1) != "choice":
            return True
        v = m.group(2)
    depth = 0
    for ch in v:
        depth += ch in "[{(" and 1 or 0
        depth -= ch in "]})" and 1 or 0
        if ch == "," and depth == 0:
            return True
    return False


def varying_keys(sweep_params: Mapping[str, Any] | None, overrides: Iterable[str] = ()) -> list[str]:
    """The dotted keys a sweep varies, in :data:`LEAD` order: the experiment's own sweep parameters
    with several values, and the command line's (``system.noise.std=0,1e-7``); a single value on the
    command line replaces the experiment's sweep of that key (a setting, not a variation)."""
    keys = [k for k, v in (sweep_params or {}).items() if _sweeps(v)]
    for ov in overrides:
        key, sep, raw = ov.lstrip("+~").partition("=")
        key = key.replace("/", ".")
        if not sep or key.split(".")[0] in SKIP:
            continue
        if _sweeps(raw):
            keys.append(key)
        elif key in keys:
            keys.remove(key)
    keys = list(dict.fromkeys(keys))
    return sorted(keys, key=lambda k: (LEAD.index(k) if k in LEAD else len(LEAD), keys.index(k)))


def display_name(values: Mapping[str, Any], varying: list[str], system: str, seed: int,
                 fallback: str, model_name: str = "") -> str:
    """``<varying values joined by ·> | <system> s<seed>``; ``fallback`` (the run key) when nothing varies."""
    if not varying:
        return fallback
    lead = "·".join(short_value(k, values.get(k), model_name) for k in varying)
    fixed = [system] if system else []
    if "seed" not in varying:
        fixed.append(f"s{seed}")
    return f"{lead} | {' '.join(fixed)}" if fixed else lead


def run_note(display: str, varying: list[str], values: Mapping[str, Any], experiment: str,
             description: str) -> str:
    """The run's MLflow description: what this run is within its experiment and where to look."""
    lines = [f"**{display}**: one job of experiment `{experiment}`."]
    if varying:
        lines.append("Varies inside the experiment: " + ", ".join(f"`{k}` = `{values.get(k)}`" for k in varying) + ".")
    if description:
        lines += ["", "Experiment: " + description.strip()]
    return "\n".join(lines)
