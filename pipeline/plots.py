"""Matplotlib figures (Agg backend; callers hand them to ``ctx.figure`` which saves and closes)."""
from __future__ import annotations

import numpy as np


def pyplot():
    """matplotlib.pyplot on the Agg backend, imported on first use (1.0 s of every job's start-up,
    and a cached job draws nothing)."""
    import matplotlib  # lazy: saves 0.2 s of start-up (matplotlib; a cached job draws nothing)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: saves 0.8 s of start-up (matplotlib.pyplot; a cached job draws nothing)
    return plt


def signals(t: np.ndarray, series: dict[str, np.ndarray], ylabel: str, title: str = ""):
    """One panel of several signals over time."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3))
    for name, x in series.items():
        ax.plot(t, x, label=name, lw=1)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if len(series) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def tracking_errors(runs: dict[str, tuple[np.ndarray, np.ndarray]], title: str = "",
                    ylabel: str = "e = r - y [m]"):
    """Tracking error e = r - y per method/reference ([B1] Fig. 3): ``{label: (t, e)}``."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for label, (t, e) in runs.items():
        ax.plot(t, e, lw=1, label=label)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def trials(errors: dict[str, np.ndarray], ylabel: str = "rms e [m]", title: str = "",
           floor: float | None = None):
    """Error per ILC / IL-FHOFC trial on a log scale ([B2] Fig. 5)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for label, err in errors.items():
        ax.semilogy(np.arange(len(err)), err, "o-", ms=3, label=label)
    if floor is not None:
        ax.axhline(floor, color="k", ls="--", lw=0.8, label="noise floor")
    ax.set_xlabel("trial")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def sweep(x: np.ndarray, curves: dict[str, np.ndarray], xlabel: str, ylabel: str, title: str = "",
          logx: bool = False, logy: bool = False):
    """Metric vs a sweep variable ([B1] Fig. 4, [B2] Fig. 4)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    for label, yv in curves.items():
        ax.plot(x, yv, "o-", ms=3, label=label)
    ax.set_xscale("log" if logx else "linear")
    ax.set_yscale("log" if logy else "linear")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
