"""The intake (zplatform.control.intake): what arrives is refused in constant time
and counted, what passes waits in a bounded mailbox where the newest valid
frame wins; the CN takes replies only from the DN's session and learns a
restarted DN's; the loop counts what the intake refused, records it and
replays it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.faults.peers import peer_config
from tests.payload import Bytes
from zplatform.config.codes import CommandStatus
from zplatform.control.commands import (
    SEQ_WINDOW,
    CommandHandler,
    request_refusal,
    request_refusal_detail,
)
from zplatform.control.fencing import ASK, ask_frame, new_nonce
from zplatform.control.handoff import Waker
from zplatform.control.intake import (
    BACKLOG,
    CnRefusals,
    ProbeIntake,
    RefusalLog,
    ReplyCheck,
    RequestIntake,
    TelemetryIntake,
    TriggerIntake,
)
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import Uplink
from zplatform.core.auth import KEY_ENV, TAG_LEN, KeySet, channel
from zplatform.core.codec import decode_frame, encode_frame
from zplatform.mission.load import decode_mission, load_mission
from zplatform.runtime.sync import REPIN_AFTER, ControlSync
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import replay
from zplatform.sim.replay_recording import Recorder, RecordReader

ROOT = Path(__file__).resolve().parents[2]
LED = ROOT / "configs" / "led_test.yaml"
M = load_mission(LED)
# Every link of the mission, from the suite's master key (tests/conftest.py):
# what a replay loads without a key file.
KEYS = KeySet.from_master(M, bytes.fromhex(os.environ[KEY_ENV]))
PERIOD = M.period_ns
T0 = 1_700_000_000_000_000_000


def trigger(loop: int, t: int, dn: int = 0) -> bytes:
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    return bytes(cn.begin(loop, t)[dn])


# -- the DN's trigger intake --------------------------------------------------


def test_a_dn_admits_only_authentic_triggers_newer_than_every_one_before() -> None:
    ch = channel(KEYS, "cn_to_dn0")
    intake: TriggerIntake[str] = TriggerIntake(M, "dn0", ch)
    t1 = trigger(1, T0 + PERIOD)
    t2 = trigger(2, T0 + 2 * PERIOD)
    copies = Bytes.copies
    assert not intake.admit(Bytes(b"x" * 5000), "huge")  # refused for its size, unread
    assert not intake.admit(Bytes(b""), "empty")
    assert Bytes.copies == copies
    assert not intake.admit(Bytes(t1[:-1] + bytes([t1[-1] ^ 1])), "forged")  # bad tag
    assert not intake.admit(Bytes(trigger(1, T0 + PERIOD, dn=1)), "dn1's")  # another channel
    assert intake.admit(Bytes(t1), "q1")
    assert not intake.admit(Bytes(t1), "q1 replayed")
    assert intake.admit(Bytes(t2), "q2")
    assert not intake.admit(Bytes(t1), "q1 replayed late")
    assert intake.take_counts() == (2, 2, 2)
    assert intake.take_counts() == (0, 0, 0)
    box = intake.box
    assert box is not None
    assert [h for h, _ in (box.pop(), box.pop())] == ["q1", "q2"]  # type: ignore[misc]


def test_a_dn_keeps_a_bounded_backlog_of_valid_triggers() -> None:
    intake: TriggerIntake[int] = TriggerIntake(M, "dn0", channel(KEYS, "cn_to_dn0"))
    for n in range(1, 20):
        assert intake.admit(Bytes(trigger(n, T0 + n * PERIOD)), n)
    box = intake.box
    assert box is not None and box.dropped == 19 - BACKLOG
    out: list[tuple[int, bytes]] = []
    box.drain(out)
    assert [h for h, _ in out] == list(range(20 - BACKLOG, 20))  # the newest, in order


def test_a_dn_takes_its_own_trigger_from_a_sync_bundle() -> None:
    text = LED.read_text() + "\ntransport: {sync_query: wildcard}\n"
    m = decode_mission(text)
    cn = ControlLogic(m, keys=KEYS, epoch=T0)
    from zplatform.core.codec import BundleEncoder

    bundle = bytes(BundleEncoder().pack(cn.begin(1, T0 + PERIOD)))
    for i, dn in enumerate(m.device_nodes):
        intake: TriggerIntake[None] = TriggerIntake(m, dn, channel(KEYS, f"cn_to_{dn}"))
        assert intake.admit(Bytes(bundle), None), dn
        assert not intake.admit(Bytes(bundle), None)  # the same bundle again: a replay
        assert intake.take_counts() == (0, 0, 1), i


def test_without_authentication_only_the_size_is_checked() -> None:
    text = LED.read_text() + "\nsecurity: {auth: false}\n"
    m = decode_mission(text)
    intake: TriggerIntake[None] = TriggerIntake(m, "dn0", None)
    frame = bytes(ControlLogic(m).begin(1, T0)[0])
    assert intake.admit(Bytes(frame), None) and intake.admit(Bytes(frame), None)
    assert not intake.admit(Bytes(b"x" * 5000), None)
    assert intake.take_counts() == (1, 0, 0)


# -- the CN's request intake ------------------------------------------------------


def test_request_refusal_is_the_command_handlers_rule() -> None:
    for epoch, seq, last in [
        (7, 1, 0),
        (7, 0, 0),
        (8, 5, 0),
        (7, 5, 5),
        (7, 4, 5),
        (7, 6, 5),
        (7, 5 + SEQ_WINDOW, 5),
        (7, 6 + SEQ_WINDOW, 5),
    ]:
        cn = ControlLogic(M, keys=KEYS, epoch=7)
        cn.commands._last_seq = last
        got = cn.commands.refusal(epoch, seq)
        assert (got[0] if got else 0) == request_refusal(epoch, seq, 7, last), (epoch, seq, last)


@pytest.mark.parametrize(
    ("epoch", "seq", "last", "status", "detail"),
    [
        (7, 1, 0, 0, None),  # the first number: any above 0
        (7, 0, 0, "REJECTED_REPLAY", "number 0 is not above the last one seen (0)"),
        (7, 6, 5, 0, None),
        (7, 5, 5, "REJECTED_REPLAY", "number 5 is not above the last one seen (5)"),
        (7, 4, 5, "REJECTED_REPLAY", "number 4 is not above the last one seen (5)"),
        (7, 5 + SEQ_WINDOW, 5, 0, None),  # the longest jump allowed
        (
            7,
            6 + SEQ_WINDOW,
            5,
            "REJECTED_REPLAY",
            f"number {6 + SEQ_WINDOW} jumps more than {SEQ_WINDOW} past the last one (5)",
        ),
        (
            8,
            6,
            5,
            "REJECTED_EPOCH",
            "epoch 8 is not this control node's (7): a request for an earlier run",
        ),
        (8, 4, 5, "REJECTED_EPOCH", None),  # another run first, whatever its number
    ],
)
def test_the_request_number_rule_table(
    epoch: int, seq: int, last: int, status: str | int, detail: str | None
) -> None:
    """The one request-number rule (zplatform.control.commands.request_refusal) on a
    CN of run 7: its status, and the detail its refusal event gives."""
    want = CommandStatus[status] if isinstance(status, str) else status
    assert request_refusal(epoch, seq, 7, last) == want
    got = request_refusal_detail(epoch, seq, 7, last)
    if not want:
        assert got is None
    else:
        assert got is not None and got[0] == want
        if detail is not None:
            assert got[1] == detail


def test_the_loop_checks_a_requests_number_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """One request frame, one application of the number rule: the loop
    admits it (CommandHandler.admit) and the command handler's step does
    not check it again (it did, once more, for the frame the loop chose)."""
    calls: list[tuple[int, int]] = []
    rule = CommandHandler.refusal

    def counted(self: CommandHandler, epoch: int, seq: int) -> tuple[int, str] | None:
        calls.append((epoch, seq))
        return rule(self, epoch, seq)

    monkeypatch.setattr(CommandHandler, "refusal", counted)
    cn = ControlLogic(M, keys=KEYS, epoch=77)
    up = Uplink(M, KEYS)
    cn.begin(1, T0)
    cn.finish([bytes(up.frame("NOOP", 1, 0, 0.0, 0, 77))])
    assert cn.dv.get_name("cn_cmd_status") == "ACCEPTED" and cn.dv.get("cn_cmd_seq") == 1
    assert calls == [(77, 1)]
    cn.begin(2, T0 + PERIOD)
    cn.finish([bytes(up.frame("NOOP", 1, 0, 0.0, 0, 77))])  # a replay: refused once
    assert calls == [(77, 1), (77, 1)]
    assert cn.dv.get("cn_cmd_rejects") == 1 and cn.dv.get("cn_cmd_seq") == 1


def test_a_replayed_request_never_reaches_the_inbox() -> None:
    up = Uplink(M, KEYS)
    last = [0]
    intake = RequestIntake(M, channel(KEYS, "gn_to_cn"), 77, lambda: last[0], 16)

    def req(cmd: str, seq: int, epoch: int = 77) -> Bytes:
        return Bytes(bytes(up.frame(cmd, seq, 0, 0.0, 0, epoch)))

    assert intake.admit(req("NOOP", 1), None)
    assert not intake.admit(req("NOOP", 1), None)  # itself again
    last[0] = 1  # the loop took it
    for _ in range(100):
        assert not intake.admit(req("LAUNCH", 1), None)
    assert not intake.admit(req("NOOP", 9, epoch=76), None)  # an earlier run's
    assert not intake.admit(req("NOOP", 2 + SEQ_WINDOW), None)  # too far ahead
    assert intake.admit(req("NOOP", 2), None)  # the operator's next: in
    assert not intake.admit(Bytes(b"\x00" * 60), None)  # bad tag
    assert intake.take_counts() == (0, 1, 103)
    # The refusal shown is the one with the highest number.
    assert intake.reported == (CommandStatus.REJECTED_REPLAY, 2 + SEQ_WINDOW)
    box = intake.box
    assert box is not None and len(box) == 2 and box.dropped == 0


def test_the_loop_refuses_replays_before_choosing_so_a_fresh_request_wins() -> None:
    """Without any intake (the lockstep runner, a replay), the loop itself
    refuses a replayed frame before it picks one: the fresh one is applied
    whatever came after it."""
    cn = ControlLogic(M, keys=KEYS, epoch=77)
    up = Uplink(M, KEYS)
    launch = bytes(up.frame("LAUNCH", 1, 0, 0.0, 0, 77))
    cn.begin(1, T0)
    cn.finish([launch])
    assert cn.dv.get_name("cn_state") == "B"
    noop = bytes(up.frame("NOOP", 2, 0, 0.0, 0, 77))
    cn.begin(2, T0 + PERIOD)
    cn.finish([noop, launch, launch])  # the fresh one, then two replays of #1
    assert cn.dv.get("cn_cmd_seq") == 2 and cn.dv.get_name("cn_cmd_status") == "ACCEPTED"
    assert cn.dv.get("cn_cmd_rejects") == 2 and cn.dv.get("cn_cmd_reject_seq") == 1
    assert cn.dv.get_name("cn_cmd_reject_status") == "REJECTED_REPLAY"
    assert cn.dv.get("cn_cmd_dropped") == 0


# -- the ground's telemetry intake ------------------------------------------------


def test_the_ground_admits_only_telemetry_newer_than_it_has() -> None:
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    frames = []
    for n in (1, 2, 3):
        cn.begin(n, T0 + n * PERIOD)
        frames.append(bytes(cn.telemetry()))
    intake = TelemetryIntake(M, channel(KEYS, "telemetry"), 8, 10**9)
    rx = [T0 + n * PERIOD for n in (1, 2, 3)]  # received as stamped
    assert intake.admit(Bytes(frames[1]), rx[1])
    assert not intake.admit(Bytes(frames[0]), rx[1])  # older
    assert not intake.admit(Bytes(frames[1]), rx[1])  # again
    assert not intake.admit(Bytes(frames[2][:-1] + bytes([frames[2][-1] ^ 1])), rx[2])  # bad tag
    assert intake.admit(Bytes(frames[2]), rx[2])
    assert intake.take_counts() == (0, 1, 2)


# -- the CN's replies: only from the DN's session ---------------------------------


class _Id:
    def __init__(self, zid: object) -> None:
        self.zid = zid


class _Ok:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = zenoh.ZBytes(payload)


class _Err:
    def __init__(self, text: bytes) -> None:
        self.payload = zenoh.ZBytes(text)


class _Reply:
    def __init__(self, zid: object, ok: _Ok | None = None, err: _Err | None = None) -> None:
        self.replier_id = _Id(zid)
        self.ok = ok
        self.err = err


@pytest.fixture
def sync() -> Any:
    session = zenoh.open(peer_config())
    cs = ControlSync(
        session,
        KeySpace(M.vehicle),
        M.device_nodes,
        2_000_000,
        0.01,
        checks=[ReplyCheck(M, dn, channel(KEYS, f"{dn}_to_cn")) for dn in M.device_nodes],
        wildcard=True,
    )
    yield cs
    cs.close()
    session.close()


def _drain(cs: ControlSync) -> list[tuple[int, object]]:
    out = []
    while not cs._q.empty():
        out.append(cs._q.get_nowait())
    return out


def _reply(loop: int, t: int, dn: str = "dn0", keys: KeySet | None = KEYS) -> bytes:
    cn = ControlLogic(M, keys=keys, epoch=T0)
    d = DeviceLogic(M, dn, keys=keys)
    i = M.device_nodes.index(dn)
    out = d.trigger(bytes(cn.begin(loop, t)[i]), t)
    assert out is not None
    return bytes(out)


def _expect(cs: ControlSync, loop: int, t: int) -> None:
    for c in cs._checks:
        c.expect(loop, t)


def test_the_cn_takes_replies_only_from_the_session_that_proved_it_is_the_dn(sync: Any) -> None:
    cs: ControlSync = sync
    key = "rocket/dn0/to_cn"
    _expect(cs, 1, T0 + PERIOD)
    good = _reply(1, T0 + PERIOD)
    # Before dn0 answered, its name on an error pins nothing on it.
    cs._handoff_any(_Reply("DN0", err=_Err(b"dn0: bad frame")))
    # A rogue's junk, a replay of an older loop's reply: checked, refused.
    cs._handoff_any(_Reply("EVIL", ok=_Ok(key, b"\x94" * 40)))
    cs._handoff_any(_Reply("EVIL", ok=_Ok(key, _reply(0, T0))))
    assert _drain(cs) == []
    cs._handoff_any(_Reply("DN0", ok=_Ok(key, good)))  # authentic, this loop: dn0's now
    assert _drain(cs) == [(0, good)]
    cs._watch([True, False, False])
    # From now on anyone else is ignored unread, junk or authentic.
    for _ in range(100):
        cs._handoff_any(_Reply("EVIL", ok=_Ok(key, good)))
        cs._handoff_any(_Reply("EVIL", err=_Err(b"dn0: forged")))
    assert _drain(cs) == []
    cs._handoff_any(_Reply("DN0", err=_Err(b"dn0: stale")))
    cs._handoff_any(_Reply("DN0", err=_Err(b"Timeout")))  # zenoh's own: not a reply
    assert _drain(cs) == [(0, None)]
    cs._handoff_any(_Reply("EVIL", ok=_Ok("rocket/gn/to_cn", good)))  # no DN's key
    r = CnRefusals()
    cs.take_refusals(r)
    assert (r.reply_size, r.reply_bad, r.reply_stale, r.reply_foreign) == (0, 1, 1, 202)


def test_a_restarted_dn_is_accepted_once_the_one_known_goes_quiet(sync: Any) -> None:
    cs: ControlSync = sync
    key = "rocket/dn0/to_cn"
    _expect(cs, 1, T0 + PERIOD)
    cs._handoff_any(_Reply("OLD", ok=_Ok(key, _reply(1, T0 + PERIOD))))
    cs._watch([True, False, False])
    assert len(_drain(cs)) == 1
    # dn0 restarts: a new session, authentic replies; ignored while the old
    # one is not yet quiet for REPIN_AFTER loops ...
    for n in range(2, 2 + REPIN_AFTER):
        t = T0 + n * PERIOD
        _expect(cs, n, t)
        cs._handoff_any(_Reply("NEW", ok=_Ok(key, _reply(n, t))))
        assert _drain(cs) == []
        cs._watch([False, False, False])
    # ... then the first authentic reply for the loop asked makes it dn0's.
    n = 2 + REPIN_AFTER
    _expect(cs, n, T0 + n * PERIOD)
    cs._handoff_any(_Reply("NEW", ok=_Ok(key, _reply(n, T0 + n * PERIOD))))
    assert [i for i, _ in _drain(cs)] == [0]
    cs._watch([True, False, False])
    cs._handoff_any(_Reply("OLD", ok=_Ok(key, _reply(n, T0 + n * PERIOD))))
    assert _drain(cs) == []  # the old session is nobody now


# -- the loop counts, records and replays what the intake refused -----------------


def test_refusals_are_counted_evented_once_a_second_recorded_and_replayed(
    tmp_path: Path,
) -> None:
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    rec = Recorder(tmp_path / "rec", M, LED, cn.dv)
    cn.recorder = rec
    r = CnRefusals()
    for n in range(1, 201):  # two seconds of a flood
        cn.begin(n, T0 + n * PERIOD)
        r.clear()
        r.reply_foreign, r.cmd_bad, r.cmd_stale = 60, 1, 30
        r.cmd_status, r.cmd_seq = CommandStatus.REJECTED_REPLAY, 4
        cn.finish((), refused=r)
    for n in range(201, 301):  # a quiet second: the rest goes out
        cn.begin(n, T0 + n * PERIOD)
        cn.finish((), refused=CnRefusals())
    rec.close()
    assert cn.dv.get("cn_bad_frames") == 200 * 61
    assert cn.dv.get("cn_cmd_rejects") == 200 * 31
    assert cn.dv.get("cn_cmd_reject_seq") == 4
    assert cn.dv.get_name("cn_cmd_reject_status") == "REJECTED_REPLAY"
    events = cn.events.drain()
    bad = [e for e in events if e.id == "bad_frame"]
    rejected = [e for e in events if e.id == "cmd_rejected"]
    assert 2 <= len(bad) <= 4 and 2 <= len(rejected) <= 4  # not 200 of each
    assert sum(int(e.text.split()[0]) for e in bad) == 200 * 61
    (loop,) = [x for x in RecordReader(tmp_path / "rec").loops() if x.loop == 7]
    assert CnRefusals().set_fields(loop.refused).reply_foreign == 60
    res = replay(tmp_path / "rec", LED)  # the keys from the suite's master key
    assert res.identical and res.loops == 300, res.first_difference


def test_frames_dropped_unchecked_are_counted_recorded_and_replayed(tmp_path: Path) -> None:
    """Issue 25: the frames an intake dropped after their header for want of
    body-MAC budget were not in the Data Vector. Now the loop's refusals
    carry them (``reply_unchecked``, ``cmd_unchecked``), ``cn_unchecked_frames``
    counts them, the recording keeps them, and a replay is identical."""
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    rec = Recorder(tmp_path / "rec", M, LED, cn.dv)
    cn.recorder = rec
    r = CnRefusals()
    for n in range(1, 101):
        cn.begin(n, T0 + n * PERIOD)
        r.clear()
        r.reply_bad, r.reply_unchecked, r.cmd_bad, r.cmd_unchecked = 5, 3, 4, 2
        cn.finish((), refused=r)
    rec.close()
    assert cn.dv.get("cn_bad_frames") == 100 * 9
    assert cn.dv.get("cn_unchecked_frames") == 100 * 5
    bad = [e for e in cn.events.drain() if e.id == "bad_frame"]
    assert bad and all("dropped after their header, unchecked" in e.text for e in bad)
    (loop,) = [x for x in RecordReader(tmp_path / "rec").loops() if x.loop == 7]
    got = CnRefusals().set_fields(loop.refused)
    assert (got.reply_unchecked, got.cmd_unchecked) == (3, 2)
    res = replay(tmp_path / "rec", LED)
    assert res.identical and res.loops == 100, res.first_difference


def test_a_dn_counts_refused_queries_and_events_them_once_a_second() -> None:
    dn = DeviceLogic(M, "dn0", keys=KEYS)
    for k in range(300):
        dn.refused(40, 10, 10, T0 + k * PERIOD)
    dn.refused(0, 0, 0, T0 + 400 * PERIOD)
    assert dn.dv.get("dn0_bad_frames") == 300 * 60
    ev = [e for e in dn.events.drain() if e.id == "bad_frame"]
    assert 3 <= len(ev) <= 5
    assert sum(int(e.text.split()[0]) for e in ev) == 300 * 60


def test_a_refusal_log_events_the_first_at_once_then_once_a_period() -> None:
    log = RefusalLog(2, period_ns=100)
    assert log.add(0, 0, 0) is None
    assert log.add(5, 1, 0) == [1, 0]
    assert log.add(50, 2, 3) is None
    assert log.add(104, 0, 0) is None
    assert log.add(105, 0, 1) == [2, 4]
    assert log.add(500, 0, 0) is None


# -- freshness bounded ahead: a stamp at the end of time locks nobody out ------------

FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
FKEYS = KeySet.from_master(FLIGHT, bytes.fromhex(os.environ[KEY_ENV]))
I64_MAX = (1 << 63) - 1


def test_a_trigger_stamped_beyond_the_clock_bound_is_refused_and_locks_nobody_out() -> None:
    """An authentic trigger stamped further ahead of the DN's clock than the
    clock bound and a period (a key holder's, or a stepped CN clock) is
    refused as stale, never the newest: the next genuine trigger is taken."""
    now = [T0]
    intake: TriggerIntake[None] = TriggerIntake(
        M, "dn0", channel(KEYS, "cn_to_dn0"), lambda: now[0]
    )
    cn = ControlLogic(M, keys=KEYS.for_node("cn"), epoch=T0)
    bound = round(M.clock.offset_bound_ms * 1e6) + PERIOD
    assert intake.admit(Bytes(bytes(cn.begin(1, T0)[0])), None)
    ahead = bytes(cn.begin(2, T0 + bound + 1)[0])  # genuine, just beyond the bound
    assert not intake.admit(Bytes(ahead), None)
    edge = bytes(cn.begin(3, T0 + bound)[0])  # at the bound: believable
    assert intake.admit(Bytes(edge), None)
    ch = channel(KEYS, "cn_to_dn0")
    assert ch is not None
    f = decode_frame(edge[:-TAG_LEN])
    end = bytes(ch.seal(encode_frame(f.layout_id, 4, I64_MAX, bytes(f.data))))
    assert not intake.admit(Bytes(end), None)
    now[0] = T0 + 2 * bound
    assert intake.admit(Bytes(bytes(cn.begin(5, T0 + 2 * bound)[0])), None)
    assert intake.take_counts() == (0, 0, 2)


def test_a_probe_question_stamped_beyond_the_clock_bound_is_refused() -> None:
    """A question of a known control node stamped beyond the DN's clock
    bound is refused unanswered (stale) and does not become its newest."""
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
    bound = round(FLIGHT.clock.offset_bound_ms * 1e6) + FLIGHT.period_ns
    assert intake.admit(Bytes(ask_frame(ch, ASK, 0, 1, 1, new_nonce(), T0)), None)
    for beyond in (bound + 1, None):
        clock[0] += FLIGHT.period_ns
        t = I64_MAX if beyond is None else clock[0] + beyond
        assert not intake.admit(Bytes(ask_frame(ch, ASK, 0, 1, 2, new_nonce(), t)), None)
    clock[0] += FLIGHT.period_ns
    assert intake.admit(Bytes(ask_frame(ch, ASK, 0, 1, 3, new_nonce(), clock[0])), None)
    assert intake.take_counts() == (0, 0, 2)


def _snapshot(epoch: int, term: int, loop: int) -> bytes:
    """A genuine snapshot of CN run ``epoch`` in ``term``, stamped ``epoch + loop periods``."""
    cn = ControlLogic(FLIGHT, keys=FKEYS.for_node("cn"), epoch=epoch)
    cn.dv.handle("cn_term").set(term)
    cn.begin(loop, epoch + loop * FLIGHT.period_ns)
    return bytes(cn.telemetry())


def test_an_earlier_runs_higher_term_snapshot_does_not_freeze_the_ground() -> None:
    """The attack on the ground's telemetry intake: a genuine snapshot of an
    earlier run of the control nodes (a day before, in a higher term after
    takeovers) replayed once. The intake orders by the run (``cn_epoch``)
    before the term, and takes a new run or term only from a snapshot of
    now, so it is refused (aged) and this run's snapshots are still taken."""
    age = 2 * 10**9
    intake = TelemetryIntake(FLIGHT, channel(FKEYS, "telemetry"), 8, age)
    run = T0
    p = FLIGHT.period_ns
    assert intake.admit(Bytes(_snapshot(run, 1, 1)), run + p)
    old = _snapshot(run - 86_400 * 10**9, 5, 9)  # the earlier run, term 5
    assert not intake.admit(Bytes(old), run + 2 * p)
    assert intake.admit(Bytes(_snapshot(run, 1, 3)), run + 3 * p)
    assert intake.take_counts() == (0, 0, 1) and intake.aged == 1
    # A recent earlier run (restarted a second ago), its snapshot fresh: an
    # older run while this one speaks.
    recent = _snapshot(run - 10**9, 7, 100_000_000 // p)
    assert not intake.admit(Bytes(recent), run + 4 * p)
    # A takeover: a higher term of this run, stamped now, is taken; the old
    # commander's later loop (a lower term) is not.
    assert intake.admit(Bytes(_snapshot(run, 2, 5)), run + 5 * p)
    assert not intake.admit(Bytes(_snapshot(run, 1, 6)), run + 6 * p)
    # A higher term stamped long before it arrived is not a takeover of now.
    assert not intake.admit(Bytes(_snapshot(run, 3, 7)), run + 7 * p + 2 * age)
    assert intake.admit(Bytes(_snapshot(run, 2, 8)), run + 8 * p)
    assert intake.take_counts() == (0, 0, 3) and intake.aged == 1


def test_check_view_checks_a_frame_in_place_and_refuses_as_check_does() -> None:
    """Intake.check_view (the intra-host path's frames in shared memory):
    a frame that passes comes back as the very view it was given (no
    copy); junk, a wrong size and another loop's reply are refused and
    counted as :meth:`check` counts them."""
    check = ReplyCheck(M, "dn0", channel(KEYS, "dn0_to_cn"))
    good = bytearray(_reply(5, T0))
    check.expect(5, T0)
    view = memoryview(good)
    assert check.check_view(view, None) is view
    forged = bytearray(good)
    forged[3] ^= 1
    assert check.check_view(memoryview(forged), None) is None
    assert check.check_view(memoryview(good)[:-1], None) is None
    assert check.check_view(memoryview(b"x" * (check.max_len + 1)), None) is None
    check.expect(6, T0)
    assert check.check_view(memoryview(good), None) is None
    size, bad, stale = check.take_counts()
    assert size == 1 and stale == 1 and bad == 2


# -- terms: a new commander's first triggers ---------------------------------


def _term_trigger(term: int, loop: int, t: int) -> bytes:
    cn = ControlLogic(FLIGHT, keys=FKEYS, epoch=T0)
    cn.take_command(term, loop)
    return bytes(cn.begin(loop, t)[0])


def test_a_new_terms_trigger_is_fresh_though_stamped_before_the_old_terms_last() -> None:
    """A commander stalled for a few loops sends on as the standby takes
    over: its trigger of term 2, stamped at 52.511 s, reached dn0 after dn0
    granted term 3 and before the new commander's first trigger, stamped at
    its loop's start, 52.494 s. By one stamp for all terms that trigger was
    refused as a replay, and the next ones too: dn0 safed, no valid trigger
    for 106 ms (the live SIGSTOP takeover beside a CPU hog). Fresh per term
    now: the new term's is taken (then run); the old term's is taken to be
    fenced and answered by the logic; replays of either, and a dead term's,
    are refused."""
    p = FLIGHT.period_ns
    intake: TriggerIntake[str] = TriggerIntake(FLIGHT, "dn0", channel(FKEYS, "cn_to_dn0"))
    old_188 = _term_trigger(2, 188, T0 + 188 * p)
    old_190 = _term_trigger(2, 190, T0 + 190 * p + p // 2)  # late, stalled
    new_188 = _term_trigger(3, 188, T0 + 188 * p + p // 4)  # stamped before old_190
    new_189 = _term_trigger(3, 189, T0 + 189 * p)
    assert intake.admit(Bytes(old_188), "old 188")
    assert intake.admit(Bytes(old_190), "old 190")
    assert intake.admit(Bytes(new_188), "new 188")  # refused as a replay before
    assert not intake.admit(Bytes(new_188), "new 188 replayed")
    assert intake.admit(Bytes(new_189), "new 189")
    assert not intake.admit(Bytes(old_190), "old 190 replayed")
    old_191 = _term_trigger(2, 191, T0 + 191 * p)
    assert intake.admit(Bytes(old_191), "old 191")  # to be fenced by the logic
    # term 1, below the two newest: refused unless stamped later than every
    # trigger admitted (then the logic fences it, as without terms)
    assert not intake.admit(Bytes(_term_trigger(1, 190, T0 + 190 * p)), "term 1: dead")
    assert intake.take_counts() == (0, 0, 3)
    assert intake.admit(Bytes(_term_trigger(4, 192, T0 + 192 * p)), "term 4, leased")
    assert intake.admit(Bytes(_term_trigger(5, 193, T0 + 193 * p)), "term 5, leased")
    # term 3 still drives the node: its next trigger, stamped later, is taken
    assert intake.admit(Bytes(_term_trigger(3, 194, T0 + 194 * p)), "term 3, driving")
    assert not intake.admit(Bytes(new_189), "term 3's old one replayed")
    assert intake.take_counts() == (0, 0, 1)


def test_a_keyless_probe_flood_never_spends_the_bound_a_genuine_question_needs() -> None:
    """Issue 25: the probe intake's channel-wide rate bound came before the
    tag, so a keyless flood of question-sized junk spent it and the
    standby's genuine question, at the same instant, was refused (a takeover
    delayed for as long as the flood lasts). Now only a question whose tag
    checks spends a bound (its asker's): every junk question is refused
    bad, none beyond a bound, and the genuine one is admitted."""
    from zplatform.control.intake import PROBE_BURST

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
    genuine = ask_frame(ch, ASK, 1, 1, 1, new_nonce(), T0)
    flood = 20 * PROBE_BURST
    for i in range(flood):
        junk = bytearray(genuine)
        junk[-20] ^= 1 + i % 255  # the same size, a header tag that fails
        assert not intake.admit(Bytes(bytes(junk)), None)
    assert intake.admit(Bytes(genuine), None)
    assert intake.take_counts() == (0, flood, 0) and intake.excess == 0
