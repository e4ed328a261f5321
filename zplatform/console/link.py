"""The console's zenoh side: telemetry and events in, operator commands out.

:class:`Link` runs one daemon thread that owns a
:class:`~zplatform.ground.link.GroundLink` (one session, the telemetry
subscriber, the event intake, the command publisher), so the textual event
loop never blocks on the network. The thread feeds the
:class:`~zplatform.console.model.ConsoleModel` under its lock: every
accepted snapshot with the ground's counters, every event, every command
outcome with its reason. Commands queued by the screen go to the ground
logic at once (:meth:`~zplatform.ground.link.GroundLink.submit`) and never
stall the telemetry: the logic sends each when the one before has its
verdict (ARM n, then COMMAND n+1 for an armed one).

It also fills the control node's events that did not arrive from the
CN's flight recorder (:class:`~zplatform.ground.gapfill.GapFill`, events
only): they reach the model marked filled. Only the mission file is needed:
the console runs on any host that can reach the endpoints it lists.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from ..control.authority import ARM_WINDOW_NS, Signer
from ..control.handoff import Mailbox
from ..control.uplink import CheckedCommand
from ..errors import ZPlatformError
from ..runtime.timebase import NodeClock
from ..telemetry.records import EventRecord
from .model import ConsoleModel

if TYPE_CHECKING:
    from ..ground.gapfill import GapFill
    from ..ground.link import GroundLink

__all__ = ["Link"]

log = logging.getLogger("zplatform.console")


class Link:
    """Connects a :class:`ConsoleModel` to a running mission (see the module doc).

    :meth:`start` returns at once; the thread connects in the background (a
    failure to open the session is shown in the model's event pane, not
    raised). :meth:`send` queues a command and returns at once. :meth:`close`
    stops the thread and closes the session; it is idempotent.
    """

    def __init__(
        self, model: ConsoleModel, *, timeout_s: float = 10.0, signer: Signer | None = None
    ) -> None:
        self.model = model
        self.signer = signer
        if signer is not None:
            model.operator = f"{signer.operator}@{signer.station}"
        self.mission = model.mission
        self.timeout_s = timeout_s
        self.clock = NodeClock()
        self._stop = threading.Event()
        self._cmds: queue.SimpleQueue[tuple[CheckedCommand, str, bool]] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self.busy = False  # a command waits for its verdict

    def now_ns(self) -> int:
        return self.clock.now_ns()

    def start(self) -> None:
        self._thread = threading.Thread(
            target=self._guard, args=("ground link", self._run), name="console-link", daemon=True
        )
        self._thread.start()

    def send(self, command: CheckedCommand, shown: str, armed: bool) -> None:
        """Queue ``command`` (:func:`~zplatform.control.uplink.validate_command`'s:
        not checked again), ``shown`` as the operator typed it; ``armed``:
        ARM n first, then it as n+1."""
        self._cmds.put((command, shown, armed))

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    # -- the thread ----------------------------------------------------------
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

    def _on_event(self, rec: EventRecord) -> None:
        with self.model.lock:
            self.model.on_event(rec)

    def _run(self) -> None:
        from ..ground.gapfill import GapFill
        from ..ground.link import GroundLink

        link = GroundLink(
            self.mission,
            commands=True,
            clock=self.clock,
            on_event=self._on_event,
            signer=self.signer,  # signed as `cmd` signs; the logic renews the lock's lease
        )
        logic = link.logic
        m = self.model
        waiting: dict[int, tuple[str, float]] = {}  # ticket -> (what, deadline)
        fill = None
        replies: Mailbox[tuple[int, bytes | None]] = Mailbox(_FILL_BACKLOG)
        if "cn" in self.mission.recording_nodes:
            try:
                # Events only: no snapshot is handed in, so no telemetry gap is asked.
                fill = GapFill(
                    self.mission,
                    link.link_keys,
                    logic.events,
                    lambda _rx, _dv: None,
                    run=logic.run,
                    logic=logic,
                    on_event=self._on_event,
                )
            except ZPlatformError as exc:  # keys without the downlink's: shown, not filled
                with m.lock:
                    m.note(self.now_ns(), f"missed events are not filled: {exc}", "WARNING_LO")
        try:
            while not self._stop.is_set():
                t = link.next(0.05)
                if fill is not None:
                    self._pump(link, fill, replies)
                m.waiting_for_run = link.waiting_for_run  # one bool: no lock needed
                if t is not None:
                    counters = logic.counters
                    with m.lock:
                        m.on_snapshot(link.dv, t, counters)
                while True:
                    try:
                        checked, shown, armed = self._cmds.get_nowait()
                    except queue.Empty:
                        break
                    what = ("armed " if armed else "") + shown
                    try:
                        ticket = link.submit(checked, armed=armed)
                    except ZPlatformError as exc:
                        with m.lock:
                            m.on_refusal(self.now_ns(), what, str(exc))
                        continue
                    waiting[ticket] = (what, time.monotonic() + self.timeout_s)
                arm = logic.awaiting_approval
                if arm != m.awaiting_arm:
                    with m.lock:
                        m.set_awaiting(self.now_ns(), arm)
                    if arm is not None:  # the approval may take the ARM's window
                        extra = ARM_WINDOW_NS / 1e9
                        waiting = {k: (w, d + extra) for k, (w, d) in waiting.items()}
                for ticket, (what, deadline) in list(waiting.items()):
                    done = logic.result(ticket)
                    if done is not None:
                        del waiting[ticket]
                        with m.lock:
                            for o in done:
                                m.on_result(self.now_ns(), o)
                            for cmd in logic.steps(ticket)[len(done) :]:
                                m.on_refusal(self.now_ns(), cmd, "not sent (ARM not accepted)")
                    elif time.monotonic() > deadline:
                        # Still waiting (the logic resends, then says NO_VERDICT): say so once.
                        waiting[ticket] = (what, float("inf"))
                        why = (
                            "still waiting"
                            if logic.joined
                            else link.why_no_telemetry(self.timeout_s)
                        )
                        with m.lock:
                            m.note(
                                self.now_ns(),
                                f"{what}: no verdict within {self.timeout_s:g} s ({why})",
                                "WARNING_HI",
                            )
                self.busy = bool(waiting)
        finally:
            link.close()

    def _pump(
        self, link: GroundLink, fill: GapFill, replies: Mailbox[tuple[int, bytes | None]]
    ) -> None:
        """The event gap fill's replies in, its requests out, time on."""
        now = self.clock.now_ns
        while (item := replies.pop()) is not None:
            rid, payload = item
            if payload is None:
                fill.on_done(rid, now())
            else:
                fill.on_reply(rid, payload)
        req = fill.take_request(now())
        if req is not None:
            rid, payload, timeout_s = req
            link.query(link.keys.recorder, payload, timeout_s, replies, rid, fill.screen)
        fill.tick(now())


_FILL_BACKLOG = 64
"""Event gap-fill replies waiting for the console's thread, at most."""
