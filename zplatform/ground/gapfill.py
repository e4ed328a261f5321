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

from collections import deque
from collections.abc import Callable
from typing import NamedTuple

from ..config import Mission
from ..core.auth import TAG_LEN, KeySet, Run, channel
from ..core.codec import RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.events import EV, Event, EventLog
from ..errors import CodecError
from ..recorder.format import (
    EVENTS_MAGIC,
    MAX_REQUEST_LOOPS,
    REPLY_BYTES,
    REPLY_END,
    REPLY_EVENTS,
    REPLY_FRAMES,
    REPLY_LEN,
    REPLY_TOTALS,
    REQUEST,
    REQUEST_MAGIC,
)
from ..telemetry.records import EventRecord
from .logic import EventGap, Gap, GroundLogic, default_max_age_ns

__all__ = ["GapFill"]

_NS = 1_000_000_000


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
        "tries",
    )

    def __init__(self, gap: EventGap) -> None:
        self.gap = gap
        self.chunk = 0  # the chunk of MAX_REQUEST_LOOPS loops asked next
        self.rid = 0
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
        self.refused = 0
        """Frames in replies that did not check."""
        self.last_refusal = ""
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
        ch = self._channel
        return f.rid, (bytes(ch.seal(body)) if ch is not None else body), timeout_ns / _NS

    def _on_events(self, f: _EvFill, payload: bytes) -> None:
        """One reply of the events request in flight (:meth:`on_reply`)."""
        logic = self._logic
        assert logic is not None
        if payload[0] == REPLY_END and len(payload) == 1 + REPLY_TOTALS.size:
            f.ended = True
            f.not_held += REPLY_TOTALS.unpack_from(payload, 1)[1]
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
        if payload[0] == REPLY_END and len(payload) == 1 + REPLY_TOTALS.size:
            _, ask.not_held, ask.not_run = REPLY_TOTALS.unpack_from(payload, 1)
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
        self.refused += 1
        if not self.last_refusal:
            self.last_refusal = why

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
        longer than ``hold_s`` are written, the gaps still open given up."""
        ask = self._ask
        if ask is not None and now_ns > ask.deadline:
            self.on_done(ask.id, now_ns)
        f = self._evf
        if f is not None and f.rid and now_ns > f.deadline:
            self._events_done(f, now_ns)
        if self._held and now_ns - self._held[0].rx_ns > self._hold_ns:
            self._abandon(now_ns, f"not filled within {self._hold_ns / _NS:g} s")

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
