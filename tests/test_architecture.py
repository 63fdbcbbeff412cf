"""The package's shape: imports point one way (function-local imports included), MJX internals stay in one adapter
module, the controllers import no simulator, the code carries no lab notebook, and the docs' pages of the current
state (performance, results) stay pages, not diaries.

The import graph is read from the sources with ``ast`` (every ``import`` and ``from ... import`` at any depth), so a
function-local import that closes a circle is found like a top-level one.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "wbc_jax"

# Layers, lowest first: a module may import from its own layer's package and from lower layers only. Within one
# layer, different packages do not import each other (control, planner, physics and metrics are siblings).
LAYERS = [
    ("wbc_jax.errors", "wbc_jax.version"),
    ("wbc_jax.types", "wbc_jax.spatial", "wbc_jax.io_utils", "wbc_jax.runtime"),
    ("wbc_jax.physics.backend", "wbc_jax.qp", "wbc_jax.analysis"),
    ("wbc_jax.robot",),
    ("wbc_jax.physics", "wbc_jax.planner", "wbc_jax.control", "wbc_jax.metrics"),
    ("wbc_jax.rollout",),
    ("wbc_jax.campaign",),
    ("wbc_jax.studies", "wbc_jax.bench"),
    ("wbc_jax.api", "wbc_jax.cli"),
    ("wbc_jax.__main__", "wbc_jax"),
]
ADAPTER = "wbc_jax/physics/backend.py"  # the one module that may read MJX internals
PRIVATE_MJX = re.compile(r"_impl\b|mjx\._src|mujoco_warp\._src")
# measurements, dates, devices and work history belong in docs/ and CHANGELOG.md (pieces joined so this line is
# not a match of its own)
NOTEBOOK = re.compile("(" + "|".join(["H1" "00", "H2" "00", r"20[0-9]{2}-[0-9]{2}-[0-9]{2}", "env-steps" "/s",
                                      "iss" r"ue [0-9]+"]) + ")")
TESTS = PKG.parent / "tests"
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80
DOC_PAGE_BYTES = 25_000  # docs/performance.md and docs/results.md: a page of the current state each


def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = p.relative_to(PKG.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """The package's modules that ``name`` imports (a ``from pkg import mod`` counts as importing ``pkg.mod``)."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                mod = ".".join(base[: len(base) - node.level + 1] + ([mod] if mod else []))
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod for a in node.names]
        else:
            continue
        out |= {t for t in targets if t in MODULES and t != name}
    return out


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _layer(name: str) -> tuple[int, str]:
    """(layer index, the layer entry that holds ``name``: the longest matching prefix)."""
    best = None
    for i, entries in enumerate(LAYERS):
        for e in entries:
            if (name == e or name.startswith(e + ".")) and (best is None or len(e) > len(best[1])):
                best = (i, e)
    assert best is not None, f"{name} is in no layer of tests/test_architecture.py"
    return best


def test_every_module_has_a_layer():
    for name in MODULES:
        _layer(name)


def test_imports_point_down():
    bad = []
    for a, targets in GRAPH.items():
        la, ea = _layer(a)
        for b in targets:
            lb, eb = _layer(b)
            if lb > la or (lb == la and ea != eb):
                bad.append(f"{a} -> {b}")
    assert not bad, "imports against the layers:\n" + "\n".join(sorted(bad))


def test_no_import_cycle():
    """Tarjan's strongly connected components of the module graph: every component is a single module."""
    index, low, stack, on, comps = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in GRAPH[v]:
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
            comps.append(comp)

    for v in GRAPH:
        if v not in index:
            visit(v)
    cycles = [sorted(c) for c in comps if len(c) > 1]
    assert not cycles, f"import cycles: {cycles}"


def test_private_mjx_names_only_in_the_adapter():
    hits = [f"{p.relative_to(PKG.parent)}:{i}" for p in MODULES.values()
            for i, line in enumerate(p.read_text().splitlines(), 1)
            if PRIVATE_MJX.search(line) and str(p.relative_to(PKG.parent)) != ADAPTER]
    assert not hits, hits


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m.startswith("wbc_jax.control")))
def test_controllers_import_no_simulator(module):
    tree = ast.parse(MODULES[module].read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert not {n for n in names if n.split(".")[0] == "mujoco" or "physics" in n or "rollout" in n}


def test_no_lab_notebook_in_code_or_tests():
    files = list(MODULES.values()) + sorted(TESTS.glob("*.py"))
    hits = [f"{p.relative_to(PKG.parent)}:{i}" for p in files
            for i, line in enumerate(p.read_text().splitlines(), 1) if NOTEBOOK.search(line)]
    assert not hits, hits


def test_module_and_function_sizes():
    big = [f"{p.relative_to(PKG.parent)}: {n} lines" for p in MODULES.values()
           if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES]
    long = [f"{p.relative_to(PKG.parent)}:{node.lineno} {node.name}: {node.end_lineno - node.lineno + 1} lines"
            for p in MODULES.values() for node in ast.walk(ast.parse(p.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES]
    assert not big and not long, big + long


def test_current_state_pages_stay_short():
    """docs/performance.md and docs/results.md describe the current state, each at most DOC_PAGE_BYTES; the history
    goes to CHANGELOG.md and git."""
    sizes = {name: len((PKG.parent / "docs" / name).read_bytes()) for name in ("performance.md", "results.md")}
    assert all(n <= DOC_PAGE_BYTES for n in sizes.values()), sizes
