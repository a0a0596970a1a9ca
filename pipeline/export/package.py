"""One self-contained package per feedforward: C source, harness, reference and study u_ff as
CSV, the law (json + npz, the MLflow model's data) and ``manifest.json`` (issue 12).

The package is written into a temporary directory and renamed into place when complete: it
appears whole or not at all.  With a C compiler the package is verified before it is kept: the
harness is compiled with ``cc`` and :data:`~pipeline.export.c_code.CFLAGS` (``-std=c99 -O2 -Wall -Wextra -Werror
-Wconversion -Wdouble-promotion``) and run on every reference, and
its u_ff must equal the study's to ``rtol`` × max|u| (:class:`~pipeline.export.law.ExportError`
otherwise); the same check runs on the Python law (what the MLflow model returns).  Without a
compiler the source is still written and the manifest says it was not compiled.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.export.c_code import CFLAGS, c_name, write_c
from pipeline.export.guard import FLAGS, zoh_loop
from pipeline.export.law import ExportError, Law, _rest_value, feedforward, guarded, start_position, strict_json
from pipeline.export.misra import cppcheck_report, readme

__all__ = ["find_compiler", "compile_harness", "run_harness", "time_harness", "write_package",
           "replace_dir", "rel_diff", "default_prefix", "check_prefix", "law_hash", "VECTOR_SAMPLES",
           "check_bound"]

#: the test vectors' length where the reference comes to rest [samples]: as many whole moves as end within it
VECTOR_SAMPLES = 4000
#: the longest test vector [samples]: a first move that ends later than VECTOR_SAMPLES is kept whole up to this
VECTOR_MOVE_MAX = 20000
#: samples of rest kept after the last whole move in a test vector (beyond the law's preview)
VECTOR_REST = 50
#: a C identifier; the prefix's symbols are <prefix>_init, <prefix>_step, <PREFIX>_TS, ...
_IDENT = __import__("re").compile(r"[A-Za-z][A-Za-z0-9_]{0,39}")


def law_hash(law: Law) -> str:
    """sha256 of the law's data (law.json fields and arrays): two different laws, two hashes."""
    h = hashlib.sha256(strict_json({k: v for k, v in law.__dict__.items() if k != "arrays"}).encode())
    for k in sorted(law.arrays):
        h.update(k.encode())
        h.update(np.ascontiguousarray(law.arrays[k]).tobytes())
    return h.hexdigest()


def default_prefix(law: Law, name: str, precision: str = "double") -> str:
    """``<package>_<8 hex of the law's hash>`` (``_f32`` added for the float build): laws of one kind from
    different runs, and the float and double builds of one law, link together."""
    return f"{c_name(name)}_{law_hash(law)[:8]}" + ("_f32" if precision == "single" else "")


def check_bound(u_study: np.ndarray, precision: str, rtol: float, single_rtol: float) -> dict:
    """The harness's --check bound per sample, |u_c(t) - u(t)| <= atol + rtol |u(t)| (manifest "check").

    The scale is the RMS of the study's u_ff on the first reference, not its max: one end spike (992 N against a
    94 N motion) set max|u| and let an all-zero output pass a bound of tol x max|u|. double: the C runs the
    study's operations in the same order, so it agrees to rounding: rtol = export.rtol, atol = rtol x the scale
    (a sample near 0 N). single: float keeps 24 bits (eps = 2^-23 = 1.2e-7) of every quantity the law forms,
    and the laws difference positions (δ²r = (r(t+1) - 2 r(t) + r(t-1))/Ts² amplifies the rounding of r by
    |r|/(|δ²r| Ts²)) and take the sign of velocities below float resolution (a Coulomb term is then missing):
    errors that scale with the law's magnitude over the motion, not with eps |u(t)|; single_rtol
    (export.single_rtol, what the float law is accepted to against the double study) bounds them per sample, as
    single_rtol x (the scale + |u(t)|)."""
    u = np.asarray(u_study, dtype=np.float64)
    scale = float(np.sqrt(np.mean(u * u))) if u.size else 0.0
    rt = float(single_rtol if precision == "single" else rtol)
    # single: a float value on a limit or on the envelope's edge falls on either side of it by rounding, so the
    # threshold flags are not compared there (the output still is, per sample); every other flag exactly
    loose = ("SATURATED", "RATE_LIMITED", "OUT_OF_RANGE") if precision == "single" else ()
    mask = sum(b for n, b, _ in FLAGS if n not in loose)
    return {"rtol": rt, "atol": rt * scale, "u_scale": scale, "u_scale_is": "RMS of the study's u_ff on the first "
            "reference", "flag_mask": int(mask),
            "bound": "|u_c(t) - u(t)| <= atol + rtol |u(t)| per sample; flags exactly"
                     + (f" but {', '.join(loose)} (float rounding decides a sample on a limit)" if loose else "")}


def check_prefix(prefix: str) -> str | None:
    """What is wrong with ``prefix`` as the C symbol prefix, or None."""
    if not _IDENT.fullmatch(prefix):
        return ("is not a C identifier prefix: a letter, then letters, digits or '_', at most 40 characters "
                "(its symbols are <prefix>_init, <prefix>_step, <PREFIX>_TS, ...)")
    if prefix.startswith("_") or "__" in prefix:
        return "is reserved in C (a leading '_' or '__'): use letters, digits and single '_'"
    return None


def find_compiler(cc: str | None = None) -> str | None:
    """Path of the C compiler ``cc`` (default ``$CC`` or ``cc``), None if there is none."""
    return shutil.which(cc or os.environ.get("CC") or "cc")


def compiler_version(cc: str) -> str:
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
        return out.stdout.splitlines()[0] if out.stdout else cc
    except (OSError, subprocess.SubprocessError):
        return cc


def compile_harness(folder: Path, name: str, cc: str) -> Path:
    """Compile ``main_<name>.c`` + ``<name>.c`` warning-free; returns the executable."""
    folder = Path(folder)
    exe = folder / f"main_{name}"
    cmd = [cc, *CFLAGS, "-o", str(exe), str(folder / f"main_{name}.c"), str(folder / f"{name}.c"), "-lm"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    if out.returncode != 0:
        raise ExportError(f"the generated C of {name} does not compile with {' '.join(cmd[:1] + list(CFLAGS))}:\n"
                          + out.stderr.strip()[:4000])
    return exe


def _write_column(path: Path, header: str, x: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write(header + "\n")
        f.writelines(f"{float(v)!r}\n" for v in np.asarray(x, dtype=np.float64))


def read_column(path: Path) -> np.ndarray:
    """The numbers of a one-column CSV (header lines skipped)."""
    vals = []
    for line in Path(path).read_text().splitlines():
        try:
            vals.append(float(line.split(",")[-1]))
        except ValueError:
            continue
    return np.array(vals)


def run_harness(exe: Path, r_csv: Path, flags: bool = False):
    """u_ff of the harness on a reference CSV; with ``flags``: (u_ff, flags)."""
    out = subprocess.run([str(exe), str(r_csv)] + (["--flags"] if flags else []), capture_output=True, text=True,
                         timeout=600)
    if out.returncode != 0:
        raise ExportError(f"{exe.name} failed on {r_csv.name}: {out.stderr.strip()[:500]}")
    if not flags:
        return np.array([float(v) for v in out.stdout.split()[1:]])
    rows = [line.split(",") for line in out.stdout.split()[1:]]
    return np.array([float(a) for a, _ in rows]), np.array([int(b) for _, b in rows], dtype=np.int64)


def check_vectors(exe: Path, vectors: Path) -> subprocess.CompletedProcess:
    """``main_<name> --check vectors.csv`` (exit 0: C agrees with the vectors)."""
    return subprocess.run([str(exe), "--check", str(vectors)], capture_output=True, text=True, timeout=600)


def time_harness(exe: Path, r_csv: Path, repeats: int = 21) -> float:
    """Median wall time per sample [ns] of the C law over ``repeats`` runs of the reference."""
    out = subprocess.run([str(exe), str(r_csv), "--time", str(int(repeats))], capture_output=True,
                         text=True, timeout=600)
    for line in out.stderr.splitlines():
        if line.startswith("ns_per_sample="):
            return float(line.split("=", 1)[1])
    raise ExportError(f"{exe.name} --time printed no timing: {out.stderr.strip()[:300]}")


def rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / max |b| (0 for two zero signals)."""
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    d = float(np.max(np.abs(a - b))) if b.size else 0.0
    return d / scale if scale > 0 else d


def replace_dir(src: Path, final: Path) -> None:
    """Move the complete folder ``src`` to ``final``, replacing an existing one: the old one is moved
    aside first, so ``final`` is always a whole package (or absent)."""
    if final.exists():
        old = final.with_name(f".old-{final.name}-{time.time_ns()}")
        os.rename(final, old)
        shutil.rmtree(old, ignore_errors=True)
    os.rename(src, final)


def write_package(law: Law, name: str, out: Path, references: dict, *, source: dict,
                  cc: str | None = "cc", rtol: float = 1e-9, timing_repeats: int = 21,
                  keep_exe: bool = False, prefix: str | None = None, precision: str = "double",
                  single_rtol: float = 1e-3, zoh_n: int = 1, cppcheck: bool = False) -> dict:
    """Write the package ``out/<name>`` for ``law``, verified on ``references`` = {ref name:
    (r, u_ff of the study)}; returns the manifest.

    ``cc``: the compiler (None: do not compile; a name not found: the package is written
    uncompiled and the manifest says so).  ``source``: provenance for the manifest (run id, git
    SHA, experiment, config hash).  Raises :class:`ExportError` before writing anything when the
    law does not reproduce the study (Python or C) to ``rtol``.  ``prefix``: the C symbols' prefix
    (default :func:`default_prefix`); ``precision``: double | single (the float C is measured against
    the double study and accepted to ``single_rtol``); ``zoh_n`` > 1: a zero-order-hold wrapper for a
    loop ``zoh_n`` times faster, its effect measured; ``cppcheck``: run cppcheck and its MISRA addon.
    """
    opts = dict(prefix=prefix or default_prefix(law, name, precision), precision=precision, single_rtol=single_rtol,
                zoh_n=int(zoh_n), cppcheck=cppcheck)
    why = check_prefix(opts["prefix"])
    if why:
        raise ExportError(f"export.prefix={opts['prefix']!r} {why}")
    name = c_name(name)
    out = Path(out)
    if not references:
        raise ExportError(f"no reference to verify {name} on: give at least one (evaluate.references)")
    clash = reference_file_clash(references)
    if clash:
        raise ExportError(clash)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{name}-", dir=out))
    try:
        manifest = _build(law, name, tmp, references, source, cc, rtol, timing_repeats, keep_exe, **opts)
        (tmp / "README.md").write_text(readme(law, name, manifest))
        manifest["files"] = sorted(p.name for p in tmp.iterdir())
        (tmp / "manifest.json").write_text(strict_json(manifest))
        replace_dir(tmp, out / name)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def reference_file_clash(names) -> str | None:
    """Two reference names that give one file name (``r_<c_name>.csv``: v0.15 and v0_15) would
    overwrite each other's files: say which, or None."""
    seen: dict[str, str] = {}
    for ref in names:
        other = seen.setdefault(c_name(ref), ref)
        if other != ref:
            return (f"references {other!r} and {ref!r} give the same file name r_{c_name(ref)}.csv in the "
                    "export package: rename one (letters, digits and '_' are kept, other characters become '_')")
    return None


def normal_window(r: np.ndarray, preview: int) -> tuple[np.ndarray, str]:
    """(the ``normal`` test vector's reference, how it was cut): ``r`` from its first sample (a table law is
    indexed from it) to :data:`VECTOR_REST` samples past the law's ``preview`` into the last rest (r constant)
    that begins within :data:`VECTOR_SAMPLES`: whole moves; if the first move ends later, up to the end of that
    move (at most :data:`VECTOR_MOVE_MAX` samples); else the first VECTOR_SAMPLES, cut in motion. A vector cut
    in motion ends in a stop the reference never makes (past its end the law holds the last sample): its forces
    and flags there are the cut's, not the reference's (a 376 N spike, SATURATED, on [B1]'s v0.15 cut at 4000)."""
    moving = np.diff(r) != 0                       # a reference at rest is constant
    idx = np.flatnonzero(moving)
    if idx.size == 0:
        return r[:VECTOR_SAMPLES], "at rest"
    hold = max(int(preview), 0) + VECTOR_REST       # the law sees rest over its preview, and the tail is at rest
    # a sample j that starts a rest of `hold` samples after motion: moving[j-1], then r[j .. j+hold] constant
    still = np.convolve((~moving).astype(np.int64), np.ones(hold, dtype=np.int64), "valid") == hold
    rest_at = np.flatnonzero(still[1:] & moving[:still.size - 1]) + 1   # j: moving[j-1] and still[j]
    ends = rest_at + hold + 1                       # the vector's end: `hold` samples into that rest
    fits = ends[ends <= VECTOR_SAMPLES]
    if fits.size:
        return r[:int(fits[-1])], "whole moves"
    if ends.size and ends[0] <= VECTOR_MOVE_MAX:
        return r[:int(ends[0])], "the first move"
    return r[:VECTOR_SAMPLES], "cut in motion"


def _vectors(law: Law, r: np.ndarray) -> dict[str, np.ndarray]:
    """The test vectors' references: normal operation ``r`` (:func:`normal_window`) and one per flag path (during
    motion); a table's ``past_end`` is its whole reference and 50 samples past it."""
    r0 = r[0]
    k = int(np.argmax(np.abs(np.diff(r)))) if r.size > 1 else 0    # the fastest sample: in motion
    nan = r.copy()
    nan[k:k + 20] = np.nan                                         # a NaN burst, then an inf
    nan[min(k + 40, r.size - 1)] = np.inf
    cases = {"normal": r, "out_of_range": r0 + 3.0 * (r - r0), "nonfinite": nan,
             "limits": r0 + 2.0 * (r - r0)}
    if law.family == "table":                                      # the whole table, then 50 samples past it
        table = law.arrays["r"]
        cases["past_end"] = np.concatenate([table, np.full(50, table[-1])])
    return cases


def _write_vectors(path: Path, r: np.ndarray, u: np.ndarray, flags: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write("r,u_ff,flags\n")
        f.writelines(f"{float(a)!r},{float(b)!r},{int(c)}\n" for a, b, c in zip(r, u, flags))


def write_feedforward_csv(path: Path, Ts: float, r, u, flags) -> None:
    """The feedforward of one reference where a user looks (issue 49): t [s], r, u_ff (17 digits: the doubles) and
    flags by name (``|``-joined, e.g. ``SATURATED|RATE_LIMITED``; empty where nothing acted)."""
    flags = np.asarray(flags, dtype=np.int64)
    words = {int(v): "|".join(n for n, b, _ in FLAGS if int(v) & b) for v in np.unique(flags)}
    with open(path, "w") as f:
        f.write("t,r,u_ff,flags\n")
        f.writelines(f"{k * Ts!r},{float(a)!r},{float(b)!r},{words[int(c)]}\n"
                     for k, (a, b, c) in enumerate(zip(r, u, flags)))


def _flag_counts(flags: np.ndarray) -> dict:
    return {n: int(np.count_nonzero(flags & b)) for n, b, _ in FLAGS if np.any(flags & b)}


def _zoh_effect(law: Law, r: np.ndarray, n: int) -> dict:
    """The zero-order hold at n x the law's rate on the reference r: its u_ff at the loop rate
    (each law output held n samples) against the law's u_ff linearly interpolated to the loop rate."""
    u = guarded(law, r)[0]
    t = np.arange(u.size)
    tf = np.arange((u.size - 1) * n + 1) / n
    du_loop = law.g.du_max(law.Ts) / n               # the wrapper's slew limit per loop sample (templates/zoh.c)
    r0 = start_position(law, r)
    held = zoh_loop(u, n, du_loop, _rest_value(law, r0 if np.isfinite(r0) else 0.0)[1])[:tf.size]  # from u(-1)
    lin = np.interp(tf, t, u)
    return {"loop_Ts": law.Ts / n, "factor": n, "du_loop": du_loop,
            "max_rel_diff_vs_interpolated": rel_diff(held, lin),
            "rms_rel_diff_vs_interpolated": float(np.sqrt(np.mean((held - lin) ** 2))
                                                  / max(np.max(np.abs(lin)), 1e-300)),
            "mean_delay_s": law.Ts * (n - 1) / (2 * n)}


def _build(law, name, folder, references, source, cc, rtol, repeats, keep_exe, *, prefix, precision,
           single_rtol, zoh_n, cppcheck) -> dict:
    refs, guarded_u = {}, {}      # guarded_u: the guarded Python law per reference (u_ff, flags), for the C check
    for ref, (r, u) in references.items():
        r, u = np.asarray(r, dtype=np.float64), np.asarray(u, dtype=np.float64)
        if r.shape != u.shape or r.ndim != 1:
            raise ExportError(f"reference {ref!r}: r {r.shape} and u_ff {u.shape} must be one 1-D length")
        safe = c_name(ref)
        _write_column(folder / f"r_{safe}.csv", "r", r)
        _write_column(folder / f"u_ff_{safe}.csv", "u_ff", u)
        refs[ref] = {"file": f"r_{safe}.csv", "study_u_ff": f"u_ff_{safe}.csv", "samples": int(r.size),
                     "max_abs_u_ff": float(np.max(np.abs(u)))}
        d = rel_diff(feedforward(law, r), u)
        refs[ref]["python_max_rel_diff"] = d
        if not d <= rtol:
            raise ExportError(f"the exported law {name} does not reproduce the study on {ref!r} in Python: "
                              f"max|Δu|/max|u| = {d:.3g} > {rtol:g}")
        ug, fg = guarded_u[ref] = guarded(law, r)
        write_feedforward_csv(folder / f"feedforward_{safe}.csv", law.Ts, r, ug, fg)     # as shipped, with its flags
        refs[ref]["feedforward"] = f"feedforward_{safe}.csv"
        refs[ref]["guard_max_rel_change"] = rel_diff(ug, u)      # 0: the guard left the study's u_ff alone
        refs[ref]["flags"] = _flag_counts(fg)
    first = next(iter(refs.values()))["file"]
    src = ", ".join(f"{k} {v}" for k, v in source.items() if v)
    single = precision == "single"
    tol = single_rtol if single else rtol
    chk = check_bound(next(iter(references.values()))[1], precision, rtol, single_rtol)
    write_c(law, name, folder, src, example=first, prefix=prefix, precision=precision, zoh_n=zoh_n,
            check_tol=chk["rtol"], check_atol=chk["atol"], check_mask=chk["flag_mask"])
    law.save(folder / "law")
    r_first = np.asarray(next(iter(references.values()))[0], dtype=np.float64)
    vectors = {}
    r_normal, cut = normal_window(r_first, law.preview)
    for case, rv in _vectors(law, r_normal).items():
        uv, fv = guarded(law, rv)
        _write_vectors(folder / f"vectors_{case}.csv", rv, uv, fv)
        vectors[case] = {"file": f"vectors_{case}.csv", "samples": int(rv.size), "flags": _flag_counts(fv)}
    vectors["normal"]["cut"] = cut
    compiler = find_compiler(cc) if cc else None
    g = law.g
    manifest = {
        "name": name, "prefix": prefix, "law": law.law, "family": law.family,
        "model": law.strings.get("model", law.law),
        "Ts": law.Ts, "rate_hz": 1.0 / law.Ts, "preview": law.preview,
        "rest_before_start": "r0" if law.start == "rest" else law.rest, "start": law.start_doc(),
        "averaged_model_input": law.averaged, "units": law.units, "precision": precision,
        "parameters": law.n_params, **law.flops_per_sample(), **source,
        "limits": {"u_min": g.u_min, "u_max": g.u_max, "rate": g.rate},
        "limits_source": law.strings.get("limits_source", "export.limits (null: no limit)"),
        "envelope": {"regressors": ["r", "dr/dt", "d2r/dt2"], "lo": g.env_lo, "hi": g.env_hi,
                     "action": g.envelope_action},
        "fallback": {"kind": g.fallback, "ramp_time": g.ramp_time, "physics": g.physics,
                     "physics_codes": g.physics_codes, "physics_consts": g.physics_consts},
        "flag_bits": {n: b for n, b, _ in FLAGS},
        "vectors": vectors,
        "files": sorted(p.name for p in folder.iterdir()),
        "compile": " ".join(["cc", *CFLAGS, "-o", f"main_{name}", f"main_{name}.c", f"{name}.c", "-lm"]),
        "references": refs, "rtol": rtol, "check": chk,
        "python_max_rel_diff": max(v["python_max_rel_diff"] for v in refs.values()),
    }
    if zoh_n > 1:
        manifest["zoh"] = _zoh_effect(law, r_first, zoh_n)
    if cppcheck:
        manifest["cppcheck"] = cppcheck_report(folder, name)
    if compiler is None:
        manifest.update(compiled=False, c_max_rel_diff=None, c_ns_per_sample=None,
                        note=f"no C compiler found ({cc!r}): source written, not compiled or verified")
        return manifest
    exe = compile_harness(folder, name, compiler)
    try:
        for ref, info in refs.items():
            u_c, f_c = run_harness(exe, folder / info["file"], flags=True)
            u = read_column(folder / info["study_u_ff"])
            if u_c.shape != u.shape:
                raise ExportError(f"{exe.name} wrote {u_c.size} samples for {ref!r}, the study has {u.size}")
            ug, fg = guarded_u[ref]
            info["c_max_rel_diff"] = rel_diff(u_c, ug)        # C against the (guarded) Python law
            info["c_vs_study_max_rel_diff"] = rel_diff(u_c, u)
            info["c_flags_agree"] = bool(np.array_equal(f_c, fg))
            if not info["c_max_rel_diff"] <= tol or not (single or info["c_flags_agree"]):
                raise ExportError(f"the C code of {name} does not reproduce the study on {ref!r}: "
                                  f"max|Δu|/max|u| = {info['c_max_rel_diff']:.3g} > {tol:g}"
                                  + ("" if info["c_flags_agree"] else " or its flags differ from the Python law's"))
        for case, info in vectors.items():
            out = check_vectors(exe, folder / info["file"])
            info["c_check"] = "pass" if out.returncode == 0 else out.stderr.strip()[-300:]
            if out.returncode != 0:
                raise ExportError(f"the C code of {name} fails its test vectors {info['file']}: {info['c_check']}")
        longest = max(refs.values(), key=lambda v: v["samples"])
        ns = time_harness(exe, folder / longest["file"], repeats) if repeats else None
    finally:
        if not keep_exe:
            exe.unlink(missing_ok=True)
    manifest.update(compiled=True, compiler=compiler_version(compiler),
                    c_max_rel_diff=max(v["c_max_rel_diff"] for v in refs.values()),
                    c_ns_per_sample=ns, timed_on=longest["file"], timing_repeats=repeats)
    if single:
        manifest["single_max_rel_diff"] = max(v["c_vs_study_max_rel_diff"] for v in refs.values())
        manifest["single_rtol"] = single_rtol
    return manifest
