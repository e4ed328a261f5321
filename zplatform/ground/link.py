"""The ground's zenoh driver: one session feeding a :class:`~.logic.GroundLogic`.

:class:`GroundLink` is the only place a ground tool meets zenoh (the ground
node, ``cmd``, ``tap``, ``log``, the prompt, the console, ``up``'s watcher). It
holds one session and at most one each of: a telemetry subscriber
(``{vehicle}/cn/telemetry``), an event intake (``{vehicle}/*/events``), a
command publisher (``{vehicle}/gn/to_cn``) and a raw tap on any key.

Contract: every zenoh callback only checks and queues (:mod:`zplatform.control.intake`),
each kind in a bounded mailbox of its own (:data:`TELEMETRY_BACKLOG`,
:data:`EVENT_BACKLOG`, :data:`TAP_BACKLOG`, :data:`ALIVE_BACKLOG`), so a flood
on one key displaces nothing on another; bad, replayed or stale input is
refused and counted, never raised. The caller's thread takes them
(:meth:`GroundLink.next`: telemetry first, then events), runs them through
the logic and publishes the requests it makes. A snapshot's age is measured
on arrival (a realtime-anchored :class:`~zplatform.runtime.timebase.NodeClock`); the
bound is the mission's or ``ZPLATFORM_TELEMETRY_MAX_AGE_MS``. Not thread-safe.

Mailboxes: docs/architecture.md#ground; its run: :class:`GroundLink`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import zenoh

from ..config import Mission
from ..control.authority import ARM_WINDOW_NS, Signer
from ..control.handoff import Mailbox, Waker
from ..control.intake import TelemetryIntake
from ..control.uplink import CheckedCommand, ScriptCommand, validate_command
from ..core.auth import KeySet, Run, channel, load_keys
from ..core.datavector import DataVector
from ..core.events import EV, MAX_TEXT, Event
from ..errors import CommandError, IntraHostError, TransportError
from ..runtime.clocksync import RunAsker
from ..runtime.queries import ask, replies
from ..runtime.timebase import NodeClock
from ..runtime.tmiox import (
    TelemetryPaths,
    TelemetryReceiver,
    open_telemetry_subscriber,
    telemetry_path_wanted,
)
from ..runtime.transport import EventPublisher, NodeSession, is_matching
from ..telemetry.records import CommandOutcome, EventRecord
from .identity import line_signer
from .logic import GroundLogic, default_max_age_ns

__all__ = [
    "EVENT_BACKLOG",
    "EVENT_MAX",
    "MAX_AGE_ENV",
    "TAP_BACKLOG",
    "TELEMETRY_BACKLOG",
    "GroundLink",
    "max_age_ns_from_env",
]

MAX_AGE_ENV = "ZPLATFORM_TELEMETRY_MAX_AGE_MS"
TELEMETRY_BACKLOG = 1000
"""Admitted snapshots kept while the caller is busy: 10 s at 100 Hz. Fewer
for a large vector: at most :data:`_BACKLOG_BYTES` of them in all."""
EVENT_MAX = 4 * MAX_TEXT + 1024
"""The longest event record read: its text (at most ``MAX_TEXT``
characters, 4 bytes each in UTF-8 at worst) and the rest."""
EVENT_BACKLOG = 4096
TAP_BACKLOG = 4096
ALIVE_BACKLOG = 1024
"""Liveliness tokens :meth:`GroundLink.alive_nodes` holds at most (a flood lets the oldest go)."""
_BACKLOG_BYTES = 64 * 2**20
RELEARN_S = 1.0
"""Run hellos a link sends at most one of per this many seconds (module doc)."""
FIRST_HELLO_S = 0.1
"""Until a link learned its first run, it says hello this often: a control
node that comes up (or dies) within a second of the link is still seen. Not
after: a flood of them would only meet the commander's hello bound."""
RUN_ANSWERS = 8
"""Answers to run hellos kept for the caller's thread (more are let go)."""
RUN_HELLO_TIMEOUT_S = 1.0

_TM, _EV = 0, 1


def max_age_ns_from_env(mission: Mission) -> int:
    """The freshness bound: ``ZPLATFORM_TELEMETRY_MAX_AGE_MS`` when set,
    else the mission's (TransportError for a value that is not a positive
    number)."""
    text = os.environ.get(MAX_AGE_ENV, "")
    if not text:
        return default_max_age_ns(mission)
    try:
        ms = float(text)
    except ValueError:
        ms = 0.0
    if not 0 < ms < float("inf"):
        raise TransportError(f"{MAX_AGE_ENV}={text!r} is not a positive number of milliseconds")
    return int(ms * 1_000_000)


def _station_router(mission: Mission, station: str | None) -> list[str] | None:
    """The router endpoints of ``station`` (None: none listed)."""
    if station is None or mission.ground is None:
        return None
    st = next((s for s in mission.ground.stations if s.name == station), None)
    return list(st.connect) if st is not None and st.connect else None


class GroundLink:
    """One zenoh session driving one :class:`GroundLogic` (module doc).

    ``node``: run as that node of the mission (``gn``: its endpoints and
    liveliness token, declared once everything is subscribed); None: a
    tool connected to every node. ``keys``: the ground's keys, or
    ``"mission"`` to load them (:func:`zplatform.core.auth.load_keys`: host role
    ``gn`` when it runs as the ground node or may command, else ``tool``,
    from ``key_file``, the environment or the default key set) before any
    session opens, so a missing key is the first and only error.
    ``telemetry``/``events``/``commands``: which of the three to declare
    (a ``script`` implies ``commands``). ``on_event`` gets every event record
    in the caller's thread. ``announce=False``: declare the node's liveliness
    token later (:meth:`announce`), after some set-up of the caller's.
    ``signer``: the operator and station its requests name and are tagged
    by (a mission with ``ground:``; :func:`zplatform.ground.identity.station_signer`),
    who also keeps the command lock while they hold it
    (:class:`~.logic.GroundLogic`'s ``renew_lock``). ``station``: the
    station a link without a signer runs at (a watching station: it
    connects through that station's router, as a signer's link does).
    ``intra_host``: as the ground node (``node="gn"``) on the CN's host,
    also take the telemetry over iceoryx2 when the mission allows it
    (:mod:`zplatform.runtime.tmiox`: zenoh's subscriber stays, each
    snapshot is taken once; :attr:`tm_paths`); a tool never does. Under
    ``transport.intra_host: shm`` an end that cannot open raises
    TransportError.

    With authentication the link is bound to the commander's run
    (:attr:`run`), learned from its answer to a run hello
    (:class:`~zplatform.runtime.clocksync.RunAsker` on ``{vehicle}/cn/clock``),
    asked at once, then once a :data:`RELEARN_S` until answered; telemetry,
    events and gap-fill replies of another run are refused (stale) and
    nothing is taken before (:attr:`GroundLogic.waiting_for_run`). A genuine
    snapshot of another run (the control node restarted) makes it ask
    again, at most once a :data:`RELEARN_S`.

    Raises KeyError_ for a missing key, TransportError when the session
    cannot open, CommandError for a script that does not fit the mission.
    """

    def __init__(
        self,
        mission: Mission,
        *,
        node: str | None = None,
        keys: KeySet | Literal["mission"] | None = "mission",
        key_file: str | None = None,
        telemetry: bool = True,
        events: bool = True,
        commands: bool = False,
        script: Sequence[ScriptCommand] = (),
        on_event: Callable[[EventRecord], None] | None = None,
        clock: NodeClock | None = None,
        announce: bool = True,
        signer: Signer | None = None,
        station: str | None = None,
        intra_host: bool = True,
    ) -> None:
        self.mission = mission
        if keys == "mission":
            role = "gn" if node == "gn" or commands or script else "tool"
            keys = load_keys(mission, role, key_file)
        self.link_keys: KeySet | None = keys
        """The keys the link checks with (None: the mission does not authenticate)."""
        self.clock = clock or NodeClock()
        self.run: Run | None = Run() if keys is not None else None
        """The run the link is bound to (module doc; None: the mission does not
        authenticate); unknown (``run.known`` False) until learned."""
        self.logic = GroundLogic(
            mission,
            keys=keys,
            node=node or "ground",
            max_age_ns=max_age_ns_from_env(mission),
            script=script,
            run=self.run,
            signer=signer,
            # A script line naming its sender is signed with their key files,
            # read as `cmd --operator` reads them (beside the link's keys).
            signers=lambda op, st: line_signer(mission, op, st, key_file),
        )
        self.on_event = on_event
        # The ground node on the CN's host also takes telemetry over iceoryx2
        # (zplatform.runtime.tmiox), zenoh's subscriber kept: each frame once.
        # Before the session: a pinned `shm` that cannot open leaves nothing open.
        tm_sub = None
        why_not = ""
        if node == "gn" and telemetry and intra_host and telemetry_path_wanted(mission):
            try:
                tm_sub = open_telemetry_subscriber(mission, keys is not None)
            except IntraHostError as exc:
                if mission.transport.intra_host == "shm":
                    raise TransportError(f"telemetry over iceoryx2: {exc}") from exc
                why_not = f"no iceoryx2 end ({exc})"
        # A station with a router (ground.stations[].connect) reaches the
        # vehicle through it, as a zenoh client of that router alone.
        at = signer.station if signer is not None else station
        via = _station_router(mission, at) if node is None else None
        overrides: dict[str, Any] = {"via": via} if via else {}
        try:
            self.ns = NodeSession(
                mission, node, announce=False, commands=bool(commands or script), **overrides
            )
        except BaseException:
            if tm_sub is not None:
                tm_sub.close()
            raise
        self.keys = self.ns.keys
        session = self.ns.session
        # One mailbox per kind (module doc), one waker for the caller's thread.
        self._waker = Waker()
        self._tm = TelemetryIntake(
            mission,
            channel(keys, "telemetry", self.run),
            max(2, min(TELEMETRY_BACKLOG, _BACKLOG_BYTES // self.logic.max_frame_len)),
            self.logic.max_age_ns,
            self._waker,
            dedupe=tm_sub is not None,
        )
        self.tm_paths = TelemetryPaths()
        """The telemetry's path (``tm_paths.path``: ``iox`` or ``zenoh``) and
        its fallbacks (zplatform.runtime.tmiox)."""
        self._tm_iox: TelemetryReceiver | None = None
        if why_not:
            self.logic.events.emit(
                EV.TM_FALLBACK, self.clock.now_ns(), node=node, why=why_not, fallbacks=0
            )
        assert self._tm.box is not None
        self._tm_box = self._tm.box
        # The run hello (module doc): answers come through their own mailbox.
        self._asker = RunAsker(keys, self.run) if self.run is not None else None
        self._run_box: Mailbox[bytes] = Mailbox(RUN_ANSWERS, self._waker)
        self._relearn = False  # set on zenoh's thread by a snapshot of another run
        self._last_hello = -RELEARN_S
        self._learned = False  # a run was known once (then RELEARN_S paces hellos)
        self._tm.on_other_run = self._on_other_run
        self._ev_box: Mailbox[tuple[str, bytes, int]] = Mailbox(EVENT_BACKLOG, self._waker)
        self._tap_box: Mailbox[tuple[str, bytes, bool]] = Mailbox(TAP_BACKLOG, self._waker)
        # Records refused as they arrived (oversize or forged): zenoh's thread
        # writes, the caller's reads (a total).
        self._ev_oversize = 0
        self._ev_oversize_seen = 0
        self._subs: list[zenoh.Subscriber[None]] = []
        if telemetry:
            self._subscribe(self.keys.telemetry, self._on_telemetry)
        if tm_sub is not None:
            self._tm_iox = TelemetryReceiver(tm_sub, self._tm, self.clock.now_ns)
        if events:
            self._subscribe(self.keys.all_events, self._on_event)
        self._pub: zenoh.Publisher | None = None
        if commands or script:
            # DROP (zenoh's default for a put, said here): a stalled link
            # loses a request, which the ground logic sends again and at last
            # ends NO_VERDICT; it never blocks the ground's thread.
            self._pub = session.declare_publisher(
                self.keys.gn_to_cn, congestion_control=zenoh.CongestionControl.DROP
            )
        # A node publishes its own events (and takes them back through its
        # intake); a tool hands them to on_event itself.
        self._ev_pub = (
            EventPublisher(
                session,
                self.keys.events(node),
                self.logic.events,
                channel(keys, f"events_{node}", self.run),
            )
            if node is not None
            else None
        )
        self._closed = False
        self._announce_pending = False
        self._learn_run()
        if announce:
            self.announce()

    def announce(self) -> None:
        """Declare the node's liveliness token (once; nothing for a tool).
        Alive only once subscribed: the CN waits for the ground node's token
        before its first loop, so a log starts at loop 1."""
        if self.waiting_for_run:
            # Alive only once it can take telemetry: declared when the run is
            # learned (_learn_run), so the log still starts at loop 1.
            self._announce_pending = True
            return
        self.ns.announce()

    # -- reading -------------------------------------------------------------
    @property
    def dv(self) -> DataVector:
        """The last accepted snapshot (:attr:`GroundLogic.dv`)."""
        return self.logic.dv

    # -- the run (module doc) --------------------------------------------------
    def _on_other_run(self) -> None:
        # zenoh's thread (the intake's lock held): a flag, nothing more.
        self._relearn = True

    def _learn_run(self) -> None:
        """Take the answers that came; send a hello when the run is unknown
        or a snapshot of another run came, at most once a RELEARN_S."""
        asker = self._asker
        if asker is None:
            return
        while (answer := self._run_box.pop()) is not None:
            if asker.check(answer) and self._announce_pending:
                self._announce_pending = False
                self.ns.announce()
        run = self.run
        assert run is not None
        if run.known and not self._relearn:
            return
        now = time.monotonic()
        if run.known:
            self._learned = True
        if now - self._last_hello < (RELEARN_S if self._learned else FIRST_HELLO_S):
            return
        self._last_hello = now
        self._relearn = False
        ask(
            self.ns.session,
            self.keys.clock,
            replies(self._on_run_answer, lambda: None),
            payload=asker.hello(),
            timeout_s=RUN_HELLO_TIMEOUT_S,
        )

    def _on_run_answer(self, reply: zenoh.Reply) -> None:
        # zenoh's thread: screen (header tag and nonce: junk and replies to
        # other hellos never reach the bounded mailbox, where a flood of them
        # would push the commander's answer out), then hand off only.
        ok = reply.ok
        asker = self._asker
        if ok is None or asker is None:
            return
        data = asker.screen(ok.payload)
        if data is not None:
            self._run_box.put(data)

    @property
    def waiting_for_run(self) -> bool:
        """Whether the link has not learned the vehicle's run yet (module doc)."""
        return self.logic.waiting_for_run

    def _pop_any(self) -> tuple[int, bytes, int, str] | None:
        """The next item of any kind (telemetry first), or None at once:
        kind, payload, receive time, the key it came on ("" for telemetry)."""
        self._learn_run()
        tm = self._tm_box.pop()
        if tm is not None:
            return _TM, tm[1], tm[0], ""
        # Events wait in their (bounded) mailbox until the run is known, then
        # are checked in it: an event of this run sent before this link
        # learned the run (a short script's script_done) is not lost.
        ev = None if self.waiting_for_run else self._ev_box.pop()
        if ev is not None:
            return _EV, ev[1], ev[2], ev[0]
        return None

    def _waiting(self) -> bool:
        events = len(self._ev_box) and not self.waiting_for_run
        return bool(len(self._tm_box) or events or len(self._run_box))

    def _pop(self, deadline: float) -> tuple[int, bytes, int, str] | None:
        while True:
            left = deadline - time.monotonic()
            if self._asker is not None and (self._relearn or self.waiting_for_run):
                left = min(left, RELEARN_S)  # wake to ask the run again
            self._waker.wait(self._waiting, left)
            got = self._pop_any()
            if got is not None or time.monotonic() >= deadline:
                break
        if got is None:
            self._after(self.clock.now_ns())
        return got

    def _take(self, kind: int, payload: bytes, rx: int, key: str) -> bool:
        """One telemetry frame or event (that came on ``key``) through the
        logic; True when a snapshot was accepted."""
        logic = self.logic
        if kind == _TM:
            # Its tag was checked on arrival (the intake): not again.
            ok = logic.on_telemetry(
                payload, rx, can_send=self.cn_listening, authentic=self._tm.authenticates
            )
            self._after(rx)
            return ok
        rec = logic.on_event_bytes(key, payload, rx)
        if rec is not None and self.on_event is not None:
            self.on_event(rec)
        self._after(rx)
        return False

    def next(self, timeout_s: float) -> int | None:
        """Take what arrived, up to ``timeout_s`` (0: only what is queued),
        until a snapshot is accepted: returns its receive time (ns), or None
        when the time ran out first. Events met on the way go to
        ``on_event``; refused snapshots are counted by the logic."""
        return self._pump(timeout_s)

    def _pump(self, timeout_s: float) -> int | None:
        """Take queued items until an accepted snapshot (its receive time),
        or the time runs out."""
        deadline = time.monotonic() + timeout_s
        while (item := self._pop(deadline)) is not None:
            kind, payload, rx, key = item
            if self._take(kind, payload, rx, key):
                return rx
        return None

    def _after(self, now_ns: int) -> None:
        """Count what the intakes refused, publish the logic's requests, hand
        over its events, let time pass."""
        logic = self.logic
        size, bad, stale = self._tm.take_counts()
        if size or bad or stale:
            tm = self._tm
            logic.refused(size, bad, stale, tm.aged, now_ns, tm.ahead, unchecked=tm.took_unchecked)
        rx = self._tm_iox
        if rx is not None:
            self._tm_path(rx, now_ns)
        oversize = self._ev_oversize
        if oversize != self._ev_oversize_seen:
            logic.refused_events(oversize - self._ev_oversize_seen)
            self._ev_oversize_seen = oversize
        logic.tick(now_ns)
        if self._pub is not None:
            for frame in logic.take_requests():
                self._pub.put(frame)
        if self._ev_pub is not None:
            self._ev_pub.flush()
        elif logic.events.pending:
            for e in logic.events.drain():
                self._own_event(e)

    def _tm_path(self, rx: TelemetryReceiver, now_ns: int) -> None:
        """The telemetry's path and counts (zplatform.runtime.tmiox) into the
        logic; a change evented (``tm_on_shm``, ``tm_fallback``)."""
        paths = self.tm_paths
        tm = self._tm
        change = paths.update(tm.taken_iox, tm.taken_zenoh, rx.publishers, rx.error)
        self.logic.count_paths(tm.taken_iox, tm.duplicates, paths.fallbacks)
        if change is not None:
            path, why = change
            ev = EV.TM_ON_SHM if path == "iox" else EV.TM_FALLBACK
            self.logic.events.emit(
                ev, now_ns, node=self.logic.node, why=why, fallbacks=paths.fallbacks
            )

    @property
    def telemetry_iox(self) -> TelemetryReceiver | None:
        """The iceoryx2 path's receiver (a ground node on the CN's host), or None."""
        return self._tm_iox

    def _own_event(self, e: Event) -> None:
        if self.on_event is not None:
            self.on_event(EventRecord.of(e, e.t_ns))

    @property
    def cn_listening(self) -> bool:
        """Whether the control node subscribes to command requests now."""
        return self._pub is not None and is_matching(self._pub)

    def wait_joined(self, timeout_s: float) -> None:
        """Block until a snapshot was accepted (the ground follows a CN run).

        Raises CommandError after ``timeout_s``, saying why: nothing came,
        or what came was refused (stale stamps name the clock bound and how
        to widen it when this host's clock is off)."""
        deadline = time.monotonic() + timeout_s
        while not self.logic.joined:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CommandError(self.why_no_telemetry(timeout_s))
            self.next(min(left, 0.2))

    def why_no_telemetry(self, waited_s: float) -> str:
        """What to tell an operator when no snapshot was accepted."""
        c = self.logic.counters
        refused = sum(c.refused.values())
        if self.waiting_for_run:
            return (
                f"waiting for the vehicle's run: the control node did not answer this "
                f"ground's run hello on {self.keys.clock} within {waited_s:g} s (is it up, "
                "and does this host hold the mission's downlink key?)"
            )
        if not c.bad and not refused:
            return f"no telemetry from the control node within {waited_s:g} s"
        what = ", ".join(f"{n} {k}" for k, n in (("bad", c.bad), *c.refused.items()) if n)
        hint = ""
        if c.refused["stale"] or c.refused["ahead"]:
            hint = (
                "; if this host's clock is off from the vehicle's, synchronise it (chrony, "
                f"NTP) or widen the bound with {MAX_AGE_ENV}=MILLISECONDS"
            )
        return (
            f"no acceptable telemetry within {waited_s:g} s: {what} snapshot(s) refused; "
            f"last: {self.logic.last_refusal}{hint}"
        )

    # -- commanding ----------------------------------------------------------
    def wait_cn_listening(self, timeout_s: float) -> None:
        """Block until the control node subscribes to command requests."""
        if self._pub is None:
            raise CommandError("this link was opened without a command publisher")
        deadline = time.monotonic() + timeout_s
        while not self.cn_listening:
            if time.monotonic() > deadline:
                raise CommandError("the control node does not subscribe to ground commands")
            self.next(0.01)

    def submit(self, checked: CheckedCommand, *, armed: bool = False) -> int:
        """Queue a command :func:`~zplatform.control.uplink.validate_command` checked
        (:meth:`GroundLogic.submit`: not checked again) and publish it if it
        can go now; returns its ticket. Never blocks."""
        ticket = self.logic.submit(
            checked, now_ns=self.clock.now_ns(), armed=armed, can_send=self.cn_listening
        )
        self._after(self.clock.now_ns())
        return ticket

    def command(
        self,
        command: str | CheckedCommand,
        element: str | None = None,
        value: str | None = None,
        *,
        armed: bool = False,
        timeout_s: float = 10.0,
        on_approval: Callable[[int], None] | None = None,
    ) -> list[CommandOutcome]:
        """Send one operator command and wait for its outcome(s). Blocks.

        An armed two-person command (``ground.two_person``) waits after its
        ARM for a second operator's approval, up to the ARM's window more
        than ``timeout_s``; ``on_approval`` is told the ARM's number once
        then (to say who must approve what).

        ``command``: its name, with ``element`` and ``value`` where it takes
        them, refused before sending (CommandError) when
        :func:`~zplatform.control.uplink.validate_command` refuses it; or what that
        function returned already (not checked again). Whether a command
        needs ``armed`` is the caller's to ask (:func:`~.logic.needs_arm`).
        Waits up to ``timeout_s`` for telemetry and the CN to listen, and as
        long again for the verdicts (and their reasons); raises CommandError
        when one does not come.
        """
        checked = (
            command
            if isinstance(command, CheckedCommand)
            else validate_command(self.mission, command, element, value)  # before anything waits
        )
        self.wait_joined(timeout_s)
        self.wait_cn_listening(timeout_s)
        ticket = self.submit(checked, armed=armed)
        deadline = time.monotonic() + timeout_s
        told = False
        while (done := self.logic.result(ticket)) is None:
            if not told and (arm := self.logic.awaiting_approval) is not None:
                told = True
                deadline += ARM_WINDOW_NS / 1e9
                if on_approval is not None:
                    on_approval(arm)
            if time.monotonic() > deadline:
                steps = " then ".join(self.logic.steps(ticket))
                raise CommandError(f"no verdict for {steps} within {timeout_s:g} s")
            # One item at a time: the outcome is released by the CN's event
            # (its reason) after the verdict's snapshot, and is returned then,
            # not with the next snapshot a loop later (next() would wait for it).
            item = self._pop(min(deadline, time.monotonic() + 0.05))
            if item is not None:
                self._take(*item)
        return done

    # -- taps and liveliness -------------------------------------------------
    # zenoh's thread: the intakes (module doc), each stamped on arrival.
    def _on_telemetry(self, sample: zenoh.Sample) -> None:
        self._tm.admit(sample.payload, self.clock.now_ns())

    def _on_event(self, sample: zenoh.Sample) -> None:
        p = sample.payload
        if len(p) > EVENT_MAX:
            self._ev_oversize += 1  # this callback is the only writer
            return
        key, data = str(sample.key_expr), p.to_bytes()
        # The tag before the mailbox: a forged record (a keyless flood) is
        # counted and let go here, never queued (a flood of them filled the
        # mailbox, up to EVENT_BACKLOG x EVENT_MAX bytes, and pushed the
        # genuine records out: a full mailbox lets the oldest go).
        if self.logic.forged_event(key, data):
            self._ev_oversize += 1
            return
        self._ev_box.put((key, data, self.clock.now_ns()))

    def _on_tap(self, sample: zenoh.Sample) -> None:
        p = sample.payload  # and whether shared memory carried it
        self._tap_box.put((str(sample.key_expr), p.to_bytes(), p.as_shm() is not None))

    def _subscribe(self, keyexpr: str, on_sample: Callable[[zenoh.Sample], None]) -> None:
        self._subs.append(
            self.ns.session.declare_subscriber(
                keyexpr, zenoh.handlers.Callback(on_sample, indirect=False)
            )
        )

    def tap(self, keyexpr: str) -> None:
        """Also subscribe to every sample on ``keyexpr``, raw, for
        :meth:`next_tap`."""
        self._subscribe(keyexpr, self._on_tap)

    def next_tap(self, timeout_s: float) -> tuple[str, bytes, bool] | None:
        """The next tapped sample ``(key, payload, came through shared
        memory)``, up to ``timeout_s``, or None. Telemetry and events that
        arrive meanwhile are not taken (:meth:`next` takes them)."""
        return self._tap_box.get(timeout_s)

    @property
    def taps_dropped(self) -> int:
        """Tapped samples let go because :data:`TAP_BACKLOG` were waiting."""
        return self._tap_box.dropped

    def query(
        self,
        key_expr: str,
        payload: bytes,
        timeout_s: float,
        into: Mailbox[tuple[int, bytes | None]],
        tag: int,
        screen: Callable[[int, bytes], bool] | None = None,
    ) -> None:
        """Send one get on ``key_expr`` (every reply kept: no consolidation)
        and return at once: each reply's payload is queued into ``into`` as
        ``(tag, payload)`` as it arrives (error replies are skipped), then
        ``(tag, None)`` when the get is over (every replier done, or
        ``timeout_s`` passed). For the gap fill from the CN's recorder.
        ``screen(tag, payload)``: whether a reply may be queued, checked in
        zenoh's callback first (the gap fill's
        :class:`~zplatform.ground.gapfill.ReplyScreen`), so junk never takes
        a place in ``into`` (issue 25).

        Sent by :func:`zplatform.runtime.queries.ask`: every queryable on the key
        is asked (a peer declaring a "complete" recorder queryable cannot
        take the request from the CN's recorder; the gap fill takes only
        replies whose tag checks), DROPped rather than blocked on a
        congested link. Never blocks."""

        def on_reply(reply: zenoh.Reply) -> None:
            ok = reply.ok  # screen, hand off only
            if ok is not None:
                data = ok.payload.to_bytes()
                if screen is None or screen(tag, data):
                    into.put((tag, data))

        ask(
            self.ns.session,
            key_expr,
            replies(on_reply, lambda: into.put((tag, None))),
            payload=payload,
            timeout_s=timeout_s,
            # The replies travel with these: behind live traffic.
            priority=zenoh.Priority.BACKGROUND,
        )

    def alive_nodes(self, timeout_s: float = 1.0) -> list[str]:
        """The mission's nodes with a liveliness token now, sorted. Blocks at
        most ``timeout_s`` (the tokens come through a bounded mailbox, read
        with that deadline: a peer that floods tokens or a query zenoh never
        ends cannot hold the caller)."""
        box: Mailbox[str | None] = Mailbox(ALIVE_BACKLOG)

        def on_reply(reply: zenoh.Reply) -> None:
            ok = reply.ok  # hand off only
            if ok is not None:
                box.put(str(ok.key_expr))

        self.ns.session.liveliness().get(
            self.keys.all_alive, replies(on_reply, lambda: box.put(None)), timeout=timeout_s
        )
        names = set()
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            key = box.get(left)
            if key is None:  # the get is over, or the deadline passed
                break
            parts = key.split("/")
            if len(parts) >= 2:
                names.add(parts[-2])
        return sorted(names)

    def close(self) -> None:
        """Undeclare everything and close the session; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._tm_iox is not None:
                self._tm_iox.close()
            if self._ev_pub is not None:
                self._ev_pub.undeclare()
            for s in self._subs:
                s.undeclare()
            if self._pub is not None:
                self._pub.undeclare()
        finally:
            self.ns.close()

    def __enter__(self) -> GroundLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
