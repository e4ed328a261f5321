"""Tests of zplatform.core.datavector: element, region and whole-vector access, layout,
layout_id."""

from __future__ import annotations

import itertools
import math
import struct
import zlib
from typing import Any

import numpy as np
import pytest

from zplatform import DataVector, DataVectorError, Layout, decode_mission
from zplatform.config import ElementConfig
from zplatform.core.datavector import LAYOUT_MAGIC, VECTOR_MAGIC, layout_id_of

MISSION = """
mission: dvtest
nodes: {cn: {}, dn0: {}}
health: null  # the vector tests pin every element; health is its own test
regions:
  cn:
    - {name: v_u8, type: u8, initial: 7}
    - {name: v_u16, type: u16}
    - {name: v_u32, type: u32}
    - {name: v_u64, type: u64}
    - {name: v_i8, type: i8, initial: -3}
    - {name: v_i16, type: i16}
    - {name: v_i32, type: i32}
    - {name: v_i64, type: i64}
    - {name: v_f32, type: f32, initial: 0.5}
    - {name: v_f64, type: f64}
    - {name: v_bool, type: bool, initial: true}
    - {name: a_f32, type: "f32[3]", initial: [1.0, 2.0, 3.0]}
    - {name: a_u8, type: "u8[4]"}
    - {name: a_i64, type: "i64[2]", initial: -1}
    - {name: a_bool, type: "bool[2]"}
    - {name: a_f64, type: "f64[2]"}
    - {name: mode, enum: [SAFE, ARMED, AUTO], initial: AUTO}
  cn_to_dn0:
    - {name: meas, type: f64, initial: 2.5}
  dn0_to_cn:
    - {name: cmd, type: u16, initial: 9}
"""

SCALARS: dict[str, tuple[Any, ...]] = {
    # type: values to round-trip (limits included)
    "u8": (0, 1, 255),
    "u16": (0, 65535),
    "u32": (0, 1, 2**32 - 1),
    "u64": (0, 2**64 - 1),
    "i8": (-128, 127, -1),
    "i16": (-32768, 32767),
    "i32": (-(2**31), 2**31 - 1),
    "i64": (-(2**63), 2**63 - 1),
    "f32": (0.0, -0.0, 1.5, -2.25, math.inf, -math.inf, 3.4028234663852886e38),
    "f64": (0.1, -0.0, 1e308, 5e-324, math.inf, -math.inf),
    "bool": (True, False),
}
OUT_OF_RANGE: dict[str, tuple[Any, ...]] = {
    "u8": (256, -1, 1.5, "1", None),
    "u16": (65536, -1),
    "u32": (2**32, -1),
    "u64": (2**64, -1),
    "i8": (128, -129),
    "i16": (32768, -32769),
    "i32": (2**31, -(2**31) - 1),
    "i64": (2**63, -(2**63) - 1),
    "f32": (1e39, -1e39, "x", None),
    "f64": ("1.0", None, [1.0]),
    "bool": (2, -1, "true", None),
}


@pytest.fixture(scope="module")
def layout() -> Layout:
    return Layout.for_node(decode_mission(MISSION), "cn")


@pytest.fixture
def dv(layout: Layout) -> DataVector:
    return DataVector(layout)


def raw(dv: DataVector, name: str) -> bytes:
    spec = dv.layout.element(name)
    return bytes(dv.buf[spec.offset : spec.offset + spec.size])


# -- elements ------------------------------------------------------------------


def test_initial_values(dv: DataVector) -> None:
    v = dv.values()
    assert (v["v_u8"], v["v_i8"], v["v_f32"], v["v_bool"]) == (7, -3, 0.5, True)
    assert v["a_f32"] == [1.0, 2.0, 3.0]
    assert v["a_i64"] == [-1, -1]
    assert v["a_bool"] == [False, False]
    assert v["mode"] == 2
    assert (v["cmd"], v["meas"]) == (9, 2.5)


@pytest.mark.parametrize(
    ("type_", "value"), [(t, v) for t, vs in SCALARS.items() for v in vs], ids=repr
)
def test_scalar_by_name_and_handle(dv: DataVector, type_: str, value: Any) -> None:
    name = f"v_{type_}"
    fmt = "<" + dv.layout.element(name).scalar.struct
    dv.set(name, value)
    got = dv.get(name)
    assert type(got) is type(value)
    assert got == value and math.copysign(1, got) == math.copysign(1, value)
    assert raw(dv, name) == struct.pack(fmt, value)
    dv.reset()
    h = dv.handle(name)
    assert dv.handle(name) is h  # cached
    h.set(value)
    assert h.get() == value and type(h.get()) is type(value)
    assert raw(dv, name) == struct.pack(fmt, value)


@pytest.mark.parametrize(
    ("type_", "value"), [(t, v) for t, vs in OUT_OF_RANGE.items() for v in vs], ids=repr
)
def test_set_refuses_out_of_range(dv: DataVector, type_: str, value: Any) -> None:
    before = bytes(dv.buf)
    with pytest.raises(DataVectorError):
        dv.set(f"v_{type_}", value)
    assert bytes(dv.buf) == before


@pytest.mark.parametrize(
    ("type_", "value"), [("u8", 256), ("i16", -32769), ("u64", -1), ("u32", None)]
)
def test_handle_set_refuses_what_struct_refuses(dv: DataVector, type_: str, value: Any) -> None:
    # The unchecked hot path: it raises, and only its own element may change
    # (struct zeroes it first; DataVector.set is the checked path).
    name = f"v_{type_}"
    spec = dv.layout.element(name)
    before = bytearray(dv.buf)
    with pytest.raises(DataVectorError, match=name):
        dv.handle(name).set(value)
    before[spec.offset : spec.offset + spec.size] = dv.buf[spec.offset : spec.offset + spec.size]
    assert dv.buf == before


def test_set_accepts_integral_float_and_numpy_scalars(dv: DataVector) -> None:
    dv.set("v_i32", 3.0)
    assert dv.get("v_i32") == 3 and type(dv.get("v_i32")) is int
    dv.set("v_u64", np.uint64(2**64 - 1))
    assert dv.get("v_u64") == 2**64 - 1
    dv.set("v_f64", np.float32(0.5))
    assert dv.get("v_f64") == 0.5
    dv.set("v_bool", 0)
    assert dv.get("v_bool") is False


@pytest.mark.parametrize(
    ("name", "value", "expected"),
    [
        ("v_u32", 1, b"\x01\x00\x00\x00"),
        ("v_u16", 0x1234, b"\x34\x12"),
        ("v_i16", -2, b"\xfe\xff"),
        ("v_i64", -(2**63), b"\x00" * 7 + b"\x80"),
        ("v_f32", 1.0, b"\x00\x00\x80\x3f"),
        ("v_f64", -2.0, b"\x00" * 6 + b"\x00\xc0"),
        ("v_bool", True, b"\x01"),
        ("v_bool", False, b"\x00"),
    ],
)
def test_little_endian_bytes(dv: DataVector, name: str, value: Any, expected: bytes) -> None:
    dv.set(name, value)
    assert raw(dv, name) == expected


def test_unknown_names(dv: DataVector) -> None:
    with pytest.raises(DataVectorError, match="no element named 'nope'"):
        dv.get("nope")
    with pytest.raises(DataVectorError, match="no element named 'nope'"):
        dv.set("nope", 1)
    with pytest.raises(DataVectorError, match="no region named 'nope'"):
        dv.region_view("nope")


# -- arrays --------------------------------------------------------------------


def test_array_view_is_zero_copy(dv: DataVector) -> None:
    spec = dv.layout.element("a_f32")
    view = dv.handle("a_f32").get()
    assert isinstance(view, np.ndarray) and view.shape == (3,) and view.dtype == np.dtype("<f4")
    assert np.shares_memory(view, np.frombuffer(dv.buf, dtype=np.uint8))
    view[1] = -8.0
    assert dv.buf[spec.offset + 4 : spec.offset + 8] == struct.pack("<f", -8.0)
    # and the other way: bytes written into the buffer are seen by the view
    dv.buf[spec.offset : spec.offset + 4] = struct.pack("<f", 42.0)
    assert view[0] == 42.0
    assert dv.get("a_f32") is not None and list(dv.get("a_f32")) == [42.0, -8.0, 3.0]


def test_array_set_checked(dv: DataVector) -> None:
    dv.set("a_u8", [0, 1, 254, 255])
    assert dv.values()["a_u8"] == [0, 1, 254, 255]
    assert raw(dv, "a_u8") == b"\x00\x01\xfe\xff"
    dv.set("a_u8", 5)  # a scalar fills the array
    assert raw(dv, "a_u8") == b"\x05" * 4
    dv.set("a_i64", np.array([-(2**63), 2**63 - 1]))
    assert dv.values()["a_i64"] == [-(2**63), 2**63 - 1]
    dv.set("a_bool", [True, False])
    assert raw(dv, "a_bool") == b"\x01\x00"


def test_array_set_exact_64_bit_ints() -> None:
    # [0, 2**64 - 1] is a float64 array to a plain np.asarray; the check must
    # not go through floats.
    m = decode_mission(
        "mission: t\nnodes: {cn: {}}\nregions:\n  cn:\n    - {name: a, type: 'u64[3]'}\n"
    )
    dv = DataVector(Layout.for_node(m, "cn"))
    dv.set("a", [0, 2**64 - 1, 2**63 + 1])
    assert dv.values()["a"] == [0, 2**64 - 1, 2**63 + 1]
    with pytest.raises(DataVectorError):
        dv.set("a", [0, 2**64, 1])
    dv.set("a", [np.uint64(1), np.int8(2), 3])  # numpy scalars in a list
    assert dv.values()["a"] == [1, 2, 3]
    dv.set("a", np.array([5, 6, 7], dtype=np.uint64))
    assert dv.values()["a"] == [5, 6, 7]


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("a_u8", [1, 2, 3]),  # too short
        ("a_u8", [1, 2, 3, 4, 5]),  # too long
        ("a_u8", [[1, 2], [3, 4]]),  # wrong shape
        ("a_u8", [1, 2, 3, 256]),  # one item out of range: nothing written
        ("a_u8", [1, 2, 3, -1]),
        ("a_f32", [1.0, 1e39, 0.0]),
        ("a_f32", ["a", "b", "c"]),
        ("a_bool", [True, 2]),
    ],
)
def test_array_set_refused_vector_unchanged(dv: DataVector, name: str, value: Any) -> None:
    before = bytes(dv.buf)
    with pytest.raises(DataVectorError):
        dv.set(name, value)
    assert bytes(dv.buf) == before


# -- enums ---------------------------------------------------------------------


def test_enum_by_name_and_int(dv: DataVector) -> None:
    assert dv.get("mode") == 2 and dv.get_name("mode") == "AUTO"
    dv.set("mode", "ARMED")
    assert dv.get("mode") == 1 and dv.get_name("mode") == "ARMED"
    dv.set("mode", 0)
    assert dv.get_name("mode") == "SAFE"
    assert raw(dv, "mode") == b"\x00"
    spec = dv.layout.element("mode")
    assert (spec.size, spec.scalar.name, spec.enum) == (1, "u8", ("SAFE", "ARMED", "AUTO"))
    assert spec.name_of(7) == "7"


@pytest.mark.parametrize("value", ["MAYBE", "safe", 3, -1, True, 1.5, None])
def test_enum_refuses(dv: DataVector, value: Any) -> None:
    before = bytes(dv.buf)
    with pytest.raises(DataVectorError):
        dv.set("mode", value)
    assert bytes(dv.buf) == before


def test_large_enum_is_u16() -> None:
    names = ", ".join(f"S{i}" for i in range(300))
    m = decode_mission(
        "mission: t\nnodes: {cn: {}}\nregions:\n  cn:\n"
        f"    - {{name: big, enum: [{names}], initial: S299}}\n"
    )
    dv = DataVector(Layout.for_node(m, "cn"))
    spec = dv.layout.element("big")
    assert (spec.scalar.name, spec.size) == ("u16", 2)
    assert spec.type_text.startswith("enum(u16:S0,S1,")
    assert dv.get_name("big") == "S299" and raw(dv, "big") == struct.pack("<H", 299)


# -- regions and whole vector ----------------------------------------------------


def in_region(dv: DataVector, region: str, name: str) -> slice:
    """Where element ``name`` sits inside region ``region``'s bytes."""
    r, e = dv.layout.region(region), dv.layout.element(name)
    return slice(e.offset - r.offset, e.offset - r.offset + e.size)


@pytest.mark.parametrize("kind", [bytearray, lambda n: memoryview(bytearray(n))])
def test_read_region_into_preallocated(dv: DataVector, kind: Any) -> None:
    r = dv.layout.region("dn0_to_cn")
    out = kind(r.size)
    dv.read_region("dn0_to_cn", out)
    assert bytes(out[in_region(dv, "dn0_to_cn", "cmd")]) == struct.pack("<H", 9)
    assert bytes(out) == bytes(dv.buf[r.offset : r.offset + r.size])


@pytest.mark.parametrize("kind", [bytes, bytearray, memoryview])
def test_write_region_from_bytes(dv: DataVector, kind: Any) -> None:
    r = dv.layout.region("dn0_to_cn")
    data = bytearray(b"\x00" * r.size)
    data[in_region(dv, "dn0_to_cn", "cmd")] = struct.pack("<H", 0xBEEF)
    data[in_region(dv, "dn0_to_cn", "dn0_loop")] = struct.pack("<Q", 77)
    dv.write_region("dn0_to_cn", kind(bytes(data)))
    assert (dv.get("cmd"), dv.get("dn0_loop")) == (0xBEEF, 77)
    assert dv.get("meas") == 2.5  # other regions untouched
    assert dv.get("v_u8") == 7


@pytest.mark.parametrize("delta", [-1, 1])
def test_region_size_mismatch_refused(dv: DataVector, delta: int) -> None:
    r = dv.layout.region("dn0_to_cn")
    before = bytes(dv.buf)
    out = bytearray(b"\xaa" * (r.size + delta))
    with pytest.raises(DataVectorError, match=f"region dn0_to_cn is {r.size}"):
        dv.read_region("dn0_to_cn", out)
    assert out == bytearray(b"\xaa" * (r.size + delta))
    with pytest.raises(DataVectorError, match=f"region dn0_to_cn is {r.size}"):
        dv.write_region("dn0_to_cn", b"\x55" * (r.size + delta))
    assert bytes(dv.buf) == before


def test_region_view_zero_copy(dv: DataVector) -> None:
    view = dv.region_view("cn_to_dn0")
    r = dv.layout.region("cn_to_dn0")
    assert len(view) == r.size and not view.readonly
    where = in_region(dv, "cn_to_dn0", "meas")
    view[where] = struct.pack("<d", 1.25)
    assert dv.get("meas") == 1.25
    dv.set("meas", -3.0)
    assert bytes(view[where]) == struct.pack("<d", -3.0)


def test_whole_vector_copy(dv: DataVector, layout: Layout) -> None:
    dv.set("v_u32", 0xDEADBEEF)
    out = bytearray(dv.size)
    dv.read_all(out)
    assert bytes(out) == bytes(dv.view()) == bytes(dv.buf[: layout.size])
    other = DataVector(layout)
    assert other.get("v_u32") == 0
    other.write_all(bytes(out))
    assert other.values() == dv.values()
    for bad in (dv.size - 1, dv.size + 1, 0):
        before = bytes(other.buf)
        with pytest.raises(DataVectorError):
            dv.read_all(bytearray(bad))
        with pytest.raises(DataVectorError):
            other.write_all(b"\x00" * bad)
        assert bytes(other.buf) == before


def test_reset_restores_initial(dv: DataVector) -> None:
    initial = dv.values()
    dv.set("v_u8", 1)
    dv.set("a_f32", [0.0, 0.0, 0.0])
    dv.set("mode", "SAFE")
    dv.reset()
    assert dv.values() == initial


# -- layout ---------------------------------------------------------------------


def test_layout_contiguous(layout: Layout) -> None:
    offset = 0
    for r in layout.regions.values():
        assert r.offset == offset
        for e in r.elements:
            assert (e.offset, e.region) == (offset, r.name)
            assert e.size == e.scalar.size * max(e.count, 1)
            offset += e.size
        assert r.size == offset - r.offset == sum(e.size for e in r.elements)
    assert layout.size == offset
    assert layout.dtype.itemsize == layout.size


def test_layout_no_padding(layout: Layout) -> None:
    # u8 then u16 then u32: packed, no alignment padding.
    offs = [layout.element(n).offset for n in ("v_u8", "v_u16", "v_u32", "v_u64")]
    assert [b - a for a, b in itertools.pairwise(offs)] == [1, 2, 4]
    assert layout.element("a_f32").size == 12


def test_node_layout_keeps_cn_index() -> None:
    m = decode_mission(MISSION)
    cn = Layout.for_node(m, "cn")
    dn = Layout.for_node(m, "dn0")
    assert list(dn.regions) == ["cn_to_dn0", "dn0_to_cn"]
    assert dn.regions["cn_to_dn0"].offset == 0
    for name, spec in dn.elements.items():
        assert spec.index == cn.elements[name].index
        assert dn.regions[spec.region].layout_id == cn.regions[spec.region].layout_id
    assert [s.index for s in cn.elements.values()] == list(range(len(cn.elements)))


def small(
    region: str = "r", elements: list[ElementConfig] | None = None, extra: bool = True
) -> Layout:
    E = ElementConfig
    els = elements or [E("a", "u8", 0), E("b", "f32[3]", [0.0] * 3), E("c", "enum", 0, ["A", "B"])]
    regions = [(region, els)] + ([("s", [E("d", "bool", False)])] if extra else [])
    return Layout(regions, [e.name for _, es in regions for e in es])


def test_layout_id_pinned() -> None:
    """A change of the descriptor format (codecs/FORMAT.md) changes these values:
    that is a wire-format change and must be deliberate."""
    L = small()
    descriptor = b"zplatform-region-v1;r;a:u8;b:f32[3];c:enum(u8:A,B)"
    assert L.regions["r"].layout_id == zlib.crc32(descriptor) == 0x409E051D
    assert L.regions["s"].layout_id == zlib.crc32(b"zplatform-region-v1;s;d:bool")
    vector = b"\n".join([b"zplatform-vector-v1", descriptor, b"zplatform-region-v1;s;d:bool"])
    assert L.layout_id == zlib.crc32(vector) == 0xA4E8E770
    assert (LAYOUT_MAGIC, VECTOR_MAGIC) == ("zplatform-region-v1", "zplatform-vector-v1")
    assert [e.type_text for e in L.regions["r"].elements] == ["u8", "f32[3]", "enum(u8:A,B)"]
    assert layout_id_of("r", L.regions["r"].elements) == 0x409E051D


def test_layout_id_stable_across_builds() -> None:
    a, b = small(), small()
    assert a.regions["r"].layout_id == b.regions["r"].layout_id
    m1, m2 = decode_mission(MISSION), decode_mission(MISSION)
    assert Layout.for_node(m1, "cn").layout_id == Layout.for_node(m2, "cn").layout_id


def _rid(elements: list[ElementConfig], region: str = "r") -> int:
    return small(region, elements, extra=False).regions[region].layout_id


def test_layout_id_changes_with_any_difference() -> None:
    E = ElementConfig
    base = [E("a", "u8", 0), E("b", "f32", 0.0), E("c", "enum", 0, ["A", "B"])]
    variants = {
        "base": base,
        "name": [E("x", "u8", 0), *base[1:]],
        "type": [E("a", "i8", 0), *base[1:]],
        "array": [base[0], E("b", "f32[1]", [0.0]), base[2]],
        "order": [base[1], base[0], base[2]],
        "enum names": [*base[:2], E("c", "enum", 0, ["A", "C"])],
        "enum order": [*base[:2], E("c", "enum", 0, ["B", "A"])],
        "extra": [*base, E("d", "bool", False)],
        "fewer": base[:2],
    }
    ids = {k: _rid(v) for k, v in variants.items()}
    ids["region name"] = _rid(base, "q")
    assert len(set(ids.values())) == len(ids), ids
    # Initial values are not part of the layout.
    assert _rid([E("a", "u8", 5), *base[1:]]) == ids["base"]


def test_vector_layout_id_changes_with_region_set() -> None:
    assert small().layout_id != small(extra=False).layout_id


# -- NaN payloads ----------------------------------------------------------------

F64_NANS = [0x7FF8000000000000, 0x7FF0000000000001, 0xFFF8000000012345, 0x7FFFFFFFFFFFFFFF]
F32_NANS = [0x7FC00000, 0x7FC12345, 0xFFC00001, 0x7FFFFFFF]


@pytest.mark.parametrize("bits", F64_NANS, ids=hex)
def test_f64_nan_payload_bit_exact(dv: DataVector, bits: int) -> None:
    r = dv.layout.region("cn_to_dn0")
    where = in_region(dv, "cn_to_dn0", "meas")
    data = bytearray(r.size)
    data[where] = struct.pack("<Q", bits)
    dv.write_region("cn_to_dn0", data)  # raw bytes in
    value = dv.get("meas")
    assert math.isnan(value)
    dv.set("meas", 0.0)
    dv.set("meas", value)  # back through a Python float
    assert raw(dv, "meas") == struct.pack("<Q", bits)
    dv.set("meas", 0.0)
    dv.handle("meas").set(value)
    out = bytearray(r.size)
    dv.read_region("cn_to_dn0", out)  # raw bytes out
    assert out[where] == struct.pack("<Q", bits)


@pytest.mark.parametrize("bits", F32_NANS, ids=hex)
def test_f32_nan_payload_bit_exact(dv: DataVector, bits: int) -> None:
    # Quiet NaNs keep their payload through a Python float. (A *signalling*
    # f32 NaN is quieted by the f32->double conversion of CPython < 3.14; the
    # frame and region copies never convert, see the golden vectors.)
    off = dv.layout.element("v_f32").offset
    dv.buf[off : off + 4] = struct.pack("<I", bits)
    value = dv.get("v_f32")
    assert math.isnan(value)
    dv.set("v_f32", 1.0)
    dv.set("v_f32", value)
    assert raw(dv, "v_f32") == struct.pack("<I", bits)


def test_nan_payloads_in_arrays_bit_exact(dv: DataVector) -> None:
    # Array views are numpy: same-dtype copies never convert, so even
    # signalling NaNs pass unchanged.
    bits32 = [0x7F800001, 0xFFC12345, 0x7FC00000]
    src = np.array(bits32, dtype="<u4").view("<f4")
    dv.handle("a_f32").get()[:] = src
    assert raw(dv, "a_f32") == struct.pack("<3I", *bits32)
    bits64 = [0x7FF0000000000001, 0xFFF8000000000002]
    dv.handle("a_f64").get()[:] = np.array(bits64, dtype="<u8").view("<f8")
    assert raw(dv, "a_f64") == struct.pack("<2Q", *bits64)


def test_bump_adds_and_saturates_at_the_type_maximum(dv: DataVector) -> None:
    h = dv.handle("v_u32")
    assert h.bump() == 1 and h.bump(4) == 5 and dv.get("v_u32") == 5
    h.set(2**32 - 2)
    assert h.bump() == 2**32 - 1
    assert h.bump() == 2**32 - 1  # a u32 counter sticks, it never wraps to 0
    assert h.bump(10) == 2**32 - 1
    u8 = dv.handle("v_u8")
    u8.set(250)
    assert u8.bump(100) == 255
    assert dv.handle("mode").bump() == 3  # enums are integers too


@pytest.mark.parametrize("name", ["v_f64", "v_bool", "a_u8"])
def test_bump_refuses_what_is_no_integer_counter(dv: DataVector, name: str) -> None:
    before = bytes(dv.buf)
    with pytest.raises(DataVectorError, match="scalar integer"):
        dv.handle(name).bump()
    assert bytes(dv.buf) == before
