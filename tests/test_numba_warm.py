"""The numba warm-up of `make install` (pipeline/numba_warm.py): its list names real kernels with their own
arity and exact types, covers every kernel, and a warmed signature is what the kernel's first call then loads
(no compile)."""
from __future__ import annotations

import inspect
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import numba_warm

ROOT = Path(__file__).resolve().parents[1]


def test_every_listed_signature_names_a_kernel_with_its_arity_and_every_kernel_is_listed():
    ns = numba_warm._types_namespace()
    kernels = {(m, n): d for m in numba_warm.kernel_modules() for n, d in numba_warm._dispatchers(m)}
    listed = set()
    for module, name, text in numba_warm.read_list():
        assert (module, name) in kernels, f"{module}.{name} is no kernel now: refresh the list (make numba-signatures)"
        sig = eval(text, ns)
        assert repr(sig) == text, f"{module}.{name}: {text} reads back as {sig!r}"   # the types, exactly
        n_args = len(inspect.signature(kernels[module, name].py_func).parameters)
        assert isinstance(sig, tuple) and len(sig) == n_args, (
            f"{module}.{name}: {len(sig)} argument types listed, the kernel takes {n_args} (make numba-signatures)")
        listed.add((module, name))
    # an inline="always" kernel is compiled into each caller (numba never caches it on its own)
    own = {k for k, d in kernels.items() if d.targetoptions.get("inline", "never") != "always"}
    assert sorted(own - listed) == [], "kernels the warm-up does not compile: run make numba-signatures"


WARM_THEN_CALL = r"""
import json, sys
from pathlib import Path
from pipeline import numba_warm
from pipeline.systems import force_terms
if sys.argv[1] == "warm":
    term = "pipeline.systems.force_terms.term "
    lines = [l for l in numba_warm.SIGNATURES.read_text().splitlines() if l.startswith(term)]
    Path(sys.argv[2]).write_text("\n".join(lines) + "\n")
    print(json.dumps(numba_warm.warm(Path(sys.argv[2]), jobs=1)))
else:
    out = force_terms.term(2, 0.01, 0.0, 0.003)       # smooth Coulomb: (tanh(v/p), 0, (1 - tanh²)/p)
    st = force_terms.term.stats
    print(json.dumps({"out": list(out), "hits": sum(st.cache_hits.values()), "misses": sum(st.cache_misses.values())}))
"""


def test_a_warmed_signature_is_loaded_by_the_first_call_not_compiled(tmp_path):
    """Warm one kernel into an empty cache folder, then call it in a fresh interpreter: numba loads it (a cache
    hit, no miss: a miss is a compile), and it computes what its Python source does."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}

    def run(*args):
        out = subprocess.run([sys.executable, "-c", WARM_THEN_CALL, *args], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    done, skipped = run("warm", str(tmp_path / "list.txt"))
    assert done >= 1 and skipped == []
    got = run("call")
    assert got["hits"] == 1 and got["misses"] == 0
    t = math.tanh(0.003 / 0.01)
    assert got["out"] == pytest.approx([t, 0.0, (1.0 - t * t) / 0.01], rel=1e-15)
