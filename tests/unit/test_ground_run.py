"""The ground bound to the commander's run (issue 25): the run hello, and
each ground receiver refusing an earlier run's genuine frame on a fresh
ground (telemetry, events, gap-fill replies) with exact counters.

Before, the ground was bound to no run: a replayed earlier run's telemetry
or events reached a ground that had just started (refused only by the clock
bound or ordering, later)."""

from __future__ import annotations

import types
from pathlib import Path
from typing import Any

import pytest

from zplatform import load_mission
from zplatform.control.intake import TelemetryIntake
from zplatform.control.loop import ControlLogic
from zplatform.core.auth import NO_RUN, KeySet, Run, channel
from zplatform.core.events import EV, EventLog, encode_event
from zplatform.ground.gapfill import GapFill
from zplatform.ground.logic import Gap, GroundLogic
from zplatform.recorder.format import REPLY_FRAMES, REPLY_LEN
from zplatform.runtime import clocksync


# Looked up when used, so that the tests that need no new name still run
# (and fail) on the code before the ground was bound to a run.
def ClockResponder(*a: object) -> Any:
    return clocksync.ClockResponder(*a)  # type: ignore[arg-type]


def RunAsker(*a: object) -> Any:
    return clocksync.RunAsker(*a)  # type: ignore[attr-defined]


CONFIGS = Path(__file__).resolve().parents[2] / "configs"
LED = load_mission(CONFIGS / "led_test.yaml")
PERIOD = LED.period_ns
MASTER = b"k" * 32
RUN1 = 1_700_000_000_000_000_000
RUN2 = RUN1 + 3_600_000_000_000  # the run after, an hour later


def _keys(role: str) -> KeySet:
    return KeySet.from_master(LED, MASTER).for_node(role)


def _frames(epoch: int, loops: int) -> list[bytes]:
    """The control node's genuine telemetry of run ``epoch``, loops 1..``loops``."""
    cn = ControlLogic(LED, keys=_keys("cn"), epoch=epoch)
    out = []
    for n in range(1, loops + 1):
        cn.begin(n, epoch + n * PERIOD)
        out.append(bytes(cn.finish([]) or b""))
    return out


# -- the run hello ------------------------------------------------------------------


def test_the_run_hello_teaches_the_commanders_run_once_per_hello() -> None:
    cn = ClockResponder(LED, _keys("cn"), Run(RUN2))
    for role in ("gn", "tool"):  # a read-only tool learns it too (the downlink's key)
        asker = RunAsker(_keys(role))
        assert not asker.run.known
        hello = asker.hello()
        answer = cn.answer(hello, 0, 0)
        assert answer is not None
        assert asker.check(answer) and asker.run.epoch == RUN2 and asker.learned == 1
        # The same answer again (a replay) is refused: one answer per hello.
        assert not asker.check(answer)
        assert (asker.refused_other, asker.refused_bad) == (1, 0)
    assert cn.hellos == 2 and cn.refused == 0


def test_an_earlier_runs_answer_teaches_nothing() -> None:
    """The answer to an earlier hello (an earlier run's, recorded) echoes a
    nonce nobody waits for: refused, the run stays unknown."""
    old_cn = ClockResponder(LED, _keys("cn"), Run(RUN1))
    asker = RunAsker(_keys("gn"))
    recorded = old_cn.answer(asker.hello(), 0, 0)
    assert recorded is not None
    asker.hello()  # a fresh ground asks with a new nonce
    assert not asker.check(recorded)
    assert not asker.run.known and asker.refused_other == 1


def test_a_forged_or_keyless_answer_is_refused_as_bad() -> None:
    asker = RunAsker(_keys("gn"))
    hello = asker.hello()
    stranger = ClockResponder(LED, KeySet.from_master(LED, b"x" * 32), Run(RUN2))
    assert stranger.answer(hello, 0, 0) is None  # the hello's tag does not check there
    nonce = hello[3:19]
    body = clocksync.RUN_ANSWER.pack(b"ZA", 1, nonce, RUN2)
    forged = channel(KeySet.from_master(LED, b"x" * 32), "run_answer", Run(RUN2))
    assert forged is not None
    assert not asker.check(bytes(forged.seal(body)))
    assert not asker.check(body)  # no tag at all
    assert (asker.refused_bad, asker.refused_other) == (2, 0) and not asker.run.known
    # The answer names its run twice (tag and body): they must agree.
    liar = channel(_keys("cn"), "run_answer", Run(RUN2))
    assert liar is not None
    assert not asker.check(bytes(liar.seal(clocksync.RUN_ANSWER.pack(b"ZA", 1, nonce, RUN1))))
    assert asker.refused_other == 1 and not asker.run.known


def test_a_clock_query_is_still_answered_as_one() -> None:
    """The hello shares the clock's queryable; a device node's query is not a hello."""
    from zplatform.runtime.clocksync import ClockLink

    cn = ClockResponder(LED, _keys("cn"), Run(RUN2))
    link = ClockLink(LED, "dn0", KeySet.from_master(LED, MASTER).for_node("dn0"))
    q, nonce = link.query(RUN2)
    reply = cn.answer(q, RUN2, RUN2)
    assert reply is not None and link.check(reply, nonce) is not None
    assert cn.hellos == 0 and link.run.epoch == RUN2


# -- each receiver, on a fresh ground ------------------------------------------------


def test_a_fresh_ground_refuses_every_snapshot_until_it_learns_the_run() -> None:
    run = Run()
    g = GroundLogic(LED, keys=_keys("gn"), run=run)
    assert g.waiting_for_run
    old = _frames(RUN1, 3)
    now = RUN1 + 4 * PERIOD  # within the clock bound: only the run can refuse them
    for f in old:
        assert not g.on_telemetry(f, now)
    c = g.counters  # let go, not counted as refused: the run is not known yet
    assert (c.received, c.bad, c.rejected, g.waited) == (0, 0, 0, 3) and not g.joined
    assert "waiting for the vehicle's run" in g.last_refusal
    run.set(RUN2)  # learned: run 2 commands
    assert not g.waiting_for_run
    for f in old:  # run 1's genuine snapshots, replayed: refused before any decode
        assert not g.on_telemetry(f, now)
    new = _frames(RUN2, 2)
    for n, f in enumerate(new, 1):
        assert g.on_telemetry(f, RUN2 + n * PERIOD)
    c = g.counters
    assert (c.received, c.bad, c.refused["stale"], c.epoch) == (2, 0, 3, RUN2)


def test_the_links_telemetry_intake_counts_another_runs_snapshot_stale() -> None:
    run = Run(RUN2)
    intake = TelemetryIntake(LED, channel(_keys("gn"), "telemetry", run), 8, 10**12)
    from tests.payload import Bytes

    for f in _frames(RUN1, 2):
        assert not intake.admit(Bytes(f), RUN1 + 3 * PERIOD)  # type: ignore[arg-type]
    assert intake.take_counts() == (0, 0, 2) and intake.aged == 2
    assert intake.admit(Bytes(_frames(RUN2, 1)[0]), RUN2 + PERIOD)  # type: ignore[arg-type]


def test_the_links_intake_lets_snapshots_go_uncounted_before_the_run_is_known() -> None:
    from tests.payload import Bytes

    run = Run()
    intake = TelemetryIntake(LED, channel(_keys("gn"), "telemetry", run), 8, 10**12)
    nudged: list[int] = []
    intake.on_other_run = lambda: nudged.append(1)
    assert not intake.admit(Bytes(_frames(RUN2, 1)[0]), RUN2 + PERIOD)  # type: ignore[arg-type]
    assert intake.take_counts() == (0, 0, 0) and intake.waiting == 1 and nudged == [1]


def test_a_fresh_ground_refuses_an_earlier_runs_events_as_stale() -> None:
    run = Run(RUN2)
    g = GroundLogic(LED, keys=_keys("gn"), run=run)
    key = f"{LED.vehicle}/cn/events"

    def record(epoch: int, seq: int) -> bytes:
        log = EventLog("cn")
        log.emit(EV.TM_JOINED, RUN2 + seq, epoch=epoch, loop=seq)
        (e,) = log.drain()
        ch = channel(_keys("cn"), "events_cn", Run(epoch))
        assert ch is not None
        return bytes(ch.seal(encode_event(e)))

    old = record(RUN1, 1)
    assert not g.forged_event(key, old)  # genuine: not counted as forged
    assert g.on_event_bytes(key, old, RUN2 + 10) is None
    assert (g.counters.stale_events, g.counters.bad_events) == (1, 0)
    assert g.on_event_bytes(key, record(RUN2, 2), RUN2 + 10) is not None
    assert (g.counters.stale_events, g.counters.bad_events) == (1, 0)


def test_a_genuine_event_of_the_run_delivered_late_is_taken_once() -> None:
    """Bound to its run, the ground takes an authentic record of that run
    delivered long after its stamp (a receiver starved for a second, beside
    a CPU hog: the console lost a state change so) once; a replay of it is
    refused by its number, and a stamp beyond the bound ahead is still
    refused (taken, it would lock every later genuine record out)."""
    run = Run(RUN2)
    g = GroundLogic(LED, keys=_keys("gn"), run=run)
    key = f"{LED.vehicle}/cn/events"
    ch = channel(_keys("cn"), "events_cn", Run(RUN2))
    assert ch is not None

    def record(seq: int, t_ns: int) -> bytes:
        from zplatform.core.events import Event

        return bytes(ch.seal(encode_event(Event("cn", seq, t_ns, 2, "state_change", "x"))))

    late = record(1, RUN2)
    now = RUN2 + 5 * g.max_age_ns  # delivered five bounds after its stamp
    assert g.on_event_bytes(key, late, now) is not None
    assert g.on_event_bytes(key, late, now) is None  # its replay
    assert g.on_event_bytes(key, record(2, now + g.max_age_ns + 1), now) is None  # ahead
    assert g.on_event_bytes(key, record(3, now), now) is not None
    assert (g.counters.stale_events, g.counters.bad_events) == (2, 0)


def test_a_gap_fill_reply_of_an_earlier_run_is_refused() -> None:
    written: list[int] = []
    run = Run(RUN2)
    fill = GapFill(LED, _keys("gn"), EventLog("gn"), lambda rx, _dv: written.append(rx), run=run)
    g = GroundLogic(LED, keys=_keys("gn"), run=run)
    g.gaps.append(Gap(RUN1, 1, 2))  # a gap of run 1 queued
    fill.snapshot(g, RUN2)
    req = fill.take_request(RUN2)
    assert req is not None
    rid = req[0]
    old = _frames(RUN1, 2)
    payload = bytes([REPLY_FRAMES]) + b"".join(REPLY_LEN.pack(len(f)) + f for f in old)
    fill.on_reply(rid, payload)
    assert fill.refused == 2 and fill.filled == 0


def test_requests_are_tagged_in_the_learned_run() -> None:
    from zplatform.core.auth import Channel

    run = Run()
    g = GroundLogic(LED, keys=_keys("gn"), run=run)
    run.set(RUN2)
    f = _frames(RUN2, 1)[0]
    assert g.on_telemetry(f, RUN2 + PERIOD)
    g.command("NOOP", now_ns=RUN2 + PERIOD)
    (req,) = g.take_requests()
    assert Channel.run_of(req) == RUN2 != NO_RUN


def test_a_link_without_authentication_is_bound_to_no_run() -> None:
    g = GroundLogic(LED, keys=None, run=None)
    assert not g.waiting_for_run


# -- the command channel ----------------------------------------------------------


def _request(tag_run: int, data_run: int, seq: int = 1) -> bytes:
    """A NOOP request naming ``data_run`` in its data, tagged in ``tag_run``
    with the uplink's genuine key (an insider's frame, or one recorded)."""
    from zplatform.control.uplink import Uplink

    frame = Uplink(LED, None).frame("NOOP", seq, 0, 0.0, RUN2, data_run)
    ch = channel(_keys("gn"), "gn_to_cn", Run(tag_run))
    assert ch is not None
    return bytes(ch.seal(frame))


def test_the_control_node_refuses_a_request_tagged_in_another_run_before_decoding() -> None:
    cn = ControlLogic(LED, keys=_keys("cn"), epoch=RUN2)
    cn.begin(1, RUN2 + PERIOD)
    cn.finish([_request(RUN1, RUN2)])  # its data names this run; its tag another
    assert int(cn.dv.get("cn_cmd_rejects")) == 1
    status = cn.dv.handle("cn_cmd_reject_status")
    assert status.spec.name_of(status.get()) == "REJECTED_EPOCH"
    assert int(cn.dv.get("cn_cmd_seq")) == 0  # no number consumed, nothing applied
    cn.begin(2, RUN2 + 2 * PERIOD)
    cn.finish([_request(RUN2, RUN2, 2)])  # tagged in this run: taken
    assert int(cn.dv.get("cn_cmd_seq")) == 2 and int(cn.dv.get("cn_cmd_rejects")) == 1


def test_the_request_intake_counts_a_request_of_another_run_stale() -> None:
    from tests.payload import Bytes
    from zplatform.control.intake import RequestIntake

    ch = channel(_keys("cn"), "gn_to_cn", Run(RUN2))
    intake = RequestIntake(LED, ch, RUN2, lambda: 0, 8)
    assert not intake.admit(Bytes(_request(RUN1, RUN2)), None)  # type: ignore[arg-type]
    assert intake.take_counts() == (0, 0, 1)
    assert intake.admit(Bytes(_request(RUN2, RUN2)), None)  # type: ignore[arg-type]
    # Tagged in no run (a ground bound to none): its data's run is checked.
    assert intake.admit(Bytes(_request(NO_RUN, RUN2, 2)), None)  # type: ignore[arg-type]
    assert not intake.admit(Bytes(_request(NO_RUN, RUN1, 3)), None)  # type: ignore[arg-type]
    assert intake.take_counts() == (0, 0, 1)


# -- the ground's zenoh link, fresh -------------------------------------------------


@pytest.fixture
def link(tmp_path: Path) -> Any:
    from zplatform.ground.link import GroundLink
    from zplatform.runtime.transport import rewrite_endpoints

    rewrite_endpoints(CONFIGS / "led_test.yaml", tmp_path / "led.yaml")
    m = load_mission(tmp_path / "led.yaml")
    gl = GroundLink(m, keys=KeySet.from_master(m, MASTER).for_node("gn"))
    yield gl
    gl.close()


def test_a_fresh_ground_link_takes_no_snapshot_of_a_run_it_did_not_learn(link: Any) -> None:
    """An earlier run's genuine snapshot, stamped within the clock bound
    (a run that ended a moment ago), reaches a ground that just started:
    let go, never shown (before: followed as the vehicle's run)."""
    from tests.payload import Bytes

    now = link.clock.now_ns()
    old = ControlLogic(link.mission, keys=_keys("cn"), epoch=now - 10 * PERIOD)
    old.begin(9, now - PERIOD)
    frame = bytes(old.finish([]) or b"")
    link._on_telemetry(types.SimpleNamespace(payload=Bytes(frame)))  # as zenoh's thread
    assert link.next(0) is None
    c = link.logic.counters
    assert (c.received, c.bad, c.rejected) == (0, 0, 0) and not link.logic.joined
    assert link.waiting_for_run and link._tm.waiting == 1
    assert "waiting for the vehicle's run" in link.why_no_telemetry(1.0)


def test_a_ground_link_that_learned_the_run_refuses_an_earlier_runs_snapshot_stale(
    link: Any,
) -> None:
    from tests.payload import Bytes

    now = link.clock.now_ns()
    old = ControlLogic(link.mission, keys=_keys("cn"), epoch=now - 10 * PERIOD)
    new = ControlLogic(link.mission, keys=_keys("cn"), epoch=now - 5 * PERIOD)
    link.run.set(new.auth_run.epoch)  # as the commander's answer to its run hello
    for cn, loop in ((old, 9), (new, 4)):
        cn.begin(loop, now - PERIOD)
        frame = bytes(cn.finish([]) or b"")
        link._on_telemetry(types.SimpleNamespace(payload=Bytes(frame)))
    assert link.next(0) is not None
    c = link.logic.counters
    assert (c.received, c.bad, c.refused["stale"], c.epoch) == (1, 0, 1, new.auth_run.epoch)
    assert link._relearn  # a genuine snapshot of another run: ask the run again (<= 1/s)


def test_a_fresh_ground_link_refuses_an_earlier_runs_event(link: Any) -> None:
    from tests.payload import Bytes

    now = link.clock.now_ns()
    log = EventLog("cn")
    log.emit(EV.TM_JOINED, now, epoch=RUN1, loop=1)
    (e,) = log.drain()
    ch = channel(_keys("cn"), "events_cn", Run(now - 10 * PERIOD))
    assert ch is not None
    key = f"{link.mission.vehicle}/cn/events"
    sample = types.SimpleNamespace(payload=Bytes(bytes(ch.seal(encode_event(e)))), key_expr=key)
    shown: list[object] = []
    link.on_event = shown.append
    link._on_event(sample)
    link.next(0)
    c = link.logic.counters  # held, never shown: the run is not known yet
    assert (c.stale_events, c.bad_events, shown) == (0, 0, [])
    link.run.set(now - 5 * PERIOD)  # learned: a later run commands
    link._on_event(sample)
    link.next(0)
    link.next(0)
    c = link.logic.counters  # the held record and the new copy: both of another run
    assert (c.stale_events, c.bad_events, shown) == (2, 0, [])


def test_an_event_sent_before_the_link_learned_the_run_is_shown_once_it_does(
    link: Any,
) -> None:
    """An event of the run that arrives before the link learned the run (a
    short script's script_done, which ends `up`) waits in its bounded
    mailbox and is taken once the run is known: never lost."""
    from tests.payload import Bytes

    now = link.clock.now_ns()
    run = now - 5 * PERIOD
    log = EventLog("cn")
    log.emit(EV.TM_JOINED, now, epoch=RUN1, loop=1)
    (e,) = log.drain()
    ch = channel(_keys("cn"), "events_cn", Run(run))
    assert ch is not None
    key = f"{link.mission.vehicle}/cn/events"
    sample = types.SimpleNamespace(payload=Bytes(bytes(ch.seal(encode_event(e)))), key_expr=key)
    shown: list[object] = []
    link.on_event = shown.append
    link._on_event(sample)
    link.next(0)
    assert shown == [] and link.waiting_for_run
    link.run.set(run)  # learned: this run commands
    link.next(0)
    assert len(shown) == 1 and link.logic.counters.stale_events == 0


def test_a_ground_link_follows_a_restarted_control_node_asking_at_most_once_a_second(
    link: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The control node restarted with a new run: its genuine snapshots are
    refused until the link asked again (a run hello, at most one per
    RELEARN_S however many such snapshots come) and took the answer."""
    import time

    from tests.payload import Bytes
    from zplatform.ground import link as link_mod

    asked: list[bytes] = []
    monkeypatch.setattr(link_mod, "ask", lambda *a, **kw: asked.append(kw["payload"]))
    now = link.clock.now_ns()
    old_run, new_run = now - 10 * PERIOD, now - 5 * PERIOD
    link.run.set(old_run)  # learned before the restart
    link._last_hello = time.monotonic()  # ... just now
    cn = ControlLogic(link.mission, keys=_keys("cn"), epoch=new_run)
    for loop in (1, 2, 3):
        cn.begin(loop, now - PERIOD + loop)
        link._on_telemetry(types.SimpleNamespace(payload=Bytes(bytes(cn.finish([]) or b""))))
    assert link.next(0) is None and link.logic.counters.refused["stale"] == 3
    assert asked == []  # within RELEARN_S of the last hello: not yet
    link._last_hello -= link_mod.RELEARN_S
    link._learn_run()
    link._learn_run()
    assert len(asked) == 1  # one hello for the three snapshots
    answer = ClockResponder(link.mission, _keys("cn"), Run(new_run)).answer(asked[0], 0, 0)
    link._run_box.put(answer)
    assert link.next(0) is None  # the answer taken (the caller's thread): bound to it
    cn.begin(4, now)
    link._on_telemetry(types.SimpleNamespace(payload=Bytes(bytes(cn.finish([]) or b""))))
    assert link.next(0) is not None  # the new run followed
    assert link.run.epoch == new_run and link.logic.counters.epoch == new_run


def test_a_link_that_never_learned_a_run_says_hello_ten_times_as_often(
    link: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The defect (`up`'s summary empty when the control node died within a
    second of starting: its link's first hello found no one, and the next
    came a second later): until the link learns its first run it says
    hello every FIRST_HELLO_S; once it has, at most once a RELEARN_S."""
    import time

    from zplatform.ground import link as link_mod

    asked: list[bytes] = []
    monkeypatch.setattr(link_mod, "ask", lambda *a, **kw: asked.append(kw["payload"]))
    assert not link.run.known
    link._last_hello = time.monotonic() - 1.5 * link_mod.FIRST_HELLO_S
    link._learn_run()
    link._learn_run()
    assert len(asked) == 1  # one FIRST_HELLO_S after the last: another, once
    link.run.set(link.clock.now_ns() - 5 * PERIOD)  # learned
    link._relearn = True  # then a snapshot of another run
    link._last_hello = time.monotonic() - 1.5 * link_mod.FIRST_HELLO_S
    link._learn_run()
    assert len(asked) == 1  # learned once: RELEARN_S paces the hellos
    link._last_hello -= link_mod.RELEARN_S
    link._learn_run()
    assert len(asked) == 2


def test_a_flood_of_junk_run_answers_never_pushes_the_commanders_out(
    link: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 25: the link's reply callback put every reply to its hello in
    a bounded mailbox (RUN_ANSWERS) unchecked, so a keyless queryable on
    the clock key answering with junk (or with replayed answers to earlier
    hellos) after the commander pushed the genuine answer out, and the
    ground never learned the run. Now the callback screens each reply (its
    header tag and the nonce echoed) before the hand-off: the junk and the
    replays are refused there, counted, and the commander's answer is taken."""
    from tests.payload import Bytes
    from zplatform.ground import link as link_mod

    asked: list[bytes] = []
    handlers: list[Any] = []

    def ask(*a: Any, **kw: Any) -> None:
        asked.append(kw["payload"])
        handlers.append(a[2])  # the replies' callback, as zenoh calls it

    monkeypatch.setattr(link_mod, "ask", ask)
    link._last_hello -= 10.0
    link._learn_run()
    assert len(asked) == 1 and not link.run.known
    on_reply = handlers[0]
    now = link.clock.now_ns()
    responder = ClockResponder(link.mission, _keys("cn"), Run(now))
    old_answer = responder.answer(clocksync.RunAsker(_keys("gn")).hello(), 0, 0)
    genuine = responder.answer(asked[0], 0, 0)
    assert genuine is not None and old_answer is not None

    def reply(data: bytes) -> Any:
        return types.SimpleNamespace(ok=types.SimpleNamespace(payload=Bytes(data)))

    on_reply(reply(genuine))
    junk = [genuine[:-24] + bytes(24), old_answer] * (2 * link_mod.RUN_ANSWERS)
    for data in junk:
        on_reply(reply(data))
    link._learn_run()  # the caller's thread takes what came
    assert link.run.known and link.run.epoch == now
    assert link._asker.screened == len(junk)
