"""The ground's gap fill from the CN's flight recorder, sans-IO (issue 20):
what it asks, what it believes, and the order it writes the log in."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from zplatform.control.loop import ControlLogic
from zplatform.core.auth import KeySet, Run
from zplatform.core.codec import decode_frame, encode_frame
from zplatform.core.datavector import DataVector
from zplatform.core.events import Event
from zplatform.ground.gapfill import GapFill
from zplatform.ground.logic import Gap, GroundLogic
from zplatform.mission.load import decode_mission
from zplatform.recorder.format import (
    REPLY_DONE,
    REPLY_END,
    REPLY_FRAMES,
    REPLY_LEN,
    REQUEST,
    REQUEST_MAGIC,
)

ROOT = Path(__file__).resolve().parents[2]
MISSION = decode_mission(
    (ROOT / "configs" / "minimal.yaml").read_text() + "\nrecorder: {}\n", code=False
)
KEYS = KeySet.from_master(MISSION, bytes(range(32)))
GROUND_KEYS = KEYS.for_node("gn")  # what a ground node holds
EPOCH = 1_700_000_000_000_000_000
PERIOD = 10_000_000
S = 1_000_000_000


def frames(epoch: int = EPOCH, keys: KeySet = KEYS, last: int = 40) -> dict[int, bytes]:
    cn = ControlLogic(MISSION, keys=keys, epoch=epoch)
    out = {}
    for n in range(1, last + 1):
        cn.begin(n, EPOCH + n * PERIOD)
        tm = cn.finish()
        assert tm is not None
        out[n] = bytes(tm)
    return out


TM = frames(last=320)


class Ground:
    """A GroundLogic and a GapFill writing rows into a list."""

    def __init__(self, **kw: Any) -> None:
        self.logic = GroundLogic(MISSION, keys=GROUND_KEYS)
        self.rows: list[tuple[int, int]] = []  # (rx_time_ns, cn_loop)
        self.fill = GapFill(MISSION, GROUND_KEYS, self.logic.events, self.write, **kw)

    def write(self, rx_ns: int, dv: DataVector) -> None:
        self.rows.append((rx_ns, int(dv.get("cn_loop"))))

    def live(self, *loops: int) -> None:
        for n in loops:
            rx = EPOCH + n * PERIOD + 1000  # arrived 1 us after its stamp
            assert self.logic.on_telemetry(TM[n], rx)
            self.fill.snapshot(self.logic, rx)

    def events(self) -> list[Event]:
        return self.logic.events.drain()


def reply(*payloads: bytes) -> bytes:
    out = bytearray([REPLY_FRAMES])
    for p in payloads:
        out += REPLY_LEN.pack(len(p)) + p
    return bytes(out)


def end(stamp: int, sent: int, not_held: int, not_run: int = 0, run: int = EPOCH) -> bytes:
    """The recorder's END reply to the request stamped ``stamp`` (tagged)."""
    body = REPLY_DONE.pack(REPLY_END, sent, not_held, not_run, stamp)
    return bytes(KEYS.channel("telemetry", Run(run)).seal(body))


def test_a_gap_is_asked_for_exactly_and_written_in_loop_order() -> None:
    g = Ground()
    g.live(*range(1, 11))
    assert g.rows == [(EPOCH + n * PERIOD + 1000, n) for n in range(1, 11)]
    g.live(*range(21, 26))  # 11..20 lost on the way
    assert list(g.logic.gaps) == [] and g.fill.busy  # taken by the fill; 21..25 held
    assert len(g.rows) == 10
    now = EPOCH + 26 * PERIOD
    req = g.fill.take_request(now)
    assert req is not None and g.fill.take_request(now) is None  # one at a time
    rid, payload, timeout_s = req
    ch = KEYS.channel("telemetry")
    assert REQUEST.unpack(ch.open(payload)) == (REQUEST_MAGIC, EPOCH, 11, 20, now)
    assert 3 <= timeout_s < 10
    forged = frames(epoch=EPOCH + 1)[15]  # another run of the CN
    bad_tag = frames(keys=KeySet.from_master(MISSION, bytes(32)))[16]
    g.fill.on_reply(rid, reply(*(TM[n] for n in range(11, 16)), forged, bad_tag, TM[30]))
    g.fill.on_reply(rid, reply(*(TM[n] for n in range(16, 21)), TM[12]))  # 12 again: refused
    g.fill.on_reply(rid, end(now, 10, 0))
    assert len(g.rows) == 10  # nothing written before the request is over
    g.fill.on_done(rid, now + S)
    assert [loop for _, loop in g.rows] == list(range(1, 26))
    # The filled rows carry the frame's own stamp; the live ones their arrival.
    assert g.rows[10:20] == [(EPOCH + n * PERIOD, n) for n in range(11, 21)]
    assert g.rows[20] == (EPOCH + 21 * PERIOD + 1000, 21)
    assert g.fill.refused == 4 and (g.fill.filled, g.fill.unfilled) == (10, 0)
    assert "control node run" in g.fill.last_refusal
    (ev,) = g.events()[-1:]
    assert ev.id == "gap_filled" and ev.text.startswith("filled loops 11..20 (10 snapshot(s))")
    assert not g.fill.busy
    g.live(26)
    assert g.rows[-1] == (EPOCH + 26 * PERIOD + 1000, 26)  # straight through again


def test_loops_the_recorder_does_not_hold_are_given_up_and_said() -> None:
    g = Ground()
    g.live(*range(1, 6), *range(11, 14))
    rid, _, _ = g.fill.take_request(EPOCH) or (0, b"", 0.0)
    g.fill.on_reply(rid, reply(TM[6], TM[7]))
    g.fill.on_reply(rid, end(EPOCH, 2, 3))
    g.fill.on_done(rid, EPOCH + S)
    assert [loop for _, loop in g.rows] == [1, 2, 3, 4, 5, 6, 7, 11, 12, 13]
    said = {e.id: e.text for e in g.events()}
    assert said["gap_unfilled"] == (
        "loops 8..10: 3 snapshot(s) not filled from the control node's recorder: the control "
        "node's recorder does not hold them"
    )
    assert g.fill.take_request(EPOCH + 10 * S) is None  # not asked again
    assert (g.fill.filled, g.fill.unfilled) == (2, 3)


def test_loops_that_never_ran_are_no_loss() -> None:
    g = Ground()
    g.live(*range(1, 6), *range(11, 14))  # 6..10 missing: 9 and 10 never ran (overruns)
    rid, _, _ = g.fill.take_request(EPOCH) or (0, b"", 0.0)
    g.fill.on_reply(rid, reply(TM[6], TM[7], TM[8]))
    g.fill.on_reply(rid, end(EPOCH, 3, 0, 2))
    g.fill.on_done(rid, EPOCH + S)
    assert [loop for _, loop in g.rows] == [1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 13]
    assert (g.fill.filled, g.fill.unfilled, g.fill.not_run) == (3, 0, 2)
    assert [e.id for e in g.events()][-1] == "gap_filled"  # and no gap_unfilled
    assert g.fill.take_request(EPOCH + 10 * S) is None


def test_an_unanswered_request_is_asked_again_later_then_given_up() -> None:
    g = Ground(tries=3, retry_s=1.0)
    g.live(1, 2, 5)
    t = EPOCH
    for attempt in range(1, 4):
        req = g.fill.take_request(t)
        assert req is not None, attempt
        g.fill.on_done(req[0], t)  # no queryable answered (the link fell again)
        assert g.fill.take_request(t) is None  # not at once: after a pause
        t += attempt * S + 1
    said = [e.text for e in g.events() if e.id == "gap_unfilled"]
    assert said == [
        "loops 3..4: 2 snapshot(s) not filled from the control node's recorder: no answer for "
        "them after 3 request(s)"
    ]
    assert [loop for _, loop in g.rows] == [1, 2, 5]


def test_a_reply_to_an_old_request_is_not_taken_for_the_new_one() -> None:
    g = Ground(retry_s=0.0)
    g.live(1, 2, 5)
    old, _, _ = g.fill.take_request(EPOCH) or (0, b"", 0.0)
    g.fill.on_done(old, EPOCH)
    new, _, _ = g.fill.take_request(EPOCH + 1) or (0, b"", 0.0)
    assert new != old
    g.fill.on_reply(old, reply(TM[3], TM[4]))  # late, for the abandoned request
    g.fill.on_done(old, EPOCH + 2)
    assert g.fill.busy and len(g.rows) == 2
    g.fill.on_reply(new, reply(TM[3], TM[4]))
    g.fill.on_done(new, EPOCH + 3)
    assert [loop for _, loop in g.rows] == [1, 2, 3, 4, 5]


def test_rows_are_held_at_most_hold_s() -> None:
    g = Ground(hold_s=2.0)
    g.live(1, 2, 5)
    req = g.fill.take_request(EPOCH)
    assert req is not None
    g.live(*range(6, 310))  # 3 s of snapshots while the request hangs
    # Held past 2 s: written, the gap given up; the request's late end is ignored.
    assert [loop for _, loop in g.rows] == [1, 2, *range(5, 310)]
    g.fill.on_done(req[0], EPOCH + 10 * S)
    assert g.fill.unfilled == 2 and not g.fill.busy
    said = [e.text for e in g.events() if e.id == "gap_unfilled"]
    assert said and said[0].endswith("not filled within 2 s")


def test_the_log_ending_writes_everything_held() -> None:
    g = Ground()
    g.live(1, 2, 5, 6)
    assert g.fill.take_request(EPOCH) is not None
    g.fill.finish(EPOCH + S)
    assert [loop for _, loop in g.rows] == [1, 2, 5, 6]
    assert g.fill.unfilled == 2
    assert [e.text.split(": ")[-1] for e in g.events() if e.id == "gap_unfilled"] == [
        "the log ended first"
    ]


def test_the_ground_logic_queues_each_gap() -> None:
    logic = GroundLogic(MISSION, keys=GROUND_KEYS)
    for n in (1, 2, 5, 6, 9):
        assert logic.on_telemetry(TM[n], EPOCH + n * PERIOD)
    assert list(logic.gaps) == [Gap(EPOCH, 3, 4), Gap(EPOCH, 7, 8)]
    assert logic.counters.gaps == 4


def test_an_empty_reply_a_replayed_frame_and_a_frame_stamped_after_the_ask_are_counted() -> None:
    """Every refusal counts: an empty reply, a frame of a loop already
    taken (a replay), and an authentic frame of a loop asked for stamped
    beyond the clock bound after the request (at i64 max it would be the
    row's time), which is not taken."""
    g = Ground()
    g.live(*range(1, 11))
    g.live(*range(21, 26))
    now = EPOCH + 26 * PERIOD
    req = g.fill.take_request(now)
    assert req is not None
    rid = req[0]
    ch = KEYS.channel("telemetry")
    f = decode_frame(ch.open(TM[12]))
    late = bytes(ch.seal(encode_frame(f.layout_id, 12, (1 << 63) - 1, bytes(f.data))))
    g.fill.on_reply(rid, b"")
    g.fill.on_reply(rid, reply(late))
    g.fill.on_reply(rid, reply(*(TM[n] for n in range(11, 21)), TM[11]))
    assert g.fill.refused == 3
    g.fill.on_reply(rid, end(now, 10, 0))
    g.fill.on_done(rid, now + S)
    assert g.rows[11] == (EPOCH + 12 * PERIOD, 12)  # the genuine stamp
    assert (g.fill.filled, g.fill.unfilled) == (10, 0)


def test_a_flood_of_junk_replies_before_and_among_the_genuine_ones_fills_the_gap(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 25: the ground's fill mailbox (FILL_BACKLOG) takes only replies
    zenoh's callback screened (size, kind, header tag, run, the request's
    range and stamp): 2,000 junk replies before and among the genuine ones
    (more than the mailbox holds after the genuine frames) push none of
    them out; the gap is filled and every junk reply counted once."""
    from types import SimpleNamespace

    from zplatform.ground import link as link_mod
    from zplatform.node.ground import FILL_BACKLOG, _Filler

    asked: list[tuple[bytes, Any]] = []
    monkeypatch.setattr(link_mod, "replies", lambda on_reply, on_done: (on_reply, on_done))
    monkeypatch.setattr(
        link_mod, "ask", lambda _s, _k, handler, **kw: asked.append((kw["payload"], handler))
    )
    logic = GroundLogic(MISSION, keys=GROUND_KEYS)
    rows: list[int] = []
    now = [EPOCH + 6 * PERIOD]
    fake: Any = SimpleNamespace(
        mission=MISSION,
        link_keys=GROUND_KEYS,
        logic=logic,
        clock=SimpleNamespace(now_ns=lambda: now[0]),
        keys=SimpleNamespace(recorder=f"{MISSION.vehicle}/cn/recorder"),
        ns=SimpleNamespace(session=None),
    )
    fake.query = lambda *a: link_mod.GroundLink.query(fake, *a)
    sink: Any = SimpleNamespace(
        snapshot=lambda _rx, dv: rows.append(int(dv.get("cn_loop"))), event=lambda _r: None
    )
    filler = _Filler(fake, sink)
    for n in (1, 2, 5):  # 3..4 lost
        rx = EPOCH + n * PERIOD + 1000
        assert logic.on_telemetry(TM[n], rx)
        filler.fill.snapshot(logic, rx)
    filler.pump()
    ((payload, (on_reply, on_done)),) = asked
    stamp = REQUEST.unpack(KEYS.channel("telemetry").open(payload))[4]
    assert stamp == now[0]

    def deliver(data: bytes) -> None:
        ok = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: data))
        on_reply(SimpleNamespace(ok=ok))

    forged = frames(keys=KeySet.from_master(MISSION, bytes(32)), last=4)[3]
    other_key = KeySet.from_master(MISSION, bytes(32)).channel("telemetry", Run(EPOCH))
    junk = [
        b"",
        b"\x07" + bytes(100),  # a kind no reply has
        reply(forged),  # a keyless peer's frame of a loop asked for
        reply(TM[30]),  # a genuine frame, not of the range asked (a replay)
        bytes(other_key.seal(REPLY_DONE.pack(REPLY_END, 0, 2, 0, stamp))),  # forged END
        end(stamp - 1, 0, 2),  # a genuine END of another request (a replay)
        bytes([REPLY_END]) + bytes(24),  # the untagged END of before
    ]
    flood = [junk[i % len(junk)] for i in range(2000)]
    for p in flood[:600]:
        deliver(p)
    deliver(reply(TM[3], TM[4]))
    for p in flood[600:1700]:  # more than the mailbox holds after the frames
        deliver(p)
    deliver(end(stamp, 2, 0))
    for p in flood[1700:]:
        deliver(p)
    on_done()
    assert FILL_BACKLOG < 1700 - 600
    filler.pump()
    assert rows == [1, 2, 3, 4, 5]
    assert filler._q.dropped == 0
    assert (filler.fill.filled, filler.fill.unfilled) == (2, 0)
    assert filler.fill.refused == 2000
    # Evented once (at most once a second), with the count.
    (ev,) = [e for e in logic.events.drain() if e.id == "bad_frame"]
    assert ev.text.startswith("2000 gap-fill reply(s)")
    now[0] += S // 2
    filler.pump()
    assert not [e for e in logic.events.drain() if e.id == "bad_frame"]
