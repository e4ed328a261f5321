"""The package's import structure: no module imports one that imports it back.

Parses every module of ``zplatform/`` with :mod:`ast` (nothing is imported)
and draws an edge for every import anywhere in it: at module level, inside a
function, under ``if TYPE_CHECKING:``. A circle among them fails the test,
listed module by module; there are no known exceptions. Importing
``zplatform.a.b`` also runs ``zplatform/a/__init__.py``, so the package
``zplatform.a`` counts as imported too (unless the importer is inside it:
its own package is already loading; so the root package ``zplatform``, which
re-exports the public API, is never a target of a module inside it).

A second rule keeps the layers: the core (config, the sans-IO modules,
boards, the world model, the records, logs, summaries and the flight
recorder) never imports a process entry point, the CLI,
a node runtime, the ground or the console. And the two zenoh-facing sides
stand apart: the ground never imports the vehicle nodes' runtime
(``zplatform.node``); what both use lives below them (``zplatform.transport``).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "zplatform"

# The layers above the core: process entry points and the zenoh-facing sides.
TOP = (
    "zplatform.cli",
    "zplatform.cli_args",
    "zplatform.cli_ground",
    "zplatform.cli_runtime",
    "zplatform.cli_sim",
    "zplatform.node",
    "zplatform.ground",
    "zplatform.console",
)
TOP_MODULES = {"zplatform.__main__", "zplatform.world_server", "zplatform.supervisor"}
# The core that must never import them (and the config package in full).
CORE = {
    "zplatform.config",
    "zplatform.boards",
    "zplatform.world",
    "zplatform.world_checks",
    "zplatform.mission",
    "zplatform.devices",
    "zplatform.controllers",
    "zplatform.components",
    "zplatform.datavector",
    "zplatform.codec",
    "zplatform.statemachine",
    "zplatform.commands",
    "zplatform.loop",
    "zplatform.records",
    "zplatform.telemetry",
    "zplatform.summary",
    "zplatform.recorder",
    "zplatform.events",
    "zplatform.schema",
}

KNOWN_CIRCLES: list[tuple[str, ...]] = []
"""Circles allowed for now, each with the reason in a comment: none."""


def _modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name)."""
    out: dict[str, Path] = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _package_of(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``name`` imports, anywhere in its body."""
    package = _package_of(name, path)
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join([*base, node.module] if node.module else base)
            else:
                mod = node.module or ""
            targets.add(mod)
            # `from pkg import sub` imports the submodule pkg.sub
            targets.update(f"{mod}.{a.name}" for a in node.names)
    out: set[str] = set()
    for t in targets:
        if t not in modules:
            continue
        # a target and the packages above it run, unless they hold the
        # importer (its own packages are already loading: `from . import x`)
        parts = t.split(".")
        for i in range(2, len(parts) + 1):
            mod = ".".join(parts[:i])
            if not (name == mod or name.startswith(mod + ".")):
                out.add(mod)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """Every strongly connected set of two or more modules (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[tuple[str, ...]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(tuple(sorted(group)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _in(name: str, prefixes: set[str] | tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def test_the_graph_sees_the_imports_it_must() -> None:
    # The check is only as good as its edges: a module-level, a function-level
    # and a TYPE_CHECKING import, and a subpackage's parent run on import.
    graph = import_graph()
    assert "zplatform.config.schema" in graph["zplatform.config.platform"]
    assert "zplatform.world_server" in graph["zplatform.cli_runtime"]  # in a function
    assert "zplatform.mission" in graph["zplatform.world_server"]  # in a function
    assert "zplatform.boards" in graph["zplatform.world"]  # parent of boards.world
    assert "zplatform.boards" not in graph["zplatform.boards.world"]  # its own package


def test_no_import_circle() -> None:
    found = [c for c in circles(import_graph()) if c not in KNOWN_CIRCLES]
    assert not found, "import circles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_the_core_never_imports_a_layer_above_it() -> None:
    graph = import_graph()
    upward = sorted(
        f"{a} -> {b}"
        for a, targets in graph.items()
        if _in(a, CORE)
        for b in targets
        if _in(b, TOP) or b in TOP_MODULES
    )
    assert not upward, "the core imports a layer above it:\n" + "\n".join(upward)


# Sides of the top layer that must not import each other: (importer, imported).
APART = [("zplatform.ground", "zplatform.node")]


def test_the_ground_never_imports_the_vehicle_nodes_runtime() -> None:
    graph = import_graph()
    across = sorted(
        f"{a} -> {b}"
        for side, other in APART
        for a, targets in graph.items()
        if _in(a, (side,))
        for b in targets
        if _in(b, (other,))
    )
    assert not across, "a side imports another it must not:\n" + "\n".join(across)
