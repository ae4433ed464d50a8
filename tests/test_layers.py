"""The package's architecture, read from its source: layers, import cycles, module size, packaging.

* No library module imports the command line (``piezo_fmu.cli``): the CLI is one layer over the API.
* The import graph of ``piezo_fmu`` (every import, at module level or inside functions) has no cycle.
* Modules import each other's public names only (no ``from .x import _private``).
* A module over 600 lines says in its docstring why it is one piece.
* Every package of the source tree is listed in pyproject.toml (an explicit list, because the
  top-level ``fmu_src/`` and ``models/`` are mapped into the package).
"""
from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "piezo_fmu"
MAX_LINES = 600


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules():
    return {_module_name(p): p for p in sorted(PKG.rglob("*.py")) if "__pycache__" not in p.parts}


def _resolve(module: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".")
    if not is_pkg:
        base = base[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph():
    """``{module: {imported piezo_fmu module, ...}}`` over every import statement."""
    mods = _modules()
    graph = {}
    private = []
    for name, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        deps = set()
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(name, path.name == "__init__.py", node)
                targets = [target]
                # "from .pkg import module" imports the submodule
                targets += [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in mods]
                if target in mods:
                    private += [(name, target, a.name) for a in node.names
                                if a.name.startswith("_") and not a.name.startswith("__")
                                and f"{target}.{a.name}" not in mods]
            for t in targets:
                while t and t not in mods:          # attribute imports: the module that holds them
                    t = t.rpartition(".")[0]
                if t and t != name and t.startswith("piezo_fmu"):
                    deps.add(t)
        graph[name] = deps
    return graph, private


def _cycle(graph):
    """One import cycle as a list of modules, or ``None``. Package ``__init__`` imports of their
    own submodules (re-exports) count like any other import."""
    state = {}
    stack = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_no_library_module_imports_the_cli():
    graph, _ = import_graph()
    offenders = sorted(m for m, deps in graph.items()
                       if not (m == "piezo_fmu.cli" or m.startswith("piezo_fmu.cli.") or m == "piezo_fmu.__main__")
                       and any(d == "piezo_fmu.cli" or d.startswith("piezo_fmu.cli.") for d in deps))
    assert offenders == []


def test_import_graph_has_no_cycle():
    graph, _ = import_graph()
    # parents import their own submodules to re-export them; a submodule importing its parent's
    # __init__ back is the cycle that matters, so the edge parent -> own child is not followed
    pruned = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}
    assert _cycle(pruned) is None


def test_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_modules_import_public_names_only():
    _, private = import_graph()
    assert private == []


@pytest.mark.parametrize("path", sorted(p for d in (PKG, ROOT / "fmu_src") for p in d.rglob("*.py")
                                        if "__pycache__" not in p.parts),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_long_modules_say_why_they_are_one_piece(path):
    lines = path.read_text(encoding="utf-8").count("\n")
    if lines <= MAX_LINES:
        return
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    assert "one piece" in doc, f"{path.relative_to(ROOT)}: {lines} lines; split it or say why it is one piece"


def test_every_package_is_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {_module_name(p.parent / "__init__.py") for p in PKG.rglob("__init__.py")
             if "__pycache__" not in p.parts}
    assert found - listed == set(), "packages missing from pyproject.toml"
    assert {"piezo_fmu.fmu_src", "piezo_fmu.model_files"} <= listed
