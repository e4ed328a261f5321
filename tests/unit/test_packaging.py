"""Packaging metadata: what a wheel of zplatform installs and requires."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _pyproject() -> dict:  # type: ignore[type-arg]
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_license_is_an_spdx_expression_with_its_file() -> None:
    p = _pyproject()
    assert p["project"]["license"] == "Apache-2.0"
    for f in p["project"]["license-files"]:
        assert (ROOT / f).is_file()
    req = p["build-system"]["requires"]
    assert any(
        r.startswith("setuptools>=") and int(r.split(">=")[1].split(".")[0]) >= 77 for r in req
    )


def test_the_wheel_installs_only_zplatform_and_its_types() -> None:
    """No top-level package but zplatform (not `nodes`, not `bench`: names
    another project may own): the packages setuptools finds with the
    project's own settings (pyproject's find is namespace-aware)."""
    from setuptools import find_namespace_packages

    p = _pyproject()
    find = p["tool"]["setuptools"]["packages"]["find"]
    packages = find_namespace_packages(
        where=str(ROOT), include=find["include"], exclude=find.get("exclude", ())
    )
    assert "zplatform" in packages and "zplatform.boards" in packages
    assert {name.split(".")[0] for name in packages} == {"zplatform"}, packages
    assert "py.typed" in p["tool"]["setuptools"]["package-data"]["zplatform"]
    assert (ROOT / "zplatform" / "py.typed").is_file()


def test_psutil_is_a_runtime_dependency_of_the_health_thread_only() -> None:
    """Health sampling (zplatform/node/health.py) reads the host through psutil:
    a runtime dependency, imported there and nowhere else in the package."""
    p = _pyproject()
    assert any(d.startswith("psutil") for d in p["project"]["dependencies"])
    importers = set()
    for f in (ROOT / "zplatform").rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            else:
                continue
            if any(n.split(".")[0] == "psutil" for n in names):
                importers.add(f.relative_to(ROOT).as_posix())
    assert importers == {"zplatform/node/health.py"}


def test_demo_prints_no_json() -> None:
    demo = (ROOT / "scripts" / "demo.sh").read_text()
    assert "--summary -" not in demo and "--summary led_test.summary.json" in demo


def test_the_console_runs_on_the_base_install_and_extras_are_named() -> None:
    """`zplatform ground` is the ground station's daily tool: its libraries are
    base dependencies; the radio side (CCSDS, XTCE) stays in the `ground` extra."""
    p = _pyproject()
    base = {d.split(">=")[0] for d in p["project"]["dependencies"]}
    assert {"textual", "textual-serve", "textual-plotext"} <= base
    ground = {d.split(">=")[0] for d in p["project"]["optional-dependencies"]["ground"]}
    assert ground == {"spacepackets", "yamcs-pymdb"}
