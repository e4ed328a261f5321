"""Tests of zplatform.config: one test per rule, checking the message and the YAML path.

Missions are built as Python dicts and dumped to YAML, so each test states only
what it changes; YAML-specific cases (duplicate keys, `1e39`) are written as text.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from zplatform import ConfigError, Mission, decode_mission, load_mission
from zplatform.config import (
    CMD_NAMES,
    CMD_STATUS_NAMES,
    CONTROLLER_MODES,
    FAULT_NAMES,
    ClockConfig,
)

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

BASE: dict[str, Any] = {
    "mission": "t",
    "loop_hz": 100,
    "sync_timeout_ms": 2,
    "nodes": {
        "cn": {"listen": ["tcp/127.0.0.1:7000"]},
        "dn0": {"listen": ["tcp/127.0.0.1:7001"], "connect": ["tcp/127.0.0.1:7000"]},
    },
    "regions": {
        "cn": [{"name": "x", "type": "u8"}],
        "dn0_to_cn": [{"name": "y", "type": "f32"}],
    },
    "health": None,  # the element tests pin every element; health has its own
}


def mission(**changes: Any) -> dict[str, Any]:
    """A deep copy of BASE with top-level keys replaced (None deletes the key)."""
    d = copy.deepcopy(BASE)
    for k, v in changes.items():
        if v is None:
            d.pop(k, None)
        else:
            d[k] = v
    return d


def load(d: dict[str, Any] | str) -> Mission:
    return decode_mission(d if isinstance(d, str) else yaml.safe_dump(d, sort_keys=False))


def fails(d: dict[str, Any] | str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load(d)
    err = info.value
    # The message always ends with the path, in msgspec's style.
    assert str(err) == f"{err.reason} - at `{err.path}`"
    return err


def with_cn(*elements: dict[str, Any]) -> dict[str, Any]:
    """BASE with the `cn` region's user elements replaced."""
    d = mission()
    d["regions"]["cn"] = list(elements)
    return d


def test_base_mission_loads() -> None:
    m = load(mission())
    assert m.mission == "t"
    assert m.device_nodes == ["dn0"]


# -- top level -----------------------------------------------------------------


@pytest.mark.parametrize("text", ["", "{}", "# only a comment\n"])
def test_empty_config(text: str) -> None:
    err = fails(text)
    assert err.path == "$"
    assert "mission config is empty" in err.reason


def test_top_level_not_a_mapping() -> None:
    err = fails("[1, 2]")
    assert (err.path, "expected a mapping at the top level" in err.reason) == ("$", True)


def test_invalid_yaml() -> None:
    err = fails("mission: [")
    assert err.path == "$"
    assert "not valid YAML" in err.reason


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_mission(tmp_path / "nope.yaml")
    assert info.value.path == "$"
    assert "cannot read mission file" in info.value.reason


def test_missing_required_field() -> None:
    err = fails(mission(mission=None))
    assert err.path == "$"
    assert "missing required field `mission`" in err.reason


def test_bad_vehicle_prefix() -> None:
    err = fails(mission(vehicle="Rocket/1"))
    assert err.path == "$.vehicle"
    assert "vehicle key prefix" in err.reason


# -- msgspec's own checks: typos and wrong types, with its path ------------------


def test_unknown_top_level_field() -> None:
    d = mission()
    d["loop_hzz"] = 100
    err = fails(d)
    assert err.path == "$"
    assert err.reason == "Object contains unknown field `loop_hzz`"


def test_unknown_element_field() -> None:
    err = fails(with_cn({"name": "x", "tpye": "u8"}))
    assert err.path == "$.regions.cn[0]"  # the key msgspec writes as [...]
    assert err.reason == "Object contains unknown field `tpye`"


def test_unknown_node_field() -> None:
    d = mission()
    d["nodes"]["cn"]["lisen"] = []
    err = fails(d)
    assert err.path == "$.nodes.cn"
    assert err.reason == "Object contains unknown field `lisen`"


def test_wrong_type_names_path() -> None:
    err = fails(mission(loop_hz="fast"))
    assert err.path == "$.loop_hz"
    assert err.reason == "Expected `float`, got `str`"


def test_constraint_names_path() -> None:
    err = fails(mission(loop_hz=0))
    assert err.path == "$.loop_hz"
    assert "> 0" in err.reason


def test_wrong_type_nested() -> None:
    d = mission()
    d["nodes"]["cn"]["cpu"] = "x"
    err = fails(d)
    assert err.path == "$.nodes.cn.cpu"
    assert "got `str`" in err.reason


# -- clock -----------------------------------------------------------------------


def test_clock_estimator_defaults_to_zenoh_ts() -> None:
    assert load(mission()).clock.estimator == "zenoh_ts"
    assert ClockConfig().estimator == "zenoh_ts"


@pytest.mark.parametrize("name", ["zenoh_ts", "node_clock"])
def test_clock_estimator_chosen(name: str) -> None:
    assert load(mission(clock={"estimator": name})).clock.estimator == name


def test_unknown_clock_estimator_names_path() -> None:
    err = fails(mission(clock={"estimator": "ptp"}))
    assert err.path == "$.clock.estimator"
    assert "ptp" in err.reason


# -- nodes -----------------------------------------------------------------------


def test_no_nodes() -> None:
    err = fails(mission(nodes={}))
    assert err.path == "$.nodes"
    assert "at least the control node 'cn'" in err.reason


def test_missing_cn() -> None:
    d = mission(regions={"dn0_to_cn": [{"name": "y", "type": "f32"}]})
    del d["nodes"]["cn"]
    err = fails(d)
    assert err.path == "$.nodes"
    assert "the control node 'cn' is missing" in err.reason


@pytest.mark.parametrize("name", ["dn", "dnx", "node1", "DN0", "gn0"])
def test_bad_node_name(name: str) -> None:
    d = mission()
    d["nodes"][name] = {}
    err = fails(d)
    assert err.path == f"$.nodes.{name}"
    want = f"node name {name!r} is not one of cn, cn_b (a standby control node), gn, dn0, dn1"
    assert want in err.reason


@pytest.mark.parametrize("dns", [["dn1"], ["dn0", "dn2"], ["dn0", "dn1", "dn3"]])
def test_dn_numbering_gap(dns: list[str]) -> None:
    d = mission(regions={"cn": [{"name": "x", "type": "u8"}]})
    d["nodes"] = {"cn": {}, **{n: {} for n in dns}}
    err = fails(d)
    assert err.path == "$.nodes"
    assert "numbered dn0.." in err.reason and "without gaps" in err.reason


def test_duplicate_endpoint() -> None:
    d = mission()
    d["nodes"]["dn0"]["listen"] = ["tcp/127.0.0.1:7000"]
    err = fails(d)
    assert err.path == "$.nodes.dn0.listen[0]"
    assert err.reason == "endpoint 'tcp/127.0.0.1:7000' is also listened on by cn"


@pytest.mark.parametrize(
    ("field", "endpoint", "reason"),
    [
        ("listen", "127.0.0.1:7000", "is not '<proto>/<address>'"),
        ("listen", "http/127.0.0.1:7000", "is not '<proto>/<address>'"),
        ("listen", "tcp/127.0.0.1", "needs host:port"),
        ("listen", "tcp/:7000", "needs host:port"),
        ("listen", "udp/127.0.0.1:70000", "needs host:port with a port 0-65535"),
        ("connect", "tcp/127.0.0.1:x", "needs host:port"),
    ],
)
def test_bad_endpoint(field: str, endpoint: str, reason: str) -> None:
    d = mission()
    d["nodes"]["dn0"][field] = [endpoint]
    err = fails(d)
    assert err.path == f"$.nodes.dn0.{field}[0]"
    assert f"endpoint {endpoint!r}" in err.reason and reason in err.reason


def test_good_endpoints() -> None:
    d = mission()
    d["nodes"]["dn0"]["listen"] = ["unixsock-stream//tmp/zp.sock", "tcp/[::1]:7447"]
    load(d)


@pytest.mark.parametrize(("loop_hz", "timeout_ms"), [(100, 10), (100, 12), (1000, 1)])
def test_sync_timeout_not_shorter_than_period(loop_hz: float, timeout_ms: float) -> None:
    err = fails(mission(loop_hz=loop_hz, sync_timeout_ms=timeout_ms))
    assert err.path == "$.sync_timeout_ms"
    assert "must be shorter than the loop period" in err.reason


def test_sync_timeout_just_shorter_than_period() -> None:
    load(mission(loop_hz=100, sync_timeout_ms=9.999))


# -- regions ---------------------------------------------------------------------


@pytest.mark.parametrize("region", ["cn_to_dn1", "dn1_to_cn", "gn_to_cn", "dn0", "telemetry"])
def test_region_not_in_topology(region: str) -> None:
    d = mission()
    d["regions"][region] = [{"name": "z", "type": "u8"}]
    err = fails(d)
    assert err.path == f"$.regions.{region}"
    assert f"region {region!r} does not match the node topology" in err.reason
    assert "'cn_to_dn0'" in err.reason  # lists the valid ones


def test_empty_region() -> None:
    d = mission()
    d["regions"]["cn_to_dn0"] = []
    err = fails(d)
    assert err.path == "$.regions.cn_to_dn0"
    assert err.reason == "a region must have at least one element"


def test_duplicate_region_key() -> None:
    text = yaml.safe_dump(mission(regions={}), sort_keys=False).replace("regions: {}\n", "")
    text += "regions:\n  cn:\n  - {name: a, type: u8}\n  cn:\n  - {name: b, type: u8}\n"
    err = fails(text)
    assert err.path == "$.regions.cn"
    assert "key 'cn' is given twice" in err.reason


def test_duplicate_key_in_element() -> None:
    text = yaml.safe_dump(mission(regions={}), sort_keys=False).replace("regions: {}\n", "")
    text += "regions:\n  cn:\n  - {name: a, type: u8, name: b}\n"
    err = fails(text)
    assert err.path == "$.regions.cn[0].name"
    assert "key 'name' is given twice" in err.reason


def test_yaml_aliases_checked_once() -> None:
    # A recursive alias must not hang the duplicate-key walk; a shared one is
    # fine, and an element repeated through an alias is a duplicate element.
    assert fails("a: &x [*x]\n").path == "$"
    base = yaml.safe_dump(mission(regions={}), sort_keys=False).replace("regions: {}\n", "")
    err = fails(base + "regions:\n  cn: [&e {name: a, type: u8}, *e]\n")
    assert err.path == "$.regions.cn[1].name"


# -- elements --------------------------------------------------------------------


def test_duplicate_element_in_region() -> None:
    err = fails(with_cn({"name": "x", "type": "u8"}, {"name": "x", "type": "u16"}))
    assert err.path == "$.regions.cn[1].name"
    assert "duplicate element name 'x'" in err.reason


def test_duplicate_element_across_regions() -> None:
    d = mission()
    d["regions"]["cn_to_dn0"] = [{"name": "x", "type": "bool"}]
    err = fails(d)
    assert err.path == "$.regions.cn_to_dn0[0].name"
    assert "duplicate element name 'x'" in err.reason


@pytest.mark.parametrize("platform", ["cn_loop", "cn_state", "cn_rx_dn0"])
def test_mission_declares_cn_platform_element(platform: str) -> None:
    err = fails(with_cn({"name": "x", "type": "u8"}, {"name": platform, "type": "u64"}))
    assert err.path == "$.regions.cn[1].name"  # the index the user wrote
    assert f"duplicate element name {platform!r}" in err.reason
    assert "platform elements are added automatically" in err.reason


def test_mission_declares_later_region_platform_element() -> None:
    # `dn0_loop` belongs to dn0_to_cn, which comes after `cn`: the user's
    # element is still the one blamed, at the index the user wrote.
    err = fails(with_cn({"name": "dn0_loop", "type": "u64"}))
    assert err.path == "$.regions.cn[0].name"
    assert "duplicate element name 'dn0_loop'" in err.reason


def test_mission_declares_controller_mode() -> None:
    d = with_cn({"name": "x", "type": "u8"}, {"name": "pid_mode", "type": "u8"})
    d["controllers"] = [{"name": "pid", "class": "m:C", "node": "cn"}]
    err = fails(d)
    assert err.path == "$.regions.cn[1].name"
    assert "duplicate element name 'pid_mode'" in err.reason


@pytest.mark.parametrize("name", ["X", "1x", "a-b", "a b", ""])
def test_bad_element_name(name: str) -> None:
    err = fails(with_cn({"name": "ok", "type": "u8"}, {"name": name, "type": "u8"}))
    assert err.path == "$.regions.cn[1].name"
    assert f"element name {name!r} must match" in err.reason


@pytest.mark.parametrize("type_", ["f33", "f32[0]", "u8[x]", "u8[]", "F32", "float", "u8[-1]"])
def test_invalid_type(type_: str) -> None:
    err = fails(with_cn({"name": "x", "type": type_}))
    assert err.path == "$.regions.cn[0].type"
    assert err.reason.startswith(f"invalid element type {type_!r}")


def test_enum_without_names() -> None:
    err = fails(with_cn({"name": "x", "type": "enum"}))
    assert err.path == "$.regions.cn[0].type"
    assert "needs a `type`" in err.reason and "`enum` names" in err.reason


def test_enum_with_empty_names() -> None:
    err = fails(with_cn({"name": "x", "enum": []}))
    assert err.path == "$.regions.cn[0].enum"
    assert err.reason == "an enum needs a non-empty list of names in `enum`"


def test_enum_name_repeated() -> None:
    err = fails(with_cn({"name": "x", "enum": ["A", "B", "A"]}))
    assert err.path == "$.regions.cn[0].enum"
    assert err.reason == "enum names repeat: ['A', 'B', 'A']"


def test_enum_name_not_identifier() -> None:
    err = fails(with_cn({"name": "x", "enum": ["A", "2B"]}))
    assert err.path == "$.regions.cn[0].enum[1]"
    assert "enum name '2B' is not an identifier" in err.reason


def test_enum_with_non_int_type() -> None:
    err = fails(with_cn({"name": "x", "type": "f32", "enum": ["A"]}))
    assert err.path == "$.regions.cn[0].type"
    assert "must have type 'enum'" in err.reason


def test_enum_with_int_type_becomes_enum() -> None:
    m = load(with_cn({"name": "x", "type": "u8", "enum": ["A", "B"], "initial": "B"}))
    _, e = m.element("x")
    assert (e.type, e.initial) == ("enum", 1)


INT_OUT_OF_RANGE = [
    ("u8", 256),
    ("u8", -1),
    ("u16", 65536),
    ("u16", -1),
    ("u32", 2**32),
    ("u32", -1),
    ("u64", 2**64),
    ("u64", -1),
    ("i8", -129),
    ("i8", 128),
    ("i16", -32769),
    ("i16", 32768),
    ("i32", -(2**31) - 1),
    ("i32", 2**31),
    ("i64", -(2**63) - 1),
    ("i64", 2**63),
]


@pytest.mark.parametrize(("type_", "value"), INT_OUT_OF_RANGE)
def test_int_initial_out_of_range(type_: str, value: int) -> None:
    err = fails(with_cn({"name": "x", "type": type_, "initial": value}))
    assert err.path == "$.regions.cn[0].initial"
    assert err.reason.startswith(f"initial value {value} does not fit {type_} (range ")


INT_LIMITS = {
    "u8": (0, 255),
    "u16": (0, 65535),
    "u32": (0, 2**32 - 1),
    "u64": (0, 2**64 - 1),
    "i8": (-128, 127),
    "i16": (-32768, 32767),
    "i32": (-(2**31), 2**31 - 1),
    "i64": (-(2**63), 2**63 - 1),
}


@pytest.mark.parametrize("type_", list(INT_LIMITS))
def test_int_initial_limits_accepted(type_: str) -> None:
    lo, hi = INT_LIMITS[type_]
    m = load(
        with_cn(
            {"name": "lo", "type": type_, "initial": lo},
            {"name": "hi", "type": type_, "initial": hi},
        )
    )
    assert m.element("lo")[1].initial == lo
    assert m.element("hi")[1].initial == hi


@pytest.mark.parametrize(
    ("type_", "value", "reason"),
    [
        ("bool", 2, "initial value 2 does not fit bool"),
        ("bool", "yes-ish", "does not fit bool"),
        ("f64", "abc", "expected a number for f64, got 'abc'"),
        ("f32", "1.5", "expected a number for f32, got '1.5'"),
        ("f32", 1e39, "does not fit f32"),
        ("f32", -1e39, "does not fit f32"),
        ("i32", 1.5, "initial value 1.5 does not fit i32"),
        ("u8", "3", "does not fit u8"),
        ("u8", True, "does not fit u8"),
    ],
)
def test_bad_scalar_initial(type_: str, value: Any, reason: str) -> None:
    err = fails(with_cn({"name": "x", "type": type_, "initial": value}))
    assert err.path == "$.regions.cn[0].initial"
    assert reason in err.reason


def test_f32_exponent_without_dot() -> None:
    # PyYAML reads `1e39` (no dot) as a string; it must still be range-checked
    # as a number, and `1e-3` must load.
    base = yaml.safe_dump(mission(regions={}), sort_keys=False).replace("regions: {}\n", "")
    err = fails(base + "regions:\n  cn:\n  - {name: x, type: f32, initial: 1e39}\n")
    assert err.path == "$.regions.cn[0].initial"
    assert "does not fit f32" in err.reason
    m = load(base + "regions:\n  cn:\n  - {name: x, type: f32, initial: 1e-3}\n")
    assert m.element("x")[1].initial == 1e-3


@pytest.mark.parametrize("word", ["nan", "inf", "-inf", "Infinity"])
def test_float_words_accepted(word: str) -> None:
    m = load(with_cn({"name": "x", "type": "f32", "initial": word}))
    v = m.element("x")[1].initial
    assert math.isnan(v) if word == "nan" else math.isinf(v)


def test_scalar_coercions() -> None:
    m = load(
        with_cn(
            {"name": "b", "type": "bool", "initial": 1},
            {"name": "i", "type": "i16", "initial": 3.0},
            {"name": "f", "type": "f64", "initial": 2},
            {"name": "d", "type": "u32"},
            {"name": "e", "enum": ["A", "B"], "initial": 1},
        )
    )
    got = {n: m.element(n)[1].initial for n in "bifde"}
    assert got == {"b": True, "i": 3, "f": 2.0, "d": 0, "e": 1}
    assert type(got["b"]) is bool and type(got["i"]) is int and type(got["f"]) is float


def test_array_initial_length_mismatch() -> None:
    err = fails(with_cn({"name": "x", "type": "f32[3]", "initial": [1.0, 2.0]}))
    assert err.path == "$.regions.cn[0].initial"
    assert err.reason == "expected 3 initial values for f32[3], got 2"


def test_array_initial_item_out_of_range() -> None:
    err = fails(with_cn({"name": "x", "type": "u8[3]", "initial": [1, 256, 3]}))
    assert err.path == "$.regions.cn[0].initial[1]"
    assert "initial value 256 does not fit u8" in err.reason


def test_array_initial_scalar_broadcasts() -> None:
    m = load(with_cn({"name": "x", "type": "i16[4]", "initial": -2}))
    assert m.element("x")[1].initial == [-2, -2, -2, -2]


def test_scalar_initial_given_list() -> None:
    err = fails(with_cn({"name": "x", "type": "u8", "initial": [1]}))
    assert err.path == "$.regions.cn[0].initial"
    assert "needs a scalar initial value" in err.reason


def test_enum_initial_not_a_name() -> None:
    err = fails(with_cn({"name": "x", "enum": ["OFF", "ON"], "initial": "MAYBE"}))
    assert err.path == "$.regions.cn[0].initial"
    assert err.reason == "'MAYBE' is not one of the enum names ['OFF', 'ON']"


@pytest.mark.parametrize("value", [2, -1, True, 0.5])
def test_enum_initial_bad_int(value: Any) -> None:
    err = fails(with_cn({"name": "x", "enum": ["OFF", "ON"], "initial": value}))
    assert err.path == "$.regions.cn[0].initial"
    assert "expected one of the enum names ['OFF', 'ON']" in err.reason


def test_state_machine_initial_not_a_state() -> None:
    d = mission(state_machine={"initial": "GO", "states": {"IDLE": {}, "RUN": {}}})
    err = fails(d)
    assert err.path == "$.state_machine.initial"
    assert "'GO' is not one of the enum names ['IDLE', 'RUN']" in err.reason


# -- controllers and devices ------------------------------------------------------


def component(
    name: str = "c", node: str = "cn", cls: str = "stub_components:Idle"
) -> dict[str, Any]:
    return {"name": name, "class": cls, "node": node}


def test_controller_on_gn() -> None:
    d = mission(controllers=[component(node="gn")])
    d["nodes"]["gn"] = {}
    err = fails(d)
    assert err.path == "$.controllers[0].node"
    assert "controller 'c' is placed on 'gn'; expected cn or a device node" in err.reason


def test_controller_on_unknown_node() -> None:
    err = fails(mission(controllers=[component(), component("d", node="dn7")]))
    assert err.path == "$.controllers[1].node"
    assert "placed on 'dn7'" in err.reason


def test_device_on_cn() -> None:
    err = fails(mission(devices=[component(node="cn")]))
    assert err.path == "$.devices[0].node"
    assert err.reason == "devices run on device nodes only"


def test_duplicate_controller() -> None:
    err = fails(mission(controllers=[component("pid"), component("pid", node="dn0")]))
    assert err.path == "$.controllers[1].name"
    assert err.reason == "duplicate controller name 'pid'"


def test_duplicate_device() -> None:
    err = fails(mission(devices=[component("s", node="dn0"), component("s", node="dn0")]))
    assert err.path == "$.devices[1].name"
    assert err.reason == "duplicate device name 's'"


@pytest.mark.parametrize("section", ["controllers", "devices"])
def test_class_without_colon(section: str) -> None:
    err = fails(mission(**{section: [component(node="dn0", cls="pkg.mod.Cls")]}))
    assert err.path == f"$.{section}[0].class"
    assert err.reason == "class 'pkg.mod.Cls' must be 'package.module:ClassName'"


def test_bad_controller_name() -> None:
    err = fails(mission(controllers=[component("Pid")]))
    assert err.path == "$.controllers[0].name"
    assert "name 'Pid' must match" in err.reason


def test_bad_initial_mode() -> None:
    err = fails(mission(controllers=[{**component(), "initial_mode": "on"}]))
    assert err.path == "$.controllers[0].initial_mode"


# -- platform elements (DESIGN §5) --------------------------------------------------

CN_PLATFORM = [
    "cn_loop",
    "cn_time_ns",
    "cn_state",
    "cn_loop_overruns",
    "cn_sync_overruns",
    "cn_errors",
    "cn_last_error",
    "cn_bad_frames",
    "cn_cmd",
    "cn_cmd_seq",
    "cn_cmd_status",
    "cn_fault",
    "cn_time_in_state_ns",
]


def dn_platform(dn: str) -> list[str]:
    return [
        f"{dn}_loop",
        f"{dn}_time_ns",
        f"{dn}_loop_overruns",
        f"{dn}_errors",
        f"{dn}_bad_frames",
        f"{dn}_clock_offset_ns",
    ]


def full_mission() -> Mission:
    d = mission(
        regions={
            "cn": [{"name": "x", "type": "u8"}],
            "cn_to_dn1": [{"name": "valve", "type": "bool"}],
            "dn0_to_cn": [{"name": "y", "type": "f32"}],
        },
        state_machine={"initial": "RUN", "states": {"IDLE": {}, "RUN": {}, "SAFE": {}}},
        controllers=[
            {**component("alpha"), "initial_mode": "enabled"},
            component("beta", node="dn1"),
            component("gamma"),
        ],
    )
    d["nodes"]["dn1"] = {}
    d["nodes"]["gn"] = {}
    return load(d)


def names(m: Mission, region: str) -> list[str]:
    return [e.name for e in m.regions[region]]


def test_region_order_follows_topology() -> None:
    m = full_mission()
    order = ["cn", "cn_to_dn0", "dn0_to_cn", "cn_to_dn1", "dn1_to_cn", "gn_to_cn"]
    assert m.region_names() == order
    assert list(m.regions) == order
    assert m.node_regions("dn1") == ["cn_to_dn1", "dn1_to_cn"]
    assert m.node_regions("gn") == ["gn_to_cn"]


def in_order(sub: list[str], seq: list[str]) -> bool:
    """Whether ``sub`` occurs in ``seq`` in this order (other items may sit between:
    modules landing later may add platform elements of their own)."""
    it = iter(seq)
    return all(x in it for x in sub)


def test_cn_platform_elements_in_order() -> None:
    m = full_mission()
    cn = names(m, "cn")
    per_dn = [f"cn_{k}_{dn}" for dn in ("dn0", "dn1") for k in ("rx", "missed", "late")]
    assert in_order([*CN_PLATFORM, *per_dn, "alpha_mode", "gamma_mode", "x"], cn)
    # Platform elements first, then controller modes, then the mission's own.
    assert cn[-3:] == ["alpha_mode", "gamma_mode", "x"]
    types = {e.name: e.type for e in m.regions["cn"]}
    assert types["cn_loop"] == "u64" and types["cn_time_ns"] == "i64"
    assert types["cn_last_error"] == "u16" and types["cn_rx_dn1"] == "u32"
    state = m.element("cn_state")[1]
    assert (state.type, state.enum, state.initial) == ("enum", ["IDLE", "RUN", "SAFE"], 1)
    assert m.element("cn_cmd")[1].enum == list(CMD_NAMES)
    assert m.element("cn_cmd_status")[1].enum == list(CMD_STATUS_NAMES)
    assert m.element("cn_fault")[1].enum == list(FAULT_NAMES)


def test_dn_and_gn_platform_elements() -> None:
    m = full_mission()
    dn0 = names(m, "dn0_to_cn")
    assert in_order(dn_platform("dn0"), dn0)
    assert dn0[-1] == "y"
    assert in_order(dn_platform("dn1"), names(m, "dn1_to_cn"))
    assert names(m, "gn_to_cn") == [
        "gn_cmd",
        "gn_cmd_seq",
        "gn_cmd_epoch",
        "gn_cmd_element",
        "gn_cmd_value",
    ]
    # u64 numbers and the CN's epoch: a sequence space no request can exhaust
    assert [e.type for e in m.regions["gn_to_cn"]] == ["enum", "u64", "u64", "u16", "f64"]


def test_controller_mode_placement() -> None:
    m = full_mission()
    # The platform's final-loop flag, then the modes, then the mission's own.
    assert names(m, "cn_to_dn0") == ["dn0_final"]  # nothing declared, no controller there
    assert names(m, "cn_to_dn1") == ["dn1_final", "beta_mode", "valve"]
    assert m.element("dn1_final")[1].type == "bool"
    modes = {n: m.element(f"{n}_mode")[1] for n in ("alpha", "beta", "gamma")}
    assert all(e.enum == list(CONTROLLER_MODES) for e in modes.values())
    assert modes["alpha"].initial == CONTROLLER_MODES.index("enabled")
    assert modes["beta"].initial == CONTROLLER_MODES.index("safed")


def test_default_state_when_no_state_machine() -> None:
    m = load(mission())
    state = m.element("cn_state")[1]
    assert (state.enum, state.initial) == (["IDLE"], 0)
    assert "gn_to_cn" not in m.regions


def test_derived_views() -> None:
    m = load(mission(loop_hz=250, sync_timeout_ms=1.5))
    assert m.period_ns == 4_000_000
    assert m.sync_timeout_ns == 1_500_000
    assert not m.has_ground
    with pytest.raises(ConfigError) as info:
        m.node_regions("dn5")
    assert info.value.path == "$.nodes"
    with pytest.raises(KeyError):
        m.element("nope")


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_configs_load(path: Path) -> None:
    m = load_mission(path)
    assert m.mission == path.stem
    assert m.region_names()[0] == "cn"
    assert in_order(CN_PLATFORM, names(m, "cn"))


def test_shipped_configs_exist() -> None:
    assert {"minimal", "led_test"} <= {p.stem for p in CONFIGS.glob("*.yaml")}


def test_a_standby_control_node_is_checked_at_load() -> None:
    """A standby (`cn_b`) needs device nodes, a takeover that fits the device
    nodes' watchdog and a lease within it; it carries no board, no
    controller of its own, no bulk channel end; `failover:` needs it."""
    d = mission()
    d["nodes"]["cn_b"] = {}
    d["failover"] = {"takeover_loops": 8}
    err = fails(d)
    assert err.path == "$.failover.takeover_loops" and "watchdog" in err.reason
    d["failover"] = {"takeover_loops": 3, "lease_loops": 4}
    err = fails(d)
    assert err.path == "$.failover.lease_loops"
    d["failover"] = {}
    d["nodes"]["cn_b"] = {"board": {"driver": "sim"}}
    assert fails(d).path == "$.nodes.cn_b.board"
    d["nodes"]["cn_b"] = {}
    d.pop("failover")
    no_dns = {k: v for k, v in d["nodes"].items() if not k.startswith("dn")}
    err = fails({**d, "nodes": no_dns, "regions": {"cn": d["regions"]["cn"]}})
    assert err.path == "$.nodes.cn_b" and "device nodes" in err.reason
    e = mission()
    e["failover"] = {}
    assert fails(e).path == "$.failover"
