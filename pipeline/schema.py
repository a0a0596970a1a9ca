"""The typed schema of the composed config: what every key may hold, checked before any work.

One dataclass per config group option (``system`` by ``_target_``, ``data`` / ``identify`` /
``invert`` by ``kind``, ``model`` by ``kind`` or layout, ``regularizer`` by ``name``) plus the
top level (:class:`Config`: seed, experiment name, stages, paths, ``export``, ``report``). A field's
annotation is its type (``bool``, ``int``, ``float``, ``str``, ``Literal[...]`` for an enumeration,
``list[...]``, ``Optional[...]`` for null, a nested dataclass for a sub-node, ``Any`` for what a
library checks itself, e.g. reference specs); its metadata (:func:`spec`) gives the range
(``gt``/``ge``/``lt``/``le``, on every item of a list), the unit, a list's shortest length, and
the rule and example quoted in the message. Every ``float`` must be finite, and every physical
quantity has an upper bound that rules out implausible magnitudes (``system.noise.std=1e300``).

:func:`check` validates the resolved config against these classes: an unknown key, a missing
mandatory value (``???``), a value of the wrong type, outside its range or not one of its choices
raises :class:`pipeline.runner.ConfigError` with one line naming the key, the value, what is allowed
and an example, e.g. ``model.hidden=[-3]: widths must be positive integers (e.g.
model.hidden=[16])``. Types are strict: nothing is coerced (``true``/``false`` only for a bool, not
``maybe``, ``yes`` or 1; an integer for an int, not 1.5 or '3'); this is why the check walks the
annotations itself instead of merging into ``OmegaConf.structured`` (which converts 'yes' and 1 to
True and '3' to 3). Keys a config leaves out keep the stages' defaults. Checks across keys or
against the plant (orders against the physics model, bounds lower < upper, references within the
plant's limits) stay in the stages' ``validate`` / ``check`` functions, which run after this one.

Adding a plant or a method: add its dataclass here and to :data:`SYSTEMS`, :data:`DATA`,
:data:`MODELS`, :data:`IDENTIFY`, :data:`REGULARIZERS` or :data:`INVERT` (tests/test_config_schema.py
checks that every stage implementation has one).
"""
from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import MISSING, dataclass, field
from typing import Any, Callable, Literal, Optional, Union

from omegaconf import OmegaConf, open_dict

from pipeline.errors import ORDER, SAFE_NAME, ConfigError

#: every schema class: keyword-only fields, so a mandatory field may follow defaulted ones
schema = dataclass(kw_only=True)

__all__ = ["check", "spec", "Config", "SYSTEMS", "DATA", "MODELS", "IDENTIFY", "REGULARIZERS", "INVERT",
           "Evaluate"]


def spec(default: Any = MISSING, *, gt: float | None = None, ge: float | None = None, lt: float | None = None,
         le: float | None = None, unit: str = "", rule: str | None = None, example: Any = MISSING,
         min_len: int = 0, check: Callable[[Any], str | None] | None = None) -> Any:
    """A schema field: ``default`` (a list is copied per instance; MISSING: mandatory), the bounds
    of the value (of each item of a list), its unit, the shortest list, the rule and example the
    error message quotes (generated from type and bounds when not given), and ``check(value)``:
    an extra rule, returning what is wrong (or None)."""
    meta = dict(gt=gt, ge=ge, lt=lt, le=le, unit=unit, rule=rule, example=example, min_len=min_len,
                check=check)
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


def _lam_rule(v) -> str | None:
    """regularizer.lam of physics_l2: a number or a list (diag Λ) of numbers, finite, >= 0."""
    vals = v if isinstance(v, list) else [v]
    if not vals or not all(_is_number(x) and math.isfinite(x) and 0 <= x <= 1e12 for x in vals):
        return "give a finite number >= 0 and <= 1e12, or a list of them (diag Λ)"
    return None


def _references_rule(v) -> str | None:
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


def _stages_rule(v) -> str | None:
    unknown = [s for s in v if s not in ORDER]
    if unknown:
        return f"unknown stage(s) {unknown}; choose from {list(ORDER)}"
    return None


def _name_rule(v) -> str | None:
    if not SAFE_NAME.fullmatch(v):
        return ("is not a name: use letters, digits, '.', '_' and '-' (it names the MLflow experiment and its "
                "artifact folder)")
    return None


# ------------------------------------------------------------------------------------------------
# top level
# ------------------------------------------------------------------------------------------------
@schema
class Paths:
    cache: Optional[str] = None      # stage output store; null = <repo>/.cache (or $PIPELINE_CACHE)
    results: Optional[str] = None    # report output; null = <repo>/results


def _prefix_rule(v) -> str | None:
    from pipeline.export.package import check_prefix  # lazy: saves 0.1 s of start-up (pipeline.export)
    return check_prefix(v)


@schema
class Limits:
    """export.limits: the guard around an exported law (pipeline.export.guard)."""
    u_min: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-200.0)
    u_max: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=200.0)
    rate: Optional[float] = spec(None, gt=0, le=1e12, unit="N/s", example=1e5)
    envelope_margin: float = spec(0.1, ge=0, le=100)
    envelope_action: Literal["flag", "fallback"] = "flag"
    fallback: Literal["hold", "physics", "ramp"] = "hold"
    ramp_time: float = spec(0.1, gt=0, le=3600.0, unit="s")


@schema
class Export:
    compile: bool = True
    cc: str = "cc"
    rtol: float = spec(1e-9, gt=0, lt=1)
    timing_repeats: int = spec(21, ge=0, le=COUNT_MAX)
    register: bool = False
    prefix: Optional[str] = spec(None, check=_prefix_rule, example="axis1_ff")
    precision: Literal["double", "single"] = "double"
    single_rtol: float = spec(0.1, gt=0, le=10)
    target_rate: Optional[float] = spec(None, gt=0, le=FREQ_MAX, unit="Hz", example=4000.0)
    cppcheck: bool = True
    limits: Limits = field(default_factory=Limits)


@schema
class Report:
    experiments: list[str] = spec(["physics_baseline"], min_len=1)
    update: bool = False


@schema
class Config:
    """The top level; each group (system, data, ...) is checked by its option's class below."""
    seed: int = spec(0, ge=0)
    experiment_name: str = spec("default", check=_name_rule, example="my_study")
    run_name: str = "default"
    description: str = ""            # the experiment's MLflow note: what it compares, which tags/metrics to read
    compare_metrics: list[str] = spec(["evaluate/*/mae"])   # metric globs of the sweep's comparison (issue 23)
    stages: list[str] = spec(["generate", "baseline", "train", "invert", "evaluate"], min_len=1,
                             check=_stages_rule, example=["generate", "baseline"],
                             rule=f"give a non-empty list of stages from {list(ORDER)}")
    paths: Paths = field(default_factory=Paths)
    export: Export = field(default_factory=Export)
    report: Report = field(default_factory=Report)
    system: Any = None
    data: Any = None
    model: Any = None
    identify: Any = None
    regularizer: Any = None
    invert: Any = None
    evaluate: Any = None


# ------------------------------------------------------------------------------------------------
# system (by _target_)
# ------------------------------------------------------------------------------------------------
@schema
class StdNoise:
    std: float = spec(0.0, ge=0, lt=NOISE_MAX, unit="m")


@schema
class MotorNoise:
    structure: Literal["equation", "output"] = "equation"
    std: float = spec(1e-6, ge=0, lt=NOISE_MAX, unit="m")


@schema
class OutputNoise:
    structure: Literal["output"] = "output"
    std: float = spec(1e-6, ge=0, lt=NOISE_MAX, unit="m")


@schema
class ArxNoise:
    structure: Literal["equation"] = "equation"
    std: float = spec(0.1, ge=0, le=1e3, unit="(output units)")


@schema
class TwoMassStribeck:
    _target_: str
    name: str = "two_mass_stribeck"
    m1: float = spec(1.0, gt=0, le=MASS_MAX, unit="kg")
    m2: float = spec(2.0, gt=0, le=MASS_MAX, unit="kg")
    k1: float = spec(1.0, ge=0, le=STIFF_MAX, unit="N/m")
    k2: float = spec(15000.0, gt=0, le=STIFF_MAX, unit="N/m")
    d2: float = spec(50.0, ge=0, le=DAMP_MAX, unit="N s/m")
    c1: float = spec(1.0, ge=0, le=DAMP_MAX, unit="N s/m")
    c2: float = spec(20.0, ge=0, le=DAMP_MAX, unit="N s/m")
    alpha: float = spec(20.0, ge=0, le=1e9, unit="s/m")
    Ts: float = spec(1e-3, gt=0, le=TS_MAX, unit="s")
    noise: StdNoise = field(default_factory=StdNoise)


@schema
class LinearMotor:
    _target_: str
    name: str = "linear_motor"
    Ts: float = spec(1e-3, gt=0, le=TS_MAX, unit="s")
    m: float = spec(20.0, gt=0, le=MASS_MAX, unit="kg")
    f_v: float = spec(50.0, ge=0, le=DAMP_MAX, unit="N s/m")
    f_c: float = spec(10.0, ge=0, le=FORCE_MAX, unit="N")
    f_s: float = spec(15.0, ge=0, le=FORCE_MAX, unit="N")
    v_s: float = spec(0.01, gt=0, le=SPEED_MAX, unit="m/s")
    eps_v: float = spec(1e-3, gt=0, le=SPEED_MAX, unit="m/s")
    p: float = spec(0.025, gt=0, le=LENGTH_MAX, unit="m")
    A1: float = spec(5.0, ge=-FORCE_MAX, le=FORCE_MAX, unit="N")
    A2: float = spec(2.0, ge=-FORCE_MAX, le=FORCE_MAX, unit="N")
    phi1: float = spec(0.3, ge=-2 * math.pi, le=2 * math.pi, unit="rad")
    phi2: float = spec(1.1, ge=-2 * math.pi, le=2 * math.pi, unit="rad")
    cogging: bool = True
    friction: Literal["stribeck", "sign"] = "stribeck"
    noise: MotorNoise = field(default_factory=MotorNoise)
    substeps: int = spec(20, ge=1, le=10_000)
    crossover_hz: float = spec(20.0, gt=0, le=FREQ_MAX, unit="Hz")
    physics_input: Literal["auto", "direct", "averaged"] = "auto"
    stroke: float = spec(0.2, gt=0, le=LENGTH_MAX, unit="m")
    v_limit: float = spec(0.5, gt=0, le=SPEED_MAX, unit="m/s")


@schema
class RotTransNMP:
    _target_: str
    name: str = "rot_trans_nmp"
    Ts: float = spec(0.01, gt=0, le=TS_MAX, unit="s")
    m: float = spec(20.0, gt=0, le=MASS_MAX, unit="kg")
    l_x: float = spec(1.0, gt=0, le=LENGTH_MAX, unit="m")
    l_y: float = spec(1.0, ge=-LENGTH_MAX, le=LENGTH_MAX, unit="m")
    J: float = spec(40.0 / 3.0, gt=0, le=MASS_MAX * LENGTH_MAX**2, unit="kg m^2")
    f_v: float = spec(50.0, ge=0, le=DAMP_MAX, unit="kg/s")
    k: float = spec(25e3 / 3.0, ge=0, le=STIFF_MAX, unit="kg/s^2")
    d: float = spec(575.0 / 3.0, ge=0, le=DAMP_MAX, unit="kg/s")
    l_m: float = spec(0.05, gt=0, le=LENGTH_MAX, unit="m")
    c: float = spec(1.0, ge=-FORCE_MAX, le=FORCE_MAX, unit="N")
    controller_gain: float = spec(5000.0, gt=0, le=STIFF_MAX, unit="N/m")
    controller_zero: float = spec(4.0 * math.pi, gt=0, le=FREQ_MAX, unit="rad/s")
    controller_pole: float = spec(20.0 * math.pi, gt=0, le=FREQ_MAX, unit="rad/s")
    noise: OutputNoise = field(default_factory=OutputNoise)
    substeps: int = spec(20, ge=1, le=10_000)
    r_limit: float = spec(0.5, gt=0, le=LENGTH_MAX, unit="m")
    v_limit: float = spec(1.0, gt=0, le=SPEED_MAX, unit="m/s")


@schema
class ArxBias:
    _target_: str
    name: str = "arx_bias"
    a: list[float] = spec([1.5, -0.7], ge=-1e3, le=1e3)
    b: list[float] = spec([1.0, 0.5], ge=-1e6, le=1e6, min_len=1)
    noise: ArxNoise = field(default_factory=ArxNoise)
    u_std: float = spec(1.0, ge=0, le=1e6)
    Ts: float = spec(1.0, gt=0, le=3600.0, unit="s")   # a discrete system: Ts is only recorded


@schema
class Controller:
    """system.controller (pipeline.systems.controller): kind cascade (kp, kv) or lti (num, den, num_r,
    delay); which keys a kind takes is checked by LTIController.from_config."""
    kind: Literal["cascade", "lti"] = "cascade"
    kp: Optional[float] = spec(None, gt=0, le=1e6, unit="1/s", example=160.18)
    kv: Optional[float] = spec(None, gt=0, le=1e9, unit="controller units per m/s", example=243.45)
    num: Optional[list[float]] = spec(None, ge=-1e15, le=1e15, min_len=1, example=[4.279e6, -8.212e6, 3.939e6])
    den: Optional[list[float]] = spec(None, ge=-1e15, le=1e15, min_len=1, example=[1.0, -1.4361, 0.4361])
    num_r: Optional[list[float]] = spec(None, ge=-1e15, le=1e15, min_len=1, example=[4.279e6, -8.212e6, 3.939e6])
    delay: Optional[int] = spec(None, ge=0, le=100, unit="samples", example=1)
    gtau: float = spec(1.0, gt=0, le=1e6, unit="N per controller unit")
    v_sat: float = spec(1e9, gt=0, le=1e12, unit="controller units")


def _terms_rule(v) -> str | None:
    from pipeline.systems.force_terms import TERMS  # lazy: saves 0.8 s of start-up (numba kernels)
    bad = [t for t in v if t not in TERMS]
    return f"unknown term(s) {bad}; choose from {list(TERMS)} (the mass is always in)" if bad else None


@schema
class ForceTermsCfg:
    """system.force_terms of a measured system (pipeline.systems.force_terms)."""
    terms: list[str] = spec(["viscous", "coulomb", "offset"], check=_terms_rule,
                            example=["viscous", "coulomb", "cogging"])
    coulomb_width: Optional[float] = spec(None, gt=0, le=SPEED_MAX, unit="m/s", example=0.002)
    stribeck_velocity: float = spec(0.01, gt=0, le=SPEED_MAX, unit="m/s")
    cogging_period: Optional[float] = spec(None, gt=0, le=LENGTH_MAX, unit="m", example=0.03)
    cogging_harmonics: int = spec(1, ge=1, le=20)


@schema
class Published:
    M: float = spec(gt=0, le=MASS_MAX, unit="kg", example=95.1)
    F_v: float = spec(ge=-DAMP_MAX, le=DAMP_MAX, unit="N s/m", example=203.5)
    F_c: float = spec(ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=20.4)
    OF: float = spec(ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-3.2)


@schema
class Idim:
    cutoff_hz: float = spec(50.0, gt=0, le=FREQ_MAX, unit="Hz")
    order: int = spec(4, ge=1, le=20)
    decimation: int = spec(10, ge=1, le=10_000)
    trim: int = spec(50, ge=0, le=10**8)


@schema
class Recording:
    _target_: str
    name: str = "measured"
    Ts: float = spec(1e-3, gt=0, le=TS_MAX, unit="s")
    controller: Controller = spec(example="{kp:160.18,kv:243.45}")
    physics_input: Literal["averaged", "direct"] = "averaged"
    force_terms: ForceTermsCfg = field(default_factory=lambda: ForceTermsCfg())
    disturbance: Optional[str] = None
    published: Optional[Published] = None
    idim: Idim = field(default_factory=Idim)


SYSTEMS: dict[str, type] = {
    "pipeline.systems.two_mass_stribeck.TwoMassStribeck": TwoMassStribeck,
    "pipeline.systems.linear_motor.LinearMotor": LinearMotor,
    "pipeline.systems.rot_trans_nmp.RotTransNMP": RotTransNMP,
    "pipeline.systems.arx_bias.ArxBias": ArxBias,
    "pipeline.systems.measured.Recording": Recording,
}


# ------------------------------------------------------------------------------------------------
# data (by kind; stages/generate/<kind>.py)
# ------------------------------------------------------------------------------------------------
@schema
class Excitation:
    std: float = spec(0.0, ge=0, le=FORCE_MAX, unit="N")
    t_start: Optional[float] = spec(None, ge=0, le=1e7, unit="s", example=10.0)
    t_stop: Optional[float] = spec(None, ge=0, le=1e7, unit="s", example=40.0)


@schema
class ClosedLoopData:
    kind: Literal["closed_loop"]
    name: str = "closed_loop"
    references: Any = spec([], check=_references_rule, example="[{name:move,kind:b2_R}]")
    feedforward: Literal["none", "exact"] = "none"
    excitation: Excitation = field(default_factory=Excitation)


@schema
class IlcParams:
    trials: int = spec(30, ge=1, le=COUNT_MAX)
    gain: float = spec(1.0, gt=0, lt=2, rule="the learning gain must be in (0, 2)")
    w_rel: float = spec(0.0, ge=0, le=1e6)
    w_delta_rel: float = spec(0.0, ge=0, le=1e6)
    tol: float = spec(0.0, ge=0, lt=NOISE_MAX, unit="m")
    backend: Literal["auto", "lifted", "matrix_free"] = "auto"
    noise: bool = True


@schema
class IlcData(ClosedLoopData):
    kind: Literal["ilc"]
    name: str = "ilc"
    ilc: IlcParams = field(default_factory=IlcParams)


@schema
class WhiteNoiseData:
    kind: Literal["white_noise"]
    name: str = "white_noise"
    n_samples: int = spec(10000, ge=10, le=10**7, rule="give an integer >= 10 and <= 10^7 (shorter is too short to "
                          "identify from; longer takes more than 80 MB per signal)")
    u_std: float = spec(1.0, ge=0, le=FORCE_MAX, unit="input units")


@schema
class MeasuredData:
    kind: Literal["measured"]
    name: str = "measured"
    path: str = spec(example="../shared/data/emps")
    format: Literal["table", "emps"] = "table"     # = stages.generate.measured.FORMATS
    file: Optional[str] = None
    files: Optional[list[str]] = spec(None, min_len=1, example=["run1.csv", "run2.csv"])   # several records


DATA: dict[str, type] = {"closed_loop": ClosedLoopData, "ilc": IlcData, "white_noise": WhiteNoiseData,
                         "measured": MeasuredData}


# ------------------------------------------------------------------------------------------------
# model (by kind; pgnn when it has a structure, else the physics model)
# ------------------------------------------------------------------------------------------------
_WIDTHS = "widths must be positive integers"


@schema
class PhysicsModel:
    name: str = "physics"


@schema
class Pgnn:
    name: str = "pgnn-forward"
    structure: Literal["forward", "inverse", "invertible"] = "forward"
    n_a: int = spec(2, ge=0, le=1000)
    n_b: int = spec(1, ge=1, le=1000)
    n_k: int = spec(0, ge=0, le=1000)
    hidden: list[int] = spec([16], ge=1, le=100_000, rule=_WIDTHS)
    activation: Literal["tanh", "sigmoid", "relu", "softplus", "elu", "gelu", "identity"] = "tanh"
    use_physics: bool = True
    use_nn: bool = True
    input_transform: Literal["raw", "delta"] = "raw"
    out_init: Literal["mirrored", "scaled"] = "mirrored"
    out_init_scale: float = spec(1.0, ge=0, le=1e6)
    mirror_jitter: float = spec(0.0, ge=0, le=10)
    nn_inputs: Literal["all", "outputs"] = "all"


@schema
class Rational:
    kind: Literal["rational"]
    name: str = "rational"
    n_a: int = spec(10, ge=1, le=1000)
    n_b: int = spec(9, ge=0, le=1000)
    basis: Literal["delta", "shift"] = "delta"


@schema
class PgnnSharedAr:
    kind: Literal["pgnn_shared_ar"]
    name: str = "pgnn_shared_ar"
    n_a: int = spec(5, ge=1, le=1000)
    n_b: int = spec(2, ge=0, le=1000)
    basis: Literal["delta", "shift"] = "delta"
    approximator: Literal["mlp", "residual"] = "mlp"
    hidden: list[int] = spec([10, 10], ge=1, le=100_000, rule=_WIDTHS)
    width: int = spec(10, ge=1, le=100_000)
    n_blocks: int = spec(2, ge=1, le=1000)
    activation: Literal["tanh", "relu", "sigmoid", "softplus"] = "tanh"
    out_bias: bool = False
    out_init_scale: float = spec(1.0, ge=0, le=1e6)
    window: int = spec(4, ge=0, le=10_000)
    window_basis: Literal["delta", "shift"] = "delta"


MODELS: dict[str, type] = {"physics": PhysicsModel, "pgnn": Pgnn, "rational": Rational,
                           "pgnn_shared_ar": PgnnSharedAr}


def _model_option(node: dict) -> str:
    """model.kind where given; else the physics model (model=physics) or a NARX PGNN (model=pgnn)."""
    if "kind" in node:
        return node["kind"]
    return "physics" if node.get("name") == "physics" else "pgnn"


# ------------------------------------------------------------------------------------------------
# identify (by kind; stages/train/<kind>.py)
# ------------------------------------------------------------------------------------------------
@schema
class IdentifyNone:
    kind: Literal["none"]
    name: str = "none"


@schema
class Narx:
    kind: Literal["narx"]
    name: str = "narx"
    n_restarts: int = spec(10, ge=1, le=COUNT_MAX)
    max_iter: int = spec(2000, ge=0, le=ITER_MAX)
    screen_iter: int = spec(50, ge=0, le=ITER_MAX)
    ftol: float = spec(1e-10, ge=0, lt=1)
    gtol: float = spec(1e-10, ge=0, lt=1)
    mu0: float = spec(1e-3, gt=0, le=1e12)
    val_fraction: float = spec(0.2, ge=0, lt=1)
    patience: int = spec(20, ge=1, le=ITER_MAX)
    geodesic: bool = False
    stat_window: int = spec(10, ge=0, le=ITER_MAX)
    stat_tol: float = spec(0.1, ge=0, le=100)
    stat_frac: float = spec(0.0, ge=0, lt=1)


@schema
class SimError:
    kind: Literal["sim_error"]
    name: str = "sim_error"
    theta_star: Literal["arx", "sim_error", "oracle"] = "sim_error"
    linear_max_iter: int = spec(500, ge=0, le=ITER_MAX)
    n_restarts: int = spec(3, ge=1, le=COUNT_MAX)
    max_iter: int = spec(8000, ge=0, le=ITER_MAX)
    screen_iter: int = spec(300, ge=0, le=ITER_MAX)
    ftol: float = spec(1e-10, ge=0, lt=1)
    gtol: float = spec(1e-10, ge=0, lt=1)
    mu0: float = spec(1e-3, gt=0, le=1e12)
    val_fraction: float = spec(0.0, ge=0, lt=0.5)
    patience: int = spec(5, ge=1, le=ITER_MAX)
    geodesic: bool = True
    stat_window: int = spec(10, ge=0, le=ITER_MAX)
    stat_tol: float = spec(1.0, ge=0, le=100)
    stat_frac: float = spec(0.3, ge=0, lt=1)


@schema
class SkOe:
    kind: Literal["sk_oe"]
    name: str = "sk_oe"
    max_iter: int = spec(30, ge=1, le=ITER_MAX)
    tol: float = spec(1e-6, gt=0, lt=1)
    lm_max_iter: int = spec(3000, ge=1, le=ITER_MAX)
    lm_ftol: float = spec(1e-9, ge=0, lt=1)
    lm_gtol: float = spec(1e-10, ge=0, lt=1)
    column_scale: bool = True
    screen_max_iter: int = spec(4, ge=0, le=ITER_MAX)
    screen_lm_max_iter: int = spec(30, ge=0, le=ITER_MAX)
    n_restarts: int = spec(5, ge=1, le=COUNT_MAX)
    n_jobs: int = spec(5, ge=1, le=1024)
    oe_check_iter: int = spec(3000, ge=1, le=ITER_MAX)
    geodesic: bool = True
    cost_tol: float = spec(1e-7, ge=0, lt=1)
    stall_window: int = spec(10, ge=0, le=ITER_MAX)
    stall_tol: float = spec(1e-3, ge=0, lt=1)
    output_tol: float = spec(0.0, ge=0, lt=1)


@schema
class InverseBias:
    kind: Literal["inverse_bias"]
    name: str = "inverse_bias"
    sample_sizes: list[int] = spec([1000, 10000, 100000], ge=10, le=10**8, min_len=2,
                                   rule="give at least two sizes >= 10 (and <= 1e8)")
    n_seeds: int = spec(20, ge=2, le=COUNT_MAX)


IDENTIFY: dict[str, type] = {"none": IdentifyNone, "narx": Narx, "sim_error": SimError, "sk_oe": SkOe,
                             "inverse_bias": InverseBias}


# ------------------------------------------------------------------------------------------------
# regularizer (by name)
# ------------------------------------------------------------------------------------------------
@schema
class RegularizerNone:
    name: Literal["none"]


@schema
class PhysicsL2:
    name: Literal["physics_l2"]
    lam: Any = spec(0.01, check=_lam_rule)


@schema
class Orthogonal:
    name: Literal["orthogonal"]
    lam: float = spec(1.0, ge=0, le=1e12)


REGULARIZERS: dict[str, type] = {"none": RegularizerNone, "physics_l2": PhysicsL2, "orthogonal": Orthogonal}


# ------------------------------------------------------------------------------------------------
# invert (by kind; stages/invert/<kind>.py)
# ------------------------------------------------------------------------------------------------
_Structure = Literal["forward", "inverse", "invertible"]


@schema
class InvertPlain:   # physics, zpetc, exact, none, rational_filter: nothing to set
    kind: str
    name: str = ""


@schema
class Direct:
    kind: Literal["direct"]
    name: str = "direct"
    model_structure: _Structure = "inverse"


@schema
class Analytic:
    kind: Literal["analytic"]
    name: str = "analytic"
    model_structure: _Structure = "invertible"


@schema
class Newton:
    kind: Literal["newton"]
    name: str = "newton"
    model_structure: _Structure = "forward"
    k: int = spec(5, ge=0, le=1000)
    u_min: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-100.0)
    u_max: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=100.0)


@schema
class Bounds:
    lower: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-100.0)
    upper: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=100.0)


@schema
class Fhofc:
    kind: Literal["fhofc"]
    name: str = "fhofc"
    model_structure: _Structure = "forward"
    gamma: float = spec(1e-6, ge=0, le=1.0, unit="m/N")
    horizon: Optional[int] = spec(None, ge=1, le=10**6, example=50)
    uff_bounds: Bounds = field(default_factory=Bounds)
    u_bounds: Bounds = field(default_factory=Bounds)
    max_iter: int = spec(50, ge=1, le=ITER_MAX)
    ftol: float = spec(1e-10, ge=0, lt=1)
    check_range: bool = True
    range_margin: float = spec(0.1, ge=0, le=100.0)


@schema
class IlFhofc(Fhofc):
    kind: Literal["il_fhofc"]
    name: str = "il_fhofc"
    gamma: float = spec(1e-8, ge=0, le=1.0, unit="m/N")
    alpha: float = spec(1.0, gt=0, le=1, rule="the learning gain must be in (0, 1]")
    n_trials: int = spec(7, ge=1, le=COUNT_MAX)
    trial_noise: bool = False
    ideal_w_rel: float = spec(1e-10, ge=0, le=1.0)
    ideal_trials: int = spec(12, ge=1, le=COUNT_MAX)


INVERT: dict[str, type] = {"physics": InvertPlain, "zpetc": InvertPlain, "exact": InvertPlain,
                           "none": InvertPlain, "rational_filter": InvertPlain, "direct": Direct,
                           "analytic": Analytic, "newton": Newton, "fhofc": Fhofc, "il_fhofc": IlFhofc}


# ------------------------------------------------------------------------------------------------
# evaluate (one layout; convention and validation_tail matter for measured systems)
# ------------------------------------------------------------------------------------------------
@schema
class Evaluate:
    references: Any = spec([], check=_references_rule, example="[{name:R,kind:b2_R}]")
    noise: bool = False
    allow_simulator: bool = False
    convention: Literal["data", "published"] = "data"   # = pipeline.identify.measured_loop.CONVENTIONS
    validation_tail: float = spec(0.2, ge=0, lt=1)


# ------------------------------------------------------------------------------------------------
# the check
# ------------------------------------------------------------------------------------------------
#: group -> (options, the key choosing one, the stage implementing them)
GROUPS: dict[str, tuple[dict[str, type], str, str]] = {
    "system": (SYSTEMS, "_target_", ""),
    "data": (DATA, "kind", "generate"),
    "model": (MODELS, "kind", ""),
    "identify": (IDENTIFY, "kind", "train"),
    "regularizer": (REGULARIZERS, "name", ""),
    "invert": (INVERT, "kind", "invert"),
}


def check(cfg) -> list[str]:
    """Validate the composed config against the schema; ConfigError (one line) on the first problem.
    Then every key left out is set to its schema default in ``cfg`` (the one place a default is
    stated: stages read every key without a default of their own); returns the keys set."""
    try:  # every interpolation resolves (a typo in ${...} fails here, not after hours of work)
        raw = OmegaConf.to_container(cfg, resolve=True)
    except Exception as exc:  # noqa: BLE001 — OmegaConf raises several error types
        raise ConfigError(f"config does not resolve: {str(exc).splitlines()[0]}") from exc
    raw.pop("hydra", None)
    _DEFAULTED.clear()
    _check_nodes(raw)
    filled = list(_DEFAULTED)
    with open_dict(cfg):
        for key, value in filled:
            OmegaConf.update(cfg, key, value, force_add=True)
    return [k for k, _ in filled]


#: (dotted key, default) of the keys the last check found left out
_DEFAULTED: list[tuple[str, Any]] = []


def _default(f: dataclasses.Field) -> Any:
    v = f.default if f.default is not MISSING else f.default_factory()
    return dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v


def _check_nodes(raw: dict) -> None:
    _check_node(Config, raw, "", "the config")
    for group, (options, by, stage) in GROUPS.items():
        node = raw.get(group)
        if node is None:
            continue
        if not isinstance(node, dict):
            raise ConfigError(f"{group}={_show(node)} is not a config group: choose an option, e.g. "
                              f"{group}=<name of a file in conf/{group}/>")
        option = _model_option(node) if group == "model" else node.get(by)
        if option not in options:
            where = f"no '{stage}' implementation" if stage else "no schema"
            raise ConfigError(f"{group}.{by}={_show(option)}: {where} for {by} {option!r}; choose one of "
                              f"{sorted(options)}" + (" (a new plant needs its dataclass in pipeline/schema.py "
                                                      "SYSTEMS)" if group == "system" else ""))
        label = f"{group} {option!r}" if group != "system" else f"system '{node.get('name', option)}'"
        _check_node(options[option], node, group, label)
    if raw.get("evaluate") is not None:
        _check_node(Evaluate, raw["evaluate"], "evaluate", "evaluate")


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _check_node(cls: type, node: Any, prefix: str, label: str) -> None:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if not isinstance(node, dict):
        raise ConfigError(f"{prefix}={_show(node)} is not a mapping: give the keys {', '.join(fields)}")
    unknown = [k for k in node if k not in fields]
    if unknown:
        raise ConfigError(f"{_join(prefix, str(unknown[0]))}: unknown key of {label}; allowed keys: "
                          f"{', '.join(fields)}")
    hints = typing.get_type_hints(cls)
    for name, f in fields.items():
        key = _join(prefix, name)
        value = node.get(name, MISSING)
        if value is MISSING and (f.default is not MISSING or f.default_factory is not MISSING):
            default = _default(f)
            if default is not None:   # left out: its default, set by check() (None: read with .get)
                _DEFAULTED.append((key, default))
            continue
        if value is MISSING or value == "???":
            raise ConfigError(f"{key} is not set: {_rule(hints[name], f)} (e.g. {key}={_example(f)})")
        _check_value(hints[name], value, f, key, label)


def _optional(tp) -> tuple[Any, bool]:
    """(inner type, True) for Optional[inner], else (tp, False)."""
    if typing.get_origin(tp) is Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _is(tp, x) -> bool:
    """x has type tp, strictly (no conversion)."""
    if tp is Any:
        return True
    if tp is bool:
        return isinstance(x, bool)
    if tp is int:
        return isinstance(x, int) and not isinstance(x, bool)
    if tp is float:
        return _is_number(x)
    if tp is str:
        return isinstance(x, str)
    if typing.get_origin(tp) is Literal:
        return any(type(x) is type(a) and x == a for a in typing.get_args(tp))
    return False


def _desc(tp) -> str:
    if typing.get_origin(tp) is list:
        return {int: "a list of integers", float: "a list of finite numbers", str: "a list of strings"}.get(
            typing.get_args(tp)[0], "a list")
    return {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}.get(tp, "a value")


def _bounds(meta) -> str:
    parts = [f"{op} {meta[k]:g}" for k, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))
             if meta.get(k) is not None]
    return " and ".join(parts)


def _rule(tp, f) -> str:
    """What the field accepts, for the message."""
    meta = f.metadata
    if meta.get("rule"):
        return meta["rule"]
    tp, nullable = _optional(tp)
    if typing.get_origin(tp) is Literal:
        return f"choose one of {typing.get_args(tp)}"
    text = f"give {_desc(tp)}"
    b = _bounds(meta)
    if b:
        text += (" with items " if typing.get_origin(tp) is list else " ") + b
    if meta.get("unit"):
        text += f" [{meta['unit']}]"
    if meta.get("min_len"):
        text += f", at least {meta['min_len']}"
    return text + (", or null" if nullable else "")


def _example(f) -> str:
    ex = f.metadata.get("example", MISSING)
    if ex is MISSING:
        ex = f.default if f.default is not MISSING else (
            f.default_factory() if f.default_factory is not MISSING else None)
    return ex if isinstance(ex, str) else _override(ex)


def _override(v) -> str:
    """A value as a command-line override writes it."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_override(x) for x in v) + "]"
    if dataclasses.is_dataclass(v):
        return "{" + ",".join(f"{k}:{_override(x)}" for k, x in dataclasses.asdict(v).items()) + "}"
    return str(v)


def _show(v) -> str:
    """A bad value as the message quotes it (strings quoted: 'abc')."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, list):
        return "[" + ",".join(_show(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ",".join(f"{k}:{_show(x)}" for k, x in v.items()) + "}"
    return repr(v)


def _in_range(meta, x) -> bool:
    return not ((meta.get("gt") is not None and not x > meta["gt"])
                or (meta.get("ge") is not None and not x >= meta["ge"])
                or (meta.get("lt") is not None and not x < meta["lt"])
                or (meta.get("le") is not None and not x <= meta["le"]))


def _why(meta, items) -> str:
    """'not finite; ' or 'implausible magnitude; ' (above the key's upper bound) where that is the
    problem, else ''."""
    nums = [x for x in items if _is_number(x)]
    if not all(math.isfinite(x) for x in nums):
        return "not finite; "
    upper = {k: meta.get(k) for k in ("lt", "le")}
    if not meta.get("rule") and any(not _in_range(upper, x) for x in nums):   # a rule says it itself
        return "implausible magnitude; "
    return ""


def _check_value(tp, value, f, key: str, label: str) -> None:
    meta = f.metadata
    inner, nullable = _optional(tp)
    if value is None:
        if nullable or inner is Any:
            return
        raise ConfigError(f"{key}=null: {_rule(tp, f)} (e.g. {key}={_example(f)})")
    if dataclasses.is_dataclass(inner):
        _check_node(inner, value, key, label)
        return
    if typing.get_origin(inner) is Literal:
        if not _is(inner, value):
            raise ConfigError(f"{key}={_show(value)}; choose one of {typing.get_args(inner)} "
                              f"(e.g. {key}={_example(f)})")
        return
    is_list = typing.get_origin(inner) is list
    item = typing.get_args(inner)[0] if is_list else inner
    items = value if is_list and isinstance(value, list) else [value]
    if (is_list and not isinstance(value, list)) or not all(_is(item, x) for x in items):
        raise ConfigError(f"{key}={_show(value)} is not {_desc(inner)}: {_rule(tp, f)} (e.g. {key}={_example(f)})")
    bad = is_list and len(value) < meta.get("min_len", 0)
    if item is float and not all(math.isfinite(x) for x in items):
        bad = True
    if _is_number(items[0] if items else 0) and not all(_in_range(meta, x) for x in items):
        bad = True
    if bad:
        raise ConfigError(f"{key}={_show(value)}: {_why(meta, items)}{_rule(tp, f)} (e.g. {key}={_example(f)})")
    why = meta.get("check") and meta["check"](value)
    if why:
        sep = " " if why.startswith("is not") else ": "
        raise ConfigError(f"{key}={_show(value)}{sep}{why} (e.g. {key}={_example(f)})")
