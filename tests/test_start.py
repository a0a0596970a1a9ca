"""Issue 48: every law starts where the machine stands. A reference resting at r0 (0, 60 mm, 1 m) gives
u_ff(0) = the static force at r0, computed here independently of the law (the force terms at zero velocity
minus the controller's rest output, by python-control's DC gain; the PGNN's fixed point by scipy's brentq on
the torch model; the [K] filter's A(r0)/B(1)), the same on every sample before the motion, C equal to Python
flag for flag, on a 2-DOF controller the code does not contain (different C_r and C_y, a delay, with and
without an integrator).

Tolerances: |u_ff(0) - static| <= 1e-9 × max|u_ff| (the issue's bound; the law's own rounding is ~1e-15 of its
terms, the brentq root is solved to 1e-15); C against Python 1e-12 relative (glibc's tanh/exp against numba's,
as in test_export.py); flags exactly.
"""
from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch
from scipy import optimize

from pipeline.export.guard import FLAG, envelope_of
from pipeline.export.law import Law, feedforward, from_k_filter, from_measured_physics, from_pgnn, guarded
from pipeline.export.package import write_package
from pipeline.invert.start import resolve, settle_count, started
from pipeline.models.physics_maps import RigidBodyForward, RigidBodyInverse
from pipeline.systems.controller import LTIController
from tests.test_export import Ts, _pgnn

CC = shutil.which("cc")
GUARD = FLAG["SATURATED"] | FLAG["RATE_LIMITED"] | FLAG["OUT_OF_RANGE"] | FLAG["NONFINITE_INPUT"] | FLAG["FALLBACK"]
REST = 60           # samples at rest before the motion
R0S = (0.0, 0.06, 1.0)

# a 2-DOF PID with a lead, set-point weighting b = 0.6 on P, no D on r, one sample of delay (not in the code):
# C_y = (kp + ki Ts/(1 - z^-1) + kd (1 - z^-1)/Ts) · lead, C_r = (b kp + ki Ts/(1 - z^-1)) · lead
KP, KI, KD, B = 2.0e4, 4.0e5, 60.0, 0.6
LEAD = (np.array([1.0, -0.6]), np.array([1.0, -0.2]))      # (1 - 0.6 z^-1) / (1 - 0.2 z^-1), DC 0.5


def _pid_2dof(integrator: bool = True) -> LTIController:
    """B_y, B_r over the common A = (1 - z^-1)(1 - 0.2 z^-1) (or (1 - 0.9 z^-1)(1 - 0.2 z^-1): a leaky one)."""
    p = 1.0 if integrator else 0.9

    def add(*polys):   # polynomials in z^-1, ascending powers
        out = np.zeros(max(len(q) for q in polys))
        for q in polys:
            out[:len(q)] += q
        return out
    one = np.array([1.0, -p])
    d = np.polymul([1.0, -1.0], one) * (KD / Ts)
    b_y = add(KP * one, [KI * Ts], d)
    b_r = add(B * KP * one, [KI * Ts])
    b_y, b_r = np.polymul(b_y, LEAD[0]), np.polymul(b_r, LEAD[0])
    a = np.polymul(one, LEAD[1])
    return LTIController.lti(list(b_y), list(a), list(b_r), gtau=2.0, delay=1)


def _reference(r0: float, n: int = 700, amp: float = 0.02) -> np.ndarray:
    t = np.arange(n - REST) * Ts
    move = amp * (1 - np.cos(2 * np.pi * t / (t.size * Ts))) / 2
    return r0 + np.concatenate([np.zeros(REST), move])


def _rest_law(law: Law, r0s, static: str = "include") -> Law:
    d = dict(law.__dict__)
    d.update(start="rest", static=static, rest="first")
    law = Law(**d)
    law.settle = settle_count(lambda r: __import__("pipeline.export.law", fromlist=["_core"])._core(law, r)[0], r0s)
    return law


def _guard(law: Law, r: np.ndarray) -> Law:
    lo, hi = envelope_of([r], law.Ts, 0.5)
    d = dict(law.__dict__)
    d["guard"] = {**law.guard, "env_lo": lo, "env_hi": hi, "u_min": -1e7, "u_max": 1e7, "rate": 1e12}
    return Law(**d)


# ---- the static force at r0, independently of the law ----------------------------------------------------
def _measured(ctrl: LTIController):
    from pipeline.systems.measured import Recording
    sys_ = Recording("vaxis", Ts, controller={"kind": "lti", "num": [1.0]},
                     force_terms={"terms": ["viscous", "coulomb", "offset", "cogging"], "cogging_period": 0.03,
                                  "coulomb_width": 1e-3}, physics_input="averaged")
    phys = {"M": 3.4, "F_v": 20.0, "F_c": 4.0, "OF": 33.4, "C_cos1": 1.5, "C_sin1": -0.7}
    theta = sys_.physics.theta_from_physical(phys)
    assert set(phys) - {"M"} <= set(sys_.physics.terms.physical_names)

    def static(r0):   # τ = M q̈ + Σ p_j T_j: at rest the offset and the cogging at r0, minus gtau K0 r0
        import control
        c_r, c_y = ctrl.transfer_functions(Ts)
        k0 = 0.0 if ctrl.integral_action else float(np.real(control.dcgain(c_r - c_y)))
        w = 2 * np.pi * r0 / 0.03
        return phys["OF"] + phys["C_cos1"] * math.cos(w) + phys["C_sin1"] * math.sin(w) - ctrl.gtau * k0 * r0
    return from_measured_physics(sys_.physics, theta, ctrl), static


def _pgnn_static(model, structure: str):
    """u* at rest at r0: the forward model's prediction equals r0 (forward, invertible), or the inverse model
    returns its own past input (inverse, n_b = 2)."""
    n_a, n_b = model.n_a, model.n_b

    def static(r0):
        def g(u):
            if structure == "inverse":
                phi = [r0] * (n_a + 1) + [u] * (n_b - 1)
                with torch.no_grad():
                    return float(model(torch.tensor([phi], dtype=torch.float64))[0]) - u
            phi = [r0] * n_a + [u] * n_b
            with torch.no_grad():
                return float(model(torch.tensor([phi], dtype=torch.float64))[0]) - r0
        lo, hi = -1e9, 1e9
        return optimize.brentq(g, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=500)
    return static


def _over_the_travel(m):
    """The PGNN's input normalisation fitted to a travel of 0 .. 1 m and forces of ±5 N (the models of
    test_export are normalised to ±1 cm: at r0 = 1 m their NN would be saturated far outside it)."""
    rng = np.random.default_rng(1)
    n_y = m.n_phi - m.n_b
    x = np.concatenate([rng.uniform(-0.1, 1.1, (400, 1)).repeat(n_y, axis=1) + 1e-3 * rng.standard_normal((400, n_y)),
                        5.0 * rng.standard_normal((400, m.n_b))], axis=1)
    m.fit_normalisation(torch.as_tensor(x))
    return m


def _family(kind: str, integrator: bool = True):
    if kind == "measured":
        return _measured(_pid_2dof(integrator))
    if kind == "direct":
        m = _over_the_travel(_pgnn("inverse", RigidBodyInverse(Ts), n_b=1, theta=(5.0, 10.0, 2.0)))
        return from_pgnn(m, "direct", Ts), _pgnn_static(m, "inverse")
    if kind in ("newton", "analytic"):
        m = _over_the_travel(_pgnn("invertible" if kind == "analytic" else "forward", RigidBodyForward(Ts, 2), n_b=1))
        return from_pgnn(m, kind, Ts, k=20), _pgnn_static(m, "forward")
    from pipeline.models.shared_ar import ReferenceWindow, SharedARPGNN, make_approximator
    g = make_approximator("mlp", 3, seed=0, hidden=(6,), activation="tanh")
    model = SharedARPGNN(4, 2, g, ReferenceWindow(2, "delta", Ts).fit(_reference(0.5)), basis="delta", Ts=Ts,
                         a=[3.0, 0.0, 20.0, 0.0], b=[2e-3, 1e-6])

    def static(r0):   # (A(r0) + g(window at rest)) / B(1): ψ_0 = r0, the δ-basis columns 0 at rest
        with torch.no_grad():
            gw = float(model.g_gain) * float(model.g(model.window(torch.tensor([[r0, 0.0, 0.0]],
                                                                               dtype=torch.float64)))[0])
        return (3.0 * r0 + gw) / float(np.sum(model.denominator()))
    return from_k_filter(model), static


FAMILIES = ["measured", "direct", "analytic", "newton", "shared_ar"]


@pytest.mark.parametrize("kind", FAMILIES)
def test_a_reference_at_rest_anywhere_starts_at_the_static_force_in_c_and_python(kind, tmp_path):
    law0, static = _family(kind)
    law = _rest_law(law0, R0S)
    for r0 in R0S:
        r = _reference(r0)
        lg = _guard(law, r)
        u, f = guarded(lg, r)
        scale = float(np.max(np.abs(u)))
        s = static(r0)
        assert abs(u[0] - s) <= 1e-9 * scale, (kind, r0, u[0], s)
        before = REST - law.preview - 1          # samples whose preview has not reached the motion
        assert np.max(np.abs(u[:before] - s)) <= 1e-9 * scale, (kind, r0)
        assert not (f & GUARD).any(), (kind, r0, np.flatnonzero(f & GUARD)[:5])    # the law's own flags may be set
        np.testing.assert_array_equal(u, feedforward(lg, r))
        if CC is not None:
            man = write_package(lg, "ff_rest", tmp_path / f"{kind}{r0}", {"ref": (r, u)}, source={}, timing_repeats=0)
            assert man["compiled"] and man["references"]["ref"]["c_flags_agree"]
            # [K]: 1/B(q) with poles near 1 carries C's and Python's different warm-up transients (each settled to
            # 1e-14 of u) in its registers: the export's own bound, 1e-9 (README: 6.9e-11 for a rational TF)
            tol = 1e-9 if kind == "shared_ar" else 1e-12
            assert man["c_max_rel_diff"] <= tol, (kind, r0, man["c_max_rel_diff"])


@pytest.mark.parametrize("kind", ["measured", "direct"])
def test_static_exclude_starts_at_zero_and_differs_from_include_by_the_static_force(kind):
    law0, static = _family(kind)
    inc, exc = _rest_law(law0, R0S), _rest_law(law0, R0S, static="exclude")
    for r0 in R0S:
        r = _reference(r0)
        u_i, u_e = feedforward(inc, r), feedforward(exc, r)
        scale = float(np.max(np.abs(u_i)))
        assert abs(u_e[0]) <= 1e-12 * scale
        np.testing.assert_allclose(u_i - u_e, static(r0), rtol=0, atol=1e-9 * scale)


def test_the_controller_term_at_rest_is_its_dc_gain_without_an_integrator_and_nothing_with_one():
    """(C_r - C_y) r from rest at r0: a leaky 2-DOF controller outputs its DC gain × r0 there (python-control's
    dcgain), constant; with an integrator the loop's integrator holds any constant, so the term counts from r0."""
    import control
    for integrator in (True, False):
        ctrl = _pid_2dof(integrator)
        db, den = ctrl.reference_filter()     # (B_r - B_y)/A as one transfer function in z (same coefficients)
        diff = control.tf(db, den, Ts)
        r = _reference(0.06)
        f = ctrl.reference_force(r, 0.06)
        k0 = 0.0 if integrator else float(np.real(control.dcgain(diff)))
        assert ctrl.integral_action == integrator
        np.testing.assert_allclose(f[:REST], ctrl.gtau * k0 * 0.06, rtol=1e-12, atol=1e-12)
        # the motion part is the zero-state filter on r - r0, as python-control's forced response
        _, y = control.forced_response(diff, T=np.arange(r.size) * Ts, U=r - 0.06)
        np.testing.assert_allclose(f - f[0], ctrl.gtau * np.asarray(y).ravel(), rtol=0,
                                   atol=1e-9 * float(np.max(np.abs(f - f[0]))))


def test_an_integrator_that_sees_r_and_y_differently_has_no_rest_and_is_refused():
    ctrl = LTIController.lti([2.0, -1.0], [1.0, -1.0], [1.5, -1.0], delay=1)   # B_r(1) = 0.5, B_y(1) = 1
    with pytest.raises(ValueError, match="no rest away from r = 0"):
        ctrl.rest_gain()


def test_start_auto_is_rest_on_a_measured_system_and_exclude_only_with_integral_action():
    class Sys:
        measured = True
        ctrl = _pid_2dof(True)
    assert resolve({}, Sys) == resolve({"at": "rest", "static": "exclude"}, Sys)
    Sys.ctrl = _pid_2dof(False)
    assert resolve({}, Sys).static == "include"

    class Sim:
        measured = False
    assert resolve({}, Sim).at == "zero" and resolve({}, Sim).static == "include"
    with pytest.raises(ValueError, match="needs start.at=rest"):
        resolve({"static": "exclude"}, Sim)


def test_settle_counts_the_recursion_and_started_drops_it():
    """A first-order recursion u(t) = 0.5 u(t-1) + r(t) from u(-1) = 0 settles (to 1e-14) after ~47 samples at
    rest; started() then gives the steady state 2 r0 from the first sample."""
    from scipy import signal
    law = lambda r: signal.lfilter([1.0], [1.0, -0.5], r)   # noqa: E731
    n = settle_count(law, [1.0])
    assert 40 <= n <= 50, n
    u, u_rest = started(law, np.full(10, 1.0), 1.0, n)
    np.testing.assert_allclose(u, 2.0, rtol=1e-13)
    assert abs(u_rest - 2.0) <= 1e-13
    with pytest.raises(ValueError, match="does not settle"):
        settle_count(lambda r: np.cumsum(r), [1.0])


def test_an_integrator_typed_with_8_digits_is_still_an_integrator_and_has_a_rest():
    """Coefficients copied with 8 significant digits move the integrator's pole ~1e-8 off z = 1: it must still be
    recognised (else the rest gain (B_r - B_y)(1)/A(1) is a 1e6 N/m artefact and u_ff(0) tens of kN); with 7 digits
    a pole lands just outside the circle and the refusal says why."""
    ctrl = _pid_2dof(True)
    rnd = lambda p, n: [float(f"{c:.{n - 1}e}") for c in p]   # noqa: E731
    typed = LTIController.lti(rnd(ctrl.b_y, 8), rnd(ctrl.a, 8), rnd(ctrl.b_r, 8), gtau=2.0, delay=1)
    assert typed.integral_action and typed.rest_gain() == 0.0
    f = typed.reference_force(_reference(0.06), 0.06)
    assert np.all(f[:REST] == 0.0)
    a7 = np.polymul([1.0, -1.000004], LEAD[1])           # an integrator typed so that its pole is outside
    with pytest.raises(ValueError, match="integrator typed with too few digits"):
        LTIController.lti([1.0, 0.5], list(a7), delay=1)


def test_default_limits_cover_the_controller_term_of_a_2dof_loop():
    """The feedforward of a 2-DOF loop carries -(C_r - C_y) r, which a D-term on y only makes far larger than the
    applied force: the default limits are those of u - (C_r - C_y) r on the training data, not of u alone (which
    clipped 37 000 of 48 000 samples of the held-out axis's law)."""
    from stages.export import data_limits
    ctrl = _pid_2dof(True)
    r = _reference(0.06, 2000, 0.05)
    u = 30.0 + 5.0 * np.sin(np.arange(r.size) * 0.01)          # the recorded force: a load and a small motion
    term = ctrl.reference_force(r, float(r[0]))
    u_abs, du_abs = data_limits([(u, r)], Ts, ctrl)
    assert u_abs == pytest.approx(float(np.max(np.abs(u - term))), rel=1e-15)
    assert u_abs > 10 * float(np.max(np.abs(u)))
    assert du_abs == pytest.approx(float(np.max(np.abs(np.diff(u - term)))) / Ts, rel=1e-15)
    assert data_limits([(u, None)], Ts) == (pytest.approx(35.0, rel=1e-3), pytest.approx(0.05 / Ts, rel=1e-3))


def test_a_rest_force_beyond_the_limits_starts_saturated_not_slewing_from_outside(tmp_path):
    """The output before t = 0 is the law at rest clamped into [u_min, u_max]: the first sample is saturated and
    no sample leaves the limits (before, the slew limit ramped from the rest value for seconds)."""
    law0, static = _family("measured")
    law = _rest_law(law0, R0S)
    r = _reference(0.06)
    lo, hi = envelope_of([r], law.Ts, 0.5)
    s = static(0.06)
    d = dict(law.__dict__)
    d["guard"] = {**law.guard, "env_lo": lo, "env_hi": hi, "u_min": -0.5 * s, "u_max": 0.5 * s, "rate": 1e3}
    lg = Law(**d)
    u, f = guarded(lg, r)
    assert np.all(np.abs(u) <= 0.5 * s) and u[0] == 0.5 * s and f[0] & FLAG["SATURATED"]
    assert np.max(np.abs(np.diff(u))) <= 1e3 * Ts * (1 + 1e-12)
    if CC is not None:
        man = write_package(lg, "ff_rest", tmp_path, {"ref": (r, feedforward(lg, r))}, source={}, timing_repeats=0)
        assert man["compiled"] and man["references"]["ref"]["c_flags_agree"] and man["c_max_rel_diff"] <= 1e-12


def test_an_integrator_cancelled_to_the_typed_digits_does_not_drift():
    """B_r(1) - B_y(1) = 1e-4 of B_y(1) (digits): accepted as the same integral weight, and the pole at z = 1 cancels
    exactly, so after a move the controller term settles to its DC value instead of integrating the rounding (it
    drifted by 30 N in 40 s before)."""
    ctrl = _pid_2dof(True)
    b_r = ctrl.b_r.copy()
    b_r[0] += 1e-4 * float(np.sum(ctrl.b_y))
    typed = LTIController.lti(list(ctrl.b_y), list(ctrl.a), list(b_r), gtau=2.0, delay=1)
    assert typed.rest_gain() == 0.0 and abs(float(np.sum(typed.reference_filter()[1]))) > 0.1   # no pole at 1 left
    r = np.concatenate([_reference(0.06), np.full(40_000, 0.08)])      # a 20 mm move, then 40 s at rest
    f = typed.reference_force(r, 0.06)
    exact = ctrl.reference_force(r, 0.06)
    end = f[-30_000:]
    assert np.ptp(end) <= 1e-9 * np.max(np.abs(f))
    assert abs(end[-1] - exact[-1]) <= 2e-4 * np.max(np.abs(exact))


@pytest.mark.skipif(CC is None, reason="no C compiler on this machine")
def test_a_past_input_recursion_starts_as_init_leaves_it_when_the_reference_moves_at_once(tmp_path):
    """A direct inverse with n_k = 1 and a past input (n_b = 2) on a reference that moves from sample 1: the C's
    init warms the recursion up on r0 alone (it cannot see the motion coming), so the Python law takes the input
    history of a rest run, not of rest samples padded in front (which saw the motion in their preview and
    disagreed with the C by 0.25 %). C = Python to 1e-12."""
    from pipeline.models.pgnn import PGNN
    m = PGNN(2, 2, 1, structure="inverse", physics=RigidBodyInverse(Ts), hidden=(8,), seed=3, out_init_scale=0.3)
    m.set_physics_estimate((0.2, 2.0, 0.4))
    law = _rest_law(from_pgnn(_over_the_travel(m), "direct", Ts), R0S)
    assert law.settle > 0                                   # a recursion to settle
    t = np.arange(700) * Ts
    r = 0.06 + 0.02 * (1 - np.cos(2 * np.pi * t / (700 * Ts))) / 2      # moving from sample 1
    lg = _guard(law, r)
    u, f = guarded(lg, r)
    man = write_package(lg, "ff", tmp_path, {"ref": (r, u)}, source={}, timing_repeats=0)
    assert man["references"]["ref"]["c_flags_agree"] and man["c_max_rel_diff"] <= 1e-12
