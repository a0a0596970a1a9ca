"""One self-contained package per feedforward: C source, harness, reference and study u_ff as
CSV, the law (json + npz, the MLflow model's data) and ``manifest.json`` (issue 12).

The package is written into a temporary directory and renamed into place when complete: it
appears whole or not at all.  With a C compiler the package is verified before it is kept: the
harness is compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror`` and run on every reference, and
its u_ff must equal the study's to ``rtol`` × max|u| (:class:`~pipeline.export.law.ExportError`
otherwise); the same check runs on the Python law (what the MLflow model returns).  Without a
compiler the source is still written and the manifest says it was not compiled.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.export.c_code import CFLAGS, c_name, write_c
from pipeline.export.law import ExportError, Law, feedforward, strict_json

__all__ = ["find_compiler", "compile_harness", "run_harness", "time_harness", "write_package",
           "replace_dir", "rel_diff"]


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


def run_harness(exe: Path, r_csv: Path) -> np.ndarray:
    out = subprocess.run([str(exe), str(r_csv)], capture_output=True, text=True, timeout=600)
    if out.returncode != 0:
        raise ExportError(f"{exe.name} failed on {r_csv.name}: {out.stderr.strip()[:500]}")
    return np.array([float(v) for v in out.stdout.split()[1:]])


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
                  keep_exe: bool = False) -> dict:
    """Write the package ``out/<name>`` for ``law``, verified on ``references`` = {ref name:
    (r, u_ff of the study)}; returns the manifest.

    ``cc``: the compiler (None: do not compile; a name not found: the package is written
    uncompiled and the manifest says so).  ``source``: provenance for the manifest (run id, git
    SHA, experiment, config hash).  Raises :class:`ExportError` before writing anything when the
    law does not reproduce the study (Python or C) to ``rtol``.
    """
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
        manifest = _build(law, name, tmp, references, source, cc, rtol, timing_repeats, keep_exe)
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


def _build(law, name, folder, references, source, cc, rtol, repeats, keep_exe) -> dict:
    refs = {}
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
    first = next(iter(refs.values()))["file"]
    src = ", ".join(f"{k} {v}" for k, v in source.items() if v)
    write_c(law, name, folder, src, example=first)
    law.save(folder / "law")
    compiler = find_compiler(cc) if cc else None
    manifest = {
        "name": name, "law": law.law, "family": law.family, "model": law.strings.get("model", law.law),
        "Ts": law.Ts, "preview": law.preview, "rest_before_start": law.rest,
        "averaged_model_input": law.averaged, "units": law.units,
        "parameters": law.n_params, **law.flops_per_sample(), **source,
        "files": sorted(p.name for p in folder.iterdir()),
        "compile": " ".join(["cc", *CFLAGS, "-o", f"main_{name}", f"main_{name}.c", f"{name}.c", "-lm"]),
        "references": refs, "rtol": rtol,
        "python_max_rel_diff": max(v["python_max_rel_diff"] for v in refs.values()),
    }
    if compiler is None:
        manifest.update(compiled=False, c_max_rel_diff=None, c_ns_per_sample=None,
                        note=f"no C compiler found ({cc!r}): source written, not compiled or verified")
        return manifest
    exe = compile_harness(folder, name, compiler)
    try:
        for ref, info in refs.items():
            u_c = run_harness(exe, folder / info["file"])
            u = read_column(folder / info["study_u_ff"])
            if u_c.shape != u.shape:
                raise ExportError(f"{exe.name} wrote {u_c.size} samples for {ref!r}, the study has {u.size}")
            info["c_max_rel_diff"] = rel_diff(u_c, u)
            if not info["c_max_rel_diff"] <= rtol:
                raise ExportError(f"the C code of {name} does not reproduce the study on {ref!r}: "
                                  f"max|Δu|/max|u| = {info['c_max_rel_diff']:.3g} > {rtol:g}")
        longest = max(refs.values(), key=lambda v: v["samples"])
        ns = time_harness(exe, folder / longest["file"], repeats) if repeats else None
    finally:
        if not keep_exe:
            exe.unlink(missing_ok=True)
    manifest.update(compiled=True, compiler=compiler_version(compiler),
                    c_max_rel_diff=max(v["c_max_rel_diff"] for v in refs.values()),
                    c_ns_per_sample=ns, timed_on=longest["file"], timing_repeats=repeats)
    return manifest
