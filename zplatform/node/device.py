"""Device Node Main (thesis 4.14): entry and the triggered loop on zenoh.

:class:`DeviceNode` opens the session, waits for the CN, measures its clock
offset (:mod:`zplatform.runtime.clocksync`, the estimator ``clock.estimator`` names),
applies it once and locks the clock, declares the sync queryable, then, its
loop serving, announces liveliness: from that moment the CN may trigger loops. Its loop
waits for the CN's query (the trigger), answers it at once
(:meth:`DeviceLogic.trigger <zplatform.control.loop.DeviceLogic.trigger>`), then runs
:meth:`~zplatform.control.loop.DeviceLogic.run` with the query's loop number and one
local timestamp.

Contract: the loop thread alone decides what the node reports: a background
thread re-estimates the clock offset every ``clock.resync_s`` and hands each
result over; an estimate that jumps beyond the clock bound is refused and
counted, and the clock is never stepped. Clock exchanges wait at most their
timeout, counted in ``dnX_clock_timeouts`` (:class:`ClockTally`: one event a
second at most). The flight recorder never blocks the loop.

Start-up, clock re-sync and the recorder: docs/architecture.md#drivers.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from ..boards import board_health, close_board, open_board
from ..config import Mission
from ..control.intake import ProbeIntake, TriggerIntake
from ..control.loop import DeviceLogic
from ..control.watchdog import Watchdog
from ..core.auth import KeySet, Run, channel, load_keys
from ..core.datavector import DataVector
from ..core.events import EV, EventLog
from ..core.health import Heartbeat, Liveness, thread_deadlines_ns
from ..errors import (
    ClockSyncError,
    IntraHostError,
    NodeError,
    RecordingError,
    TransportError,
    ZPlatformError,
)
from ..recorder import FlightRecorder, open_recorder, summary_line
from ..runtime.bulk import NodeBulk, open_bulk
from ..runtime.clocksync import (
    RELEARN_S,
    RESYNC_EXCHANGES,
    ClockEstimate,
    ClockLink,
    Estimator,
    drift_exchanges,
    estimator_for,
    learn_run,
)
from ..runtime.process import StopFlag, realtime_setup
from ..runtime.scheduler import GcGuard
from ..runtime.sync import DeviceSync, SyncTrace, open_shm_server
from ..runtime.timebase import NodeClock
from ..runtime.transport import EventPublisher, KeySpace, NodeSession, wait_for_nodes
from ..telemetry.summary import DnSummary, board_line, board_trouble
from .health import NodeHealth

__all__ = ["ClockResync", "ClockTally", "DeviceNode", "run_device_node"]

log = logging.getLogger("zplatform.dn")


TIMEOUT_EVENT_EVERY_NS = 1_000_000_000
"""A ``clock_timeout`` event at most this often (the counter counts every one)."""


class ClockTally:
    """The loop thread's account of the clock exchanges, into the Data Vector.

    ``link``'s refusals (:class:`~zplatform.runtime.clocksync.ClockLink`) plus the
    estimates refused for a jump (:meth:`jump_refused`) go to
    ``dnX_clock_refused``, with a ``clock_refused`` event per :meth:`count`
    that met new ones; exchanges left unanswered (``link.timeouts``: a
    silent, slow or unreachable clock, a query dropped on a congested link)
    go to ``dnX_clock_timeouts``, with a ``clock_timeout`` event at most once
    a second (:data:`TIMEOUT_EVENT_EVERY_NS`). Never blocks, never raises.
    Not thread-safe: the loop thread alone calls it (the link's counters
    are written by the measuring thread and only read here)."""

    def __init__(self, dv: DataVector, node: str, link: ClockLink, events: EventLog) -> None:
        self.node = node
        self.link = link
        self.events = events
        self._refused_h = dv.handle(f"{node}_clock_refused")
        self._timeouts_h = dv.handle(f"{node}_clock_timeouts")
        self.jumps_refused = 0
        self._refused_seen = (0, 0)
        self._timeouts_seen = 0  # at the last clock_timeout event
        self._timeout_event_ns: int | None = None

    def jump_refused(self) -> None:
        """An estimate refused for jumping beyond the clock bound."""
        self.jumps_refused += 1
        self._refused_h.set(self.link.refused + self.jumps_refused)

    def count(self, t_ns: int) -> None:
        """Bring the counters up to date at loop time ``t_ns``; emit the events due."""
        link = self.link
        bad, other = link.refused_bad, link.refused_other
        seen_bad, seen_other = self._refused_seen
        if (bad, other) != (seen_bad, seen_other):
            self._refused_seen = (bad, other)
            self._refused_h.set(bad + other + self.jumps_refused)
            self.events.emit(
                EV.CLOCK_REFUSED,
                t_ns,
                node=self.node,
                n=bad + other - seen_bad - seen_other,
                auth=bad - seen_bad,
                replay=other - seen_other,
            )
        timeouts = link.timeouts
        if timeouts == self._timeouts_seen:
            return
        self._timeouts_h.set(timeouts)
        last = self._timeout_event_ns
        if last is not None and t_ns - last < TIMEOUT_EVENT_EVERY_NS:
            return  # counted; told with the next event
        self._timeout_event_ns = t_ns
        self.events.emit(
            EV.CLOCK_TIMEOUT,
            t_ns,
            node=self.node,
            n=timeouts - self._timeouts_seen,
            total=timeouts,
        )
        self._timeouts_seen = timeouts


class ClockResync:
    """A device node's re-sync thread (module doc): every ``clock.resync_s`` an
    estimate (``estimate``, over ``link``), handed to the loop thread as
    :attr:`measured`; and at once, at most once a
    :data:`~zplatform.runtime.clocksync.RELEARN_S`, on :meth:`cue` (the trigger
    intake's ``on_other_run``: a genuine trigger of another run), first
    forgetting the run so that the exchange asks it with a hello. With
    ``clock.resync_s`` 0 nothing is periodic and a cue asks the run alone
    (:func:`~zplatform.runtime.clocksync.learn_run`), measuring nothing.
    ``run_ended``: no periodic measurement while it says so (nobody serves
    the clock between runs), but a cue is answered (a control node's trigger
    came). :attr:`attempts` counts the attempts ended (each sets
    :attr:`done` for the loop thread and :attr:`ended`). Never writes what the
    loop uses; :meth:`close` stops it (at most 2 s)."""

    def __init__(
        self,
        mission: Mission,
        name: str,
        session: zenoh.Session,
        keys: KeySpace,
        now_ns: Callable[[], int],
        link: ClockLink,
        estimate: Estimator,
        stop: StopFlag,
        run_ended: Callable[[], bool],
    ) -> None:
        self.name = name
        self._resync_s = mission.clock.resync_s
        self._keep = mission.clock.keep_fraction
        self._session = session
        self._keys = keys
        self._now = now_ns
        self.link = link
        self._estimate = estimate
        self._stop = stop
        self._run_ended = run_ended
        self._cue = threading.Event()  # set: ask now, the run may be new
        self.heartbeat = Heartbeat("clock")
        self.measured: ClockEstimate | None = None
        """The newest estimate, for the loop thread (a reference swap)."""
        self.done = False
        """Set after every attempt; the loop thread clears it when it judges."""
        self.attempts = 0
        self.ended = threading.Event()
        """Set after every attempt (tests wait on it)."""
        self._thread = threading.Thread(target=self._loop, name="clock-resync", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def cue(self) -> None:
        """Ask the run now (any thread, never blocks)."""
        self._cue.set()

    def close(self) -> None:
        self._cue.set()  # wakes it to see the stop (the caller set it)
        self._thread.join(timeout=2)

    def _loop(self) -> None:
        # Idle between measurements; during one it checks in at every clock
        # read, i.e. every exchange (each waits at most its timeout).
        hb = self.heartbeat
        now_ns = self._now
        me = threading.get_ident()

        def now() -> int:
            # This thread's reads alone check in: zenoh's thread reads the
            # clock too (a reply's arrival), and a reply that came after its
            # exchange gave up, once the series had ended, checked in for an
            # idle thread, which then "stalled" waiting for its next re-sync
            # (THREAD_STALLED; aborts recovery_igniter from ARMED).
            if threading.get_ident() == me:
                hb.beat()
            return now_ns()

        hb.idle()
        last_relearn = -RELEARN_S
        periodic = self._resync_s > 0
        while True:
            nudged = self._cue.wait(self._resync_s if periodic else None)
            if self._stop.is_set():
                return
            if nudged:
                # A trigger of another run (intake.on_other_run): ask with a
                # hello, whose answer tells the run, at most once a RELEARN_S
                # (a replay of an earlier run's triggers costs one exchange
                # series a RELEARN_S, never more).
                wait_s = last_relearn + RELEARN_S - time.monotonic()
                if wait_s > 0 and self._stop.event.wait(wait_s):
                    return
                self._cue.clear()
                last_relearn = time.monotonic()
                self.link.forget()
            hb.beat()
            if self._run_ended() and not nudged:
                # Nobody serves the clock between runs: no measurement, and no
                # "re-sync failed" at the end of every flight. (A cue is a
                # control node's genuine trigger: one serves the clock again.)
                hb.idle()
                continue
            try:
                if not periodic:  # the run alone: clock.resync_s 0 never re-measures
                    if not learn_run(self._session, self._keys, now, self.link):
                        log.warning("%s: no control node told its run", self.name)
                else:
                    self.measured = self._estimate(
                        self._session,
                        self._keys,
                        now,
                        self.link,
                        exchanges=RESYNC_EXCHANGES,  # the clock server bounds askers by it
                        keep_fraction=self._keep,
                    )
            except Exception as exc:  # the CN may be gone; report and keep trying
                log.warning("%s clock re-sync failed: %s", self.name, exc)
            finally:
                hb.idle()
            self.attempts += 1
            self.done = True
            self.ended.set()


class StarvedWait:
    """Whether the device node's own starvation, not the control node's
    silence, explains a wait that found no trigger (the loop thread; no
    allocation).

    A wait that ended more than ``overslept_ns`` after the last wake-up means
    this process was not scheduled (a loaded box): zenoh's thread starved with
    the loop's, and a trigger may still wait unread in its socket. The
    driver then waits one more idle period before the watchdog judges, once
    per silence (reset by a trigger), so a control node truly gone costs one
    period more, and only on a box that starved this node."""

    __slots__ = ("_graced", "_last", "_overslept")

    def __init__(self, overslept_ns: int, now_ns: int) -> None:
        self._overslept = overslept_ns
        self._last = now_ns
        self._graced = False

    def idle(self, now_ns: int) -> bool:
        """A wait ended without a trigger at ``now_ns`` (monotonic): True to
        wait once more before the watchdog judges."""
        late = now_ns - self._last > self._overslept
        self._last = now_ns
        if late and not self._graced:
            self._graced = True
            return True
        return False

    def triggered(self, now_ns: int) -> None:
        """A trigger came at ``now_ns``: the next silence starts afresh."""
        self._last = now_ns
        self._graced = False


class DeviceNode:
    """One DN process. Build, :meth:`start` (blocks for clock sync), :meth:`run`.

    ``sync_trace``: a :data:`~zplatform.runtime.sync.SyncTrace` for the sync's hops
    (benchmarks)."""

    def __init__(
        self,
        mission: Mission,
        name: str,
        *,
        stop: StopFlag | None = None,
        clock: NodeClock | None = None,
        lowlatency: bool | None = None,
        keys: KeySet | None = None,
        sync_trace: SyncTrace | None = None,
    ) -> None:
        if name not in mission.device_nodes:
            raise NodeError(f"{name!r} is not a device node of mission {mission.mission!r}")
        self.mission = mission
        self.name = name
        self.stop = stop or StopFlag(install=False)
        self.clock = clock or NodeClock()
        # A trigger stamped (CN time) more than a period ago belongs to a loop
        # the CN has already closed: answer it, do not run it.
        # The control node's run (zplatform.core.auth.Run), learned by the clock
        # exchange before the sync queryable is declared: triggers and probe
        # questions of another run (an earlier run's, replayed) are refused.
        self.auth_run = Run()
        self.logic = DeviceLogic(
            mission, name, stale_after_ns=mission.period_ns, keys=keys, run=self.auth_run
        )
        self.dv = self.logic.dv
        self._keys = keys
        # The clock exchange, tagged with this node's link key; one thread
        # measures at a time (start-up, then the re-sync thread).
        self.clock_link = ClockLink(mission, name, keys, run=self.auth_run)
        self.ns = NodeSession(mission, name, announce=False, lowlatency=lowlatency)
        # One estimator for the start-up sync, its residual and the re-syncs.
        self.estimate_offset = estimator_for(mission.clock)
        self._offset_h = self.dv.handle(f"{name}_clock_offset_ns")
        self._drift_h = self.dv.handle(f"{name}_clock_drift_ns")
        self._overruns = self.dv.handle(f"{name}_loop_overruns")
        self._tally = ClockTally(self.dv, name, self.clock_link, self.logic.events)
        self._bound_ns = round(mission.clock.offset_bound_ms * 1e6)
        self.drift_ns = 0
        self.loops = 0
        self.sync: DeviceSync | None = None
        self._sync_trace = sync_trace
        self.bulk: NodeBulk | None = None
        self._events: EventPublisher | None = None
        self.flight_recorder: FlightRecorder | None = None
        # The re-sync thread (ClockResync), from start() on: its newest
        # measurement is a reference swap the loop thread judges.
        self._resync: ClockResync | None = None
        # Every thread this node runs checks in (zplatform.core.health).
        self.liveness = Liveness(thread_deadlines_ns(mission))
        self._loop_hb = self.liveness.add(Heartbeat("loop"))
        board_hb = getattr(self.logic.board, "heartbeat", None)
        if isinstance(board_hb, Heartbeat):  # a board with an I/O thread of its own
            self.liveness.add(board_hb)
        self.health: NodeHealth | None = None
        if mission.health is not None:
            self.health = NodeHealth(mission, name, self.liveness, session=self.ns.session)
            self.logic.attach_health(self.health)
        wd = mission.nodes[name].watchdog
        self.watchdog = (
            Watchdog(wd, name, self.liveness, self.logic.events) if wd is not None else None
        )
        self._stopped_cleanly = False

    def start(self, ready_timeout_s: float = 60.0) -> int:
        """Wait for the CN, sync the clock, declare the queryable (:meth:`run`
        announces the node's liveliness, once it serves).

        Returns the applied offset (ns). Raises NodeError on failure.
        """
        s, keys, m = self.ns.session, self.ns.keys, self.mission
        deadline = time.monotonic() + ready_timeout_s
        try:
            # Whichever control node runs (a redundant mission's standby may
            # command by the time this node starts); the commander serves the clock.
            wait_for_nodes(s, keys, m.control_nodes, ready_timeout_s, self.stop.event, any_of=True)
            est = self._estimate_by(deadline, m.clock.exchanges)
        except (TransportError, ClockSyncError) as exc:
            raise NodeError(f"{self.name} cannot start: {exc}") from exc
        try:
            open_board(self.logic.board)
        except ZPlatformError as exc:
            raise NodeError(f"{self.name} cannot start: its board: {exc}") from exc
        self.clock.apply_offset(est.offset_ns)
        self.clock.lock()
        self._offset_h.set(est.offset_ns)
        # What the bound is about: the error left after the correction. One
        # more exchange series on the corrected clock measures it; the CN
        # checks it before loop 1 and the background re-sync keeps it in
        # telemetry (dnX_clock_drift_ns) for the whole run.
        try:
            res = self.estimate_offset(
                s,
                keys,
                self.clock.now_ns,
                self.clock_link,
                exchanges=drift_exchanges(m.clock),
                keep_fraction=m.clock.keep_fraction,
            )
        except (TransportError, ClockSyncError) as exc:
            raise NodeError(f"{self.name} cannot start: {exc}") from exc
        self.drift_ns = res.offset_ns
        self._drift_h.set(res.offset_ns)
        self._tally.count(self.clock.now_ns())  # events go out with the first flush
        log.info(
            "%s clock corrected by %+.3f ms (%s estimator, delay %.0f us, %d of %d exchanges "
            "kept); residual %+.3f us (%s)",
            self.name,
            est.offset_ns / 1e6,
            est.estimator,
            est.delay_ns / 1e3,
            est.kept,
            est.exchanges,
            res.offset_ns / 1e3,
            res.estimator,
        )
        trigger_intake: TriggerIntake[zenoh.Query] = TriggerIntake(
            m,
            self.name,
            channel(self._keys, f"cn_to_{self.name}", self.auth_run),
            self.clock.now_ns,
        )
        assert trigger_intake.box is not None
        # A genuine trigger of another run: the control node may have started
        # a new one; the re-sync thread asks the run now (at most once a
        # RELEARN_S), not at its next re-sync.
        self._resync = ClockResync(
            m,
            self.name,
            s,
            keys,
            self.clock.now_ns,
            self.clock_link,
            self.estimate_offset,
            self.stop,
            lambda: self.logic.run_ended,
        )
        trigger_intake.on_other_run = self._resync.cue
        # The intra-host link (transport.intra_host): its triggers pass the
        # same intake; a pinned `shm` that cannot open stops the node.
        try:
            shm = open_shm_server(m, self.name)
        except IntraHostError as exc:
            raise NodeError(f"{self.name} cannot open its intra-host link: {exc}") from exc
        self.sync = DeviceSync(
            s,
            keys,
            self.name,
            self.clock.now_ns,
            # The intake's own channel: zenoh's thread checks tags with it.
            intake=trigger_intake,
            probes=(
                ProbeIntake(
                    self.name,
                    channel(self._keys, f"probe_cn_to_{self.name}", self.auth_run),
                    trigger_intake.box.waker,
                    period_ns=m.period_ns,
                    askers=len(m.control_nodes),
                    clock_ns=self.clock.now_ns,
                    bound_ns=round(m.clock.offset_bound_ms * 1e6),
                )
                if m.standby is not None
                else None
            ),
            trace=self._sync_trace,
            shm=shm,
            path=self.dv.handle(f"{self.name}_sync_path"),
        )
        self.bulk = open_bulk(s, m, self.name, self.logic, self._keys, self.clock.now_ns)
        if self.name in m.recording_nodes:
            try:
                rec = open_recorder(
                    m,
                    self.name,
                    self.dv,
                    run=self.clock.now_ns(),
                    authenticated=self._keys is not None,
                )
            except RecordingError as exc:
                raise NodeError(f"{self.name} cannot start its flight recorder: {exc}") from exc
            rec.attach(self.dv, self.logic.events)
            self.flight_recorder = rec
            self.sync.keep_reply = True  # it records each reply after the loop ran
            self.liveness.add(rec.heartbeat)
            log.info("%s flight recorder: %s", self.name, rec.directory)
        self._events = EventPublisher(
            s,
            keys.events(self.name),
            self.logic.events,
            channel(self._keys, f"events_{self.name}", self.auth_run),
            recorder=self.flight_recorder,
        )
        # Without periodic re-syncs (clock.resync_s: 0) the thread still
        # answers the intake's cue, with hellos only: the run may be new.
        if m.clock.resync_s > 0 or self._keys is not None:
            self.liveness.add(self._resync.heartbeat)
            self._resync.start()
        else:
            self._resync = None  # no re-sync, and no run to learn
        return est.offset_ns

    def _estimate_by(self, deadline: float, exchanges: int) -> ClockEstimate:
        """The clock's offset to the commander's; while no control node serves
        the clock yet (a standby is alive before the commander runs), ask
        again every 0.1 s until ``deadline`` (then the last ClockSyncError)."""
        m = self.mission
        while True:
            try:
                return self.estimate_offset(
                    self.ns.session,
                    self.ns.keys,
                    self.clock.now_ns,
                    self.clock_link,
                    exchanges=exchanges,
                    keep_fraction=m.clock.keep_fraction,
                )
            except ClockSyncError:
                if m.standby is None or time.monotonic() > deadline or self.stop.is_set():
                    raise
            self.stop.event.wait(0.1)

    def _take_measured(self, t_ns: int) -> None:
        """Loop thread: accept or refuse the re-sync thread's newest estimate
        (module doc), and count the clock replies it refused."""
        rs = self._resync
        assert rs is not None
        rs.done = False
        est, rs.measured = rs.measured, None
        self._tally.count(t_ns)
        if est is None:
            return
        jump = est.offset_ns - self.drift_ns
        if abs(jump) > self._bound_ns:
            self._tally.jump_refused()
            self.logic.events.emit(
                EV.CLOCK_JUMP_REFUSED,
                t_ns,
                node=self.name,
                new_ms=est.offset_ns / 1e6,
                jump_ms=jump / 1e6,
                old_ms=self.drift_ns / 1e6,
                bound_ms=self._bound_ns / 1e6,
            )
            return
        self.drift_ns = est.offset_ns
        self._drift_h.set(est.offset_ns)

    def run(self, *, max_loops: int | None = None, realtime: bool = True) -> None:
        """Serve triggers until stopped (or ``max_loops``). Blocks."""
        assert self.sync is not None and self._events is not None, "start() first"
        nc = self.mission.nodes[self.name]
        if realtime:
            realtime_setup(nc.priority, nc.cpu)
        period = self.mission.period_ns
        logic = self.logic
        wait = self.sync.wait
        run = logic.run
        now = self.clock.now_ns
        mono = time.monotonic_ns
        loop_hb = self._loop_hb
        health = self.health
        wd = self.watchdog
        loop_hb.beat()
        if health is not None:
            health.start()
        if wd is not None:
            wd.open()
        gc_guard = GcGuard()
        gc_guard.freeze_after_startup()
        # Alive only now, serving: announced at the end of start(), the token
        # let the control node's warm-up query a node that was still
        # promoting its threads and collecting (tens of ms): its queries went
        # unanswered, and it re-declared its queriers as if zenoh had lost a
        # route (query_recovered, a warning at most starts).
        self.ns.announce()
        try:
            # Wake at least once a period without a trigger: the watchdog
            # safes the node when the control node has gone quiet.
            idle_s = min(0.2, period / 1e9)
            starved = StarvedWait(int(idle_s * 1e9) + period, mono())
            while not self.stop.is_set():
                if not wait(logic, idle_s):
                    m0 = mono()
                    loop_hb.beat_at(m0)  # alive, if idle: no trigger came
                    if starved.idle(m0):
                        continue  # this node overslept: a trigger may be unread yet
                    logic.watchdog(now())
                    if wd is not None:
                        wd.stroke(m0, now())
                    self._events.flush()  # a safing, refused queries: cheap when none
                    continue
                t = now()
                m0 = mono()
                starved.triggered(m0)
                loop_hb.beat_at(m0)
                if health is not None:  # lateness: from the CN's scheduled start
                    health.note(t - logic.last_t_ns)
                resync = self._resync
                if resync is not None and resync.done:  # an attempt ended: judge it here
                    self._take_measured(t)
                rec = self.flight_recorder
                if rec is not None:  # its counters into the next reply
                    rec.tick(t)
                run(t)  # with the bulk channels, in the loop's order
                if rec is not None and self.sync.reply is not None:
                    rec.frame(logic.triggered, self.sync.reply, t)
                if wd is not None:
                    wd.stroke(m0, t)
                self._events.flush()
                if health is not None:
                    health.kick()  # sample now, in the slack before the next trigger
                # Slack until the next trigger is due: gc only runs there.
                slack = t + period - now()
                if slack < 0:
                    self._overruns.bump()
                    if health is not None:
                        health.overran()
                else:
                    gc_guard.on_slack(slack)
                self.loops += 1
                if max_loops is not None and self.loops >= max_loops:
                    break
        finally:
            gc_guard.restore()
        self._stopped_cleanly = True

    def summary(self) -> DnSummary:
        """The node's run so far; ``board`` is its board's health for a board
        with a link (:attr:`zplatform.control.loop.DeviceLogic.board_link`), else None."""
        return DnSummary(
            node=self.name,
            loops=self.loops,
            clock_offset_ns=int(self._offset_h.get()),
            clock_drift_ns=self.drift_ns,
            bad_frames=int(self.dv.get(f"{self.name}_bad_frames")),
            errors=int(self.dv.get(f"{self.name}_errors")),
            stale_queries=self.logic.stale,
            safed_why=self.logic.safed_why if self.logic.safed else "",
            board=board_health(self.logic.board) if self.logic.board_link else None,
        )

    def close(self) -> None:
        """Safe the outputs, publish the last events, release everything."""
        self.stop.set()
        # A clean exit leaves the vehicle safe: actuators, then the board.
        self.logic.safe(self.clock.now_ns(), "the node is stopping", exiting=True)
        if self._events is not None:
            self._events.undeclare()  # flushes the dn_safed event first
        if self.sync is not None:
            self.sync.close()
        if self.bulk is not None:
            self.bulk.close()
        if self._resync is not None:
            self._resync.close()
        if self.watchdog is not None:
            # A loop that ended in an exception leaves the watchdog armed.
            self.watchdog.close(clean=self._stopped_cleanly)
        if self.health is not None:
            self.health.close()
        close_board(self.logic.board)
        if self.flight_recorder is not None:
            self.flight_recorder.close()
            log.info("%s flight recorder: %s", self.name, summary_line(self.flight_recorder))
        self.ns.close()


def run_device_node(
    mission: Mission,
    name: str,
    *,
    realtime: bool = True,
    ready_timeout_s: float = 60.0,
    key_file: str | None = None,
) -> DnSummary:
    """Entry function: start, serve until SIGTERM. Blocks; returns the summary.
    KeyError_ before anything starts when this node's key is missing."""
    stop = StopFlag()
    node = DeviceNode(mission, name, stop=stop, keys=load_keys(mission, name, key_file))
    try:
        node.start(ready_timeout_s)
        node.run(realtime=realtime)
        summary = node.summary()
    finally:
        node.close()
    if summary.board is not None:  # once, at exit: the link's account for the operator
        level = logging.WARNING if board_trouble(summary.board) else logging.INFO
        log.log(level, "%s", board_line(name, summary.board))
    return summary
