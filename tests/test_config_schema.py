"""The config schema (pipeline.schema): a bad value of any key fails before any work (no MLflow run,
no cache entry) with one line naming the key, the value, what is allowed and an example; every
group option of conf/ still passes (every experiment: tests/test_experiments.py); every option
declares its parameter class next to its code (found by its kind, as the runner finds the stage)
and it agrees with the libraries' own lists of choices."""
from __future__ import annotations

import os
import subprocess
import sys
import typing
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline import runner, schema
from tests.conftest import CONF, ROOT, SHORT_TWO_MASS, compose_config, composed_prefix, hydra_compose

TWO_MASS = ["experiment=physics_two_mass",
            "data.references=[{name:short,kind:out_and_back,distance:0.02,v_max:0.05,a_max:5,j_max:200}]",
            "stages=[generate]"]
PGNN = ["experiment=physics_linear_motor", "model=pgnn", "identify=narx", "invert=newton"]

#: (overrides, the message must contain these)
PROBES = [
    pytest.param([*TWO_MASS, "evaluate.noise=maybe"],
                 ["evaluate.noise='maybe' is not true or false", "e.g. evaluate.noise=false"], id="noise-maybe"),
    pytest.param([*TWO_MASS, "evaluate.noise=1"], ["evaluate.noise=1 is not true or false"], id="noise-1"),
    pytest.param([*TWO_MASS, "seed=1.5"], ["seed=1.5 is not an integer", ">= 0", "e.g. seed=0"], id="seed-1.5"),
    pytest.param([*TWO_MASS, "seed=-1"], ["seed=-1: give an integer >= 0", "e.g. seed=0"], id="seed-negative"),
    pytest.param([*TWO_MASS, "seed=abc"], ["seed='abc' is not an integer"], id="seed-abc"),
    pytest.param([*TWO_MASS[:2], "stages=[]"], ["stages=[]", "non-empty list of stages", "generate"],
                 id="stages-empty"),
    pytest.param([*TWO_MASS[:2], "stages=[generate,fly]"], ["unknown stage(s) ['fly']"], id="stages-unknown"),
    pytest.param([*PGNN, "model.hidden=[-3]"],
                 ["model.hidden=[-3]: widths must be positive integers (e.g. model.hidden=[16])"],
                 id="hidden-negative"),
    pytest.param([*PGNN, "model.hidden=abc"], ["model.hidden='abc' is not a list of integers"], id="hidden-abc"),
    pytest.param([*PGNN, "identify.max_iter=abc"], ["identify.max_iter='abc' is not an integer"],
                 id="max_iter-abc"),
    pytest.param([*PGNN, "identify.patience=0"], ["identify.patience=0", ">= 1"], id="patience-0"),
    pytest.param([*PGNN, "identify.stat_window=-1"], ["identify.stat_window=-1", ">= 0"], id="stat-window-negative"),
    pytest.param([*PGNN, "identify.geodesic=yes"], ["identify.geodesic"], id="geodesic-yes"),
    pytest.param([*PGNN, "model.use_physics=false", "model.hidden=abc"],
                 ["model.hidden='abc' is not a list of integers"], id="black-box-hidden-abc"),
    pytest.param([*PGNN, "invert.k=1.5"], ["invert.k=1.5 is not an integer"], id="newton-k"),
    pytest.param([*PGNN, "identify.val_fraction=-0.1"], ["identify.val_fraction=-0.1", ">= 0 and < 1"],
                 id="val_fraction"),
    pytest.param(["experiment=physics_arx", "data.u_std=nan"], ["data.u_std=nan: not finite"], id="u_std-nan"),
    pytest.param(["experiment=physics_arx", "data.u_std=inf"], ["data.u_std=inf: not finite"], id="u_std-inf"),
    pytest.param(["experiment=physics_arx", "data.n_samples=5"], ["data.n_samples=5", ">= 10"], id="n_samples"),
    pytest.param([*TWO_MASS, "system.noise.std=inf"], ["system.noise.std=inf: not finite", "< 1 [m]"],
                 id="two_mass-noise-inf"),
    pytest.param([*TWO_MASS, "system.noise.std=1e300"],
                 ["system.noise.std=1e+300: implausible magnitude", ">= 0 and < 1 [m]"], id="two_mass-noise-1e300"),
    pytest.param([*PGNN, "system.noise.std=1e300"], ["system.noise.std=1e+300: implausible magnitude"],
                 id="motor-noise-1e300"),
    pytest.param(["experiment=physics_rot_trans", "system.noise.std=nan"], ["system.noise.std=nan"],
                 id="rot_trans-noise-nan"),
    pytest.param(["experiment=physics_arx", "system.noise.std=-1"], ["system.noise.std=-1"], id="arx-noise"),
    pytest.param([*TWO_MASS, "system.m1=1e300"], ["system.m1=1e+300: implausible magnitude", "[kg]"], id="mass"),
    pytest.param([*TWO_MASS, "system.Ts=0"], ["system.Ts=0", "> 0"], id="Ts"),
    pytest.param(["experiment=physics_rot_trans", "data=ilc", "data.ilc.gain=3"],
                 ["data.ilc.gain=3: the learning gain must be in (0, 2)"], id="ilc-gain"),
    pytest.param([*TWO_MASS, "export.rtol=2"], ["export.rtol=2"], id="export-rtol"),
    pytest.param([*TWO_MASS, "+system.foo=1"], ["system.foo: unknown key", "allowed keys: _target_, name, m1"],
                 id="unknown-key"),
    pytest.param([*TWO_MASS, "invert.kind=teleport"], ["no 'invert' implementation for kind 'teleport'"],
                 id="unknown-kind"),
    pytest.param([*TWO_MASS, "experiment_name=../../evil"], ["experiment_name='../../evil' is not a name"],
                 id="experiment-name"),
    pytest.param(["experiment=b2_rot_trans", "hydra.mode=RUN", "identify.theta_star=ls"],
                 ["identify.theta_star='ls'; choose one of ('arx', 'sim_error', 'oracle')"], id="theta_star"),
    pytest.param([*TWO_MASS, "system.alpha=${oops}"], ["config does not resolve"], id="interpolation"),
    pytest.param([*TWO_MASS[:1], "data.references=[{name:a,kind:b2_R},{name:a,kind:b2_R,repeats:2}]",
                  "stages=[generate]"], ["reference name(s) ['a'] given more than once"], id="reference-twice"),
    pytest.param([*TWO_MASS, "paths.cache=/"], ["paths.cache=/ is the file system's root"], id="cache-root"),
    pytest.param([*TWO_MASS, f"paths.cache={ROOT}/pipeline/c"], ["inside the source tree"], id="cache-in-source"),
    pytest.param([*TWO_MASS[:1], "data.references=[{name:'x/../y',kind:b2_R}]", "stages=[generate]"],
                 ["reference name(s) ['x/../y'] are not names"], id="reference-path"),
    # issue 24 item 9: values that failed late or gave garbage
    pytest.param(["experiment=emps_physics", "system.idim.order=20"],
                 ["idim.order=20", "inaccurate in (b, a) form", "lower idim.order"], id="idim-order-20"),
    pytest.param(["experiment=emps_physics", "system.idim.order=8", "system.idim.cutoff_hz=5"],
                 ["idim.order=8 with idim.cutoff_hz=5"], id="idim-order-8-at-5Hz"),
    pytest.param(["experiment=emps_physics", "system.idim.cutoff_hz=500"], ["idim.cutoff_hz=500", "Nyquist"],
                 id="idim-cutoff-nyquist"),
    pytest.param(["experiment=physics_arx", "data.n_samples=1000000000"], ["data.n_samples=1000000000", "10^7"],
                 id="n_samples-1e9"),
    pytest.param([*TWO_MASS[:1], "data.references=[{name:a,kind:move,distance:true,v_max:0.05,a_max:5,j_max:200}]",
                  "stages=[generate]"], ["must be a number, got True"], id="distance-true"),
    pytest.param([*TWO_MASS[:1], "data.references=[{name:a,kind:sequence,steps:[{rest:1e9}]}]", "stages=[generate]"],
                 ["more than 1e+07", "shorten it"], id="reference-1e12-samples"),
    pytest.param([*TWO_MASS[:1], "data.references=[{name:a,kind:b2_R,repeats:100000}]", "stages=[generate]"],
                 ["repeated 100000 times", "more than 1e+07"], id="reference-repeats"),
    pytest.param(["experiment=physics_linear_motor", "data.references=[{name:tr,kind:b1_training,duration:1e9}]",
                  "stages=[generate]"], ["oscillating reference has 1e+12 samples"], id="training-duration-1e9"),
    pytest.param(["experiment=b1_linear_motor", "hydra.mode=RUN", "stages=[generate,baseline,train,invert,export]",
                  "evaluate.references=[{name:v0.15,kind:b1_evaluation,v_max:0.15},"
                  "{name:v0_15,kind:b1_evaluation,v_max:0.1}]"],
                 ["references 'v0.15' and 'v0_15' give the same file name r_v0_15.csv"], id="export-file-clash"),
    pytest.param([*TWO_MASS, f"paths.cache={ROOT}"], ["inside the source tree"], id="cache-at-repo-top"),
    # issue 22: the export's guard, rate, prefix and precision
    pytest.param([*TWO_MASS, "export.limits.fallback=teleport"],
                 ["export.limits.fallback='teleport'; choose one of ('hold', 'physics', 'ramp')"],
                 id="export-fallback"),
    pytest.param([*TWO_MASS, "export.limits.rate=0"], ["export.limits.rate=0", "> 0", "[N/s]"], id="export-rate-0"),
    pytest.param([*TWO_MASS, "export.limits.u_max=inf"], ["export.limits.u_max=inf: not finite"],
                 id="export-u_max-inf"),
    pytest.param([*TWO_MASS, "export.precision=half"], ["export.precision='half'; choose one of ('double', 'single')"],
                 id="export-precision"),
    pytest.param([*TWO_MASS, "export.prefix=9axis"], ["export.prefix='9axis' is not a C identifier prefix"],
                 id="export-prefix-digit"),
    pytest.param([*TWO_MASS, "export.prefix='a-b'"], ["export.prefix='a-b' is not a C identifier prefix"],
                 id="export-prefix-dash"),
    pytest.param([*TWO_MASS, "+export.limits.max_force=3"], ["export.limits.max_force: unknown key"],
                 id="export-limits-unknown"),
    pytest.param(["experiment=b1_linear_motor", "hydra.mode=RUN", "stages=[generate,baseline,train,invert,export]",
                  "export.target_rate=1500"],
                 ["export.target_rate=1500: the law runs at 1000 Hz", "integer multiple", "export.target_rate=2000"],
                 id="export-target-rate"),
    pytest.param(["experiment=b1_linear_motor", "hydra.mode=RUN", "stages=[generate,baseline,train,invert,export]",
                  "export.limits.u_min=5", "export.limits.u_max=1"],
                 ["export.limits.u_min=5 is not below export.limits.u_max=1"], id="export-u-min-above-max"),
    pytest.param(["experiment=k_two_mass", "hydra.mode=RUN", "export.limits.fallback=physics"],
                 ["export.limits.fallback=physics needs a rigid-body physics law", "use export.limits.fallback=hold"],
                 id="export-physics-fallback-two-mass"),

    pytest.param(["experiment=emps_physics", "system.idim.decimation=10000"],
                 ["fewer than the 200100 the filtered least squares needs", "lower system.idim.trim or "
                  "system.idim.decimation"], id="idim-decimation-too-large"),
]


def _nothing_written(store: Path, fresh: bool = False) -> None:
    """No cache entry and no MLflow run; ``fresh`` (a folder without the fixture's empty store): the store is
    not even created."""
    cache = store / "cache"
    assert not cache.exists() or not any(p for p in cache.glob("*/*") if p.parent.name != ".locks"), \
        sorted(cache.glob("*/*"))
    db = store / "mlflow.db"
    assert not (fresh and db.exists()), "a bad config created the MLflow store"
    if db.exists():
        import mlflow
        mlflow.set_tracking_uri(f"sqlite:///{db}")
        assert mlflow.search_runs(search_all_experiments=True).empty


@pytest.mark.parametrize("overrides, expected", PROBES)
def test_bad_value_fails_before_any_work_with_one_line(store, cfg_of, overrides, expected):
    with pytest.raises(runner.ConfigError) as err:
        runner.run_job(cfg_of(*overrides))
    msg = str(err.value)
    assert "\n" not in msg
    for part in expected:
        assert part in msg, msg
    _nothing_written(store)


def _measured(tmp_path, frame: pd.DataFrame, name: str) -> list[str]:
    path = tmp_path / name
    frame.to_parquet(path) if name.endswith(".parquet") else frame.to_csv(path, index=False)
    return ["experiment=physics_two_mass", "data=measured", f"data.path={tmp_path}", f"data.file={name}",
            "stages=[generate]"]


def _record(n: int = 50) -> pd.DataFrame:
    return pd.DataFrame({"t": np.arange(n) * 1e-3, "r": np.zeros(n), "u": np.zeros(n), "y": np.zeros(n)})


def test_measured_format_is_one_the_loader_reads(store, cfg_of, tmp_path):
    from stages.generate.measured import FORMATS
    with pytest.raises(runner.ConfigError, match=r"data\.format='bogus'; choose one of \('table', 'emps'\)"):
        runner.run_job(cfg_of(*_measured(tmp_path, _record(), "rec.csv"), "data.format=bogus"))
    with pytest.raises(runner.ConfigError, match=r"^data\.path is not set"):
        runner.run_job(cfg_of("experiment=physics_two_mass", "data=measured", "stages=[generate]"))
    _nothing_written(store)
    from stages.generate.measured import Params
    assert typing.get_args(typing.get_type_hints(Params)["format"]) == FORMATS


@pytest.mark.parametrize("name", ["rec.parquet", "rec.csv"])
def test_text_column_in_a_measured_file_is_named(store, cfg_of, tmp_path, name):
    df = _record()
    df["u"] = df["u"].astype(object)
    df.loc[4, "u"] = "3 N"
    if name.endswith(".parquet"):
        df["u"] = df["u"].astype(str)
    with pytest.raises(runner.ConfigError) as err:
        runner.run_job(cfg_of(*_measured(tmp_path, df, name)))
    msg = str(err.value)
    assert "\n" not in msg and f"{name}: column 'u' is not numeric" in msg and "'3 N' at row 4" in msg, msg
    _nothing_written(store)


@pytest.mark.parametrize("override, expected", [
    ("evaluate.noise=maybe", "error: evaluate.noise='maybe' is not true or false"),
    # the CLI path once in the default run (~5-10 s a process); this message is checked in-process above
    pytest.param("system.noise.std=1e300", "error: system.noise.std=1e+300: implausible magnitude",
                 marks=pytest.mark.slow),
])
def test_cli_prints_one_error_line_and_exits_2(tmp_path, override, expected):
    env = {**os.environ, "PIPELINE_CACHE": str(tmp_path / "cache"),
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
           "PIPELINE_CACHE_KEY_FILE": str(tmp_path / "cache.key")}
    out = subprocess.run([sys.executable, "-m", "pipeline", *TWO_MASS, override,
                          f"hydra.run.dir={tmp_path / 'hydra'}"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert out.returncode == 2, out.stderr
    assert len(lines) == 1 and lines[0].startswith(expected), out.stderr
    _nothing_written(tmp_path, fresh=True)


@pytest.mark.parametrize("overrides, applied", [
    (SHORT_TWO_MASS, 2),
    (["experiment=physics_linear_motor", "model=pgnn", "system.noise.std=nan", "model.hidden=[-3]"], 2),
    (["system=measured", "system.controller.num=[1.0]", "system.actuator.lag_tau=0.0004"], 2),
    ([*TWO_MASS, "system.m_typo=3"], 3),                          # Hydra's error for an unknown key
    (["experiment=physics_two_mass", "system.m1=2", "model=pgnn", "seed=3"], 1),   # a group after a key
])
def test_the_tests_compose_as_hydra_does(overrides, applied):
    """The suite's shortcut (tests/conftest.py ``compose_config``: the leading overrides composed once, the
    trailing plain ones applied by Hydra's own function) gives the config, or the error, Hydra's compose
    gives."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf
    assert len(overrides) - composed_prefix(OverridesParser.create().parse_overrides(overrides)) == applied

    def outcome(compose):
        try:
            cfg = compose(*overrides)
        except Exception as exc:  # noqa: BLE001 - the error itself is compared
            return type(exc), str(exc)
        return OmegaConf.to_yaml(cfg), OmegaConf.is_struct(cfg)    # YAML: a NaN compares equal
    assert outcome(compose_config) == outcome(hydra_compose)


GROUPS = {g: [f"{g}={p.stem}" for p in sorted((CONF / g).glob("*.yaml"))]
          for g in ("system", "data", "model", "identify", "regularizer", "invert", "evaluate")}
#: every group option once, one of each group per compose (a compose costs ~0.3 s; the check reads each
#: section against its own option's class)
OPTIONS = [[opts[i] for opts in GROUPS.values() if i < len(opts)] for i in range(max(map(len, GROUPS.values())))]
#: the mandatory values (???) of the templates
NEEDS = {"system=measured": ["system.controller.num=[4.279e6,-8.212e6,3.939e6]",
                             "system.controller.den=[1.0,-1.4361,0.4361]"],
         "data=measured": ["data.path=/nowhere"]}


@pytest.mark.parametrize("options", OPTIONS, ids=["+".join(o.split("=")[1] for o in opts) for opts in OPTIONS])
def test_every_group_option_passes(cfg_of, options):
    schema.check(cfg_of(*options, *(v for o in options for v in NEEDS.get(o, []))))


def test_every_option_declares_its_parameter_class_next_to_its_code():
    """Issue 21 item 1: each stage implementation (stages/<stage>/<kind>.py) and each plant module
    (pipeline/systems/<plant>.py with a System) declares its ``Params`` dataclass; the schema finds it
    by the option's kind (no registry), and every option file of conf/ resolves to one."""
    import dataclasses
    import importlib

    from pipeline.systems.base import System
    for group, stage in schema.STAGE.items():
        kinds = {p.stem for p in (ROOT / "stages" / stage).glob("*.py") if not p.stem.startswith("_")}
        assert kinds and set(schema.options(group)) == kinds
        for kind in kinds:
            cls = importlib.import_module(f"stages.{stage}.{kind}").Params
            assert dataclasses.is_dataclass(cls)
            assert typing.get_args(typing.get_type_hints(cls)["kind"]) in ((kind,), ()), (stage, kind)
    plants = []
    for p in sorted((ROOT / "pipeline" / "systems").glob("*.py")):
        mod = importlib.import_module(f"pipeline.systems.{p.stem}")
        if any(isinstance(o, type) and issubclass(o, System) and o is not System and o.__module__ == mod.__name__
               for o in vars(mod).values()):
            assert dataclasses.is_dataclass(getattr(mod, "Params", None)), p.name
            plants.append(p.stem)
    assert {t.split(".")[2] for t in schema.options("system")} == set(plants)
    assert set(schema.options("model")) == {"physics", "pgnn", "rational", "pgnn_shared_ar"}
    assert set(schema.options("regularizer")) == {"none", "physics_l2", "orthogonal"}
    for group in schema.CHOOSER:
        for p in sorted((CONF / group).glob("*.yaml")):
            schema.option_class(group, schema._selector(p.parent, p.stem))


def test_the_parameter_classes_agree_with_the_libraries_choices():
    from pipeline.identify.measured_loop import CONVENTIONS
    from pipeline.models import pgnn
    from pipeline.models.pgnn import _ACTIVATIONS, _STRUCTURES
    from stages.train import sim_error
    from stages.train.sim_error import THETA_STAR

    def choices(cls, key):
        return typing.get_args(typing.get_type_hints(cls)[key])
    assert choices(schema.Evaluate, "convention") == CONVENTIONS
    assert choices(pgnn.Params, "structure") == _STRUCTURES
    assert set(choices(pgnn.Params, "activation")) == set(_ACTIVATIONS)
    assert choices(sim_error.Params, "theta_star") == THETA_STAR


def test_an_unknown_option_names_the_choices_and_where_a_class_goes(cfg_of):
    cfg = cfg_of(*TWO_MASS)
    cfg.system._target_ = "pipeline.systems.nowhere.Plant"
    with pytest.raises(runner.ConfigError) as err:
        schema.check(cfg)
    msg = str(err.value)
    assert "pipeline.systems.linear_motor.LinearMotor" in msg and "`Params` dataclass" in msg, msg


def test_the_schema_sets_every_key_left_out_to_its_default(cfg_of):
    """Issue 21 item 1 (part): schema.check fills the keys a config leaves out with the schema's
    defaults (what stages then read), and leaves set keys alone."""
    from omegaconf import open_dict

    from pipeline import schema
    cfg = cfg_of(*TWO_MASS)
    with open_dict(cfg):
        cfg.evaluate.pop("validation_tail", None)
        cfg.evaluate.convention = "published"
        cfg.report.pop("update", None)
    filled = schema.check(cfg)
    assert "evaluate.validation_tail" in filled and "report.update" in filled
    assert "evaluate.convention" not in filled
    assert cfg.evaluate.validation_tail == 0.2 and cfg.report["update"] is False
    assert cfg.evaluate.convention == "published"
    assert schema.check(cfg) == []                      # nothing left out the second time


def test_registered_defaults_are_kept_by_content_hash(tmp_path, monkeypatch):
    """schema.register's defaults of every option are computed once per content of pipeline/, stages/ and
    conf/ (importing every option module costs seconds of start-up), read back equal, and recomputed
    when a config file changes."""
    import json
    import shutil
    from pipeline import schema
    monkeypatch.setattr(schema, "DEFAULTS_CACHE", tmp_path / "cache")
    conf = ROOT / "conf"
    first = schema._cached_defaults(conf)
    assert first == json.loads(json.dumps(schema._all_defaults(conf)))
    assert first["_params/identify/narx"]["patience"] >= 1 and "_params_config" in first
    assert len(list((tmp_path / "cache").glob("params-defaults-*.json"))) == 1

    def no_import(_conf):
        raise AssertionError("recomputed")
    monkeypatch.setattr(schema, "_all_defaults", no_import)
    assert schema._cached_defaults(conf) == first            # read back, no module imported
    other = tmp_path / "conf"
    shutil.copytree(conf, other)
    (other / "identify" / "narx.yaml").write_text((other / "identify" / "narx.yaml").read_text() + "\n# edited\n")
    with pytest.raises(AssertionError, match="recomputed"):
        schema._cached_defaults(other)
