"""Control Node Main (thesis 4.13): entry and the periodic loop on zenoh.

Entry: open the session, serve the clock, wait for every DN to be alive,
read each DN's clock offset with a warm-up sync (refusing to start beyond the
mission bound), then run the loop on absolute deadlines. Initialisation
errors raise :class:`~zplatform.errors.NodeError` (the CLI prints and exits
non-zero); errors after start are counted in the Data Vector and the loop
goes on.

Loop (one timestamp per loop)::

    t = clock.now_ns()
    sync every DN (2 ms deadline)
    take at most one ground command frame
    logic: faults -> commands -> state machine -> controllers
    telemetry (every Nth loop), events
"""

from __future__ import annotations

import logging
import queue
import time
from typing import Any

import zenoh

from ..clocksync import ClockServer
from ..codec import RegionCodec, VectorCodec
from ..config import Mission
from ..datavector import DataVector
from ..errors import CodecError, NodeError, TransportError
from ..events import EV
from ..scheduler import GcGuard, PeriodicLoop
from ..sync import ControlSync
from ..timebase import NodeClock
from ..transport import NodeSession, wait_for_nodes
from .logic import ControlLogic
from .runtime import EventPublisher, StopFlag, realtime_setup

__all__ = ["ControlNode", "run_control_node"]

log = logging.getLogger("zplatform.cn")


class ControlNode:
    """The CN process: session, sync, ground input, telemetry, logic.

    Build, then :meth:`run`; :meth:`close` releases every zenoh entity. Not
    thread-safe: one loop thread.
    """

    def __init__(
        self,
        mission: Mission,
        *,
        stop: StopFlag | None = None,
        lowlatency: bool | None = None,
        clock: NodeClock | None = None,
    ) -> None:
        self.mission = mission
        self.stop = stop or StopFlag(install=False)
        self.clock = clock or NodeClock()
        self.clock.lock()  # the CN is the reference clock: never adjusted
        self.logic = ControlLogic(mission)
        self.dv: DataVector = self.logic.dv
        self.ns = NodeSession(mission, "cn", announce=False, lowlatency=lowlatency)
        s = self.ns.session
        keys = self.ns.keys
        self.clock_server = ClockServer(s, keys, self.clock.now_ns)
        self.sync = ControlSync(
            s,
            keys,
            self.dv,
            mission.device_nodes,
            mission.sync_timeout_ns,
            query_timeout_s=max(mission.period_ns / 1e9, 0.01),
            on_bad=self._on_bad_reply,
        )
        self._gq: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._gsub: zenoh.Subscriber[Any] | None = None
        self._gcodec: RegionCodec | None = None
        if mission.has_ground:
            self._gcodec = RegionCodec(self.dv, "gn_to_cn")
            self._gsub = s.declare_subscriber(
                keys.gn_to_cn,
                zenoh.handlers.Callback(self._on_ground, indirect=False),
            )
        self._tm = VectorCodec(self.dv)
        self._tm_pub = s.declare_publisher(
            keys.telemetry, congestion_control=zenoh.CongestionControl.DROP
        )
        self._events = EventPublisher(s, keys.events("cn"), self.logic.events)
        self._bad = self.dv.handle("cn_bad_frames")
        self._overruns = self.dv.handle("cn_loop_overruns")
        self._divisor = mission.telemetry_divisor
        self.ns.announce()
        self.first_loop_ns = 0
        self.last_loop_ns = 0
        self.loops = 0

    def _on_bad_reply(self, dn: str, reason: str) -> None:
        # Rare by definition: an event per bad frame is affordable and wanted.
        self.logic.events.emit(
            EV.BAD_FRAME, self.clock.now_ns(), source=f"reply from {dn}", reason=reason
        )

    def _on_ground(self, sample: zenoh.Sample) -> None:
        self._gq.put(sample.payload.to_bytes())  # zenoh's thread: hand off only

    # -- start-up --------------------------------------------------------
    def wait_ready(
        self, timeout_s: float = 60.0, ground_wait_s: float | None = None
    ) -> dict[str, int]:
        """Wait for every DN, then read their clock offsets; returns them.

        Raises NodeError naming the node whose offset exceeds the bound, or
        the nodes that never came up.
        """
        m = self.mission
        dns = m.device_nodes
        start = time.monotonic()
        if dns:
            try:
                wait_for_nodes(self.ns.session, self.ns.keys, dns, timeout_s, self.stop.event)
            except TransportError as exc:
                raise NodeError(f"control node cannot start: {exc}") from exc
        if m.has_ground:
            # Wait for the ground (alive = subscribed to telemetry) so its log
            # starts at loop 1; but never make flight depend on the ground link.
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
            return {}
        # Warm-up syncs with loop 0: DNs answer (not applied as a loop) and
        # the replies carry each DN's measured clock offset.
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.sync.sync(0, self.clock.now_ns())
            if st.replied == len(dns):
                break
            if time.monotonic() > deadline or self.stop.is_set():
                raise NodeError("control node cannot start: device nodes do not answer sync")
        offsets = {dn: int(self.dv.get(f"{dn}_clock_offset_ns")) for dn in dns}
        bound = int(m.clock.offset_bound_ms * 1e6)
        for dn, off in offsets.items():
            if abs(off) > bound:
                raise NodeError(
                    f"control node refuses to start: {dn}'s clock is off by {off / 1e6:.3f} ms, "
                    f"beyond the mission bound of {m.clock.offset_bound_ms:g} ms"
                )
        # The warm-up counted rx/missed; the flight loop starts from zero,
        # once no warm-up reply can still arrive.
        self.sync.quiesce(timeout_s=max(2 * m.period_ns / 1e9, 1.0))
        for dn in dns:
            for name in (f"cn_rx_{dn}", f"cn_missed_{dn}", f"cn_late_{dn}"):
                self.dv.set(name, 0)
        self.dv.set("cn_sync_overruns", 0)
        return offsets

    # -- the loop ------------------------------------------------------------
    def _on_overrun(self, k: int, lateness_ns: int) -> None:
        self._overruns.bump()

    def step(self, k: int, deadline_ns: int) -> bool:
        """One loop; returns False to stop."""
        loop = k + 1
        t = self.clock.now_ns()
        if self.loops == 0:
            self.first_loop_ns = t
        self.sync.sync(loop, t)
        new_request = False
        # empty() first: raising queue.Empty every loop would allocate.
        if self._gcodec is not None and not self._gq.empty():
            payload = self._gq.get_nowait()
            try:
                self._gcodec.apply(payload)
                new_request = True
            except CodecError as exc:
                # Not our software failing: counted as a bad frame, not an error.
                self._bad.bump()
                self.logic.events.emit(EV.BAD_FRAME, t, source="ground frame", reason=exc)
        self.logic.step(loop, t, new_request)
        if loop % self._divisor == 0:
            self._tm_pub.put(self._tm.encode(loop, t))
        self._events.flush()
        self.loops += 1
        self.last_loop_ns = t
        return not self.stop.is_set()

    def run(
        self,
        *,
        max_loops: int | None = None,
        realtime: bool = True,
        record: int = 0,
    ) -> PeriodicLoop:
        """Run the loop until stopped or ``max_loops``; returns the loop (stats)."""
        nc = self.mission.nodes["cn"]
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

    def summary(self) -> dict[str, Any]:
        dv = self.dv
        dur = (self.last_loop_ns - self.first_loop_ns) / 1e9
        dns = self.mission.device_nodes
        return {
            "node": "cn",
            "loops": self.loops,
            "duration_s": dur,
            "rate_hz": (self.loops - 1) / dur if dur > 0 else 0.0,
            "loop_overruns": int(dv.get("cn_loop_overruns")),
            "sync_overruns": int(dv.get("cn_sync_overruns")),
            "missed": {dn: int(dv.get(f"cn_missed_{dn}")) for dn in dns},
            "late": {dn: int(dv.get(f"cn_late_{dn}")) for dn in dns},
            "rx": {dn: int(dv.get(f"cn_rx_{dn}")) for dn in dns},
            "bad_frames": int(dv.get("cn_bad_frames")),
            "errors": int(dv.get("cn_errors")) + sum(int(dv.get(f"{dn}_errors")) for dn in dns),
            "final_state": dv.get_name("cn_state"),
        }

    def close(self) -> None:
        """Publish the final snapshot if the divisor skipped it; release zenoh (idempotent)."""
        if self.ns._closed:
            return
        try:
            last = int(self.dv.get("cn_loop"))
            if last % self._divisor:  # the last loop's snapshot was not sent yet
                self._tm_pub.put(self._tm.encode(last, self.clock.now_ns()))
            self._events.undeclare()
            self.sync.close()
            self.clock_server.close()
            if self._gsub is not None:
                self._gsub.undeclare()
            self._tm_pub.undeclare()
        finally:
            self.ns.close()


def run_control_node(
    mission: Mission,
    *,
    max_loops: int | None = None,
    duration_s: float | None = None,
    realtime: bool = True,
    ready_timeout_s: float = 60.0,
    ground_wait_s: float | None = None,
) -> dict[str, Any]:
    """Entry function: build, wait for DNs, loop until SIGTERM/duration. Blocks."""
    stop = StopFlag()
    node = ControlNode(mission, stop=stop)
    try:
        offsets = node.wait_ready(ready_timeout_s, ground_wait_s)
        log.info("device nodes ready; clock offsets (ns): %s", offsets)
        if duration_s is not None:
            n = max(1, round(duration_s * mission.loop_hz))
            max_loops = n if max_loops is None else min(max_loops, n)
        node.run(max_loops=max_loops, realtime=realtime)
        return node.summary()
    finally:
        node.close()
