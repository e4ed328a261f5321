"""Property tests of the Data Vector and the region frame, on random missions and values."""

from __future__ import annotations

import struct
from functools import lru_cache
from typing import Any

import msgspec
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.property.strategies import frame_headers, mutated, region_bytes, vector_missions
from zplatform import (
    CodecError,
    DataVector,
    Layout,
    RegionCodec,
    decode_frame,
    decode_mission,
    encode_frame,
)
from zplatform.core.datavector import ElementSpec

# Random missions cost a config decode each: 60 examples keep the file near 8 s.
_SETTINGS = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@lru_cache(maxsize=256)
def cn_layout(text: str) -> Layout:
    return Layout.for_node(decode_mission(text), "cn")


def element_raw(dv: DataVector, spec: ElementSpec) -> bytes:
    return bytes(dv.buf[spec.offset : spec.offset + spec.size])


def set_from_bytes(dv: DataVector, spec: ElementSpec, raw: bytes) -> None:
    """Write ``raw`` into ``spec`` the way a node does: the checked ``set`` for
    ints, bools and enums (enums by name), the raw bytes for floats (a Python
    float may not carry an f32 NaN's exact bits)."""
    st_ = spec.scalar
    if st_.kind == "float":
        dv.buf[spec.offset : spec.offset + spec.size] = raw
        return
    n = max(spec.count, 1)
    items = list(struct.unpack(f"<{n}{st_.struct}", raw))
    if spec.enum is not None:
        dv.set(spec.name, spec.enum[items[0]])
    else:
        dv.set(spec.name, items if spec.count else items[0])


@_SETTINGS
@given(vector_missions(), frame_headers, st.data())
def test_region_round_trip_bit_exact(text: str, header: tuple[int, int, int], data: Any) -> None:
    """Any valid values of any region, encoded and decoded, come back bit for bit."""
    layout = cn_layout(text)
    tx, rx = DataVector(layout), DataVector(layout)
    _, seq, t_ns = header
    for region in layout.regions.values():
        raw = data.draw(region_bytes(region), label=region.name)
        pos = 0
        for spec in region.elements:
            set_from_bytes(tx, spec, raw[pos : pos + spec.size])
            pos += spec.size
        assert bytes(tx.region_view(region.name)) == raw  # set encodes as specified
        frame = RegionCodec(tx, region.name).encode(seq, t_ns)
        f = RegionCodec(rx, region.name).apply(frame)
        assert (f.layout_id, f.seq, f.t_ns) == (region.layout_id, seq, t_ns)
        assert bytes(rx.region_view(region.name)) == raw
        for spec in region.elements:
            assert element_raw(rx, spec) == element_raw(tx, spec)
            if spec.scalar.kind != "float":
                got, want = rx.get(spec.name), tx.get(spec.name)
                assert (list(got) == list(want)) if spec.count else (got == want)
    assert bytes(rx.view()) == bytes(tx.view())


@_SETTINGS
@given(frame_headers, st.binary(max_size=300))
def test_frame_round_trip(header: tuple[int, int, int], data: bytes) -> None:
    """encode_frame then decode_frame gives back every header field and the data."""
    frame = encode_frame(*header, data)
    f = decode_frame(frame)
    assert (f.layout_id, f.seq, f.t_ns, bytes(f.data)) == (*header, data)
    assert msgspec.msgpack.decode(frame) == [*header, data]  # plain MessagePack
    # and the minimal encoding another peer might send decodes the same
    g = decode_frame(msgspec.msgpack.encode((*header, data)))
    assert (g.layout_id, g.seq, g.t_ns, bytes(g.data)) == (*header, data)


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=120))
def test_any_bytes_decode_or_codec_error(blob: bytes) -> None:
    """Any byte string fed to decode_frame either decodes or raises CodecError."""
    try:
        f = decode_frame(blob)
    except CodecError:
        return
    assert 0 <= f.layout_id < 2**32 and 0 <= f.seq < 2**64 and -(2**63) <= f.t_ns < 2**63


_MISSION = """
mission: prop
nodes: {cn: {}, dn0: {}}
regions:
  cn_to_dn0:
    - {name: a, type: u32}
    - {name: b, type: "f32[3]"}
    - {name: c, enum: [P, Q]}
"""


@settings(max_examples=400, deadline=None)
@given(st.data())
def test_any_bytes_apply_or_codec_error_region_untouched(data: Any) -> None:
    """RegionCodec.apply on any bytes applies a valid frame or raises CodecError, region intact."""
    layout = cn_layout(_MISSION)
    dv = DataVector(layout)
    region = layout.region("cn_to_dn0")
    valid = encode_frame(region.layout_id, 5, 6, data.draw(region_bytes(region)))
    blob = data.draw(st.binary(max_size=80) | mutated(valid) | st.just(valid))
    before = bytes(dv.buf)
    try:
        f = RegionCodec(dv, "cn_to_dn0").apply(blob)
    except CodecError:
        assert bytes(dv.buf) == before
        return
    assert f.layout_id == region.layout_id and len(f.data) == region.size
    assert bytes(dv.region_view("cn_to_dn0")) == bytes(f.data)
    outside = bytes(dv.buf[: region.offset]) + bytes(dv.buf[region.offset + region.size :])
    assert outside == before[: region.offset] + before[region.offset + region.size :]


@_SETTINGS
@given(vector_missions(), st.data())
def test_region_copy_out_then_in_is_identity(text: str, data: Any) -> None:
    """Copying every region out of a vector and into a fresh one reproduces it."""
    layout = cn_layout(text)
    src = DataVector(layout)
    src.write_all(b"".join(data.draw(region_bytes(r)) for r in layout.regions.values()))
    dst = DataVector(layout)
    for r in layout.regions.values():
        out = bytearray(r.size)
        src.read_region(r.name, out)
        dst.write_region(r.name, out)
    assert bytes(dst.view()) == bytes(src.view())
    whole = bytearray(layout.size)
    dst.read_all(whole)
    assert bytes(whole) == bytes(src.view())
    # and through the telemetry frame
    tm = DataVector(layout)
    RegionCodec(tm).apply(RegionCodec(src).encode(1, 2))
    assert bytes(tm.view()) == bytes(src.view())


@_SETTINGS
@given(vector_missions())
def test_layouts_contiguous_and_ids_stable(text: str) -> None:
    """Every random layout is packed without gaps, and rebuilding it gives the same ids."""
    layout = cn_layout(text)
    again = Layout.for_node(decode_mission(text), "cn")
    offset = 0
    for r in layout.regions.values():
        assert r.offset == offset
        for e in r.elements:
            assert e.offset == offset
            offset += e.size
        assert again.regions[r.name].layout_id == r.layout_id
    assert offset == layout.size
    assert again.layout_id == layout.layout_id
    ids = [r.layout_id for r in layout.regions.values()]
    assert len(set(ids)) == len(ids)  # different regions, different ids
