"""The import graph keeps its layers: found with ``ast`` over every module, nothing imported.

Layers, bottom to top:

- core: ``estimator.geometry``, ``estimator.types``, ``estimator.config``,
  ``estimator.imu_sampling`` and the packages
  ``registration``, ``frontend``, ``backend``, ``formats``, ``evaluation``, ``rendered`` and
  ``compiled`` (the kernels' declaration and their build ahead of time).
  ``config`` counts as core: it is the typed schema the front end and the back end read their
  own section from, and it imports nothing from the estimator itself.
- pipeline: ``estimator.odometry``, ``estimator.rig_settings``, ``estimator.pipeline`` (the
  library API the apps use).
- apps: ``estimator.cli``, ``estimator.bench`` and the ``service`` package.

Rules: a core module imports only core modules; no estimator module imports an app package
except the app packages themselves (the CLI may start a benchmark); nothing in ``estimator``
imports ``service`` (``swarmvo serve`` reaches it by name at run time); and no module imports
itself back through a chain of other modules. Every import statement counts, also the ones inside
functions and under ``TYPE_CHECKING``: a lazy import is still an arrow.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("estimator", "service")
CORE = (
    "estimator.geometry",
    "estimator.types",
    "estimator.config",
    "estimator.imu_sampling",
    "estimator.registration",
    "estimator.frontend",
    "estimator.backend",
    "estimator.formats",
    "estimator.evaluation",
    "estimator.rendered",
    "estimator.compiled",
)
PIPELINE = ("estimator.odometry", "estimator.rig_settings", "estimator.pipeline")
APPS = ("estimator.cli", "estimator.bench", "service")
# Known cycles, each with the reason it is still there. Remove an entry when its cycle is gone
# (the test fails on a listed cycle that no longer exists, so the list cannot go stale).
KNOWN_CYCLES: dict[frozenset[str], str] = {}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if "migrations" not in path.parts:
                found[_module_name(path)] = path
    return found


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The project module an import names: itself, or the package holding the name."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def imports_of(module: str, path: Path) -> set[str]:
    """Project modules ``module`` imports anywhere in its source."""
    is_package = path.name == "__init__.py"
    package = module if is_package else module.rpartition(".")[0]
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            # `from package import module` names a module; `from module import name` does not
            names = [f"{base}.{alias.name}" for alias in node.names] + [base]
        else:
            continue
        for name in names:
            resolved = _resolve(name)
            if resolved and resolved != module:
                targets.add(resolved)
    return targets


GRAPH = {module: imports_of(module, path) for module, path in MODULES.items()}


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == prefix or module.startswith(prefix + ".") for prefix in prefixes)


def arrows(graph: dict[str, set[str]], sources: tuple[str, ...], targets: tuple[str, ...]):
    """Every import from a module under ``sources`` of a module under ``targets``."""
    return sorted(
        f"{module} -> {target}"
        for module, imported in graph.items()
        if _within(module, sources)
        for target in imported
        if _within(target, targets)
    )


def upward_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Arrows that break a layer rule (see the module docstring)."""
    broken = (
        arrows(graph, CORE, PIPELINE + APPS)
        + arrows(graph, PIPELINE, APPS)
        + arrows(graph, ("estimator",), ("service",))
    )
    return sorted(set(broken))


def cycles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == node:
                    break
            if len(component) > 1:
                found.add(frozenset(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_graph_sees_the_packages():
    """Guards the test itself: an empty or blind graph would pass every rule."""
    assert {"estimator.registration.registry", "estimator.odometry", "service.app"} <= set(MODULES)
    assert "estimator.geometry" in GRAPH["estimator.registration.result"]
    assert "estimator.odometry" in GRAPH["estimator.pipeline"]
    # lazy imports inside functions count
    assert "estimator.registration.pso_support" in GRAPH["estimator.registration.registry"]


def test_no_arrow_points_up_a_layer():
    assert upward_arrows(GRAPH) == []


def test_no_import_cycles():
    found = cycles(GRAPH)
    assert sorted(map(sorted, found - KNOWN_CYCLES.keys())) == []
    assert sorted(map(sorted, KNOWN_CYCLES.keys() - found)) == [], "a known cycle is gone"


@pytest.mark.parametrize(
    ("source", "target"),
    [
        ("estimator.frontend.stereo", "estimator.odometry"),
        ("estimator.formats.datasets", "estimator.pipeline"),
        ("estimator.backend.fusion", "estimator.cli.main"),
        ("estimator.evaluation.metrics", "estimator.bench.odometry"),
        ("estimator.pipeline", "estimator.bench.odometry"),
        ("estimator.odometry", "service.app"),
        ("estimator.cli.main", "service.cli"),
    ],
)
def test_an_upward_import_is_caught(source, target):
    graph = {module: set(imported) for module, imported in GRAPH.items()}
    graph[source].add(target)
    assert upward_arrows(graph) == [f"{source} -> {target}"]


def test_a_new_cycle_is_caught():
    graph = {module: set(imported) for module, imported in GRAPH.items()}
    graph["estimator.geometry"].add("estimator.registration.registry")
    assert cycles(graph) - cycles(GRAPH)
