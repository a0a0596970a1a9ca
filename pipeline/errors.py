"""Errors and names every layer shares (no imports from the rest of the pipeline, so no cycle)."""
from __future__ import annotations

import re

#: the order stages run in; ``cfg.stages`` selects a subset
ORDER = ("generate", "baseline", "train", "invert", "evaluate", "export", "report")

#: an experiment name: it is also a folder of the artifact store, so no path separators or '..'
SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


class ConfigError(ValueError):
    """A bad config key or value, raised before any work is done."""


class NonPhysical(ValueError):
    """An identified model with no physical inverse (1/M not positive): the invert stage names it in one
    line instead of a traceback (issue 51)."""


class ExportError(ValueError):
    """A feedforward the exporter cannot ship (unsupported law or model shape, no compiler, a
    package that does not reproduce the study); ``pipeline.export.law`` re-exports it."""
