"""Every paper experiment config composes and passes the runner's up-front validation for each
value it sweeps; `make reproduce` runs only experiments that exist and reports every one it runs."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from pipeline import runner
from tests.conftest import compose_config, hydra_config

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


def _compose(*overrides, hydra=False):
    return hydra_config(*overrides) if hydra else compose_config(*overrides)


def _sweep(experiment: str) -> dict[str, list[str]]:
    """The experiment's hydra.sweeper.params as {key: [values]} (simple comma lists and choice())."""
    params = _compose(f"experiment={experiment}", hydra=True).hydra.sweeper.params
    out = {}
    for k, v in (OmegaConf.to_container(params) if params else {}).items():
        v = str(v)
        m = re.fullmatch(r"choice\((.*)\)", v)
        out[k] = re.findall(r"\[[^\]]*\]", m.group(1)) if m else v.split(",")
    return out


def _makefile_experiments() -> list[str]:
    text = (ROOT / "Makefile").read_text()
    m = re.search(r"^ALL_EXPERIMENTS :=((?:.*\\\n)*.*)$", text, re.M)
    return m.group(1).replace("\\\n", " ").split()


# the sibling sweeps of b1_linear_motor, b2_rot_trans, k_two_mass and emps are slow (CI budget: `make test-full`)
SIBLING_SWEEPS = {"b1_noise_sweep", "b2_rot_trans_il", "b2_rot_trans_linear", "k_lambda_sweep", "emps_physics"}


@pytest.mark.parametrize("experiment", [pytest.param(e, marks=pytest.mark.slow) if e in SIBLING_SWEEPS else e
                                        for e in EXPERIMENTS])
def test_experiment_validates_for_every_swept_value(experiment):
    base = [f"experiment={experiment}", "hydra.mode=RUN"]
    runner.validate(_compose(*base))
    params = _compose(f"experiment={experiment}", hydra=True).hydra.sweeper.params or {}
    for key, values in _sweep(experiment).items():
        for v in values:  # each swept value on its own (the full product is the sweep itself)
            cfg = _compose(*base, f"{key}={v.strip()}")
            runner.validate(cfg)
            # the experiment's run-name template shows every key it sweeps: no suffix is added, and
            # the reported run names (report providers, results/) stay what they were; a group the
            # template does not show (b1_linear_motor's regularizer) is named only off its headline
            # (first) value, so the headline runs keep their names
            ov = [f"experiment={experiment}", f"{key}={v.strip()}", "hydra/launcher=local"]
            template = str(cfg._get_node("run_name")._value())
            shown = "${" + key + "}" in template or "${" + key + "." in template or "." in key
            side = not shown and v.strip() != values[0].strip()
            assert runner.run_name_with_overrides(cfg, ov, params) == \
                str(cfg.run_name) + (f"-{key}={v.strip()}" if side else ""), (key, v)


@pytest.mark.parametrize("experiment", sorted(SIBLING_SWEEPS & set(EXPERIMENTS)))
def test_a_sibling_sweep_validates_at_its_own_values(experiment):
    """What the default run checks of a sibling sweep (its every swept value: the slow test above): the
    experiment's own config passes the schema and the runner's up-front validation."""
    runner.validate(_compose(f"experiment={experiment}", "hydra.mode=RUN"))


def test_noise_sweep_is_the_linear_motor_setup_over_sigma():
    sweep = _sweep("b1_noise_sweep")
    assert [float(s) for s in sweep["system.noise.std"]] == [0.0, 1e-8, 1e-7, 1e-6]
    assert sweep["system.noise.structure"] == ["equation", "output"]
    assert set(sweep["invert"]) == {"newton", "physics", "direct", "analytic"}
    a, b = (OmegaConf.to_container(_compose(f"experiment={e}", "hydra.mode=RUN"), resolve=True)
            for e in ("b1_noise_sweep", "b1_linear_motor"))
    assert a["experiment_name"] == "b1_noise_sweep"
    assert a["identify"]["n_restarts"] < b["identify"]["n_restarts"]
    # apart from the restarts and the names, the set-up is the headline's
    for c in (a, b):
        for k in ("experiment_name", "run_name", "description"):
            c.pop(k)
        c["identify"].pop("n_restarts")
    assert a == b


def test_reproduce_runs_existing_experiments_and_reports_each_of_them():
    make = _makefile_experiments()
    assert make and set(make) <= set(EXPERIMENTS), sorted(set(make) - set(EXPERIMENTS))
    reported = set(_compose().report.experiments)
    names = {e: str(_compose(f"experiment={e}", "hydra.mode=RUN").experiment_name) for e in make}
    unreported = {e: n for e, n in names.items() if n not in reported}
    assert not unreported, f"run by make reproduce but missing from report.experiments: {unreported}"
