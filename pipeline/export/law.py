"""A feedforward law as flat data: the one description the C code, the MLflow model and the
manifest are generated from (issue 12).

A :class:`Law` holds what a per-sample implementation needs and nothing else: integer sizes,
float constants and float arrays (the same flat arrays the numba kernels run on, see
:func:`pipeline.models.pgnn.fast_pgnn`), plus the sample time and how the law meets the
reference:

- ``preview`` P: the step at time t reads r(t), …, r(t+P) (the direct inverse needs
  r(t+n_k+1), [B1] (13); an averaged model input needs one sample more, SPEC §2.2);
- ``rest``: before t = 0 the reference was at rest at ``'zero'`` or at its ``'first'`` sample
  (the study's conventions: the [K] filters and the physics law (8) start from r = 0, the PGNN
  inversions hold r(0), ``padded_reference``); after its end it is held at the last sample.

Families (``family``):

- ``pgnn``: physics (8), direct inverse (13)-(14), analytic (27), Newton ([B1] Alg. 1) on the
  ``blob``/``meta`` arrays of ``fast_pgnn``;
- ``k_filter``: the rational filter and the shared-AR PGNN of [K] (6):
  f = (A(r) + g_φ(r)) / B(q), run as ``scipy.signal.lfilter`` runs it (direct form II transposed);
- ``table``: FHOFC / IL-FHOFC ([B2] (17)), a signal optimised offline for one known reference;
- ``rigid_body``: the physics feedforward of a measured system (issue 20): the analytic inverse of
  :class:`~pipeline.systems.measured.RigidBodyPhysics` (its force terms) minus the known
  controller's reference force (C_r - C_y) r (``LTIController.reference_force``).

:func:`feedforward` evaluates a law in Python with the study's own kernels and classes (the
numba inversions, :class:`~pipeline.models.shared_ar.SharedARPGNN`), so the MLflow model returns
the study's numbers.  Stored as ``law.json`` + ``law.npz`` (no pickle: loading runs no code).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import ExportError
from pipeline.export.guard import FLAG, Guard, run_guard
from pipeline.systems.controller import LTIController, advanced_reference

__all__ = ["Law", "ExportError", "LAWS", "guarded", "from_pgnn", "controller_fields", "advanced_reference",
           "from_linear_motor_physics", "from_measured_physics", "from_k_filter", "from_table", "feedforward"]

#: every law the exporter covers, by ``invert.kind``
LAWS = ("physics", "direct", "analytic", "newton", "rational_filter", "fhofc", "il_fhofc")
_FAMILY = {"physics": "pgnn", "direct": "pgnn", "analytic": "pgnn", "newton": "pgnn",
           "rational_filter": "k_filter", "fhofc": "table", "il_fhofc": "table"}
# numba kernel layout of fast_pgnn's meta (pipeline.models.pgnn.FastPGNN)
_META = ("kind", "p", "H", "n_phi", "u_index", "use_phys", "use_nn", "n_a", "n_b", "n_k", "n_cfg")


@dataclass
class Law:
    """A feedforward law as sizes, constants and arrays (module docstring)."""

    law: str                      # invert.kind
    family: str                   # pgnn | k_filter | table | rigid_body
    Ts: float                     # sample time [s]
    preview: int                  # the step at t reads r(t) … r(t+preview)
    rest: str                     # 'zero' | 'first': the reference before t = 0
    averaged: bool = False        # u(t) = (w(t) + w(t+1))/2 of the model input w (SPEC §2.2)
    ints: dict = field(default_factory=dict)
    floats: dict = field(default_factory=dict)
    arrays: dict = field(default_factory=dict)
    strings: dict = field(default_factory=dict)
    units: dict = field(default_factory=lambda: {"r": "m", "u_ff": "N"})
    guard: dict = field(default_factory=dict)   # limits, envelope, fallback (pipeline.export.guard.Guard)
    start: str = "study"          # 'study': rest as above | 'rest': every state at rest at r0 (pipeline.invert.start)
    static: str = "include"       # 'include': u_ff(0) = the law at rest at r0 | 'exclude': that constant taken off
    settle: int = 0               # start 'rest': rest samples the law runs at init (+1) to reach its steady state

    def __post_init__(self):
        if self.law not in LAWS:
            raise ExportError(f"unknown feedforward law {self.law!r}; the exporter covers {list(LAWS)}")
        if self.rest not in ("zero", "first"):
            raise ExportError(f"rest must be 'zero' or 'first', got {self.rest!r}")
        if self.start not in ("study", "rest") or self.static not in ("include", "exclude") or self.settle < 0:
            raise ExportError(f"start must be 'study' or 'rest', static 'include' or 'exclude', settle >= 0; got "
                              f"{self.start!r}, {self.static!r}, {self.settle}")
        if self.static == "exclude" and self.start != "rest":
            raise ExportError("static 'exclude' takes the force at rest at r0 off: it needs start 'rest'")
        if self.start == "rest" and self.family == "table":
            raise ExportError("a table replays a signal optimised for one reference: it has no rest to start from")
        for k, a in self.arrays.items():
            a = np.ascontiguousarray(a, dtype=np.float64) if np.asarray(a).dtype.kind == "f" \
                else np.ascontiguousarray(a)
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                raise ExportError(f"law array {k!r} holds NaN/inf: the model is not usable")
            self.arrays[k] = a
        self.guard = asdict(Guard(**self.guard))   # checked; "inf" strings of law.json read back as floats

    @property
    def g(self) -> Guard:
        return Guard(**self.guard)

    def start_doc(self) -> dict:
        """What the law assumes before t = 0 and what it gives at switch-on (manifest ``start``, README)."""
        if self.start == "rest":
            at = (f"init(&s, r0) puts every state at rest at r0 (the axis standing there, the loop running): it "
                  f"runs the law {self.settle + 1} sample(s) on a reference held at r0; pass r0 = r(0), where the "
                  "axis stands")
            u0 = ("0 N: the force at rest at r0 (gravity, springs, offsets, the controller's rest output) is taken "
                  "off every sample, because the loop's integrator already holds it at switch-on"
                  if self.static == "exclude" else
                  "the law's force at rest at r0 (gravity, springs, offsets minus the controller's rest output): "
                  "right when the feedforward is on from power-up, before any integrator holds the load")
        elif self.family == "table":
            at = ("a table for one reference, sample k its output at the k-th call after init: init(&s, r(0)) at "
                  "switch-on, the axis at rest at r(0), where the table's reference starts (the table was made, or "
                  "learned on the machine, from there); r(t) away from that reference is flagged OTHER_REFERENCE")
            u0 = "the table's first sample"
        else:
            r0 = "0" if self.rest == "zero" else "r(0)"
            at = (f"the papers' convention: the reference at rest at {r0} before t = 0 and past inputs 0 (the study's "
                  f"references start at 0); init(&s, {r0}) reproduces the study; init at another position gives a "
                  "start transient: re-export with start.at=rest for a machine that starts where it stands")
            u0 = "the law's first sample as the study computed it"
        at += "; call init once, at switch-on (a re-init resets the output's slew history)"
        return {"at": "rest" if self.start == "rest" else "zero", "static": self.static,
                "settle_samples": self.settle, "init": at, "u_ff_at_switch_on": u0}

    # ---- storage (json + npz: nothing executes on load) -----------------------------------
    def save(self, folder: Path) -> None:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        meta = {k: v for k, v in asdict(self).items() if k != "arrays"}
        (folder / "law.json").write_text(strict_json(meta))
        np.savez(folder / "law.npz", **self.arrays)

    @classmethod
    def load(cls, folder: Path) -> "Law":
        folder = Path(folder)
        for f in ("law.json", "law.npz"):
            if not (folder / f).is_file():
                raise ExportError(f"{folder} has no {f}: not an exported feedforward law")
        meta = json.loads((folder / "law.json").read_text())
        meta["floats"] = {k: float(v) for k, v in meta.get("floats", {}).items()}
        with np.load(folder / "law.npz", allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        return cls(arrays=arrays, **meta)

    # ---- figures of the manifest ------------------------------------------------------------
    @property
    def n_params(self) -> int:
        """Number of model parameters the law carries (weights, coefficients; table: samples)."""
        if self.family == "pgnn":
            m = self.ints
            return int(m["p"] + (m["H"] * (m["n_phi"] + 2) + 1 if m["use_nn"] else 0)
                       + (2 * m["n_den"] if m.get("has_ctrl") else 0))
        if self.family == "k_filter":
            return int(sum(self.arrays[k].size for k in self.arrays if k.startswith(("g_W", "g_b")))
                       + self.ints["n_a"] + self.ints["n_b"])
        if self.family == "rigid_body":
            return int(self.arrays["theta"].size + (2 * self.ints["n_den"] if self.ints["has_ctrl"] else 0))
        return int(self.arrays["u"].size)

    def flops_per_sample(self) -> dict:
        """Floating-point operations per sample (multiply and add counted apart) and elementary
        function calls (tanh/exp/log), worst case (Newton: every update runs)."""
        if self.family == "pgnn":
            m = self.ints
            nn = 2 * m["H"] * m["n_phi"] + 5 * m["H"] + 1 if m["use_nn"] else 0   # W φ + b, w2 h, (1 - h²)
            evals = {"newton": self.ints.get("k", 0) + 1}.get(self.law, 1)
            phys = {0: 2 * m["n_phi"], 1: 14, 2: 12, 3: 9 + 5 * (m["n_cfg"] - 2) // 2,
                    4: 7 + 2 * (m["n_cfg"] - 2) // 2}.get(m["kind"], 0)
            flops = evals * (nn + 4) + 2 * phys + (3 if self.averaged else 0)
            flops += 4 * m["n_den"] + 2 if m.get("has_ctrl") else 0          # the controller term, as rigid_body
            calls = evals * m["H"] * int(bool(m["use_nn"]))
            if m["kind"] in (3, 4):     # the force terms' tanh/exp/cos/sin (the blob's cfg: Ts, n, codes, consts)
                cfg = self.arrays["blob"][self.arrays["blob"].size - m["n_cfg"]:]
                calls += 2 * sum(int(c) in (2, 3, 5, 6) for c in cfg[2:2 + int(cfg[1])])
            return {"flops": int(flops), "elementary_calls": int(calls)}
        if self.family == "k_filter":
            i = self.ints
            flops = 2 * (i["n_a"] + i["d_a"] + i["d_w"]) + 2 * 3 * (i["n_b"] + 1)
            calls = 0
            if i["has_g"]:
                widths = [i["n_window"]] + [self.arrays[f"g_W{j}"].shape[0] for j in range(i["n_layers"])]
                flops += 2 * (i["n_window"]) + sum(2 * a * b for a, b in zip(widths[:-1], widths[1:])) + 1
                calls = sum(widths[1:-1])
            return {"flops": int(flops), "elementary_calls": int(calls)}
        if self.family == "rigid_body":
            codes = self.arrays["codes"]
            per = {0: 0, 1: 0, 2: 1, 3: 5, 4: 0, 5: 1, 6: 1, 7: 1}  # T_j beyond the velocity; (q/p)^k: k
            w = 7 + 2 * codes.size + sum(per.get(int(c), int(c) - 7) for c in codes)
            calls = int(sum(int(c) in (2, 3, 5, 6) for c in codes))
            flops = (2 if self.averaged else 1) * w + (3 if self.averaged else 0)
            flops += 6 if "lag_tau" in self.floats else 0       # the actuator lag's inverse
            calls *= 2 if self.averaged else 1
            if self.ints["has_ctrl"]:
                flops += 4 * self.ints["n_den"] + 2
            return {"flops": int(flops), "elementary_calls": calls}
        return {"flops": 0, "elementary_calls": 0}


def _json_float(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(f"cannot store {type(x).__name__} in law.json")


def strict_json(obj) -> str:
    """JSON that strict parsers read (RFC 8259 has no Infinity/NaN): a non-finite number is written
    as the string "inf", "-inf" or "nan" (``float()`` reads each back)."""
    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, (float, np.floating)) and not math.isfinite(x):
            return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
        return x
    return json.dumps(clean(obj), indent=1, default=_json_float, allow_nan=False)


# --------------------------------------------------------------------------------------------
# builders
# --------------------------------------------------------------------------------------------
def from_pgnn(model, law: str, Ts: float, *, averaged: bool = False, k: int = 5,
              u_bounds=(-math.inf, math.inf), theta_start=None, ctrl=None) -> Law:
    """The [B1] inversion ``law`` (direct | analytic | newton | physics) of a PGNN, from the
    flat arrays of :func:`~pipeline.models.pgnn.fast_pgnn` (the numba kernels' own data); an averaged
    input of a physics with an actuator lag is inverted with the lag (pipeline.systems.actuator_lag). ``ctrl``: the
    known controller of a measured axis, whose force on y = r, (C_r - C_y) r, the law subtracts
    (:func:`controller_fields`; the invert stage's u_ff on a measured system, issue 49)."""
    from pipeline.models.fast_pgnn import fast_pgnn  # lazy: saves 2.2 s of start-up (torch, numba kernels)
    if law not in ("direct", "analytic", "newton", "physics"):
        raise ExportError(f"a PGNN is exported by law direct | analytic | newton | physics, not {law!r}")
    fm = fast_pgnn(model, theta_start=theta_start)
    if fm is not None and fm.meta[0] > 4:   # the C kernel knows the kinds 0-4 (templates/pgnn.c)
        fm = None
    if fm is None:
        phys = type(model.physics).__name__ if model.use_physics else "none"
        raise ExportError(
            f"the exporter supports a PGNN with no NN or one tanh hidden layer and a built-in physics "
            f"map (LinearFeatures, RigidBodyForward, RigidBodyInverse, a measured rigid body with force terms on its "
            f"direct input); this model has hidden="
            f"{list(model.hidden)}, activation={model.activation}, physics={phys}: use model.hidden=[H] "
            "with model.activation=tanh, or keep the Python feedforward")
    need = {"direct": ("inverse",), "analytic": ("invertible", "forward"),
            "newton": ("forward", "invertible"), "physics": ("forward", "invertible", "inverse")}[law]
    if fm.structure not in need:
        raise ExportError(f"law {law} needs a PGNN of structure {need}, got {fm.structure!r}")
    if law == "analytic" and not model.analytically_invertible:   # [B1] (26): the NN is blind to u(t-n_k-1)
        raise ExportError("law analytic needs an invertible PGNN ([B1] (26)) or a physics-only forward model; "
                          "export a forward PGNN with law newton")
    ints = {name: int(v) for name, v in zip(_META, fm.meta)}
    ints["inverse_layout"] = int(fm.structure == "inverse")
    floats = {}
    if law == "newton":
        if int(k) != k or k < 0:
            raise ExportError(f"Newton needs a non-negative integer k, got {k}")
        ints["k"] = int(k)
        floats = {"u_min": float(u_bounds[0]), "u_max": float(u_bounds[1])}
    if averaged and model.use_physics:
        floats.update(_lag_floats(getattr(model.physics, "pm", model.physics)))
    arrays, strings = {"blob": fm.blob}, {"structure": fm.structure,
                                          "model": "physics" if law == "physics" else f"pgnn-{fm.structure}"}
    if ctrl is not None:      # a measured axis: minus gtau (C_r - C_y) r (none of these keys on the simulators)
        c_ints, c_floats, c_arrays = controller_fields(ctrl)
        ints.update(c_ints)
        floats.update(c_floats)
        arrays.update(c_arrays)
        strings["controller"] = ctrl.structure
    return Law(law=law, family="pgnn", Ts=float(Ts), preview=fm.n_k + 1 + int(averaged) + ints.get("advance", 0),
               rest="zero" if law == "physics" and fm.structure == "inverse" else "first",
               averaged=bool(averaged), ints=ints, floats=floats, arrays=arrays, strings=strings)


def controller_fields(ctrl) -> tuple[dict, dict, dict]:
    """(ints, floats, arrays) of the known controller's force on y = r, gtau (C_r - C_y) r
    (``LTIController.reference_force``), that a measured axis's law subtracts: B_r, B_y, A and the filter
    (B_r - B_y)/A normalised as ``lfilter`` normalises it, its rest gain K0 per metre (start 'rest')."""
    db, den = ctrl.reference_filter()
    has_ctrl = bool(np.any(db))
    try:
        k0 = ctrl.rest_gain() if has_ctrl else 0.0      # the controller term's rest value per metre (start 'rest')
    except ValueError:
        k0 = 0.0                                         # no rest away from 0: start 'rest' is refused upstream
    # advance D: the controller's computational delay, u = gtau (sat(v + u_ff/gtau)(k - D) + d): u_ff(k) reaches
    # the plant at k + D, so the model's force is that of r(k + D) (advanced_reference); its term on r(k) is not
    return ({"has_ctrl": int(has_ctrl), "n_den": int(den.size), "advance": int(ctrl.delay)},
            {"gtau": float(ctrl.gtau), "k0": float(k0)},
            {"b_r": ctrl.b_r, "b_y": ctrl.b_y, "a": ctrl.a,
             "num": db / den[0], "den": den / den[0]})     # lfilter divides by den[0] first


def from_linear_motor_physics(physics, theta) -> Law:
    """The physics feedforward (8) of the linear motor, w(k) = m δ²r(k+1) + f_v δr(k) +
    f_c sign δr(k) with r(-1) = 0 (``LinearMotorPhysics.feedforward``), as the physics part of
    an inverse PGNN (the same numba kernel)."""
    from pipeline.models.pgnn import PGNN  # lazy: saves 2.7 s of start-up (torch, numba kernels)
    from pipeline.models.physics_maps import RigidBodyInverse  # lazy: saves 1.8 s of start-up (torch)
    if physics.physics_law != "linear_motor":
        raise ExportError(f"the exporter ships the physics feedforward (8) of the linear motor "
                          f"(LinearMotorPhysics); this system's physics is {type(physics).__name__}")
    model = PGNN(2, 1, 0, structure="inverse", physics=RigidBodyInverse(physics.Ts), use_nn=False)
    model.set_physics_estimate(physics.inverse_theta(theta))
    return from_pgnn(model, "physics", physics.Ts, averaged=bool(physics.averaged_input))


def from_measured_physics(physics, theta, ctrl) -> Law:
    """The physics feedforward of a measured system (``invert.kind=physics`` on a
    :class:`~pipeline.systems.measured.Recording`): u_ff = ``physics.feedforward(theta, r)`` -
    ``ctrl.reference_force(r)``, i.e. w(k) = θ'ᵀ [δ²r(k+1), T_1(r(k), δr(k)), …] with r(-1) = 0, the
    applied input of w (identity or averaged), minus gtau · lfilter(B_r - B_y, A, r) from rest."""
    if physics.physics_law != "rigid_body":
        raise ExportError(f"the measured-system physics feedforward is exported for RigidBodyPhysics; "
                          f"this system's physics is {type(physics).__name__}")
    theta = physics._check_theta(theta)
    codes, consts = physics.terms.kernel()
    t = physics.terms
    c_ints, c_floats, c_arrays = controller_fields(ctrl)
    return Law(law="physics", family="rigid_body", Ts=float(physics.Ts),
               preview=1 + int(physics.averaged_input) + c_ints["advance"],
               rest="zero", averaged=bool(physics.averaged_input),
               ints={"n_terms": int(codes.size), **c_ints, "cogging_harmonics": int(t.cogging_harmonics),
                     "position_order": int(t.position_order)},
               floats={**c_floats, "stribeck_velocity": float(t.stribeck_velocity),
                       "coulomb_width": 0.0 if t.coulomb_width is None else float(t.coulomb_width),
                       "cogging_period": 0.0 if t.cogging_period is None else float(t.cogging_period),
                       "position_scale": 0.0 if t.position_scale is None else float(t.position_scale),
                       **_lag_floats(physics)},
               arrays={"theta": theta, "theta_inv": physics.inverse_theta(theta), "codes": codes,
                       "consts": consts, **c_arrays},
               strings={"model": "physics-measured", "terms": ",".join(t.names), "controller": ctrl.structure})


def _lag_floats(physics) -> dict:
    """{"lag_tau": τ} of a physics with an actuator lag (its inverse replaces the averaged input's), else {}."""
    lag = getattr(physics, "lag", None) or getattr(physics, "input_lag", None)   # input_lag: a PGNN's map on w
    return {} if lag is None else {"lag_tau": float(lag.tau)}


def lag_of(law: Law):
    """The law's actuator lag (:class:`pipeline.systems.actuator_lag.ActuatorLag`) or None."""
    if "lag_tau" not in law.floats:
        return None
    if not law.averaged:
        raise ExportError("an actuator lag's inverse replaces the averaged input's: a corrupted law")
    from pipeline.systems.actuator_lag import ActuatorLag  # lazy: saves 0.3 s of start-up (scipy.signal)
    return ActuatorLag(law.floats["lag_tau"], law.Ts)


def _applied(law: Law, w: np.ndarray) -> np.ndarray:
    """u(0 .. N-1) of the law's w(0 .. N): (w(t) + w(t+1))/2, or the actuator lag's inverse (actuator_lag)."""
    lag = lag_of(law)
    if lag is None:
        return 0.5 * (w[:-1] + w[1:])
    return lag.applied_input(w[:-1], w[-1])


def from_k_filter(model, law: str = "rational_filter") -> Law:
    """The [K] filter f = (A(r) + g_φ(r))/B(q) of a :class:`RationalFeedforward` or
    :class:`SharedARPGNN` (MLP approximator), with B normalised as ``lfilter`` normalises it."""
    from torch import nn  # lazy: saves 1.8 s of start-up (torch)

    from pipeline.models.shared_ar import MLP, SharedARPGNN  # lazy: saves 3.8 s of start-up (torch, scipy.signal)
    model.check_stable()
    den = model.denominator()
    num = np.zeros_like(den)
    num[0] = 1.0
    arrays = {"a": model.a.detach().numpy().copy(), "b": model.b.detach().numpy().copy(),
              "num": num / den[0], "den": den / den[0]}   # lfilter divides by den[0] first
    ints = {"n_a": model.n_a, "n_b": model.n_b, "basis_delta": int(model.basis == "delta"),
            "d_a": max(model.n_a - 1, 0), "has_g": 0, "d_w": 0, "n_window": 0, "n_layers": 0,
            "window_delta": 0, "out_bias": 0}
    strings = {"model": type(model).__name__, "basis": model.basis, "activation": ""}
    floats = {"g_gain": 1.0}
    if isinstance(model, SharedARPGNN):
        g = model.g
        if not isinstance(g, MLP):
            raise ExportError(f"the exporter supports the MLP approximator of [K] (4) "
                              f"(model.approximator=mlp); this model's g_φ is {type(g).__name__}")
        linear = [m for m in g.net if isinstance(m, nn.Linear)]
        acts = {type(m).__name__.lower() for m in g.net if not isinstance(m, nn.Linear)}
        if len(acts) > 1 or not acts <= {"tanh", "relu", "sigmoid", "softplus"}:
            raise ExportError(f"approximator activations {sorted(acts)} are not supported; "
                              "supported: tanh, relu, sigmoid, softplus")
        w = model.window
        ints.update(has_g=1, d_w=w.q, n_window=w.q + 1, n_layers=len(linear),
                    window_delta=int(w.basis == "delta"), out_bias=int(linear[-1].bias is not None))
        strings["activation"] = acts.pop() if acts else "tanh"
        floats["g_gain"] = float(model.g_gain)
        arrays["w_mean"] = w.mean.numpy().copy()
        arrays["w_std"] = w.std.numpy().copy()
        for j, lin in enumerate(linear):
            arrays[f"g_W{j}"] = lin.weight.detach().numpy().copy()
            arrays[f"g_b{j}"] = (lin.bias.detach().numpy().copy() if lin.bias is not None
                                 else np.zeros(lin.weight.shape[0]))
        strings["window_basis"] = w.basis
        strings["normalisation"] = w.normalisation
        floats["window_Ts"] = w.Ts
    return Law(law=law, family="k_filter", Ts=float(model.Ts), preview=0, rest="zero",
               ints=ints, floats=floats, arrays=arrays, strings=strings)


def from_table(law: str, Ts: float, r, u) -> Law:
    """An FHOFC / IL-FHOFC signal u [N] optimised offline for the one reference r [N]."""
    r, u = np.asarray(r, dtype=np.float64), np.asarray(u, dtype=np.float64)
    if r.ndim != 1 or r.shape != u.shape:
        raise ExportError(f"a table needs a reference and a signal of one length, got {r.shape} and {u.shape}")
    return Law(law=law, family="table", Ts=float(Ts), preview=0, rest="first",
               ints={"n": int(r.size)}, floats={"r_tol": 1e-9 * float(np.max(np.abs(r)) or 1.0)},
               arrays={"r": r, "u": u})


# --------------------------------------------------------------------------------------------
# Python evaluation with the study's kernels
# --------------------------------------------------------------------------------------------
def padded(law: Law, r: np.ndarray, n_before: int, n_after: int) -> np.ndarray:
    """r with ``n_before`` samples of rest before t = 0 (0 or r(0), ``law.rest``) and
    ``n_after`` samples held at r(N-1) after the end."""
    r0 = 0.0 if law.rest == "zero" else r[0]
    return np.concatenate([np.full(n_before, r0), r, np.full(n_after, r[-1])])


def feedforward(law: Law, r) -> np.ndarray:
    """u_ff [N] of ``law`` on the reference r [N] (the study's kernels), unguarded: NaN/inf in r and,
    for a table, another reference are errors (:func:`guarded` flags them and falls back)."""
    r = _check_reference(r)
    if not np.all(np.isfinite(r)):
        raise ExportError(f"the reference holds NaN/inf (first at sample {int(np.flatnonzero(~np.isfinite(r))[0])})")
    if law.family == "table":
        R = law.arrays["r"]
        if r.shape != R.shape or np.max(np.abs(r - R)) > law.floats["r_tol"]:
            raise ExportError(f"this {law.law} signal was optimised offline for one reference of "
                              f"{R.size} samples; the given reference ({r.size} samples) differs from it")
    return _started(law, r, start_position(law, r))[0]


def guarded(law: Law, r) -> tuple[np.ndarray, np.ndarray]:
    """(u_ff [N], flags [N]) of ``law`` with its guard (:mod:`pipeline.export.guard`): what the C
    ``<prefix>_step`` returns and leaves in ``s->status``, sample for sample, after ``<prefix>_init(&s, r0)``
    with r0 = :func:`start_position`. On a clean reference inside the limits u_ff is :func:`feedforward`'s to
    the bit."""
    r = _check_reference(r)
    r0 = start_position(law, r)
    r0 = r0 if math.isfinite(r0) else 0.0
    g = law.g
    u_start = min(max(_rest_value(law, r0)[1], g.u_min), g.u_max)   # inside the limits, as the C's init clamps it
    return run_guard(g, law.Ts, law.preview, r, r0, lambda r_c: _started(law, r_c, r0), u_start=u_start)


def start_position(law: Law, r) -> float:
    """The r0 of ``<prefix>_init(&s, r0)`` that reproduces the study: r(0), or 0 for a law the study ran from
    r = 0 (``rest == 'zero'`` with start 'study')."""
    return 0.0 if (law.start == "study" and law.rest == "zero") else float(np.asarray(r, dtype=np.float64)[0])


def _rest_value(law: Law, r0: float) -> tuple[float, float]:
    """(u_rest, u_start): the law at rest at r0 (its last sample on [r0] × (settle + 1), the C's last warm-up
    step at init) and what the guard takes as the previous output at t = 0 (u_rest, 0 when excluded; 0 for
    start 'study', the actuator at rest)."""
    if law.start != "rest":
        return 0.0, 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        u_rest = float(_core(law, np.full(law.settle + 1, r0))[0][-1])
    if not math.isfinite(u_rest):     # an absurd r0 overflowed the law: nothing to take off; its samples fall back
        u_rest = 0.0
    return u_rest, (0.0 if law.static == "exclude" else u_rest)


def _started(law: Law, r: np.ndarray, r0: float) -> tuple[np.ndarray, np.ndarray]:
    """(u_ff, flags) of the law started as ``law.start`` says (pipeline.invert.start): for 'rest' the law runs
    on [r0] × (settle + 1) + r, the rest samples dropped, the force at rest taken off when excluded."""
    if law.start != "rest":
        return _core(law, r)
    n = law.settle + 1
    if law.family == "pgnn" and law.ints["n_b"] > 1:
        # a past-input recursion: its history is the C's after init, n steps whose preview is r0 only (a padded
        # run's last rest steps would see the motion coming, which init cannot), then the reference from r(0)
        kept: list = []
        _core(law, np.full(n, r0), keep=kept)
        n_y = law.ints["n_a"] + 1
        u, f = _core(law, r, u_past=kept[0][n_y:n_y + law.ints["n_b"]].copy(), r0=r0)
    else:
        u, f = _core(law, np.concatenate([np.full(n, r0), r]))
        u, f = u[n:], f[n:]
    if law.static == "exclude":
        u = u - _rest_value(law, r0)[0]
    return u, f


def _check_reference(r) -> np.ndarray:
    r = np.asarray(r, dtype=np.float64)
    if r.ndim != 1 or r.size < 1:
        raise ExportError(f"the reference must be a non-empty 1-D signal, got shape {r.shape}")
    return r


def _core(law: Law, r: np.ndarray, r0: float | None = None, **pgnn) -> tuple[np.ndarray, np.ndarray]:
    """(u_ff, the law's own flags) on a finite reference r, as the C law_step computes them (``pgnn``: the
    input history before t = 0 and the state's receiver, :func:`_pgnn_run`; ``r0``: where the controller term
    starts at rest, default r(0) for start 'rest')."""
    r0 = (float(r[0]) if law.start == "rest" else 0.0) if r0 is None else r0
    N = r.size
    if law.family == "table":
        R, U, n = law.arrays["r"], law.arrays["u"], law.ints["n"]
        k = np.arange(N)
        inside = k < n
        kk = np.minimum(k, n - 1)
        other = inside & ~(np.abs(r - R[kk]) <= law.floats["r_tol"])
        flags = np.where(other, FLAG["OTHER_REFERENCE"], 0) | np.where(inside, 0, FLAG["PAST_END"])
        return U[kk].copy(), flags
    if law.family in ("k_filter", "rigid_body"):
        if law.family == "k_filter":
            from pipeline.invert.rational_filter import (  # lazy: saves 3.4 s of start-up (torch, scipy.signal)
                rational_feedforward,
            )
            u = rational_feedforward(_k_model(law), r).f
        else:
            physics = _rigid_body(law)   # feedforward's w, its overflow kept (applied_input refuses it)
            w = physics.inverse_force(law.arrays["theta"], advanced_reference(r, law.ints.get("advance", 0)))
            with np.errstate(over="ignore", invalid="ignore"):
                u = (_applied(law, w) if law.averaged else w[:-1]) - _controller_force(law, r, r0)
        return u, np.where(np.isfinite(u), 0, FLAG["SINGULAR"])
    rf = advanced_reference(r, law.ints.get("advance", 0))      # the model's force: of r(k + D)
    w, f = _pgnn_run(law, np.append(rf, rf[-1]) if law.averaged else rf, **pgnn)
    f = f | np.where(np.isfinite(w), 0, FLAG["SINGULAR"])    # an overflow: kept, the guard falls back
    if law.averaged:
        flags = f[1:].copy()          # step t runs w(t+1); the first also w(0)
        flags[0] |= f[0]
        w, f = _applied(law, w), flags
    if "gtau" not in law.floats:      # no controller term (a simulator's law)
        return w, f
    with np.errstate(over="ignore", invalid="ignore"):
        u = w - _controller_force(law, r, r0)      # a measured axis: minus gtau (C_r - C_y) r, as stages/invert
    return u, f | np.where(np.isfinite(u), 0, FLAG["SINGULAR"])


def _controller_force(law: Law, r: np.ndarray, r0: float) -> np.ndarray:
    """gtau (C_r - C_y) r from rest at r0 (``LTIController.reference_force``, the study's class) of the law's
    controller (:func:`controller_fields`)."""
    a = law.arrays
    return LTIController(a["b_r"], a["b_y"], a["a"], law.floats["gtau"]).reference_force(r, r0)


def _pgnn_run(law: Law, r: np.ndarray, u_past=None, keep: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(w, flags): the numba kernels' w(t) (Newton's per-sample flags; the other laws raise none here); ``u_past``:
    the input history before t = 0 (default 0), ``keep``: receives the kernel state after the run."""
    from pipeline.invert.analytic import _run  # lazy: saves 2.8 s of start-up (torch, numba kernels)
    from pipeline.invert.direct import (  # lazy: saves 2.5 s of start-up (torch, numba kernels)
        _direct_run,
        initial_state,
    )
    from pipeline.invert.newton import _newton_run  # lazy: saves 3.6 s of start-up (torch, numba kernels)
    from pipeline.models.fast_pgnn import FastPGNN  # lazy: saves 3.1 s of start-up (torch, numba kernels)
    m = law.ints
    blob = law.arrays["blob"]
    meta = np.array([m[k] for k in _META], dtype=np.int64)
    fm = FastPGNN(blob, meta, law.strings["structure"], m["n_a"], m["n_b"], m["n_k"])
    r_ext = padded(law, r, m["n_a"], m["n_k"] + 1)
    state = initial_state(fm, r_ext)
    if u_past is not None:            # state[n_y .. n_y + n_b): u(t-1), u(t-2), ... (fast_push_input)
        state[m["n_a"] + 1:m["n_a"] + 1 + m["n_b"]] = u_past
    if keep is not None:
        keep.append(state)            # the kernels advance it in place
    N = r.size
    none = np.zeros(N, dtype=np.int64)
    if law.law == "direct":
        return _direct_run(blob, meta, state, r_ext, N), none
    if law.law == "newton":
        u, _, flags, _ = _newton_run(blob, meta, state, r_ext, N, m["k"], law.floats["u_min"], law.floats["u_max"])
        return u, flags.astype(np.int64)
    return _run(blob, meta, state, r_ext, N, law.law == "physics", bool(m["inverse_layout"])), none


def _rigid_body(law: Law):
    """The RigidBodyPhysics rebuilt from the law (the study's class)."""
    from pipeline.systems.force_terms import ForceTerms  # lazy: saves 0.6 s of start-up (numba kernels)
    from pipeline.systems.measured import RigidBodyPhysics  # lazy: saves 0.6 s of start-up (numba kernels)
    f = law.floats
    terms = ForceTerms(tuple(law.strings["terms"].split(",")) if law.strings["terms"] else (),
                       coulomb_width=f["coulomb_width"] or None, stribeck_velocity=f["stribeck_velocity"],
                       cogging_period=f["cogging_period"] or None,
                       cogging_harmonics=law.ints["cogging_harmonics"],
                       position_order=law.ints.get("position_order", 3),
                       position_scale=f.get("position_scale", 0.0) or None)
    physics = RigidBodyPhysics(law.Ts, averaged_input=law.averaged, terms=terms, lag=lag_of(law))
    a = law.arrays
    if not (np.array_equal(terms.kernel()[0], a["codes"]) and np.array_equal(terms.kernel()[1], a["consts"])):
        raise ExportError("the law's force terms do not match its kernel codes: a corrupted law")
    return physics


def _k_model(law: Law):
    """The [K] model rebuilt from the law's arrays (the study's class, so the study's numbers)."""
    import torch  # lazy: saves 2.0 s of start-up (torch)

    from pipeline.models.rational import RationalFeedforward  # lazy: saves 2.6 s of start-up (torch, scipy.signal)
    from pipeline.models.shared_ar import (  # lazy: saves 3.8 s of start-up (torch, scipy.signal)
        MLP,
        ReferenceWindow,
        SharedARPGNN,
    )
    i, a = law.ints, law.arrays
    basis, b = law.strings["basis"], a["b"]
    if not i["has_g"]:
        return RationalFeedforward(i["n_a"], i["n_b"], basis=basis, Ts=law.Ts, a=a["a"], b=b)
    hidden = [a[f"g_W{j}"].shape[0] for j in range(i["n_layers"] - 1)]
    g = MLP(i["n_window"], hidden, law.strings["activation"], out_bias=bool(i["out_bias"]))
    lin = [m for m in g.net if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for j, m in enumerate(lin):
            m.weight.copy_(torch.from_numpy(a[f"g_W{j}"]))
            if m.bias is not None:
                m.bias.copy_(torch.from_numpy(a[f"g_b{j}"]))
    w = ReferenceWindow(i["d_w"], law.strings["window_basis"], law.floats["window_Ts"],
                        law.strings["normalisation"])
    with torch.no_grad():
        w.mean.copy_(torch.from_numpy(a["w_mean"]))
        w.std.copy_(torch.from_numpy(a["w_std"]))
    model = SharedARPGNN(i["n_a"], i["n_b"], g, w, basis=basis, Ts=law.Ts, a=a["a"], b=b)
    with torch.no_grad():
        model.g_gain.fill_(law.floats["g_gain"])
    return model
