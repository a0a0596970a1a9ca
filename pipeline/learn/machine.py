"""Virtual machines behind the campaign's files (issue 50 item 5).

``--machine sim:<module>:<function>`` names a user's simulator: a Python function ``function(r, u_ff)``
(r [m] and u_ff [N], numpy arrays of one trial) returning a recording dict with at least ``u`` [N] (the
force applied) and ``y`` [m] (the measured position), e.g. ``sim:tests.heldout_axis:simulate`` (the held-out
vertical axis). The module is imported from the working directory or the Python path. :func:`run` plays the
machine's operator: it runs each trial's ``u_ff_<j>.csv``, writes the recording to
``<campaign>/machine/trial_<j>.csv`` (t, r, u, y, u_ff: exactly what a real machine would hand back) and
calls :func:`pipeline.learn.campaign.step` on it, so a virtual campaign goes through the same files and
checks as a real one.
"""
from __future__ import annotations

import importlib
import inspect
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError
from pipeline.learn import campaign

__all__ = ["resolve", "run"]


def resolve(spec: str) -> Callable:
    """The simulator named ``sim:<module>:<function>``."""
    parts = spec.split(":")
    if len(parts) != 3 or parts[0] != "sim" or not all(parts[1:]):
        raise ConfigError(f"--machine {spec!r}: give sim:<module>:<function>, e.g. sim:tests.heldout_axis:simulate "
                          "(a function (r, u_ff) -> dict with u and y)")
    if str(Path.cwd()) not in sys.path:
        sys.path.insert(0, str(Path.cwd()))
    try:
        fn = getattr(importlib.import_module(parts[1]), parts[2])
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"--machine {spec!r}: {exc}; the module must be importable from {Path.cwd()} or the "
                          "Python path") from None
    if not callable(fn) or len(inspect.signature(fn).parameters) < 2:
        raise ConfigError(f"--machine {spec!r}: {parts[2]} must be a function taking (r, u_ff)")
    return fn


def run(folder, machine: str, trials: int, seed0: int = 100) -> list[dict]:
    """Up to ``trials`` trials of the campaign in ``folder`` on the simulator ``machine`` (module docstring);
    stops early when the campaign stops. A simulator that takes ``seed`` gets seed0 + j (its noise differs
    from trial to trial, as a machine's does)."""
    fn = resolve(machine)
    seeded = "seed" in inspect.signature(fn).parameters
    c = campaign.load(folder)
    out_dir = Path(folder) / "machine"
    out_dir.mkdir(exist_ok=True)
    log = []
    for _ in range(trials):
        c = campaign.load(folder)
        j = len(c.state["trials"])
        if c.state["stopped"]:
            break
        u_ff = c.u_ff(j)
        rec = fn(c.reference.copy(), u_ff.copy(), **({"seed": seed0 + j} if seeded else {}))
        for k in ("u", "y"):
            got = np.shape(rec[k]) if k in rec else "no"
            if got != u_ff.shape:
                raise ConfigError(f"{machine}: returned {k!r} of shape {got} for a reference of {u_ff.size} samples; "
                                  f"a machine returns {{'u': …, 'y': …}}, one sample per reference sample")
        path = out_dir / f"trial_{j}.csv"
        pd.DataFrame({"t": np.arange(u_ff.size) * c.Ts, "r": c.reference, "u": np.asarray(rec["u"], np.float64),
                      "y": np.asarray(rec["y"], np.float64), "u_ff": u_ff}).to_csv(path, index=False,
                                                                                     float_format="%.17g")
        log.append(campaign.step(folder, path))
    return log
