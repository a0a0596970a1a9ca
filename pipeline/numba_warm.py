"""Compile the package's numba kernels into their cache at install, as ``compileall`` does for the bytecode.

numba compiles a ``cache=True`` kernel the first time it is called with a new signature and keeps the machine
code in ``pipeline/__pycache__/numba-<hash>`` (:func:`pipeline.numba_cache_dir`). On a fresh clone that first
call lands in whatever runs first: ~1 min of a fresh ``make test`` (both workers compiling, measured: 4 min 43 s
cold against 3 min 37 s warm on one clone) and ~10 s of each worker's first ``make reproduce`` job.
``make install`` runs this module, which compiles each kernel for the signatures listed in
``numba_signatures.txt`` (one ``module.kernel (argument types)`` per line), over the usable cores (at most 4).

The list is what the test suite and ``make reproduce`` compile, read from numba's own cache index
(``python -m pipeline.numba_warm --record`` after a test run: ``make numba-signatures``). A stale line (a
kernel renamed, its arguments changed) is skipped with a note and that kernel compiles on first use, as before:
the warm-up can make a first run faster, never wrong, and never fails the install. numba's cache itself keeps a
compiled signature valid only for the kernel's current source and this CPU target (its index key).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

from filelock import FileLock
from numba.core import caching, types
from numba.core.dispatcher import Dispatcher

import pipeline  # the package's __init__ (the ISA pin, NUMBA_CACHE_DIR) runs before this module, numba included

SIGNATURES = Path(__file__).with_name("numba_signatures.txt")


def kernel_modules() -> list[str]:
    """Modules of the package that define numba kernels (the sources :func:`pipeline.numba_cache_dir` hashes)."""
    root = Path(pipeline.__file__).resolve().parent
    return ["pipeline." + ".".join(p.relative_to(root).with_suffix("").parts) for p in pipeline.kernel_sources(root)]


def _dispatchers(module: str):
    mod = importlib.import_module(module)
    for name, obj in sorted(vars(mod).items()):
        if isinstance(obj, Dispatcher) and obj.py_func.__module__ == module:
            yield name, obj


def record() -> list[str]:
    """``module.kernel (types)`` of every signature in numba's cache for the current sources and CPU target."""
    lines = []
    for module in kernel_modules():
        for name, disp in _dispatchers(module):
            cache = getattr(disp, "_cache", None)
            index = cache._cache_file._load_index() if hasattr(cache, "_cache_file") else {}  # {} if stale
            magic = disp.targetctx.codegen().magic_tuple()
            lines += [f"{module}.{name} {key[0]!r}" for key in index if key[1] == magic]
    return sorted(set(lines))


def _types_namespace() -> dict:
    class _Literal:   # Literal[bool](True), as numba prints a literal argument
        def __getitem__(self, _kind):
            return types.literal

    def array(dtype, ndim, layout, readonly=False, aligned=True):
        return types.Array(dtype, ndim, layout, readonly=readonly, aligned=aligned)
    names = {n: getattr(types, n) for n in ("float64", "float32", "int64", "int32", "uint8", "none")}
    return {"__builtins__": {}, "Array": array, "UniTuple": types.UniTuple, "Tuple": types.Tuple,
            "Literal": _Literal(), "bool": types.boolean, **names}


def _lock_cache_saves() -> None:
    """One save of a numba cache entry at a time across the warm-up's processes. numba files a new entry by
    reading the kernel's index, taking the first free data-file number and writing both, unlocked
    (numba/core/caching.py ``IndexDataCacheFile.save``; numba issue #10128): two processes saving signatures of
    one kernel (a callee of kernels in two modules, compiled with each caller) can file one signature's code
    under the other's key. The lock is a file beside the cache."""
    save = caching.IndexDataCacheFile.save
    if getattr(save, "locked", False):      # once per process (a worker warms several modules)
        return
    lock = FileLock(str(Path(os.environ["NUMBA_CACHE_DIR"]) / ".warm.lock"))

    def locked_save(self, key, data):
        with lock:
            return save(self, key, data)
    locked_save.locked = True
    caching.IndexDataCacheFile.save = locked_save


def _warm_module(module: str, entries: list[tuple[str, str]]) -> tuple[int, list[str]]:
    """Compile (or load from the cache) each (kernel, signature) of one module; the lines it could not."""
    _lock_cache_saves()
    ns = _types_namespace()
    try:
        kernels = dict(_dispatchers(module))
    except Exception as exc:   # noqa: BLE001  (a module that no longer imports: its kernels compile on first use)
        return 0, [f"{module}: {type(exc).__name__}: {exc}"]
    done, skipped = 0, []
    for name, text in entries:
        try:
            kernels[name].compile(eval(text, ns))     # our own file; types only, no builtins
            done += 1
        except Exception as exc:   # noqa: BLE001
            skipped.append(f"{module}.{name} {text[:60]}…: {type(exc).__name__}: {str(exc).splitlines()[0][:120]}")
    return done, skipped


def read_list(path: Path = SIGNATURES) -> list[tuple[str, str, str]]:
    """(module, kernel, argument types as numba prints them) of each line of the list."""
    out = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            full, text = line.split(" ", 1)
            out.append((*full.rsplit(".", 1), text))
    return out


def warm(path: Path = SIGNATURES, jobs: int | None = None) -> tuple[int, list[str]]:
    """Compile every listed signature, modules spread over ``jobs`` processes (default: the cores this process
    may use, at most 4: each worker imports torch, ~350 MB)."""
    if not path.exists():
        return 0, [f"{path}: no list (make numba-signatures)"]
    by_module: dict[str, list[tuple[str, str]]] = {}
    for module, name, text in read_list(path):
        by_module.setdefault(module, []).append((name, text))
    jobs = max(1, min(jobs or len(os.sched_getaffinity(0)), 4, len(by_module)))
    done, skipped = 0, []
    # spawn: a fresh interpreter per worker (the pins are read when numba and the BLAS load)
    with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
        for n, bad in pool.map(_warm_module, by_module, by_module.values()):
            done, skipped = done + n, skipped + bad
    return done, skipped


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.numba_warm", description=__doc__.splitlines()[0])
    ap.add_argument("--record", action="store_true",
                    help=f"write {SIGNATURES.name} from numba's cache (after `make test` and `make reproduce`)")
    ap.add_argument("--jobs", type=int, default=None, help="processes (default: the usable cores, at most 4)")
    args = ap.parse_args(argv)
    if args.record:
        lines = record()
        head = ("# numba kernels and argument types that `make install` compiles (pipeline/numba_warm.py);\n"
                "# written by `make numba-signatures` from numba's cache after a test run\n")
        SIGNATURES.write_text(head + "".join(line + "\n" for line in lines))
        print(f"{SIGNATURES}: {len(lines)} signatures")
        return 0
    t0 = time.perf_counter()
    done, skipped = warm(jobs=args.jobs)
    print(f"numba kernels: {done} signatures compiled or loaded from the cache in {time.perf_counter() - t0:.0f} s"
          + (f"; {len(skipped)} skipped (they compile on first use):" if skipped else ""))
    for line in skipped:
        print("  " + line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
