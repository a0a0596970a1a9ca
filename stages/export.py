"""export: ship every learned feedforward of the job to C99 code, an MLflow model and a manifest
(issue 12; ``pipeline.export``).

One package per feedforward (``export/<package>/`` artifacts of the run): ``<name>.h``/``.c``,
the harness ``main_<name>.c``, every evaluation reference ``r_<ref>.csv`` with the study's u_ff
``u_ff_<ref>.csv``, the law (``law/``: json + npz) and ``manifest.json``.  The laws are the
``invert.kind`` of the job: physics (8), direct (13)-(14), analytic (27), newton ([B1] Alg. 1),
rational_filter ([K]: rational TF or shared-AR PGNN), and fhofc / il_fhofc as a table (one
package per reference: the signal was optimised offline for it).  On a measured system
(``Recording``): physics (the inverse rigid-body force, ``laws.from_measured_physics``) and the PGNN's
direct, analytic and Newton inversions (its rigid body with force terms, kinds 4 and 3 of the numba kernels;
issue 49), each minus the controller's force on the reference (C_r - C_y) r.

Every law is wrapped in its guard (``pipeline.export.guard``; ``export.limits``): input sanitation, the
training envelope of the identification data's y, the fallback, force saturation and slew limit,
status flags; the defaults leave a clean sample's u_ff untouched. ``export.prefix`` names the C
symbols, ``export.precision=single`` writes the law in float (measured against the double study),
``export.target_rate`` adds a zero-order hold for an integer multiple of the law's rate (refused
otherwise, before any work), and with cppcheck installed its MISRA addon's findings go to the
manifest and the package README.

Verified here: the C compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror`` and the Python law
(the MLflow model's code) must reproduce the invert stage's u_ff on every evaluation reference to
``export.rtol`` × max|u| (metric ``export/max_rel_diff``), else the stage fails and writes nothing.
Timed: median ns per sample of the C law (``export/<package>/c_ns_per_sample``).  The pyfunc model
is logged as ``runs:/<run id>/<package>`` (registered when ``export.register=true``).
"""
from __future__ import annotations

import math
import sys
import warnings
from dataclasses import asdict, field
from typing import Literal, Optional

import numpy as np

from omegaconf import OmegaConf

from pipeline import tracking
from pipeline.errors import ConfigError
from pipeline.export import law as laws
from pipeline.export.c_code import c_name
from pipeline.export.guard import Guard, envelope_of
from pipeline.export.misra import find_cppcheck
from pipeline.export.package import check_prefix, find_compiler, reference_file_clash, write_package
from pipeline.invert.start import settle_count
from pipeline.params import COUNT_MAX, FORCE_MAX, FREQ_MAX, schema, spec
from pipeline.runner import exportable, implementation
from stages._common import baseline_lag, reference_specs


@schema
class Limits:
    """export.limits: the guard around an exported law (pipeline.export.guard)."""
    # actuator force saturation [N]; null: from the identification data (data_margin)
    u_min: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=-200.0)
    u_max: Optional[float] = spec(None, ge=-FORCE_MAX, le=FORCE_MAX, unit="N", example=200.0)
    # slew limit [N/s]; null: from the identification data (data_margin)
    rate: Optional[float] = spec(None, gt=0, le=1e12, unit="N/s", example=1e5)
    # a null limit is ±(1 + data_margin) max|u| and (1 + data_margin) max|Δu|/Ts of the identification data's
    # applied force u (the recorded command range of a measured axis, the simulated actuator's of a plant);
    # null here: no limit where none is set
    data_margin: Optional[float] = spec(0.5, ge=0, le=100, example=0.5)
    # training envelope of r, dr/dt, d2r/dt2 (the identification data's y) widened by this x its range
    envelope_margin: float = spec(0.1, ge=0, le=100)
    # flag: OUT_OF_RANGE only | fallback: also the fallback
    envelope_action: Literal["flag", "fallback"] = "flag"
    # on NaN/inf input (and out of range with envelope_action=fallback): hold | physics | ramp
    fallback: Literal["hold", "physics", "ramp"] = "hold"
    # [s] ramp: the last valid output to 0 over this time
    ramp_time: float = spec(0.1, gt=0, le=3600.0, unit="s")


@schema
class Params:
    # compile the C (cc -std=c99 -O2 -Wall -Wextra -Werror) and verify it against the study
    compile: bool = True
    # the C compiler; when it is missing the stage says so and writes the source only
    cc: str = "cc"
    # max |Δu| / max |u| the package must reach on every evaluation reference (C and Python)
    rtol: float = spec(1e-9, gt=0, lt=1)
    # runs of the longest reference for the C ns per sample (median; 0 = no timing)
    timing_repeats: int = spec(21, ge=0, le=COUNT_MAX)
    # also register the MLflow model in the Model Registry as <experiment>-<package>
    register: bool = False
    # C symbol prefix (<prefix>_init, <prefix>_step); null = <package>_<8 hex of the law's hash>
    prefix: Optional[str] = spec(None, check=check_prefix, example="axis1_ff")
    # double | single: the C law in float, its max |Δu|/max|u| against the double study in the manifest
    precision: Literal["double", "single"] = "double"
    # the largest max |Δu|/max|u| a float law may reach against the double study
    single_rtol: float = spec(0.1, gt=0, le=10)
    # loop rate [Hz]; null = the law's own; an integer multiple adds a zero-order-hold wrapper
    target_rate: Optional[float] = spec(None, gt=0, le=FREQ_MAX, unit="Hz", example=4000.0)
    # run cppcheck and its MISRA C:2012 addon when installed (findings: manifest, package README)
    cppcheck: bool = True
    # the guard around the law (README: Deploy the feedforward); null = no limit
    limits: Limits = field(default_factory=Limits)


UPSTREAM = ("generate", "baseline", "train", "invert")
DEPENDS = ("invert", "start", "export.compile", "export.cc", "export.rtol", "export.timing_repeats",
           "export.prefix", "export.precision", "export.single_rtol", "export.target_rate", "export.cppcheck",
           "export.limits", "evaluate.references")


#: the laws the exporter ships for a measured system (their stages/invert/<kind>.py set EXPORTS_MEASURED)
MEASURED_LAWS = ("physics", "direct", "analytic", "newton")

VERSION = 11     # 3: the guard (limits, envelope, flags, fallback), vectors, README, prefix (issue 22); 4: the envelope
                 # is checked over the whole window r(t-2) .. r(t+P), not only at its newest sample; 5: the start at
                 # rest, default limits from the data, the guard's return ramp and latch (issue 48); 6: the start's
                 # header text, the float harness's flag mask; 7: one force_term (templates/force_term.c) for the
                 # law and the guard, with the spring, position_poly and drag terms (issue 49); 8: the PGNN of a
                 # measured axis (issue 49), the controller term as a shared C fragment, feedforward_<ref>.csv;
                 # 9: the normal test vector ends at rest (pipeline.export.package.normal_window), not cut at 4000;
                 # 10: a measured axis's law gives the force of r(t + D), D its controller's delay (preview + D);
                 # 11: a table's past_end vector runs past the whole table, its start text says where it starts


def validate(cfg, system) -> None:
    kind = str(cfg.invert.kind)
    impl = implementation("invert", kind)
    if not hasattr(impl, "export_laws"):
        raise ConfigError(f"export: invert.kind={kind} has no feedforward law to ship; export covers "
                          f"invert.kind in {exportable()} (drop 'export' from stages)")
    if system is not None and system.measured and not getattr(impl, "EXPORTS_MEASURED", False):
        raise ConfigError(f"export: on a measured system the exporter ships invert.kind in {list(MEASURED_LAWS)} "
                          f"(each minus the controller's force on the reference); invert.kind={kind} is not exported "
                          "for a measured system: use one of those, or drop 'export' from stages")
    if hasattr(impl, "export_check"):
        impl.export_check(cfg, system)
    clash = reference_file_clash(s["name"] for s in reference_specs(OmegaConf.select(cfg, "evaluate.references")))
    if clash:
        raise ConfigError(f"export: evaluate.{clash}")
    e = cfg.get("export")
    if e is None:
        raise ConfigError("export: the config has no 'export' node (conf/config.yaml defines it)")
    # export.rtol in (0, 1), export.timing_repeats >= 0, the prefix a C identifier: pipeline.schema
    lim = e.get("limits") or {}
    lo, hi = lim.get("u_min"), lim.get("u_max")
    if lo is not None and hi is not None and not lo < hi:
        raise ConfigError(f"export.limits.u_min={lo} is not below export.limits.u_max={hi}: give u_min < u_max "
                          "(e.g. export.limits.u_min=-200 export.limits.u_max=200)")
    if lim.get("fallback") == "physics" and system is not None and physics_coefficients(system, None) is None:
        raise ConfigError(f"export.limits.fallback=physics needs a rigid-body physics law (linear motor or a measured "
                          f"axis); system '{getattr(system, 'name', '?')}' has none: use export.limits.fallback=hold "
                          "or ramp")
    if system is not None and e.get("target_rate") is not None:
        zoh_factor(float(e.target_rate), float(system.Ts))


def zoh_factor(target_rate: float, Ts: float) -> int:
    """N of the zero-order hold for a loop at ``target_rate`` [Hz] of a law of sample time Ts: an
    integer >= 1 (1: the law's own rate), else a ConfigError."""
    n = target_rate * Ts
    N = round(n)
    if N < 1 or abs(n - N) > 1e-9 * max(N, 1):
        raise ConfigError(f"export.target_rate={target_rate:g}: the law runs at {1 / Ts:g} Hz (Ts = {Ts:g} s); a "
                          f"wrapper is generated for an integer multiple of it (e.g. export.target_rate={2 / Ts:g}), "
                          "or null for the law's own rate")
    return int(N)


def physics_coefficients(system, theta) -> dict | None:
    """The physics fallback of the system's rigid-body law, every force term of it (Guard's ``physics`` =
    [M, p_1, ...], ``physics_codes``, ``physics_consts``: M δ²r + Σ_j p_j T_j(r, δr)), None if it has none;
    with theta None only whether it has one (zeros). A measured axis keeps all its configured terms (the offset
    is gravity on a vertical axis: without it the fallback dropped the load); the linear motor's (8) is
    [m, f_v, f_c] with T = δr, sign δr."""
    physics = getattr(system, "physics", None)
    law = getattr(physics, "physics_law", None)
    if law not in ("linear_motor", "rigid_body"):
        return None
    if law == "linear_motor":          # [m, f_v, f_c], (8): viscous, sign (force_terms codes 0, 1)
        codes, consts = [0, 1], [0.0, 0.0]
    else:                              # before the baseline an auto Coulomb width is not chosen: its shape is NaN
        e = physics.terms.expanded() if theta is None else None
        c, k = ([x[2] for x in e], [0.0] * len(e)) if e is not None else physics.terms.kernel()
        codes, consts = [int(v) for v in c], [float(v) for v in k]
    if theta is None:
        t = [0.0] * (1 + len(codes))
    else:
        t = [float(v) for v in physics.inverse_theta(theta)][:1 + len(codes)]
    return {"physics": t, "physics_codes": codes, "physics_consts": consts}


def data_limits(segments, Ts: float, ctrl=None, rest: bool = True) -> tuple[float, float]:
    """(max|u_ff| [N], max|Δu_ff|/Ts [N/s]) a feedforward of the identification data would need, per experiment
    (segments of (u, r): no difference across a boundary): the applied force u (the model's inverse force on the
    data is that force) plus, on a 2-DOF loop, the controller term (C_r - C_y) r the law cancels, which can be far
    larger than the force itself (a D-term on y only: kd dr/dt); the base of the default limits."""
    u_abs = du_abs = 0.0
    for u, r in segments:
        u = np.asarray(u, dtype=np.float64)
        if ctrl is not None:
            r = np.asarray(r, dtype=np.float64)
            u = u - ctrl.reference_force(r, float(r[0]) if rest else 0.0)   # as the law's start counts it
        u = u[np.isfinite(u)]
        if u.size:
            u_abs = max(u_abs, float(np.max(np.abs(u))))
        if u.size > 1:
            du_abs = max(du_abs, float(np.max(np.abs(np.diff(u)))) / Ts)
    return u_abs or math.inf, du_abs or math.inf


def guard_of(ctx, start_at: str | None = None) -> tuple[dict, str]:
    """(the guard of every law of the job, where its limits come from): export.limits, else the identification
    data's force range and slew (``data_limits``, ``Limits.data_margin``), the data's envelope and the physics
    fallback's coefficients (pipeline.export.guard.Guard). ``start_at``: the invert stage's ``start.at`` (default:
    its output's; the invert stage passes its own to flag its u_ff CSV)."""
    lim = ctx.cfg.export.limits          # every key set by pipeline.schema (null: no limit)
    bound = lambda k, none: none if lim.get(k) is None else float(lim.get(k))   # noqa: E731
    ds = ctx.inputs["generate"]["dataset"]
    lo, hi = envelope_of((seg["y"].to_numpy(dtype=float) for seg in ds.segments()), float(ctx.system.Ts),
                         float(lim.envelope_margin))
    ctrl = ctx.system.ctrl if ctx.system.measured else None
    pairs = ((seg["u"].to_numpy(dtype=float), None if ctrl is None else seg["r"].to_numpy(dtype=float))
             for seg in ds.segments())
    if start_at is None:
        start_at = (ctx.inputs["invert"].get("start") or {"at": "zero"})["at"]
    u_abs, du_abs = data_limits(pairs, float(ctx.system.Ts), ctrl, start_at == "rest")
    if lim.get("data_margin") is not None:     # a null limit from the identification data (Limits.data_margin)
        f = 1.0 + float(lim.data_margin)
        bound = lambda k, none: (f * (-u_abs if k == "u_min" else u_abs if k == "u_max" else du_abs)  # noqa: E731
                                 if lim.get(k) is None else float(lim.get(k)))
    given = [k for k in ("u_min", "u_max", "rate") if lim.get(k) is not None]
    src = (f"{', '.join(given) or 'none'} from export.limits; "
           + ("the others none (export.limits.data_margin=null)" if lim.get("data_margin") is None else
              "the others from the identification data's applied force u"
              + (" minus the controller term (C_r - C_y) r" if ctrl is not None else "")
              + f": ±{1 + float(lim.data_margin):g} x {u_abs:.6g} N (its largest magnitude) and "
              f"{1 + float(lim.data_margin):g} x {du_abs:.6g} N/s (its largest slew) "
              f"(export.limits.data_margin={float(lim.data_margin):g})"))
    phys = {}                            # the Guard's default physics (unused unless fallback=physics)
    if lim.fallback == "physics":
        phys = physics_coefficients(ctx.system, ctx.inputs["baseline"]["theta"])
    return asdict(Guard(u_min=bound("u_min", -math.inf), u_max=bound("u_max", math.inf),
                        rate=bound("rate", math.inf), env_lo=lo, env_hi=hi, envelope_action=str(lim.envelope_action),
                        fallback=str(lim.fallback), ramp_time=float(lim.ramp_time), **phys)), src


def set_start(law: "laws.Law", start: dict, r0s: list[float]) -> None:
    """The invert stage's start (pipeline.invert.start) on the law: 'zero' keeps the study's conventions;
    'rest' puts every state at rest at r0 at init, ``settle`` (the rest samples the law needs, the most over
    the references' r(0) and the training envelope's ends) measured on the law itself."""
    if start["at"] != "rest" or law.family == "table":
        return
    law.start, law.static, law.rest = "rest", str(start["static"]), "first"
    lo, hi = law.g.env_lo[0], law.g.env_hi[0]
    r0s = sorted(set(r0s) | {v for v in (lo, hi) if math.isfinite(v)})
    try:
        law.settle = settle_count(lambda r: laws._core(law, r)[0], r0s)
    except ValueError as exc:
        raise ConfigError(f"export: {exc}") from exc


def build_laws(ctx) -> dict[str, tuple["laws.Law", list[str]]]:
    """{package name: (law, the evaluation references it is verified on)}: the invert option's own
    ``export_laws(ctx)`` (stages/invert/<kind>.py), a law builder's ExportError as one config line."""
    try:
        return implementation("invert", str(ctx.cfg.invert.kind)).export_laws(ctx)
    except laws.ExportError as exc:
        raise ConfigError(f"export: {exc}") from exc


# ---- the shared parts of the invert options' ``export_laws`` / ``export_check``
def every_reference(ctx) -> list[str]:
    return list(ctx.inputs["invert"]["r"])


def pgnn_check(cfg, kind: str) -> None:
    """A [B1] PGNN law is exported with no NN or one tanh hidden layer."""
    m = cfg.model
    hidden = list(m.get("hidden") or [])
    if len(hidden) > 1 or (hidden and str(m.get("activation")) != "tanh"):
        raise ConfigError(f"export: invert.kind={kind} is exported for a PGNN with no NN or one tanh hidden "
                          f"layer; got model.hidden={hidden}, model.activation={m.get('activation')}: use "
                          "e.g. model.hidden=[16] model.activation=tanh, or drop 'export' from stages")


def pgnn_laws(ctx, kind: str, **kw) -> dict:
    """The [B1] inversion ``kind`` of the trained PGNN, verified on every reference."""
    train = ctx.inputs["train"]
    model = train.get("model")
    if model is None:
        raise ConfigError(f"export: invert.kind={kind} needs a trained PGNN; the train stage has none")
    averaged = bool(train.get("model_input")) and bool(getattr(ctx.system.physics, "averaged_input", False))
    ctrl = ctx.system.ctrl if ctx.system.measured else None      # minus (C_r - C_y) r, as stages/invert
    return {f"ff_{kind}": (laws.from_pgnn(model, kind, float(ctx.system.Ts), averaged=averaged, ctrl=ctrl, **kw),
                           every_reference(ctx))}


def table_laws(ctx, kind: str) -> dict:
    """One table package per reference: a signal optimised offline for that reference (FHOFC, IL-FHOFC)."""
    inv = ctx.inputs["invert"]
    return {f"ff_{kind}_{ref}": (laws.from_table(kind, float(ctx.system.Ts), r, inv["u_ff"][ref]), [ref])
            for ref, r in inv["r"].items()}


def run(ctx) -> dict:
    e = ctx.cfg.export
    baseline_lag(ctx)
    cc = str(e.cc) if e.compile else None
    if cc and find_compiler(cc) is None:
        print(f"[{ctx.cfg.run_name}] export: no C compiler '{cc}' on this machine: writing the C source "
              "without compiling or verifying it (install gcc or clang, or set export.cc=<compiler>)",
              file=sys.stderr, flush=True)
        ctx.tag("export.compiled", "no compiler")
    inv = ctx.inputs["invert"]
    source = {"run_id": ctx.run_id, "git_sha": tracking.git_sha(), "experiment": str(ctx.cfg.experiment_name),
              "config_hash": ctx.key[:20]}
    out = ctx.workdir / "artifacts"
    manifests, worst = {}, 0.0
    built = build_laws(ctx)
    guard, limits_source = guard_of(ctx)
    zoh_n = 1 if e.get("target_rate") is None else zoh_factor(float(e.target_rate), float(ctx.system.Ts))
    start = inv.get("start") or {"at": "zero", "static": "include"}
    for name, (law, names) in built.items():
        law.guard = dict(guard)
        law.strings["limits_source"] = limits_source
        set_start(law, start, [float(inv["r"][ref][0]) for ref in names])
        refs = {ref: (inv["r"][ref], inv["u_ff"][ref]) for ref in names}
        prefix = e.get("prefix")
        if prefix and len(built) > 1:     # one table per reference: one prefix each
            prefix = c_name(f"{prefix}_{name.removeprefix(f'ff_{ctx.cfg.invert.kind}_')}")
        man = write_package(law, name, out, refs, source=source, cc=cc, rtol=float(e.rtol),
                            timing_repeats=int(e.timing_repeats), prefix=prefix,
                            precision=str(e.precision), single_rtol=float(e.single_rtol),
                            zoh_n=zoh_n, cppcheck=bool(e.cppcheck) and find_cppcheck() is not None)
        manifests[name] = man
        touched = {ref: v for ref, v in man["references"].items() if v["guard_max_rel_change"] > 0}
        if touched:    # the package as shipped is not the study's feedforward on a reference it was verified on
            msg = (f"export: the guard of {name} changes its u_ff on " + ", ".join(
                f"'{ref}' (max|Δu|/max|u| = {v['guard_max_rel_change']:.3g}, flags {v['flags']})"
                for ref, v in touched.items())
                + f"; limits: {man['limits_source']}. The machine gets the guarded u_ff: set export.limits "
                "(u_min, u_max, rate) to the actuator's, or record training data that cover the reference")
            warnings.warn(msg, stacklevel=1)
            ctx.tag(f"export_warning/{name}", msg)
        ctx.artifacts += sorted(str(p.relative_to(out)) for p in (out / name).rglob("*") if p.is_file())
        ctx.models.append({"name": name, "law": f"artifacts/{name}/law",
                           "example": f"artifacts/{name}/{next(iter(man['references'].values()))['file']}"})
        diff = man["c_max_rel_diff"] if man["compiled"] else man["python_max_rel_diff"]
        worst = max(worst, diff)
        ctx.metric(f"{name}/python_max_rel_diff", man["python_max_rel_diff"])
        if man["compiled"]:
            ctx.metric(f"{name}/c_max_rel_diff", man["c_max_rel_diff"])
            if man["c_ns_per_sample"] is not None:
                ctx.metric(f"{name}/c_ns_per_sample", man["c_ns_per_sample"])
        ctx.metric(f"{name}/flops", man["flops"])
        if "single_max_rel_diff" in man:
            ctx.metric(f"{name}/single_max_rel_diff", man["single_max_rel_diff"])
        if man.get("cppcheck", {}).get("ran"):
            ctx.metric(f"{name}/misra_findings", man["cppcheck"]["misra_total"])
        if "zoh" in man:
            ctx.metric(f"{name}/zoh_max_rel_diff", man["zoh"]["max_rel_diff_vs_interpolated"])
        ctx.metric(f"{name}/parameters", man["parameters"])
    ctx.metric("max_rel_diff", worst)
    return {"packages": manifests}
