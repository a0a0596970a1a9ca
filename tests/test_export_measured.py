"""Export of a measured system's physics feedforward (issue 20): the inverse rigid-body force with
its force terms minus the known controller's force on the reference, u_ff = physics.feedforward(θ, r)
- ctrl.reference_force(r) (the invert stage's u_ff), in Python and as generated C."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from pipeline.export.law import Law, feedforward, from_measured_physics
from pipeline.export.package import write_package
from pipeline.systems.measured import Recording

RTOL = 1e-9
Ts = 1e-3
needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on this machine")

PID = {"kind": "lti", "num": [4.279e6, -8.212e6, 3.939e6], "den": [1.0, -1.4361, 0.4361]}
EMPS = {"kind": "cascade", "kp": 160.18, "kv": 243.45, "gtau": 35.150652, "v_sat": 10.0}
COGGING = {"terms": ["viscous", "coulomb", "cogging"], "coulomb_width": 0.002, "cogging_period": 0.03}


def _reference(n=1500, amp=0.08):
    t = np.arange(n) * Ts
    r = amp * (1 - np.cos(2 * np.pi * t / (n * Ts))) / 2 + 0.2 * amp * np.sin(2 * np.pi * 3 * t / (n * Ts))
    r[-100:] = r[-100] + np.linspace(0, 2e-3, 100)     # ends moving: w(N) on the held reference matters
    return r


def _system(controller, terms, averaged):
    return Recording("axis", Ts, controller=controller, force_terms=terms,
                     physics_input="averaged" if averaged else "direct")


def _theta(physics):
    physical = {"M": 12.0, "F_v": 40.0, "F_c": 8.0, "OF": -1.5, "C_cos1": 2.2, "C_sin1": -1.2}
    return physics.theta_from_physical(physical)


@pytest.mark.parametrize("averaged", [True, False])
@pytest.mark.parametrize("controller,terms", [(PID, COGGING), (EMPS, COGGING), (EMPS, None)],
                         ids=["pid-cogging", "cascade-cogging", "cascade-emps"])
def test_measured_physics_law_equals_the_invert_stage(controller, terms, averaged, tmp_path):
    sys_ = _system(controller, terms, averaged)
    theta = _theta(sys_.physics)
    r = _reference()
    u = sys_.physics.feedforward(theta, r) - sys_.ctrl.reference_force(r)   # stages/invert
    assert np.max(np.abs(u)) > 0
    law = from_measured_physics(sys_.physics, theta, sys_.ctrl)
    assert law.law == "physics" and law.rest == "zero" and law.preview == 1 + int(averaged)
    assert law.ints["has_ctrl"] == int(controller is EMPS)      # error feedback: no extra term
    np.testing.assert_array_equal(feedforward(law, r), u)      # the study's own classes
    law.save(tmp_path / "law")
    np.testing.assert_array_equal(feedforward(Law.load(tmp_path / "law"), r), u)
    if shutil.which("cc") is None:
        pytest.skip("no C compiler on this machine")
    man = write_package(law, "ff_physics", tmp_path / "pkg", {"ref": (r, u)}, source={"run_id": "test"},
                        rtol=RTOL, timing_repeats=0)
    assert man["compiled"] and man["c_max_rel_diff"] <= RTOL and man["python_max_rel_diff"] <= RTOL, man
    assert man["family"] == "rigid_body" and man["preview"] == 1 + int(averaged)


def test_other_laws_on_a_measured_system_are_refused_naming_the_shipped_ones():
    from pipeline.errors import ConfigError
    from stages.export import validate

    from omegaconf import OmegaConf
    sys_ = _system(PID, COGGING, True)
    cfg = OmegaConf.create({"invert": {"kind": "rational_filter"}, "model": {}, "export": {}})
    with pytest.raises(ConfigError, match=r"ships invert.kind in \['physics', 'direct', 'analytic', 'newton'\] .* "
                                          r"invert.kind=rational_filter is not exported"):
        validate(cfg, sys_)
    validate(OmegaConf.create({"invert": {"kind": "physics"}, "model": {}, "export": {}}), sys_)     # accepted
    for kind in ("direct", "analytic", "newton"):      # the PGNN's inversions (issue 49)
        validate(OmegaConf.create({"invert": {"kind": kind}, "model": {"hidden": [16], "activation": "tanh"},
                                   "export": {}}), sys_)
