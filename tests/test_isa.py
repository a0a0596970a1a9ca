"""Issue 52: one instruction set for the code paths that decide the bits (``PIPELINE_ISA``, pipeline/__init__.py).

Each check runs a fresh interpreter (the libraries read their code path once, at load). What a library
reports is the check: numpy's dispatched loops, torch's CPU capability, numba's target CPU, OpenBLAS's core.
"""
from __future__ import annotations

import json
import shutil
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import ISA_PINS

ROOT = Path(__file__).resolve().parents[1]
#: the variables the avx2 pin sets (a caller's own values are left out of the probes' environment)
PINS = tuple(ISA_PINS["avx2"])
PROBE = r"""
import json, pipeline, numpy, torch, numba
from numba.core.registry import cpu_target
from numpy._core import _multiarray_umath as m
from threadpoolctl import threadpool_info
cores = sorted({i.get("architecture") for i in threadpool_info() if i.get("internal_api") == "openblas"})
print(json.dumps({"isa": pipeline.ISA, "tag": pipeline.isa_setting(), "torch": torch.backends.cpu.get_cpu_capability(),
                  "numba": numba.config.CPU_NAME,
                  "numba_target": list(cpu_target.target_context.codegen().magic_tuple()[1:]),
                  "x86_v4": bool(m.__cpu_features__.get("X86_V4")), "openblas": cores}))
"""


def _probe(**env) -> dict:
    full = {k: v for k, v in os.environ.items() if k not in ("PIPELINE_ISA", *PINS)}
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, env={**full, **env}, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_default_pins_every_library_to_avx2():
    got = _probe()
    assert got["isa"] == "avx2" and "not applied" not in got["tag"]
    assert got["torch"] in ("AVX2", "DEFAULT")          # DEFAULT on a CPU without AVX2 (nothing faster to pin)
    assert got["numba"] == "haswell" and got["x86_v4"] is False
    # the target numba compiles for (its cache key): Haswell with Haswell's own features ('': LLVM's CPU model);
    # NUMBA_CPU_NAME alone leaves numba the host's feature string, AVX-512 included where the CPU has it
    assert got["numba_target"] == ["haswell", ""]
    assert got["openblas"] in ([], ["Haswell"])         # threadpoolctl names the core OpenBLAS runs


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_native_opts_out_and_is_recorded():
    got = _probe(PIPELINE_ISA="native")
    assert got["isa"] == "native" and got["tag"].startswith("native")
    assert got["numba"] in (None, "host") and got["numba_target"][1] != ""


def test_an_unknown_setting_is_one_line_before_any_work():
    out = subprocess.run([sys.executable, "-c", "import pipeline"], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "PIPELINE_ISA": "avx9"}, timeout=120)
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert "PIPELINE_ISA='avx9' is not known" in out.stderr and "native" in out.stderr


def test_the_cache_key_holds_the_setting(monkeypatch):
    from omegaconf import OmegaConf

    import pipeline
    from pipeline import runner

    class Stage:
        DEPENDS, UPSTREAM = ("seed",), ()
    cfg = OmegaConf.create({"seed": 0})
    a = runner.stage_key(cfg, "generate", Stage, {})
    monkeypatch.setattr(pipeline, "ISA", "native")
    assert runner.stage_key(cfg, "generate", Stage, {}) != a


@pytest.mark.skipif(not Path("/proc/cpuinfo").exists() or "avx512f" not in Path("/proc/cpuinfo").read_text(),
                    reason="needs an AVX-512 CPU: there the native and the pinned paths differ")
def test_the_pin_changes_the_bits_where_the_cpu_has_more():
    """On an AVX-512 CPU a BLAS product (OpenBLAS's dgemm kernel) and numpy's vectorised exp of the pinned and the
    native path differ in the last bits (seen on an AVX-512 EPYC: both): the pin acts; were they equal, pinning
    would be a no-op and an AVX2 laptop would still differ."""
    code = ("import pipeline, numpy as np; rng = np.random.default_rng(0); a = rng.standard_normal((300, 300)); "
            "x = rng.standard_normal(100001); print((a @ a).tobytes().hex()[:4000], np.exp(x).tobytes().hex()[-4000:])")
    runs = []
    for isa in ("avx2", "native"):
        env = {k: v for k, v in os.environ.items() if k not in (*PINS, "MKL_ENABLE_INSTRUCTIONS")}
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env={**env, "PIPELINE_ISA": isa},
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        runs.append(out.stdout)
    assert runs[0] != runs[1]


KERNELS = r"""
import hashlib, json, pipeline, numba, numpy as np, torch
rng = np.random.default_rng(0); a = rng.standard_normal((300, 300)); x = rng.standard_normal(100001)
t = torch.tensor(a)

@numba.njit
def loop(v):
    s = 0.0
    for e in v:
        s += np.tanh(e) * e
    return s

h = lambda z: hashlib.sha256(np.ascontiguousarray(z).tobytes()).hexdigest()
print(json.dumps({"gemm": h(a @ a), "exp": h(np.exp(x)),
                  "lstsq": h(np.linalg.lstsq(a[:, :50], a[:, 0], rcond=None)[0]), "torch_mm": h((t @ t).numpy()),
                  "torch_tanh": h(torch.tanh(t).numpy()), "numba": h(np.array(loop(x)))}))
"""
QEMU = shutil.which("qemu-x86_64")


@pytest.mark.slow      # ~2 min: Python, numpy and torch under the emulator
@pytest.mark.skipif(QEMU is None, reason="needs qemu-user (Debian: apt-get install qemu-user) to emulate an Intel "
                                          "Haswell, an AVX2 CPU without AVX-512")
def test_an_emulated_avx2_laptop_gives_the_same_bits():
    """The same kernels here and on an emulated Intel Haswell (qemu's CPU model: AVX2, FMA, no AVX-512, vendor
    Intel), both with the default pin: equal to the bit. This is what a laptop meets, as its libraries see it."""
    def run(prefix):
        out = subprocess.run([*prefix, sys.executable, "-c", KERNELS], cwd=ROOT, capture_output=True, text=True,
                             timeout=1800, env={k: v for k, v in os.environ.items() if k != "PIPELINE_ISA"})
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])
    assert run([QEMU, "-cpu", "Haswell"]) == run([])
