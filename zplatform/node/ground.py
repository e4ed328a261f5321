"""Ground Node Main (thesis 4.15) and the ground-side tools.

* :class:`TelemetryReceiver` subscribes to the CN's telemetry and decodes each
  snapshot into a CN-layout Data Vector (the GN's first Data Vector, thesis
  4.15), counting gaps (missing loop numbers) and bad frames: nothing is
  lost silently.
* :func:`run_ground_logger` logs every snapshot to CSV (``zplatform log`` and
  the GN process that ``zplatform up`` starts).
* :class:`CommandSender` sends one operator command on ``{vehicle}/gn/to_cn``
  (the GN's second Data Vector holds the request) and waits for the CN's
  verdict in telemetry (``cn_cmd_seq``/``cn_cmd_status``).
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from ..codec import RegionCodec, VectorCodec
from ..commands import fill_request
from ..config import CMD_NAMES, Mission
from ..datavector import DataVector, Layout
from ..errors import CodecError, CommandError
from ..lockstep import ScriptCommand, resolve_write
from ..telemetry import CsvLogger
from ..timebase import NodeClock
from ..transport import KeySpace, NodeSession, is_matching
from .runtime import StopFlag

__all__ = [
    "CommandResult",
    "CommandSender",
    "TelemetryReceiver",
    "run_ground_logger",
    "validate_command",
]

log = logging.getLogger("zplatform.gn")


class TelemetryReceiver:
    """Decodes CN telemetry into ``self.dv``; counts received, gaps, bad frames.

    :meth:`next` blocks up to ``timeout_s`` for one snapshot and returns the
    receive time (ns, this node's clock) or None. The zenoh callback only
    queues the bytes (a FIFO: every snapshot is kept until read).
    """

    def __init__(self, session: zenoh.Session, mission: Mission, now_ns: Callable[[], int]):
        self.mission = mission
        self.dv = DataVector(Layout.for_node(mission, "cn"))
        self._codec = VectorCodec(self.dv)
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
                frame = self._codec.apply(payload)
            except CodecError as exc:
                self.bad += 1
                log.warning("bad telemetry frame: %s", exc)
                continue
            div = self.mission.telemetry_divisor
            if self.last_seq >= 0 and frame.seq > self.last_seq + div:
                self.gaps += (frame.seq - self.last_seq) // div - 1
            if self.first_seq < 0:
                self.first_seq = frame.seq
            self.received += 1
            self.last_seq = frame.seq
            return rx

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
) -> dict[str, Any]:
    """Log telemetry snapshots to CSV until stopped or ``duration_s``. Blocks.

    ``as_node``: run as the mission's ``gn`` node (its endpoints, its
    liveliness token); otherwise as a tool connected to every node.
    ``idle_exit_s``: stop when no telemetry came for this long *after* some
    did (the CN finished). Returns the summary.
    """
    stop = stop or StopFlag()
    clock = NodeClock()
    node = "gn" if as_node and mission.has_ground else None
    ns = NodeSession(mission, node, announce=False)
    rx = TelemetryReceiver(ns.session, mission, clock.now_ns)
    logger = CsvLogger(out_csv, rx.dv.layout) if out_csv else None
    player = ScriptPlayer(ns.session, mission, script) if script else None
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
            if player is not None:
                player.on_telemetry(rx.dv)
        # Drain what is already queued so nothing received is dropped.
        while (t := rx.next(0.0)) is not None:
            if logger is not None:
                logger.write(t, rx.dv)
    finally:
        if logger is not None:
            logger.close()
        if player is not None:
            player.close()
        rx.close()
        ns.close()
    return {
        "node": "gn",
        "telemetry_received": rx.received,
        "telemetry_gaps": rx.gaps,
        "telemetry_bad": rx.bad,
        "first_seq": rx.first_seq,
        "last_seq": rx.last_seq,
        "final_state": rx.dv.get_name("cn_state") if rx.received else None,
        "commands": [
            {"command": r.command, "seq": r.seq, "status": r.status}
            for r in (player.results if player is not None else [])
        ],
    }


def validate_command(
    mission: Mission, command: str, element: str | None = None, value: str | None = None
) -> tuple[str, int, float]:
    """Check an operator command against the mission before anything is sent.

    Returns ``(COMMAND, element index, value)`` as they go into ``gn_to_cn``.
    Raises CommandError for an unknown command, element, or a value that
    does not fit the element (enum names and true/false accepted).
    """
    cmd = command.upper()
    if cmd not in CMD_NAMES or cmd == "NONE":
        raise CommandError(
            f"unknown command {command!r}; expected one of "
            f"{', '.join(c.lower() for c in CMD_NAMES[1:])}"
        )
    if cmd != "WRITE":
        if element is not None:
            raise CommandError(f"{command} takes no arguments")
        return cmd, 0, 0.0
    if element is None or value is None:
        raise CommandError("write needs ELEMENT VALUE")
    index, num = resolve_write(Layout.for_node(mission, "cn"), element, value, "write")
    return cmd, index, num


class ScriptPlayer:
    """Plays a command script (``at 1.0 launch``) from the ground node.

    Times count from the first telemetry snapshot, on the CN's clock (its
    ``cn_time_ns``), so a script means the same thing live and in the
    lockstep runner. Commands go out one at a time: the next is sent only
    after the CN's verdict on the previous one is seen, so numbers stay
    consecutive (ARM n, LAUNCH n+1). Call :meth:`on_telemetry` after each
    snapshot; it never blocks.
    """

    def __init__(self, session: zenoh.Session, mission: Mission, script: list[ScriptCommand]):
        self.mission = mission
        self.script = list(script)
        self.req = DataVector(Layout.for_regions(mission, ["gn_to_cn"]))
        self._codec = RegionCodec(self.req, "gn_to_cn")
        self._pub = session.declare_publisher(KeySpace(mission.vehicle).gn_to_cn)
        self._t0: int | None = None
        self._waiting: tuple[int, ScriptCommand] | None = None
        self.results: list[CommandResult] = []

    @property
    def done(self) -> bool:
        return not self.script and self._waiting is None

    def on_telemetry(self, dv: DataVector) -> None:
        t = int(dv.get("cn_time_ns"))
        if self._t0 is None:
            self._t0 = t
        if self._waiting is not None:
            seq, sc = self._waiting
            if int(dv.get("cn_cmd_seq")) == seq and dv.get_name("cn_cmd_status") != "NONE":
                r = CommandResult(sc.command, seq, dv.get_name("cn_cmd_status"))
                self.results.append(r)
                log.info("%s: %s #%d %s", sc.source, sc.command, seq, r.status)
                self._waiting = None
            return
        if not self.script or t - self._t0 < self.script[0].at_ns:
            return
        if not is_matching(self._pub):
            return  # the CN is not subscribed yet: try again next snapshot
        sc = self.script.pop(0)
        cmd, index, num = validate_command(self.mission, sc.command, sc.element, sc.value)
        seq = int(dv.get("cn_cmd_seq")) + 1
        fill_request(self.req, cmd, seq, index, num)
        self._pub.put(bytes(self._codec.encode(seq, t)))
        self._waiting = (seq, sc)

    def close(self) -> None:
        self._pub.undeclare()


@dataclass(frozen=True, slots=True)
class CommandResult:
    command: str
    seq: int
    status: str

    @property
    def accepted(self) -> bool:
        return self.status == "ACCEPTED"


class CommandSender:
    """Sends operator commands from the ground side and waits for verdicts.

    Opens a tool session (connected to every node). :meth:`send` blocks until
    the CN's telemetry shows the verdict for the command's number, or raises
    CommandError on timeout. Unknown commands and elements are refused
    before anything is sent.
    """

    def __init__(self, mission: Mission, *, timeout_s: float = 10.0) -> None:
        if not mission.has_ground:
            raise CommandError(f"mission {mission.mission!r} has no ground node 'gn'")
        self.mission = mission
        self.timeout_s = timeout_s
        self.clock = NodeClock()
        self.ns = NodeSession(mission, None)
        self.rx = TelemetryReceiver(self.ns.session, mission, self.clock.now_ns)
        self.req = DataVector(Layout.for_regions(mission, ["gn_to_cn"]))
        self._codec = RegionCodec(self.req, "gn_to_cn")
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
    ) -> CommandResult:
        cmd, index, num = self.validate(command, element, value)
        return self._send(cmd, self._next_seq(), index, num)

    def _next_seq(self) -> int:
        """Wait until the CN is up and listening; the number after its last verdict."""
        self.wait_telemetry()
        self._wait_cn_subscribed()
        return int(self.rx.dv.get("cn_cmd_seq")) + 1

    def _send(self, cmd: str, seq: int, index: int, num: float) -> CommandResult:
        fill_request(self.req, cmd, seq, index, num)
        self._pub.put(bytes(self._codec.encode(seq, self.clock.now_ns())))
        deadline = time.monotonic() + self.timeout_s
        dv = self.rx.dv
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CommandError(f"no verdict for {cmd} #{seq} within {self.timeout_s:g} s")
            if self.rx.next(left) is None:
                continue
            if int(dv.get("cn_cmd_seq")) == seq and dv.get_name("cn_cmd_status") != "NONE":
                return CommandResult(cmd, seq, dv.get_name("cn_cmd_status"))

    def send_armed(self, command: str) -> list[CommandResult]:
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
