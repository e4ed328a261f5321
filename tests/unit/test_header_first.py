"""The header-first check (codecs/FORMAT.md §6.1, zplatform.control.intake):
every intake refuses a full-size junk frame by its header tag, and a
replayed genuine frame by the freshness its authentic header tells,
without computing the MAC over the body; a genuine header spliced onto
junk costs at most the budget's body MACs a loop.

The body's MAC is counted where the channel computes it
(``zplatform.core.auth._RunKey.mac``, every tag's MAC over a whole frame,
before and after the header tag existed); names only from before it, so
these tests fail, rather than error, on an intake that MACs every body."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.payload import Bytes
from zplatform.control.fencing import ASK, ask_frame, new_nonce
from zplatform.control.handoff import Waker
from zplatform.control.intake import (
    MirrorIntake,
    ProbeIntake,
    ReplyCheck,
    RequestIntake,
    TelemetryIntake,
    TriggerIntake,
)
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import Uplink
from zplatform.core import auth
from zplatform.core.auth import KEY_ENV, RUN_LEN, TAG_LEN, KeySet, Run, channel
from zplatform.mission.load import load_mission

ROOT = Path(__file__).resolve().parents[2]
M = load_mission(ROOT / "configs" / "led_test.yaml")
KEYS = KeySet.from_master(M, bytes.fromhex(os.environ[KEY_ENV]))
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
FKEYS = KeySet.from_master(FLIGHT, bytes.fromhex(os.environ[KEY_ENV]))
PERIOD = M.period_ns
T0 = 1_700_000_000_000_000_000
SPARE = 2  # zplatform.control.intake.MAC_SPARE


class _Macs:
    """Counts the body MACs (MACs over more than a header's bytes)."""

    def __init__(self) -> None:
        self.n = 0

    def reset(self) -> None:
        self.n = 0


@pytest.fixture
def macs(monkeypatch: pytest.MonkeyPatch) -> Iterator[_Macs]:
    counter = _Macs()
    real = auth._RunKey.mac

    def counted(self: Any, frame: bytes | bytearray | memoryview) -> bytes:
        counter.n += 1
        return real(self, frame)

    monkeypatch.setattr(auth._RunKey, "mac", counted)
    yield counter


def _junk(n: int) -> Bytes:
    """``n`` random bytes: a keyless peer's frame of full size."""
    return Bytes(os.urandom(n))


def _forged(genuine: bytes) -> Bytes:
    """A keyless peer's best junk: a genuine, full-size frame's header and run
    word (copied off the wire), the rest of its tag random."""
    keep = len(genuine) - TAG_LEN + RUN_LEN
    return Bytes(genuine[:keep] + os.urandom(len(genuine) - keep))


def _trigger(loop: int, t: int, dn: int = 0) -> bytes:
    return bytes(ControlLogic(M, keys=KEYS, epoch=T0).begin(loop, t)[dn])


def _spliced(genuine: bytes) -> bytes:
    """A genuine frame's header (and tag) on another body: what only a man in
    the middle, who saw the genuine frame, can send."""
    at = len(genuine) - TAG_LEN - 1  # the body's last byte: beyond the header's 40
    assert at >= 40
    body = bytearray(genuine)
    body[at] ^= 0xFF
    return bytes(body)


def test_a_trigger_intake_refuses_junk_and_replays_without_a_body_mac(macs: _Macs) -> None:
    intake: TriggerIntake[None] = TriggerIntake(M, "dn0", channel(KEYS, "cn_to_dn0"))
    t1 = _trigger(1, T0 + PERIOD)
    t2 = _trigger(2, T0 + 2 * PERIOD)  # never sent: its header is fresh
    assert intake.admit(Bytes(t1), None)
    macs.reset()
    for _ in range(50):
        assert not intake.admit(_junk(intake.max_len), None)
        assert not intake.admit(_forged(t2), None)
        assert not intake.admit(Bytes(t1), None)  # replayed
    assert macs.n == 0
    assert intake.take_counts() == (0, 100, 50)


def test_check_view_refuses_junk_and_replays_in_place_without_a_body_mac(macs: _Macs) -> None:
    """The intra-host path (shared memory, zplatform.runtime.intrahost):
    the trigger intake's and the CN's reply check's check_view."""
    intake: TriggerIntake[None] = TriggerIntake(M, "dn0", channel(KEYS, "cn_to_dn0"))
    t1 = bytearray(_trigger(1, T0 + PERIOD))
    assert intake.check_view(memoryview(t1), None) is not None
    check = ReplyCheck(M, "dn0", channel(KEYS, "dn0_to_cn"))
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    reply = DeviceLogic(M, "dn0", keys=KEYS).trigger(bytes(cn.begin(5, T0)[0]), T0)
    assert reply is not None
    r5 = bytearray(reply)
    check.expect(5, T0)
    assert check.check_view(memoryview(r5), None) is not None
    check.expect(6, T0 + PERIOD)  # the next loop: loop 5's reply is a replay
    macs.reset()
    for _ in range(20):
        assert intake.check_view(memoryview(bytearray(os.urandom(intake.max_len))), None) is None
        assert intake.check_view(memoryview(t1), None) is None
        assert check.check_view(memoryview(bytearray(os.urandom(check.max_len))), None) is None
        assert check.check_view(memoryview(r5), None) is None
    assert macs.n == 0
    assert intake.take_counts() == (0, 20, 20) and check.take_counts() == (0, 20, 20)


def test_the_telemetry_intake_refuses_junk_and_old_replays_without_a_body_mac(
    macs: _Macs,
) -> None:
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    frames = []
    for n in (1, 2):
        cn.begin(n, T0 + n * PERIOD)
        frames.append(bytes(cn.telemetry()))
    age = 10**9
    intake = TelemetryIntake(M, channel(KEYS, "telemetry", Run(T0)), 8, age)
    assert intake.admit(Bytes(frames[0]), T0 + PERIOD)
    assert intake.admit(Bytes(frames[1]), T0 + 2 * PERIOD)
    macs.reset()
    later = T0 + 2 * PERIOD + 2 * age  # replayed beyond the freshness bound
    for _ in range(20):
        assert not intake.admit(_junk(intake.max_len), later)
        assert not intake.admit(_forged(frames[1]), T0 + 2 * PERIOD)
        assert not intake.admit(Bytes(frames[0]), later)
        assert not intake.admit(Bytes(frames[1]), later)
    assert macs.n == 0
    assert intake.take_counts() == (0, 40, 40) and intake.aged == 40
    # Replayed within the bound, the header cannot tell (a takeover's new
    # term may stamp behind the newest): at most the budget's body MACs a loop.
    for _ in range(20):
        assert not intake.admit(Bytes(frames[0]), T0 + 3 * PERIOD)
    assert macs.n == SPARE
    assert intake.take_counts() == (0, 0, 20)


def test_the_mirror_intake_refuses_junk_without_a_body_mac_and_replays_within_a_budget(
    macs: _Macs,
) -> None:
    intake = MirrorIntake(FLIGHT, "cn_b", FKEYS.for_node("cn_b").channel("mirror"))
    cn = ControlLogic(FLIGHT, keys=FKEYS.for_node("cn"), epoch=T0)
    cn.dv.handle("cn_term").set(1)
    mirrors = []
    for loop in (1, 2):
        cn.begin(loop, T0 + loop * FLIGHT.period_ns)
        cn.finish()
        assert cn.mirror is not None
        mirrors.append(bytes(cn.mirror))
    assert intake.admit(Bytes(mirrors[1]), None)
    macs.reset()
    for _ in range(20):
        assert not intake.admit(_junk(intake.max_len), None)
        assert not intake.admit(_forged(mirrors[1]), None)
        assert not intake.admit(Bytes(mirrors[0]), None)  # an older loop, replayed
        assert not intake.admit(Bytes(mirrors[1]), None)  # the newest, replayed
    # The term is in the data: a replay costs a body MAC only within the
    # budget of headers that cannot tell, SPARE a loop; junk never does.
    assert macs.n == SPARE
    assert intake.take_counts() == (0, 40, 40)


def test_the_probe_intake_refuses_junk_and_replays_without_a_body_mac(macs: _Macs) -> None:
    clock = [T0]
    ch = channel(FKEYS, "probe_cn_to_dn0")
    intake: ProbeIntake[None] = ProbeIntake(
        "dn0",
        channel(FKEYS, "probe_cn_to_dn0"),
        Waker(),
        period_ns=FLIGHT.period_ns,
        now_ns=lambda: clock[0],
        clock_ns=lambda: clock[0],
        bound_ns=round(FLIGHT.clock.offset_bound_ms * 1e6),
    )
    ask = ask_frame(ch, ASK, 0, 1, 1, new_nonce(), T0)
    assert intake.admit(Bytes(ask), None)
    macs.reset()
    for _ in range(3):  # within the rate bound: the header decides
        clock[0] += FLIGHT.period_ns
        assert not intake.admit(_junk(intake.max_len), None)
        assert not intake.admit(Bytes(ask), None)
    assert macs.n == 0
    assert intake.take_counts() == (0, 3, 3)


def test_the_request_intake_refuses_junk_without_a_body_mac_and_replays_within_a_budget(
    macs: _Macs,
) -> None:
    up = Uplink(M, KEYS)
    last = [0]
    intake = RequestIntake(M, channel(KEYS, "gn_to_cn", Run(77)), 77, lambda: last[0], 16)
    first = bytes(up.frame("NOOP", 1, 0, 0.0, 0, 77))
    assert intake.admit(Bytes(first), None)
    last[0] = 1
    macs.reset()
    for _ in range(20):
        assert not intake.admit(_junk(intake.max_len), None)
        assert not intake.admit(Bytes(first), None)
    assert macs.n == SPARE  # the number is in the header, its run in the data
    assert intake.take_counts() == (0, 20, 20)
    assert intake.admit(Bytes(bytes(up.frame("NOOP", 2, 0, 0.0, 0, 77))), None)


def test_a_genuine_header_on_junk_costs_at_most_the_budget_then_the_next_loop_is_taken(
    macs: _Macs,
) -> None:
    """A man in the middle splices the fresh trigger's header onto junk:
    each is refused bad; the body's MAC is computed SPARE times, then the
    rest (the genuine trigger among them, which such a peer could as well
    drop) are dropped after their header until the loop takes the counts."""
    intake: TriggerIntake[None] = TriggerIntake(FLIGHT, "dn0", channel(FKEYS, "cn_to_dn0"))
    cn = ControlLogic(FLIGHT, keys=FKEYS.for_node("cn"), epoch=T0)
    t1 = bytes(cn.begin(1, T0 + FLIGHT.period_ns)[0])
    macs.reset()
    for _ in range(10):
        assert not intake.admit(Bytes(_spliced(t1)), None)
    assert macs.n == SPARE
    assert not intake.admit(Bytes(t1), None)  # this loop's budget is spent
    assert intake.take_counts() == (0, 11, 0) and intake.took_unchecked == 11 - SPARE
    assert intake.admit(Bytes(t1), None)  # the next loop's


class _Payload:
    def __init__(self, data: bytes) -> None:
        self._data = data

    def __len__(self) -> int:
        return len(self._data)

    def to_bytes(self) -> bytes:
        return self._data


class _Query:
    """A zenoh query as the recorder's server sees it (the replies kept)."""

    def __init__(self, payload: bytes) -> None:
        self.payload = _Payload(payload)
        self.replies: list[bytes] = []

    def reply(self, key: str, payload: bytes) -> None:
        self.replies.append(payload)

    def reply_err(self, payload: bytes) -> None:
        pass

    def drop(self) -> None:
        pass


class _Session:
    def declare_queryable(self, key: str, handler: object) -> Any:
        return type("Q", (), {"undeclare": lambda self: None})()


def _recorder_server(**kw: Any) -> Any:
    """A CN's recorder server on a fake session, at T0, holding no run
    (never the run asked: no file is read); ``kw``: more of its arguments."""
    from zplatform.recorder.server import RecorderServer

    rec: Any = type("R", (), {"run": -1})()
    return RecorderServer(
        _Session(),  # type: ignore[arg-type]
        "v/cn/recorder",
        rec,
        channel(KEYS, "telemetry"),
        now_ns=lambda: T0,
        max_age_ns=10**9,
        serve_bps=10**9,
        **kw,
    )


def test_the_recorder_server_refuses_junk_and_a_replayed_request_without_a_body_mac(
    macs: _Macs,
) -> None:
    from zplatform.recorder.format import REQUEST, REQUEST_MAGIC

    ch = channel(KEYS, "telemetry")
    assert ch is not None
    server = _recorder_server()
    server.close()
    request = bytes(ch.seal(REQUEST.pack(REQUEST_MAGIC, 7, 1, 5, T0)))

    def serve(payload: bytes) -> _Query:
        q = _Query(payload)
        server.serve(q)  # type: ignore[arg-type]
        return q

    assert serve(request).replies and server.served == 1
    macs.reset()
    for _ in range(10):
        assert serve(request).replies == []  # replayed
        assert serve(os.urandom(len(request))).replies == []
    assert macs.n == 0
    assert server.served == 1 and server.refused == 20


def test_a_keyless_recorder_flood_never_spends_the_bound_a_grounds_request_needs() -> None:
    """Issue 25: the recorder server's rate bound came before any check, so
    a keyless flood of request-sized junk spent it and the ground's genuine
    request, at the same instant, was dropped unanswered (``excess``). Now
    zenoh's callback checks the header tag first: every junk request is
    refused (counted, never handed off), none beyond the bound, and the
    genuine one is handed to the serving thread."""
    from tests.payload import FakeQuery
    from zplatform.recorder.format import REQUEST, REQUEST_MAGIC
    from zplatform.recorder.server import REQUEST_BURST

    ch = channel(KEYS, "telemetry")
    assert ch is not None
    server = _recorder_server(mono_ns=lambda: 5 * 10**9)  # one instant: the bound never refills
    try:
        request = bytes(ch.seal(REQUEST.pack(REQUEST_MAGIC, 7, 1, 5, T0)))
        flood = [FakeQuery(os.urandom(len(request))) for _ in range(20 * REQUEST_BURST)]
        for q in flood:
            server.on_query(q)
        assert all(q.dropped for q in flood)
        assert server.refused == len(flood) and server.excess == 0 and server.busy == 0
        genuine = FakeQuery(request)
        server.on_query(genuine)
        assert not genuine.dropped and server.excess == 0  # handed to the serving thread
    finally:
        server.close()


def test_the_clock_and_run_askers_refuse_junk_and_replayed_answers_without_a_body_mac(
    macs: _Macs,
) -> None:
    from zplatform.runtime.clocksync import ClockLink, ClockResponder, RunAsker

    dn = KEYS.for_node("dn0")
    link = ClockLink(M, "dn0", dn)
    server = ClockResponder(M, KEYS.for_node("cn"), Run(T0))
    q1, n1 = link.query(T0)
    r1 = server.answer(q1, T0 + 1, T0 + 2)
    assert r1 is not None and link.check(r1, n1) is not None
    _, n2 = link.query(T0 + 10**6)  # the next exchange: r1 is a replay now
    asker = RunAsker(KEYS.for_node("gn"), Run())
    a1 = server.answer(asker.hello(), T0, T0)
    assert a1 is not None and asker.check(a1)
    asker.hello()  # a new hello: a1 answers a nonce nobody waits for any more
    macs.reset()
    for _ in range(10):
        assert server.answer(q1, T0 + 3, T0 + 4) is None  # the query replayed
        assert server.answer(os.urandom(len(q1)), T0 + 3, T0 + 4) is None
        assert link.check(r1, n2) is None
        assert link.check(os.urandom(len(r1)), n2) is None
        assert not asker.check(a1)
        assert not asker.check(os.urandom(len(a1)))
    assert macs.n == 0
    assert (link.refused_bad, link.refused_other) == (10, 10)
    assert (asker.refused_bad, asker.refused_other) == (10, 10)
    assert server.stale == 10 and server.refused == 20


def test_the_event_intake_refuses_junk_and_passes_replays_on_without_a_body_mac(
    macs: _Macs,
) -> None:
    """The ground's zenoh callback (EventReader.forged): junk of any size is
    refused by its header tag; a replayed genuine record is passed on to
    read(), which refuses it by its number, without the callback's MAC."""
    from zplatform.core.events import Event, EventReader, encode_event

    record = bytes(KEYS.channel("events_cn").seal(encode_event(Event("cn", 1, T0, 2, "x", "y"))))
    reader = EventReader(M, KEYS.for_node("gn"), 10**9)
    key = f"{M.vehicle}/cn/events"
    macs.reset()
    for _ in range(10):
        assert reader.forged(key, os.urandom(4096))
        assert reader.forged(key, os.urandom(len(record)))
        assert not reader.forged(key, record)
    assert macs.n == 0


# -- frames dropped unchecked are in the Data Vector (issue 25) ------------------


def test_a_dn_counts_triggers_dropped_unchecked_in_its_data_vector(macs: _Macs) -> None:
    """Issue 25: the triggers a DN's intake dropped after their header, their
    body's MAC unchecked because the loop's budget was spent (a man in the
    middle splicing the fresh trigger's header onto junk), were kept on the
    intake only. Now the driver hands them to the logic: counted in
    ``dn0_unchecked_frames`` (and in ``dn0_bad_frames``, as refused), and
    the refusal event says how many."""
    intake: TriggerIntake[None] = TriggerIntake(FLIGHT, "dn0", channel(FKEYS, "cn_to_dn0"))
    cn = ControlLogic(FLIGHT, keys=FKEYS.for_node("cn"), epoch=T0)
    dn = DeviceLogic(FLIGHT, "dn0", keys=FKEYS.for_node("dn0"))
    t1 = bytes(cn.begin(1, T0 + FLIGHT.period_ns)[0])
    for _ in range(10):
        assert not intake.admit(Bytes(_spliced(t1)), None)
    size, bad, stale = intake.take_counts()
    dn.refused(size, bad, stale, T0, unchecked=intake.took_unchecked)
    assert dn.dv.get("dn0_bad_frames") == 10
    assert dn.dv.get("dn0_unchecked_frames") == 10 - SPARE
    (ev,) = [e for e in dn.events.drain() if e.id == "bad_frame"]
    assert f"{10 - SPARE} of them dropped after their header, unchecked" in ev.text


def test_a_cn_counts_requests_dropped_unchecked_in_its_data_vector(macs: _Macs) -> None:
    """The same on the control node: command requests whose genuine header
    (a number above every one seen) carries another body, past the budget,
    reach the loop's refusals (``cmd_unchecked``) and ``cn_unchecked_frames``."""
    from zplatform.control.intake import CnRefusals

    up = Uplink(M, KEYS)
    intake = RequestIntake(M, channel(KEYS, "gn_to_cn", Run(T0)), T0, lambda: 0, 16)
    fresh = bytes(up.frame("NOOP", 1, 0, 0.0, 0, T0))
    for _ in range(10):
        assert not intake.admit(Bytes(_spliced(fresh)), None)
    r = CnRefusals()
    intake.take_refusals(r)
    assert (r.cmd_bad, r.cmd_unchecked) == (10, 10 - SPARE)
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    cn.begin(1, T0 + M.period_ns)
    cn.finish((), refused=r)
    assert cn.dv.get("cn_bad_frames") == 10
    assert cn.dv.get("cn_unchecked_frames") == 10 - SPARE
    (ev,) = [e for e in cn.events.drain() if e.id == "bad_frame"]
    assert f"{10 - SPARE} of them dropped after their header, unchecked" in ev.text


def test_a_ground_counts_snapshots_dropped_unchecked(macs: _Macs) -> None:
    """Issue 25, the ground's side: snapshots its intake dropped after their
    header (a genuine, fresh snapshot's header spliced onto junk, past the
    budget) were kept on the intake only. Now the link hands them to the
    ground's logic: ``unchecked`` in its counters (and in ``bad``), and the
    first is an event."""
    from zplatform.ground.logic import GroundLogic

    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    cn.begin(1, T0 + PERIOD)
    fresh = bytes(cn.telemetry())
    intake = TelemetryIntake(M, channel(KEYS, "telemetry", Run(T0)), 8, 10**9)
    for _ in range(10):
        assert not intake.admit(Bytes(_spliced(fresh)), T0 + PERIOD)
    size, bad, stale = intake.take_counts()
    ground = GroundLogic(M, keys=KEYS)
    ground.refused(size, bad, stale, intake.aged, T0, intake.ahead, unchecked=intake.took_unchecked)
    c = ground.counters
    assert (c.bad, c.unchecked) == (10, 10 - SPARE)
    evs = [e for e in ground.events.drain() if e.id == "tm_refused"]
    assert any(f"{10 - SPARE} snapshot(s) dropped after their header" in e.text for e in evs)


def test_a_replayed_recorder_request_never_spends_the_bound_a_grounds_request_needs() -> None:
    """Issue 25, the replayer's door: a captured request replayed within its
    stamp's bound passed the header tag and spent the rate bound (refused
    only by the serving thread, as served before), so the ground's next
    request, at the same instant, was dropped. Now zenoh's callback keeps
    every request it let through while its stamp is within the bound and
    refuses a replay of one there: the bound is the ground's."""
    from tests.payload import FakeQuery
    from zplatform.recorder.format import REQUEST, REQUEST_MAGIC
    from zplatform.recorder.server import REQUEST_BURST

    ch = channel(KEYS, "telemetry")
    assert ch is not None
    server = _recorder_server(mono_ns=lambda: 5 * 10**9)  # one instant: the bound never refills
    try:
        captured = bytes(ch.seal(REQUEST.pack(REQUEST_MAGIC, 7, 1, 5, T0)))
        first = FakeQuery(captured)
        server.on_query(first)
        assert not first.dropped
        flood = [FakeQuery(captured) for _ in range(20 * REQUEST_BURST)]
        for q in flood:
            server.on_query(q)
        genuine = FakeQuery(bytes(ch.seal(REQUEST.pack(REQUEST_MAGIC, 7, 6, 9, T0))))
        server.on_query(genuine)
        assert not genuine.dropped and server.excess == 0
        assert all(q.dropped for q in flood)
    finally:
        server.close()


def test_more_captured_requests_than_a_ring_holds_are_all_refused_while_fresh() -> None:
    """Issue 25: zenoh's callback remembered the last 64 requests, so a
    replayer holding more could cycle them, each replay let through again
    once 64 others had passed. Now a request is remembered until its stamp
    leaves the bound: 200 captured requests (let through one per rate
    period), replayed in turn, are every one refused; once the clock has
    moved past their stamps' bound the stamp refuses them, and the memory
    has forgotten them (it stays bounded)."""
    from tests.payload import FakeQuery
    from zplatform.recorder.format import REQUEST, REQUEST_MAGIC
    from zplatform.recorder.server import REQUEST_EVERY_NS

    ch = channel(KEYS, "telemetry")
    assert ch is not None
    mono, clock = [0], [T0]
    server = _recorder_server(mono_ns=lambda: mono[0])
    server._now = lambda: clock[0]
    server.stop_serving()  # the callback is the point: what it hands off is cleared
    try:
        captured = [
            bytes(ch.seal(REQUEST.pack(REQUEST_MAGIC, 7, 1 + k, 5 + k, T0 + k))) for k in range(200)
        ]
        for c in captured:  # the genuine ground's, one per rate period
            mono[0] += REQUEST_EVERY_NS
            q = FakeQuery(c)
            server.on_query(q)
            assert not q.dropped
            server._pending.clear()
        refused = server.refused
        for _ in range(3):
            for c in captured:
                mono[0] += REQUEST_EVERY_NS
                q = FakeQuery(c)
                server.on_query(q)
                assert q.dropped
        assert server.refused == refused + 600 and server.excess == 0
        assert len(server._seen) == 200
        assert server.last_refusal == "a request seen before (a replay)"
        clock[0] = T0 + 10**9 + 300  # past every stamp's bound
        q = FakeQuery(captured[0])
        server.on_query(q)
        assert q.dropped and "stamped" in (server.last_refusal or "")
        assert len(server._seen) == 0
    finally:
        server.close()
