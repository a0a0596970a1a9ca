"""Tests of the two_mass_stribeck plant (SPEC §2.1, [K] Section VI)."""
from __future__ import annotations

import warnings
from pathlib import Path

import control
import numpy as np
import pytest
from scipy.signal import lfilter

from pipeline.references import K_TRAINING_MOVES, out_and_back
from pipeline.systems.two_mass_stribeck import (TwoMassStribeck, ar_roots, delta_to_monic_shift,
                                                rational_feedforward, sech)

TS = 1e-3
CONF = Path(__file__).resolve().parents[1] / "conf" / "system" / "two_mass_stribeck.yaml"


def k_reference(d: float, v: float) -> np.ndarray:
    """[K] §VI out-and-back move (a_max 5 m/s², j_max 200 m/s³)."""
    return out_and_back(d, v, 5.0, 200.0, TS).r


def rel(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_sech_has_no_overflow():
    x = np.array([-1e6, -800.0, -3.0, 0.0, 0.5, 700.0, 1e6])
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # an overflow warning fails the test
        s = sech(x)
    mid = np.abs(x) < 700
    np.testing.assert_allclose(s[mid], 1.0 / np.cosh(x[mid]), rtol=1e-15)
    assert np.all(s[~mid] >= 0) and np.all(s[~mid] < 1e-300)


def test_continuous_model_has_the_corrected_coefficients():
    """Newton's law state space = B(s)/(A(s) + c s B(s)) with SPEC §2.1's (corrected) a2, a3."""
    sysm = TwoMassStribeck(c1=3.0, c2=3.0)
    tf = control.tf(sysm.continuous_linear_model())
    num = np.asarray(tf.num[0][0], float)
    den = np.asarray(tf.den[0][0], float)
    a, b = sysm.delta_coefficients(3.0)        # lowest power first
    # normalise both by the leading denominator coefficient a4 = m1 m2 (ss2tf leaves ~1e-14
    # residues in the structurally zero s^3 coefficient of the numerator: compare padded)
    np.testing.assert_allclose(den / den[0], a[::-1] / a[-1], rtol=1e-10)
    num_ref = np.r_[np.zeros(num.size - 3), b[::-1] / a[-1]]
    np.testing.assert_allclose(num / den[0], num_ref, rtol=1e-10, atol=1e-10 * np.abs(num_ref).max())
    # the paper's misprinted a2 = m2 k1 + k1 m1 - k2 m2 would be unstable; ours is stable
    assert np.all(np.real(control.poles(tf)) < 0)


def test_linear_part_matches_c2d_forced_response():
    """c1 = c2: the Newton simulator is the backward-Euler (δ) discretisation, cross-checked
    against python-control c2d(method='backward_diff') + forced_response to 1e-8 relative."""
    sysm = TwoMassStribeck(c1=5.0, c2=5.0)
    rng = np.random.default_rng(1)
    f = np.r_[np.zeros(10), rng.normal(0.0, 10.0, 1990)]
    y = sysm.forward(f)
    sysd = control.c2d(sysm.continuous_linear_model(), TS, method="backward_diff")
    y_ref = control.forced_response(sysd, np.arange(f.size) * TS, f).outputs
    assert rel(y, y_ref) < 1e-8
    # the discrete model handed to ILC is the same system
    y_lin = control.forced_response(sysm.linear_model(), np.arange(f.size) * TS, f).outputs
    assert rel(y_lin, y_ref) < 1e-8


def test_exact_inverse_reproduces_training_references():
    """Simulating with f̂ = (A/B) r + d_NL(δr) tracks every [K] training reference to 1e-7."""
    sysm = TwoMassStribeck()
    for d, v in K_TRAINING_MOVES:
        r = k_reference(d, v)
        f_hat = sysm.exact_inverse(r)
        y = sysm.simulate(r, u_ff=f_hat).y
        assert rel(y, r) < 1e-7, (d, v)
    # the nonlinear term matters: the linear (c1) inverse alone misses by far more
    r = k_reference(0.02, 0.02)
    f_lin = sysm.physics.feedforward(sysm.physics_theta(), r)
    assert rel(sysm.forward(f_lin), r) > 1e-2


def test_exact_inverse_matches_the_polynomial_filter():
    """Cross-check the δ expansion: A(q^-1)/B(q^-1) as one lfilter on the raw polynomials
    (ill-conditioned: SPEC quotes ~1.5e-8, so compare to 1e-6)."""
    sysm = TwoMassStribeck()
    r = k_reference(0.1, 0.2)
    a, b = sysm.delta_coefficients(0.0)
    P = np.polynomial.polynomial

    def shift_poly(coef):   # Σ c_i δ^i -> coefficients of q^0, q^-1, …
        out = np.zeros(len(coef))
        for i, ci in enumerate(coef):
            out[: i + 1] += ci * TS ** -i * P.polypow([1.0, -1.0], i)
        return out

    num, den = shift_poly(a), shift_poly(b)
    f_poly = lfilter(num, den, r) + sysm.d_nl(np.diff(r, prepend=0.0) / TS)
    assert rel(sysm.exact_inverse(r), f_poly) < 1e-6


def test_same_seed_is_bit_identical():
    sysm = TwoMassStribeck(noise={"std": 1e-6})
    r = k_reference(0.05, 0.1)
    f = sysm.exact_inverse(r)
    runs = [sysm.simulate(r, u_ff=f, v=sysm.noise(r.size, np.random.default_rng(7))) for _ in range(2)]
    for key in ("y", "v", "u", "y_clean"):
        assert np.array_equal(getattr(runs[0], key), getattr(runs[1], key))
    other = sysm.simulate(r, u_ff=f, v=sysm.noise(r.size, np.random.default_rng(8)))
    assert not np.array_equal(runs[0].y, other.y)
    assert abs(np.std(runs[0].v) / 1e-6 - 1) < 0.1           # N ≈ 1800: ±3.3% std error
    np.testing.assert_array_equal(runs[0].y, runs[0].y_clean + runs[0].v)
    assert not np.any(TwoMassStribeck().noise(50, np.random.default_rng(0)))  # default: none


def test_physics_least_squares_recovers_coefficients():
    """c1 = c2: the plant is in the rational class; LS on noise-free data recovers θ and the
    physical parameters to 1e-6 relative."""
    sysm = TwoMassStribeck(c1=2.0, c2=2.0)
    rows, rhs = [], []
    for d, v in K_TRAINING_MOVES[:4]:
        r = k_reference(d, v)
        f = sysm.exact_inverse(r)
        Phi, z = sysm.physics.regressor(sysm.forward(f), f)
        rows.append(Phi)
        rhs.append(z)
    Phi, z = np.vstack(rows), np.concatenate(rhs)
    scale = np.linalg.norm(Phi, axis=0)                # column scaling (SPEC §5)
    theta = np.linalg.lstsq(Phi / scale, z, rcond=None)[0] / scale
    theta_true = sysm.physics_theta()
    np.testing.assert_allclose(theta, theta_true, rtol=1e-6)
    phys = sysm.physics.physical(theta)
    for key, val in dict(m1=1.0, m2=2.0, k1=1.0, k2=15000.0, d2=50.0, c=2.0).items():
        assert phys[key] == pytest.approx(val, rel=1e-6), key


def test_physics_feedforward_is_the_exact_inverse_when_linear():
    sysm = TwoMassStribeck(c1=4.0, c2=4.0)
    r = k_reference(0.15, 0.15)
    f = sysm.physics.feedforward(sysm.physics_theta(), r)
    assert rel(f, sysm.exact_inverse(r)) < 1e-12
    # 1/B has DC gain ≈ 138 at Ts = 1e-3 (SPEC §3 item 6) and B is stable
    beta = sysm.physics_theta()[5:]
    assert 1.0 / (1.0 + beta.sum()) == pytest.approx(137.67, rel=1e-4)
    assert np.max(np.abs(ar_roots(beta))) < 1.0


def test_feedforward_rejects_unstable_ar_polynomial():
    theta = TwoMassStribeck().physics_theta()
    theta[5:] = [-2.1, 1.1]                           # roots 1.1 and 1.0
    with pytest.raises(ValueError, match="unstable"):
        TwoMassStribeck().physics.feedforward(theta, np.zeros(10))


def test_delta_to_monic_shift_round_trip():
    a_bar, beta = delta_to_monic_shift([1.0], [3.0, 0.2, 0.01], 0.1)
    # B(δ) = 3 + 0.2δ + 0.01δ² expanded: δ = (1 - q^-1)/0.1
    b_shift = np.array([3 + 2 + 1, -2 - 2, 1.0])
    np.testing.assert_allclose(np.r_[1.0, beta], b_shift / b_shift[0], rtol=1e-14)
    assert a_bar[0] == pytest.approx(1 / 6)
    # a rational filter with B ≡ 1 is a pure difference operator
    np.testing.assert_allclose(rational_feedforward([0.0, 1.0], [], [0.0, 1.0, 3.0], 0.5), [0, 2, 4])


def test_bad_input_raises_clear_errors():
    with pytest.raises(ValueError, match="m1"):
        TwoMassStribeck(m1=0.0)
    with pytest.raises(ValueError, match="noise"):
        TwoMassStribeck(noise={"sigma": 1e-6})
    with pytest.raises(ValueError, match="too large"):
        TwoMassStribeck(Ts=2.0, c2=200.0)
    with pytest.raises(ValueError, match="NaN"):
        TwoMassStribeck().simulate(np.array([0.0, np.nan]))


def test_config_instantiates():
    hydra_utils = pytest.importorskip("hydra.utils")
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(CONF)
    sysm = hydra_utils.instantiate(cfg)
    assert isinstance(sysm, TwoMassStribeck)
    assert (sysm.m1, sysm.m2, sysm.k1, sysm.k2, sysm.d2) == (1.0, 2.0, 1.0, 15000.0, 50.0)
    assert (sysm.c1, sysm.c2, sysm.alpha, sysm.Ts, sysm.noise_std) == (1.0, 20.0, 20.0, 1e-3, 0.0)
    assert sysm.controller() is None
