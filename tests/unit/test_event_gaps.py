"""No event lost unseen: gaps in a node's event numbers are detected,
counted, told, and (the control node's) filled from its flight recorder.

In process, sans-IO: the CN's logic frames telemetry and its events, its
flight recorder keeps both (the events untagged, as EventPublisher hands
them), a GroundLogic takes what "arrives", a GapFill asks, and the
RecorderServer answers on this thread through fake zenoh queries."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.payload import FakeQuery, FakeSession, deliver
from tests.waits import wait_until
from zplatform.console.model import ConsoleModel
from zplatform.control.loop import ControlLogic
from zplatform.core.auth import KeySet, Run
from zplatform.core.events import EV, Event, EventLog, encode_event
from zplatform.errors import CodecError
from zplatform.ground.gapfill import GapFill
from zplatform.ground.logic import GroundLogic
from zplatform.mission.load import decode_mission
from zplatform.recorder import RECORDER_DIR_ENV, open_recorder
from zplatform.recorder import format as fmt
from zplatform.recorder.format import (
    REPLY_DONE,
    REPLY_END,
    REPLY_FRAMES,
    REPLY_LEN,
    REPLY_TOTALS,
    REQUEST,
    REQUEST_MAGIC,
)
from zplatform.recorder.server import RecorderServer
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
MISSION = decode_mission(
    (ROOT / "configs" / "minimal.yaml").read_text() + "\nrecorder: {}\n", code=False
)
KEYS = KeySet.from_master(MISSION, bytes(range(32)))
GROUND_KEYS = KEYS.for_node("gn")
EPOCH = 1_700_000_000_000_000_000
PERIOD = MISSION.period_ns
S = 1_000_000_000
CN_EVENTS = f"{MISSION.vehicle}/cn/events"
DN_EVENTS = f"{MISSION.vehicle}/dn0/events"
# New with event gaps: read where used, so each test fails by itself without them.
EVENTS_MAGIC = getattr(fmt, "EVENTS_MAGIC", b"ZRE1")
REPLY_EVENTS = getattr(fmt, "REPLY_EVENTS", 3)


class Vehicle:
    """The CN (telemetry, events, recorder, recorder server) and a ground
    (logic, gap fill) that takes what is not dropped on the way."""

    def __init__(self, d: Path) -> None:
        self.cn = ControlLogic(MISSION, keys=KEYS, epoch=EPOCH)
        self.cn.events.drain()
        self.rec = open_recorder(MISSION, "cn", self.cn.dv, run=EPOCH, authenticated=True)
        self.seal = KEYS.channel("events_cn", Run(EPOCH))  # as the CN's EventPublisher tags
        self.now = EPOCH
        self.server = RecorderServer(
            FakeSession(),  # type: ignore[arg-type]
            f"{MISSION.vehicle}/cn/recorder",
            self.rec,
            KEYS.channel("telemetry"),
            now_ns=lambda: self.now,
            max_age_ns=2 * S,
            serve_bps=10**9,
            events=KEYS.channel("events_cn", Run()),
        )
        self.server.close()  # its thread: deliver() serves on this one
        self.ground = GroundLogic(MISSION, keys=GROUND_KEYS)
        self.shown: list[EventRecord] = []
        self.fill = GapFill(
            MISSION,
            GROUND_KEYS,
            self.ground.events,
            lambda _rx, _dv: None,
            logic=self.ground,
            on_event=self.shown.append,
        )
        self.loop = 0
        self.sent: dict[int, tuple[str, bytes]] = {}  # seq -> (text, tagged record)

    def step(self, *texts: str, drop: tuple[int, ...] = ()) -> None:
        """One CN loop emitting ``texts`` as error events; those whose
        number is in ``drop`` do not reach the ground."""
        self.loop += 1
        n = self.loop
        t = EPOCH + n * PERIOD
        self.now = t
        self.cn.begin(n, t)
        for text in texts:
            self.cn.events.emit(EV.ERROR, t, text=text)
        tm = self.cn.finish()
        assert tm is not None
        self.rec.frame(n, tm)
        rx = t + 1000
        assert self.ground.on_telemetry(tm, rx)
        self.fill.snapshot(self.ground, rx)
        for e in self.cn.events.drain():
            raw = encode_event(e)
            self.rec.event(raw)
            tagged = bytes(self.seal.seal(raw))
            self.sent[e.seq] = (e.text, tagged)
            if e.seq not in drop:
                got = self.ground.on_event_bytes(CN_EVENTS, tagged, rx)
                assert got is not None
                self.shown.append(got)
        self.ground.tick(rx)

    def written(self) -> None:
        wait_until(lambda: not self.rec.backlog, 10, "the recorder's writer thread")

    def ask(self) -> tuple[int, list[FakeQuery]]:
        """The fill's next request, served by the recorder (not yet handed back)."""
        self.written()
        req = self.fill.take_request(self.now)
        assert req is not None
        rid, payload, _ = req
        return rid, deliver(self.server, payload)

    def said(self) -> list[Event]:
        return self.ground.events.drain()

    def close(self) -> None:
        self.rec.close()


@pytest.fixture
def vehicle(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Vehicle]:
    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp_path))
    v = Vehicle(tmp_path)
    yield v
    v.close()


def test_a_dropped_cn_event_is_detected_told_once_asked_and_filled_with_its_text(
    vehicle: Vehicle,
) -> None:
    v = vehicle
    v.step("SAFE -> ARMED")  # #0
    for _ in range(5):
        v.step()
    v.step("ARMED -> BOOST", drop=(1,))  # #1: lost on the way
    v.step("BOOST -> MECO", drop=(2,))  # #2: lost on the way
    for _ in range(5):
        v.step()
    v.step("BOOST -> COAST")  # #3: the gap shows
    assert v.ground.counters.events_missed == 2
    (told,) = [e for e in v.said() if e.id == "events_missed"]
    assert told.text == (
        "2 event(s) of cn (#1..#2) did not arrive: asked of the control node's recorder"
    )
    rid, (q,) = v.ask()
    body = KEYS.channel("telemetry").open(q.payload.to_bytes())  # tagged like every request
    magic, run, first, last, _ = REQUEST.unpack(body)
    assert (magic, run) == (EVENTS_MAGIC, EPOCH)
    assert first <= 7 and last >= 8 and last - first < 20  # the loops around the gap
    for p in q.replies:
        v.fill.on_reply(rid, p)
    assert [r.seq for r in v.shown] == [0, 3]  # nothing handed on before the end
    v.fill.on_done(rid, v.now + S)
    filled = v.shown[2:]
    assert [(r.seq, r.text, r.filled, r.verified) for r in filled] == [
        (1, "ARMED -> BOOST", True, True),
        (2, "BOOST -> MECO", True, True),
    ]
    assert [r.text for r in filled] == [v.sent[1][0], v.sent[2][0]]
    said = {e.id: e.text for e in v.said()}
    assert said == {
        "events_filled": "filled 2 event(s) of cn (#1..#2) from the control node's recorder"
    }
    assert (v.fill.events_filled, v.fill.events_unfilled, v.fill.refused) == (2, 0, 0)
    assert v.fill.take_request(v.now + 10 * S) is None  # not asked again


def test_a_filled_event_replayed_is_refused(vehicle: Vehicle) -> None:
    v = vehicle
    v.step("one")
    v.step("two", drop=(1,))
    v.step("three")
    rid, (q,) = v.ask()
    events = [p for p in q.replies if p[0] == REPLY_EVENTS]
    assert events
    for p in events:  # every reply twice: each record again is a replay
        v.fill.on_reply(rid, p)
        v.fill.on_reply(rid, p)
    v.fill.on_reply(rid, q.replies[-1])
    v.fill.on_done(rid, v.now)
    assert [(r.seq, r.filled) for r in v.shown] == [(0, False), (2, False), (1, True)]
    assert v.fill.refused == 1 and "again" in v.fill.last_refusal  # #1 again (#0, #2 arrived)
    # The gap is closed: the same record brought again fills nothing.
    from zplatform.ground.logic import EventGap

    gap = EventGap("cn", EPOCH, 1, 1, 1, 5)
    with pytest.raises(CodecError, match="not being filled"):
        v.ground.check_filled(gap, v.sent[1][1])
    # Nor does it come in live: it is not newer than the last taken.
    assert v.ground.on_event_bytes(CN_EVENTS, v.sent[1][1], v.now) is None
    assert v.ground.counters.stale_events == 1
    assert [r.seq for r in v.shown] == [0, 2, 1]


def test_junk_or_forged_replies_carry_no_events_in(vehicle: Vehicle) -> None:
    v = vehicle
    v.step("zero")
    v.step("one", "two", drop=(1, 2))
    v.step("three")
    rid, _ = v.ask()
    raw1 = encode_event(Event("cn", 1, EPOCH + 2 * PERIOD, 4, "error", "forged one"))
    wrong_key = KeySet.from_master(MISSION, bytes(32)).channel("events_cn", Run(EPOCH))
    other_run = KEYS.channel("events_cn", Run(EPOCH + 1))
    dn_key = KEYS.channel("events_dn0", Run(EPOCH))
    junk = [
        b"",
        b"\x07" + b"x" * 40,  # a kind no reply has
        b"\x03\xff\xff",  # cut inside a length
        bytes([REPLY_EVENTS]) + REPLY_LEN.pack(1 << 30) + b"abc",  # longer than it is
        bytes([REPLY_FRAMES]) + REPLY_LEN.pack(3) + b"abc",  # frames, to an events request
    ]
    forged = [
        bytes(wrong_key.seal(raw1)),  # another key: a bad tag
        bytes(other_run.seal(raw1)),  # another run of the CN
        bytes(dn_key.seal(raw1)),  # a device node's key on the CN's record
        raw1,  # untagged
        b"\x00" * 60,
    ]
    for p in junk:
        v.fill.on_reply(rid, p)
    out = bytearray([REPLY_EVENTS])
    for f in forged:
        out += REPLY_LEN.pack(len(f)) + f
    v.fill.on_reply(rid, bytes(out))
    assert v.fill.refused == len(junk) + len(forged)
    tm_end = KEYS.channel("telemetry", Run(EPOCH))  # the request was stamped v.now
    v.fill.on_reply(rid, bytes(tm_end.seal(REPLY_DONE.pack(REPLY_END, 0, 0, 0, v.now))))
    v.fill.on_done(rid, v.now)
    assert [r.seq for r in v.shown] == [0, 3]  # nothing came in
    said = {e.id: e.text for e in v.said()}
    assert said["events_unfilled"] == (
        "2 event(s) of cn (#1..#2) not filled from the control node's recorder: not among "
        "the records of their loops (the recorder dropped them)"
    )
    assert (v.fill.events_filled, v.fill.events_unfilled) == (0, 2)


def test_a_gap_the_recorder_never_answers_ends_in_one_event(vehicle: Vehicle) -> None:
    v = vehicle
    v.step("zero")
    v.step("one", drop=(1,))
    v.step("two")
    v.written()
    for tries in range(3):
        req = v.fill.take_request(v.now)
        assert req is not None, tries
        v.fill.tick(v.now + 10 * S)  # its time runs out, no END
        v.now += 20 * S  # past the wait before it is asked again
    assert v.fill.take_request(v.now + 100 * S) is None
    (told,) = [e for e in v.said() if e.id in ("events_filled", "events_unfilled")]
    assert told.id == "events_unfilled" and told.text.endswith("no answer after 3 request(s)")
    assert v.fill.events_unfilled == 1


def test_a_device_nodes_dropped_event_is_counted_and_told_only() -> None:
    g = GroundLogic(MISSION, keys=GROUND_KEYS)
    fill = GapFill(MISSION, GROUND_KEYS, g.events, lambda _rx, _dv: None, logic=g)
    seal = KEYS.channel("events_dn0", Run(EPOCH))
    log = EventLog("dn0")
    t = EPOCH
    for i in range(6):
        log.emit(EV.ERROR, t + i, text=f"dn0 says {i}")
    for e in log.drain():
        if e.seq not in (2, 3):
            assert g.on_event_bytes(DN_EVENTS, seal.seal(encode_event(e)), t) is not None
    assert g.counters.events_missed == 2
    (told,) = g.events.drain()
    assert told.text == (
        "2 event(s) of dn0 (#2..#3) did not arrive: not filled (dn0 serves no recorder to ask)"
    )
    assert not g.event_gaps and fill.take_request(t) is None


def test_a_restarted_nodes_numbers_are_no_gap() -> None:
    g = GroundLogic(MISSION, keys=GROUND_KEYS)
    seal = KEYS.channel("events_dn0", Run(EPOCH))
    t = EPOCH
    for incarnation in range(2):  # the node restarts in the run: numbered from 0 again
        log = EventLog("dn0")
        for i in range(4):
            log.emit(EV.ERROR, t, text=f"{incarnation}.{i}")
            t += 1000
        for e in log.drain():
            assert g.on_event_bytes(DN_EVENTS, seal.seal(encode_event(e)), t) is not None
    # A new run of the vehicle numbers from 0 too (a ground bound to no run).
    seal2 = KEYS.channel("events_dn0", Run(EPOCH + 1))
    log = EventLog("dn0")
    for _ in range(7):
        log.emit(EV.ERROR, t, text="new run")
    for e in log.drain()[5:]:
        assert g.on_event_bytes(DN_EVENTS, seal2.seal(encode_event(e)), t) is not None
    assert g.counters.events_missed == 0 and g.events.drain() == []


def test_gaps_are_told_at_most_once_a_second() -> None:
    g = GroundLogic(MISSION, keys=GROUND_KEYS)
    seal = KEYS.channel("events_dn0", Run(EPOCH))
    log = EventLog("dn0")
    for i in range(10):
        log.emit(EV.ERROR, EPOCH + i, text=str(i))
    evs = {e.seq: e for e in log.drain()}

    def arrive(seq: int, rx: int) -> None:
        assert g.on_event_bytes(DN_EVENTS, seal.seal(encode_event(evs[seq])), rx) is not None

    arrive(0, EPOCH)
    arrive(2, EPOCH + 1)  # #1
    arrive(4, EPOCH + 2)  # #3
    arrive(7, EPOCH + 3)  # #5..#6
    assert [e.text.split(":")[0] for e in g.events.drain()] == [
        "1 event(s) of dn0 (#1) did not arrive"
    ]
    g.tick(EPOCH + S // 2)
    assert g.events.drain() == []
    g.tick(EPOCH + S + 1)  # the rest, in one
    (told,) = g.events.drain()
    assert told.text.startswith("3 event(s) of dn0 (#3), dn0 (#5..#6) did not arrive")
    assert g.counters.events_missed == 4


def test_the_recorder_answers_an_events_request_with_tagged_events_only(
    vehicle: Vehicle,
) -> None:
    v = vehicle
    v.step("a")
    v.step("b", "c")
    v.step()
    v.step("d")
    v.written()
    ch = KEYS.channel("telemetry")
    reader = KEYS.channel("events_cn", Run(EPOCH))

    def ask(magic: bytes, first: int, last: int, run: int = EPOCH) -> list[bytes]:
        v.now += 1
        (q,) = deliver(v.server, bytes(ch.seal(REQUEST.pack(magic, run, first, last, v.now))))
        return q.replies

    *events, end = ask(EVENTS_MAGIC, 2, 3)
    assert all(p[0] == REPLY_EVENTS for p in events)
    seqs = []
    for p in events:
        off = 1
        while off < len(p):
            (n,) = REPLY_LEN.unpack_from(p, off)
            rec = reader.open(p[off + 4 : off + 4 + n])  # tagged with the CN's events key
            seqs.append(bytes(rec))
            off += 4 + n
    assert [bytes(reader.open(v.sent[s][1])) for s in (1, 2)] == seqs
    assert end[0] == REPLY_END and REPLY_TOTALS.unpack_from(end, 1) == (2, 0, 0)
    # Past what is written: not held; another run: nothing of it here.
    assert REPLY_TOTALS.unpack_from(ask(EVENTS_MAGIC, 4, 10)[-1], 1) == (1, 6, 0)
    (other,) = ask(EVENTS_MAGIC, 1, 4, run=EPOCH + 1)
    # The END is tagged under the run asked for, with the request's stamp.
    opened = KEYS.channel("telemetry", Run(EPOCH + 1)).open(other)
    assert REPLY_DONE.unpack(opened) == (REPLY_END, 0, 4, 0, v.now)
    # A frames request still brings frames alone.
    assert {p[0] for p in ask(REQUEST_MAGIC, 1, 4)} == {REPLY_FRAMES, REPLY_END}
    assert v.server.events_sent == 3 and v.server.refused == 0


def test_the_console_shows_a_filled_event_in_its_place_and_the_missed_count() -> None:
    m = ConsoleModel(MISSION)

    def rec(seq: int, text: str, *, node: str = "cn", filled: bool = False) -> EventRecord:
        return EventRecord(
            0, node, seq, EPOCH + seq, "ACTIVITY_HI", "state_change", text, True, filled
        )

    m.on_event(rec(0, "SAFE -> ARMED"))
    m.on_event(rec(7, "dn0 0", node="dn0"))
    m.on_event(rec(2, "BOOST -> COAST"))
    m.on_event(rec(3, "COAST -> APOGEE"))
    m.on_event(rec(1, "ARMED -> BOOST", filled=True))
    assert [x.text for x in m.events()] == [
        "state_change: SAFE -> ARMED",
        "state_change: dn0 0",
        "state_change: ARMED -> BOOST (filled)",
        "state_change: BOOST -> COAST",
        "state_change: COAST -> APOGEE",
    ]
    g = GroundLogic(MISSION, keys=GROUND_KEYS)
    seal = KEYS.channel("events_cn", Run(EPOCH))
    for seq in (0, 5):
        e = Event("cn", seq, EPOCH + seq, 2, "state_change", "x")
        assert g.on_event_bytes(CN_EVENTS, seal.seal(encode_event(e)), EPOCH) is not None
    cn = ControlLogic(MISSION, keys=KEYS, epoch=EPOCH)
    cn.begin(1, EPOCH)
    m.on_snapshot(cn.dv, EPOCH, g.counters)
    assert m.status().events_missed == 4


def test_the_consoles_link_asks_and_shows_the_filled_events_in_its_pane(
    vehicle: Vehicle,
) -> None:
    """The console's thread drives an events-only fill: its requests go out
    as zenoh gets on the recorder's key, their replies come back through a
    mailbox, and the filled events reach the model in their place."""
    from types import SimpleNamespace

    from zplatform.console.link import Link
    from zplatform.control.handoff import Mailbox

    v = vehicle
    model = ConsoleModel(MISSION)
    link = Link(model)
    v.fill._on_event = link._on_event  # as the console's thread builds it
    v.shown.clear()
    v.step("SAFE -> ARMED")
    v.step("ARMED -> BOOST", drop=(1,))
    v.step("BOOST -> COAST")
    for r in v.shown:
        model.on_event(r)  # the live ones, as the link hands them over
    v.written()
    asked: list[tuple[str, bytes, int]] = []
    replies: Mailbox[tuple[int, bytes | None]] = Mailbox(8)
    zenoh_side: Any = SimpleNamespace(
        keys=SimpleNamespace(recorder=f"{MISSION.vehicle}/cn/recorder"),
        query=lambda key, payload, _timeout, _into, rid, *_: asked.append((key, payload, rid)),
    )
    link.clock = SimpleNamespace(now_ns=lambda: v.now)  # type: ignore[assignment]
    link._pump(zenoh_side, v.fill, replies)
    ((key, payload, rid),) = asked
    assert key == f"{MISSION.vehicle}/cn/recorder"
    (q,) = deliver(v.server, payload)
    for p in q.replies:
        replies.put((rid, p))
    replies.put((rid, None))  # the get is over
    link._pump(zenoh_side, v.fill, replies)
    assert [x.text.split(": ", 1)[1] for x in model.events()] == [
        "SAFE -> ARMED",
        "ARMED -> BOOST (filled)",
        "BOOST -> COAST",
    ]
    assert len(asked) == 1  # nothing more to ask
