"""Third-order reference generator (SPEC §1) and the papers' named references."""
import math

import numpy as np
import pytest
from scipy.integrate import cumulative_trapezoid

from pipeline import references as R

TOL = 1e-9   # SPEC §1: bounds are never exceeded (beyond rounding)

# (distance, v_max, a_max, j_max): every regime (cruise / no cruise, a_max reached / not)
MOVES = [(d, v, 5.0, 200.0) for d, v in R.K_TRAINING_MOVES + R.K_HELDOUT_MOVES] + [
    (0.1, 0.1, 4.0, 40.0),        # [B2] R: jerk-limited to 2 m/s²
    (0.2, 0.05, 4.0, 1000.0),     # [B1] training stroke
    (0.2, 0.2, 4.0, 1000.0),
    (1e-4, 1.0, 4.0, 1000.0),     # tiny move: neither v_max nor a_max
    (0.05, 1.0, 2.0, 1000.0),     # long accel plateau, no cruise
    (-0.07, 0.1, 3.0, 100.0),     # negative direction
]


def _reachable(D, v, a, j):
    """Closed-form reachability of v_max and a_max, derived independently of move_times:
    the shortest move that reaches v_max has length v (v/a + a/j) if v j >= a², else
    2 v^{3/2}/sqrt(j); a move reaches a_max iff its peak velocity allows a full jerk ramp
    (v_peak >= a²/j)."""
    D = abs(D)
    d_v = v * (v / a + a / j) if v * j >= a * a else 2.0 * v ** 1.5 / math.sqrt(j)
    v_reach = D >= d_v * (1 - 1e-12)
    if v_reach:
        a_reach = v * j >= a * a * (1 - 1e-12)
    else:
        a_reach = D >= 2.0 * a ** 3 / j ** 2 * (1 - 1e-12)
    return v_reach, a_reach


@pytest.mark.parametrize("D,v,a,j", MOVES)
def test_move_bounds_final_position_and_reached_bounds(D, v, a, j):
    Ts = 1e-3
    ref = R.move(D, v, a, j, Ts)
    mt = R.move_times(D, v, a, j)
    assert ref.r[-1] == D                                   # lands exactly on the target
    assert np.all(np.abs(ref.v) <= v + TOL)
    assert np.all(np.abs(ref.a) <= a + TOL)
    assert np.all(np.abs(ref.j) <= j + TOL)
    assert ref.v[-1] == 0.0 and ref.a[-1] == 0.0
    # monotone (no overshoot of the target)
    assert np.all(np.sign(D) * np.diff(ref.r) >= -1e-15)
    v_reach, a_reach = _reachable(D, v, a, j)
    assert mt.velocity_limited == v_reach
    assert mt.acceleration_limited == a_reach
    if v_reach:
        assert mt.v_peak == pytest.approx(v, rel=1e-12)
    else:
        assert mt.v_peak < v
    if a_reach:
        assert mt.a_peak == pytest.approx(a, rel=1e-12)
    else:
        assert mt.a_peak < a
    # the sampled profile attains the peaks up to the sampling of a smooth maximum
    assert mt.v_peak - np.abs(ref.v).max() <= 0.5 * j * Ts ** 2 + 1e-12
    assert mt.a_peak - np.abs(ref.a).max() <= j * Ts + 1e-12
    # the distance follows from the peaks: D = v_peak (T - t_j·2 - t_a) for a symmetric profile
    assert abs(D) == pytest.approx(mt.v_peak * (mt.duration - 2 * mt.t_j - mt.t_a), rel=1e-12)


@pytest.mark.parametrize("D,v,a,j", [(0.1, 0.2, 5.0, 200.0), (0.02, 0.02, 5.0, 200.0),
                                     (0.1, 0.1, 4.0, 40.0), (-0.05, 1.0, 2.0, 1000.0)])
def test_derivatives_are_consistent_integrals(D, v, a, j):
    """r, v, a, j are mutually consistent: integrate the sampled jerk/acc/vel on a fine grid
    and compare.  Trapezoid errors: a jerk step between samples costs ≤ j Ts in a; each of
    the ≤ 8 kinks of a costs ≤ 2j Ts²/8 in v; v is C¹ with |v''| ≤ j, so r is off by at
    most a_max Ts²/12 plus O(j Ts³) per kink."""
    Ts = 1e-5
    ref = R.move(D, v, a, j, Ts)
    a_int = cumulative_trapezoid(ref.j, ref.t, initial=0.0)
    v_int = cumulative_trapezoid(ref.a, ref.t, initial=0.0)
    r_int = cumulative_trapezoid(ref.v, ref.t, initial=0.0)
    assert np.max(np.abs(a_int - ref.a)) <= j * Ts * 1.01      # jerk steps: one-sample error
    assert np.max(np.abs(v_int - ref.v)) <= 2.0 * j * Ts ** 2
    assert np.max(np.abs(r_int - ref.r)) <= a * Ts ** 2


def test_k_out_and_back_structure():
    Ts = 1e-3
    for d, v in R.K_TRAINING_MOVES + R.K_HELDOUT_MOVES:
        ref = R.out_and_back(d, v, 5.0, 200.0, Ts)
        T = R.move_times(d, v, 5.0, 200.0).duration
        assert len(ref) == math.ceil((0.1 + T + 0.1 + T + 0.5) / Ts - 1e-9)
        t = ref.t
        assert np.all(ref.r[t < 0.1 - 1e-12] == 0.0)
        dwell = (t >= 0.1 + T + 1e-12) & (t < 0.1 + T + 0.1 - 1e-12)
        assert dwell.any() and np.all(ref.r[dwell] == d)
        assert np.all(ref.r[t >= 0.1 + 2 * T + 0.1 + 1e-12] == 0.0)
        assert ref.r.max() == d and ref.r[-1] == 0.0
        assert np.all(np.abs(ref.v) <= v + TOL) and np.all(np.abs(ref.a) <= 5.0 + TOL)


def test_b2_reference_R():
    ref = R.b2_reference()
    assert len(ref) == 300 and ref.Ts == 0.01
    assert ref.t[-1] == pytest.approx(2.99)
    assert np.all(ref.r[ref.t < 0.5 - 1e-12] == 0.0)
    moving = ref.t[np.abs(ref.v) > 0]
    assert moving.min() == pytest.approx(0.51) and moving.max() == pytest.approx(2.89)
    plateau = (ref.t > 1.6 + 1e-9) & (ref.t < 1.8 - 1e-9)
    assert np.all(ref.r[plateau] == 0.1)
    assert np.abs(ref.v).max() == pytest.approx(0.1, abs=TOL)
    assert np.abs(ref.a).max() == pytest.approx(2.0, abs=TOL)      # jerk-limited below 4
    assert np.abs(ref.j).max() == pytest.approx(40.0, abs=TOL)
    assert ref.r[-1] == 0.0 and np.all(ref.r[ref.t > 2.9 + 1e-9] == 0.0)
    Rd = R.b2_training_reference()
    assert len(Rd) == 4500 and np.array_equal(Rd.r[3000:3300], ref.r)
    assert np.all(np.diff(Rd.t) == pytest.approx(0.01))


def test_b1_references():
    ref = R.b1_training_reference()
    assert len(ref) == 120_000
    assert ref.r.max() == 0.1 and ref.r.min() == -0.1 and ref.r[-1] == 0.0
    assert np.abs(ref.v).max() == pytest.approx(0.05, abs=TOL)
    assert np.abs(ref.a).max() == pytest.approx(4.0, abs=TOL)
    assert np.all(np.abs(ref.j) <= 1000.0 + TOL)
    # oscillates: many strokes between the two ends
    n_strokes = np.count_nonzero(np.diff(np.sign(ref.v[ref.v != 0])) != 0)
    assert n_strokes >= 20
    for vmax in R.B1_EVAL_VMAX:
        ev = R.b1_evaluation_reference(vmax)
        assert ev.r.max() == 0.1 and ev.r.min() == -0.1 and ev.r[-1] == 0.0
        assert np.abs(ev.v).max() == pytest.approx(vmax, abs=TOL)


def test_repeat_requires_closed_reference():
    with pytest.raises(ValueError, match="repeated"):
        R.move(0.1, 0.1, 1.0, 10.0, 1e-3).repeat(2)


@pytest.mark.parametrize("bad", [dict(v_max=0.0), dict(a_max=-1.0), dict(j_max=float("nan")),
                                 dict(v_max="fast")])
def test_invalid_bounds_raise(bad):
    kw = dict(distance=0.1, v_max=0.1, a_max=1.0, j_max=10.0, Ts=1e-3)
    kw.update(bad)
    with pytest.raises(ValueError, match=list(bad)[0]):
        R.move(**kw)


def test_invalid_sequence_inputs():
    with pytest.raises(ValueError, match="Ts"):
        R.move(0.1, 0.1, 1.0, 10.0, Ts=0.0)
    with pytest.raises(ValueError, match="duration"):
        R.sequence([R.Rest(-1.0)], 1e-3)
    with pytest.raises(ValueError, match="n_samples"):
        R.sequence([R.MoveTo(0.1, 0.1, 1.0, 10.0)], 1e-3, n_samples=10)
    with pytest.raises(TypeError, match="Rest"):
        R.sequence([0.5], 1e-3)


def test_from_spec():
    r = R.from_spec({"name": "x", "kind": "b2_R", "repeats": 2}, 0.01)
    assert r.shape == (600,)
    r = R.from_spec({"kind": "out_and_back", "distance": 0.05, "v_max": 0.05, "a_max": 5,
                     "j_max": 200}, 1e-3)
    assert np.array_equal(r, R.out_and_back(0.05, 0.05, 5, 200, 1e-3).r)
    r = R.from_spec({"kind": "sequence", "steps": [{"rest": 0.1},
                     {"to": 0.02, "v_max": 0.1, "a_max": 2, "j_max": 50}, {"rest": 0.1}]}, 1e-3)
    assert r[-1] == 0.02 and r[0] == 0.0
    with pytest.raises(ValueError, match="unknown reference kind"):
        R.from_spec({"kind": "sine"}, 1e-3)
    with pytest.raises(ValueError, match="does not take"):
        R.from_spec({"kind": "b2_R", "vmax": 1}, 0.01)
    with pytest.raises(ValueError, match="needs"):
        R.from_spec({"kind": "move", "distance": 0.1}, 1e-3)
    assert set(R.KINDS) >= {"move", "out_and_back", "oscillating", "b1_training",
                            "b1_evaluation", "b2_R", "sequence"}
