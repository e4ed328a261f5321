"""Tests of zplatform.mission.load: load_mission runs every semantic check at load."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import zplatform
from zplatform.config import parse_mission
from zplatform.errors import ConfigError
from zplatform.mission.load import check_mission, decode_mission, load_mission

ROOT = Path(__file__).resolve().parents[2]

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
    dev = text + "devices:\n  - {name: d, class: 'zplatform.control.devices:Sensor', node: dn0}\n"
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


def _package_imports(path: Path) -> tuple[set[str], set[str]]:
    """A module of a subpackage's imports: (its siblings, the package's modules above)."""
    siblings: set[str] = set()
    above: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level in (1, 2):
            into = siblings if node.level == 1 else above
            into.update([node.module] if node.module else [a.name for a in node.names])
    return siblings, above


def test_config_imports_no_module_that_gives_the_sections_meaning() -> None:
    # The package's rooms import downwards only: schema <- platform <- checks.
    below: dict[str, set[str]] = {
        "codes": set(),
        "types": set(),
        "schema": {"codes", "types"},
        "platform": {"schema", "codes", "types"},
        "checks": {"schema", "platform", "types"},
    }
    below["__init__"] = {"schema", "platform", "checks"}
    for name, allowed in below.items():
        siblings, above = _package_imports(PKG / "config" / f"{name}.py")
        assert siblings <= allowed, name
        assert above <= {"errors"}, name
    assert _imported_modules(PKG / "config" / "codes.py") == set()
    assert not (PKG / "_checks.py").exists()


def test_the_sans_io_core_never_imports_the_os_scheduler() -> None:
    for name in (
        "control/controllers.py",
        "control/devices.py",
        "core/components.py",
        "control/rategroups.py",
    ):
        assert "scheduler" not in _imported_modules(PKG / name), name


# -- limits and names (safety review) ---------------------------------------

SMALL = """
mission: limits
nodes: {cn: {}, dn0: {}}
regions:
  cn:
    - {name: a, type: u8}
"""


def _refused(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        decode_mission(text)
    return ei.value


@pytest.mark.parametrize("type_", ["u8[99999999999]", "f64[16777217]", "u8[16777217]"])
def test_an_array_over_16_mi_items_is_refused_with_its_path(type_: str) -> None:
    err = _refused(SMALL + f"    - {{name: big, type: '{type_}'}}\n")
    assert err.path == "$.regions.cn[1].type"
    assert "an array holds at most 16777216 (16 Mi)" in str(err)


def test_a_region_over_256_mib_is_refused_with_its_path() -> None:
    # f64[400000000] used to fail with MemoryError; 3 x 128 MiB is also too much.
    assert _refused(SMALL + "    - {name: big, type: 'f64[400000000]'}\n").path == (
        "$.regions.cn[1].type"
    )
    three = "".join(f"    - {{name: b{i}, type: 'f64[16777216]'}}\n" for i in range(3))
    err = _refused(SMALL + three)  # b0 + b1 + `a` + platform elements: one byte too many
    assert err.path == "$.regions.cn[2].type"
    assert "a region holds at most 268435456 bytes (256 MiB)" in str(err)
    assert "'b1'" in str(err)


def test_the_whole_vector_is_limited_too() -> None:
    text = SMALL + (
        "    - {name: b0, type: 'f64[16777216]'}\n"
        "  dn0_to_cn:\n"
        "    - {name: b1, type: 'f64[16777216]'}\n"
    )
    err = _refused(text)
    assert err.path == "$.regions.dn0_to_cn[0].type"  # cn already holds b0
    assert "Data Vector (every region)" in str(err) and "268435456" in str(err)


def test_arrays_at_the_limit_are_fine() -> None:
    m = parse_mission(SMALL + "    - {name: big, type: 'u8[16777216]'}\n")
    assert m.element("big")[1].type == "u8[16777216]"


def test_cpu_must_not_be_negative_but_may_exceed_this_host() -> None:
    err = _refused(SMALL.replace("cn: {}", "cn: {cpu: -1}"))
    assert err.path == "$.nodes.cn.cpu" and ">= 0" in str(err)
    m = decode_mission(SMALL.replace("cn: {}", "cn: {cpu: 4096}"))  # another host's CPU
    assert m.nodes["cn"].cpu == 4096


@pytest.mark.parametrize(
    ("name", "why"),
    [
        ('"led\\u0000test"', "control character"),
        ('"led\\ntest"', "control character"),
        ('"led/test"', "zenoh key expressions"),
        ('"led*"', "zenoh key expressions"),
        ('""', "is empty"),
    ],
)
def test_mission_names_are_printable_and_key_safe(name: str, why: str) -> None:
    err = _refused(SMALL.replace("mission: limits", f"mission: {name}"))
    assert err.path == "$.mission" and why in str(err)


@pytest.mark.parametrize(
    ("edit", "path"),
    [
        (("mission: limits", 'mission: limits\nvehicle: "rocket\\n"'), "$.vehicle"),
        (("mission: limits", 'mission: limits\nvehicle: "ro\\u0000cket"'), "$.vehicle"),
        (("{name: a, type: u8}", '{name: "a\\n", type: u8}'), "$.regions.cn[0].name"),
        (("{name: a, type: u8}", '{name: "a*", type: u8}'), "$.regions.cn[0].name"),
        (("dn0: {}", '"dn0\\n": {}'), "$.nodes.dn0\n"),
    ],
)
def test_key_names_refuse_control_characters_and_specials(edit: tuple[str, str], path: str) -> None:
    # `$` in a regex also matches before a final newline: names use fullmatch.
    err = _refused(SMALL.replace(*edit))
    assert err.path == path


ZERO = (
    SMALL
    + """
state_machine:
  initial: A
  states:
    A: {transitions: [{after_s: 0, to: B}]}
    B: {transitions: [{after_s: 0.5, to: C}, {after_s: 0, to: C}]}
    C: {transitions: [{after_s: 0, to: A}]}
"""
)


def test_a_cycle_of_zero_time_transitions_is_refused_naming_the_states() -> None:
    err = _refused(ZERO)
    assert "A -> B -> C -> A" in str(err) and "after_s: 0" in str(err)
    assert err.path == "$.state_machine.states.C.transitions[0]"
    selfloop = SMALL + (
        "state_machine:\n  initial: A\n  states:\n    A: {transitions: [{after_s: 0, to: A}]}\n"
    )
    err = _refused(selfloop)
    assert "A -> A" in str(err) and err.path == "$.state_machine.states.A.transitions[0]"


def test_zero_time_chains_without_a_cycle_and_timed_cycles_are_fine() -> None:
    decode_mission(ZERO.replace("C: {transitions: [{after_s: 0, to: A}]}", "C: {}"))
    decode_mission(ZERO.replace("{after_s: 0, to: A}", "{after_s: 0.01, to: A}"))


def test_tls_endpoints_load_without_a_deployment_and_quic_is_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A tls/ mission loads on any host; its sessions need the deployment
    # (tests/unit/test_deploy.py). quic/ is not supported yet.
    monkeypatch.delenv("ZPLATFORM_DEPLOYMENT", raising=False)
    assert decode_mission(SMALL.replace("cn: {}", "cn: {listen: ['tls/10.0.0.1:7447']}")).mtls
    err = _refused(SMALL.replace("cn: {}", "cn: {listen: ['quic/10.0.0.1:7447']}"))
    assert err.path == "$.nodes.cn.listen[0]"
    assert "TLS certificate settings" in str(err) and "not support" in str(err)
    text = SMALL.replace("dn0: {}", "dn0: {connect: ['quic/10.0.0.1:7447']}")
    assert _refused(text).path == "$.nodes.dn0.connect[0]"


def test_errors_inside_named_mappings_name_the_key() -> None:
    # msgspec says `$.nodes[...].priority`; the user needs the node's name.
    err = _refused(SMALL.replace("dn0: {}", "dn0: {priority: 100}"))
    assert err.path == "$.nodes.dn0.priority"
    err = _refused(
        SMALL + "state_machine:\n  initial: A\n  states:\n"
        "    A: {}\n    B: {transitions: [{after_s: -1, to: A}]}\n"
    )
    assert err.path == "$.state_machine.states.B.transitions[0].after_s"


def test_limits_are_checked_at_load() -> None:
    base = (ROOT / "configs" / "minimal.yaml").read_text()
    ok = base.replace(
        "- {name: heartbeat, type: u32, initial: 0}",
        "- {name: heartbeat, type: u32, initial: 0, limits: {yellow: [0, 100], red: [null, 200]}}",
    )
    m = decode_mission(ok)
    assert m.element("heartbeat")[1].limits is not None
    bad = base.replace(
        "- {name: heartbeat, type: u32, initial: 0}",
        "- {name: heartbeat, type: u32, initial: 0, limits: {red: [5, 1]}}",
    )
    with pytest.raises(ConfigError) as ei:
        decode_mission(bad)
    assert ei.value.path == "$.regions.cn[0].limits.red"
