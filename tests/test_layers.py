"""The package's import graph: every import of one dfvo subpackage by another points down the layer order of
``docs/architecture.md``, so the subpackage graph has no cycle, and no two modules import each other either.

Every module of ``dfvo/`` is parsed with :mod:`ast` (nothing is imported); module-level imports and imports inside
functions and classes count alike, so a cycle cannot hide in a function body.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dfvo"
ROOT = "(root)"  # the package's own __init__.py and the modules beside it (dfvo/evaluate.py)

# Bottom to top; a subpackage may import only from layers below its own (not from a peer in its layer).
# The same table, with the reasons, is in docs/architecture.md.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("validation",),
    ("geometry", "vis"),
    ("io",),
    ("data", "synthetic"),
    ("eval", "viewer"),
    ("matching",),
    ("models", "losses", "tracking"),
    ("sources",),
    ("source_eval", "training"),
    ("inference",),
    ("cli",),
    ("conf", ROOT),
)
DATA_ONLY = ("checkpoints",)  # shipped files, no code
BOTTOM_MODULES = ("dfvo.validation",)  # modules beside __init__.py that every layer may import (they import no dfvo)
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _subpackage(module: str) -> str:
    parts = module.split(".")
    if module in BOTTOM_MODULES:
        return parts[1]
    if len(parts) == 1 or not (PACKAGE / parts[1]).is_dir():
        return ROOT
    return parts[1]


def _imported(module: str, is_package: bool, tree: ast.Module) -> list[tuple[str, int]]:
    """(imported dfvo module or package, line) for every import statement in ``tree``, at any depth."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            # `from dfvo import data` imports the subpackage `data`, not the package root
            names = [f"{target}.{a.name}" for a in node.names] if target == "dfvo" else [target]
            found += [(name, node.lineno) for name in names]
    return [(name, line) for name, line in found if name == "dfvo" or name.startswith("dfvo.")]


def _module_edges() -> dict[tuple[str, str], list[str]]:
    """(importing module, imported module or package) -> ["module:line", ...]; ``from dfvo.x import y`` counts as an
    import of the module ``dfvo.x.y`` when there is one, else of the package ``dfvo.x``."""
    modules = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}
    edges: dict[tuple[str, str], list[str]] = defaultdict(list)
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for target, line in _imported(module, path.name == "__init__.py", tree):
            while target not in modules and "." in target:  # a name imported from a module: the module
                target = target.rpartition(".")[0]
            if target != module:
                edges[(module, target)].append(f"{module}:{line}")
    return dict(edges)


def _edges() -> dict[tuple[str, str], list[str]]:
    """(importing subpackage, imported subpackage) -> ["module:line", ...] for imports across subpackages."""
    edges: dict[tuple[str, str], list[str]] = defaultdict(list)
    for (module, target), where in _module_edges().items():
        a, b = _subpackage(module), _subpackage(target)
        if a != b:
            edges[(a, b)] += where
    return dict(edges)


def _cycle(edges: dict[tuple[str, str], list[str]]) -> list[str] | None:
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_every_subpackage_has_a_layer():
    subpackages = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert subpackages - set(RANK) - set(DATA_ONLY) == set(), "add the new subpackage to LAYERS (and the docs)"
    modules = {m.split(".")[1] for m in BOTTOM_MODULES}
    assert set(RANK) - subpackages - modules - {ROOT} == set(), "LAYERS names a subpackage that does not exist"


def test_subpackage_imports_point_down_the_layers():
    upward = [f"{a} -> {b} ({', '.join(where)})" for (a, b), where in sorted(_edges().items())
              if RANK[b] >= RANK[a]]
    assert upward == [], "imports up or sideways in the layer order:\n" + "\n".join(upward)


def test_subpackage_import_graph_is_acyclic():
    assert _cycle(_edges()) is None


def test_module_import_graph_is_acyclic():
    """No module imports (directly or through others) a module that imports it back, in a function or not; a
    package's ``__init__`` importing its own modules is not a cycle unless one of them imports the package."""
    edges = _module_edges()
    cycle = _cycle(edges)
    assert cycle is None, " -> ".join(cycle) + "\n" + "\n".join(
        f"{a} -> {b}: {', '.join(edges[(a, b)])}" for a, b in zip(cycle, cycle[1:], strict=False))


@pytest.mark.parametrize("source,expected", [
    ("from dfvo.data import image_io\nfrom dfvo.geometry.camera import K\n", ["data", "geometry"]),
    ("def f():\n    from dfvo.training import x\n", ["training"]),
    ("class A:\n    def f(self):\n        import dfvo.inference.loop\n", ["inference"]),
    ("from dfvo import synthetic\n", ["synthetic"]),
    ("from ..sources import build\n", ["sources"]),
    ("from .flow import y\n", ["source_eval"]),
])
def test_the_parser_sees_module_function_and_relative_imports(source, expected):
    module = "dfvo.source_eval.depth"
    found = [_subpackage(name) for name, _ in _imported(module, False, ast.parse(source))]
    assert sorted(found) == sorted(expected)


def test_a_cycle_is_found():
    assert _cycle({("data", "eval"): [], ("eval", "sources"): [], ("sources", "data"): []}) == \
        ["data", "eval", "sources", "data"]
    assert _cycle({("data", "geometry"): [], ("eval", "io"): []}) is None
