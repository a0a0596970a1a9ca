"""The plumbing stays acyclic (issue 21): no import cycle among the modules of pipeline/ and stages/,
counting imports inside functions too (they hide cycles as well as they hide start-up cost)."""
import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _graph() -> dict[str, set[str]]:
    mods = {}
    for base in ("pipeline", "stages"):
        for f in (ROOT / base).rglob("*.py"):
            parts = f.relative_to(ROOT).with_suffix("").parts
            mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph = {m: set() for m in mods}
    for m, f in mods.items():
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                r = resolve(t)
                if r and r != m and not m.startswith(r + "."):    # a package's own __init__ is not an edge
                    graph[m].add(r)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, on, stack, out = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_in_pipeline_and_stages():
    graph = _graph()
    assert "pipeline.runner" in graph and "pipeline.errors" in graph["pipeline.schema"]
    assert _cycles(graph) == []


def test_errors_and_cache_import_nothing_of_the_pipeline():
    graph = _graph()
    assert graph["pipeline.errors"] == set()
    assert graph["pipeline.atomic"] == set()     # the safe writer (issue 51): a leaf the cache may use
    assert graph["pipeline.cache"] <= {"pipeline.atomic"}


#: names a stage holds config nodes in (cfg, ctx.cfg, a group node such as m = cfg.model)
_CONFIG_NAMES = ("cfg", "m", "ident", "e", "reg", "model", "identify", "evaluate", "regularizer", "data",
                 "report", "export", "invert", "system")


def _inline_defaults(tree: ast.AST) -> list[str]:
    """``<config>.get("key", default)`` and ``OmegaConf.select(..., default=...)`` calls."""
    out = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        receiver = ast.unparse(node.func.value)
        parts = set(receiver.replace("(", ".").replace(")", ".").split("."))
        if node.func.attr == "get" and len(node.args) == 2 and parts & set(_CONFIG_NAMES):
            out.append(ast.unparse(node))
        if node.func.attr == "select" and any(k.arg == "default" for k in node.keywords):
            out.append(ast.unparse(node))
    return out


def test_the_inline_default_finder_finds_one():
    assert _inline_defaults(ast.parse("x = cfg.evaluate.get('tail', 0.2)")) == ["cfg.evaluate.get('tail', 0.2)"]
    assert _inline_defaults(ast.parse("x = m.get('hidden')")) == []          # None: a key that may be unset
    assert _inline_defaults(ast.parse("x = info.get('rtol', 0.02)")) == []   # not a config node


def test_no_stage_reads_a_config_key_with_a_default_of_its_own():
    """Issue 21 item 1 (part): a key's default is stated once, in its option's parameter class, which
    Hydra composes in (schema.register) and schema.check sets if still left out, before any stage runs;
    stages read keys without a default."""
    files = [f for f in sorted((ROOT / "stages").rglob("*.py")) if "report" not in f.parts]  # report: run metrics
    found = {str(f.relative_to(ROOT)): hits for f in files if (hits := _inline_defaults(ast.parse(f.read_text())))}
    assert found == {}


def test_stages_ask_the_objects_not_their_class_names():
    """Issue 21 item 3 (part): stages and the export law builders dispatch on what a system or a
    physics model says (``System.measured``, ``PhysicsModel.physics_law``), not on
    ``isinstance(…, Recording)`` or ``type(…).__name__``."""
    hits = []
    files = sorted((ROOT / "stages").rglob("*.py")) + sorted((ROOT / "pipeline" / "export").rglob("*.py"))
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            text = ast.unparse(node) if isinstance(node, (ast.Call, ast.Compare)) else ""
            if (isinstance(node, ast.Call) and text.startswith("isinstance(") and "Recording" in text) or \
                    (isinstance(node, ast.Compare) and "__name__" in text and "type(" in text):
                hits.append(f"{f.relative_to(ROOT)}: {text}")
    assert hits == []


def _function_imports() -> list[tuple[str, int, str]]:
    """(file, line, source line) of every import inside a function in pipeline/ and stages/."""
    out = []
    for base in ("pipeline", "stages"):
        for f in sorted((ROOT / base).rglob("*.py")):
            src = f.read_text()
            lines = src.splitlines()
            seen = set()
            for node in ast.walk(ast.parse(src)):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    for sub in ast.walk(node):
                        if isinstance(sub, (ast.Import, ast.ImportFrom)) and sub.lineno not in seen:
                            seen.add(sub.lineno)
                            out.append((str(f.relative_to(ROOT)), sub.lineno, lines[sub.lineno - 1].strip()))
    return out


def test_every_import_inside_a_function_says_why_it_is_lazy():
    """Issue 21 item 5: imports at module top, unless deliberately lazy: a measured start-up saving
    (``# lazy: saves N.N s of start-up (<what>)``) or, kept only for a large restructuring, a cycle
    it would close (``# lazy: would close the cycle a -> b -> a``). A new hidden import is refused."""
    found = _function_imports()
    assert any(f == "pipeline/plots.py" for f, _, _ in found)       # the walk sees function bodies
    bare = [f"{f}:{n}: {line}" for f, n, line in found if "# lazy: " not in line]
    assert bare == []
    for f, n, line in found:
        why = line.split("# lazy: ", 1)[1]
        assert re.match(r"saves \d+\.\d+ s of start-up \(.+\)|would close the cycle \S+( -> \S+)+", why), \
            f"{f}:{n}: {line}"


#: the numerical library: what a user scripts against without Hydra, OmegaConf or MLflow
_LIBRARY = ("pipeline.systems", "pipeline.models", "pipeline.identify", "pipeline.invert", "pipeline.metrics",
            "pipeline.metrics_bound", "pipeline.references", "pipeline.params")


def _external(module: str) -> set[str]:
    """Top-level names of the packages outside pipeline/ and stages/ a module imports (anywhere in it)."""
    parts = module.split(".")
    f = ROOT.joinpath(*parts).with_suffix(".py")
    if not f.exists():
        f = ROOT.joinpath(*parts, "__init__.py")
    out = set()
    for node in ast.walk(ast.parse(f.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out - {"pipeline", "stages"}


def test_the_numerical_library_imports_no_config_or_tracking_machinery():
    """Issue 21 item 2: the library modules (plants with their parameter classes, models, identification,
    inversion, metrics) reach neither Hydra, OmegaConf nor MLflow, also through the pipeline modules they
    import: their parameter classes are written with pipeline.params, which imports none of them."""
    graph = _graph()
    lib = [m for m in graph if m.startswith(_LIBRARY)]
    assert "pipeline.systems.linear_motor" in lib and "pipeline.models.pgnn" in lib
    seen, todo = set(), list(lib)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo += sorted(graph[m])
    bad = {m: sorted(_external(m) & {"hydra", "omegaconf", "mlflow"}) for m in sorted(seen)}
    assert {m: v for m, v in bad.items() if v} == {}


def test_the_export_stage_asks_the_invert_option_not_its_name():
    """Issue 21 item 3: stages/export.py ships whatever law the invert option's module declares
    (``export_laws``, ``export_check``, ``EXPORTS_MEASURED``); it compares the kind with no option name,
    so an exportable inversion is added in its own module (README: Architecture)."""
    tree = ast.parse((ROOT / "stages" / "export.py").read_text())
    kinds = {p.stem for p in (ROOT / "stages" / "invert").glob("*.py") if not p.stem.startswith("_")}
    named = sorted({ast.unparse(c) for c in ast.walk(tree) if isinstance(c, ast.Compare) and "kind" in ast.unparse(c)
                    and any(isinstance(n, ast.Constant) and n.value in kinds for n in ast.walk(c))})
    assert "physics" in kinds and named == []
    assert [ast.unparse(c) for c in ast.walk(ast.parse("if kind in ('direct', 'newton'): pass"))
            if isinstance(c, ast.Compare)] == ["kind in ('direct', 'newton')"]    # the walk sees such a test
    declared = [k for k in sorted(kinds) if "def export_laws" in (ROOT / "stages" / "invert" / f"{k}.py").read_text()]
    assert len(declared) >= 7


def test_the_numba_cache_is_a_folder_per_version_of_the_numba_modules(tmp_path):
    """numba keys a cached kernel by its own file only; the package's cache folder changes with any
    module that defines a kernel (a stale inlined callee cannot survive an edit), not with others,
    and the package sets it before numba loads."""
    import os

    import pipeline
    (tmp_path / "kernels.py").write_text("import numba\n\n@numba.njit(cache=True)\ndef f(x):\n    return x\n")
    (tmp_path / "plain.py").write_text("X = 1\n")
    first = pipeline.numba_cache_dir(tmp_path)
    assert first == pipeline.numba_cache_dir(tmp_path) and first.startswith(str(tmp_path))
    (tmp_path / "plain.py").write_text("X = 2\n")
    (tmp_path / "uses.py").write_text("import numba  # calls kernels, defines none\n")
    assert pipeline.numba_cache_dir(tmp_path) == first
    (tmp_path / "kernels.py").write_text("import numba\n\n@numba.njit(cache=True)\ndef f(x):\n    return 2 * x\n")
    assert pipeline.numba_cache_dir(tmp_path) != first
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    code = "import pipeline, numba; print(numba.config.CACHE_DIR)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == pipeline.numba_cache_dir()
