"""pgnn-feedforward: data-driven feedforward control with physics-guided neural networks."""
from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

# One BLAS/OpenMP thread per job unless the caller chose otherwise: a multi-threaded GEMM sums in
# another order, so the same config would give different trained models depending on how the job
# was started (measured on EMPS: test force error 4.73 vs 4.64 %). Parallelism comes from running
# jobs side by side (Hydra launchers), not from threads inside one. Set before numpy/torch load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def numba_cache_dir(root: Path | None = None) -> str:
    """The numba cache folder of this version of the package's numba kernels.

    numba keys a ``cache=True`` function by its own source file only: a kernel calling (inlining) a
    function of another module keeps the old callee after that module changes, and computes with it
    silently (seen here: the analytic inversion kept a stale ``_fast_physics``).  One folder per
    SHA-256 of every module that compiles with numba makes any such edit a new cache.  Beside the
    bytecode (``pipeline/__pycache__/numba-<hash>``), or in the temp folder where that is read-only."""
    root = Path(__file__).resolve().parent if root is None else Path(root)
    sources = ((p.relative_to(root).as_posix(), p.read_bytes()) for p in sorted(root.rglob("*.py")))
    digest = source_digest((name, text) for name, text in sources if b"numba" in text)
    base = root / "__pycache__"
    if not os.access(base if base.exists() else root, os.W_OK):
        base = Path(tempfile.gettempdir()) / "pgnn-feedforward"
    return str(base / f"numba-{digest[:16]}")


def source_digest(sources) -> str:
    """SHA-256 (hex) of ``(name, bytes)`` pairs in the given order: the key of a cache compiled from
    source files (the numba folder above, the options' defaults of :mod:`pipeline.schema`)."""
    h = hashlib.sha256()
    for name, text in sources:
        h.update(name.encode() + b"\0" + text)
    return h.hexdigest()


# before numba loads (a caller's own NUMBA_CACHE_DIR wins)
os.environ.setdefault("NUMBA_CACHE_DIR", numba_cache_dir())
