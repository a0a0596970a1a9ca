"""The exported feedforward as an MLflow pyfunc model (``loader_module`` flavour: no pickle).

``mlflow models predict -m runs:/<run id>/<package> -i reference.csv -t csv --env-manager local``
reads a one-column table ``r`` (one reference, in time order) and returns ``u_ff`` and ``flags``,
computed by :func:`pipeline.export.law.guarded` from the law's ``law.json`` + ``law.npz`` (the data
the C code was generated from): the law with its guard, flag for flag as the C.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from mlflow.models import ModelSignature
from mlflow.types import ColSpec, Schema

from pipeline.export.law import ExportError, Law, guarded

__all__ = ["FeedforwardModel", "signature", "_load_pyfunc"]


class FeedforwardModel:
    """pyfunc interface: ``predict(DataFrame with column r) -> DataFrame with column u_ff``."""

    def __init__(self, law: Law):
        self.law = law

    def predict(self, model_input, params=None):
        if isinstance(model_input, pd.DataFrame):
            if "r" not in model_input.columns:
                raise ExportError(f"the input needs a column 'r' (the reference [{self.law.units['r']}], "
                                  f"one row per sample); got columns {list(model_input.columns)}")
            r = model_input["r"].to_numpy(np.float64)
        else:
            r = np.asarray(model_input, dtype=np.float64).reshape(-1)
        u, flags = guarded(self.law, r)
        return pd.DataFrame({"u_ff": u, "flags": flags})


def signature(law: Law, r_example: np.ndarray):
    """Input/output signature and example of the model (the first samples of a reference)."""
    ex = pd.DataFrame({"r": np.asarray(r_example, dtype=np.float64)})
    # stated, not inferred: flags are a bit field (int64), never missing (inference warns about that)
    sig = ModelSignature(inputs=Schema([ColSpec("double", "r")]),
                         outputs=Schema([ColSpec("double", "u_ff"), ColSpec("long", "flags")]))
    return sig, ex


def _load_pyfunc(data_path: str) -> FeedforwardModel:
    """MLflow's entry point: the model from the package's ``law`` folder."""
    return FeedforwardModel(Law.load(data_path))
