"""export: ship every learned feedforward of the job to C99 code, an MLflow model and a manifest
(issue 12; ``pipeline.export``).

One package per feedforward (``export/<package>/`` artifacts of the run): ``<name>.h``/``.c``,
the harness ``main_<name>.c``, every evaluation reference ``r_<ref>.csv`` with the study's u_ff
``u_ff_<ref>.csv``, the law (``law/``: json + npz) and ``manifest.json``.  The laws are the
``invert.kind`` of the job: physics (8), direct (13)-(14), analytic (27), newton ([B1] Alg. 1),
rational_filter ([K]: rational TF or shared-AR PGNN), and fhofc / il_fhofc as a table (one
package per reference: the signal was optimised offline for it).  On a measured system
(``Recording``) physics only: the inverse rigid-body force minus the controller's force on the
reference (``laws.from_measured_physics``).

Verified here: the C compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror`` and the Python law
(the MLflow model's code) must reproduce the invert stage's u_ff on every evaluation reference to
``export.rtol`` × max|u| (metric ``export/max_rel_diff``), else the stage fails and writes nothing.
Timed: median ns per sample of the C law (``export/<package>/c_ns_per_sample``).  The pyfunc model
is logged as ``runs:/<run id>/<package>`` (registered when ``export.register=true``).
"""
from __future__ import annotations

import math
import sys

from omegaconf import OmegaConf

from pipeline import tracking
from pipeline.export import law as laws
from pipeline.export.package import find_compiler, reference_file_clash, write_package
from pipeline.errors import ConfigError
from stages._common import reference_specs

UPSTREAM = ("generate", "baseline", "train", "invert")
DEPENDS = ("invert", "export.compile", "export.cc", "export.rtol", "export.timing_repeats",
           "evaluate.references")
VERSION = 2      # 2: the harness refuses lines it cannot read as one number (issue 24 item 10)


def validate(cfg, system) -> None:
    kind = str(cfg.invert.kind)
    if kind not in laws.LAWS:
        raise ConfigError(f"export: invert.kind={kind} has no feedforward law to ship; export covers "
                          f"invert.kind in {list(laws.LAWS)} (drop 'export' from stages)")
    if system is not None and system.measured:
        if kind != "physics":
            raise ConfigError(f"export: on a measured system the exporter ships invert.kind=physics (the inverse "
                              f"rigid-body force minus the controller's force on the reference); invert.kind={kind} "
                              "is not exported for a measured system: use invert=physics or drop 'export' from stages")
    elif kind == "physics" and getattr(getattr(system, "physics", None), "physics_law", None) != "linear_motor":
        raise ConfigError(f"export: the physics feedforward (8) is exported for the linear motor only, not "
                          f"for system '{system.name}'; drop 'export' from stages")
    m = cfg.model
    if kind in ("direct", "analytic", "newton"):
        hidden = list(m.get("hidden") or [])
        if len(hidden) > 1 or (hidden and str(m.get("activation")) != "tanh"):
            raise ConfigError(f"export: invert.kind={kind} is exported for a PGNN with no NN or one tanh hidden "
                              f"layer; got model.hidden={hidden}, model.activation={m.get('activation')}: use "
                              "e.g. model.hidden=[16] model.activation=tanh, or drop 'export' from stages")
    if kind == "rational_filter" and str(m.get("kind")) == "pgnn_shared_ar" and str(m.get("approximator")) != "mlp":
        raise ConfigError(f"export: the [K] PGNN is exported with the MLP approximator (model.approximator=mlp), "
                          f"got {m.get('approximator')!r}")
    clash = reference_file_clash(s["name"] for s in reference_specs(OmegaConf.select(cfg, "evaluate.references")))
    if clash:
        raise ConfigError(f"export: evaluate.{clash}")
    e = cfg.get("export")
    if e is None:
        raise ConfigError("export: the config has no 'export' node (conf/config.yaml defines it)")
    # export.rtol in (0, 1), export.timing_repeats >= 0: pipeline.schema


def build_laws(ctx) -> dict[str, tuple["laws.Law", list[str]]]:
    """{package name: (law, the evaluation references it is verified on)}: every reference, or for
    FHOFC / IL-FHOFC one table package per reference."""
    cfg, train = ctx.cfg, ctx.inputs["train"]
    every = list(ctx.inputs["invert"]["r"])
    kind, Ts = str(cfg.invert.kind), float(ctx.system.Ts)
    if kind == "physics" and ctx.system.measured:   # minus the controller's force on y = r
        try:
            law = laws.from_measured_physics(ctx.system.physics, ctx.inputs["baseline"]["theta"], ctx.system.ctrl)
        except laws.ExportError as exc:
            raise ConfigError(f"export: {exc}") from exc
        return {"ff_physics": (law, every)}
    if kind == "physics":
        return {"ff_physics": (laws.from_linear_motor_physics(ctx.system.physics, ctx.inputs["baseline"]["theta"]),
                               every)}
    if kind in ("direct", "analytic", "newton"):
        model = train.get("model")
        if model is None:
            raise ConfigError(f"export: invert.kind={kind} needs a trained PGNN; the train stage has none")
        averaged = bool(train.get("model_input")) and bool(getattr(ctx.system.physics, "averaged_input", False))
        kw = {}
        if kind == "newton":
            lo, hi = cfg.invert.get("u_min"), cfg.invert.get("u_max")
            kw = {"k": int(cfg.invert.k), "u_bounds": (-math.inf if lo is None else float(lo),
                                                       math.inf if hi is None else float(hi))}
        try:
            return {f"ff_{kind}": (laws.from_pgnn(model, kind, Ts, averaged=averaged, **kw), every)}
        except laws.ExportError as exc:
            raise ConfigError(f"export: {exc}") from exc
    if kind == "rational_filter":
        model = train["model"]
        return {f"ff_{'pgnn_shared_ar' if hasattr(model, 'g') else 'rational'}": (laws.from_k_filter(model), every)}
    inv = ctx.inputs["invert"]
    return {f"ff_{kind}_{ref}": (laws.from_table(kind, Ts, r, inv["u_ff"][ref]), [ref]) for ref, r in inv["r"].items()}


def run(ctx) -> dict:
    e = ctx.cfg.export
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
    for name, (law, names) in build_laws(ctx).items():
        refs = {ref: (inv["r"][ref], inv["u_ff"][ref]) for ref in names}
        man = write_package(law, name, out, refs, source=source, cc=cc, rtol=float(e.rtol),
                            timing_repeats=int(e.timing_repeats))
        manifests[name] = man
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
        ctx.metric(f"{name}/parameters", man["parameters"])
    ctx.metric("max_rel_diff", worst)
    return {"packages": manifests}
