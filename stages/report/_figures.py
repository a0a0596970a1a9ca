"""Copy a run's figure artifact from MLflow into results/figures/."""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import mlflow

from pipeline import tracking


def copy_figure(run_id: str, artifact: str, figdir: Path, filename: str) -> str | None:
    """Return ``figures/<filename>`` (relative to REPORT.md) or None if the run has no such figure."""
    tracking.client()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=artifact,
                                                        dst_path=tmp)
        except Exception:  # noqa: BLE001 — a missing artifact only drops the figure
            return None
        shutil.copyfile(local, figdir / filename)
    return f"figures/{filename}"
