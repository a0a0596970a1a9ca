"""C99 code of a feedforward :class:`~pipeline.export.law.Law` (issue 12).

One header, one source and one harness per law.  The source is a line-by-line port of the numba
kernels it mirrors (``pipeline.invert.{direct,analytic,newton}``, ``pipeline.models.pgnn``'s
``fast_*`` functions, ``scipy.signal.lfilter``'s direct form II transposed): the same operations
in the same order, so the C output equals the study's to rounding.  Weights are ``static const``
arrays printed with 17 significant digits (exact round trip); the state is a fixed-size struct;
no allocation, no I/O, only ``<math.h>``.  Every helper is ``static inline`` so a law compiles
what it uses with ``-Wall -Wextra -Werror`` and nothing else.

The C is package data, ``pipeline/export/templates/`` (:data:`TEMPLATES`: one file per law family,
the guard, the zero-order hold, the harness and the shared fragments, with ``string.Template``
placeholders); this module formats the numbers, chooses the fragments and fills the placeholders.
Each family's template defines the law as ``static`` ``law_init`` / ``law_step``; the public
``<prefix>_init`` / ``<prefix>_step`` are the guard around them (``templates/guard.c``, the C of
:func:`pipeline.export.guard.run_guard`, same operations in the same order). ``<file>`` names the
files (the package), ``<prefix>`` the symbols (``export.prefix``).
"""
from __future__ import annotations

import functools
import re
import textwrap
from importlib import resources
from pathlib import Path
from string import Template

import numpy as np

from pipeline.export.guard import CORE_FLAGS, FALLBACKS, FLAGS, GUARD_FLAGS, REGRESSORS
from pipeline.export.law import ExportError, Law, lag_of

__all__ = ["c_name", "write_c", "CFLAGS"]

#: the compile line the package is verified with (and the README quotes); clean under gcc and clang
CFLAGS = ("-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-Wconversion", "-Wdouble-promotion")

_LAW_DOC = {
    "physics": "physics feedforward [B1] (8): the analytic inverse of the physics model with θ*_phy",
    "physics_measured": "physics feedforward of a measured axis: the inverse rigid-body force M δ²r + Σ p_j T_j(r, δr) "
                        "minus the known controller's force on y = r, gtau (C_r - C_y) r",
    "direct": "direct-inverse PGNN [B1] (13)-(14): u_ff(t) = û(θ̂, φ'_ff(t)), recursive in u_ff",
    "analytic": "analytic inverse of the invertible PGNN [B1] (26)-(27): u_ff(t) = (r(t+n_k+1) - a - f_NN)/ψ",
    "newton": "Newton inversion of the forward PGNN, [B1] Algorithm 1: k updates from the physics feedforward, "
              "best iterate returned",
    "rational_filter": "the [K] feedforward filter f = (A(r) + g_φ(r))/B(q) ([K] (6); g = 0 for the rational TF)",
    "fhofc": "FHOFC [B2] (17): a signal optimised OFFLINE for ONE known reference, replayed from a table",
    "il_fhofc": "IL-FHOFC [B2] §V: a signal learnt OFFLINE over trials for ONE known reference, replayed from a table",
}


def c_name(name: str) -> str:
    """A C identifier from a package name (letters, digits, '_'; starts with a letter)."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", name)
    if not s or not s[0].isalpha():
        s = "ff_" + s
    return s


def _num(x: float) -> str:
    x = float(x)
    if np.isinf(x):
        return "HUGE_VAL" if x > 0 else "(-HUGE_VAL)"
    if np.isnan(x):
        raise ExportError("a law constant is NaN")
    s = repr(x)   # shortest string that round-trips: the C compiler reads back the same double
    return s if any(c in s for c in ".eE") else s + ".0"


def _array(name: str, a, comment: str = "") -> str:
    a = np.asarray(a, dtype=np.float64).ravel()
    body = ", ".join(_num(v) for v in a) if a.size else "0.0"   # C99 has no empty arrays
    lines, line = [], "    "
    for item in body.split(", "):
        if len(line) + len(item) > 96:
            lines.append(line.rstrip())
            line = "    "
        line += item + ", "
    lines.append(line.rstrip().rstrip(","))
    c = f"  /* {comment} */" if comment else ""
    return f"static const double {name}[{max(a.size, 1)}] = {{{c}\n" + "\n".join(lines) + "\n};\n"


# --------------------------------------------------------------------------------------------
# the C: package data under pipeline/export/templates/ (string.Template placeholders ${...})
# --------------------------------------------------------------------------------------------
#: the template files, what each holds (the C and the papers' equations it implements are in the files)
TEMPLATES = {
    "header.h": "the header of every law: its contract in a comment, rate check, flags, state struct, API",
    "guard.c": "the guard around law_step (pipeline.export.guard, same order of operations as run_guard)",
    "zoh.h": "the zero-order-hold wrapper's API, for a loop N times faster than the law (export.target_rate)",
    "zoh.c": "the zero-order-hold wrapper's code",
    "law_reset.c": "shared by the laws: the state reset of law_init()",
    "averaged_step.c": "shared by the laws: law_step()'s input u from the law's w, which on the averaged (ZOH) "
                       "input runs one sample ahead",
    "pgnn.c": "the [B1] laws on the fast_pgnn arrays (physics, direct, analytic, newton)",
    "df2t.c": "scipy.signal.lfilter's direct form II transposed on the arrays NUM, DEN (NDEN coefficients, "
              "DEN[0] = 1)",
    "k_filter.c": "the [K] filter (rational TF, shared-AR PGNN)",
    "mlp_input.c": "the [K] approximator g_φ: its input normalisation (opens the function)",
    "mlp_hidden.c": "the [K] approximator g_φ: one hidden layer",
    "mlp_output.c": "the [K] approximator g_φ: the output layer (closes the function)",
    "force_term.c": "shared by the rigid-body laws and the guard's physics fallback: T_j(q, q̇) of one force term "
                    "(pipeline.systems.force_terms.term)",
    "reference_force.c": "shared by the laws of a measured axis: minus the controller's force on y = r, gtau (C_r - "
                         "C_y) r, from its rest at r0 (LTIController.reference_force)",
    "rigid_body.c": "the physics feedforward of a measured system (rigid body with force terms, minus the controller)",
    "table.c": "the FHOFC / IL-FHOFC table replay",
    "harness.c": "the test harness main_<file>.c (CSV in, u_ff out, --flags, --time, --check)",
}


@functools.cache
def _text(name: str) -> str:
    """The text of the template file ``name`` (package data: shipped in the wheel)."""
    if name not in TEMPLATES:
        raise KeyError(f"no C template {name!r}")
    return resources.files(__package__).joinpath("templates", name).read_text(encoding="utf-8")


def _template(name: str) -> Template:
    return Template(_text(name))


def _snippets(law: Law) -> dict:
    """The fragments every law's template takes verbatim; the model's force of a measured axis read ``advance``
    samples ahead in the preview (its controller's delay, law.controller_fields)."""
    d = int(law.ints.get("advance", 0))
    step = _text("averaged_step.c").replace("r_preview + ADVANCE", f"r_preview + {d}" if d else "r_preview")
    return {"reset": _text("law_reset.c"), "averaged_step": step}


def _nx(law: Law) -> int:
    return _nx_law(law) + (2 if "lag_tau" in law.floats else 0)    # + the actuator lag's [p(t-1), u(t-1)]


def _lag_defines(law: Law) -> str:
    """The actuator lag's inverse as constants (templates/averaged_step.c; empty without a lag)."""
    lag = lag_of(law)
    if lag is None:
        return ""
    (p0, p1), (_, b1), (a0, a1) = lag.inverse_coefficients()
    return (f"/* actuator lag tau = {_num(lag.tau)} s: p = LAG_P0 w(t) + LAG_P1 w(t+1), "
            "LAG_A0 u(t) = p(t) + LAG_B1 p(t-1) - LAG_A1 u(t-1) */\n"
            + "".join(f"#define {k} ({_num(v)})\n" for k, v in
                      (("LAG_P0", p0), ("LAG_P1", p1), ("LAG_B1", b1), ("LAG_A0", a0), ("LAG_A1", a1)))
            + f"#define XLAG ({_nx(law) - 2})\n")


def _nx_law(law: Law) -> int:
    i = law.ints
    if law.family == "pgnn":
        nrh = max(0, i["n_a"] - i["n_k"] - 1)
        return nrh + i["n_b"] + i["n_a"] + 1 + i["n_phi"] + (i["n_den"] + 1 if "has_ctrl" in i else 0)
    if law.family == "k_filter":
        return i["d_a"] + 1 + i["d_w"] + 1 + 2 * (i["n_b"] + 1)
    if law.family == "rigid_body":
        return 2 + i["n_den"]
    return 1


def _start_lines(law: Law) -> str:
    """The header's start paragraph (``Law.start_doc``): what init assumes, what u_ff(0) is."""
    d = law.start_doc()
    text = f"{d['init']}. u_ff at switch-on, on a reference at rest: {d['u_ff_at_switch_on']}."
    return "\n".join(f" *              {line}" for line in textwrap.wrap(text, 92))


def _cost_doc(law: Law) -> str:
    f = law.flops_per_sample()
    base = f"{f['flops']} flops, {f['elementary_calls']} tanh/exp calls"
    if law.law == "newton":
        return base + f" (at most k = {law.ints['k']} Newton updates, worst case counted)"
    if law.family == "table":
        return "one table lookup"
    return base


def _blob_offsets(law: Law) -> dict:
    """Offsets of the parts of the fast_pgnn blob (FastPGNN docstring)."""
    i, blob = law.ints, law.arrays["blob"]
    p, H, n = i["p"], i["H"], i["n_phi"]
    o, offsets = 0, {}
    for name, size in (("TH", p), ("TS", p), ("W", H * n), ("B", H), ("W2", H), ("B2", 1),
                       ("CFG", i["n_cfg"])):
        offsets[name] = o
        o += size
    if o != blob.size:
        raise ExportError(f"the PGNN blob has {blob.size} entries, its layout {o}")
    return offsets


def _g_code(law: Law) -> tuple[str, str]:
    """Arrays and the C function of the approximator g_φ (MLP, [K] (4))."""
    i, a = law.ints, law.arrays
    if not i["has_g"]:
        return "", ""
    act = {"tanh": "tanh(z)", "relu": "(z > 0.0 ? z : 0.0)", "sigmoid": "1.0 / (1.0 + exp(-z))",
           "softplus": "(z > 20.0 ? z : log1p(exp(z)))"}[law.strings["activation"]]
    arrays = _array("W_MEAN", a["w_mean"], "window normalisation") + _array("W_STD", a["w_std"])
    widths = [i["n_window"]] + [a[f"g_W{j}"].shape[0] for j in range(i["n_layers"])]
    code = "\n" + _template("mlp_input.c").substitute(buf=max(widths), n_in=widths[0])
    for j in range(i["n_layers"]):
        W, b = a[f"g_W{j}"], a[f"g_b{j}"]
        last = j == i["n_layers"] - 1
        arrays += _array(f"G_W{j}", W, f"layer {j}: {W.shape[0]} x {W.shape[1]}")
        if not last or i["out_bias"]:
            arrays += _array(f"G_B{j}", b)
        if last:
            code += _template("mlp_output.c").substitute(layer=j, cols=W.shape[1],
                                                         start=f"G_B{j}[0]" if i["out_bias"] else "0.0")
        else:
            code += _template("mlp_hidden.c").substitute(layer=j, rows=W.shape[0], cols=W.shape[1], act=act)
    return arrays, code


def _pgnn_controller(law: Law, NAME: str, df2t: str) -> dict:
    """The pgnn.c placeholders of a measured axis's controller term (``reference_force.c``, as the rigid-body
    law subtracts it; state after the regressor: the lfilter z, NDEN, then r0); empty on the simulators."""
    i, a = law.ints, law.arrays
    if "has_ctrl" not in i:
        return {"controller": "", "controller_init": "", "controller_step": ""}
    defs = (f"#define HAS_CTRL {i['has_ctrl']}    /* C_r != C_y: subtract gtau (C_r - C_y) r */\n"
            f"#define NDEN {i['n_den']}           /* (B_r - B_y), A coefficients in q^-1 (A[0] = 1) */\n"
            f"#define GTAU ({_num(law.floats['gtau'])})\n"
            f"#define START_REST_CTRL {int(law.start == 'rest')}   /* the controller term from its rest at r0 */\n"
            f"#define K0 ({_num(law.floats['k0'])})   /* (C_r - C_y) at rest [units/m]; 0 with integral action */\n"
            "/* the controller term's state: lfilter z of (C_r - C_y) (r - r0), NDEN, then r0 */\n"
            "#define XZ (XPHI + NPHI)\n#define XR0 (XZ + NDEN)\n")
    if i["has_ctrl"]:
        defs += (_array("NUM", a["num"], "B_r - B_y / A's first coefficient")
                 + _array("DEN", a["den"], "A in q^-1 / its first coefficient") + df2t)
    step = _text("reference_force.c") + f"    if (!isfinite(u)) s->status |= {NAME}_SINGULAR;\n"
    return {"controller": defs, "controller_init": "    s->x[XR0] = START_REST_CTRL ? r0 : 0.0;\n",
            "controller_step": step}


def ts_ns(Ts: float) -> int:
    """Ts in whole nanoseconds (the header's compile-time rate check)."""
    return int(round(float(Ts) * 1e9))


def _single(text: str) -> str:
    """The float variant of generated C (export.precision=single): float for double, the float
    functions of <math.h> (C99 7.12) and f-suffixed constants."""
    text = re.sub(r"\bdouble\b", "float", text)
    text = re.sub(r"\b(tanh|exp|log1p|fabs|cos|sin)\(", r"\1f(", text)
    text = text.replace("HUGE_VAL", "HUGE_VALF")
    return re.sub(r"(?<![\w.])(\d+\.\d*(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+)(?![\w.])", r"\1f", text)


def write_c(law: Law, name: str, folder: Path, source: str, example: str = "reference.csv", *,
            prefix: str | None = None, precision: str = "double", zoh_n: int = 1,
            check_tol: float = 1e-9, check_atol: float = 0.0, check_mask: int = 1023) -> list[Path]:
    """Write ``<name>.h``, ``<name>.c`` and ``main_<name>.c`` into ``folder``; returns the paths.
    ``prefix``: the C symbols' prefix (default ``name``); ``precision``: double | single (the law's
    arithmetic; the harness reads and writes double); ``zoh_n`` > 1: also a zero-order-hold wrapper
    for a loop ``zoh_n`` times faster; the harness's --check accepts |u_c(t) - u(t)| <= ``check_atol``
    + ``check_tol`` |u(t)| per sample, and the flags exactly."""
    file = c_name(name)
    name = c_name(prefix or name)
    NAME = name.upper()
    folder = Path(folder)
    g = law.g
    flags = [f for f in FLAGS if f[0] in CORE_FLAGS[law.family] + GUARD_FLAGS]
    doc = _LAW_DOC["physics_measured" if law.family == "rigid_body" else law.law]
    if law.family == "pgnn" and "has_ctrl" in law.ints:     # a measured axis's PGNN (issue 49)
        doc += "; on a measured axis, minus the known controller's force on y = r, gtau (C_r - C_y) r"
    lim = lambda x: "none" if np.isinf(x) else f"{x:g}"   # noqa: E731
    env = ", ".join(f"{n} in [{lo:.6g}, {hi:.6g}]" for n, lo, hi in zip(REGRESSORS, g.env_lo, g.env_hi))
    common = dict(name=name, NAME=NAME, file=file, doc=doc, source=source, Ts=_num(law.Ts), ts_ns=ts_ns(law.Ts),
                  preview=law.preview, r_unit=law.units["r"], u_unit=law.units["u_ff"],
                  rest_zero=int(law.rest == "zero" and law.start == "study"),
                  rest_doc="0" if (law.rest == "zero" and law.start == "study") else "r(0), the first reference sample",
                  cost_doc=_cost_doc(law), nx=_nx(law), precision=precision, start_lines=_start_lines(law),
                  precision_doc="" if precision == "double" else
                  " The float variant: max|du|/max|u| against the double study is in manifest.json.",
                  envelope_doc=f"{env}; {'falls back' if g.envelope_action == 'fallback' else 'flag only'}",
                  fallback=g.fallback,
                  fallback_doc={"hold": " (the last valid output)",
                                "ramp": f" (the last valid output ramped to 0 over {g.ramp_time:g} s)",
                                "physics": f" (M d2r + sum_j p_j T_j(r, dr), every force term: [M, p_j] = "
                                           f"[{', '.join(f'{v:.6g}' for v in g.physics)}], T_j codes "
                                           f"{g.physics_codes}; holds on NaN)"}[g.fallback],
                  u_min_doc=lim(g.u_min), u_max_doc=lim(g.u_max), rate_doc=lim(g.rate),
                  status_lines="\n".join(f" *                {NAME}_{f} = {v}: {d}" for f, v, d in flags),
                  source_lines="\n".join(f" *   {line}" for line in textwrap.wrap(source, 96)),
                  flag_defines="\n".join(f"#define {NAME}_{f} {v}" for f, v, _ in FLAGS),
                  zoh_doc="" if zoh_n == 1 else f"\n *              {name}_zoh_step: the law held for a loop "
                                                f"{zoh_n} x faster (Ts_loop = Ts / {zoh_n}, {NAME}_LOOP_TS_NS = "
                                                f"{ts_ns(law.Ts / zoh_n)} passes too).",
                  # the loop period of the ZOH wrapper passes the rate check as well as the law's own
                  zoh_rate_check="" if zoh_n == 1 else f" && ({NAME}_LOOP_TS_NS != {ts_ns(law.Ts / zoh_n)})",
                  zoh_rate_doc="" if zoh_n == 1 else
                  f" (or Ts_loop = {_num(law.Ts / zoh_n)} s through {name}_zoh_step)")
    zoh = dict(zoh_n=zoh_n, ts_loop=_num(law.Ts / zoh_n), zoh_ts_ns=ts_ns(law.Ts / zoh_n),
               du_loop=_num(g.du_max(law.Ts) / zoh_n))      # the slew limit per loop sample: rate Ts / N
    common["zoh_api"] = "\n" + _template("zoh.h").substitute(common, **zoh) if zoh_n > 1 else ""
    guard = "\n" + _template("guard.c").substitute(
        common, sat_lo=_num(g.u_min), sat_hi=_num(g.u_max), du_max=_num(g.du_max(law.Ts)),
        fallback_kind=FALLBACKS.index(g.fallback) if g.fallback != "ramp" else 2,
        env_fallback=int(g.envelope_action == "fallback"), ramp_n=_num(g.ramp_n(law.Ts)),
        env_lo=", ".join(_num(v) for v in g.env_lo), env_hi=", ".join(_num(v) for v in g.env_hi),
        phys=", ".join(_num(v) for v in g.physics), n_phys=len(g.physics) - 1,
        phys_codes=", ".join([str(c) for c in g.physics_codes] + ["0"]),        # + one unused: C99 has no
        phys_consts=", ".join([_num(v) for v in g.physics_consts] + ["0.0"]),   # empty arrays (no terms)
        start_rest=int(law.start == "rest"), settle_n=law.settle,
        static_exclude=int(law.static == "exclude"),
        force_term="" if law.family == "rigid_body" else _text("force_term.c"))   # the law's own, defined once
    if zoh_n > 1:
        guard += "\n" + _template("zoh.c").substitute(common, **zoh)
    snippets, df2t = _snippets(law), "\n" + _text("df2t.c")
    i = law.ints
    if law.family == "pgnn":
        offsets = _blob_offsets(law)
        arrays = _array("BLOB", law.arrays["blob"]) + _lag_defines(law)
        src = _template("pgnn.c").substitute(
            common, **snippets, arrays=arrays, LAW=law.law.upper(), **_pgnn_controller(law, NAME, df2t),
            force_term=_text("force_term.c") if i["kind"] in (3, 4) else "",
            **{f"o_{k.lower()}": v for k, v in offsets.items()},
            nrh=max(0, i["n_a"] - i["n_k"] - 1), averaged=int(law.averaged),
            k=i.get("k", 0), u_min=_num(law.floats.get("u_min", -np.inf)),
            u_max=_num(law.floats.get("u_max", np.inf)),
            **{k: i[k] for k in ("kind", "H", "n_phi", "u_index", "use_phys", "use_nn",
                                 "n_a", "n_b", "n_k", "inverse_layout")})
    elif law.family == "k_filter":
        g_arrays, g_code = _g_code(law)
        arrays = (_array("A_COEF", law.arrays["a"], "a_i of A = Σ a_i ψ_{i-1}(r)")
                  + _array("NUM", law.arrays["num"], "lfilter numerator / B's first coefficient")
                  + _array("DEN", law.arrays["den"], "B(q) in q^-1 / its first coefficient") + g_arrays)
        src = _template("k_filter.c").substitute(
            common, **snippets, arrays=arrays, g_code=g_code, df2t=df2t, nden=i["n_b"] + 1,
            window_Ts=_num(law.floats.get("window_Ts", law.Ts)), g_gain=_num(law.floats["g_gain"]),
            **{k: i[k] for k in ("n_a", "d_a", "basis_delta", "has_g", "d_w", "window_delta")})
    elif law.family == "rigid_body":
        a = law.arrays
        codes = ", ".join(str(int(c)) for c in a["codes"]) or "0"
        arrays = (_array("THETA_INV", a["theta_inv"], "θ' = [M, p_1, ...] of the inverse form")
                  + _array("CONSTS", a["consts"], "shape constant of each force term")
                  + f"static const int CODES[{max(a['codes'].size, 1)}] = {{{codes}}};"
                  + "  /* kernel code of each term */\n" + _lag_defines(law))
        if i["has_ctrl"]:
            arrays += (_array("NUM", a["num"], "B_r - B_y / A's first coefficient")
                       + _array("DEN", a["den"], "A in q^-1 / its first coefficient"))
        src = _template("rigid_body.c").substitute(
            common, **snippets, arrays=arrays, df2t=df2t if i["has_ctrl"] else "",
            force_term=_text("force_term.c"), reference_force=_text("reference_force.c"),
            n_terms=i["n_terms"], averaged=int(law.averaged), has_ctrl=i["has_ctrl"],
            nden=i["n_den"], gtau=_num(law.floats["gtau"]), start_rest=int(law.start == "rest"),
            k0=_num(law.floats.get("k0", 0.0)))
    else:
        arrays = (_array("R_TABLE", law.arrays["r"], "the reference the signal was optimised for")
                  + _array("U_TABLE", law.arrays["u"], "u_ff"))
        src = _template("table.c").substitute(common, **snippets, arrays=arrays, n=i["n"],
                                              r_tol=_num(law.floats["r_tol"]))
    header, src = _template("header.h").substitute(common), src + guard
    if precision == "single":
        header, src = _single(header), _single(src)
    harness = _template("harness.c").substitute(common, example=example, check_tol=_num(check_tol),
                                                check_atol=_num(check_atol), check_mask=int(check_mask))
    files = {f"{file}.h": header, f"{file}.c": src, f"main_{file}.c": harness}
    out = []
    for fname, text in files.items():
        p = folder / fname
        p.write_text(text)
        out.append(p)
    return out
