"""Control Node Main (thesis 4.13): entry and the periodic loop on zenoh.

Entry: open the session, serve the clock, wait for every DN to be alive,
read each DN's clock offset with a warm-up sync (refusing to start beyond the
mission bound), then run the loop on absolute deadlines. Initialisation
errors raise :class:`~zplatform.errors.NodeError` (the CLI prints and exits
non-zero); errors after start are counted in the Data Vector and the loop
goes on.

Loop (one timestamp per loop), the order of :mod:`zplatform.loop`::

    t = the loop's scheduled start, on the node clock
    frames = logic.begin(loop, t, final=...); sync every DN with them (2 ms deadline)
    tm = logic.finish(at most one ground frame, overrun flags)
    publish tm (every Nth loop), events

The run's last loop is flagged final (``dnX_final``, so the DNs safe
themselves as the run's end, not as a lost CN): the last of ``max_loops``
(``--duration``), or, once a stop is asked for (SIGTERM, Ctrl-C under
``up``), one more loop after it, after which the node stops.

``record`` attaches a :class:`~zplatform.recording.Recorder` after the
warm-up: every input of every loop goes to disk for ``zplatform replay``.

Parameters (:mod:`zplatform.params`): :meth:`ControlNode.wait_ready` ends by
loading the parameter file (before loop 1, so a recording starts with the
values loaded); each loop hands an accepted PRM_SAVE to a
:class:`~zplatform.params.ParamSaver` (a writer thread) and passes the saves
it finished to the next loop.
"""

from __future__ import annotations

import collections
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from ..auth import KeySet, channel, load_keys
from ..bulk import open_bulk
from ..clocksync import ClockServer
from ..config import Mission
from ..datavector import DataVector
from ..errors import NodeError, TransportError
from ..loop import ControlLogic
from ..messages import wildcard_sync_for
from ..params import ParamSaver, params_path, read_params_file
from ..recording import Recorder
from ..scheduler import GcGuard, PeriodicLoop
from ..summary import CnSummary, LoopWork, cn_summary
from ..sync import ControlSync, SyncTrace
from ..timebase import NodeClock
from ..transport import NodeSession, wait_for_nodes
from .runtime import EventPublisher, StopFlag, realtime_setup

__all__ = ["ControlNode", "run_control_node"]

log = logging.getLogger("zplatform.cn")

INBOX = 16
"""Command request frames kept between two loops (the newest ones)."""


class ControlNode:
    """The CN process: session, sync, ground input, telemetry, logic.

    Build, then :meth:`run`; :meth:`close` releases every zenoh entity. Not
    thread-safe: one loop thread. ``sync_trace``: a
    :data:`~zplatform.sync.SyncTrace` for the sync's hops (benchmarks).
    ``params_file``: the parameter file (default
    :func:`~zplatform.params.params_path`; unused without ``params``).
    """

    def __init__(
        self,
        mission: Mission,
        *,
        stop: StopFlag | None = None,
        lowlatency: bool | None = None,
        clock: NodeClock | None = None,
        keys: KeySet | None = None,
        sync_trace: SyncTrace | None = None,
        params_file: str | Path | None = None,
    ) -> None:
        self.mission = mission
        self.stop = stop or StopFlag(install=False)
        self.clock = clock or NodeClock()
        self.clock.lock()  # the CN is the reference clock: never adjusted
        # The run's epoch: this clock's start, unique per run of the CN.
        self.logic = ControlLogic(mission, keys=keys, epoch=self.clock.now_ns())
        self.dv: DataVector = self.logic.dv
        self.ns = NodeSession(mission, "cn", announce=False, lowlatency=lowlatency)
        s = self.ns.session
        space = self.ns.keys
        self.clock_server = ClockServer(s, space, self.clock.now_ns, mission, keys)
        self.sync = ControlSync(
            s,
            space,
            mission.device_nodes,
            mission.sync_timeout_ns,
            query_timeout_s=max(mission.period_ns / 1e9, 0.01),
            wildcard=wildcard_sync_for(mission),
            trace=sync_trace,
        )
        # The command inbox: bounded, newest kept; a frame's size is checked
        # before its bytes are copied out of zenoh, so a flood of junk costs
        # neither memory nor a valid command more than a loop.
        self._inbox: collections.deque[bytes] = collections.deque(maxlen=INBOX)
        self._inbox_max = self.logic.max_request_len
        self._inbox_dropped = 0
        self._inbox_oversize = 0
        self._seen_dropped = 0
        self._seen_oversize = 0
        self._grounds: list[bytes] = []
        self._gsub: zenoh.Subscriber[Any] | None = None
        if mission.has_ground:
            self._gsub = s.declare_subscriber(
                space.gn_to_cn,
                zenoh.handlers.Callback(self._on_ground, indirect=False),
            )
        self._tm_pub = s.declare_publisher(
            space.telemetry, congestion_control=zenoh.CongestionControl.DROP
        )
        self._events = EventPublisher(
            s, space.events("cn"), self.logic.events, channel(keys, "events_cn")
        )
        self._radio = _Radio(mission, s, space.downlink) if mission.downlink.ccsds else None
        self.bulk = open_bulk(s, mission, "cn", self.logic)
        self.params_file = Path(params_file) if params_file else params_path(mission)
        self._saver = ParamSaver(self.params_file) if mission.params else None
        self._skipped = 0
        self._last_step: int | None = None  # self.loops after the run's planned last loop
        self.ns.announce()
        self.first_loop_ns = 0
        self.last_loop_ns = 0
        self.loops = 0
        self.recorder: Recorder | None = None
        # Work time of each loop (sync and logic, not the sleep), for the
        # summary: a preallocated ring, one int store per loop.
        self._work = np.zeros(1 << 16, dtype=np.int64)
        self._mono = time.monotonic_ns

    def _on_ground(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: check the size, hand off, nothing more.
        payload = sample.payload
        if len(payload) > self._inbox_max:
            self._inbox_oversize += 1
            return
        if len(self._inbox) == INBOX:
            self._inbox_dropped += 1  # the deque drops the oldest
        self._inbox.append(payload.to_bytes())

    def record(self, directory: str | Path, mission_source: str | Path) -> Recorder:
        """Record every loop's inputs into ``directory`` from now on (call
        after :meth:`wait_ready`). RecordingError if it cannot start."""
        self.recorder = Recorder(directory, self.mission, mission_source, self.dv)
        self.logic.recorder = self.recorder
        return self.recorder

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
        if dns:
            try:
                wait_for_nodes(self.ns.session, self.ns.keys, dns, timeout_s, self.stop.event)
            except TransportError as exc:
                raise NodeError(f"control node cannot start: {exc}") from exc
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
        self._load_params()
        return offsets

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
        self._skipped += 1  # an input of the next loop (replayed as such)

    def step(self, k: int, deadline_ns: int) -> bool:
        """One loop; returns False to stop: after the run's final loop (the
        last of ``max_loops``, or the loop after a stop was asked for)."""
        m0 = self._mono()
        loop = k + 1
        # The loop's one timestamp is its scheduled start, not the moment the
        # thread woke: loop n is then at t1 + (n - 1) * period exactly, as in
        # the lockstep runner, so timers and rate phases fire in the same loop
        # live and in sim (wake-up jitter would move a 3 s timer by a loop
        # about half the time).
        t = self.clock.at(deadline_ns)
        if self.loops == 0:
            self.first_loop_ns = t
        logic = self.logic
        final = self.loops + 1 == self._last_step or self.stop.is_set()
        overrun = self.sync.sync(logic.begin(loop, t, final=final), logic)
        grounds = self._grounds
        grounds.clear()
        inbox = self._inbox
        while inbox:
            grounds.append(inbox.popleft())
        skipped, self._skipped = self._skipped, 0
        # Totals only zenoh's thread writes; the loop keeps what it has seen.
        d_total, o_total = self._inbox_dropped, self._inbox_oversize
        dropped, oversize = d_total - self._seen_dropped, o_total - self._seen_oversize
        self._seen_dropped, self._seen_oversize = d_total, o_total
        saver = self._saver
        saved = saver.poll() if saver is not None else None
        tm = logic.finish(
            grounds,
            sync_overrun=overrun,
            loop_overruns=skipped,
            inbox_dropped=dropped,
            inbox_oversize=oversize,
            saves=(saved,) if saved is not None else (),
        )
        if saver is not None:
            save = logic.params.take_save()
            if save is not None:
                saver.submit(*save)
        if tm is not None:
            self._tm_pub.put(tm)
            if self._radio is not None:
                self._radio.send(self.dv, loop, t)
        self._events.flush()
        self._work[self.loops & 0xFFFF] = self._mono() - m0
        self.loops += 1
        self.last_loop_ns = t
        return not final

    def run(
        self,
        *,
        max_loops: int | None = None,
        realtime: bool = True,
        record: int = 0,
    ) -> PeriodicLoop:
        """Run the loop until stopped or ``max_loops``; returns the loop (stats).

        The last loop of the call (the ``max_loops``-th, or the one after a
        stop) is the run's final loop (module doc)."""
        nc = self.mission.nodes["cn"]
        self._last_step = None if max_loops is None else self.loops + max_loops
        if realtime:
            realtime_setup(nc.priority, nc.cpu)
        gc_guard = GcGuard()
        loop = PeriodicLoop(
            self.mission.period_ns,
            on_overrun=self._on_overrun,
            slack_hook=gc_guard.on_slack,
            record=record,
        )
        gc_guard.freeze_after_startup()
        try:
            loop.run(self.step, max_loops=max_loops)
        finally:
            gc_guard.restore()
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
        )

    def close(self) -> None:
        """Publish the final snapshot if the divisor skipped it; release zenoh;
        flush the recording (idempotent)."""
        if self.ns._closed:
            return
        try:
            last = int(self.dv.get("cn_loop"))
            if last % self.mission.telemetry_divisor:  # the last snapshot was not sent yet
                self._tm_pub.put(self.logic.telemetry())
            self._events.undeclare()
            self.sync.close()
            self.clock_server.close()
            if self._gsub is not None:
                self._gsub.undeclare()
            if self._radio is not None:
                self._radio.pub.undeclare()
            if self.bulk is not None:
                self.bulk.close()
            self._tm_pub.undeclare()
        finally:
            if self.recorder is not None:
                self.recorder.close()
            if self._saver is not None:  # a save in progress is finished, not torn
                self._saver.close()
            self.ns.close()


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
            from ..ccsds import CcsdsEncoder
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
    node = ControlNode(mission, stop=stop, keys=load_keys(mission, "cn", key_file))
    try:
        offsets = node.wait_ready(ready_timeout_s, ground_wait_s)
        log.info("device nodes ready; clock offsets (ns): %s", offsets)
        if record is not None:
            if mission_source is None:
                raise NodeError("recording needs the mission file's path")
            node.record(record, mission_source)
            log.info("recording loop inputs into %s", record)
        if duration_s is not None:
            n = max(1, round(duration_s * mission.loop_hz))
            max_loops = n if max_loops is None else min(max_loops, n)
        node.run(max_loops=max_loops, realtime=realtime)
        return node.summary()
    finally:
        node.close()
