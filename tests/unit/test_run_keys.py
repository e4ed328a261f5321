"""Keys bound to the run (zplatform.core.auth.Run, codecs/FORMAT.md §6.1): the
nodes' logic and intakes refuse another run's frames, answer in the run of
what they answer, and follow their vector's run."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

from tests.payload import Bytes
from tests.zsession import lone_session
from zplatform import load_mission
from zplatform.control.failover import MirrorReader, Standby
from zplatform.control.fencing import ASK, STATUS, ask_frame, new_nonce
from zplatform.control.intake import TriggerIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import load_commands
from zplatform.core.auth import NO_RUN, RUN_LEN, TAG_LEN, Channel, Run
from zplatform.node.device import ClockResync
from zplatform.runtime.clocksync import ClockLink, ClockServer, ClockSyncError, estimate_offset
from zplatform.runtime.process import StopFlag
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import DEFAULT_START_NS, LockstepRunner, sim_keys

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
IGNITER = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
IGNITER_CMDS = load_commands(ROOT / "configs" / "recovery_igniter.commands")
KEYS = sim_keys(FLIGHT)
assert KEYS is not None
P = FLIGHT.period_ns
T0 = 1_700_000_000_000_000_000
OLD, NEW = T0 - 86_400 * 10**9, T0


def at(loop: int) -> int:
    return T0 + loop * P


def _cn(epoch: int, name: str = "cn") -> ControlLogic:
    return ControlLogic(FLIGHT, keys=KEYS.for_node(name), epoch=epoch, name=name)


def _trigger(cn: ControlLogic, loop: int, i: int = 0) -> bytes:
    return bytes(cn.begin(loop, at(loop))[i])


def test_a_bound_device_node_runs_only_its_runs_triggers_and_answers_in_it() -> None:
    """dn0 bound to the run its clock exchange told (NEW): a genuine trigger
    of an earlier run (OLD, a later loop and stamp) is refused and counted,
    never run; this run's is run, and the reply names this run, so the
    control node (bound to its own run) takes it."""
    run = Run(NEW)
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"), run=run)
    old, new = _cn(OLD), _cn(NEW)
    assert dn.trigger(_trigger(old, 9), at(9)) is None and dn.triggered == 0
    assert int(dn.dv.get("dn0_bad_frames")) == 1
    assert "not of this run" in dn.reject_reason
    reply = dn.trigger(_trigger(new, 1), at(1))
    assert reply is not None and dn.triggered == 1
    assert Channel.run_of(reply) == NEW
    new.reply(0, reply)
    assert new.replied[0]
    # Before it knows the run, nothing is run.
    fresh = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"), run=Run())
    assert fresh.trigger(_trigger(new, 2), at(2)) is None and fresh.triggered == 0


def test_the_trigger_intake_counts_another_runs_genuine_trigger_stale_and_junk_bad() -> None:
    intake: TriggerIntake[None] = TriggerIntake(
        FLIGHT, "dn0", KEYS.for_node("dn0").channel("cn_to_dn0", Run(NEW))
    )
    old = _trigger(_cn(OLD), 5)
    assert not intake.admit(Bytes(old), None)
    assert intake.take_counts() == (0, 0, 1)
    # The same bytes under a run word rewritten to this run's: a bad tag.
    n = len(old) - TAG_LEN
    forged = old[:n] + NEW.to_bytes(8, "little") + old[n + 8 :]
    assert not intake.admit(Bytes(forged), None)
    assert intake.take_counts() == (0, 1, 0)
    assert intake.admit(Bytes(_trigger(_cn(NEW), 1)), None)


def test_a_device_node_answers_a_status_in_any_run_but_an_ask_only_in_its_own() -> None:
    """A STATUS moves nothing: answered in the asker's run (a restarted
    control node asks before it knows the run). An ASK of another run (an
    earlier run's, replayed) would move the node's term: refused."""
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"), run=Run(NEW))
    old = KEYS.for_node("cn").channel("probe_cn_to_dn0", Run(OLD))
    status = dn.probe(ask_frame(old, STATUS, 0, 1, 0, new_nonce(), at(1)), at(1))
    assert status is not None and Channel.run_of(status) == OLD
    assert dn.probe(ask_frame(old, ASK, 0, 1, 2, new_nonce(), at(2)), at(2)) is None
    assert dn.guard is not None and dn.guard.promised(at(2)) == 0
    mine = KEYS.for_node("cn").channel("probe_cn_to_dn0", Run(NEW))
    reply = dn.probe(ask_frame(mine, STATUS, 0, 1, 0, new_nonce(), at(3)), at(3))
    assert reply is not None and Channel.run_of(reply) == NEW


def test_a_standby_refuses_a_mirror_of_another_run() -> None:
    """cn_b learned the commander's run (NEW): the commander's mirror of an
    earlier run, however newer its term and loop, never verifies."""
    sb = Standby(FLIGHT, _cn(NEW, "cn_b"), KEYS.for_node("cn_b"))
    old = _cn(OLD)
    old.take_command(5, 1)
    old.begin(50, at(50))
    old.finish()
    assert old.mirror is not None
    assert not sb.mirror(bytes(old.mirror), at(50)) and sb.bad == 1
    cn = _cn(NEW)
    cn.begin(1, at(1))
    cn.finish()
    assert cn.mirror is not None and sb.mirror(bytes(cn.mirror), at(1))
    reader = MirrorReader(_cn(NEW), KEYS.for_node("cn"))
    assert reader.read(bytes(old.mirror)) is None


def test_the_control_logic_follows_its_vectors_run() -> None:
    """A resumed vector (adopt) or a taken-over one brings its run: the
    logic's frames name it from then on."""
    cn = _cn(NEW)
    assert Channel.run_of(_trigger(cn, 1)) == NEW
    resumed = _cn(NEW + 1)
    resumed.dv.write_all(bytes(cn.dv.view()))
    resumed.adopt()
    assert resumed.auth_run.epoch == NEW
    assert Channel.run_of(_trigger(resumed, 2)) == NEW
    assert Run().epoch == NO_RUN and not Run().known


def test_a_restarted_control_nodes_warm_up_is_answered_in_its_run_then_it_resumes() -> None:
    """A control node restarted in flight has a new run (NEW) until it
    resumes the device nodes' (OLD, its recorder's): its warm-up (loop 0,
    answered, never run) is answered in NEW at the intake and by the
    logic, so it learns where they are; its loop 1 of NEW is not run; once
    it has adopted the recorded vector, its triggers are of OLD again and run."""
    intake: TriggerIntake[None] = TriggerIntake(
        FLIGHT, "dn0", KEYS.for_node("dn0").channel("cn_to_dn0", Run(OLD)), lambda: at(0)
    )
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"), run=Run(OLD))
    first = _cn(OLD)
    assert dn.trigger(_trigger(first, 1), at(1)) is not None and dn.triggered == 1
    restarted = _cn(NEW)
    warm = bytes(restarted.begin(0, at(2))[0])
    assert intake.admit(Bytes(warm), None)
    reply = dn.trigger(warm, at(2), authentic=True)
    assert reply is not None and dn.triggered == 0 and Channel.run_of(reply) == NEW
    restarted.reply(0, reply)
    assert restarted.replied[0]
    assert dn.trigger(_trigger(restarted, 3), at(3)) is None and dn.triggered == 0
    assert not intake.admit(Bytes(_trigger(restarted, 4)), None)
    assert intake.take_counts() == (0, 0, 1)
    restarted.dv.write_all(bytes(first.dv.view()))
    restarted.adopt()
    reply = dn.trigger(_trigger(restarted, 5), at(5))
    assert reply is not None and dn.triggered == 5 and Channel.run_of(reply) == OLD


def test_a_genuine_trigger_of_another_run_cues_the_device_node_to_ask_the_run() -> None:
    """The intake calls on_other_run for a genuine frame of another run
    (the device node then asks its clock exchange for the run: the control
    node may have started a new one), never for junk or this run's frames."""
    cues: list[int] = []
    intake: TriggerIntake[None] = TriggerIntake(
        FLIGHT, "dn0", KEYS.for_node("dn0").channel("cn_to_dn0", Run(NEW))
    )
    intake.on_other_run = lambda: cues.append(1)
    old = _trigger(_cn(OLD), 5)
    assert not intake.admit(Bytes(old), None) and cues == [1]
    # Junk: its header tag (after the run word) does not check. (A genuine
    # header of another run on another body is refused too, as stale, by
    # its header alone: codecs/FORMAT.md §6.1.)
    at = len(old) - TAG_LEN + RUN_LEN
    junk = old[:at] + bytes([old[at] ^ 1]) + old[at + 1 :]
    assert not intake.admit(Bytes(junk), None) and cues == [1]
    assert intake.admit(Bytes(_trigger(_cn(NEW), 1)), None) and cues == [1]
    assert intake.take_counts() == (0, 1, 1)


# -- the lockstep runner binds its device nodes as live ---------------------------------


def _bad(r: LockstepRunner, dn: str) -> int:
    return int(r.devices[r.mission.device_nodes.index(dn)].dv.get(f"{dn}_bad_frames"))


def test_lockstep_device_nodes_refuse_an_earlier_runs_trigger_and_the_flight_deploys() -> None:
    """recovery_igniter in lockstep: each device node learns the commander's
    run by a hello, as live. A genuine dn0 trigger of an earlier run (a later
    loop, a fresh stamp: a replay of the last flight) reaches it mid-flight:
    refused at its intake unanswered, never run, counted in
    ``dn0_bad_frames`` as live counts it (the intake's stale), and it cues one
    hello (the run may be new: it is not, and stays); a second one within
    the second is counted and cues none. The flight deploys as planned."""
    r = LockstepRunner(IGNITER, commands=IGNITER_CMDS)
    assert [d.auth_run.epoch for d in r.devices] == [DEFAULT_START_NS] * len(r.devices)
    r.run(1.0)
    keys = sim_keys(IGNITER)
    assert keys is not None
    old = ControlLogic(IGNITER, keys=keys.for_node("cn"), epoch=DEFAULT_START_NS - 86_400 * 10**9)
    replayed = bytes(old.begin(r.loop + 5000, r.clock.now_ns())[0])
    dn0 = r.dns[0]
    hellos = dn0.hellos
    assert r.inject("dn0", replayed) is None
    assert _bad(r, "dn0") == 1 and dn0.logic.last_loop == r.loop
    assert dn0.hellos == hellos + 1 and dn0.run.epoch == DEFAULT_START_NS
    assert r.inject("dn0", replayed) is None
    assert _bad(r, "dn0") == 2 and dn0.hellos == hellos + 1
    res = r.run(30.0)
    assert res.states == ["SAFE", "ARMED", "FIRE", "DEPLOYED"], res.states
    assert res.fault == "NONE" and res.errors == 0
    assert set(res.missed.values()) == {0}
    assert int(r.control.dv.get("dn0_bad_frames")) == 2  # the CN's copy, as telemetry
    assert _bad(r, "dn1") == 0
    told = [e.text for e in res.events if e.node == "dn0" and e.id == "bad_frame"]
    assert told and "1 replayed" in told[0] and "another run's" in told[0], told


def test_lockstep_device_nodes_follow_a_control_node_that_starts_over() -> None:
    """A control node restarted in flight with no usable record starts over:
    a new run. Each device node refuses the new run's first loop (another
    run's: unanswered, so the control node counts it missed), asks the run
    with a hello on that cue, and runs the new run's loops from the next."""
    r = LockstepRunner(IGNITER, commands=IGNITER_CMDS)
    r.run(1.5)
    r.kill("cn")
    r.run(1.0)
    assert r.restart("cn", record=None) == "start_over"
    res = r.run(1.0)
    assert res.states == ["SAFE", "ARMED", "SAFE"], res.states
    assert res.missed == dict.fromkeys(IGNITER.device_nodes, 1)
    assert res.rx == dict.fromkeys(IGNITER.device_nodes, 99)
    assert [_bad(r, dn) for dn in IGNITER.device_nodes] == [1] * len(r.devices)
    new = DEFAULT_START_NS + 250 * IGNITER.period_ns
    assert r.control.auth_run.epoch == new
    assert [d.auth_run.epoch for d in r.devices] == [new] * len(r.devices)


# -- a device node without periodic re-syncs --------------------------------------------


def test_a_device_node_without_resyncs_learns_a_new_run_by_a_hello_on_demand() -> None:
    """``clock.resync_s: 0``: no periodic re-sync. The control node has started
    a new run (NEW) while dn0 is bound to the last one (OLD), whose end it
    ran: its intake refuses the new run's genuine trigger as stale and cues
    the node's re-sync thread, which asks the run with a hello over zenoh
    in this process (the control node's clock server), learns NEW and
    measures nothing; the new run's next trigger is admitted and runs."""
    mission = msgspec.structs.replace(
        IGNITER, clock=msgspec.structs.replace(IGNITER.clock, resync_s=0.0)
    )
    keys = sim_keys(mission)
    assert keys is not None
    run = Run(OLD)
    dn = DeviceLogic(mission, "dn0", keys=keys.for_node("dn0"), run=run)
    intake: TriggerIntake[None] = TriggerIntake(
        mission, "dn0", keys.for_node("dn0").channel("cn_to_dn0", run), lambda: at(0)
    )
    cn = ControlLogic(mission, keys=keys.for_node("cn"), epoch=NEW)
    space = KeySpace(mission.vehicle)
    session = lone_session()
    server = ClockServer(
        session, space, lambda: at(1), mission, keys.for_node("cn"), run=cn.auth_run
    )
    link = ClockLink(mission, "dn0", keys.for_node("dn0"), run=run)
    stop = StopFlag(install=False)
    resync = ClockResync(
        mission, "dn0", session, space, lambda: at(1), link, estimate_offset, stop, lambda: True
    )
    intake.on_other_run = resync.cue
    resync.start()
    try:
        assert not intake.admit(Bytes(bytes(cn.begin(1, at(1))[0])), None)
        assert intake.take_counts() == (0, 0, 1)
        assert resync.ended.wait(30.0), "the cue was never answered"
    finally:
        stop.set()
        resync.close()
        server.close()
        session.close()
    assert run.epoch == NEW and link.refused == 0 and link.timeouts == 0
    assert resync.attempts == 1 and resync.measured is None
    second = bytes(cn.begin(2, at(2))[0])
    assert intake.admit(Bytes(second), None)
    reply = dn.trigger(second, at(2), authentic=True)
    assert reply is not None and dn.triggered == 2 and Channel.run_of(reply) == NEW


def test_a_late_reply_never_checks_the_idle_clock_thread_in() -> None:
    """A clock reply read after its series ended (zenoh's thread reads the
    clock in the reply's callback) must not check the re-sync thread in:
    that made an idle thread look busy, and past its deadline while it
    waited for the next re-sync (a live flight without real-time priority
    latched THREAD_STALLED so). The thread's own reads still check it in."""
    mission = msgspec.structs.replace(
        IGNITER, clock=msgspec.structs.replace(IGNITER.clock, resync_s=3600.0)
    )
    readers: list[Callable[[], int]] = []
    during: list[int] = []

    def estimate(session: Any, keys: Any, now: Callable[[], int], link: Any, **kw: Any) -> Any:
        hb = resync.heartbeat
        hb.idle()
        now()  # the thread's own read: it checks in
        during.append(hb.age_ns(time.monotonic_ns()))
        readers.append(now)
        raise ClockSyncError("no answer")  # the series is over either way

    link = ClockLink(mission, "dn0", None)
    stop = StopFlag(install=False)
    resync = ClockResync(
        mission, "dn0", None, KeySpace(mission.vehicle), time.monotonic_ns, link, estimate,
        stop, lambda: False,
    )  # fmt: skip
    resync.start()
    try:
        resync.cue()
        assert resync.ended.wait(30.0)
        assert during and during[0] >= 0  # checked in during the series
        assert resync.heartbeat.age_ns(time.monotonic_ns()) == -1  # idle after it
        late = threading.Thread(target=readers[0])  # a late reply's callback
        late.start()
        late.join(10)
        assert resync.heartbeat.age_ns(time.monotonic_ns()) == -1
    finally:
        stop.set()
        resync.close()
