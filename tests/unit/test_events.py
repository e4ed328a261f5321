"""Tests of zplatform.events: the bounded log and the wire form."""

from __future__ import annotations

import msgspec
import pytest

from zplatform.errors import CodecError, FrameFormatError
from zplatform.events import Event, EventLog, Severity, decode_event, encode_event


def test_emit_then_drain_in_order_with_sequence_numbers() -> None:
    log = EventLog("cn")
    log.emit(Severity.INFO, "a", "first", 10)
    log.emit(Severity.WARNING, "b", "second", 20)
    assert log.pending == 2
    evs = log.drain()
    assert evs == [
        Event("cn", 0, 10, 1, "a", "first"),
        Event("cn", 1, 20, 2, "b", "second"),
    ]
    assert log.pending == 0 and log.drain() == []
    log.emit(Severity.DEBUG, "c", "third", 30)
    assert log.drain()[0].seq == 2
    assert log.emitted == 3 and log.dropped == 0


def test_full_log_keeps_the_oldest_and_counts_drops() -> None:
    log = EventLog("dn0", capacity=3)
    for i in range(5):
        log.emit(Severity.ERROR, "e", f"n{i}", i)
    assert log.dropped == 2 and log.emitted == 5
    evs = log.drain()
    assert [e.text for e in evs] == ["n0", "n1", "n2"]
    log.emit(Severity.INFO, "e", "after", 9)
    (e,) = log.drain()
    assert e.seq == 5  # the gap 3, 4 shows the drops


def test_capacity_must_be_positive() -> None:
    with pytest.raises(ValueError):
        EventLog("cn", capacity=0)


def test_drain_returns_a_list_the_caller_owns() -> None:
    log = EventLog("cn")
    log.emit(Severity.INFO, "a", "x", 0)
    first = log.drain()
    log.emit(Severity.INFO, "a", "y", 1)
    assert [e.text for e in first] == ["x"]


def test_round_trip_and_severity_name() -> None:
    e = Event("cn", 7, -5, int(Severity.CRITICAL), "fault", "fault DN_LOST: ünïcode")
    b = encode_event(e)
    assert isinstance(b, bytes)
    assert decode_event(b) == e
    assert decode_event(bytearray(b)) == e
    assert decode_event(memoryview(b)) == e
    assert e.severity_name == "CRITICAL"
    assert Event("cn", 0, 0, 9, "", "").severity_name == "9"
    # a self-describing map, so taps in any language can read it
    assert msgspec.msgpack.decode(b)["text"] == "fault DN_LOST: ünïcode"


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xc1",
        b"\x93\x01\x02\x03",
        msgspec.msgpack.encode({"node": "cn"}),
        msgspec.msgpack.encode(
            {"node": "cn", "seq": 0, "t_ns": 0, "severity": 5, "id": "x", "text": "y"}
        ),
        msgspec.msgpack.encode(
            {"node": "cn", "seq": -1, "t_ns": 0, "severity": 1, "id": "x", "text": "y"}
        ),
        msgspec.msgpack.encode(
            {"node": 3, "seq": 0, "t_ns": 0, "severity": 1, "id": "x", "text": "y"}
        ),
    ],
)
def test_decode_refuses_anything_else(data: bytes) -> None:
    with pytest.raises(FrameFormatError) as ei:
        decode_event(data)
    assert isinstance(ei.value, CodecError)
    assert "not an event record" in str(ei.value)


def test_severity_values() -> None:
    assert [int(s) for s in Severity] == [0, 1, 2, 3, 4]
    assert Severity.WARNING > Severity.INFO
