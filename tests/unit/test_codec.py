"""Tests of zplatform.core.codec: the region frame, its fixed-width form, and every rejection."""

from __future__ import annotations

import random
import struct
from typing import Any

import msgspec
import pytest

from zplatform import (
    CodecError,
    DataVector,
    DataVectorError,
    FrameDecoder,
    FrameEncoder,
    FrameFormatError,
    FrameSizeError,
    Layout,
    LayoutMismatchError,
    RegionCodec,
    decode_frame,
    decode_mission,
    encode_frame,
)
from zplatform.core.codec import frame_overhead

MISSION = """
mission: codectest
nodes: {cn: {}, dn0: {}}
health: null  # the frame tests pin every element; health is its own test
regions:
  cn:
    - {name: c_u32, type: u32, initial: 7}
  cn_to_dn0:
    - {name: setpoint, type: f64, initial: 1.5}
    - {name: gains, type: "f32[3]", initial: [0.1, 0.2, 0.3]}
    - {name: valve, enum: [CLOSED, OPEN], initial: OPEN}
  dn0_to_cn:
    - {name: temp, type: f32}
    - {name: raw, type: "u8[300]"}
"""

HDR = 24  # fixarray + u32 + u64 + i64, fixed width


@pytest.fixture(scope="module")
def mission() -> Any:
    return decode_mission(MISSION)


@pytest.fixture
def cn(mission: Any) -> DataVector:
    return DataVector(Layout.for_node(mission, "cn"))


@pytest.fixture
def dn(mission: Any) -> DataVector:
    return DataVector(Layout.for_node(mission, "dn0"))


def mp(*items: Any) -> bytes:
    """msgspec's own (minimal) MessagePack encoding of ``items`` as an array."""
    return msgspec.msgpack.encode(list(items))


# -- encoding ----------------------------------------------------------------------


def test_round_trip() -> None:
    data = bytes(range(200))
    f = decode_frame(encode_frame(0xDEADBEEF, 12345, -987654321, data))
    assert (f.layout_id, f.seq, f.t_ns, bytes(f.data)) == (0xDEADBEEF, 12345, -987654321, data)
    assert isinstance(f.data, memoryview)


def test_decoded_data_is_a_view_of_the_input() -> None:
    buf = bytearray(encode_frame(1, 2, 3, b"abcd"))
    f = decode_frame(buf)
    assert f.data.obj is buf
    buf[-1] = ord("z")
    assert bytes(f.data) == b"abcz"


HEADERS = [
    (0, 0, 0),
    (1, 1, 1),
    (127, 127, -1),
    (128, 128, -32),
    (0xFFFF_FFFF, 2**64 - 1, 2**63 - 1),
    (0x1234_5678, 2**32, -(2**63)),
]


@pytest.mark.parametrize("n", [0, 5, 255, 256, 65535, 65536])
def test_fixed_width_header(n: int) -> None:
    enc = FrameEncoder()
    data = bytes(i % 251 for i in range(n))
    bin_hdr = 2 if n < 256 else 3 if n < 65536 else 5
    lengths = set()
    for layout_id, seq, t_ns in HEADERS:
        frame = bytes(enc.encode(layout_id, seq, t_ns, data))
        lengths.add(len(frame))
        assert [frame[i] for i in (0, 1, 6, 15)] == [0x94, 0xCE, 0xCF, 0xD3]
        assert frame[24] == {2: 0xC4, 3: 0xC5, 5: 0xC6}[bin_hdr]
        assert struct.unpack_from(">I", frame, 2)[0] == layout_id
        assert struct.unpack_from(">Q", frame, 7)[0] == seq
        assert struct.unpack_from(">q", frame, 16)[0] == t_ns
        assert int.from_bytes(frame[25 : 24 + bin_hdr], "big") == n
        assert frame[HDR + bin_hdr :] == data
        # plain MessagePack: any decoder reads it
        assert msgspec.msgpack.decode(frame) == [layout_id, seq, t_ns, data]
    assert lengths == {HDR + bin_hdr + n}
    assert frame_overhead(n) == HDR + bin_hdr


@pytest.mark.parametrize(
    ("n", "header"),
    [
        (0, b"\xc4\x00"),
        (255, b"\xc4\xff"),
        (256, b"\xc5\x01\x00"),
        (65535, b"\xc5\xff\xff"),
        (65536, b"\xc6\x00\x01\x00\x00"),
        (1 << 20, b"\xc6\x00\x10\x00\x00"),
    ],
)
def test_bin_boundaries(n: int, header: bytes) -> None:
    data = b"\x5a" * n
    frame = encode_frame(1, 2, 3, data)
    assert frame[HDR : HDR + len(header)] == header
    assert len(frame) == HDR + len(header) + n
    f = decode_frame(frame)
    assert len(f.data) == n and bytes(f.data) == data
    assert FrameDecoder(1, n).decode(frame).seq == 2


def test_worked_example_bytes() -> None:
    # The example of codecs/FORMAT.md.
    frame = encode_frame(0x409E051D, 1, 1_700_000_000_000_000_000, b"\x01\x00\x00\x80\x3f")
    assert frame.hex() == ("94ce409e051dcf0000000000000001d317979cfe362a0000c405010000803f")


def test_encoder_reuses_its_buffer() -> None:
    enc = FrameEncoder(4)
    a = enc.encode(1, 1, 1, b"abcd")
    b = enc.encode(1, 2, 1, b"wxyz")
    assert a is b
    assert decode_frame(b).seq == 2 and bytes(decode_frame(b).data) == b"wxyz"
    c = enc.encode(1, 3, 1, b"longer data")  # another size: regrown
    assert bytes(decode_frame(c).data) == b"longer data"
    d = enc.encode(1, 4, 1, b"")
    assert bytes(decode_frame(d).data) == b""


@pytest.mark.parametrize(
    ("layout_id", "seq", "t_ns"),
    [(-1, 0, 0), (2**32, 0, 0), (0, -1, 0), (0, 2**64, 0), (0, 0, 2**63), (0, 0, -(2**63) - 1)],
)
def test_encoder_refuses_out_of_range_header(layout_id: int, seq: int, t_ns: int) -> None:
    with pytest.raises(FrameFormatError, match="header out of range"):
        encode_frame(layout_id, seq, t_ns, b"x")


@pytest.mark.parametrize("bad", [1.5, "1", None])
def test_encoder_refuses_non_int_header(bad: Any) -> None:
    with pytest.raises(FrameFormatError):
        encode_frame(1, bad, 0, b"x")


# -- decoding what other encoders write ---------------------------------------------------


@pytest.mark.parametrize("n", [0, 3, 255, 256, 65536])
@pytest.mark.parametrize(("layout_id", "seq", "t_ns"), HEADERS)
def test_decoder_accepts_minimal_msgspec_frame(layout_id: int, seq: int, t_ns: int, n: int) -> None:
    data = bytes(i % 7 for i in range(n))
    wire = msgspec.msgpack.encode((layout_id, seq, t_ns, data))
    f = decode_frame(wire)
    assert (f.layout_id, f.seq, f.t_ns, bytes(f.data)) == (layout_id, seq, t_ns, data)
    if seq < 128 and layout_id < 128 and -32 <= t_ns < 128 and n < 256:
        assert len(wire) == 4 + 2 + n  # really the minimal form


def test_decoder_accepts_any_valid_encoding() -> None:
    # array16 holding 4 items, u8/i8 int markers, bin32 for 3 bytes.
    wire = (
        b"\xdc\x00\x04" + b"\xcc\xc8" + b"\xcd\x01\x00" + b"\xd0\x80" + b"\xc6\x00\x00\x00\x03abc"
    )
    f = decode_frame(wire)
    assert (f.layout_id, f.seq, f.t_ns, bytes(f.data)) == (200, 256, -128, b"abc")
    # positive t_ns written with an unsigned marker is still an i64
    f = decode_frame(b"\x94\x01\x02\xcf" + (2**63 - 1).to_bytes(8, "big") + b"\xc4\x00")
    assert f.t_ns == 2**63 - 1


# -- rejections ------------------------------------------------------------------


def good_frame(n: int = 300) -> bytes:
    return encode_frame(0xCAFE, 9, 10, bytes(range(256)) * (n // 256) + bytes(n % 256))


@pytest.mark.parametrize("n", [0, 5, 300])
def test_truncated_at_every_length(n: int) -> None:
    frame = good_frame(n)
    for cut in range(len(frame)):
        with pytest.raises(FrameFormatError):
            decode_frame(frame[:cut])


def test_empty_input() -> None:
    with pytest.raises(FrameFormatError, match="truncated"):
        decode_frame(b"")


@pytest.mark.parametrize("extra", [b"\x00", b"\xc0", b"garbage", good_frame(3)])
def test_trailing_garbage(extra: bytes) -> None:
    with pytest.raises(FrameFormatError, match="trailing"):
        decode_frame(good_frame() + extra)


@pytest.mark.parametrize("items", [(), (1,), (1, 2, 3), (1, 2, 3, b"", 5), (1, 2, 3, b"", b"")])
def test_wrong_array_length(items: tuple[Any, ...]) -> None:
    with pytest.raises(FrameFormatError, match="length"):
        decode_frame(mp(*items))


BAD_ITEMS = {
    "seq str": (1, "2", 3, b""),
    "seq negative": (1, -2, 3, b""),
    "seq float": (1, 2.0, 3, b""),
    "seq nil": (1, None, 3, b""),
    "t_ns beyond i64": (1, 2, 2**63, b""),
    "t_ns float": (1, 2, 3.5, b""),
    "t_ns bool": (1, 2, True, b""),
    "layout_id > u32": (2**32, 2, 3, b""),
    "layout_id negative": (-1, 2, 3, b""),
    "layout_id bool": (True, 2, 3, b""),
    "layout_id str": ("1", 2, 3, b""),
    "data str": (1, 2, 3, "abc"),
    "data int": (1, 2, 3, 5),
    "data array": (1, 2, 3, [1, 2]),
    "data nil": (1, 2, 3, None),
}


@pytest.mark.parametrize("items", list(BAD_ITEMS.values()), ids=list(BAD_ITEMS))
def test_wrong_item_types(items: tuple[Any, ...]) -> None:
    with pytest.raises(FrameFormatError, match=r"at `\$\[[0-3]\]`"):
        decode_frame(mp(*items))


@pytest.mark.parametrize(
    "wire",
    [
        msgspec.msgpack.encode({"layout_id": 1, "seq": 2, "t_ns": 3, "data": b""}),
        msgspec.msgpack.encode(b"bytes"),
        msgspec.msgpack.encode(7),
        msgspec.msgpack.encode(None),
        b"\xc1",  # the never-used MessagePack marker
        b"\x94\xce\x00",
    ],
)
def test_not_a_frame(wire: bytes) -> None:
    with pytest.raises(FrameFormatError):
        decode_frame(wire)


@pytest.mark.parametrize("obj", ["abc", None, 12, [1, 2, 3, b""]])
def test_not_a_buffer(obj: Any) -> None:
    with pytest.raises(FrameFormatError):
        decode_frame(obj)


def test_random_bytes_only_raise_codec_errors() -> None:
    rng = random.Random(1234)
    decoded = 0
    for i in range(3000):
        n = rng.randrange(0, 64)
        blob = bytes(rng.randrange(256) for _ in range(n))
        if i % 3 == 0:  # start like a frame, to get past the first byte
            blob = b"\x94" + blob
        try:
            decode_frame(blob)
            decoded += 1
        except CodecError:
            pass
    assert decoded < 3000


def test_layout_mismatch() -> None:
    dec = FrameDecoder(0xCAFE, 300, "dn0_to_cn")
    with pytest.raises(LayoutMismatchError, match=r"dn0_to_cn: frame layout_id 0x0000cafd"):
        dec.decode(encode_frame(0xCAFD, 1, 1, bytes(300)))


@pytest.mark.parametrize("n", [0, 299, 301, 65536])
def test_wrong_size(n: int) -> None:
    dec = FrameDecoder(0xCAFE, 300, "dn0_to_cn")
    with pytest.raises(FrameSizeError, match=f"carries {n} data bytes, region is 300"):
        dec.decode(encode_frame(0xCAFE, 1, 1, bytes(n)))


def test_layout_checked_before_size() -> None:
    with pytest.raises(LayoutMismatchError):
        FrameDecoder(1, 10).decode(encode_frame(2, 1, 1, bytes(3)))


def test_error_classes() -> None:
    for cls in (FrameFormatError, LayoutMismatchError, FrameSizeError):
        assert issubclass(cls, CodecError)


# -- RegionCodec: regions and the whole vector -------------------------------------------------


def test_region_codec_round_trip(cn: DataVector, dn: DataVector) -> None:
    cn.set("setpoint", -42.25)
    cn.set("gains", [1.0, -2.0, 0.5])
    cn.set("valve", "CLOSED")
    tx = RegionCodec(cn, "cn_to_dn0")
    rx = RegionCodec(dn, "cn_to_dn0")
    assert tx.layout_id == rx.layout_id == cn.layout.region("cn_to_dn0").layout_id
    frame = tx.encode(77, 123_456)
    region = cn.layout.region("cn_to_dn0")
    assert len(frame) == frame_overhead(region.size) + region.size == 26 + 22  # dn0_final + 21 B
    f = rx.apply(frame)
    assert (f.layout_id, f.seq, f.t_ns) == (tx.layout_id, 77, 123_456)
    assert dn.get("setpoint") == -42.25
    assert list(dn.get("gains")) == [1.0, -2.0, 0.5]
    assert dn.get_name("valve") == "CLOSED"
    # the other region of dn is untouched
    assert bytes(dn.region_view("dn0_to_cn")) == bytes(
        DataVector(dn.layout).region_view("dn0_to_cn")
    )


def test_region_codec_encode_reuses_buffer(cn: DataVector) -> None:
    rc = RegionCodec(cn, "cn_to_dn0")
    a = rc.encode(1, 1)
    cn.set("setpoint", 9.0)
    b = rc.encode(2, 2)
    assert a is b
    f = decode_frame(b)
    setpoint = cn.layout.element("setpoint").offset - cn.layout.region("cn_to_dn0").offset
    assert f.seq == 2 and struct.unpack_from("<d", f.data, setpoint)[0] == 9.0


def test_region_codec_check_does_not_apply(cn: DataVector, dn: DataVector) -> None:
    cn.set("setpoint", 3.0)
    frame = bytes(RegionCodec(cn, "cn_to_dn0").encode(5, 6))
    before = bytes(dn.buf)
    f = RegionCodec(dn, "cn_to_dn0").check(frame)
    assert f.seq == 5
    assert bytes(dn.buf) == before


def bad_frames(cn: DataVector, dn: DataVector) -> dict[str, bytes]:
    """One frame per rejection, for region dn0_to_cn."""
    good = bytes(RegionCodec(dn, "dn0_to_cn").encode(1, 2))
    lid = dn.layout.region("dn0_to_cn").layout_id
    size = dn.layout.region("dn0_to_cn").size
    return {
        "other region": bytes(RegionCodec(cn, "cn_to_dn0").encode(1, 2)),
        "layout_id": encode_frame(lid ^ 1, 1, 2, bytes(size)),
        "short": encode_frame(lid, 1, 2, bytes(size - 1)),
        "long": encode_frame(lid, 1, 2, bytes(size + 1)),
        "truncated": good[:-1],
        "trailing": good + b"\x00",
        "five items": mp(lid, 1, 2, bytes(size), 0),
        "seq str": mp(lid, "1", 2, bytes(size)),
        "empty": b"",
    }


EXPECTED = {
    "other region": LayoutMismatchError,
    "layout_id": LayoutMismatchError,
    "short": FrameSizeError,
    "long": FrameSizeError,
    "truncated": FrameFormatError,
    "trailing": FrameFormatError,
    "five items": FrameFormatError,
    "seq str": FrameFormatError,
    "empty": FrameFormatError,
}


@pytest.mark.parametrize("case", list(EXPECTED))
def test_region_codec_apply_leaves_region_untouched(
    cn: DataVector, dn: DataVector, case: str
) -> None:
    frame = bad_frames(cn, dn)[case]
    target = DataVector(dn.layout)
    target.set("temp", 36.5)
    target.set("raw", 0xAB)
    before = bytes(target.buf)
    with pytest.raises(EXPECTED[case]):
        RegionCodec(target, "dn0_to_cn").apply(frame)
    assert bytes(target.buf) == before


def test_region_codec_unknown_region(cn: DataVector) -> None:
    with pytest.raises(DataVectorError, match="no region named"):
        RegionCodec(cn, "dn7_to_cn")


def test_vector_codec_round_trip(mission: Any) -> None:
    layout = Layout.for_node(mission, "cn")
    src, dst = DataVector(layout), DataVector(layout)
    src.set("c_u32", 0xFFFF_FFFF)
    src.set("temp", -1.5)
    src.set("cn_loop", 2**64 - 1)
    vc = RegionCodec(src)
    assert vc.layout_id == layout.layout_id
    frame = vc.encode(3, 4)
    assert len(frame) == frame_overhead(layout.size) + layout.size
    f = RegionCodec(dst).apply(frame)
    assert (f.layout_id, f.seq, f.t_ns) == (layout.layout_id, 3, 4)
    assert dst.values() == src.values()
    assert bytes(dst.view()) == bytes(src.view())


def test_vector_codec_refuses_region_frames(cn: DataVector) -> None:
    region_frame = bytes(RegionCodec(cn, "cn").encode(1, 1))
    dst = DataVector(cn.layout)
    dst.set("c_u32", 5)
    before = bytes(dst.buf)
    with pytest.raises(LayoutMismatchError, match="telemetry"):
        RegionCodec(dst).apply(region_frame)
    lid = cn.layout.layout_id
    with pytest.raises(FrameSizeError, match="telemetry"):
        RegionCodec(dst).apply(encode_frame(lid, 1, 1, bytes(cn.size - 1)))
    assert bytes(dst.buf) == before


def test_node_and_cn_layouts_agree(cn: DataVector, dn: DataVector) -> None:
    # Each node builds its own layout; region ids must match across nodes.
    for region in ("cn_to_dn0", "dn0_to_cn"):
        assert cn.layout.region(region).layout_id == dn.layout.region(region).layout_id
        assert cn.layout.region(region).size == dn.layout.region(region).size
    dn.set("temp", 21.0)
    RegionCodec(cn, "dn0_to_cn").apply(RegionCodec(dn, "dn0_to_cn").encode(1, 1))
    assert cn.get("temp") == 21.0


@pytest.mark.parametrize("n", [0, 1, 255, 256, 65535, 65536, 100_003])
@pytest.mark.parametrize("tail", [0, 24])
def test_encode_into_writes_the_bytes_encode_writes(n: int, tail: int) -> None:
    """A frame encoded into a caller's view (a loaned shared-memory sample)
    is the encoder's own frame byte for byte, the tail room untouched."""
    data = bytes(random.Random(n).randrange(256) for _ in range(min(n, 64))) * (n // 64 + 1)
    data = data[:n]
    enc = FrameEncoder(tail=tail)
    want = bytes(enc.encode(7, 2**40 + 3, -5, data))
    out = bytearray(b"\xaa" * enc.frame_len(n))
    assert len(out) == len(want)
    view = enc.encode_into(memoryview(out), 7, 2**40 + 3, -5, data)
    assert view.obj is out
    assert bytes(out[: len(out) - tail]) == want[: len(want) - tail]
    assert bytes(out[len(out) - tail :]) == b"\xaa" * tail


def test_encode_into_refuses_a_view_of_another_length_and_bad_headers() -> None:

    enc = FrameEncoder(tail=24)
    n = enc.frame_len(10)
    for wrong in (n - 1, n + 1):
        with pytest.raises(ValueError, match="buffer"):
            enc.encode_into(memoryview(bytearray(wrong)), 1, 1, 1, bytes(10))
    with pytest.raises(FrameFormatError):
        enc.encode_into(memoryview(bytearray(n)), -1, 1, 1, bytes(10))
