"""The package's import graph: no cycle, and every package imports only from the layers below it.

Every ``import`` statement of ``sumhe/`` counts, at module level, inside functions and under ``TYPE_CHECKING``
alike (a function-level import is a dependency that is only discovered later)."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import sumhe

ROOT = Path(sumhe.__file__).parent

LAYERS: tuple[frozenset[str], ...] = tuple(
    frozenset(layer)
    for layer in (
        # plain data, maths
        {"sumhe", "sumhe.errors", "sumhe.messages", "sumhe.records", "sumhe.geo", "sumhe.floats", "sumhe.settings"},
        {"sumhe.config"},  # the only module reading configuration files or the environment
        {"sumhe.model", "sumhe.io"},  # vehicle models; parsers, sources and sinks
        {"sumhe.frontend", "sumhe.sim"},  # samples to measurements; the simulator (writes what io reads)
        {"sumhe.calibration"},  # a car's installation parameters from a recorded drive (sumhe calibrate)
        {"sumhe.estimator"},  # the SU estimators, the Estimator interface and registry
        {"sumhe.baseline"},  # the peers, on the same interface
        {"sumhe.service"},  # the daemon: sources -> pipeline -> estimator -> sinks
        {"sumhe.bench"},  # the evaluation layer: benchmarks, metrics, tuning, the demo
        {"sumhe.plot"},
        {"sumhe.commands"},
        {"sumhe.cli", "sumhe.__main__"},
    )
)
"""Packages from the bottom up; a package may import its own layer's modules and any layer below."""


def modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        name = ".".join(("sumhe", *path.relative_to(ROOT).with_suffix("").parts))
        out[name.removesuffix(".__init__")] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the sumhe modules it imports (``from a import b`` counts ``a``, and ``a.b`` if it is a module)."""
    mods = modules()
    graph: dict[str, set[str]] = defaultdict(set)
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*parts, *([node.module] if node.module else [])])
                targets = [base, *(f"{base}.{a.name}" for a in node.names)]
            else:
                continue
            graph[name] |= {t for t in targets if t in mods and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def layer_of(module: str) -> int:
    package = ".".join(module.split(".")[:2])
    for level, layer in enumerate(LAYERS):
        if package in layer:
            return level
    raise AssertionError(f"{module}: package {package} is in no layer of LAYERS (add it where it belongs)")


def test_the_graph_is_read() -> None:
    graph = import_graph()
    assert "sumhe.estimator.mhe.estimator" in graph["sumhe.estimator.mhe"]
    assert "sumhe.frontend.stream" in graph["sumhe.estimator.base"]
    assert "sumhe.bench.mhe" in graph["sumhe.commands.bench"]  # imports inside functions count too


def test_no_import_cycle() -> None:
    assert cycles(import_graph()) == []
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]  # the detector detects


def test_layers_import_downwards_only() -> None:
    upward = [
        f"{a} -> {b}"
        for a, targets in sorted(import_graph().items())
        for b in sorted(targets)
        if layer_of(b) > layer_of(a)
    ]
    assert upward == []
