"""Ground Node Main (thesis 4.15) and the ground-side tools.

* :class:`TelemetryReceiver` subscribes to the CN's telemetry and decodes each
  snapshot into a CN-layout Data Vector (the GN's first Data Vector, thesis
  4.15), counting gaps (missing loop numbers) and bad frames: nothing is
  lost silently.
* :func:`run_ground_logger` logs every snapshot to CSV and every event
  (``{vehicle}/*/events``) to JSON lines beside it (``zplatform log`` and the
  GN process that ``zplatform up`` starts).
* :class:`CommandSender` sends one operator command on ``{vehicle}/gn/to_cn``
  (the GN's second Data Vector holds the request) and waits for the CN's
  verdict in telemetry (``cn_cmd_seq``/``cn_cmd_status``).

What a request holds, how a script is timed and how a verdict is read are
:mod:`zplatform.uplink`'s; this module only moves the frames.
"""

from __future__ import annotations

import logging
import queue
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import zenoh

from ..auth import KeySet, channel, load_keys
from ..codec import RegionCodec
from ..config import Mission
from ..datavector import DataVector, Layout
from ..errors import CodecError, CommandError
from ..events import EventReader
from ..summary import GnSummary
from ..telemetry import CsvLogger, EventWriter
from ..timebase import NodeClock
from ..transport import KeySpace, NodeSession, is_matching
from ..uplink import CommandOutcome, ScriptCommand, ScriptPlayer, Uplink, validate_command, verdict
from .runtime import StopFlag

__all__ = ["CommandSender", "TelemetryReceiver", "run_ground_logger"]

log = logging.getLogger("zplatform.gn")

_U64 = struct.Struct("<Q")


class TelemetryReceiver:
    """Decodes CN telemetry into ``self.dv``; counts received, gaps, bad frames.

    :meth:`next` blocks up to ``timeout_s`` for one snapshot and returns the
    receive time (ns, this node's clock) or None. The zenoh callback only
    queues the bytes (a FIFO: every snapshot is kept until read).

    Nothing unchecked is applied: a snapshot must carry the telemetry
    channel's tag (``keys``, the downlink's; "mission": a read-only tool's
    keys from where the mission keeps them; None when the mission does not
    authenticate), be
    newer than the last one of the same CN run (``cn_epoch``; a restarted CN
    starts a new run), and not jump further ahead than the time since the
    last one allows. Anything else is counted in :attr:`bad` and dropped.
    """

    def __init__(
        self,
        session: zenoh.Session,
        mission: Mission,
        now_ns: Callable[[], int],
        keys: KeySet | Literal["mission"] | None = "mission",
    ):
        self.mission = mission
        self.dv = DataVector(Layout.for_node(mission, "cn"))
        self._codec = RegionCodec(self.dv)
        if keys == "mission":  # a read-only tool's keys, from where the mission keeps them
            keys = load_keys(mission, "tool")
        self._open = channel(keys, "telemetry")
        self._epoch_at = self.dv.layout.element("cn_epoch").offset
        self._epoch = -1
        self._last_rx = 0
        self._period = mission.period_ns
        self._now = now_ns
        self._q: queue.SimpleQueue[tuple[bytes, int]] = queue.SimpleQueue()
        self.received = 0
        self.gaps = 0
        self.bad = 0
        self.last_seq = -1
        self.first_seq = -1
        self._sub = session.declare_subscriber(
            KeySpace(mission.vehicle).telemetry,
            zenoh.handlers.Callback(self._on_sample, indirect=False),
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._q.put((sample.payload.to_bytes(), self._now()))  # hand off only

    def next(self, timeout_s: float) -> int | None:
        while True:
            try:
                payload, rx = self._q.get(timeout=timeout_s)
            except queue.Empty:
                return None
            try:
                frame = self._codec.check(self._open.open(payload) if self._open else payload)
                epoch = _U64.unpack_from(frame.data, self._epoch_at)[0]
                self._believable(frame.seq, epoch, rx)
            except CodecError as exc:
                self.bad += 1
                log.warning("bad telemetry frame: %s", exc)
                continue
            self._codec.write(frame)
            if epoch != self._epoch:  # a (re)started CN: a new run of loop numbers
                self._epoch = epoch
                self.last_seq = -1
            self._last_rx = rx
            div = self.mission.telemetry_divisor
            if self.last_seq >= 0 and frame.seq > self.last_seq + div:
                self.gaps += (frame.seq - self.last_seq) // div - 1
            if self.first_seq < 0:
                self.first_seq = frame.seq
            self.received += 1
            self.last_seq = frame.seq
            return rx

    def _believable(self, seq: int, epoch: int, rx: int) -> None:
        if epoch != self._epoch or self.last_seq < 0:
            return
        if seq <= self.last_seq:
            raise CodecError(f"snapshot of loop {seq} is not newer than loop {self.last_seq}")
        allowed = 2 * (max(rx - self._last_rx, 0) // self._period + 1) + 100
        if seq - self.last_seq > allowed:
            raise CodecError(
                f"snapshot of loop {seq} jumps {seq - self.last_seq} loops past loop "
                f"{self.last_seq} in {(rx - self._last_rx) / 1e6:.1f} ms"
            )

    def close(self) -> None:
        self._sub.undeclare()


def run_ground_logger(
    mission: Mission,
    out_csv: str | None,
    *,
    as_node: bool = True,
    duration_s: float | None = None,
    stop: StopFlag | None = None,
    idle_exit_s: float | None = None,
    script: list[ScriptCommand] | None = None,
    key_file: str | None = None,
    events_out: str | Path | None = None,
) -> GnSummary:
    """Log telemetry snapshots to CSV until stopped or ``duration_s``. Blocks.

    ``events_out``: also write every event of every node there, as JSON
    lines (:class:`~zplatform.telemetry.EventWriter`); an undecodable event
    is logged as a warning and skipped.

    ``as_node``: run as the mission's ``gn`` node (its endpoints, its
    liveliness token); otherwise as a tool connected to every node.
    ``idle_exit_s``: stop when no telemetry came for this long *after* some
    did (the CN finished). Returns the summary.
    """
    stop = stop or StopFlag()
    clock = NodeClock()
    node = "gn" if as_node and mission.has_ground else None
    ns = NodeSession(mission, node, announce=False)
    # Commands need the uplink (the ground's keys); logging needs only the
    # downlink and the events (a read-only tool's).
    keys = load_keys(mission, "gn" if script else "tool", key_file)
    rx = TelemetryReceiver(ns.session, mission, clock.now_ns, keys)
    logger = CsvLogger(out_csv, rx.dv.layout) if out_csv else None
    events = EventWriter(events_out) if events_out else None
    ev_q: queue.SimpleQueue[tuple[str, bytes, int]] = queue.SimpleQueue()
    ev_sub = None
    reader = EventReader(mission, keys)
    if events is not None:

        def on_event(sample: zenoh.Sample) -> None:
            ev_q.put((str(sample.key_expr), sample.payload.to_bytes(), clock.now_ns()))

        ev_sub = ns.session.declare_subscriber(
            ns.keys.all_events, zenoh.handlers.Callback(on_event, indirect=False)
        )

    def drain_events() -> None:
        if events is None:
            return
        while True:
            try:
                key, payload, t_rx = ev_q.get_nowait()
            except queue.Empty:
                return
            try:
                e, _ = reader.read(key, payload)  # the ground holds every node's event key
                events.write(t_rx, e)
            except CodecError as exc:
                log.warning("bad event record on %s: %s", key, exc)

    player = ScriptPlayer(mission, script, keys=keys) if script else None
    cmd_pub = ns.session.declare_publisher(ns.keys.gn_to_cn) if player is not None else None
    # Alive only once subscribed: the CN waits for this token before its
    # first loop, so the log starts at loop 1.
    ns.announce()
    start = time.monotonic()
    last_rx = start
    try:
        while not stop.is_set():
            if duration_s is not None and time.monotonic() - start >= duration_s:
                break
            t = rx.next(0.2)
            drain_events()
            if t is None:
                if (
                    idle_exit_s is not None
                    and rx.received
                    and time.monotonic() - last_rx > idle_exit_s
                ):
                    break
                continue
            last_rx = time.monotonic()
            if logger is not None:
                logger.write(t, rx.dv)
            if player is not None and cmd_pub is not None:
                # A command goes out only while the CN listens (else it waits).
                frame = player.on_telemetry(rx.dv, can_send=is_matching(cmd_pub))
                if frame is not None:
                    cmd_pub.put(bytes(frame))
        # Drain what is already queued so nothing received is dropped.
        while (t := rx.next(0.0)) is not None:
            if logger is not None:
                logger.write(t, rx.dv)
        drain_events()
    finally:
        if ev_sub is not None:
            ev_sub.undeclare()
        if events is not None:
            events.close()
        if logger is not None:
            logger.close()
        if cmd_pub is not None:
            cmd_pub.undeclare()
        rx.close()
        ns.close()
    return GnSummary(
        telemetry_received=rx.received,
        telemetry_gaps=rx.gaps,
        telemetry_bad=rx.bad,
        first_seq=rx.first_seq,
        last_seq=rx.last_seq,
        final_state=rx.dv.get_name("cn_state") if rx.received else None,
        commands=list(player.results) if player is not None else [],
        pending_commands=player.pending if player is not None else [],
    )


class CommandSender:
    """Sends operator commands from the ground side and waits for verdicts.

    Opens a tool session (connected to every node). :meth:`send` blocks until
    the CN's telemetry shows the verdict for the command's number, or raises
    CommandError on timeout. Unknown commands and elements are refused
    before anything is sent.
    """

    def __init__(
        self, mission: Mission, *, timeout_s: float = 10.0, key_file: str | None = None
    ) -> None:
        if not mission.has_ground:
            raise CommandError(f"mission {mission.mission!r} has no ground node 'gn'")
        self.mission = mission
        self.timeout_s = timeout_s
        keys = load_keys(mission, "gn", key_file)  # before any session: a clear error first
        self.clock = NodeClock()
        self.ns = NodeSession(mission, None)
        self.rx = TelemetryReceiver(self.ns.session, mission, self.clock.now_ns, keys)
        self._uplink = Uplink(mission, keys)
        self._pub = self.ns.session.declare_publisher(self.ns.keys.gn_to_cn)

    def validate(
        self, command: str, element: str | None, value: str | None
    ) -> tuple[str, int, float]:
        return validate_command(self.mission, command, element, value)

    def wait_telemetry(self) -> None:
        """Block until one telemetry snapshot arrived (the CN is up)."""
        deadline = time.monotonic() + self.timeout_s
        while self.rx.received == 0:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CommandError(
                    f"no telemetry from the control node within {self.timeout_s:g} s"
                )
            self.rx.next(min(left, 0.5))

    def _wait_cn_subscribed(self) -> None:
        deadline = time.monotonic() + self.timeout_s
        while not is_matching(self._pub):
            if time.monotonic() > deadline:
                raise CommandError("the control node does not subscribe to ground commands")
            self.rx.next(0.01)

    def send(
        self, command: str, element: str | None = None, value: str | None = None
    ) -> CommandOutcome:
        cmd, index, num = self.validate(command, element, value)
        return self._send(cmd, self._next_seq(), index, num)

    def _next_seq(self) -> int:
        """Wait until the CN is up and listening; the number after its last verdict."""
        self.wait_telemetry()
        self._wait_cn_subscribed()
        return int(self.rx.dv.get("cn_cmd_seq")) + 1

    def _send(self, cmd: str, seq: int, index: int, num: float) -> CommandOutcome:
        epoch = int(self.rx.dv.get("cn_epoch"))
        frame = self._uplink.frame(cmd, seq, index, num, self.clock.now_ns(), epoch)
        self._pub.put(bytes(frame))
        deadline = time.monotonic() + self.timeout_s
        dv = self.rx.dv
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CommandError(f"no verdict for {cmd} #{seq} within {self.timeout_s:g} s")
            if self.rx.next(left) is None:
                continue
            status = verdict(dv, seq)
            if status is not None:
                return CommandOutcome(cmd, seq, status, int(dv.get("cn_loop")))

    def send_armed(self, command: str) -> list[CommandOutcome]:
        """ARM n then COMMAND n+1 (seed 003's double confirmation)."""
        cmd, index, num = self.validate(command, None, None)
        seq = self._next_seq()
        arm = self._send("ARM", seq, 0, 0.0)
        if not arm.accepted:
            return [arm]
        return [arm, self._send(cmd, seq + 1, index, num)]

    def close(self) -> None:
        self._pub.undeclare()
        self.rx.close()
        self.ns.close()
