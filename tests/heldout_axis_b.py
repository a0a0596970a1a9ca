"""A second held-out axis (issue 49): a horizontal linear-motor stage on flexure guides, a machine the pipeline
does not contain. numpy/scipy only; nothing here imports ``pipeline``.

The plant, simulated in continuous time (RK4 sub-steps under a zero-order-hold command), position q [m]::

    τ_a Ḟ + F = u                                         (the drive's current loop: a first-order force lag)
    M q̈ = F - K_F (q - Q_F) - F_V q̇ - F_C tanh(q̇ / W_C) - OF

flexure guides (a spring about Q_F), viscous and smooth Coulomb friction, a constant cable pull OF, and
the current loop's lag τ_a. Ts = 1/8000 s, force limit ±40 N, 20 nm measurement noise.

The controller (:func:`controller_paths`), as the drive's tuning tool shows it: two transfer functions with
their own denominators, each Tustin-discretised on its own (nothing here writes them over one)::

    C_r(z) = N_r/D_r: a set-point weighted PI behind a second-order reference prefilter
    C_y(z) = N_y/D_y: a PID with a filtered D, a lead and a notch
    v(k) = C_r r - C_y y (each path its own difference equation),  c(k) = sat±40(v(k) + u_ff(k)),
    u(k) = c(k - 1)  (one sample of computational delay).

Both paths integrate (1/s) with the same integral gain, so C_r - C_y has no integrator. The loop starts at
rest at r0 = r(0) with the integrators holding the static load K_F (r0 - Q_F) + OF.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy import signal

TS = 1.0 / 8000.0                 # sample time [s]
M = 1.35                          # moving mass [kg]
TAU_A = 0.35e-3                   # current-loop lag [s]
K_F, Q_F = 600.0, 0.0             # flexure stiffness [N/m] about Q_F [m]
F_V = 6.0                         # viscous friction [N s/m]
F_C, W_C = 1.8, 1.5e-3            # Coulomb friction [N], tanh width [m/s]
OF = 0.9                          # cable pull [N]
U_MAX = 40.0                      # actuator limit [N] on the total command
NOISE = 20e-9                     # measurement noise std [m]
DELAY = 1                         # computational delay [samples]
SUBSTEPS = 4

FC = 90.0                         # crossover [Hz]
B_WEIGHT = 0.7                    # set-point weight on P in C_r
PREFILTER_HZ, PREFILTER_ZETA = 250.0, 0.8
LEAD_HZ = (200.0, 800.0)
NOTCH_HZ, NOTCH_ZETA = 1600.0, (0.03, 0.4)

TRAIN_FILES = ("run_a.csv", "run_b.csv")
TEST_FILE = "check.csv"
TEST_R0 = -0.012                  # the test reference rests here at t = 0 [m]
TEST_SECONDS = 6.0


def axis_params() -> dict:
    """The truth, with the names the pipeline's force terms would give (its offset is the force at q = 0)."""
    return {"Ts": TS, "M": M, "tau_a": TAU_A, "K": K_F, "Q_F": Q_F, "F_v": F_V, "F_c": F_C,
            "coulomb_width": W_C, "OF_at_q0": OF - K_F * Q_F, "u_max": U_MAX, "noise_std": NOISE, "delay": DELAY,
            "static_force_at_test_r0": static_force(TEST_R0)}


def static_force(q: float) -> float:
    return K_F * (q - Q_F) + OF


def _tustin(num_s, den_s):
    """Tustin of a polynomial C(s) (scipy's bilinear on the coefficients: no ill-conditioned state space)."""
    n, d = signal.bilinear(num_s, den_s, fs=1 / TS)
    n = np.concatenate([np.zeros(d.size - n.size), n])    # same degree: powers of z⁻¹ from z⁰
    return n / d[0], d / d[0]


def _design():
    """(N_r, D_r, N_y, D_y) in powers of z⁻¹ (module docstring), scaled for |L| = 1 at FC on the mass."""
    wc = 2 * math.pi * FC
    wi, wz, wf = wc / 5, wc / 3, 4 * wc
    kp = 1.0
    # C_y(s) = kp (1 + wi/s + s/wz · wf/(s + wf)) · lead · notch
    pid_n = kp * np.polyadd(np.polymul([1.0, wi], [1.0, wf]), [wf / wz, 0.0, 0.0])
    pid_d = np.polymul([1.0, 0.0], [1.0, wf])
    wl1, wl2 = (2 * math.pi * f for f in LEAD_HZ)
    wn = 2 * math.pi * NOTCH_HZ
    zz, zp = NOTCH_ZETA
    num_y = np.polymul(np.polymul(pid_n, [1 / wl1, 1.0]), [1.0, 2 * zz * wn, wn ** 2])
    den_y = np.polymul(np.polymul(pid_d, [1 / wl2, 1.0]), [1.0, 2 * zp * wn, wn ** 2])
    # C_r(s) = kp (b + wi/s) · wp²/(s² + 2ζ wp s + wp²)
    wp = 2 * math.pi * PREFILTER_HZ
    num_r = np.polymul(kp * np.array([B_WEIGHT, wi]), [wp ** 2])
    den_r = np.polymul([1.0, 0.0], [1.0, 2 * PREFILTER_ZETA * wp, wp ** 2])
    n_r, d_r = _tustin(num_r, den_r)
    n_y, d_y = _tustin(num_y, den_y)
    z = np.exp(1j * wc * TS)
    p = TS ** 2 / (2 * M) * (z + 1) / (z - 1) ** 2
    L = np.polyval(n_y[::-1], 1 / z) / np.polyval(d_y[::-1], 1 / z) * p / z ** DELAY
    g = 1.0 / abs(L)
    return n_r * g, d_r, n_y * g, d_y


_N_R, _D_R, _N_Y, _D_Y = _design()


def controller_paths() -> dict:
    """The controller as typed into a config: num_r/den_r (C_r), num/den (C_y), delay."""
    f = lambda p: [float(x) for x in p]
    return {"num_r": f(_N_R), "den_r": f(_D_R), "num": f(_N_Y), "den": f(_D_Y), "delay": DELAY}


def _rk4(q, v, F, u, dt, n):
    tanh = math.tanh

    def f(q_, v_, F_):
        return v_, (F_ - K_F * (q_ - Q_F) - F_V * v_ - F_C * tanh(v_ / W_C) - OF) / M, (u - F_) / TAU_A
    h2, h6 = dt / 2, dt / 6
    for _ in range(n):
        a1 = f(q, v, F)
        a2 = f(q + h2 * a1[0], v + h2 * a1[1], F + h2 * a1[2])
        a3 = f(q + h2 * a2[0], v + h2 * a2[1], F + h2 * a2[2])
        a4 = f(q + dt * a3[0], v + dt * a3[1], F + dt * a3[2])
        q += h6 * (a1[0] + 2 * a2[0] + 2 * a3[0] + a4[0])
        v += h6 * (a1[1] + 2 * a2[1] + 2 * a3[1] + a4[1])
        F += h6 * (a1[2] + 2 * a2[2] + 2 * a3[2] + a4[2])
    return q, v, F


class _Path:
    """One controller path as its own difference equation D v = N x, at rest on x0 with output v0."""

    def __init__(self, n, d, x0, v0):
        self.n, self.d = list(n), list(d)
        self.x, self.v = [x0] * len(n), [v0] * len(d)

    def step(self, x):
        self.x.insert(0, x)
        self.x.pop()
        vk = sum(a * b for a, b in zip(self.n, self.x)) - sum(self.d[i] * self.v[i - 1] for i in range(1, len(self.d)))
        self.v.insert(0, vk)
        self.v.pop()
        return vk


def simulate(r, u_ff=None, r0: float | None = None, seed: int = 0, substeps: int = SUBSTEPS) -> dict:
    """The loop from rest at r0 (default r(0)); u_ff [N] is added before the limit. Returns t, r, u, y, e, v,
    saturated (module docstring)."""
    r = np.asarray(r, dtype=np.float64)
    N = r.size
    u_ff = np.zeros(N) if u_ff is None else np.asarray(u_ff, dtype=np.float64)
    if u_ff.shape != r.shape or not np.all(np.isfinite(u_ff)):
        raise ValueError(f"u_ff must be {N} finite samples, got shape {u_ff.shape}")
    r0 = float(r[0]) if r0 is None else float(r0)
    noise = NOISE * np.random.default_rng(seed).standard_normal(N)
    f0 = static_force(r0)
    # at rest: both integrators hold their share; the path outputs differ by f0 (v = v_r - v_y = f0).
    # Static gains: C_r and C_y both integrate, so the split is free: start v_r at f0, v_y at 0 on x = r0 by
    # shifting the inputs (a path's steady state on a constant input is its integrator's value).
    pr, py = _Path(_N_R, _D_R, 0.0, f0), _Path(_N_Y, _D_Y, 0.0, 0.0)
    c_h = [f0] * (DELAY + 1)
    q, qd, F = r0, 0.0, f0
    y, u, v_out = np.empty(N), np.empty(N), np.empty(N)
    sat = 0
    dt = TS / substeps
    for k in range(N):
        yk = q + noise[k]
        vk = pr.step(float(r[k]) - r0) - py.step(yk - r0)      # both paths on deviations from r0
        ck = vk + u_ff[k]
        if abs(ck) >= U_MAX:
            sat += 1
            ck = math.copysign(U_MAX, ck)
        c_h.insert(0, ck)
        c_h.pop()
        uk = c_h[DELAY]
        y[k], u[k], v_out[k] = yk, uk, vk
        q, qd, F = _rk4(q, qd, F, uk, dt, substeps)
    return {"t": np.arange(N) * TS, "r": r.copy(), "u": u, "y": y, "e": r - y, "v": v_out, "saturated": sat}


def equation_error(r, y, u) -> float:
    """‖D_r D_y c - N_r D_y r + N_y D_r y‖ / ‖D_r D_y c‖, c(k) = u(k + DELAY) (independent of the pipeline)."""
    c = np.asarray(u, np.float64)[DELAY:]
    r, y = np.asarray(r, np.float64)[:c.size], np.asarray(y, np.float64)[:c.size]
    dd = np.polymul(_D_R, _D_Y)
    ac = signal.lfilter(dd, [1.0], c)
    bx = signal.lfilter(np.polymul(_N_R, _D_Y), [1.0], r) - signal.lfilter(np.polymul(_N_Y, _D_R), [1.0], y)
    n = dd.size
    return float(np.linalg.norm(ac[n:] - bx[n:]) / np.linalg.norm(ac[n:]))


# ---- references: cosine-bell velocity profiles (not the minimum-jerk of heldout_axis) ----------------
def _move(a: float, b: float, T: float) -> np.ndarray:
    """A move a → b in T s with a cosine-bell velocity (1 - cos) : peak speed 2 Δ/T, peak acc 2π Δ/T²."""
    s = np.arange(1, int(round(T / TS)) + 1) * TS / T
    return a + (b - a) * (s - np.sin(2 * np.pi * s) / (2 * np.pi))


def _chirp(c: float, amp: float, f0: float, f1: float, T: float) -> np.ndarray:
    t = np.arange(1, int(round(T / TS)) + 1) * TS
    x = np.clip(np.minimum(t, T - t) / 0.3, 0.0, 1.0)
    fade = x * x * (3 - 2 * x)                               # smoothstep: the acceleration stays continuous
    return c + amp * fade * signal.chirp(t, f0, T, f1, method="logarithmic", phi=-90)


def reference(start: float, segments) -> np.ndarray:
    parts, pos = [np.array([start])], start
    for seg in segments:
        if seg[0] == "move":
            parts.append(_move(pos, seg[1], seg[2]))
            pos = seg[1]
        elif seg[0] == "dwell":
            parts.append(np.full(int(round(seg[1] / TS)), pos))
        else:
            parts.append(_chirp(pos, *seg[1:]))
    return np.concatenate(parts)


TRAIN_SEGMENTS = {
    "run_a.csv": (0.0, [("dwell", 0.3), ("move", 0.02, 0.25), ("dwell", 0.2), ("move", -0.02, 0.35),
                        ("dwell", 0.2), ("move", 0.01, 0.18), ("dwell", 0.2), ("chirp", 0.004, 0.5, 12.0, 4.0),
                        ("dwell", 0.2), ("move", -0.015, 0.3), ("dwell", 0.2), ("move", 0.022, 0.5),
                        ("dwell", 0.3)]),
    "run_b.csv": (-0.01, [("dwell", 0.3), ("move", 0.018, 0.3), ("dwell", 0.2), ("move", -0.022, 0.22),
                          ("dwell", 0.2), ("chirp", 0.012, 0.3, 6.0, 4.0), ("dwell", 0.2), ("move", 0.005, 0.15),
                          ("dwell", 0.2), ("move", -0.012, 0.4), ("dwell", 0.3)]),
}
TEST_SEGMENTS = (TEST_R0, [("dwell", 0.5), ("move", 0.015, 0.3), ("dwell", 0.3), ("move", -0.018, 0.35),
                           ("dwell", 0.3), ("chirp", 0.006, 1.0, 8.0, 2.5), ("dwell", 0.3), ("move", 0.0, 0.25)])


def eval_reference() -> np.ndarray:
    r = reference(*TEST_SEGMENTS)
    n = int(round(TEST_SECONDS / TS))
    if r.size > n:
        raise AssertionError(f"the test segments last {r.size * TS} s > {TEST_SECONDS} s")
    return np.concatenate([r, np.full(n - r.size, r[-1])])


def write_recording(path: Path, rec: dict) -> None:
    path = Path(path)
    np.savetxt(path, np.column_stack([rec["t"], rec["r"], rec["u"], rec["y"]]), delimiter=",",
               header="t,r,u,y", comments="", fmt="%.17g")
    Path(f"{path}.json").write_text(json.dumps({"Ts": TS}))


def training_recordings(folder, seed: int = 11) -> dict:
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
    import time
    r = eval_reference()
    t0 = time.process_time()
    rec = simulate(r)
    t1 = time.process_time()
    ref = simulate(r, substeps=16)
    print(f"test reference: {r.size} samples, simulate {t1 - t0:.2f} s CPU; MAE {1e6 * np.mean(np.abs(rec['e'])):.3f}"
          f" µm, max |u| {np.abs(rec['u']).max():.2f} N, saturated {rec['saturated']}; RK4 vs 16 sub-steps max |Δy| "
          f"{np.abs(rec['y'] - ref['y']).max():.2e} m; equation error "
          f"{equation_error(rec['r'], rec['y'], rec['u']):.2e}")
    rest = simulate(np.full(4000, TEST_R0))
    print(f"at rest at {TEST_R0} m: max |e| {np.abs(rest['e']).max() * 1e9:.1f} nm, u {rest['u'].mean():.6f} N "
          f"(static {static_force(TEST_R0):.6f} N)")
    for name, (start, segs) in TRAIN_SEGMENTS.items():
        rr = reference(start, segs)
        v, a = np.diff(rr) / TS, np.diff(rr, 2) / TS ** 2
        print(f"{name}: {rr.size} samples, |v| ≤ {np.abs(v).max():.3f} m/s, |a| ≤ {np.abs(a).max():.2f} m/s²")
    v, a = np.diff(r) / TS, np.diff(r, 2) / TS ** 2
    print(f"test: |v| ≤ {np.abs(v).max():.3f} m/s, |a| ≤ {np.abs(a).max():.2f} m/s²")


if __name__ == "__main__":
    _selfcheck()
