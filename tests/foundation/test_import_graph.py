"""No import cycle between the modules of ``reflectmm_cli/``, and none hidden inside a function.

Every ``import`` and ``from ... import`` statement of every module is read with :mod:`ast` — at module level
*and* inside functions, methods and class bodies, since an import moved into a function to dodge a cycle is
still a dependency — and the edges between project modules form a graph that must have no cycle.
Imports of third-party packages (torch, dask, dlib, scipy ...) are not edges: a function-level import of a
heavy optional package is fine.

How a statement becomes edges (the rule):

* relative imports are resolved against the importing module's package (``from .design import x`` in
  ``reflectance/fit.py`` is ``reflectmm_cli.reflectance.design``);
* ``import a.b.c`` is an edge to ``a.b.c``;
* ``from m import name`` where ``m.name`` is a module (``from reflectmm_cli.stages import checksum``) is an edge
  to the submodule ``m.name``;
* ``from pkg import name`` where ``pkg`` is a package whose ``__init__.py`` re-exports ``name`` (binds it with
  a ``from ... import``) is an edge to the module that defines ``name``, followed through re-export chains;
* any other ``from m import name`` is an edge to ``m`` itself (a plain module, or a name a package's
  ``__init__.py`` defines);
* a package ``__init__.py`` is a node like any module, so its re-exports are edges package → submodule;
* importing anything under a package from outside it is also an edge to that package (and to each enclosing
  package the importer is not in): Python runs ``pkg/__init__.py`` first, and with it every re-export.  So
  ``from reflectmm_cli.stages import run_stage`` in ``commands/_common.py`` is an edge to the module defining
  ``run_stage`` and one to ``reflectmm_cli.stages`` (hence to all it re-exports), while the same statement in
  a module of ``stages/`` is only the first edge.  A module's own enclosing packages are not edges: they are
  already running when it is imported (counting them would make every re-exporting package a cycle).

Dynamic imports (``importlib.import_module`` of a computed name) are not statements and are not edges: the two
that exist are the registries — ``cli.COMMAND_MODULES`` and ``stages.registry.STAGE_MODULES`` — which load a
verb's module by name, the direction layering already expects (tests/stages/test_structure.py).
"""

from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "reflectmm_cli"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@lru_cache(maxsize=None)
def _modules() -> dict[str, Path]:
    """Dotted name → file of every module of the package (``pkg`` for ``pkg/__init__.py``)."""
    return {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _is_package(name: str) -> bool:
    return _modules()[name].name == "__init__.py"


@lru_cache(maxsize=None)
def _tree(name: str) -> ast.Module:
    path = _modules()[name]
    return ast.parse(path.read_text(), str(path))


def _from_base(importer: str, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` statement reads from (relative levels resolved)."""
    if not node.level:
        return node.module or ""
    pkg = importer if _is_package(importer) else importer.rpartition(".")[0]
    parts = pkg.split(".")
    parts = parts[: len(parts) - node.level + 1]
    return ".".join(parts + ([node.module] if node.module else []))


@lru_cache(maxsize=None)
def _reexports(pkg: str) -> dict[str, tuple[str, str]]:
    """Names a package's ``__init__.py`` binds with ``from m import name`` at module level: name → (m, name in m)."""
    out = {}
    for node in _tree(pkg).body:
        if isinstance(node, ast.ImportFrom):
            base = _from_base(pkg, node)
            for a in node.names:
                out[a.asname or a.name] = (base, a.name)
    return out


def _target(base: str, name: str, seen: frozenset = frozenset()) -> str:
    """The project module ``from base import name`` depends on (see the module docstring for the rule)."""
    mods = _modules()
    if f"{base}.{name}" in mods:
        return f"{base}.{name}"
    if _is_package(base) and name in _reexports(base) and (base, name) not in seen:
        src, src_name = _reexports(base)[name]
        if src in mods:
            return _target(src, src_name, seen | {(base, name)})
    return base


def _packages_run(name: str, importer: str) -> list[str]:
    """The project packages whose ``__init__.py`` importing ``name`` runs from ``importer``: ``name`` itself and
    its parents when they are packages, except those that contain ``importer`` (already running)."""
    parts = name.split(".")
    out = []
    for k in range(1, len(parts) + 1):
        pkg = ".".join(parts[:k])
        if pkg in _modules() and _is_package(pkg) and importer != pkg and not importer.startswith(pkg + "."):
            out.append(pkg)
    return out


def _edges(importer: str) -> list[tuple[str, int, bool]]:
    """(imported module, line, inside a function) for every project import statement of ``importer``."""
    mods = _modules()
    out: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for a in child.names:
                    out.extend((p, child.lineno, in_function) for p in _packages_run(a.name, importer))
                    if a.name in mods:
                        out.append((a.name, child.lineno, in_function))
            elif isinstance(child, ast.ImportFrom):
                base = _from_base(importer, child)
                out.extend((p, child.lineno, in_function) for p in _packages_run(base, importer))
                if base in mods:
                    out.extend((_target(base, a.name), child.lineno, in_function) for a in child.names)
            visit(child, inner)

    visit(_tree(importer), False)
    return [(t, line, fn) for t, line, fn in out if t != importer]


def import_graph() -> dict[str, dict[str, tuple[int, bool]]]:
    """importer → {imported: (first line, inside a function)} over every module of ``reflectmm_cli/``."""
    graph: dict[str, dict[str, tuple[int, bool]]] = {}
    for name in _modules():
        graph[name] = {}
        for target, line, fn in _edges(name):
            graph[name].setdefault(target, (line, fn))
    return graph


def find_cycle(graph: dict[str, dict[str, object]]) -> list[str] | None:
    """A cycle ``[a, b, ..., a]`` of ``graph`` (importer → imported), or None (iterative depth-first search)."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(graph, WHITE)
    for start in sorted(graph):
        if colour[start] != WHITE:
            continue
        path = [start]
        stack = [iter(sorted(graph[start]))]
        colour[start] = GREY
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                colour[path.pop()] = BLACK
                stack.pop()
            elif colour.get(nxt, BLACK) == GREY:
                return path[path.index(nxt):] + [nxt]
            elif colour.get(nxt, BLACK) == WHITE:
                colour[nxt] = GREY
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


def _describe(cycle: list[str], graph) -> str:
    steps = []
    for a, b in zip(cycle, cycle[1:]):
        line, fn = graph[a][b]
        rel = _modules()[a].relative_to(ROOT)
        steps.append(f"  {a} -> {b}   ({rel}:{line}{', inside a function' if fn else ''})")
    return "import cycle:\n" + "\n".join(steps)


def test_project_modules_import_each_other_without_cycles():
    graph = import_graph()
    cycle = find_cycle(graph)
    assert cycle is None, _describe(cycle, graph)


def test_the_graph_sees_relative_function_level_and_re_exported_imports():
    graph = import_graph()
    fit = graph["reflectmm_cli.reflectance.fit"]
    assert fit["reflectmm_cli.reflectance.design"] == (fit["reflectmm_cli.reflectance.design"][0], False)
    assert fit["reflectmm_cli.reflectance.adam"][1] is True  # `from .adam import fit_adam` inside fit_maps
    # `from reflectmm_cli.stages import get_stage, run_stage` from outside the package: the defining module, and
    # the package whose __init__ runs first
    assert {"reflectmm_cli.stages.registry", "reflectmm_cli.stages"} <= set(graph["reflectmm_cli.commands._common"])
    # `from reflectmm_cli.stages import evaluate_albedo, ...`: submodules
    assert "reflectmm_cli.stages.evaluate_albedo" in graph["reflectmm_cli.commands.evaluate"]
    # a package's re-exports are edges to its submodules; a submodule does not depend on its own package
    assert "reflectmm_cli.reflectance.fit" in graph["reflectmm_cli.reflectance"]
    assert "reflectmm_cli.stages" not in graph["reflectmm_cli.stages.checksum"]


def test_find_cycle_reports_the_cycle_path():
    assert find_cycle({"a": {"b": 0}, "b": {"c": 0}, "c": {"a": 0}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": 0}, "b": {"b2": 0}, "b2": {"b": 0}}) == ["b", "b2", "b"]
    assert find_cycle({"a": {"b": 0, "c": 0}, "b": {"c": 0}, "c": {}}) is None
