"""The package's import structure: no module imports one that imports it back.

Parses every module of ``zplatform/`` with :mod:`ast` (nothing is imported)
and draws an edge for every import anywhere in it: at module level, inside a
function, under ``if TYPE_CHECKING:``. A circle among them fails the test,
listed module by module; there are no known exceptions. Importing
``zplatform.a.b`` also runs ``zplatform/a/__init__.py``, so the package
``zplatform.a`` counts as imported too (unless the importer is inside it:
its own package is already loading; so the root package ``zplatform``, which
re-exports the public API, is never a target of a module inside it).

A second rule keeps the layers: the core (config, the data core, boards,
the world model, the control logic, security, telemetry, the mission checks
and the flight recorder) never imports a process entry point, the CLI, a
node runtime, the zenoh runtime, the ground or the console; the ground never
imports the vehicle nodes' runtime (``zplatform.node``). A third: every
module sits in a package of LAYERS (or is a root module: errors, trace), and
a package imports only those before it in LAYERS, the order of
docs/architecture.md's package layout table.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "zplatform"

# The packages bottom-up: each imports only those before it and the root
# modules (ROOT_MODULES); docs/architecture.md's package layout, in order.
LAYERS = (
    "zplatform.config",
    "zplatform.core",
    "zplatform.boards",
    "zplatform.world",
    "zplatform.control",
    "zplatform.security",
    "zplatform.telemetry",
    "zplatform.mission",
    "zplatform.recorder",
    "zplatform.runtime",
    "zplatform.archive",
    "zplatform.ground",
    "zplatform.sim",
    "zplatform.node",
    "zplatform.console",
    "zplatform.cli",
)
ROOT_MODULES = {"zplatform.errors", "zplatform.trace"}
# The layers above the core: process entry points and the zenoh-facing sides.
TOP = (
    "zplatform.cli",
    "zplatform.node",
    "zplatform.ground",
    "zplatform.console",
    "zplatform.sim",
    "zplatform.runtime",
)
TOP_MODULES = {"zplatform.__main__"}
# The core that must never import them.
CORE = {
    "zplatform.config",
    "zplatform.core",
    "zplatform.boards",
    "zplatform.world",
    "zplatform.control",
    "zplatform.security",
    "zplatform.telemetry",
    "zplatform.mission",
    "zplatform.recorder",
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
    assert "zplatform.sim.world_server" in graph["zplatform.cli.runtime"]  # in a function
    assert "zplatform.mission.load" in graph["zplatform.sim.world_server"]  # in a function
    assert "zplatform.boards" in graph["zplatform.world.model"]  # parent of boards.world
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


def _layer(name: str) -> int | None:
    """The index in LAYERS of the package holding ``name`` (None: a root module)."""
    for i, pkg in enumerate(LAYERS):
        if _in(name, (pkg,)):
            return i
    return None


def test_every_module_sits_in_a_layer() -> None:
    # a new module goes into the package of its layer, not beside them
    stray = [
        name
        for name in import_graph()
        if name != "zplatform"
        and _layer(name) is None
        and name not in ROOT_MODULES
        and name != "zplatform.__main__"
    ]
    assert not stray, f"modules outside LAYERS (place them, or add their package): {stray}"


def test_every_package_imports_only_layers_below_it() -> None:
    # The packages form a ladder: no package imports one above it, so no two
    # packages import each other either (a circle of packages is one upward).
    upward = []
    for a, targets in import_graph().items():
        la = _layer(a)
        for b in targets:
            lb = _layer(b)
            if a in ROOT_MODULES and b not in ROOT_MODULES:
                upward.append(f"{a} -> {b}")  # the root modules are the ground floor
            elif la is not None and lb is not None and lb > la:
                upward.append(f"{a} -> {b}")
    assert not upward, "a package imports one above it:\n" + "\n".join(upward)
