"""Tests of zplatform.mission: load_mission runs every semantic check at load."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import zplatform
from zplatform.config import parse_mission
from zplatform.errors import ConfigError
from zplatform.mission import check_mission, decode_mission, load_mission

PKG = Path(zplatform.__file__).parent

BASE = """
mission: mtest
nodes:
  cn: {}
  dn0: {board: {physics: '%s'}}
regions:
  dn0_to_cn:
    - {name: v, type: f64}
"""


def test_public_front_door_is_the_checked_loader() -> None:
    assert zplatform.load_mission is load_mission
    assert zplatform.decode_mission is decode_mission


@pytest.mark.parametrize(
    ("physics", "match"),
    [
        ("os:getcwd", r"cannot be called as physics\(board, t_ns\)"),
        ("os:sep", "not a function"),
        ("no_such_zp_mod:f", "cannot import physics module"),
    ],
)
def test_a_bad_physics_function_is_refused_at_load(physics: str, match: str) -> None:
    text = BASE % physics
    parse_mission(text)  # structurally fine: only the semantic check sees it
    with pytest.raises(ConfigError, match=match) as ei:
        decode_mission(text)
    assert ei.value.path == "$.nodes.dn0.board.physics"


def test_a_bad_controller_or_device_class_is_refused_at_load() -> None:
    text = (BASE % "math:hypot").replace("  dn0: {board: {physics: 'math:hypot'}}\n", "  dn0: {}\n")
    ctl = text + "controllers:\n  - {name: c, class: 'no_such_zp_mod:C', node: cn}\n"
    with pytest.raises(ConfigError, match="cannot import module 'no_such_zp_mod'") as ei:
        decode_mission(ctl)
    assert ei.value.path == "$.controllers[0].class"
    dev = text + "devices:\n  - {name: d, class: 'zplatform.devices:Sensor', node: dn0}\n"
    with pytest.raises(ConfigError, match="is abstract") as ei:
        decode_mission(dev)
    assert ei.value.path == "$.devices[0].class"


def test_check_mission_accepts_a_parsed_good_mission(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("mission: ok\nnodes: {cn: {}}\nregions:\n  cn:\n    - {name: a, type: u8}\n")
    m = load_mission(p)
    check_mission(m)  # idempotent
    assert m.mission == "ok"


def _imported_modules(path: Path) -> set[str]:
    """The package-relative modules a file imports (``.errors`` -> ``errors``)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            if node.module:
                out.add(node.module)
            else:
                out.update(a.name for a in node.names)
    return out


def test_config_imports_no_module_that_gives_the_sections_meaning() -> None:
    assert _imported_modules(PKG / "config.py") <= {"codes", "errors", "types"}
    assert _imported_modules(PKG / "codes.py") == set()
    assert not (PKG / "_checks.py").exists()


def test_the_sans_io_core_never_imports_the_os_scheduler() -> None:
    for name in ("controllers.py", "devices.py", "components.py", "rategroups.py"):
        assert "scheduler" not in _imported_modules(PKG / name), name
