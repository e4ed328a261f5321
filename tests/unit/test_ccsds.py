"""CCSDS downlink: packet layout, rate control, and a bit-exact round trip."""

from __future__ import annotations

import io
from pathlib import Path

import fastcrc
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from spacepackets.ccsds.spacepacket import SequenceFlags, SpacePacketHeader

from zplatform import load_mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import ConfigError
from zplatform.telemetry.ccsds import (
    APID_BASE,
    CcsdsDecoder,
    CcsdsEncoder,
    CcsdsError,
    crc16,
    packet_plan,
    split_stream,
)
from zplatform.telemetry.logs import CsvLogger

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
LED = load_mission(CONFIGS / "led_test.yaml")


def _snapshots(n: int, seed_bytes: list[bytes]) -> list[bytes]:
    size = Layout.for_node(LED, "cn").size
    return [(seed_bytes[i % len(seed_bytes)] * size)[:size] for i in range(n)]


def test_crc_is_spacepackets_crc() -> None:
    """Our CRC is the CRC-16/CCITT-FALSE that spacepackets (fastcrc) computes."""
    for data in (b"", b"123456789", bytes(range(256)) * 3):
        assert crc16(memoryview(bytearray(data))) == fastcrc.crc16.ibm_3740(data)


def test_one_packet_per_nonempty_region_with_stable_apids() -> None:
    plan = packet_plan(LED)
    layout = Layout.for_node(LED, "cn")
    names = LED.region_names()
    nonempty = [r for r in names if layout.region(r).size]
    assert [p.region for p in plan] == nonempty
    for p in plan:
        assert p.apid == APID_BASE + names.index(p.region)
        assert p.seq_flags == SequenceFlags.UNSEGMENTED


def test_header_fields_and_sequence_counts() -> None:
    enc = CcsdsEncoder(LED)
    dv = DataVector(enc.layout)
    for loop in (1, 2):
        pkts = enc.encode(dv, loop, loop * 10_000_000)
        for p, raw in zip(enc.plan, pkts, strict=True):
            h = SpacePacketHeader.unpack(bytes(raw[:6]))
            assert h.apid == p.apid
            assert h.seq_count == loop - 1
            assert h.sec_header_flag
            assert h.packet_len == len(raw)
            assert crc16(raw[:-2]) == int.from_bytes(raw[-2:], "big")


@settings(max_examples=30, deadline=None)
@given(
    blobs=st.lists(st.binary(min_size=1, max_size=64), min_size=1, max_size=6),
    max_data=st.sampled_from([24, 31, 64, 65536]),
)
def test_round_trip_is_bit_exact(blobs: list[bytes], max_data: int) -> None:
    """Packets decoded give the same vector bytes and the same CSV, segmented or not."""
    enc = CcsdsEncoder(LED, max_data=max_data)
    dec = CcsdsDecoder(LED, max_data=max_data)
    src = DataVector(enc.layout)
    direct, via = io.StringIO(), io.StringIO()
    log_direct, log_via = CsvLogger(direct, src.layout), CsvLogger(via, dec.dv.layout)
    for i, snap in enumerate(_snapshots(len(blobs) + 1, blobs)):
        src.write_all(snap)
        t_ns = 1_000_000_000 + i * 10_000_000
        log_direct.write(t_ns, src)
        stream = b"".join(bytes(p) for p in enc.encode(src, i + 1, t_ns))
        done = list(dec.feed_all(split_stream(stream)))
        assert done == [(i + 1, t_ns)]
        assert dec.dv.buf == src.buf
        log_via.write(done[0][1], dec.dv)
    assert via.getvalue() == direct.getvalue()
    assert dec.bad == {} and dec.seq_gaps == 0 and dec.incomplete == 0


def test_segments_large_regions() -> None:
    plan = packet_plan(LED, max_data=24)  # 6 region bytes per packet
    cn = [p for p in plan if p.region == "cn"]
    assert len(cn) > 2
    assert cn[0].seq_flags == SequenceFlags.FIRST_SEGMENT
    assert cn[-1].seq_flags == SequenceFlags.LAST_SEGMENT
    assert all(p.seq_flags == SequenceFlags.CONTINUATION_SEGMENT for p in cn[1:-1])
    assert sum(p.length for p in cn) == Layout.for_node(LED, "cn").region("cn").size


def test_decimation_and_budget_are_counted() -> None:
    enc = CcsdsEncoder(LED, divisor=2)
    dv = DataVector(enc.layout)
    sent = [bool(enc.encode(dv, i, i * 10_000_000)) for i in range(10)]
    assert sent == [True, False] * 5
    assert enc.decimated == 5

    # Budget of 2.5 snapshots per second at 100 snapshots per second:
    # the first burst drains the bucket, then about one in 40 goes.
    enc = CcsdsEncoder(LED, budget_bps=int(enc.snapshot_bytes * 2.5))
    n = sum(bool(enc.encode(dv, i, i * 10_000_000)) for i in range(200))
    assert enc.sent_snapshots == n
    assert enc.dropped_budget == 200 - n
    assert 3 <= n <= 8
    with pytest.raises(ConfigError, match="below one snapshot"):
        CcsdsEncoder(LED, budget_bps=10)


def test_decoder_refuses_and_counts() -> None:
    enc = CcsdsEncoder(LED)
    dec = CcsdsDecoder(LED)
    dv = DataVector(enc.layout)
    pkts = [bytearray(p) for p in enc.encode(dv, 1, 0)]
    bad = bytearray(pkts[0])
    bad[-5] ^= 0xFF
    with pytest.raises(CcsdsError, match="CRC"):
        dec.feed(bad)
    with pytest.raises(CcsdsError, match="bytes"):
        dec.feed(pkts[0][:-1])
    assert dec.bad == {"crc": 1, "length": 1}
    # A lost packet: that snapshot is incomplete, the next one completes.
    for p in pkts[1:]:
        assert dec.feed(p) is None
    done = list(dec.feed_all(bytes(p) for p in enc.encode(dv, 2, 1)))
    assert done == [(2, 1)]
    assert dec.incomplete == 1
    with pytest.raises(CcsdsError, match="truncated"):
        list(split_stream(bytes(pkts[0])[:-3]))


def test_decode_verb_writes_the_same_csv(tmp_path: Path) -> None:
    """`zplatform ccsds --decode` turns a packet file into the telemetry CSV."""
    from zplatform.cli.main import main

    enc = CcsdsEncoder(LED)
    src = DataVector(enc.layout)
    direct = io.StringIO()
    log = CsvLogger(direct, src.layout)
    stream = bytearray()
    for i, snap in enumerate(_snapshots(5, [b"\x01\x02", b"\x00\xff\x10"])):
        src.write_all(snap)
        log.write(i * 10_000_000, src)
        for p in enc.encode(src, i, i * 10_000_000):
            stream += p
    (tmp_path / "down.bin").write_bytes(bytes(stream))
    out = tmp_path / "down.csv"
    cfg = str(CONFIGS / "led_test.yaml")
    assert main(["ccsds", cfg, "--decode", str(tmp_path / "down.bin"), "--out", str(out)]) == 0
    assert out.read_text() == direct.getvalue()
    assert main(["ccsds", cfg, "--decode", str(tmp_path / "none.bin"), "--out", str(out)]) == 2
