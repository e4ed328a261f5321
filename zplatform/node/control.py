"""Control Node Main (thesis 4.13): entry and the periodic loop on zenoh.

:class:`ControlNode` opens the session, serves the clock, waits for every DN
to be alive, reads each DN's clock offset with a warm-up sync (refusing to
start beyond the mission bound) and loads the parameter file
(:meth:`ControlNode.wait_ready`), then runs the loop of :mod:`zplatform.control.loop`
on absolute deadlines (:meth:`ControlNode.run`): ``begin`` at the loop's
scheduled start, sync every DN, ``finish`` with at most one ground frame,
publish the telemetry every Nth loop. The run's last loop is flagged final
(the last of ``max_loops``, or one more after a stop was asked for); after
a takeover the new commander ends the run at that loop of the schedule.

Contract: initialisation errors raise :class:`~zplatform.errors.NodeError`
(the CLI prints and exits non-zero); errors after start are counted in the
Data Vector and the loop goes on. The loop thread never blocks on disk: the
loop recorder (``record``), parameter saves, the flight recorder and the
gap-fill server run on threads of their own.

Start-up, the last loop and what runs beside the loop: docs/architecture.md#drivers.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from .. import trace
from ..config import Mission
from ..control.failover import Standby, probe_wait_ns
from ..control.handoff import Mailbox
from ..control.intake import (
    INBOX,
    CnRefusals,
    MirrorIntake,
    RefusalLog,
    ReplyCheck,
    RequestIntake,
)
from ..control.loop import ControlLogic
from ..control.params import ParamSaver, params_path, read_params_file
from ..control.role import (
    Command,
    ControlRole,
    Probe,
    Release,
    Resume,
    StandDown,
    StartOver,
    Take,
    check_recorded,
)
from ..control.watchdog import Watchdog
from ..core.auth import KeySet, Run, channel, load_keys, new_run_epoch
from ..core.codec import Frame
from ..core.datavector import DataVector
from ..core.events import EV
from ..core.health import Heartbeat, Liveness, thread_deadlines_ns
from ..core.messages import wildcard_sync_for
from ..errors import ClockSyncError, IntraHostError, NodeError, RecordingError, TransportError
from ..ground.logic import default_max_age_ns
from ..recorder import FlightRecorder, RecorderReader, open_recorder, recorder_dir, summary_line
from ..recorder.server import RecorderServer
from ..runtime.bulk import open_bulk
from ..runtime.clocksync import ClockLink, ClockServer, estimator_for
from ..runtime.process import StopFlag, realtime_setup
from ..runtime.queries import unanswered_loops
from ..runtime.scheduler import GcGuard, PeriodicLoop
from ..runtime.sync import ControlSync, ProbeSync, SyncTrace, TapPublisher, open_shm_links
from ..runtime.timebase import NodeClock
from ..runtime.tmiox import open_telemetry_publisher
from ..runtime.transport import EventPublisher, NodeSession, wait_for_nodes
from ..sim.replay_recording import Recorder
from ..telemetry.summary import CnSummary, LoopWork, cn_summary
from .health import NodeHealth

__all__ = ["ControlNode", "run_control_node"]

log = logging.getLogger("zplatform.cn")

_DROP = zenoh.CongestionControl.DROP


class ControlNode:
    """The CN process: session, sync, ground input, telemetry, logic.

    Build, then :meth:`run`; :meth:`close` releases every zenoh entity. Not
    thread-safe: one loop thread. ``sync_trace``: a
    :data:`~zplatform.runtime.sync.SyncTrace` for the sync's hops (benchmarks).
    ``params_file``: the parameter file (default
    :func:`~zplatform.control.params.params_path`; unused without ``params``).
    """

    def __init__(
        self,
        mission: Mission,
        *,
        name: str = "cn",
        stop: StopFlag | None = None,
        lowlatency: bool | None = None,
        clock: NodeClock | None = None,
        keys: KeySet | None = None,
        sync_trace: SyncTrace | None = None,
        params_file: str | Path | None = None,
    ) -> None:
        if name not in mission.control_nodes:
            raise NodeError(
                f"{name!r} is not a control node of mission {mission.mission!r}: "
                f"{mission.control_nodes}"
            )
        self.mission = mission
        self.name = name
        self.keys = keys
        self.redundant = mission.standby is not None
        self.stop = stop or StopFlag(install=False)
        self.clock = clock or NodeClock()
        if not self.redundant:
            self.clock.lock()  # the CN is the reference clock: never adjusted
        # (In a redundant mission a control node locks its clock once it knows
        # its role: a standby first sets it by the commander's, module doc.)
        # The run's epoch: this clock's start, its low bits random, so unique
        # per run of the CN even on a clock that repeats across boots: the
        # run every frame's key is bound to (zplatform.core.auth.new_run_epoch).
        self.clock_epoch = new_run_epoch(self.clock.now_ns())
        self.logic = ControlLogic(mission, keys=keys, epoch=self.clock_epoch, name=name)
        self.dv: DataVector = self.logic.dv
        # The intra-host links (transport.intra_host), before the session: a
        # pinned `shm` that cannot open stops the node with nothing to undo.
        try:
            shm_links = open_shm_links(mission, name)
        except IntraHostError as exc:
            raise NodeError(f"control node cannot open its intra-host links: {exc}") from exc
        # The telemetry to a ground node on this host (zplatform.runtime.tmiox),
        # beside zenoh's; a redundant mission's frame is read after the send
        # (the standby's mirror), so it is never encoded into a loan there.
        try:
            self._tm_iox = open_telemetry_publisher(mission, self.logic.telemetry_length)
        except TransportError as exc:
            for link in shm_links or ():
                if link is not None:
                    link.client.close()
            raise NodeError(f"control node cannot open its intra-host telemetry: {exc}") from exc
        self._tm_lend = self._tm_iox is not None and not self.redundant
        self.ns = NodeSession(mission, name, announce=False, lowlatency=lowlatency)
        s = self.ns.session
        space = self.ns.keys
        # Every thread this node runs checks in (zplatform.core.health).
        self.liveness = Liveness(thread_deadlines_ns(mission))
        self._loop_hb = self.liveness.add(Heartbeat("loop"))
        # The commander serves the clock; a mission's only control node from
        # the start (the device nodes set their clocks by it before anything
        # runs); in a redundant mission the node that commands, once it knows
        # it does (wait_ready).
        self.clock_server: ClockServer | None = None
        if not self.redundant:
            self._serve_clock()
        # The intakes get channels of their own (zenoh's threads check tags
        # with them; the loop's are not shared across threads).
        self.sync = ControlSync(
            s,
            space,
            mission.device_nodes,
            mission.sync_timeout_ns,
            query_timeout_s=max(mission.period_ns / 1e9, 0.01),
            checks=[
                ReplyCheck(mission, dn, channel(keys, f"{dn}_to_cn", self.logic.auth_run))
                for dn in mission.device_nodes
            ],
            wildcard=wildcard_sync_for(mission),
            trace=sync_trace,
            shm=shm_links,
            # A lost route recovered well before the DNs' watchdog.
            unanswered=unanswered_loops(mission.faults.dn_watchdog_loops),
        )
        self._path_changes: list[tuple[str, str, str]] = []
        # The command inbox (zplatform.control.intake): size, tag, this run, a number
        # above every one seen, then bounded, newest kept. A flood of junk or
        # of replayed requests is refused as it arrives and counted; it costs
        # neither memory nor the operator's fresh command.
        # A mission without a ground node has no request region: no intake,
        # and an inbox that stays empty.
        self._requests: RequestIntake | None = None
        self._inbox: Mailbox[tuple[None, bytes]] = Mailbox(1)
        self._taken: list[tuple[None, bytes]] = []
        self._seen_dropped = 0
        self._refused = CnRefusals()
        # Mirrors the intake refused, not yet in the vector (cn_mirror_refused):
        # a standby's, while it follows, go in with its first loop in command.
        self._mirror_unfiled = 0
        # Queriers the sync declared again (a live DN unanswered, zenoh#2517).
        self._recoveries: list[tuple[str, int]] = []
        self._recovered_dns: dict[str, int] = {}
        self._recovery_log = RefusalLog(1)
        self._recovery_unsent = False
        self._grounds: list[bytes] = []
        self._gsub: zenoh.Subscriber[Any] | None = None
        if not self.redundant:  # a redundant mission's commander opens it to command
            self._take_requests()
        # Telemetry goes out every telemetry_divisor loops, but only to a
        # subscriber: a whole-vector snapshot nobody takes (a vehicle flying
        # without its ground, a bench) is not copied into zenoh for nothing.
        # The flight recorder records it all the same.
        self._tm_pub = TapPublisher(s, space.telemetry, exact=True)
        # The flight recorder: opened before anything runs, so a directory it
        # cannot use (or one another CN holds) stops the node on the pad.
        self.flight_recorder: FlightRecorder | None = None
        self._rec_server: RecorderServer | None = None
        # What this node recorded last (a restart in flight resumes from it).
        self._recorded: Frame | None = None
        if name in mission.recording_nodes:
            self._recorded = _last_recorded(mission, name, self.logic, keys)
            try:
                rec = open_recorder(
                    mission, name, self.dv, run=self.clock_epoch, authenticated=keys is not None
                )
            except RecordingError as exc:
                self.ns.close()
                raise NodeError(f"control node cannot start its flight recorder: {exc}") from exc
            rec.attach(self.dv, self.logic.events, prefix="cn")  # either CN: cn_rec_*
            self.flight_recorder = rec
            self.liveness.add(rec.heartbeat)
            log.info("flight recorder: %s", rec.directory)
            if not self.redundant:  # a redundant mission's commander serves it
                self._serve_recorder()
        self._events = EventPublisher(
            s,
            space.events(name),
            self.logic.events,
            channel(keys, f"events_{name}", self.logic.auth_run),
            recorder=self.flight_recorder,
        )
        self._radio = _Radio(mission, s, space.downlink) if mission.downlink.ccsds else None
        self.bulk = open_bulk(s, mission, "cn", self.logic, keys)
        self.health: NodeHealth | None = None
        if mission.health is not None:
            self.health = NodeHealth(mission, "cn", self.liveness, session=s)
            self.logic.attach_health(self.health)
        wd = mission.nodes[name].watchdog
        self.watchdog = (
            Watchdog(wd, "cn", self.liveness, self.logic.events) if wd is not None else None
        )
        self.params_file = Path(params_file) if params_file else params_path(mission)
        self._saver = ParamSaver(self.params_file) if mission.params else None
        if self._saver is not None:
            self.liveness.add(self._saver.heartbeat)
        self._skipped = 0
        self._gap = False  # the next loop is a takeover's first
        self._take_at = 0
        self._origin: int | None = None  # a resumed run's schedule (monotonic ns)
        self._next_recorder: Recorder | None = None  # a standby's --record, not started
        self._stopped_cleanly = False
        self._last_step: int | None = None  # self.loops after the run's planned last loop
        # The run's last loop in the vehicle's numbering (the schedule's), so
        # a run with an end ends whichever control node then commands: a
        # commander from the start runs its ``max_loops`` (more loop numbers
        # when the box made it skip some: they are counted), a node that took
        # command mid-run ends at this loop, and a follower stops with the
        # commander's final loop or, past this loop, once it falls silent
        # (without it, after a takeover neither node would ever end).
        self._end_loop: int | None = None
        # Failover (zplatform.control.failover): the mirror out and in, the probes, the
        # other control node's liveliness, and the standby while not commanding.
        # Who commands, resumes, follows, stands down and takes over: the
        # role (zplatform.control.role) decides; this node delivers and carries out.
        self.role = ControlRole(mission, self.logic, keys)
        self._peer_alive = False  # the other control node's standby token (zenoh's thread)
        self.takeovers = 0
        """Times this node took command (a standby's takeovers)."""
        if self.redundant:
            self._mirror_pub = s.declare_publisher(space.mirror, congestion_control=_DROP)
            # The mirror's intake (zplatform.control.intake.MirrorIntake): size, tag,
            # range, from the other node, newer in (term, loop); only then the
            # bounded mailbox, so junk and replays never displace a genuine one.
            self.mirror_intake = MirrorIntake(
                mission, name, channel(keys, "mirror", self.logic.auth_run)
            )
            assert self.mirror_intake.box is not None
            self._mirrors: Mailbox[tuple[None, bytes]] = self.mirror_intake.box
            self._mirror_log = RefusalLog(4)  # size, bad, stale, then those unchecked
            self._mirror_sub = s.declare_subscriber(
                space.mirror,
                zenoh.handlers.Callback(self._on_mirror, indirect=False),
                allowed_origin=zenoh.Locality.REMOTE,
            )
            # Its own channels for the replies' screen (zenoh's threads):
            # junk never pushes a device node's reply out (issue 25).
            screens = [
                channel(keys, f"probe_{dn}_to_cn", self.logic.auth_run)
                for dn in mission.device_nodes
            ]
            self.probes = ProbeSync(
                s, space, mission.device_nodes, probe_wait_ns(mission), screens=screens
            )
            self._peer = next(n for n in mission.control_nodes if n != name)
            self._peer_seen = False
            self._ready_token: zenoh.LivelinessToken | None = None
            self._peer_sub = s.liveliness().declare_subscriber(
                space.standby(self._peer),
                zenoh.handlers.Callback(self._on_peer, indirect=False),
                history=True,
            )
        if not self.redundant:
            # The device nodes wait for a control node's token, then set their
            # clocks by its server (served above). A redundant mission's `cn`
            # announces in wait_ready, once it knows whether it serves the
            # clock; a standby, once it follows.
            self.ns.announce()
        self.first_loop_ns = 0
        self.last_loop_ns = 0
        self.loops = 0
        self.recorder: Recorder | None = None
        # Work time of each loop (sync and logic, not the sleep), for the
        # summary: a preallocated ring, one int store per loop.
        self._work = np.zeros(1 << 16, dtype=np.int64)
        self._mono = time.monotonic_ns
        self._on_loop: Callable[[int, int, int], None] | None = None  # run()'s hook

    # -- what a commander serves, opened when it commands ----------------------
    def _serve_clock(self) -> None:
        if self.clock_server is None:
            self.clock_server = ClockServer(
                self.ns.session,
                self.ns.keys,
                self.clock.now_ns,
                self.mission,
                self.keys,
                run=self.logic.auth_run,
            )
            self.liveness.add(self.clock_server.heartbeat)

    def _take_requests(self) -> None:
        """The command inbox (zplatform.control.intake): size, tag, this run, a number
        above every one seen, then bounded, newest kept. A flood of junk or of
        replayed requests is refused as it arrives and counted; it costs
        neither memory nor the operator's fresh command. A mission without a
        ground node has no request region: no intake, and an inbox that
        stays empty."""
        m = self.mission
        if not m.has_ground or self._requests is not None:
            return
        commands = self.logic.commands
        self._requests = RequestIntake(
            m,
            # Bound to this run: a request tagged in another is refused before
            # any decode (zplatform.core.auth.RunError, counted stale).
            channel(self.keys, "gn_to_cn", self.logic.auth_run),
            int(self.dv.get("cn_epoch")),
            lambda: commands.last_seq,
            INBOX,
        )
        assert self._requests.box is not None
        self._inbox = self._requests.box
        self._gsub = self.ns.session.declare_subscriber(
            self.ns.keys.gn_to_cn,
            zenoh.handlers.Callback(self._on_ground, indirect=False),
        )

    def _serve_recorder(self) -> None:
        rec, m = self.flight_recorder, self.mission
        if rec is None or self._rec_server is not None:
            return
        assert m.recorder is not None
        self._rec_server = RecorderServer(
            self.ns.session,
            self.ns.keys.recorder,
            rec,
            channel(self.keys, "telemetry"),
            now_ns=self.clock.now_ns,
            max_age_ns=default_max_age_ns(m),
            serve_bps=m.recorder.serve_bps,
            divisor=m.telemetry_divisor,
            # Its own channel and run (the serving thread's): tags the
            # recorded events a ground's event gap fill asks for.
            events=channel(self.keys, f"events_{self.name}", Run()),
        )

    def _stop_serving(self) -> None:
        """A commander standing down: the clock, the inbox and the recorder's
        server are the new commander's now."""
        if self.clock_server is not None:
            self.liveness.remove(self.clock_server.heartbeat)
            self.clock_server.close()
            self.clock_server = None
        if self._gsub is not None:
            self._gsub.undeclare()
            self._gsub = None
        self._requests = None
        self._inbox = Mailbox(1)
        if self._rec_server is not None:
            self._rec_server.close()
            self._rec_server = None

    def _on_peer(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: one flag, read by the loop (the other node's standby token).
        self._peer_alive = sample.kind == zenoh.SampleKind.PUT

    def _on_mirror(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: the intake's checks and the hand-off, nothing more.
        self.mirror_intake.admit(sample.payload, None)

    def _mirror_refusals(self, t_ns: int) -> None:
        """The mirrors the intake refused since the last call, evented at most
        once a second, and counted for ``cn_mirror_refused`` (the next loop's
        :meth:`_take_refusals`; the loop thread, every loop or beat)."""
        intake = self.mirror_intake
        counts = intake.take_counts()
        self._mirror_unfiled += sum(counts)
        ev = self._mirror_log.add(t_ns, *counts, intake.took_unchecked)
        if ev is not None:
            unchecked = (
                f"; {ev[3]} of them dropped after their header, unchecked (the body-MAC "
                "budget spent)"
                if ev[3]
                else ""
            )
            self.logic.events.emit(
                EV.BAD_FRAME,
                t_ns,
                source=f"{sum(ev[:3])} mirror frame(s)",
                reason=f"refused as they arrived by {self.name}: {ev[0]} of a wrong size, "
                f"{ev[1]} with bad tags or values out of range, {ev[2]} not newer than the "
                "newest (replayed, or its own)" + unchecked,
            )

    def _on_ground(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: the intake's checks and the hand-off, nothing more.
        assert self._requests is not None  # subscribed only with a ground node
        self._requests.admit(sample.payload, None)

    def record(self, directory: str | Path, mission_source: str | Path) -> Recorder | None:
        """Record every loop's inputs into ``directory`` from now on (call
        after :meth:`wait_ready`). RecordingError if it cannot start. A
        standby (None returned) starts recording when it takes command, from
        the vector it took over (:func:`zplatform.sim.lockstep.replay` adopts a
        recording that starts mid-run); a node that stands down ends its
        recording there: a recording is one reign."""
        rec = Recorder(directory, self.mission, mission_source, self.dv, start=self.standby is None)
        self.liveness.add(rec.heartbeat)
        if self.standby is not None:  # made now; started when it takes command
            self._next_recorder = rec
            return None
        self.recorder = rec
        self.logic.recorder = rec
        return rec

    # -- start-up --------------------------------------------------------
    def wait_ready(
        self, timeout_s: float = 60.0, ground_wait_s: float | None = None
    ) -> dict[str, int]:
        """Wait for every DN, then read their clock offsets; returns them.

        Blocks up to ``timeout_s`` for the DNs; then, if the mission has a
        ground node, up to ``ground_wait_s`` for it (None: what is left of
        ``timeout_s``; 0: not at all) and starts without it after a warning.

        Raises NodeError naming the node whose clock error after correction
        exceeds the bound (:func:`check_clocks`), or the nodes that never
        came up.
        """
        m = self.mission
        dns = m.device_nodes
        start = time.monotonic()
        if self.redundant and self.name == "cn" and not self._alive_now(dns):
            # A fresh start (the device nodes are not up): they set their clocks
            # by cn's before they come up. Device nodes already running mean a
            # run may be going on: ask them first (_first_to_command).
            self._serve_clock()
        if self.redundant and self.name == "cn":
            # Only now: its token tells a starting device node that the clock
            # is served. Announced in __init__, the token came before the
            # server by this look for running device nodes (ALIVE_LOOK_S),
            # and a device node starting then found no clock: its 200
            # exchanges ended unanswered at once, counted and evented as a
            # silent clock (clock_timeout), before it asked again.
            self.ns.announce()
        if dns:
            try:
                wait_for_nodes(self.ns.session, self.ns.keys, dns, timeout_s, self.stop.event)
            except TransportError as exc:
                raise NodeError(f"control node cannot start: {exc}") from exc
        if self.redundant and not self._first_to_command(timeout_s):
            return {}
        if m.has_ground and ground_wait_s != 0:
            # Wait for the ground (alive = subscribed to telemetry) so its log
            # starts at loop 1; but never make flight depend on the ground link.
            # An explicit 0 means the caller does not wait (benches, or an
            # operator's --ground-wait 0), so it is not worth a warning.
            if ground_wait_s is None:
                ground_wait_s = max(0.0, timeout_s - (time.monotonic() - start))
            try:
                wait_for_nodes(
                    self.ns.session, self.ns.keys, ["gn"], ground_wait_s, self.stop.event
                )
            except TransportError:
                log.warning(
                    "ground node not alive after %.1f s: starting without it", ground_wait_s
                )
        if not dns:
            self._load_params()
            return {}
        # Warm-up syncs with loop 0: DNs answer (not applied as a loop) and
        # the replies carry each DN's measured clock offset.
        deadline = time.monotonic() + timeout_s
        logic = self.logic
        while True:
            self.sync.sync(logic.begin(0, self.clock.now_ns()), logic, warmup=True)
            if logic.pending == 0:
                break
            if time.monotonic() > deadline or self.stop.is_set():
                raise NodeError("control node cannot start: device nodes do not answer sync")
        offsets = {dn: int(self.dv.get(f"{dn}_clock_offset_ns")) for dn in dns}
        residuals = {dn: int(self.dv.get(f"{dn}_clock_drift_ns")) for dn in dns}
        check_clocks(offsets, residuals, m.clock.offset_bound_ms)
        # The warm-up counted rx/missed; the flight loop starts from zero,
        # once no warm-up reply can still arrive.
        self.sync.quiesce(logic, timeout_s=max(2 * m.period_ns / 1e9, 1.0))
        logic.reset_sync_counters()
        logic.events.drain()  # warm-up bad frames were logged; flight starts clean
        # Device nodes that ran loops and were not told the run ended: this
        # node restarted in flight (its run goes on without it).
        if self._resume():
            return offsets
        self._load_params()
        return offsets

    def _resume(self) -> bool:
        """Restarted while the device nodes are mid-run (their loops, from the
        warm-up; or a driverless run this node resumes in a new term): the role
        takes up the run from this node's own flight recorder, its newest
        telemetry frame (:meth:`~zplatform.control.role.ControlRole.resume`), never
        starting over in SAFE, or says why it starts over; this node carries
        it out: the schedule where it was (loop numbers follow time), the
        command inbox in the recorded epoch. Returns whether it resumed."""
        action = self.role.resume(
            self.flight_recorder is not None, self._recorded, self.clock.now_ns()
        )
        if isinstance(action, StartOver):
            log.error("%s restarted in flight and starts over: %s", self.name, action.why)
        if not isinstance(action, Resume):
            return False
        self._origin = self.clock.monotonic_at(action.origin)
        self._gap = True
        if self._requests is not None:
            self._requests.follow(int(self.dv.get("cn_epoch")))
        log.warning(
            "%s resumed the run in flight from its recorder (loop %d)", self.name, action.loop
        )
        return True

    def _alive_now(self, nodes: list[str]) -> bool:
        """Whether every one of ``nodes`` has its liveliness token now (a short
        look: tokens come with the subscriber's history)."""
        try:
            wait_for_nodes(self.ns.session, self.ns.keys, nodes, ALIVE_LOOK_S, self.stop.event)
        except TransportError:
            return False
        return True

    def _first_to_command(self, timeout_s: float) -> bool:
        """A redundant mission's control node at start: asks every device node
        what it runs (a STATUS probe round, :mod:`zplatform.control.fencing`). True:
        none has ever run a loop and this is ``cn``, the first commander: it
        starts the run (term 1). Else it follows as the standby: it sets its
        clock by the commander's and waits for its mirrors (a control node
        restarted in flight rejoins the flight this way, never in SAFE).
        NodeError when no device node answers."""
        role = self.role
        deadline = time.monotonic() + timeout_s
        while True:
            if self.probes.round(role.status_probe(self.clock.now_ns()), role.answer):
                break
            if time.monotonic() > deadline or self.stop.is_set():
                raise NodeError(f"{self.name} cannot start: no device node answers its probe")
        action = role.start()
        if isinstance(action, Command):
            self._serve_clock()
            self.clock.lock()
            self._take_requests()
            self._serve_recorder()
            return True
        self._stop_serving()
        self._set_clock_by_commander(deadline)
        log.info(
            "%s follows as the standby: %s",
            self.name,
            f"the device nodes run term {action.term}" if action.ran else "the run has not begun",
        )
        return False

    def _set_clock_by_commander(self, deadline: float) -> None:
        """A standby's clock follows the commander's (its clock server, over the
        control nodes' link), measured as a device node measures it, then
        locked. NodeError when no commander serves the clock by ``deadline``."""
        m = self.mission
        # The exchange also tells the commander's run, which this node's
        # channels take on (mirrors, probes; zplatform.core.auth.Run).
        link = ClockLink(m, self.name, self.keys, run=self.logic.auth_run)
        estimate = estimator_for(m.clock)
        while True:
            try:
                est = estimate(
                    self.ns.session,
                    self.ns.keys,
                    self.clock.now_ns,
                    link,
                    exchanges=m.clock.exchanges,
                    keep_fraction=m.clock.keep_fraction,
                )
                break
            except ClockSyncError as exc:
                if time.monotonic() > deadline or self.stop.is_set():
                    raise NodeError(f"{self.name} cannot set its clock: {exc}") from exc
            self.stop.event.wait(0.1)
        self.clock.apply_offset(est.offset_ns)
        self.clock.lock()
        log.info(
            "%s clock set by the commander's: %+.3f ms (%s estimator, %d of %d exchanges kept)",
            self.name,
            est.offset_ns / 1e6,
            est.estimator,
            est.kept,
            est.exchanges,
        )

    def _load_params(self) -> None:
        """Load the parameter file into the Data Vector (its events go out
        with loop 1's). Blocks on one small file read, before the loop."""
        if self._saver is None:
            return
        status = self.logic.params.load(
            read_params_file(self.params_file), self.clock.now_ns(), source=str(self.params_file)
        )
        log.info("parameters: %s (%s)", status.name, self.params_file)

    # -- the loop ------------------------------------------------------------
    def _on_overrun(self, k: int, lateness_ns: int) -> None:
        # The periods the scheduler skips (every deadline passed: ceil of the
        # lateness over the period), not 1 per overrun: cn_loop_overruns
        # counts the loops no one ran, as after a takeover's gap. An input of
        # the next loop (replayed as such).
        self._skipped += -(-lateness_ns // self.mission.period_ns)
        if self.health is not None:
            self.health.overran()

    def step(self, k: int, deadline_ns: int) -> bool:
        """One loop; returns False to stop: after the run's final loop (the
        last of ``max_loops``, or the loop after a stop was asked for), or,
        in a redundant mission, when this node stands down (a newer term
        commands: :attr:`standby` is then set)."""
        m0 = self._mono()
        self._loop_hb.beat_at(m0)
        if self.health is not None:
            self.health.note(m0 - deadline_ns)
        loop = k + 1
        ready = self._peer_alive  # read once: zenoh's thread writes it
        if self.redundant and not self._still_commanding(ready):
            return False
        # The loop's one timestamp is its scheduled start, not the moment the
        # thread woke: loop n is then at t1 + (n - 1) * period exactly, as in
        # the lockstep runner, so timers and rate phases fire in the same loop
        # live and in sim (wake-up jitter would move a 3 s timer by a loop
        # about half the time).
        t = self.clock.at(deadline_ns)
        if self.loops == 0:
            self.first_loop_ns = t
        logic = self.logic
        if self.loops == 0 and self._last_step is not None and self._end_loop is None:
            self._end_loop = loop + self._last_step - 1  # a commander from the start
        end = self._end_loop
        final = (
            self.loops + 1 == self._last_step
            or (self.takeovers > 0 and end is not None and loop >= end)
            or self.stop.is_set()
        )
        standby = ready if self.redundant else None
        # Triggers over shared memory are encoded straight into their loans.
        frames = self.sync.begin(logic, loop, t, final=final, standby=standby)
        overrun = self.sync.sync(frames, logic)
        self._query_recoveries(t)
        self._sync_paths(t)
        grounds = self._grounds
        grounds.clear()
        taken = self._taken
        if len(self._inbox):
            taken.clear()
            self._inbox.drain(taken)
            for _, frame in taken:
                grounds.append(frame)
        skipped, self._skipped = self._skipped, 0
        if self._gap:  # the first loop after a takeover: the periods no one ran
            self._gap = False
            skipped = max(loop - 1 - logic.loop, 0)
        rec = self.flight_recorder
        if rec is not None:  # its counters into this loop's telemetry
            rec.tick(t)
        # A total only zenoh's thread writes; the loop keeps what it has seen.
        d_total = self._inbox.dropped
        dropped, self._seen_dropped = d_total - self._seen_dropped, d_total
        saver = self._saver
        saved = saver.poll() if saver is not None else None
        tmx = self._tm_iox
        # A ground node on this host: this loop's telemetry encoded straight
        # into a loaned sample when zenoh takes no copy of it.
        into = (
            tmx.lend(self._tm_pub.wanted())
            if self._tm_lend and tmx is not None and loop % self.mission.telemetry_divisor == 0
            else None
        )
        tm = logic.finish(
            grounds,
            sync_overrun=overrun,
            loop_overruns=skipped,
            inbox_dropped=dropped,
            refused=self._take_refusals(),
            saves=(saved,) if saved is not None else (),
            tm_into=into,
        )
        if saver is not None:
            save = logic.params.take_save()
            if save is not None:
                saver.submit(*save)
        down = self.role.finished()  # most device nodes follow a newer term
        if down is not None:
            self._stood_down(down.why)
            return False
        if logic.mirror is not None:  # the standby's copy, before anything else
            self._mirror_pub.put(logic.mirror)
        if tm is not None:
            tr = trace.tracer
            if tr is not None:  # the frame is ready: either path's latency counts from here
                tr.mark("tm.put", loop, len(tm))
            if type(tm) is memoryview:
                # The lent sample: everything reads it before it goes (zenoh
                # only if a subscriber came since the lend: rare, one copy).
                if rec is not None:
                    rec.frame(loop, tm, t)
                if self._tm_pub.wanted():
                    self._tm_pub.pub.put(bytes(tm))
                assert tmx is not None
                tmx.publish(tm)
                if tr is not None:
                    tr.mark("tm.sent", loop)
            else:
                if tmx is not None:  # the local path first
                    tmx.publish(tm)
                self._tm_pub.put(tm)
                if tr is not None:
                    tr.mark("tm.sent", loop)
                if rec is not None:
                    rec.frame(loop, tm, t)
            if self._radio is not None:
                self._radio.send(self.dv, loop, t)
        elif into is not None:
            tmx.withdraw()  # type: ignore[union-attr]
        end = self._mono()
        if self.watchdog is not None:
            self.watchdog.stroke(end, t)
        self._events.flush()
        self._work[self.loops & 0xFFFF] = end - m0
        self.loops += 1
        self.last_loop_ns = t
        if self.health is not None:
            self.health.kick()  # sample now, in the slack before the next loop
        hook = self._on_loop
        if hook is not None:
            hook(loop, deadline_ns, m0)
        return not final

    # -- failover (a redundant mission) ------------------------------------------
    def _still_commanding(self, ready: bool) -> bool:
        """A commander's check at the top of each loop: a mirror of a newer
        term from the other control node makes it stand down before it sends
        anything (a commander woken from a stop learns it here); and the
        other node's liveliness goes into ``cn_standby_ready``."""
        self._mirror_refusals(self.logic.t_ns)
        item = self._mirrors.pop()
        while item is not None:
            down = self.role.mirror(item[1], self.clock.now_ns())
            if isinstance(down, StandDown):
                self._stood_down(down.why)
                if down.followed:  # the newer term's mirror is the standby's first
                    self._followed()
                return False
            item = self._mirrors.pop()
        if ready != self._peer_seen:
            self._peer_seen = ready
            self.logic.events.emit(
                EV.CN_STANDBY_READY,
                self.logic.t_ns,
                node=self.name,
                peer=self._peer,
                what="alive and following"
                if ready
                else "not ready (gone, or its mirrors stopped coming)",
            )
        return True

    @property
    def standby(self) -> Standby | None:
        """The role's standby while this node does not command (None: it commands)."""
        return self.role.standby

    def _stood_down(self, why: str) -> None:
        """Carry out a stand-down the role decided (it follows now)."""
        self._stop_serving()
        if self.recorder is not None:  # the recording of this reign ends here
            self.logic.recorder = None
        log.warning("%s stands down: %s", self.name, why)

    def _follow(self, gc_guard: GcGuard) -> int | None:
        """Follow the commander as the standby until this node takes command;
        returns the schedule's start (monotonic ns) to command from, or None
        when stopped first. Blocks."""
        sb = self.standby
        assert sb is not None
        while sb.origin is None:  # the first mirror gives the schedule
            if self.stop.is_set():
                return None
            self._loop_hb.beat()
            item = self._mirrors.get(0.2)
            if item is not None:
                self._apply_mirror(item[1], self.clock.now_ns())
            self._events.flush()
        self._take_at = 0
        follower = PeriodicLoop(self.mission.period_ns, slack_hook=gc_guard.on_slack)
        # Half a period into each of the commander's loops: its mirror is due.
        start = self.clock.monotonic_at(sb.origin) + self.mission.period_ns // 2
        follower.run(self._tick, start_ns=start)
        if not self._take_at:
            return None
        # What a commander serves, first; then the loop: the next one of the
        # schedule not yet begun, so the term's first loop is one that runs
        # (cn_term_loop), however long the set-up took.
        self._serve_clock()
        self._take_requests()
        self._serve_recorder()
        self.ns.announce()
        loop = max(self._take_at, sb.slot(self.clock.now_ns()) + 1)
        if self._end_loop is not None and loop > self._end_loop:
            log.info(
                "%s does not take command: the run ended at loop %d", self.name, self._end_loop
            )
            return None
        logic = self.role.take(loop)
        rec, self._next_recorder = self._next_recorder, None
        if rec is not None:
            try:
                rec.start(self.dv)
                self.recorder = rec
                logic.recorder = rec
            except RecordingError as exc:  # the flight goes on; say why nothing is recorded
                log.error("%s cannot record its loops: %s", self.name, exc)
        if self._ready_token is not None:
            self._ready_token.undeclare()
            self._ready_token = None
        self.takeovers += 1
        self._gap = True
        log.warning("%s took command in term %d at loop %d", self.name, logic.term, loop)
        assert sb.origin is not None
        return self.clock.monotonic_at(sb.origin)

    def _apply_mirror(self, payload: bytes, now: int) -> None:
        if self.role.mirror(payload, now) is True:
            self._followed()

    def _followed(self) -> None:
        """The standby applied a mirror: ready, and its own flight record."""
        sb = self.standby
        assert sb is not None
        if self._ready_token is None:  # following: ready (the commander's cn_standby_ready)
            self.ns.announce()
            self._ready_token = self.ns.session.liveliness().declare_token(
                self.ns.keys.standby(self.name)
            )
        rec = self.flight_recorder
        if rec is not None and sb.mirrored % self.mission.telemetry_divisor == 0:
            # A standby's own flight record: the commander's telemetry, as it was.
            rec.frame(sb.mirrored, self.logic.telemetry(), sb.mirrored_t)

    def _tick(self, k: int, deadline_ns: int) -> bool:
        """One beat of the standby, half a period into the commander's loop:
        the mirrors that came, a PRM_SAVE to follow, and, when the commander
        has fallen silent, a probe round that may end in a takeover."""
        m0 = self._mono()
        self._loop_hb.beat_at(m0)
        sb = self.standby
        assert sb is not None
        now = self.clock.now_ns()
        item = self._mirrors.pop()
        while item is not None:
            self._apply_mirror(item[1], now)
            item = self._mirrors.pop()
        self._mirror_refusals(now)
        save = sb.take_save()
        if save is not None and self._saver is not None:
            self._saver.submit(*save)
        if self._saver is not None:
            self._saver.poll()  # a follower's save is its own: the result only logged
        slot = sb.slot(now)
        end = self._end_loop
        if end is not None and (sb.ended or (slot > end and sb.blind(slot))):
            return False  # the run is over: its final loop, or silence past its end
        if self._ready_token is not None and sb.blind(slot):
            # Too old a mirror to take command from: not ready (the commander's
            # cn_standby_ready falls) until the next one comes.
            self._ready_token.undeclare()
            self._ready_token = None
            log.warning(
                "%s has had no mirror since loop %d: not ready to take over until the next one",
                self.name,
                sb.mirrored,
            )
        role = self.role
        # The role's probe rounds (zplatform.control.role): this node asks, hands answers.
        action: Probe | Take | Release | None = role.tick(slot, now)
        while isinstance(action, Probe):
            self.probes.round(action.asks, role.answer)
            action = role.round_over(slot, self.clock.now_ns())
        if isinstance(action, Take):
            self._take_at = action.loop
            return False
        if isinstance(action, Release):
            self.probes.send(action.releases)
        if self.watchdog is not None:
            self.watchdog.stroke(self._mono(), now)
        self._events.flush()
        return not self.stop.is_set()

    def _query_recoveries(self, t_ns: int) -> None:
        """The device nodes whose querier the sync declared again this loop
        (zplatform.runtime.queries.Unanswered), evented at most once a second
        (the loop counts them: ``cn_query_recoveries``, from the sync's
        refusals, :meth:`_take_refusals`)."""
        got = self._recoveries
        self.sync.take_recoveries(got)
        if not got and not self._recovery_unsent:
            return  # every loop but a recovering one: nothing allocated
        for dn, total in got:
            self._recovered_dns[dn] = total
        ev = self._recovery_log.add(t_ns, len(got))
        got.clear()
        self._recovery_unsent = ev is None
        if ev is not None:
            self.logic.events.emit(
                EV.QUERY_RECOVERED,
                t_ns,
                node=self.name,
                dns=", ".join(sorted(self._recovered_dns)),
                n=ev[0],
                total=sum(self._recovered_dns.values()),
                loops=self.sync.unanswered.after,
            )

    def _sync_paths(self, t_ns: int) -> None:
        """Event each intra-host link's path change (ShmLink: at most a
        fallback and a return per RETRY_LOOPS loops and DN)."""
        got = self._path_changes
        self.sync.take_path_changes(got)
        if not got:
            return
        for dn, path, why in got:
            i = self.mission.device_nodes.index(dn)
            link = self.sync.shm[i]
            fallbacks = link.fallbacks if link is not None else 0
            ev = EV.SYNC_ON_SHM if path == "shm" else EV.SYNC_FALLBACK
            self.logic.events.emit(ev, t_ns, node=self.name, dn=dn, why=why, fallbacks=fallbacks)
        got.clear()

    def _take_refusals(self) -> CnRefusals:
        """What the intakes refused since the last loop (an input of the loop)."""
        r = self._refused
        self.sync.take_refusals(r)
        r.mirror_refused, self._mirror_unfiled = self._mirror_unfiled, 0
        req = self._requests
        if req is None:
            r.cmd_size = r.cmd_bad = r.cmd_stale = r.cmd_status = r.cmd_seq = 0
            r.cmd_unchecked = 0
            return r
        req.take_refusals(r)
        return r

    def run(
        self,
        *,
        max_loops: int | None = None,
        realtime: bool = True,
        record: int = 0,
        on_loop: Callable[[int, int, int], None] | None = None,
    ) -> PeriodicLoop:
        """Run the loop until stopped or ``max_loops``; returns the loop (stats).

        The last loop of the call (the ``max_loops``-th, or the one after a
        stop) is the run's final loop (module doc). ``on_loop``: called on
        the loop thread after each loop this node commands (not a
        standby's beats, not a loop it stood down in) with ``(loop,
        deadline_ns, started_ns)``: the loop's number, its scheduled start
        and when it started (both ``time.monotonic_ns``). What it takes
        delays the next loop (benchmarks use it; None costs one test a
        loop)."""
        nc = self.mission.nodes[self.name]
        self._last_step = None if max_loops is None else self.loops + max_loops
        if max_loops is not None and self.standby is not None and self._end_loop is None:
            # A standby from the start: ``max_loops`` are the run's, counted
            # on the commander's schedule from its first loop.
            self._end_loop = max_loops
        if realtime:
            realtime_setup(nc.priority, nc.cpu)
        self._loop_hb.beat()
        if self.health is not None:
            self.health.start()
        if self.watchdog is not None:
            self.watchdog.open()
        gc_guard = GcGuard()
        loop = PeriodicLoop(
            self.mission.period_ns,
            on_overrun=self._on_overrun,
            slack_hook=gc_guard.on_slack,
            record=record,
        )
        gc_guard.freeze_after_startup()
        self._on_loop = on_loop
        try:
            start: int | None = self._origin  # a resumed run's schedule
            while not self.stop.is_set():
                if self.standby is not None:  # a redundant mission's standby
                    start = self._follow(gc_guard)
                    if start is None:
                        break
                left = None if self._last_step is None else self._last_step - self.loops
                if left is not None and left <= 0:
                    break
                loop.run(self.step, max_loops=left, start_ns=start)
                if self.standby is None:  # the run ended; not a stand-down
                    break
        finally:
            self._on_loop = None
            gc_guard.restore()
        self._stopped_cleanly = True
        return loop

    def summary(self) -> CnSummary:
        dv = self.dv
        dur = (self.last_loop_ns - self.first_loop_ns) / 1e9
        work = self._work[: min(self.loops, len(self._work))]
        rec = self.recorder
        return cn_summary(
            self.mission,
            dv,
            loops=self.loops,
            duration_s=dur,
            loop_work_us=LoopWork(
                float(np.percentile(work, 50)) / 1e3,
                float(np.percentile(work, 99)) / 1e3,
                float(work.max()) / 1e3,
            )
            if len(work)
            else None,
            recorded_loops=rec.loops if rec is not None else None,
            recording_dropped_loops=rec.dropped_loops if rec is not None else None,
            node=self.name,
            commanding=self.standby is None,
            takeovers=self.takeovers,
        )

    def close(self) -> None:
        """Publish the final snapshot if the divisor skipped it; release zenoh;
        flush the recording (idempotent)."""
        if self.ns._closed:
            return
        try:
            last = int(self.dv.get("cn_loop"))
            rec = self.flight_recorder
            if last % self.mission.telemetry_divisor:  # the last snapshot was not sent yet
                tm = self.logic.telemetry()
                if self._tm_iox is not None:
                    self._tm_iox.publish(tm)
                self._tm_pub.put(tm)
                if rec is not None:
                    rec.frame(last, tm, self.logic.t_ns)
            if self._rec_server is not None:
                self._rec_server.close()
            self._events.undeclare()
            self.sync.close()
            if self.clock_server is not None:
                self.clock_server.close()
            if self._gsub is not None:
                self._gsub.undeclare()
            if self.redundant:
                if self._ready_token is not None:
                    self._ready_token.undeclare()
                self._mirror_sub.undeclare()
                self._mirror_pub.undeclare()
                self._peer_sub.undeclare()
            if self._radio is not None:
                self._radio.pub.undeclare()
            if self.bulk is not None:
                self.bulk.close()
            self._tm_pub.undeclare()
            if self._tm_iox is not None:
                self._tm_iox.close()
        finally:
            if self.watchdog is not None:
                # A loop that ended in an exception leaves the watchdog armed.
                self.watchdog.close(clean=self._stopped_cleanly)
            if self.health is not None:
                self.health.close()
            for r in (self.recorder, self._next_recorder):
                if r is not None:
                    r.close()
            if self._saver is not None:  # a save in progress is finished, not torn
                self._saver.close()
            if self.flight_recorder is not None:
                self.flight_recorder.close()
                log.info("flight recorder: %s", summary_line(self.flight_recorder))
            self.ns.close()


ALIVE_LOOK_S = 0.5
"""How long a starting control node looks for device nodes already running."""


def _last_recorded(
    mission: Mission, node: str, logic: ControlLogic, keys: KeySet | None
) -> Frame | None:
    """The newest telemetry frame ``node``'s flight recorder holds, checked
    (its tag, this mission's layout); None when there is none, or it does not
    check. Reads only the newest segment that holds a frame."""
    try:
        got = RecorderReader(recorder_dir(mission, node)).last_frame()
    except RecordingError:
        return None
    if got is None or got[0].mission != mission.mission:
        return None
    return check_recorded(logic, keys, got[1].payload)


def check_clocks(offsets: dict[str, int], residuals: dict[str, int], bound_ms: float) -> None:
    """Refuse to fly when a DN's clock, corrected by ``offsets[dn]``, is
    still off by more than the mission bound (thesis 4.9): the bound is about
    the error the loop sees, the residual, not about how far the DN's clock
    had to be moved. NodeError naming the node, the correction and the
    residual."""
    bound = int(bound_ms * 1e6)
    for dn, res in residuals.items():
        if abs(res) > bound:
            raise NodeError(
                f"control node refuses to start: {dn}'s clock, corrected by "
                f"{offsets.get(dn, 0) / 1e6:+.3f} ms, is still off by {res / 1e6:+.3f} ms, "
                f"beyond the mission bound of {bound_ms:g} ms"
            )


class _Radio:
    """The CCSDS downlink: packs telemetry snapshots and publishes each packet.

    Packets are plain CCSDS (CRC, no HMAC): a radio downlink is read-only
    telemetry and its receivers check the CRC and the sequence counts."""

    def __init__(self, mission: Mission, session: zenoh.Session, key: str) -> None:
        try:
            from ..telemetry.ccsds import CcsdsEncoder
        except ImportError as exc:
            raise NodeError(
                "the mission's downlink needs spacepackets: pip install 'zplatform[ground]'"
            ) from exc
        d = mission.downlink
        self.enc = CcsdsEncoder(
            mission, divisor=d.divisor, budget_bps=d.budget_bps, max_data=d.max_data
        )
        self.pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)

    def send(self, dv: DataVector, loop: int, t_ns: int) -> None:
        for packet in self.enc.encode(dv, loop, t_ns):
            self.pub.put(bytes(packet))


def run_control_node(
    mission: Mission,
    *,
    name: str = "cn",
    max_loops: int | None = None,
    duration_s: float | None = None,
    realtime: bool = True,
    ready_timeout_s: float = 60.0,
    ground_wait_s: float | None = None,
    record: str | Path | None = None,
    mission_source: str | Path | None = None,
    key_file: str | Path | None = None,
) -> CnSummary:
    """Entry function: build, wait for DNs, loop until SIGTERM/duration. Blocks.

    ``record``: a directory to record every loop's inputs into (needs
    ``mission_source``, the mission file, which the recording keeps)."""
    stop = StopFlag()
    node = ControlNode(mission, name=name, stop=stop, keys=load_keys(mission, name, key_file))
    try:
        offsets = node.wait_ready(ready_timeout_s, ground_wait_s)
        if node.standby is None:
            log.info("device nodes ready; clock offsets (ns): %s", offsets)
        if record is not None:
            if mission_source is None:
                raise NodeError("recording needs the mission file's path")
            if node.record(record, mission_source) is not None:
                log.info("recording loop inputs into %s", record)
            else:
                log.info("recording loop inputs into %s once it commands", record)
        if duration_s is not None:
            n = max(1, round(duration_s * mission.loop_hz))
            max_loops = n if max_loops is None else min(max_loops, n)
        node.run(max_loops=max_loops, realtime=realtime)
        return node.summary()
    finally:
        node.close()
