"""The parameter-class vocabulary every option's ``Params`` is written in (issue 21 item 1): the
``schema`` decorator, :func:`spec` (a field's default, range, unit, rule and example), the plausible
magnitudes of physical quantities and two shared rules. Imports nothing of Hydra or OmegaConf, so the
library modules that declare their parameters next to their code (``pipeline/systems``,
``pipeline/models``) stay usable without the config machinery; :mod:`pipeline.schema` checks a config
against these classes.
"""
from __future__ import annotations

from dataclasses import MISSING, dataclass, field
from typing import Any, Callable

from pipeline.errors import SAFE_NAME

__all__ = ["schema", "spec", "is_number", "references_rule", "TS_MAX", "MASS_MAX", "STIFF_MAX", "DAMP_MAX",
           "FORCE_MAX", "LENGTH_MAX", "SPEED_MAX", "NOISE_MAX", "FREQ_MAX", "ITER_MAX", "COUNT_MAX"]

#: every schema class: keyword-only fields, so a mandatory field may follow defaulted ones
schema = dataclass(kw_only=True)


def spec(default: Any = MISSING, *, gt: float | None = None, ge: float | None = None, lt: float | None = None,
         le: float | None = None, unit: str = "", rule: str | None = None, example: Any = MISSING,
         min_len: int = 0, check: Callable[[Any], str | None] | None = None, fill: bool = True) -> Any:
    """A schema field: ``default`` (a list is copied per instance; MISSING: mandatory), the bounds
    of the value (of each item of a list), its unit, the shortest list, the rule and example the
    error message quotes (generated from type and bounds when not given), and ``check(value)``:
    an extra rule, returning what is wrong (or None). ``fill=False``: a key only some settings take
    (a controller kind's own gains), absent unless given (a null default is then never set)."""
    meta = dict(gt=gt, ge=ge, lt=lt, le=le, unit=unit, rule=rule, example=example, min_len=min_len,
                check=check, fill=fill)
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


# ------------------------------------------------------------------------------------------------
# plausible magnitudes (upper bounds of physical quantities; SI units)
# ------------------------------------------------------------------------------------------------
TS_MAX = 1.0          # [s] sample time of a motion system (1 Hz is already far below any servo loop)
MASS_MAX = 1e6        # [kg]
STIFF_MAX = 1e12      # [N/m]
DAMP_MAX = 1e9        # [N s/m]
FORCE_MAX = 1e7       # [N]
LENGTH_MAX = 100.0    # [m] strokes, lengths, pitches
SPEED_MAX = 100.0     # [m/s]
NOISE_MAX = 1.0       # [m] std of a position noise: a metre of noise is no motion system
FREQ_MAX = 1e6        # [Hz] or [rad/s]
ITER_MAX = 10**7      # iteration caps
COUNT_MAX = 10**4     # restarts, trials, seeds


def references_rule(v) -> str | None:
    """Reference specs: a list (or mapping by name) of mappings with a kind (pipeline.references)."""
    items = list(v.values()) if isinstance(v, dict) else v
    if not isinstance(items, list) or not all(isinstance(s, dict) for s in items):
        return "give a list of reference specs {name: ..., kind: ..., ...} (see conf/evaluate/*.yaml)"
    keys = list(v) if isinstance(v, dict) else [None] * len(items)
    names = [str(s.get("name", k if k is not None else f"ref{i}")) for i, (k, s) in enumerate(zip(keys, items))]
    bad = [n for n in names if not SAFE_NAME.fullmatch(n)]
    if bad:          # a name is a metric key and a file name: no '/', '..' or spaces
        return f"reference name(s) {bad} are not names: use letters, digits, '.', '_' and '-'"
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:        # the second would silently replace the first in every table
        return f"reference name(s) {twice} given more than once: give each reference its own name"
    return None


def is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)
