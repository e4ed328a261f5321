"""The ground's sans-IO logic with crafted frames and a real control loop.

Every check a snapshot passes (size, tag, encoding, freshness, run, order,
jump), the counters, and the command verdicts, which are read only from a
snapshot provably after the request: a replay of an earlier run (issue 18's
attack) can never make the ground report ACCEPTED for a command the control
node did not accept.
"""

from __future__ import annotations

import types
from pathlib import Path
from typing import Any

import pytest

from zplatform import load_mission
from zplatform.control.loop import ControlLogic
from zplatform.control.uplink import Uplink, parse_commands, validate_words
from zplatform.core.auth import KeySet
from zplatform.core.events import EV, Event, Severity
from zplatform.errors import CommandError
from zplatform.ground.logic import (
    REASON_GRACE_NS,
    GroundLogic,
    _read_cmd_event,
    default_max_age_ns,
    needs_arm,
)
from zplatform.ground.status import RateMeter, status_line
from zplatform.telemetry.records import format_outcome

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
LED = load_mission(CONFIGS / "led_test.yaml")
IGN = load_mission(CONFIGS / "recovery_igniter.yaml")
PERIOD = LED.period_ns
KEY = b"k" * 32
RUN2 = 1_700_000_000_000_000_000  # the control node's start (its epoch) in run 2
RUN1 = RUN2 - 3_600_000_000_000  # an hour earlier
LATENCY = 1_000_000  # 1 ms from the CN's loop to the ground


def _keys(mission: object, role: str, master: bytes = KEY) -> KeySet:
    """Host role ``role``'s keys, every link derived from ``master``."""
    return KeySet.from_master(mission, master).for_node(role)  # type: ignore[arg-type]


class Vehicle:
    """A control node's loop and a ground logic; frames passed by hand.

    Loop ``n`` runs at ``epoch + n * PERIOD``; its telemetry reaches the
    ground ``LATENCY`` later, and the ground's requests reach the CN's next
    loop (unless held back)."""

    def __init__(
        self,
        mission: object = LED,
        *,
        epoch: int = RUN2,
        ground: GroundLogic | None = None,
        key: bytes = KEY,
    ) -> None:
        self.mission = mission
        self.cn = ControlLogic(mission, keys=_keys(mission, "cn", key), epoch=epoch)  # type: ignore[arg-type]
        self.ground = ground or GroundLogic(mission, keys=_keys(mission, "gn"))  # type: ignore[arg-type]
        self.epoch = epoch
        self.loop = 0
        self.inbox: list[bytes] = []
        self.frames: list[tuple[int, bytes]] = []  # (loop time, telemetry) as sent
        self.lost: list[bytes] = []  # requests held back from the CN

    @property
    def t(self) -> int:
        return self.epoch + self.loop * PERIOD

    def step(self, *, tm: bool = True, events: bool = True, requests: bool = True) -> bytes:
        self.loop += 1
        self.cn.begin(self.loop, self.t)
        grounds, self.inbox = self.inbox, []
        frame = bytes(self.cn.finish(grounds) or b"")
        self.frames.append((self.t, frame))
        g = self.ground
        drained = self.cn.events.drain()
        if tm:
            g.on_telemetry(frame, self.t + LATENCY)
        out = g.take_requests()
        (self.inbox if requests else self.lost).extend(out)
        if events:
            for e in drained:
                g.on_event(e, self.t + 2 * LATENCY)
        return frame

    def run(self, loops: int, **kw: bool) -> None:
        for _ in range(loops):
            self.step(**kw)

    def command(self, *args: str | None, armed: bool = False) -> int:
        return self.ground.command(*args, now_ns=self.t + LATENCY, armed=armed)

    def until_done(self, ticket: int, loops: int = 50) -> list:  # type: ignore[type-arg]
        for _ in range(loops):
            done = self.ground.result(ticket)
            if done is not None:
                return done
            self.step()
        raise AssertionError(f"no result for ticket {ticket} in {loops} loops")


def _ids(g: GroundLogic) -> list[str]:
    return [e.id for e in g.events.drain()]


# -- telemetry checks ---------------------------------------------------------------


def test_fresh_telemetry_is_followed_and_counted() -> None:
    v = Vehicle()
    v.run(5)
    c = v.ground.counters
    assert (c.received, c.gaps, c.bad, c.epoch, c.first_seq, c.last_seq) == (5, 0, 0, RUN2, 1, 5)
    assert c.rejected == 0 and c.epoch_changes == 0
    assert int(v.ground.dv.get("cn_loop")) == 5
    assert _ids(v.ground) == ["tm_joined"]


def test_a_frame_without_the_telemetry_key_is_bad_and_never_applied() -> None:
    v = Vehicle(ground=GroundLogic(LED, keys=_keys(LED, "gn", b"x" * 32)))
    v.run(3)
    c = v.ground.counters
    assert (c.received, c.bad) == (0, 3) and not v.ground.joined
    assert int(v.ground.dv.get("cn_loop")) == 0
    assert "bad authentication tag" in v.ground.last_refusal
    assert _ids(v.ground) == ["tm_refused"]  # the first of its kind; the rest counted


def test_a_snapshot_the_intake_verified_is_only_stripped_of_its_tag() -> None:
    """``authentic=True``: the driver's intake checked this payload's tag, so
    the logic does not compute it again (a tag it would refuse shows that it
    was not); without it, the same payload is refused for its tag."""
    v = Vehicle()
    frame = bytearray(v.step(tm=False))
    frame[-1] ^= 0xFF  # a tag that does not verify
    g = GroundLogic(LED, keys=_keys(LED, "gn"))
    assert not g.on_telemetry(frame, v.t + LATENCY)
    assert g.counters.bad == 1 and "bad authentication tag" in g.last_refusal
    assert g.on_telemetry(frame, v.t + LATENCY, authentic=True)
    assert g.counters.received == 1 and int(g.dv.get("cn_loop")) == 1


def test_the_ground_link_checks_a_snapshots_tag_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A snapshot through the ground's zenoh link: its tag is computed once,
    by the intake as it arrives (it was computed again by the logic)."""
    from tests.payload import Bytes
    from zplatform.core.auth import Channel
    from zplatform.ground.link import GroundLink
    from zplatform.runtime.transport import rewrite_endpoints

    rewrite_endpoints(CONFIGS / "led_test.yaml", tmp_path / "led.yaml")
    m = load_mission(tmp_path / "led.yaml")
    link = GroundLink(m, keys=_keys(m, "gn"), events=False)
    try:
        cn = ControlLogic(m, keys=_keys(m, "cn"), epoch=link.clock.now_ns())
        assert link.run is not None
        link.run.set(cn.auth_run.epoch)  # as the commander's answer to its run hello
        cn.begin(1, link.clock.now_ns())
        frame = bytes(cn.finish([]) or b"")
        opened: list[str] = []
        real_check = Channel.check_body

        def counted(self: Channel, payload: bytes | bytearray | memoryview) -> memoryview:
            opened.append(self.name)
            return real_check(self, payload)

        # Channel.open is open_header then check_body: the body's MAC, once.
        monkeypatch.setattr(Channel, "check_body", counted)
        sample = types.SimpleNamespace(payload=Bytes(frame))
        link._on_telemetry(sample)  # type: ignore[arg-type]  # as zenoh's thread does
        assert link.next(0) is not None
        assert link.logic.counters.received == 1
        assert opened == ["telemetry"]
    finally:
        link.close()


def test_an_oversized_frame_is_refused_by_its_size_first() -> None:
    g = GroundLogic(LED, keys=_keys(LED, "gn"))
    assert not g.on_telemetry(b"\x00" * 100_000, RUN2)
    assert g.counters.bad == 1 and "longer than any telemetry frame" in g.last_refusal


def test_stale_and_future_stamps_are_refused_with_the_clock_named() -> None:
    v = Vehicle()
    frame = v.step(tm=False)
    g = v.ground
    bound = default_max_age_ns(LED)
    assert g.max_age_ns == bound == 1_100_000_000  # the clock bound (100 ms) + 1 s
    assert not g.on_telemetry(frame, v.t + bound + 1)
    assert "before this ground's clock" in g.last_refusal and "replay" in g.last_refusal
    assert not g.on_telemetry(frame, v.t - bound - 1)
    assert "this host's clock is behind" in g.last_refusal
    assert g.counters.refused["stale"] == 1 and g.counters.refused["ahead"] == 1
    assert g.on_telemetry(frame, v.t + bound)  # at the bound: fresh
    assert g.counters.received == 1


def test_duplicates_reordered_and_jumping_snapshots_are_refused() -> None:
    v = Vehicle()
    first = v.step()
    second = v.step()
    g = v.ground
    assert not g.on_telemetry(second, v.t + LATENCY)  # a duplicate
    assert not g.on_telemetry(first, v.t + LATENCY)  # an older one
    assert g.counters.refused["not_newer"] == 2
    # A snapshot 5000 loops ahead of the last, 10 ms after it: a jump.
    v.cn.begin(5000, v.t + PERIOD)
    far = bytes(v.cn.finish() or b"")
    assert not g.on_telemetry(far, v.t + PERIOD + LATENCY)
    assert g.counters.refused["jump"] == 1
    assert int(g.dv.get("cn_loop")) == 2 and g.counters.received == 2


def test_gaps_count_the_loops_lost_between_snapshots() -> None:
    v = Vehicle()
    v.step()
    v.run(3, tm=False)
    v.step()
    assert v.ground.counters.gaps == 3


def test_a_replayed_earlier_run_is_stale_and_never_followed() -> None:
    """Issue 18's attack at the ground: run 1's telemetry, replayed during run 2."""
    run1 = Vehicle(epoch=RUN1)
    run1.run(20)
    g = GroundLogic(LED, keys=_keys(LED, "gn"))
    now = RUN2 + PERIOD
    for _, frame in run1.frames:
        assert not g.on_telemetry(frame, now)
    assert not g.joined and g.counters.refused["stale"] == 20
    run2 = Vehicle(ground=g)
    run2.run(3)
    assert g.counters.epoch == RUN2 and g.counters.received == 3
    for _, frame in run1.frames:  # interleaved with run 2's: still refused
        assert not g.on_telemetry(frame, run2.t + LATENCY)
    assert g.counters.received == 3 and g.counters.refused["stale"] == 40


def test_an_older_run_is_refused_while_the_run_followed_is_fresh() -> None:
    new = Vehicle(epoch=RUN2)
    new.run(3)
    g = new.ground
    old = Vehicle(epoch=RUN2 - 10 * PERIOD, ground=GroundLogic(LED, keys=_keys(LED, "gn")))
    old.run(13)  # fresh, but of a run that started earlier
    for _, frame in old.frames[-3:]:
        assert not g.on_telemetry(frame, new.t + LATENCY)
    assert g.counters.refused["old_epoch"] == 3 and g.counters.epoch == RUN2


def test_a_restarted_control_node_is_followed_as_a_decision() -> None:
    a = Vehicle(epoch=RUN2)
    a.run(10)
    g = a.ground
    _ids(g)
    b = Vehicle(epoch=RUN2 + 11 * PERIOD, ground=g)  # restarted: a newer run
    b.run(3)
    c = g.counters
    assert c.epoch == RUN2 + 11 * PERIOD and c.epoch_changes == 1 and c.received == 13
    assert _ids(g) == ["cn_restarted"]
    assert int(g.dv.get("cn_loop")) == 3  # the new run's loops: followed from its loop 1


def test_an_older_run_is_followed_once_the_run_followed_went_stale() -> None:
    """A restarted CN whose host clock went back (a smaller epoch) is the
    newest run alive once the old one is silent past the bound."""
    a = Vehicle(epoch=RUN2)
    a.run(3)
    g = a.ground
    b = Vehicle(epoch=RUN2 - PERIOD, ground=g)
    b.loop = 400  # 4 s later: run a has been silent past the bound
    b.step()
    assert g.counters.epoch == RUN2 - PERIOD and g.counters.epoch_changes == 1


# -- command verdicts ---------------------------------------------------------------


def test_a_command_is_numbered_after_the_last_verdict_and_reported_with_its_reason() -> None:
    v = Vehicle()
    v.run(2)
    t = v.command("write", "led_a_cmd", "true")
    (o,) = v.until_done(t)
    assert (o.command, o.seq, o.status, o.reason_from) == ("WRITE", 1, "ACCEPTED", "cn")
    assert format_outcome(o) == "WRITE #1: ACCEPTED (led_a_cmd = True)"
    t = v.command("launch")
    (o,) = v.until_done(t)
    assert (o.seq, o.status) == (2, "ACCEPTED")
    t = v.command("write", "led_a_cmd", "false")  # state B allows no WRITE
    (o,) = v.until_done(t)
    assert (o.seq, o.status, o.reason_from) == (3, "REJECTED_NOT_ALLOWED", "cn")
    assert format_outcome(o) == "WRITE #3: REJECTED_NOT_ALLOWED: not allowed in state B"
    assert [x.seq for x in v.ground.outcomes] == [1, 2, 3]


def test_a_verdict_comes_only_from_a_later_loop_of_the_same_run() -> None:
    """The attack at the verdict: while the request waits, snapshots claiming
    its number was ACCEPTED arrive from run 1 (stale) and from an older run
    (fresh); the CN refuses the request; the ground reports the refusal."""
    run1 = Vehicle(epoch=RUN1)
    up1 = Uplink(LED, _keys(LED, "gn"))
    run1.inbox.append(bytes(up1.frame("LAUNCH", 3, 0, 0.0, RUN1, RUN1)))
    run1.run(3)
    assert run1.cn.dv.get("cn_cmd_seq") == 3  # run 1's snapshots say "#3 ACCEPTED"
    older = Vehicle(epoch=RUN2 - 5 * PERIOD, ground=GroundLogic(LED, keys=_keys(LED, "gn")))
    up = Uplink(LED, _keys(LED, "gn"))
    older.inbox.append(bytes(up.frame("NOOP", 3, 0, 0.0, RUN2, RUN2 - 5 * PERIOD)))
    v = Vehicle()
    v.inbox.append(bytes(Uplink(LED, _keys(LED, "gn")).frame("LAUNCH", 2, 0, 0.0, RUN2, RUN2)))
    v.run(3)  # run 2 in state B: cn_cmd_seq 2
    g = v.ground
    t = v.command("write", "led_a_cmd", "true")  # #3: state B refuses WRITE
    hold = g.take_requests() or v.inbox
    v.inbox = []
    older.run(8)
    for (_, stale), (_, fresh_old) in zip(run1.frames, older.frames[-3:], strict=True):
        g.on_telemetry(stale, v.t + LATENCY)
        g.on_telemetry(fresh_old, v.t + LATENCY)
    assert g.result(t) is None and g.counters.refused["stale"] == 3
    assert g.counters.refused["old_epoch"] == 3
    v.inbox = list(hold)
    (o,) = v.until_done(t)
    assert (o.seq, o.status) == (3, "REJECTED_NOT_ALLOWED")
    assert not o.accepted


def test_a_refusal_that_consumes_no_number_is_reported_at_once() -> None:
    """Another tool took numbers ahead: the CN refuses ours as a replay
    without consuming it; cn_cmd_reject_seq tells the ground at once."""
    v = Vehicle()
    v.run(2)
    t = v.command("noop")
    mine = v.ground.take_requests() or v.inbox
    v.inbox = [bytes(Uplink(LED, _keys(LED, "gn")).frame("NOOP", 5, 0, 0.0, v.t, RUN2))]
    v.step(requests=False)  # the other tool's #5 first
    v.inbox = list(mine)
    (o,) = v.until_done(t, loops=3)
    assert (o.seq, o.status, o.reason_from) == (1, "REJECTED_REPLAY", "cn")
    assert "not above the last one seen (5)" in o.reason
    t = v.command("noop")  # numbered after the CN's last verdict (#5)
    assert v.until_done(t)[0].seq == 6


def test_a_request_for_a_run_that_restarted_ends_without_a_verdict() -> None:
    a = Vehicle()
    a.run(3)
    t = a.command("noop")
    a.inbox = []  # the CN dies before taking it
    b = Vehicle(epoch=RUN2 + 10 * PERIOD, ground=a.ground)
    b.run(2)
    (o,) = a.ground.result(t) or [None]
    assert o is not None and (o.status, o.reason_from) == ("NO_VERDICT", "ground")
    assert "restarted" in o.reason


def test_a_reason_is_derived_and_said_so_when_the_event_does_not_come() -> None:
    v = Vehicle()
    v.run(2)
    t = v.command("launch")
    v.until_done(t)
    t = v.command("write", "led_a_cmd", "false")
    for _ in range(3):
        v.step(events=False)
    assert v.ground.result(t) is None  # the verdict is in; its reason is awaited
    v.ground.tick(v.t + REASON_GRACE_NS + 2 * LATENCY)
    (o,) = v.ground.result(t) or [None]
    assert o is not None and (o.status, o.reason_from) == ("REJECTED_NOT_ALLOWED", "derived")
    assert "not allowed in state B" in o.reason
    assert "[derived from telemetry" in format_outcome(o)


def test_a_forged_event_cannot_change_a_verdict() -> None:
    """Events are not authenticated: one claiming ACCEPTED for a refused
    request does not match its verdict and is never its reason."""
    v = Vehicle()
    v.run(2)
    v.until_done(v.command("launch"))
    t = v.command("write", "led_a_cmd", "false")
    forged = Event(
        "cn", 99, v.t, int(Severity.COMMAND), "cmd_accepted", "command WRITE #2 accepted"
    )
    v.ground.on_event(forged, v.t)
    for _ in range(3):
        v.step(events=False)
    v.ground.finish(v.t)
    (o,) = v.ground.result(t) or [None]
    assert o is not None and (o.status, o.reason_from) == ("REJECTED_NOT_ALLOWED", "derived")


def test_an_armed_command_goes_arm_then_command() -> None:
    v = Vehicle(IGN)
    v.run(2)
    t = v.command("launch", armed=True)
    outcomes = v.until_done(t)
    assert [(o.command, o.seq, o.status) for o in outcomes] == [
        ("ARM", 1, "ACCEPTED"),
        ("LAUNCH", 2, "ACCEPTED"),
    ]
    v.run(2)
    assert v.ground.dv.get_name("cn_state") == "ARMED"


def test_an_armed_write_of_a_protected_element_is_accepted() -> None:
    v = Vehicle(IGN)
    v.run(2)
    outcomes = v.until_done(v.command("write", "safety0_mode", "enabled", armed=True))
    assert [(o.command, o.status) for o in outcomes] == [("ARM", "ACCEPTED"), ("WRITE", "ACCEPTED")]
    assert v.cn.dv.get_name("safety0_mode") == "enabled"


def test_a_refused_arm_stops_the_armed_command() -> None:
    v = Vehicle()
    v.run(2)
    v.until_done(v.command("launch"))  # state B: ARM is not allowed
    t = v.command("abort", armed=True)
    outcomes = v.until_done(t)
    assert [(o.command, o.status) for o in outcomes] == [("ARM", "REJECTED_NOT_ALLOWED")]
    assert v.ground.steps(t) == ["ARM", "ABORT"]
    v.run(5)
    assert v.cn.dv.get("cn_cmd_seq") == 2 and v.cn.dv.get_name("cn_state") == "B"


def test_a_lost_request_is_sent_again_then_ends_without_a_verdict() -> None:
    g = GroundLogic(LED, keys=_keys(LED, "gn"), resend_loops=10, tries=3)
    v = Vehicle(ground=g)
    v.run(2)
    t = v.command("noop")
    v.run(40, requests=False)
    (o,) = g.result(t) or [None]
    assert len(v.lost) == 3 and len(set(v.lost)) == 3  # the same number, stamped anew
    assert o is not None and o.status == "NO_VERDICT"
    assert o.reason_from == "ground" and "3 send(s)" in o.reason


def test_commands_wait_for_a_followed_run_and_for_the_cn_to_listen() -> None:
    g = GroundLogic(LED, keys=_keys(LED, "gn"))
    t = g.command("noop", now_ns=RUN2)
    assert not g.take_requests() and g.result(t) is None  # no run followed yet
    v = Vehicle(ground=g)
    v.cn.begin(1, v.t + PERIOD)
    frame = bytes(v.cn.finish() or b"")
    assert g.on_telemetry(frame, v.t + PERIOD + LATENCY, can_send=False)
    assert not g.take_requests()  # the CN does not listen
    v.loop = 1
    v.step()
    assert len(v.inbox) == 1


def test_needs_arm_names_hazardous_commands_and_protected_elements() -> None:
    assert needs_arm(IGN, "launch") == "LAUNCH is hazardous (commands.hazardous)"
    assert (
        needs_arm(IGN, "write", "dn0_ign_armed")
        == "dn0_ign_armed is protected (commands.protected)"
    )
    assert needs_arm(IGN, "noop") is None and needs_arm(IGN, "arm") is None
    assert needs_arm(LED, "launch") is None and needs_arm(LED, "write", "led_a_cmd") is None


@pytest.mark.parametrize(
    ("ev", "args", "read"),
    [
        (EV.CMD_ACCEPTED, {"name": "WRITE", "seq": 4, "detail": " (x = 1)"}, ("ACCEPTED", "x = 1")),
        (EV.CMD_ACCEPTED, {"name": "NOOP", "seq": 4, "detail": ""}, ("ACCEPTED", "")),
        (
            EV.CMD_REJECTED,
            {"name": "LAUNCH", "seq": 4, "status": "REJECTED_NOT_ARMED", "detail": "a: b (c)"},
            ("REJECTED_NOT_ARMED", "a: b (c)"),
        ),
    ],
)
def test_command_events_read_back_from_their_catalogue_format(
    ev: object, args: dict[str, object], read: tuple[str, str]
) -> None:
    e = Event("cn", 0, 5, 3, ev.name, ev.text(**args))  # type: ignore[attr-defined]
    ce = _read_cmd_event(e)
    assert ce is not None and (ce.seq, ce.name) == (4, args["name"])
    assert (ce.status, ce.detail) == read
    assert _read_cmd_event(Event("dn0", 0, 5, 3, ev.name, e.text)) is None  # not the CN's  # type: ignore[attr-defined]


def test_the_script_player_says_when_the_script_is_done() -> None:
    script = parse_commands("at 0.02 arm\nat 0.03 launch\n")
    g = GroundLogic(IGN, keys=_keys(IGN, "gn"), script=script)
    v = Vehicle(IGN, ground=g)
    v.run(10)
    assert [(o.command, o.status) for o in g.player.results(g)] == [  # type: ignore[union-attr]
        ("ARM", "ACCEPTED"),
        ("LAUNCH", "ACCEPTED"),
    ]
    assert "script_done" in _ids(g)


def _count_checks(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every element a ground check resolves from now on (the heart of
    zplatform.control.uplink.validate_command for a WRITE), in order."""
    import zplatform.control.uplink as uplink

    seen: list[str] = []
    real = uplink.resolve_write

    def counted(layout: Any, element: str, value: str, where: str) -> tuple[int, float]:
        seen.append(element)
        return real(layout, element, value, where)

    monkeypatch.setattr(uplink, "resolve_write", counted)
    return seen


def test_a_scripted_command_is_checked_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The player checks each line against the mission when it is built and
    hands the checked command to the logic, which does not check it again
    (it did, a second time, as it was played)."""
    checks = _count_checks(monkeypatch)
    script = parse_commands("at 0.02 write led_a_cmd true\n")
    g = GroundLogic(LED, keys=_keys(LED, "gn"), script=script)
    assert checks == ["led_a_cmd"]
    v = Vehicle(LED, ground=g)
    v.run(10)
    g.finish(v.t)
    assert [(o.command, o.status) for o in g.outcomes] == [("WRITE", "ACCEPTED")]
    assert int(g.dv.get("led_a_cmd")) == 1
    assert checks == ["led_a_cmd"]


def test_a_checked_command_is_submitted_unchecked_and_a_named_one_checked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    checks = _count_checks(monkeypatch)
    v = Vehicle()
    v.run(2)
    checked = validate_words(LED, "write", ["led_a_cmd", "true"])
    assert checks == ["led_a_cmd"]
    done = v.until_done(v.ground.submit(checked, now_ns=v.t + LATENCY))
    assert [o.status for o in done] == ["ACCEPTED"] and checks == ["led_a_cmd"]
    done = v.until_done(v.command("write", "led_a_cmd", "false"))
    assert [o.status for o in done] == ["ACCEPTED"] and checks == ["led_a_cmd"] * 2
    with pytest.raises(CommandError, match=r"write takes at most ELEMENT VALUE, got \["):
        validate_words(LED, "write", ["led_a_cmd", "true", "now"])


# -- status -------------------------------------------------------------------------


def test_the_rate_is_unknown_until_two_snapshots_give_it() -> None:
    r = RateMeter()
    assert r.hz is None
    r.add(0, 1)
    assert r.hz is None
    r.add(100_000_000, 11)
    assert r.hz == pytest.approx(100.0)
    r.add(50_000_000, 1)  # a restarted CN: its own rate, from its own samples
    assert r.hz is None
    v = Vehicle()
    v.step()
    line = status_line(LED, v.ground.dv, None, ["led_a_fb"])
    assert "     - Hz" in line and "0.0 Hz" not in line and "led_a_fb=False" in line


def test_event_records_must_be_fresh_per_node_and_replays_are_counted() -> None:
    """An authentic event record is taken once, stamped within the ground's
    clock bound: a replay, or one stamped at the end of time (which, taken,
    would leave every genuine record after it 'not newer'), is refused and
    counted in stale_events, and the node's next genuine record is taken."""
    from zplatform.core.auth import channel
    from zplatform.core.events import encode_event

    keys = KeySet.from_master(IGN, KEY)
    g = GroundLogic(IGN, keys=keys.for_node("gn"))
    ch = channel(keys, "events_dn0")
    assert ch is not None
    key = f"{IGN.vehicle}/dn0/events"
    now = 1_700_000_000_000_000_000
    bound = g.max_age_ns

    def rec(seq: int, t_ns: int) -> bytes:
        return bytes(ch.seal(encode_event(Event("dn0", seq, t_ns, 2, "bad_frame", "x"))))

    first = rec(1, now)
    assert g.on_event_bytes(key, first, now) is not None
    assert g.on_event_bytes(key, rec(2, now), now) is not None  # same loop, numbered up
    assert g.on_event_bytes(key, first, now) is None  # a replay
    assert g.on_event_bytes(key, rec(3, (1 << 63) - 1), now) is None  # the end of time
    assert g.on_event_bytes(key, rec(4, now + bound + 1), now) is None  # beyond the bound
    assert g.on_event_bytes(key, rec(5, now - bound - 1), now) is None  # an old record
    assert g.on_event_bytes(key, rec(6, now + 1), now) is not None
    # Numbered up but stamped before (the loop's time after the clock's): taken;
    # then a replay of any record taken is not.
    assert g.on_event_bytes(key, rec(7, now), now) is not None
    assert g.on_event_bytes(key, rec(6, now + 1), now) is None
    assert g.on_event_bytes(key, rec(2, now), now) is None
    # A restarted node numbers from 0 again, later.
    assert g.on_event_bytes(key, rec(0, now + 2), now) is not None
    c = g.counters
    assert (c.stale_events, c.bad_events) == (6, 0)


def test_the_ground_keeps_logging_after_an_earlier_runs_higher_term_snapshot() -> None:
    """The ground's intake and its logic agree on the order (run, term,
    stamp): a genuine snapshot of an earlier run of the control nodes in a
    higher term, replayed, is refused at the intake (counted as the logic's
    ``stale``) and never raises the term the intake holds, so every genuine
    snapshot of this run after it is still logged; one stamped far ahead is
    refused as ``ahead``."""
    import os

    from zplatform.control.intake import TelemetryIntake
    from zplatform.core.auth import KEY_ENV, channel

    flight = load_mission(CONFIGS / "flight.yaml")
    keys = KeySet.from_master(flight, bytes.fromhex(os.environ[KEY_ENV]))
    g = GroundLogic(flight, keys=keys.for_node("gn"))
    intake = TelemetryIntake(flight, channel(keys, "telemetry"), 8, g.max_age_ns)
    assert intake.box is not None
    p = flight.period_ns
    run = 1_700_000_000_000_000_000

    class _Payload:
        def __init__(self, data: bytes) -> None:
            self.data = data

        def __len__(self) -> int:
            return len(self.data)

        def to_bytes(self) -> bytes:
            return self.data

    def snapshot(epoch: int, term: int, loop: int, t_ns: int) -> bytes:
        cn = ControlLogic(flight, keys=keys.for_node("cn"), epoch=epoch)
        cn.dv.handle("cn_term").set(term)
        cn.begin(loop, t_ns)
        return bytes(cn.telemetry())

    def arrive(frame: bytes, rx: int) -> bool:
        if not intake.admit(_Payload(frame), rx):
            g.refused(*intake.take_counts(), intake.aged, rx, intake.ahead)
            return False
        item = intake.box.pop()
        assert item is not None
        return g.on_telemetry(item[1], item[0])

    assert arrive(snapshot(run, 1, 1, run + p), run + p)
    old = snapshot(run - 86_400 * 10**9, 5, 9, run - 86_400 * 10**9 + 9 * p)
    assert not arrive(old, run + 2 * p)
    assert not arrive(snapshot(run, 1, 3, (1 << 63) - 1), run + 3 * p)
    for n in range(4, 8):
        assert arrive(snapshot(run, 1, n, run + n * p), run + n * p)
    c = g.counters
    assert (c.received, c.term, c.last_seq) == (5, 1, 7)
    assert (c.refused["stale"], c.refused["ahead"], c.refused["not_newer"]) == (1, 1, 0)
