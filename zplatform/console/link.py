"""The console's zenoh side: telemetry and events in, operator commands out.

:class:`Link` runs two daemon threads and owns every zenoh object, so the
textual event loop never blocks on the network:

* the **telemetry thread** opens a tool session (connected to every node),
  a :class:`~zplatform.node.ground.TelemetryReceiver` and a subscriber on
  every node's events (whose callback only queues the bytes), and feeds the
  :class:`~zplatform.console.model.ConsoleModel` under its lock;
* the **command thread** takes requests from a queue and sends them with a
  :class:`~zplatform.node.ground.CommandSender` (its own session, created
  on first use), which blocks until the CN's verdict or its timeout; verdicts
  go to the model. A hazardous command goes ARM n, then COMMAND n+1.

Only the mission file is needed: the sessions connect to the endpoints the
mission lists, so the console runs on any host that can reach them.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

import zenoh

from ..errors import CodecError, ZPlatformError
from ..events import EventReader
from ..timebase import NodeClock
from ..transport import KeySpace, NodeSession
from .model import ConsoleModel

__all__ = ["Link"]

log = logging.getLogger("zplatform.console")


class Link:
    """Connects a :class:`ConsoleModel` to a running mission (see the module doc).

    :meth:`start` returns at once; the threads connect in the background (a
    failure to open a session is shown in the model's event pane, not raised).
    :meth:`send` queues a command and returns at once. :meth:`close` stops
    both threads and closes every session; it is idempotent.
    """

    def __init__(self, model: ConsoleModel, *, timeout_s: float = 10.0) -> None:
        self.model = model
        self.mission = model.mission
        self.timeout_s = timeout_s
        self.clock = NodeClock()
        self._stop = threading.Event()
        self._cmds: queue.SimpleQueue[tuple[str, list[str], bool] | None] = queue.SimpleQueue()
        self._events: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []
        self.busy = False  # a command is waiting for its verdict

    def now_ns(self) -> int:
        return self.clock.now_ns()

    def start(self) -> None:
        for target, name in ((self._telemetry, "console-tm"), (self._commands, "console-cmd")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def send(self, command: str, args: list[str], armed: bool) -> None:
        """Queue ``command`` (validated already); ``armed``: ARM first."""
        self._cmds.put((command, args, armed))

    def close(self) -> None:
        self._stop.set()
        self._cmds.put(None)
        for t in self._threads:
            t.join(timeout=5)

    # -- threads -------------------------------------------------------------
    def _guard(self, what: str, fn: Callable[[], None]) -> None:
        try:
            fn()
        except ZPlatformError as exc:
            with self.model.lock:
                self.model.note(self.now_ns(), f"{what}: {exc}", "FATAL")
        except Exception as exc:  # the console must show it, not die silently
            log.exception("%s failed", what)
            with self.model.lock:
                self.model.note(self.now_ns(), f"{what} failed: {exc!r}", "FATAL")

    def _on_event(self, sample: zenoh.Sample) -> None:
        self._events.put((str(sample.key_expr), sample.payload.to_bytes()))  # hand off only

    def _telemetry(self) -> None:
        self._guard("telemetry link", self._telemetry_loop)

    def _telemetry_loop(self) -> None:
        # Imported here: node/ground.py pulls in the runtime, which the
        # model (and the unit tests of the model) do not need.
        from ..auth import load_keys
        from ..node.ground import TelemetryReceiver

        keys = load_keys(self.mission, "tool")  # the downlink's and the events' keys
        reader = EventReader(self.mission, keys)
        ns = NodeSession(self.mission, None)
        rx = TelemetryReceiver(ns.session, self.mission, self.now_ns, keys)
        sub = ns.session.declare_subscriber(
            KeySpace(self.mission.vehicle).all_events,
            zenoh.handlers.Callback(self._on_event, indirect=False),
        )
        m = self.model
        try:
            while not self._stop.is_set():
                t = rx.next(0.05)
                if t is not None:
                    with m.lock:
                        m.on_snapshot(rx.dv, t, received=rx.received, gaps=rx.gaps, bad=rx.bad)
                while True:
                    try:
                        key, raw = self._events.get_nowait()
                    except queue.Empty:
                        break
                    try:
                        e, _ = reader.read(key, raw)
                    except CodecError:  # not a record, or a bad tag
                        with m.lock:
                            m.on_bad_event()
                        continue
                    with m.lock:
                        m.on_event(e)
        finally:
            sub.undeclare()
            rx.close()
            ns.close()

    def _commands(self) -> None:
        from ..node.ground import CommandSender

        sender: CommandSender | None = None
        try:
            while True:
                item = self._cmds.get()
                if item is None or self._stop.is_set():
                    return
                cmd, args, armed = item
                self.busy = True
                try:
                    if sender is None:
                        sender = CommandSender(self.mission, timeout_s=self.timeout_s)
                    if armed:
                        results = sender.send_armed(cmd)
                    else:
                        el = args[0] if args else None
                        val = args[1] if len(args) > 1 else None
                        results = [sender.send(cmd, el, val)]
                    with self.model.lock:
                        for r in results:
                            self.model.on_result(self.now_ns(), r.command, r.seq, r.status)
                except ZPlatformError as exc:
                    with self.model.lock:
                        self.model.on_result(self.now_ns(), cmd.upper(), -1, str(exc))
                finally:
                    self.busy = False
        finally:
            if sender is not None:
                sender.close()
