"""Tests of zplatform.core.events: the catalogue, the bounded log and the wire form."""

from __future__ import annotations

import string
from typing import Any

import msgspec
import pytest

from zplatform.core.events import (
    EV,
    Event,
    EventLog,
    EventType,
    Severity,
    decode_event,
    encode_event,
)
from zplatform.errors import CodecError, EventError, FrameFormatError, ZPlatformError

# Three catalogue entries with one text field each, for the log's own tests.
A = EV.ERROR  # "{text}"
B = EV.BAD_FRAME  # "{source} rejected: {reason}"


def test_emit_then_drain_in_order_with_sequence_numbers() -> None:
    log = EventLog("cn")
    log.emit(A, 10, text="first")
    log.emit(B, 20, source="sync query", reason="second")
    assert log.pending == 2
    evs = log.drain()
    assert evs == [
        Event("cn", 0, 10, int(Severity.WARNING_LO), "error", "first"),
        Event("cn", 1, 20, int(Severity.WARNING_LO), "bad_frame", "sync query rejected: second"),
    ]
    assert log.pending == 0 and log.drain() == []
    log.emit(EV.HOLD_ENDED, 30)
    assert log.drain()[0].seq == 2
    assert log.emitted == 3 and log.dropped == 0


def test_full_log_keeps_the_oldest_and_counts_drops() -> None:
    log = EventLog("dn0", capacity=3)
    for i in range(5):
        log.emit(A, i, text=f"n{i}")
    assert log.dropped == 2 and log.emitted == 5
    evs = log.drain()
    assert [e.text for e in evs] == ["n0", "n1", "n2"]
    log.emit(A, 9, text="after")
    (e,) = log.drain()
    assert e.seq == 5  # the gap 3, 4 shows the drops


def test_capacity_must_be_positive() -> None:
    with pytest.raises(ValueError):
        EventLog("cn", capacity=0)


def test_drain_returns_a_list_the_caller_owns() -> None:
    log = EventLog("cn")
    log.emit(A, 0, text="x")
    first = log.drain()
    log.emit(A, 1, text="y")
    assert [e.text for e in first] == ["x"]


def test_round_trip_and_severity_name() -> None:
    e = Event("cn", 7, -5, int(Severity.FATAL), "fault", "fault DN_LOST: ünïcode")
    b = encode_event(e)
    assert isinstance(b, bytes)
    assert decode_event(b) == e
    assert decode_event(bytearray(b)) == e
    assert decode_event(memoryview(b)) == e
    assert e.severity_name == "FATAL"
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
            {"node": "cn", "seq": 0, "t_ns": 0, "severity": 7, "id": "x", "text": "y"}
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
    # F Prime's seven, least to most important; the values are the wire encoding.
    assert [s.name for s in Severity] == [
        "DIAGNOSTIC",
        "ACTIVITY_LO",
        "ACTIVITY_HI",
        "COMMAND",
        "WARNING_LO",
        "WARNING_HI",
        "FATAL",
    ]
    assert [int(s) for s in Severity] == [0, 1, 2, 3, 4, 5, 6]
    assert Severity.FATAL > Severity.WARNING_HI > Severity.WARNING_LO > Severity.COMMAND
    for s in Severity:  # every severity is a valid record
        e = Event("cn", 0, 0, int(s), "x", "y")
        assert decode_event(encode_event(e)).severity_name == s.name


def _fields(fmt: str) -> set[str]:
    return {f for _, f, _, _ in string.Formatter().parse(fmt) if f is not None}


def test_catalogue_ids_and_names_are_unique_and_every_entry_formats() -> None:
    entries = EV.ALL
    assert len(entries) >= 13
    assert len({e.id for e in entries}) == len(entries)
    assert len({e.name for e in entries}) == len(entries)
    for e in entries:
        assert isinstance(e.severity, Severity)
        assert e.name.isidentifier() and e.name == e.name.lower(), e
        fields = _fields(e.format)
        assert all(f.isidentifier() for f in fields), e  # named fields only
        args: dict[str, Any] = {f: 1.5 for f in fields}
        text = e.text(**args)
        assert "{" not in text and text == e.format.format(**args)
        log = EventLog("cn")
        log.emit(e, 1, **args)
        (rec,) = log.drain()
        assert (rec.id, rec.severity, rec.text) == (e.name, int(e.severity), text)


def test_the_shipped_names_are_kept() -> None:
    # Ground tools and tests key on these names: renaming one breaks them.
    names = {e.name for e in EV.ALL}
    assert {
        "state_change",
        "hold",
        "resume",
        "hold_ended",
        "cmd_accepted",
        "cmd_rejected",
        "fault",
        "error",
        "controller_failed",
        "controller_disabled",
        "device_failed",
        "board_failed",
        "bad_frame",
    } <= names


def test_emit_refuses_an_entry_not_in_the_catalogue() -> None:
    log = EventLog("cn")
    twin = EventType(EV.ERROR.id, EV.ERROR.name, EV.ERROR.severity, EV.ERROR.format)
    for bad in (twin, "error", None):
        with pytest.raises(EventError, match="not an entry of the event catalogue") as ei:
            log.emit(bad, 0, text="x")  # type: ignore[arg-type]
        assert isinstance(ei.value, ZPlatformError)
    assert log.emitted == 0 and log.pending == 0


def test_bad_format_arguments_never_raise() -> None:
    log = EventLog("cn")
    log.emit(EV.HOLD, 3, state="A")  # tis_s missing
    log.emit(EV.HOLD, 4, state="A", tis_s="not a number")
    texts = [e.text for e in log.drain()]
    assert texts[0].startswith(EV.HOLD.format) and "'state': 'A'" in texts[0]
    assert texts[1].startswith(EV.HOLD.format)
