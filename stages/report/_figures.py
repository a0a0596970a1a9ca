"""Copy a run's figure artifacts from MLflow into results/figures/."""
from __future__ import annotations

import functools
import os
import re
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")

import mlflow  # noqa: E402
import numpy as np

from pipeline import tracking  # noqa: E402


def safe_name(name: str) -> str:
    """``name`` as one file name: characters other than letters, digits and ``._-[]=,`` become ``_``."""
    return re.sub(r"[^A-Za-z0-9._\-\[\]=,]", "_", name).lstrip(".") or "_"


def copy_figures(run_id: str, figdir: Path, prefix: str, only: tuple[str, ...] = ()) -> list[str]:
    """Copy the run's ``figures/*.png`` (those whose name contains one of ``only``, if given) to
    ``figdir/<prefix>-<name>``; return the paths relative to REPORT.md (``figures/...``)."""
    c = tracking.client()
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for art in c.list_artifacts(run_id, "figures"):
            if not art.path.endswith(".png") or (only and not any(s in art.path for s in only)):
                continue
            local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=art.path,
                                                        dst_path=tmp)
            name = safe_name(f"{prefix}-{Path(art.path).name}")   # a run name is not a path
            shutil.copyfile(local, figdir / name)
            out.append(f"figures/{name}")
    return out


@functools.lru_cache(maxsize=64)  # the Fig. 3 plot and the peak lags read the same runs
def load_errors(run_id: str) -> dict | None:
    """The run's ``evaluate/errors.npz`` (Ts, and ``<ref>/r``, ``<ref>/e``) as a dict of arrays, or
    None if the run has none (runs made before the evaluate stage logged it)."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path="evaluate/errors.npz",
                                                        dst_path=tmp)
        except Exception:  # noqa: BLE001 — MLflow raises several types for a missing artifact
            return None
        with np.load(local) as z:
            return {k: z[k] for k in z.files}
