"""Static checks of a generated package (issue 22 item 4) and the package's README.

:func:`cppcheck_report` runs ``cppcheck`` (warning, style, performance, portability: expected clean)
and its MISRA C:2012 addon (``--addon=misra``) on the law's ``<name>.c`` + ``<name>.h`` (not the
harness: it does I/O and is not shipped to the target) and counts the findings per rule. Every
MISRA rule the generated code still breaks has a reason in :data:`DEVIATIONS`; the package README
lists the ones found in that package with their count and reason.
"""
from __future__ import annotations

import re
import shutil
import subprocess
from collections import Counter
from pathlib import Path

from pipeline.export.guard import FLAGS

__all__ = ["DEVIATIONS", "cppcheck_report", "readme", "find_cppcheck"]

#: MISRA C:2012 rules the generated C deviates from, and why (a deviation record per rule)
DEVIATIONS = {
    "2.2": "dead code: `(void)x;` casts keep the unused parameters of a compile-time branch quiet "
           "(#if on the law's shape)",
    "2.3": "an unused type: the header declares `<prefix>_real` for the caller even where the law does not use it",
    "2.5": "unused macros: the header defines every flag bit and size for the caller; the source's layout macros "
           "document the state vector",
    "2.7": "unused parameters of a compile-time branch (see 2.2)",
    "8.4": "the harness-facing functions are declared in the header; cppcheck checks the source alone",
    "8.7": "init/step have external linkage by design: they are the API",
    "8.9": "the weight tables are file-scope `static const` (generated once, read by several helpers)",
    "10.1": "`flags & BIT` on int flags and `!` on int: the flags are a plain int bit mask (the documented API)",
    "10.3": "int/double conversions of generated constants (layout indices stored in the parameter blob)",
    "10.4": "mixed essential types in the port of the numba kernels (int index arithmetic with double data)",
    "10.8": "a composite expression cast (the layout indices of the blob)",
    "11.5": "none expected",
    "12.1": "operator precedence left to C where the line-by-line port of the kernels reads as the Python does",
    "12.3": "several declarators in one declaration (`int i, j;`), as in the kernels",
    "13.3": "`++i` in for loops",
    "13.4": "none expected",
    "13.5": "none expected",
    "14.4": "int used as a boolean in conditions (`if (s->status)`, `#if`-selected flags): C99 has no bool in the API",
    "15.1": "none expected",
    "15.4": "more than one `break` in the Newton loop (the kernel's own exits: converged, singular, out of bounds)",
    "15.5": "more than one return (switch of the force terms; early returns of the kernels)",
    "15.6": "single-statement bodies of if/for without braces (the kernels' port, one line per Python line)",
    "15.7": "`if ... else if` without a final `else` (the saturation and slew limit: nothing to do otherwise)",
    "16.3": "none expected",
    "17.7": "none expected",
    "17.8": "none expected",
    "18.4": "pointer arithmetic `p + k` on the parameter blob and the preview window (fixed offsets, in bounds)",
    "20.7": "macro parameters without parentheses: none expected",
    "20.9": "an undefined macro in #if evaluates to 0 (the optional loop period <PREFIX>_LOOP_TS_NS is tested "
            "with defined() first)",
    "21.1": "none expected",
}


#: how the `normal` test vector was cut (pipeline.export.package.normal_window), in the package README's words
_NORMAL_CUT = {"whole moves": "whole moves, ending at rest",
               "the first move": "its first move whole, ending at rest",
               "cut in motion": "cut IN MOTION (no rest early enough): the law then stops at once, so the last "
                                "samples' forces and flags are the cut's, not the reference's",
               "at rest": "the reference does not move"}


def find_cppcheck() -> str | None:
    return shutil.which("cppcheck")


def cppcheck_report(folder: Path, name: str, exe: str | None = None) -> dict:
    """{"version", "warnings": [...], "misra": {rule: count}, "misra_total", "unexplained": [...]}
    of cppcheck on the package's law (``{"ran": False, ...}`` without cppcheck)."""
    exe = exe or find_cppcheck()
    if exe is None:
        return {"ran": False, "note": "cppcheck not found on the exporting machine"}
    folder = Path(folder)
    files = [str(folder / f"{name}.c"), str(folder / f"{name}.h")]
    version = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60).stdout.strip()
    tmpl = "--template={id}|{severity}|{line}|{message}"
    base = [exe, "--std=c99", "--quiet", tmpl, f"-I{folder}"]
    plain = subprocess.run(base + ["--enable=warning,style,performance,portability", *files],
                           capture_output=True, text=True, timeout=600)
    warnings = [line for line in plain.stderr.splitlines() if "|" in line and not line.startswith("misra")
                and "missingInclude" not in line and "checkersReport" not in line]
    misra = subprocess.run(base + ["--addon=misra", files[0]], capture_output=True, text=True, timeout=600,
                           cwd=folder)
    rules = Counter(m.group(1) for m in re.finditer(r"misra-c2012-(\d+\.\d+)", misra.stderr))
    return {"ran": True, "version": version, "warnings": warnings, "n_warnings": len(warnings),
            "misra": dict(sorted(rules.items(), key=lambda kv: [int(x) for x in kv[0].split(".")])),
            "misra_total": int(sum(rules.values())),
            "unexplained": sorted(r for r in rules if r not in DEVIATIONS or DEVIATIONS[r] == "none expected")}


def readme(law, name: str, man: dict) -> str:
    """The package's README.md: API, guard, flags, vectors, checks."""
    p = man["prefix"]
    P = p.upper()
    lim = man["limits"]
    env = man["envelope"]
    lines = [f"# {name}: exported feedforward ({man['law']}, {man['model']})", "",
             f"Ts = {law.Ts:g} s ({1 / law.Ts:g} Hz), preview P = {law.preview}, precision {man['precision']}, "
             f"symbol prefix `{p}`. Generated: do not edit, re-export.", "",
             "## C API", "", "```c",
             f'#include "{name}.h"',
             f"{p}_state s;",
             f"{p}_init(&s, r0);                    /* at rest at r0: where the axis stands (below) */",
             f"u = {p}_step(&s, r_preview);        /* r_preview[0..{P}_PREVIEW] = r(t) .. r(t+P) */",
             f"if (s.status & {P}_FALLBACK) ...     /* flags of this sample, table below */", "```", "",
             "## Start and switch-on", "",
             f"- start: {man['start']['init']}.",
             f"- u_ff at switch-on, on a reference at rest: {man['start']['u_ff_at_switch_on']}.", ""]
    if "zoh" in man:
        z = man["zoh"]
        lines += [f"Loop {z['factor']} x faster (Ts_loop = {z['loop_Ts']:g} s): `{p}_zoh_init`, `{p}_zoh_step(&z, "
                  f"r_fast)` with r_fast[0..{P}_ZOH_PREVIEW]; the law runs every {z['factor']}th call and its "
                  f"output is held (zero-order hold), reached at the slew limit per loop sample (|du| <= "
                  f"{z.get('du_loop', float('inf')):g} N, `{P}_ZOH_DU`); `{P}_LOOP_TS_NS` may be the loop period. "
                  f"Effect on u_ff on the first reference: max|Δu|/max|u| = "
                  f"{z['max_rel_diff_vs_interpolated']:.3g} against the law's u_ff interpolated linearly, mean delay "
                  f"{z['mean_delay_s']:g} s.", ""]
    lines += [f"Compile: `{man['compile']}`. A build for another loop rate stops with `#error` when "
              f"`{P}_LOOP_TS_NS` (the loop period in ns) is defined and differs from `{P}_TS_NS`.", "",
              "## Guard (limits, envelope, fallback)", "",
              f"- saturation u_ff in [{lim['u_min']}, {lim['u_max']}] N (flag SATURATED); slew |Δu| <= {lim['rate']} "
              "N/s x Ts (RATE_LIMITED), from the output at rest before t = 0 (" + ("the law at rest at r0"
              if man["start"]["at"] == "rest" else "0 N") + "); " + man.get("limits_source", ""),
              "- training envelope of (r, dr/dt, d2r/dt2) at every sample of the window r(t-2) .. r(t+P): lo = "
              f"{[float(f'{v:.6g}') for v in env['lo']]}, hi = {[float(f'{v:.6g}') for v in env['hi']]}; outside: "
              f"OUT_OF_RANGE ({'and the fallback' if env['action'] == 'fallback' else 'flag only'})",
              "- a NaN/inf reference sample is replaced by the last finite one (NONFINITE_INPUT) and the sample "
              f"gets the fallback `{man['fallback']['kind']}` (FALLBACK): hold = the last valid output; ramp = that "
              f"output ramped to 0 over {man['fallback']['ramp_time']:g} s; physics = M d2r + sum_j p_j T_j(r, dr) "
              "with every force term of the system (holds on a NaN reference). Never a step to 0 N.",
              "- an overflow (a non-finite regressor or law output, SINGULAR) falls back too; a non-finite law output "
              "latches the fallback until the next init; otherwise the output returns to the law's linearly over "
              f"{man['fallback']['ramp_time']:g} s (FALLBACK until it is back)", "",
              "## Flags (`s.status`)", "", "| flag | bit | meaning |", "| --- | --- | --- |"]
    lines += [f"| `{P}_{n}` | {b} | {d.replace('|', chr(92) + '|')} |" for n, b, d in FLAGS]
    lines += ["", "## Test vectors", "",
              f"`vectors_<case>.csv` (r, u_ff, flags; from the Python law, the MLflow model's code). Check: "
              f"`./main_{name} --check vectors_normal.csv` (exit 0: the flags exactly, u_ff per sample within "
              f"{man['check']['atol']:.3g} N + {man['check']['rtol']:g} |u|; manifest `check`). Never build with "
              "-ffast-math/-Ofast: the C stops with #error.", "",
              "Cases: `normal` (the first evaluation reference from its first sample to a rest: "
              f"{_NORMAL_CUT.get(man['vectors']['normal'].get('cut'), 'as cut')}), `out_of_range` (3 x its "
              "motion), `nonfinite` (a NaN burst and an inf where it moves fastest), `limits` (2 x its motion: "
              "SATURATED / RATE_LIMITED where export.limits sets limits), `past_end` (tables).", "",
              "| case | samples | flags raised (samples) |", "| --- | --- | --- |"]
    lines += [f"| {c} | {v['samples']} | {', '.join(f'{k}: {n}' for k, n in v['flags'].items()) or 'none'} |"
              for c, v in man["vectors"].items()]
    lines += ["", "## Static checks (cppcheck, MISRA C:2012 addon)", ""]
    cc = man.get("cppcheck")
    if not cc or not cc.get("ran"):
        lines += ["Not run at export (" + (cc or {}).get("note", "export.cppcheck=false") + "). Run: "
                  f"`cppcheck --std=c99 --enable=warning,style,performance,portability {name}.c {name}.h` and "
                  f"`cppcheck --std=c99 --addon=misra {name}.c`. Known deviations:", ""]
        rules = {r: "" for r in DEVIATIONS if DEVIATIONS[r] != "none expected"}
    else:
        lines += [f"{cc['version']}: {cc['n_warnings']} finding(s) of warning/style/performance/portability; "
                  f"MISRA C:2012 addon: {cc['misra_total']} finding(s) in {len(cc['misra'])} rule(s):", ""]
        rules = cc["misra"]
    lines += ["| rule | findings | reason |", "| --- | --- | --- |"]
    lines += [f"| {r} | {n if n != '' else '-'} | {DEVIATIONS.get(r, 'not explained')} |" for r, n in rules.items()]
    return "\n".join(lines) + "\n"
