"""pgnn-feedforward: data-driven feedforward control with physics-guided neural networks."""
from __future__ import annotations

import hashlib
import os
import re
import sys
import tempfile
from pathlib import Path

#: libraries that read their code path at load: loaded before this package, the pin below comes too late
_LOADED_BEFORE = frozenset(m for m in ("numpy", "torch", "numba") if m in sys.modules)

# One BLAS/OpenMP thread per job unless the caller chose otherwise: a multi-threaded GEMM sums in
# another order, so the same config would give different trained models depending on how the job
# was started (measured on EMPS: test force error 4.73 vs 4.64 %). Parallelism comes from running
# jobs side by side (Hydra launchers), not from threads inside one. Set before numpy/torch load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# One instruction set for the kernels that decide the bits (issue 52): a BLAS, a vectorised loop or a
# compiled kernel picks its code path by the CPU (AVX-512 on a server, AVX2 on a laptop, another MKL branch
# on AMD than on Intel), and each path sums in its own order, so a nonconvex fit lands elsewhere.
# PIPELINE_ISA=avx2 (default) sets every library this package computes with to a path that every x86-64 CPU
# with AVX2 runs the same way (checked against an emulated Intel Haswell: tests/test_isa.py);
# PIPELINE_ISA=native leaves each library its own choice and your own variables (faster on AVX-512, other
# bits). Under avx2 these values are set, not defaulted: a shell's MKL_CBWR=AVX2 would pick MKL's
# vendor-specific branch again. Read before numpy, scipy, torch and numba load (they read them once).
ISA_PINS = {"avx2": {
    "OPENBLAS_CORETYPE": "Haswell",            # numpy's and scipy's OpenBLAS (DYNAMIC_ARCH builds)
    "MKL_CBWR": "COMPATIBLE",                  # torch's MKL: its one branch for Intel and AMD alike (AVX2 differs)
    "ATEN_CPU_CAPABILITY": "avx2",             # torch's own vectorised kernels
    "NUMBA_CPU_NAME": "haswell",               # numba's target (its cache is keyed by it)
    "NUMBA_CPU_FEATURES": "",                  # ... and its own features (unset: the host's, AVX-512 too)
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",   # numpy 2.x: its loops to X86_V3 (AVX2)
}}
ISA = os.environ.setdefault("PIPELINE_ISA", "avx2")
if ISA not in ("native", *ISA_PINS):
    raise SystemExit(f"error: PIPELINE_ISA={ISA!r} is not known; use one of {['native', *ISA_PINS]} "
                     "(avx2: the same bits on any x86-64 with AVX2, the default; native: each library's own choice)")
#: variables the caller had set otherwise, replaced by the pin (named in the run tag)
_REPLACED = {k: os.environ[k] for k, v in ISA_PINS.get(ISA, {}).items() if os.environ.get(k, v) != v}
os.environ.update(ISA_PINS.get(ISA, {}))


def isa_setting() -> str:
    """What pins the code paths of this process (the run tag ``isa``): the setting and the variables in
    force, what it replaced, or why it may not hold (a library loaded before this package set them)."""
    late = [m for m in ("numpy", "torch", "numba") if m in _LOADED_BEFORE]
    pins = {k: os.environ.get(k, "") for k in ISA_PINS["avx2"]}
    text = f"{ISA}: " + ", ".join(f"{k}={v}" for k, v in pins.items() if v or ISA in ISA_PINS)  # '': set empty
    if _REPLACED and ISA != "native":
        text += " (replaced " + ", ".join(f"{k}={v}" for k, v in _REPLACED.items()) + ")"
    return text + (f" (not applied: {', '.join(late)} loaded before pipeline)" if late and ISA != "native" else "")


def numba_cache_dir(root: Path | None = None) -> str:
    """The numba cache folder of this version of the package's numba kernels.

    numba keys a ``cache=True`` function by its own source file only: a kernel calling (inlining) a
    function of another module keeps the old callee after that module changes, and computes with it
    silently (seen here: the analytic inversion kept a stale ``_fast_physics``).  One folder per
    SHA-256 of every module that defines a kernel (:func:`kernel_sources`) makes any such edit a new cache.  Beside the
    bytecode (``pipeline/__pycache__/numba-<hash>``), or in the temp folder where that is read-only."""
    root = Path(__file__).resolve().parent if root is None else Path(root)
    digest = source_digest((p.relative_to(root).as_posix(), p.read_bytes()) for p in kernel_sources(root))
    base = root / "__pycache__"
    if not os.access(base if base.exists() else root, os.W_OK):
        base = Path(tempfile.gettempdir()) / "pgnn-feedforward"
    return str(base / f"numba-{digest[:16]}")


#: a module numba compiles from: a line decorated ``@numba.njit``, ``@njit``, ``@jit``, ``@vectorize``, ``@intrinsic``,
#: ``@overload``, ``@register_jitable`` (with or without ``numba.``/``nb.``; a typing ``@overload`` only adds a file)
_KERNEL = re.compile(rb"^[ \t]*@(?:numba\.|nb\.)?"
                     rb"(?:njit|jit|vectorize|guvectorize|intrinsic|overload|register_jitable)\b", re.M)


def kernel_sources(root: Path | None = None) -> list[Path]:
    """The package's source files that define numba kernels or what they compile with (sorted)."""
    root = Path(__file__).resolve().parent if root is None else Path(root)
    return [p for p in sorted(root.rglob("*.py")) if _KERNEL.search(p.read_bytes())]


def source_digest(sources) -> str:
    """SHA-256 (hex) of ``(name, bytes)`` pairs in the given order: the key of a cache compiled from
    source files (the numba folder above, the options' defaults of :mod:`pipeline.schema`)."""
    h = hashlib.sha256()
    for name, text in sources:
        h.update(name.encode() + b"\0" + text)
    return h.hexdigest()


# before numba loads (a caller's own NUMBA_CACHE_DIR wins)
os.environ.setdefault("NUMBA_CACHE_DIR", numba_cache_dir())
