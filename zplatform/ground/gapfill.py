"""Filling the ground log's telemetry gaps from the CN's flight recorder.

:class:`GapFill` asks the CN's recorder (``{vehicle}/cn/recorder``,
:mod:`zplatform.recorder.server`) for the loops
:attr:`~.logic.GroundLogic.gaps` queued, as soon as a snapshot shows the
link is back, and writes the log **in loop order**: while a gap is being
filled, arriving snapshots are held (copies, in memory, at most
``hold_s``); with nothing to fill each is written as accepted (no copy).

Sans-IO, single-threaded (the driver's thread): the driver hands in every
accepted snapshot (:meth:`GapFill.snapshot`), sends the requests it is
given (:meth:`GapFill.take_request`, one at a time) and hands back their
replies and end (:meth:`GapFill.on_reply`, :meth:`GapFill.on_done`).
Every frame a reply carries is checked as live telemetry is, then for the
gap's run, range, divisor, replay and stamp; refused frames are counted
(:attr:`GapFill.refused`, :attr:`GapFill.last_refusal`), never raised.
Loops never run are counted apart (:attr:`GapFill.not_run`); each request
ends in ``gap_filled`` / ``gap_unfilled`` events.
Detail: docs/architecture.md#the-gap-fill.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import NamedTuple

from ..config import Mission
from ..core.auth import TAG_LEN, KeySet, Run, channel
from ..core.codec import RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.events import EV, EventLog
from ..errors import CodecError
from ..recorder.format import (
    MAX_REQUEST_LOOPS,
    REPLY_END,
    REPLY_FRAMES,
    REPLY_LEN,
    REPLY_TOTALS,
    REQUEST,
    REQUEST_MAGIC,
)
from .logic import Gap, GroundLogic, default_max_age_ns

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
    None: bound to none. Not thread-safe: the driver's thread calls
    everything.
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
        if self._ask is not None or not self._todo:
            return None
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

    def on_reply(self, rid: int, payload: bytes) -> None:
        """One reply of request ``rid``: frames (each checked, module doc)
        or the recorder's end totals. A reply of a request no longer in
        flight is ignored; an empty one is refused (counted). Never raises."""
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
        if self._held and now_ns - self._held[0].rx_ns > self._hold_ns:
            self._abandon(now_ns, f"not filled within {self._hold_ns / _NS:g} s")

    def finish(self, now_ns: int) -> None:
        """The log ends: whatever is still open is given up, every row written."""
        self._abandon(now_ns, "the log ended first")

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
