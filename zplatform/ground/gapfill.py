"""Filling the ground log's telemetry gaps from the CN's flight recorder.

:class:`GapFill` asks the CN's recorder (``{vehicle}/cn/recorder``,
:mod:`zplatform.recorder.server`) for the loops
:attr:`~.logic.GroundLogic.gaps` queued, as soon as a snapshot shows the
link is back, and writes the log **in loop order**: while a gap is being
filled, arriving snapshots are held (copies, in memory, at most
``hold_s``); with nothing to fill each is written as accepted (no copy).

Sans-IO, single-threaded: the driver hands in snapshots
(:meth:`GapFill.snapshot`), sends requests (:meth:`GapFill.take_request`)
and hands back replies (:meth:`GapFill.on_reply`, :meth:`GapFill.on_done`).
Every frame a reply carries is checked as live telemetry is, then for the
gap's run, range, divisor, replay and stamp; refused ones are counted.
Loops never run are counted apart (:attr:`GapFill.not_run`); requests end
in ``gap_filled`` / ``gap_unfilled`` events. Then the gaps in the CN's
event numbers (:attr:`GroundLogic.event_gaps`): records checked as live ones
(:meth:`GroundLogic.check_filled`), handed on in number order, marked
filled (``events_filled`` / ``events_unfilled``). See docs/architecture.md.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import NamedTuple

from ..config import Mission
from ..control.intake import RefusalLog
from ..core.auth import TAG_LEN, AuthError, Channel, KeySet, Run, channel
from ..core.codec import RegionCodec, fixed_stamp
from ..core.datavector import DataVector, Layout
from ..core.events import EV, Event, EventLog
from ..errors import CodecError
from ..recorder.format import (
    EVENTS_MAGIC,
    MAX_REQUEST_LOOPS,
    REPLY_BYTES,
    REPLY_DONE,
    REPLY_END,
    REPLY_EVENTS,
    REPLY_FRAMES,
    REPLY_LEN,
    REQUEST,
    REQUEST_MAGIC,
)
from ..telemetry.records import EventRecord
from .logic import EventGap, Gap, GroundLogic, default_max_age_ns

__all__ = ["GapFill", "ReplyScreen"]

_NS = 1_000_000_000


class _Expect(NamedTuple):
    """The request in flight, as :class:`ReplyScreen` checks its replies."""

    rid: int
    kind: int  # REPLY_FRAMES or REPLY_EVENTS
    run: int
    first: int
    last: int
    stamp: int


def _end_totals(ch: Channel | None, payload: bytes, run: int, stamp: int) -> tuple[int, ...] | str:
    """The totals of the ``END`` reply ``payload`` (:data:`REPLY_DONE`) if it
    answers the request of ``run`` stamped ``stamp``, else why not."""
    if len(payload) != REPLY_DONE.size + (TAG_LEN if ch is not None else 0):
        return f"an end reply of {len(payload)} bytes"
    if ch is not None:
        try:
            body = ch.open(payload, any_run=True)
        except AuthError as exc:
            return str(exc)
        if Channel.run_of(payload) != run:
            return f"an end reply of run {Channel.run_of(payload)}, not {run}"
    else:
        body = memoryview(payload)
    _, sent, not_held, not_run, t_ns = REPLY_DONE.unpack_from(body)
    if t_ns != stamp:
        return "an end reply of another request"
    return sent, not_held, not_run


class ReplyScreen:
    """Screens the recorder's replies in zenoh's callback, before the
    ground's bounded mailbox (issue 25): a reply of the request in flight,
    of its kind and of a size a recorder sends; a chunk's first frame (or
    event record) with a header tag that checks for the request's run (and
    for frames a loop of the range); an ``END`` whole (tag, run, the
    request's stamp). Junk from a keyless peer so never takes a place a
    genuine reply needs. Refusals are counted (:attr:`refused`, in
    :attr:`GapFill.refused`); a reply of a request no longer in flight is
    dropped uncounted (a late genuine one). Thread-safe (one lock); copies
    nothing, allocates nothing but an error's text; never raises."""

    __slots__ = ("_ev", "_expect", "_lock", "_max", "_tm", "last_refusal", "refused")

    def __init__(self, tm: Channel | None, ev: Channel | None, frame_max: int) -> None:
        self._tm = tm.twin() if tm is not None else None  # unbound: the run is checked here
        if self._tm is not None:
            self._tm.run = None
        self._ev = ev
        self._max = 1 + REPLY_LEN.size + max(REPLY_BYTES, frame_max)
        self._lock = threading.Lock()
        self._expect: _Expect | None = None
        self.refused = 0
        self.last_refusal = ""

    def expect(self, e: _Expect | None) -> None:
        """The request now in flight (the driver's thread)."""
        self._expect = e  # one reference swap

    def __call__(self, rid: int, payload: bytes) -> bool:
        """Whether ``payload``, a reply of request ``rid``, may be queued."""
        e = self._expect
        if e is None or e.rid != rid:
            return False
        with self._lock:
            why = self._why(e, payload)
            if why is None:
                return True
            self.refused += 1
            self.last_refusal = why
            return False

    def _why(self, e: _Expect, p: bytes) -> str | None:
        n = len(p)
        if not 1 < n <= self._max:
            return f"a reply of {n} bytes"
        if p[0] == REPLY_END:
            why = _end_totals(self._tm, p, e.run, e.stamp)
            return why if isinstance(why, str) else None
        if p[0] != e.kind:
            return f"a reply of kind {p[0]} to a request for kind {e.kind}"
        ch = self._tm if e.kind == REPLY_FRAMES else self._ev
        if n < 1 + REPLY_LEN.size:
            return "a reply cut inside its first length"
        (k,) = REPLY_LEN.unpack_from(p, 1)
        if k > n - 1 - REPLY_LEN.size or k < 1:
            return f"a first item of {k} bytes in a reply"
        if ch is None:
            return None
        item = memoryview(p)[1 + REPLY_LEN.size : 1 + REPLY_LEN.size + k]
        try:
            ch.open_header(item, any_run=True)
        except AuthError as exc:
            return str(exc)
        run = Channel.run_of(item)
        if run != e.run:
            return f"a reply of run {run}, not {e.run}"
        if e.kind == REPLY_FRAMES:
            stamp = fixed_stamp(item)
            if stamp is None:
                return "a reply whose first item is not a region frame"
            seq = stamp[0]
            if not e.first <= seq <= e.last:
                return f"a reply from loop {seq}, not asked for ({e.first}..{e.last})"
        return None


class _Ask:
    """One request in flight: its number, range, tries, deadline and what came."""

    __slots__ = (
        "asked",
        "deadline",
        "epoch",
        "first",
        "got",
        "id",
        "last",
        "not_held",
        "not_run",
        "tries",
    )

    def __init__(self, rid: int, gap: Gap, tries: int, deadline: int, asked: int) -> None:
        self.id = rid
        self.asked = asked  # when it was asked, on the ground's clock
        self.epoch, self.first, self.last = gap
        self.tries = tries
        self.deadline = deadline
        self.got: dict[int, tuple[int, bytes]] = {}  # loop -> (t_ns, vector bytes)
        self.not_held: int | None = None  # from the recorder's END reply
        self.not_run = 0


class _EvFill:
    """The event gap being filled: its chunks of loops, the request in
    flight (``rid``, 0: none), its tries, and the records checked so far."""

    __slots__ = (
        "chunk",
        "deadline",
        "ended",
        "gap",
        "got",
        "not_before",
        "not_held",
        "rid",
        "stamp",
        "tries",
    )

    def __init__(self, gap: EventGap) -> None:
        self.gap = gap
        self.chunk = 0  # the chunk of MAX_REQUEST_LOOPS loops asked next
        self.rid = 0
        self.stamp = 0  # the request in flight's
        self.tries = 0
        self.not_before = 0
        self.deadline = 0
        self.ended = False  # the request in flight had its END
        self.not_held = 0  # loops the recorder said it does not hold
        self.got: dict[int, Event] = {}  # number -> record, checked


class _Row(NamedTuple):
    epoch: int
    loop: int
    rx_ns: int
    data: bytes


class GapFill:
    """Fills the gaps of one ground log (module doc).

    ``write(rx_ns, dv)`` writes one row (the log's
    :meth:`~zplatform.ground.logger.TelemetryLog.snapshot`); ``events`` gets
    the ``gap_filled``/``gap_unfilled`` events (the ground's own log,
    :attr:`GroundLogic.events`). ``keys``: the ground's keys (a ground
    node's or a tool's: both hold the downlink's, which tags the requests
    and the frames; None: the mission does not authenticate); KeyError_
    when they do not hold it. ``run``: the run the ground learned
    (:attr:`GroundLogic.run`): a frame of another run is refused (an
    earlier run's, replayed), and so is every frame while it is unknown;
    None: bound to none. ``logic``: the ground's logic, whose event gaps
    of the control node are filled too (module doc; it is told so:
    :attr:`GroundLogic.fill_events_of`), the records handed to
    ``on_event``. Not thread-safe: the driver's thread calls everything.
    """

    def __init__(
        self,
        mission: Mission,
        keys: KeySet | None,
        events: EventLog,
        write: Callable[[int, DataVector], None],
        *,
        hold_s: float = 30.0,
        tries: int = 3,
        retry_s: float = 1.0,
        run: Run | None = None,
        logic: GroundLogic | None = None,
        on_event: Callable[[EventRecord], None] | None = None,
    ) -> None:
        rec = mission.recorder
        self._bps = rec.serve_bps if rec is not None else 1_000_000
        self._layout = Layout.for_node(mission, "cn")
        self._dv = DataVector(self._layout)
        self._codec = RegionCodec(self._dv)
        self._channel = channel(keys, "telemetry", run)
        self._frame_max = self._codec.max_frame_len + (TAG_LEN if self._channel else 0)
        self._epoch_at = self._layout.element("cn_epoch").offset
        self._loop_at = self._layout.element("cn_loop").offset
        self._div = mission.telemetry_divisor
        self._events = events
        self._write = write
        self._hold_ns = int(hold_s * _NS)
        self._tries = tries
        self._retry_ns = int(retry_s * _NS)
        self._max_age = default_max_age_ns(mission)
        self._todo: deque[tuple[Gap, int, int]] = deque()  # (range, tries so far, not before)
        self._ask: _Ask | None = None
        self._next_id = 0
        self._filled: list[_Row] = []
        self._held: deque[_Row] = deque()
        self.filled = 0
        """Rows written from the recorder."""
        self.unfilled = 0
        """Loops given up (not held by the recorder, no answer, or held too long)."""
        self.not_run = 0
        """Gap loops the CN never ran (its scheduler skipped their periods):
        no telemetry of them exists, so they are not missing from the log."""
        self._refused = 0
        self._last_refusal = ""
        self._latest = ""  # the latest reason (the event's)
        self._ref_log = RefusalLog(1)  # refusals evented at most once a second
        self._ref_ours = self._ref_screened = 0  # counted in the event log so far
        self._ev_why = ""
        self.requests = 0
        # Event gaps (module doc): the logic's, filled one at a time.
        self._logic = logic
        self._on_event = on_event
        self._evf: _EvFill | None = None
        if logic is not None and rec is not None and "cn" in mission.recording_nodes:
            logic.fill_events_of = frozenset({"cn"})
        self.events_filled = 0
        """Events handed on filled from the recorder."""
        self.events_unfilled = 0
        """Missing events the recorder's replies did not bring (given up)."""
        ev = None
        if keys is not None and logic is not None and logic.fill_events_of:
            ev = channel(keys, "events_cn")
        self.screen = ReplyScreen(self._channel, ev, self._frame_max)
        """For the zenoh callback of the requests' replies (:class:`ReplyScreen`)."""

    @property
    def refused(self) -> int:
        """Replies refused in zenoh's callback (:attr:`screen`) and frames
        or records in replies that did not check."""
        return self._refused + self.screen.refused

    @property
    def last_refusal(self) -> str:
        return self._last_refusal or self.screen.last_refusal

    @property
    def busy(self) -> bool:
        """A gap is being filled (rows are held)."""
        return bool(self._todo or self._ask is not None or self._held)

    # -- the log -------------------------------------------------------------
    def snapshot(self, logic: GroundLogic, rx_ns: int) -> None:
        """Take the snapshot ``logic`` just accepted at ``rx_ns``: new gaps
        are queued for asking; the row is written now when nothing is being
        filled, else held (a copy) until the gaps before it are."""
        while logic.gaps:
            gap = logic.gaps.popleft()
            step = MAX_REQUEST_LOOPS - MAX_REQUEST_LOOPS % self._div
            for first in range(gap.first, gap.last + 1, step):
                chunk = Gap(gap.epoch, first, min(first + step - 1, gap.last))
                self._todo.append((chunk, 0, 0))
        if not self.busy:
            self._write(rx_ns, logic.dv)
            return
        buf = bytes(logic.dv.buf)
        self._held.append(
            _Row(self._u64(buf, self._epoch_at), self._u64(buf, self._loop_at), rx_ns, buf)
        )
        self.tick(rx_ns)

    @staticmethod
    def _u64(buf: bytes, at: int) -> int:
        return int.from_bytes(buf[at : at + 8], "little")

    # -- asking --------------------------------------------------------------
    def take_request(self, now_ns: int) -> tuple[int, bytes, float] | None:
        """The next request to send now, as ``(id, payload, timeout_s)``
        (hand its replies and its end back with that id; ``timeout_s`` is
        the zenoh get's), or None: one is in flight, or nothing is due (a
        range asked again waits ``retry_s`` times its tries)."""
        if self._ask is not None or (self._evf is not None and self._evf.rid):
            return None
        if not self._todo:
            return self._ask_events(now_ns)
        gap, tries, not_before = self._todo[0]
        if now_ns < not_before:
            return None
        self._todo.popleft()
        loops = (gap.last - gap.first) // self._div + 1
        timeout_ns = 3 * _NS + 2 * loops * (self._frame_max + REPLY_LEN.size) * _NS // self._bps
        self._next_id += 1
        self._ask = _Ask(self._next_id, gap, tries + 1, now_ns + timeout_ns + _NS, now_ns)
        self.requests += 1
        body = REQUEST.pack(REQUEST_MAGIC, gap.epoch, gap.first, gap.last, now_ns)
        self.screen.expect(
            _Expect(self._next_id, REPLY_FRAMES, gap.epoch, gap.first, gap.last, now_ns)
        )
        ch = self._channel
        return self._next_id, (bytes(ch.seal(body)) if ch is not None else body), timeout_ns / _NS

    def _ask_events(self, now_ns: int) -> tuple[int, bytes, float] | None:
        """The next events request (module doc), or None: none is due."""
        f = self._evf
        if f is None:
            logic = self._logic
            if logic is None or not logic.event_gaps:
                return None
            f = self._evf = _EvFill(logic.event_gaps.popleft())
        if now_ns < f.not_before:
            return None
        gap = f.gap
        first = gap.first_loop + f.chunk * MAX_REQUEST_LOOPS
        last = min(first + MAX_REQUEST_LOOPS - 1, gap.last_loop)
        timeout_ns = 3 * _NS
        self._next_id += 1
        f.rid = self._next_id
        f.tries += 1
        f.ended = False
        f.deadline = now_ns + timeout_ns + _NS
        self.requests += 1
        body = REQUEST.pack(EVENTS_MAGIC, gap.run, first, last, now_ns)
        f.stamp = now_ns
        self.screen.expect(_Expect(f.rid, REPLY_EVENTS, gap.run, first, last, now_ns))
        ch = self._channel
        return f.rid, (bytes(ch.seal(body)) if ch is not None else body), timeout_ns / _NS

    def _on_events(self, f: _EvFill, payload: bytes) -> None:
        """One reply of the events request in flight (:meth:`on_reply`)."""
        logic = self._logic
        assert logic is not None
        if payload[0] == REPLY_END:
            got = _end_totals(self._channel, payload, f.gap.run, f.stamp)
            if isinstance(got, str):
                self._refuse(got)
            else:
                f.ended = True
                f.not_held += got[1]
            return
        if payload[0] != REPLY_EVENTS:
            self._refuse("a reply of an unknown kind")
            return
        off, end = 1, len(payload)
        while off < end:
            if end - off < REPLY_LEN.size:
                self._refuse("a reply cut inside an event's length")
                return
            (n,) = REPLY_LEN.unpack_from(payload, off)
            off += REPLY_LEN.size
            if n > REPLY_BYTES or n > end - off:
                self._refuse(f"an event of {n} bytes in a reply")
                return
            raw = payload[off : off + n]
            off += n
            try:
                e = logic.check_filled(f.gap, raw)
            except CodecError as exc:
                self._refuse(str(exc))
                continue
            if e is None:
                continue  # genuine, of the same loops, not missing
            if e.seq in f.got:
                self._refuse(f"{e.node}'s event #{e.seq} again in a reply (a replay)")
            else:
                f.got[e.seq] = e

    def _events_done(self, f: _EvFill, now_ns: int) -> None:
        """The events request in flight is over: the next chunk, again
        later, or the gap's end (:meth:`_end_events`)."""
        f.rid = 0
        gap = f.gap
        if not f.ended:
            if f.tries < self._tries:
                f.not_before = now_ns + int(self._retry_ns * f.tries)
                return
            self._end_events(now_ns, f"no answer after {f.tries} request(s)")
            return
        f.tries = 0
        f.chunk += 1
        done = len(f.got) == gap.last - gap.first + 1
        if done or gap.first_loop + f.chunk * MAX_REQUEST_LOOPS > gap.last_loop:
            why = (
                "the recorder does not hold all of their loops"
                if f.not_held
                else "not among the records of their loops (the recorder dropped them)"
            )
            self._end_events(now_ns, why)

    def _end_events(self, now_ns: int, why: str) -> None:
        """The event gap being filled is over: its records handed on in
        number order, marked filled; the rest told not filled."""
        f, self._evf = self._evf, None
        logic = self._logic
        if f is None or logic is None:
            return
        gap = f.gap
        taken = []
        for seq in sorted(f.got):
            rec = logic.take_filled(gap, f.got[seq], now_ns)
            if rec is not None:
                taken.append(seq)
                if self._on_event is not None:
                    self._on_event(rec)
        if taken:
            self.events_filled += len(taken)
            self._events.emit(
                EV.EVENTS_FILLED,
                now_ns,
                n=len(taken),
                node=gap.node,
                first=taken[0],
                last=taken[-1],
            )
        n, rest = logic.close_event_gap(gap)
        if n:
            self.events_unfilled += n
            self._events.emit(
                EV.EVENTS_UNFILLED, now_ns, n=n, node=gap.node, which=rest.which, why=why
            )

    def on_reply(self, rid: int, payload: bytes) -> None:
        """One reply of request ``rid``: frames (each checked, module doc),
        events (each checked, for an events request) or the recorder's end
        totals. A reply of a request no longer in flight is ignored; an
        empty one is refused (counted). Never raises."""
        f = self._evf
        if f is not None and f.rid and f.rid == rid:
            if not payload:
                self._refuse("an empty reply")
            else:
                self._on_events(f, payload)
            return
        ask = self._ask
        if ask is None or ask.id != rid:
            return
        if not payload:
            self._refuse("an empty reply")
            return
        if payload[0] == REPLY_END:
            got = _end_totals(self._channel, payload, ask.epoch, ask.asked)
            if isinstance(got, str):
                self._refuse(got)
            else:
                _, ask.not_held, ask.not_run = got
            return
        if payload[0] != REPLY_FRAMES:
            self._refuse("a reply of an unknown kind")
            return
        off, end = 1, len(payload)
        while off < end:
            if end - off < REPLY_LEN.size:
                self._refuse("a reply cut inside a frame's length")
                return
            (n,) = REPLY_LEN.unpack_from(payload, off)
            off += REPLY_LEN.size
            if n > self._frame_max or n > end - off:
                self._refuse(f"a frame of {n} bytes in a reply")
                return
            self._take(ask, payload[off : off + n])
            off += n

    def _take(self, ask: _Ask, raw: bytes) -> None:
        try:
            body = self._channel.open(raw) if self._channel is not None else raw
            frame = self._codec.check(body)
        except CodecError as exc:
            self._refuse(str(exc))
            return
        data = bytes(frame.data)
        seq = frame.seq
        epoch = self._u64(data, self._epoch_at)
        if epoch != ask.epoch:
            self._refuse(f"a frame of control node run {epoch}, not {ask.epoch}")
        elif not ask.first <= seq <= ask.last or seq % self._div:
            self._refuse(f"a frame of loop {seq}, not asked for ({ask.first}..{ask.last})")
        elif frame.t_ns - ask.asked > self._max_age:
            # A recorded loop is older than the request: a stamp beyond the
            # clock bound after it is no clock's (it would be the row's time).
            self._refuse(f"a frame of loop {seq} stamped after it was asked for")
        elif seq in ask.got:
            self._refuse(f"a frame of loop {seq} again (a replay)")
        else:
            ask.got[seq] = (frame.t_ns, data)

    def _refuse(self, why: str) -> None:
        self._refused += 1
        self._latest = why
        if not self._last_refusal:
            self._last_refusal = why

    def _event_refusals(self, now_ns: int) -> None:
        """The replies and frames refused since the last call, evented at
        most once a second (a ``bad_frame`` event of the ground's log)."""
        ours, screened = self._refused, self.screen.refused
        new = ours - self._ref_ours + screened - self._ref_screened
        if screened > self._ref_screened:
            self._ev_why = self.screen.last_refusal
        elif ours > self._ref_ours:
            self._ev_why = self._latest
        self._ref_ours, self._ref_screened = ours, screened
        ev = self._ref_log.add(now_ns, new)
        if ev is not None:
            self._events.emit(
                EV.BAD_FRAME,
                now_ns,
                source=f"{ev[0]} gap-fill reply(s) or frame(s) from the recorder's key",
                reason=f"refused (the last: {self._ev_why})",
            )

    def on_done(self, rid: int, now_ns: int) -> None:
        """Request ``rid`` is over (all replies in, or its time ran out): keep
        what came, ask again later for what did not, tell the outcome."""
        f = self._evf
        if f is not None and f.rid and f.rid == rid:
            self._events_done(f, now_ns)
            return
        ask = self._ask
        if ask is None or ask.id != rid:
            return
        self._ask = None
        self._keep(ask, now_ns)
        missing = [s for s in range(ask.first, ask.last + 1, self._div) if s not in ask.got]
        if missing:
            if ask.not_held is not None and ask.not_held + ask.not_run >= len(missing):
                # All explained: loops that never ran (no telemetry to fill)
                # and loops the recorder does not hold (lost for this log).
                never = min(ask.not_run, len(missing))
                self.not_run += never
                if len(missing) > never:
                    why = "the control node's recorder does not hold them"
                    if never:
                        why += f" ({never} of the loops there never ran: skipped periods)"
                    self._give_up(ask.epoch, missing, now_ns, why, len(missing) - never)
            elif ask.tries >= self._tries:
                why = f"no answer for them after {ask.tries} request(s)"
                self._give_up(ask.epoch, missing, now_ns, why)
            else:  # again later, for the loops still missing
                again = now_ns + int(self._retry_ns * ask.tries)
                self._todo.appendleft((Gap(ask.epoch, missing[0], missing[-1]), ask.tries, again))
        self._release()

    def _keep(self, ask: _Ask, now_ns: int) -> None:
        """The frames a request brought, to be written; one event for them."""
        for seq, (t_ns, data) in ask.got.items():
            self._filled.append(_Row(ask.epoch, seq, t_ns, data))
        if ask.got:
            first, last = min(ask.got), max(ask.got)
            self._events.emit(EV.GAP_FILLED, now_ns, first=first, last=last, n=len(ask.got))

    def _give_up(
        self, epoch: int, missing: list[int], now_ns: int, why: str, n: int | None = None
    ) -> None:
        """``n`` (default: all) of the loops ``missing`` will not be in the log."""
        n = len(missing) if n is None else n
        self.unfilled += n
        self._events.emit(EV.GAP_UNFILLED, now_ns, first=missing[0], last=missing[-1], n=n, why=why)

    # -- time ----------------------------------------------------------------
    def tick(self, now_ns: int) -> None:
        """Let time pass: a request whose end never came is over; rows held
        longer than ``hold_s`` are written, the gaps still open given up;
        refusals since the last event evented (at most once a second)."""
        ask = self._ask
        if ask is not None and now_ns > ask.deadline:
            self.on_done(ask.id, now_ns)
        f = self._evf
        if f is not None and f.rid and now_ns > f.deadline:
            self._events_done(f, now_ns)
        if self._held and now_ns - self._held[0].rx_ns > self._hold_ns:
            self._abandon(now_ns, f"not filled within {self._hold_ns / _NS:g} s")
        self._event_refusals(now_ns)

    def finish(self, now_ns: int) -> None:
        """The log ends: whatever is still open is given up, every row
        written, every event gap ended (what came handed on)."""
        self._abandon(now_ns, "the log ended first")
        logic = self._logic
        while logic is not None and (self._evf is not None or logic.event_gaps):
            if self._evf is None:
                self._evf = _EvFill(logic.event_gaps.popleft())
            self._end_events(now_ns, "the log ended first")

    def _abandon(self, now_ns: int, why: str) -> None:
        ask, self._ask = self._ask, None
        open_gaps = [g for g, _, _ in self._todo]
        self._todo.clear()
        got: set[int] = set()
        if ask is not None:  # what it brought so far is kept
            self._keep(ask, now_ns)
            got = set(ask.got)
            open_gaps.insert(0, Gap(ask.epoch, ask.first, ask.last))
        for g in open_gaps:
            missing = [s for s in range(g.first, g.last + 1, self._div) if s not in got]
            if missing:
                self._give_up(g.epoch, missing, now_ns, why)
        self._release()

    # -- writing ---------------------------------------------------------------
    def _release(self) -> None:
        """With nothing left to ask, write the filled rows and the held ones,
        merged in (run, loop) order."""
        if self._todo or self._ask is not None:
            return
        filled = sorted(self._filled, key=lambda r: (r.epoch, r.loop))
        self._filled = []
        held = self._held
        dv = self._dv
        i = 0
        while i < len(filled) or held:
            if held and (
                i == len(filled)
                or (held[0].epoch, held[0].loop) < (filled[i].epoch, filled[i].loop)
            ):
                row = held.popleft()
            else:
                row = filled[i]
                i += 1
                self.filled += 1
            dv.buf[:] = row.data
            self._write(row.rx_ns, dv)
