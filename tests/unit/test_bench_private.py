"""The benchmarks use the platform's public API only (bench/*.py): no private
(underscore, not dunder) attribute of anything but the bench's own objects, no
private name or module imported from zplatform, no zplatform module or class
patched. What they time, they time through zplatform.trace's points (and
public attributes): a bench that reached into the platform's insides broke, or
worse measured something else, whenever those insides moved."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"

#: Private names of other libraries a bench may use (the standard library's).
ALLOWED = {("os", "_exit")}

PATCHERS = {"patch", "setattr", "delattr"}


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _root(node: ast.expr) -> str | None:
    while isinstance(node, ast.Attribute | ast.Subscript | ast.Call):
        node = node.func if isinstance(node, ast.Call) else node.value
    return node.id if isinstance(node, ast.Name) else None


def _zplatform_names(tree: ast.Module) -> set[str]:
    """Names the file binds to zplatform modules or their members."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "zplatform" or a.name.startswith("zplatform."):
                    out.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and (
            node.module == "zplatform" or (node.module or "").startswith("zplatform.")
        ):
            out.update(a.asname or a.name for a in node.names)
    return out


def _own(cls: ast.ClassDef) -> set[str]:
    """The private attributes a bench class makes itself: assigned on ``self``,
    or defined in its body."""
    own: set[str] = set()
    for node in ast.walk(cls):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id in ("self", "cls")
        ):
            own.add(node.attr)
    for stmt in cls.body:
        if isinstance(stmt, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            own.add(stmt.name)
        elif isinstance(stmt, ast.Assign | ast.AnnAssign):
            targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]
            own.update(t.id for t in targets if isinstance(t, ast.Name))
    return own


def violations(source: str, name: str = "<bench>") -> list[str]:
    """Every private access or zplatform patch in ``source`` (module doc)."""
    tree = ast.parse(source)
    zp = _zplatform_names(tree)
    found: list[str] = []

    def say(node: ast.AST, what: str) -> None:
        found.append(f"{name}:{getattr(node, 'lineno', 0)}: {what}")

    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            mod = node.module
            if mod == "zplatform" or mod.startswith("zplatform."):
                if any(_private(p) for p in mod.split(".")):
                    say(node, f"private module {mod}")
                for a in node.names:
                    if _private(a.name):
                        say(node, f"private name {mod}.{a.name}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("zplatform.") and any(_private(p) for p in a.name.split(".")):
                    say(node, f"private module {a.name}")
        elif isinstance(node, ast.ClassDef):
            own = _own(node)
            for sub in ast.walk(node):
                if (
                    isinstance(sub, ast.Attribute)
                    and isinstance(sub.value, ast.Name)
                    and sub.value.id in ("self", "cls")
                    and _private(sub.attr)
                    and sub.attr not in own
                ):
                    say(sub, f"inherited private attribute {sub.value.id}.{sub.attr}")
        elif isinstance(node, ast.Attribute) and _private(node.attr):
            base = node.value
            if isinstance(base, ast.Name) and base.id in ("self", "cls"):
                continue  # the bench's own (checked per class above)
            if isinstance(base, ast.Name) and (base.id, node.attr) in ALLOWED:
                continue
            say(node, f"private attribute {ast.unparse(node)}")
        if isinstance(node, ast.Assign | ast.AugAssign | ast.AnnAssign | ast.Delete):
            targets = node.targets if isinstance(node, ast.Assign | ast.Delete) else [node.target]
            for t in targets:
                if isinstance(t, ast.Attribute) and _root(t) in zp:
                    say(t, f"patches {ast.unparse(t)}")
        if isinstance(node, ast.Call):
            fn = node.func
            called = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
            if called in PATCHERS and node.args:
                first = node.args[0]
                if (isinstance(first, ast.Name) and first.id in zp) or (
                    isinstance(first, ast.Constant)
                    and isinstance(first.value, str)
                    and first.value.startswith("zplatform")
                ):
                    say(node, f"patches zplatform with {called}()")
    return found


def test_no_bench_touches_a_private_name_or_patches_the_platform() -> None:
    files = sorted(BENCH.glob("*.py"))
    assert len(files) > 20  # the scan sees the benches
    found = [v for f in files for v in violations(f.read_text(encoding="utf-8"), f.name)]
    assert found == []


@pytest.mark.parametrize(
    "source",
    [
        "def f(node):\n    node.logic._open = 1\n",
        "def f(cn):\n    return cn._tm_pub\n",
        "from zplatform.control.intake import TriggerIntake\nTriggerIntake.admit = None\n",
        "import zplatform.runtime.process as rt\nrt.realtime_setup = None\n",
        "from zplatform import trace\ntrace.tracer = object()\n",
        "from zplatform.runtime.sync import _ignore\n",
        "from zplatform.runtime.sync import ControlSync\nsetattr(ControlSync, 'sync', None)\n",
        "def f(mp):\n    mp.setattr('zplatform.runtime.sync.ControlSync.sync', None)\n",
        "from zplatform.control.loop import ControlLogic\n"
        "class L(ControlLogic):\n    def f(self):\n        return self._got\n",
    ],
)
def test_the_scan_catches_each_kind(source: str) -> None:
    assert violations(source)


@pytest.mark.parametrize(
    "source",
    [
        "class A:\n    def __init__(self):\n        self._n = 0\n    def f(self):\n"
        "        return self._n\n",
        "import os\nos._exit(0)\n",
        "from zplatform import trace\ntrace.install(object())\n",
        "def f(x):\n    return x.__class__\n",
    ],
)
def test_the_scan_allows_a_benchs_own_and_the_public(source: str) -> None:
    assert violations(source) == []
