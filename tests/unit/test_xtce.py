"""XTCE export: every Data Vector element, with its type and bit position."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from zplatform import load_mission
from zplatform.cli.main import main
from zplatform.cli.xtce import HEADER_BITS, mission_xtce
from zplatform.config import CMD_NAMES, Mission
from zplatform.core.datavector import ElementSpec, Layout
from zplatform.mission.load import decode_mission
from zplatform.telemetry.ccsds import packet_plan

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
NS = {"x": "http://www.omg.org/spec/XTCE/20180204"}

ALL_TYPES = """
mission: all_types
nodes:
  cn: {listen: ["tcp/127.0.0.1:7999"]}
  dn0: {listen: ["tcp/127.0.0.1:7998"], connect: ["tcp/127.0.0.1:7999"]}
  gn: {listen: ["tcp/127.0.0.1:7997"], connect: ["tcp/127.0.0.1:7999"]}
regions:
  cn:
    - {name: a_u8, type: u8}
    - {name: a_i16, type: i16}
    - {name: a_u32, type: u32}
    - {name: a_i64, type: i64}
    - {name: a_f32, type: f32}
    - {name: a_f64, type: f64}
    - {name: a_bool, type: bool}
    - {name: a_vec, type: "f32[3]"}
    - {name: a_ints, type: "i8[4]"}
    - {name: a_mode, type: enum, enum: [IDLE_M, RUN_M, AUTO_M]}
  dn0_to_cn:
    - {name: d_u64, type: u64}
"""


def _missions() -> list[Mission]:
    return [
        load_mission(CONFIGS / "led_test.yaml"),
        load_mission(CONFIGS / "recovery_igniter.yaml"),
        decode_mission(ALL_TYPES),
    ]


def _check_type(t: ET.Element, spec: ElementSpec) -> None:
    """The XTCE parameter type ``t`` describes one value of ``spec``."""
    st = spec.scalar
    bits = str(st.size * 8)
    tag = t.tag.split("}")[1]
    if spec.enum is not None:
        assert tag == "EnumeratedParameterType", spec.name
        labels = {
            int(e.get("value", "")): e.get("label") for e in t.iterfind(".//x:Enumeration", NS)
        }
        assert labels == dict(enumerate(spec.enum))
        enc = t.find("x:IntegerDataEncoding", NS)
    elif st.kind == "bool":
        assert tag == "BooleanParameterType", spec.name
        enc = t.find("x:IntegerDataEncoding", NS)
        bits = "8"
    elif st.kind == "float":
        assert tag == "FloatParameterType", spec.name
        enc = t.find("x:FloatDataEncoding", NS)
    else:
        assert tag == "IntegerParameterType", spec.name
        assert t.get("signed") == ("true" if st.name.startswith("i") else "false"), spec.name
        enc = t.find("x:IntegerDataEncoding", NS)
        assert enc is not None
        want = "twosComplement" if st.name.startswith("i") else "unsigned"
        assert enc.get("encoding") == want, spec.name
    assert enc is not None, spec.name
    assert enc.get("sizeInBits") == bits, spec.name
    if bits != "8":  # byte order means nothing for one byte; pymdb leaves it out
        assert enc.get("byteOrder") == "leastSignificantByteFirst", spec.name


@pytest.mark.parametrize("mission", _missions(), ids=lambda m: m.mission)
def test_every_element_has_name_type_and_bit_position(mission: Mission) -> None:
    layout = Layout.for_node(mission, "cn")
    root = ET.fromstring(mission_xtce(mission).xml)
    tm = root.find("x:TelemetryMetaData", NS)
    assert tm is not None
    types = {t.get("name"): t for t in tm.iterfind("x:ParameterTypeSet/*", NS)}
    params = {p.get("name"): p for p in tm.iterfind("x:ParameterSet/x:Parameter", NS)}
    containers = {c.get("name"): c for c in tm.iterfind("x:ContainerSet/x:SequenceContainer", NS)}
    apids = {p.region: p.apid for p in packet_plan(mission)}

    for spec in layout.elements.values():
        p = params[spec.name]
        t = types[p.get("parameterTypeRef")]
        if spec.count:
            assert t.tag.endswith("ArrayParameterType"), spec.name
            dim = t.find(".//x:Dimension/x:EndingIndex/x:FixedValue", NS)
            assert dim is not None and int(dim.text or "") == spec.count - 1
            t = types[t.get("arrayTypeRef")]
        _check_type(t, spec)

        region = layout.region(spec.region)
        c = containers[spec.region]
        refs = {
            e.get("parameterRef"): int(e.findtext(".//x:FixedValue", "", NS))
            for e in c.iterfind("x:EntryList/x:ParameterRefEntry", NS)
        }
        assert refs[spec.name] == HEADER_BITS + (spec.offset - region.offset) * 8, spec.name
        apid = c.find(".//x:Condition/x:Value", NS)
        assert apid is not None and int(apid.text or "") == apids[spec.region]


def test_commands_are_meta_commands() -> None:
    mission = load_mission(CONFIGS / "recovery_igniter.yaml")
    root = ET.fromstring(mission_xtce(mission).xml)
    cmds = {c.get("name"): c for c in root.iterfind(".//x:MetaCommand", NS)}
    assert set(CMD_NAMES[1:]) <= set(cmds)
    launch = cmds["LAUNCH"].find("x:DefaultSignificance", NS)
    assert launch is not None and launch.get("consequenceLevel") == "critical"
    assert cmds["NOOP"].find("x:DefaultSignificance", NS) is None or (
        cmds["NOOP"].find("x:DefaultSignificance", NS).get("consequenceLevel") == "normal"  # type: ignore[union-attr]
    )


def test_xtce_verb_writes_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "led.xml"
    assert main(["xtce", str(CONFIGS / "led_test.yaml"), "--out", str(out)]) == 0
    ET.parse(out)
    assert main(["xtce", str(tmp_path / "missing.yaml")]) == 2
    assert "error" in capsys.readouterr().err


def test_limits_become_alarms() -> None:
    mission = decode_mission(ALL_TYPES)
    xml = mission_xtce(
        mission, limits={"a_f32": {"yellow": [-1, 1], "red": [None, 5]}, "a_i16": {"red": [0, 9]}}
    ).xml
    root = ET.fromstring(xml)
    types = {t.get("name"): t for t in root.iterfind(".//x:ParameterTypeSet/*", NS)}
    warn = types["a_f32"].find(".//x:WarningRange", NS)
    crit = types["a_f32"].find(".//x:CriticalRange", NS)
    assert warn is not None and crit is not None
    assert float(warn.get("minInclusive", "nan")) == -1.0
    assert float(warn.get("maxInclusive", "nan")) == 1.0
    assert crit.get("minInclusive") is None and float(crit.get("maxInclusive", "nan")) == 5.0
    assert types["a_i16"].find(".//x:CriticalRange", NS) is not None
    assert types["a_u8"].find(".//x:DefaultAlarm", NS) is None


def test_segmented_regions_get_a_container_per_segment() -> None:
    """With a small packet, elements sit in their segment's container, offset from it."""
    mission = load_mission(CONFIGS / "led_test.yaml")
    layout = Layout.for_node(mission, "cn")
    x = mission_xtce(mission, max_data=40)  # 22 region bytes per packet
    root = ET.fromstring(x.xml)
    containers = {c.get("name"): c for c in root.iterfind(".//x:SequenceContainer", NS)}
    plan = [p for p in packet_plan(mission, max_data=40) if p.region == "cn"]
    assert len(plan) > 1
    for p in plan:
        c = containers[f"cn_seg{p.offset}"]
        for e in c.iterfind("x:EntryList/x:ParameterRefEntry", NS):
            spec = layout.element(e.get("parameterRef", ""))
            rel = spec.offset - layout.region("cn").offset - p.offset
            assert rel >= 0 and rel + spec.size <= p.length
            assert int(e.findtext(".//x:FixedValue", "", NS)) == HEADER_BITS + rel * 8
    placed = {e.get("parameterRef") for e in root.iterfind(".//x:ParameterRefEntry", NS)}
    # Every element is either in a packet or reported as straddling a boundary.
    assert set(layout.elements) == (placed - {None}) - {
        "ccsds_packet_id",
        "ccsds_packet_sequence",
        "ccsds_packet_length",
        "ccsds_loop",
        "ccsds_time_ns",
        "ccsds_segment_offset",
    } | set(x.unplaced)


def _decode_by_xtce(t: ET.Element, types: dict[str | None, ET.Element], raw: bytes) -> object:
    """Decode one parameter from ``raw`` (its bytes) the way an XTCE tool reads the type."""
    import struct

    tag = t.tag.split("}")[1]
    if tag == "ArrayParameterType":
        item = types[t.get("arrayTypeRef")]
        enc = item.find("x:IntegerDataEncoding", NS)
        if enc is None:  # (an Element without children is falsy: no `or` here)
            enc = item.find("x:FloatDataEncoding", NS)
        assert enc is not None
        n = int(enc.get("sizeInBits", "0")) // 8
        return [_decode_by_xtce(item, types, raw[i : i + n]) for i in range(0, len(raw), n)]
    fenc = t.find("x:FloatDataEncoding", NS)
    if fenc is not None:
        assert fenc.get("byteOrder") == "leastSignificantByteFirst"
        return struct.unpack("<f" if fenc.get("sizeInBits") == "32" else "<d", raw)[0]
    ienc = t.find("x:IntegerDataEncoding", NS)
    assert ienc is not None
    order = "big" if ienc.get("byteOrder") == "mostSignificantByteFirst" else "little"
    signed = ienc.get("encoding") == "twosComplement"
    v = int.from_bytes(raw, order, signed=signed)
    if tag == "BooleanParameterType":
        return bool(v)
    if tag == "EnumeratedParameterType":
        labels = {
            int(e.get("value", "")): e.get("label") for e in t.iterfind(".//x:Enumeration", NS)
        }
        return labels.get(v, v)
    return v


@pytest.mark.parametrize("mission", _missions(), ids=lambda m: m.mission)
def test_packets_decode_by_the_xtce_alone(mission: Mission) -> None:
    """Reading our CCSDS packets with nothing but the XTCE gives the Data Vector's values."""
    import random

    from zplatform.core.datavector import DataVector
    from zplatform.telemetry.ccsds import CcsdsEncoder

    rnd = random.Random(7)
    enc = CcsdsEncoder(mission)
    dv = DataVector(enc.layout)
    dv.write_all(bytes(rnd.randrange(256) for _ in range(enc.layout.size)))
    for spec in enc.layout.elements.values():  # bools and enums hold what they can name
        if spec.scalar.kind == "bool":
            dv.write_all(
                dv.buf[: spec.offset] + bytes([rnd.randrange(2)]) + dv.buf[spec.offset + 1 :]
            )
        elif spec.enum is not None and not spec.count:
            dv.set(spec.name, rnd.randrange(len(spec.enum)))
    packets = [bytes(p) for p in enc.encode(dv, 12345, 678)]

    root = ET.fromstring(mission_xtce(mission).xml)
    tm = root.find("x:TelemetryMetaData", NS)
    assert tm is not None
    types = {t.get("name"): t for t in tm.iterfind("x:ParameterTypeSet/*", NS)}
    ptype = {p.get("name"): p.get("parameterTypeRef") for p in tm.iterfind(".//x:Parameter", NS)}
    by_apid = {}
    for c in tm.iterfind("x:ContainerSet/x:SequenceContainer", NS):
        v = c.find(".//x:Condition/x:Value", NS)
        if v is not None:
            by_apid[int(v.text or "")] = c
    seen = set()
    for pkt in packets:
        apid = ((pkt[0] & 0x07) << 8) | pkt[1]
        c = by_apid[apid]
        for e in c.iterfind("x:EntryList/x:ParameterRefEntry", NS):
            name = e.get("parameterRef", "")
            spec = enc.layout.element(name)
            pos = int(e.findtext(".//x:FixedValue", "", NS)) // 8
            got = _decode_by_xtce(types[ptype[name]], types, pkt[pos : pos + spec.size])
            want = dv.values()[name] if spec.count else dv.get(name)
            if spec.enum is not None and not spec.count:
                want = dv.get_name(name)
            if spec.scalar.kind == "float":
                import numpy as np

                assert np.array_equal(np.array(got), np.array(want), equal_nan=True), name
            else:
                assert got == want, name
            seen.add(name)
    assert seen == {n for n, s in enc.layout.elements.items() if s.size}
