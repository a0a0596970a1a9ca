"""A held-out vertical linear-motor axis (issue 48): a machine the pipeline does not contain, with its own
continuous-time plant, controller and recordings. numpy/scipy only; nothing here imports ``pipeline``.

The plant, simulated in continuous time (RK4 sub-steps under a zero-order-hold force, not the pipeline's
one-step exact-ZOH rigid body), position q [m] upwards::

    M q̈ = u - M g - K_S (q - Q_C) - F_V q̇ - F_C tanh(q̇ / W_C)

gravity, a cable carrier (a spring about Q_C: no term of the pipeline's force library models it),
viscous and smooth Coulomb friction. Ts = 1/4000 s, force limit ±60 N, 50 nm measurement noise.

The controller (:func:`controller`): a 2-DOF PID (set-point weight b = 0.6 on P, no D on r, a filtered D),
a lead and a notch, Tustin-discretised, written over ONE common denominator in powers of z⁻¹::

    A(z⁻¹) v(k) = B_r(z⁻¹) r(k) - B_y(z⁻¹) y(k),   A[0] = 1, a pole at z = 1 (the integrator),
    B_r(1) = B_y(1) (the integral acts on the error e = r - y),
    c(k) = sat±60 N(v(k) + u_ff(k)),   u(k) = c(k - 1)   (one sample of computational delay).

u is the force applied over [k Ts, (k+1) Ts): the pipeline's ``u = gtau (sat(v + u_ff/gtau)(k - D) + d)``
with gtau = 1, D = 1, d = 0, v_sat = 60. The loop starts at rest at r0 = r(0) with the integrator holding
the static load (y = r0, every controller output in the past = M g + K_S (r0 - Q_C)).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy import signal

TS = 1.0 / 4000.0                 # sample time [s]
M = 3.4                           # moving mass [kg]
G = 9.81                          # [m/s²]
K_S, Q_C = 40.0, 0.07             # cable-carrier stiffness [N/m] about Q_C [m]
F_V = 12.0                        # viscous friction [N s/m]
F_C, W_C = 4.5, 0.7e-3            # Coulomb friction [N], tanh width [m/s]
U_MAX = 60.0                      # actuator limit [N], on the total force (controller + feedforward)
NOISE = 50e-9                     # measurement noise std [m]
DELAY = 1                         # computational delay [samples]
SUBSTEPS = 4                      # RK4 sub-steps per sample (the error is < 1e-9 of that with 16, see _selfcheck)

# controller design (continuous time, Tustin): crossover FC on the rigid mass, PID in series form
# K (1 + w_i/s)(1 + s/w_z)/(1 + s/w_f) written in parallel form (P, I, filtered D), then a lead and a notch
FC = 60.0                         # crossover [Hz]
B_WEIGHT = 0.6                    # set-point weight on P (no D on r)
LEAD_HZ = (150.0, 500.0)          # lead zero, pole [Hz]
NOTCH_HZ, NOTCH_ZETA = 900.0, (0.02, 0.3)   # notch frequency [Hz], damping of its zeros, poles

TRAIN_FILES = ("train1.csv", "train2.csv")
TEST_FILE = "test.csv"
TEST_R0 = 0.06                    # the test reference rests here at t = 0 [m]
TEST_SECONDS = 12.0


def axis_params() -> dict:
    """The truth, with the force terms the pipeline would name (its offset OF is the static force at q = 0)."""
    return {"Ts": TS, "M": M, "g": G, "K_S": K_S, "Q_C": Q_C, "F_v": F_V, "F_c": F_C, "coulomb_width": W_C,
            "u_max": U_MAX, "noise_std": NOISE, "delay": DELAY,
            "OF_at_q0": M * G - K_S * Q_C, "static_force_at_test_r0": static_force(TEST_R0)}


def static_force(q: float) -> float:
    """The force that holds the axis at rest at q [N]: gravity plus the cable carrier."""
    return M * G + K_S * (q - Q_C)


def _add(*polys) -> np.ndarray:
    out = np.zeros(max(len(p) for p in polys))
    for p in polys:
        out[:len(p)] += p
    return out


def _design() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(b_r, b_y, a) in powers of z⁻¹, a[0] = 1 (module docstring)."""
    wc = 2 * math.pi * FC
    wz, wf, wi = wc / 3, 3 * wc, wc / 6
    kp, ki, kd = 1 + wi / wz - wi / wf, wi, 1 / wz - (1 + wi / wz - wi / wf) / wf   # gain 1, scaled below
    al = 2 / (TS * wf)
    d_den = np.array([1 + al, 1 - al])                      # Tustin of 1 + s/w_f (times 1 + z⁻¹)
    a_pid = np.polymul([1.0, -1.0], d_den)                  # the integrator's pole at z = 1, the D filter's
    integ = ki * TS / 2 * np.polymul([1.0, 1.0], d_den)
    deriv = kd * 2 / TS * np.polymul([1.0, -1.0], [1.0, -1.0])
    b_y = _add(kp * a_pid, integ, deriv)
    b_r = _add(B_WEIGHT * kp * a_pid, integ)                # same integral term: B_r(1) = B_y(1)
    wl1, wl2 = (2 * math.pi * f for f in LEAD_HZ)
    b_l, a_l = signal.bilinear([1 / wl1, 1.0], [1 / wl2, 1.0], fs=1 / TS)
    wn = 2 / TS * math.tan(math.pi * NOTCH_HZ * TS)         # prewarped
    zz, zp = NOTCH_ZETA
    b_n, a_n = signal.bilinear([1.0, 2 * zz * wn, wn ** 2], [1.0, 2 * zp * wn, wn ** 2], fs=1 / TS)
    filt_b, filt_a = np.polymul(b_l, b_n), np.polymul(a_l, a_n)
    b_y, b_r, a = np.polymul(b_y, filt_b), np.polymul(b_r, filt_b), np.polymul(a_pid, filt_a)
    b_y, b_r, a = b_y / a[0], b_r / a[0], a / a[0]
    gain = 1.0 / abs(loop_gain(b_y, a, 2 * math.pi * FC))   # |L| = 1 at FC on the rigid mass
    return b_r * gain, b_y * gain, a


def loop_gain(b_y, a, w) -> np.ndarray:
    """L(e^{jωTs}) = C_y · z^-DELAY · P_zoh of the rigid mass M (frequency response at ω [rad/s])."""
    z = np.exp(1j * np.asarray(w) * TS)
    zi = 1 / z
    p = TS ** 2 / (2 * M) * (z + 1) / (z - 1) ** 2
    return np.polyval(np.asarray(b_y)[::-1], zi) / np.polyval(np.asarray(a)[::-1], zi) * p * zi ** DELAY


_B_R, _B_Y, _A = _design()


def controller() -> tuple[list, list, list, int]:
    """(b_r, b_y, a, delay): B_r, B_y, A in powers of z⁻¹ (a[0] = 1), the delay in samples."""
    return [float(x) for x in _B_R], [float(x) for x in _B_Y], [float(x) for x in _A], DELAY


def closed_loop_poles() -> np.ndarray:
    """Poles of the sampled linear loop (the plant without Coulomb friction, exact ZOH): all |z| < 1."""
    num, den, _ = signal.cont2discrete(([1.0], [M, F_V, K_S]), TS, method="zoh")
    num, den = np.trim_zeros(np.ravel(num), "f"), np.ravel(den)          # P(z) = num/den in powers of z
    n = _A.size - 1                                                       # C_y(z) = B_y(z)/A(z), same degree n
    by = np.concatenate([_B_Y, np.zeros(n + 1 - _B_Y.size)])
    char = np.polyadd(np.polymul(np.polymul(_A, den), [1.0] + [0.0] * DELAY), np.polymul(by, num))
    return np.roots(char)


def _rk4(q: float, v: float, u: float, dt: float, n: int) -> tuple[float, float]:
    """n RK4 steps of M q̈ = u - M g - K_S (q - Q_C) - F_V q̇ - F_C tanh(q̇/W_C) under a constant u."""
    tanh = math.tanh
    c0 = (u - M * G + K_S * Q_C) / M
    ks, fv, fc = K_S / M, F_V / M, F_C / M

    def acc(q_, v_):
        return c0 - ks * q_ - fv * v_ - fc * tanh(v_ / W_C)
    h2, h6 = dt / 2, dt / 6
    for _ in range(n):
        a1 = acc(q, v)
        q2, v2 = q + h2 * v, v + h2 * a1
        a2 = acc(q2, v2)
        q3, v3 = q + h2 * v2, v + h2 * a2
        a3 = acc(q3, v3)
        q4, v4 = q + dt * v3, v + dt * a3
        a4 = acc(q4, v4)
        q, v = q + h6 * (v + 2 * v2 + 2 * v3 + v4), v + h6 * (a1 + 2 * a2 + 2 * a3 + a4)
    return q, v


def simulate(r, u_ff=None, r0: float | None = None, seed: int = 0, substeps: int = SUBSTEPS) -> dict:
    """The loop on the true plant from rest at r0 (default r(0)), the integrator holding the static load.

    u_ff [N] (default 0) is added to the controller output before the ±U_MAX limit. Returns t, r, u (the
    applied force [N] over each sample), y (measured), e = r - y, v (controller output), and ``saturated``:
    the number of samples whose total command reached the limit."""
    r = np.asarray(r, dtype=np.float64)
    N = r.size
    u_ff = np.zeros(N) if u_ff is None else np.asarray(u_ff, dtype=np.float64)
    if u_ff.shape != r.shape or not np.all(np.isfinite(u_ff)):
        raise ValueError(f"u_ff must be {N} finite samples, got shape {u_ff.shape}")
    r0 = float(r[0]) if r0 is None else float(r0)
    noise = NOISE * np.random.default_rng(seed).standard_normal(N)
    b_r, b_y, a = _B_R.tolist(), _B_Y.tolist(), _A.tolist()
    nr, ny, na = len(b_r), len(b_y), len(a)
    f0 = static_force(r0)
    r_h, y_h, v_h = [r0] * nr, [r0] * ny, [f0] * na      # newest first; index 0 is overwritten each sample
    c_h = [f0] * (DELAY + 1)                             # c(k), c(k-1), …: the applied force is c(k - DELAY)
    q, qd = r0, 0.0
    y, u, v_out = np.empty(N), np.empty(N), np.empty(N)
    sat = 0
    dt = TS / substeps
    for k in range(N):
        yk = q + noise[k]
        r_h.insert(0, float(r[k]))
        r_h.pop()
        y_h.insert(0, yk)
        y_h.pop()
        vk = sum(b_r[i] * r_h[i] for i in range(nr)) - sum(b_y[i] * y_h[i] for i in range(ny)) \
            - sum(a[i] * v_h[i - 1] for i in range(1, na))
        v_h.insert(0, vk)
        v_h.pop()
        ck = vk + u_ff[k]
        if abs(ck) >= U_MAX:
            sat += 1
            ck = math.copysign(U_MAX, ck)
        c_h.insert(0, ck)
        c_h.pop()
        uk = c_h[DELAY]
        y[k], u[k], v_out[k] = yk, uk, vk
        q, qd = _rk4(q, qd, uk, dt, substeps)
    return {"t": np.arange(N) * TS, "r": r.copy(), "u": u, "y": y, "e": r - y, "v": v_out, "saturated": sat}


def equation_error(r, y, u) -> float:
    """‖A c - B_r r + B_y y‖ / ‖A c‖ with c(k) = u(k + DELAY), past the first samples (the pipeline's check of
    a recording against its controller, done here independently)."""
    c = np.asarray(u, np.float64)[DELAY:]
    r, y = np.asarray(r, np.float64)[:c.size], np.asarray(y, np.float64)[:c.size]
    ac = signal.lfilter(_A, [1.0], c)
    bx = signal.lfilter(_B_R, [1.0], r) - signal.lfilter(_B_Y, [1.0], y)
    n = _A.size
    return float(np.linalg.norm(ac[n:] - bx[n:]) / np.linalg.norm(ac[n:]))


# ---- references --------------------------------------------------------------------------------------
def _move(r_a: float, r_b: float, T: float) -> np.ndarray:
    """A minimum-jerk move (quintic) from r_a to r_b in T s, at rest at both ends: peak speed 1.875 Δ/T,
    peak acceleration 5.77 Δ/T²."""
    s = np.arange(1, int(round(T / TS)) + 1) * TS / T
    return r_a + (r_b - r_a) * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)


def _sine(r_c: float, amp: float, f: float, T: float) -> np.ndarray:
    """amp sin(2π f t) about r_c, faded in and out over one period each (starts and ends at rest at r_c)."""
    t = np.arange(1, int(round(T / TS)) + 1) * TS
    fade = np.clip(np.minimum(t, T - t) * f, 0.0, 1.0)
    fade = fade ** 2 * (3 - 2 * fade)
    return r_c + amp * fade * np.sin(2 * math.pi * f * t)


def reference(start: float, segments) -> np.ndarray:
    """A reference from rest at ``start``: segments ('move', to, T), ('dwell', T), ('sine', amp, f, T)."""
    parts, pos = [np.array([start])], start
    for seg in segments:
        if seg[0] == "move":
            parts.append(_move(pos, seg[1], seg[2]))
            pos = seg[1]
        elif seg[0] == "dwell":
            parts.append(np.full(int(round(seg[1] / TS)), pos))
        else:
            parts.append(_sine(pos, *seg[1:]))
    return np.concatenate(parts)


#: training references [m], [s]: moves of 5-90 mm at 0.01-0.33 m/s and 0.1-3 m/s², slow sines, within
#: r ∈ [20 mm, 120 mm]; each starts and ends at rest, away from 0
TRAIN_SEGMENTS = {
    "train1.csv": (0.04, [("dwell", 0.5), ("move", 0.10, 0.45), ("dwell", 0.4), ("move", 0.03, 0.6),
                          ("dwell", 0.4), ("move", 0.11, 0.55), ("dwell", 0.3), ("move", 0.05, 0.34),
                          ("dwell", 0.3), ("move", 0.075, 0.8), ("dwell", 0.3), ("move", 0.065, 0.9),
                          ("dwell", 0.3), ("sine", 0.035, 0.5, 6.0), ("dwell", 0.3), ("move", 0.02, 0.7),
                          ("dwell", 0.4), ("move", 0.05, 0.35), ("dwell", 0.3), ("sine", 0.01, 2.0, 3.0),
                          ("dwell", 0.3), ("move", 0.12, 0.9), ("dwell", 0.4), ("move", 0.06, 1.2),
                          ("dwell", 1.0)]),
    "train2.csv": (0.09, [("dwell", 0.5), ("move", 0.025, 0.5), ("dwell", 0.4), ("move", 0.115, 0.6),
                          ("dwell", 0.3), ("move", 0.105, 0.5), ("dwell", 0.3), ("move", 0.095, 0.5),
                          ("dwell", 0.3), ("move", 0.07, 0.4), ("dwell", 0.3), ("sine", 0.04, 0.3, 7.0),
                          ("dwell", 0.3), ("move", 0.10, 0.7), ("dwell", 0.3), ("move", 0.05, 0.8),
                          ("dwell", 0.3), ("sine", 0.02, 1.0, 4.0), ("dwell", 0.3), ("move", 0.11, 0.4),
                          ("dwell", 0.3), ("move", 0.08, 1.5), ("dwell", 1.0)]),
}
#: the test reference: at rest at 60 mm, a few moves inside the training envelope, 12 s
TEST_SEGMENTS = (TEST_R0, [("dwell", 1.0), ("move", 0.10, 0.5), ("dwell", 0.5), ("move", 0.035, 0.6),
                           ("dwell", 0.5), ("move", 0.045, 1.0), ("dwell", 0.5), ("move", 0.09, 0.45),
                           ("dwell", 0.5), ("sine", 0.02, 0.8, 3.75), ("dwell", 0.5), ("move", 0.06, 0.7)])


def eval_reference() -> np.ndarray:
    """The test reference: 48 000 samples, at rest at 60 mm for the first second and at the end."""
    r = reference(*TEST_SEGMENTS)
    n = int(round(TEST_SECONDS / TS))
    if r.size > n:
        raise AssertionError(f"the test segments last {r.size * TS} s > {TEST_SECONDS} s")
    return np.concatenate([r, np.full(n - r.size, r[-1])])


def write_recording(path: Path, rec: dict) -> None:
    """CSV t, r, u, y (17 digits: the values as simulated) with its sidecar ``<file>.json`` {"Ts": …}."""
    path = Path(path)
    np.savetxt(path, np.column_stack([rec["t"], rec["r"], rec["u"], rec["y"]]), delimiter=",",
               header="t,r,u,y", comments="", fmt="%.17g")
    Path(f"{path}.json").write_text(json.dumps({"Ts": TS}))


def training_recordings(folder, seed: int = 1) -> dict:
    """Writes train1.csv, train2.csv and test.csv (+ sidecars) into ``folder``; returns the recordings by
    file name. Raises when a recording saturates or does not satisfy the controller equation."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    refs = {name: reference(*segs) for name, segs in TRAIN_SEGMENTS.items()}
    refs[TEST_FILE] = eval_reference()
    out = {}
    for i, (name, r) in enumerate(refs.items()):
        rec = simulate(r, seed=seed + i)
        if rec["saturated"]:
            raise AssertionError(f"{name}: {rec['saturated']} samples at the ±{U_MAX} N limit")
        res = equation_error(rec["r"], rec["y"], rec["u"])
        if res > 1e-9:
            raise AssertionError(f"{name}: the recorded u does not satisfy the controller equation ({res:.3g})")
        write_recording(folder / name, rec)
        out[name] = rec
    return out


def _selfcheck() -> None:
    """Loop stable, integrator exact, RK4 converged, recordings consistent (``python tests/heldout_axis.py``)."""
    import time
    b_r, b_y, a, _ = controller()
    poles = closed_loop_poles()
    w = 2 * math.pi * np.linspace(1.0, 1999.0, 40000)
    L = loop_gain(_B_Y, _A, w)
    i = int(np.argmin(np.abs(np.abs(L) - 1)))
    print(f"controller: order {len(a) - 1}, A(1) = {sum(a):.2e}, B_r(1) - B_y(1) = {sum(b_r) - sum(b_y):.2e} "
          f"(B_y(1) = {sum(b_y):.4g}); max |closed-loop pole| {np.abs(poles).max():.5f}; crossover "
          f"{w[i] / 2 / math.pi:.1f} Hz, phase margin {180 + np.angle(L[i], deg=True):.1f}°, "
          f"max |S| {np.abs(1 / (1 + L)).max():.3f}")
    r = eval_reference()
    t0 = time.process_time()
    ref = simulate(r, substeps=16)
    t1 = time.process_time()
    rec = simulate(r)
    print(f"test reference: {r.size} samples, simulate {time.process_time() - t1:.2f} s CPU "
          f"(16 sub-steps {t1 - t0:.2f} s); MAE {1e6 * np.mean(np.abs(rec['e'])):.3f} µm, "
          f"max |u| {np.abs(rec['u']).max():.2f} N, saturated {rec['saturated']}; "
          f"RK4 {SUBSTEPS} vs 16 sub-steps: max |Δy| {np.abs(rec['y'] - ref['y']).max():.2e} m; "
          f"equation error {equation_error(rec['r'], rec['y'], rec['u']):.2e}")
    rest = simulate(np.full(4000, TEST_R0))
    print(f"at rest at {TEST_R0} m: max |e| {np.abs(rest['e']).max() * 1e9:.1f} nm, "
          f"u {rest['u'].mean():.6f} N (static {static_force(TEST_R0):.6f} N)")


if __name__ == "__main__":
    _selfcheck()
