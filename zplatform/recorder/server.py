"""The CN's recorder answers the ground's gap-fill requests over zenoh.

:class:`RecorderServer` declares a queryable on ``{vehicle}/cn/recorder``
(formats: :mod:`~.format`) and costs the control loop nothing but the GIL's
share of one thread. Zenoh's callback checks the size (unread), the
request's header tag and stamp (a channel of its own: junk and old
replays dropped unanswered, counted in ``refused``), then a rate bound
(a GCRA: :data:`REQUEST_BURST`, then one every :data:`REQUEST_EVERY_NS`;
the excess counted in ``excess``), and hands the query to a bounded inbox
(:data:`MAX_PENDING`; more counted in ``busy``); it never blocks. A
thread logs refusals at most once a :data:`LOG_PERIOD_S`. The bound comes
after the tag so junk never spends it (issue 25).

One serving thread checks each request (tag, stamp, not served before, a
range of this run), drops and counts one that does not check, reads the
segment files (never the loop's buffer) and replies in paced chunks (the
frames of the loops asked, or their ``EVENT`` records, tagged as when
published), then a tagged ``END`` with the totals and the request's stamp.
Detail: docs/architecture.md#the-gap-fill.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import zenoh

from ..control.handoff import QueryWorker
from ..core.auth import TAG_LEN, AuthError, Channel, Run
from .format import (
    DROPPED,
    EVENT,
    EVENTS_MAGIC,
    FRAME,
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
from .reader import counts, scan_segment
from .writer import FlightRecorder

__all__ = [
    "MAX_PENDING",
    "REMEMBERED",
    "REQUEST_BURST",
    "REQUEST_EVERY_NS",
    "WRITE_WAIT_S",
    "RecorderServer",
]

MAX_PENDING = 2
"""Requests waiting or being served; any more are dropped unanswered."""
REMEMBERED = 64
"""Requests the serving thread remembers (served), a second check behind
the callback's: zenoh's callback remembers every request it let through
until its stamp leaves the bound (:meth:`RecorderServer.on_query`)."""
LOG_PERIOD_S = 1.0
"""At most one log line of refused requests this often (:class:`RecorderServer`)."""
log = logging.getLogger("zplatform.recorder")
REQUEST_BURST = 8
"""Requests a recorder server takes at once (module doc); a ground asks one
at a time, each after the last one's answer."""
REQUEST_EVERY_NS = 100_000_000
"""Then one request this often (ns): ten a second, far above a ground's gap fills."""
_REQUEST_TAU_NS = (REQUEST_BURST - 1) * REQUEST_EVERY_NS
WRITE_WAIT_S = 1.0
"""How long a request for loops still in the recorder's buffer waits for them
to be written (then what is in the files is sent)."""


class RecorderServer(QueryWorker):
    """Serves gap-fill requests from ``recorder``'s files (module doc).

    The serving thread checks each request (the telemetry channel's tag, a
    stamp within the clock bound, none let through before (the callback's
    memory, :meth:`on_query`) or served lately, a range of at most
    :data:`~.format.MAX_REQUEST_LOOPS` loops of this run); one that does not
    check is dropped unanswered and counted (:attr:`refused`,
    :attr:`last_refusal`), never raised. It reads the segment files (waits
    up to :data:`WRITE_WAIT_S` for loops still in the loop's buffer, never
    reading it) and replies in chunks of at most
    :data:`~.format.REPLY_BYTES` paced to ``serve_bps``; a blocked reply
    holds this thread, never the loop. The final ``END`` reply counts the
    frames sent, the loops not held and the loops never run.

    ``channel``: the telemetry channel (its own instance: channels are not
    thread-safe), None when the mission does not authenticate; ``now_ns``:
    this node's clock; ``max_age_ns``: how far a request's stamp may be from
    it; ``divisor``: the mission's telemetry divisor; ``events``: the node's
    events channel (its own instance, bound to a
    :class:`~zplatform.core.auth.Run` of its own, which the serving thread
    sets to the recorder's run), which tags the event records an events
    request is answered with (None: the mission does not authenticate, they
    go untagged). Declares the
    queryable and starts the thread at construction; :meth:`close` stops
    both (idempotent)."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        recorder: FlightRecorder,
        channel: Channel | None,
        *,
        now_ns: Callable[[], int],
        max_age_ns: int,
        serve_bps: int,
        divisor: int = 1,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        events: Channel | None = None,
    ) -> None:
        self.recorder = recorder
        self._mono = mono_ns
        self._tat = -(1 << 63)  # the rate bound's theoretical arrival time
        # zenoh's threads: the header tag (with a channel of its own: the
        # serving thread's is not shared) and the rate bound, under one lock.
        self._rx_lock = threading.Lock()
        self._rx_channel = channel.twin() if channel is not None else None
        self.excess = 0
        """Authentic requests dropped unanswered beyond the rate bound (module doc)."""
        self._refused_early = 0  # by header tag or stamp, on zenoh's threads (in `refused`)
        # Every request zenoh's callback let through whose stamp is still
        # within the bound (its run, range and stamp, with the stamp, in the
        # order let through; and as a set): a replay of any is refused there.
        # Only requests within the rate bound are kept, so at most
        # REQUEST_BURST + (2 * max_age_ns) / REQUEST_EVERY_NS of them.
        self._seen_fifo: deque[tuple[int, bytes]] = deque()
        self._seen: set[bytes] = set()
        self._channel = channel
        # The END reply's (the serving thread's): tagged under the run the
        # request names, so the ground's screen takes it as a frame of it.
        self._end_ch = channel.twin() if channel is not None else None
        if self._end_ch is not None:
            self._end_ch.run = Run()
        self._events = events
        self._now = now_ns
        self._max_age = max_age_ns
        self._bps = serve_bps
        self._div = divisor
        self._key = key_expr
        self._req_len = REQUEST.size + (TAG_LEN if channel is not None else 0)
        # The requests served lately (the serving thread's): a replay of one
        # is refused, not served again.
        self._served: deque[tuple[int, int, int, int]] = deque(maxlen=REMEMBERED)
        self._closed = False
        self.served = 0
        """Requests answered."""
        self.frames_sent = 0
        self.events_sent = 0
        super().__init__("recorder-serve", MAX_PENDING, (zenoh.ZError,))
        self.logged = 0
        """Refusals (:attr:`refusals`) reported in the log so far."""
        self._stop_log = threading.Event()
        self._logger = threading.Thread(target=self._log_loop, name="recorder-log", daemon=True)
        self._logger.start()
        self.queryable = session.declare_queryable(
            key_expr, zenoh.handlers.Callback(self.on_query, indirect=False)
        )

    @property
    def refused(self) -> int:
        """Requests dropped unanswered because they did not check: of a wrong
        size, header tag or stamp (zenoh's callback), or any other check
        (the serving thread)."""
        return super().refused + self._refused_early

    @property
    def refusals(self) -> int:
        """Every request dropped unanswered: beyond the rate bound, of a wrong
        size or failing a check (:attr:`refused`), or past a full inbox."""
        return self.excess + self.refused + self.busy

    def log_refusals(self) -> bool:
        """Log one line if requests were refused since the last one (the
        count, how many beyond the rate bound, the last reason); returns
        whether it did. The logging thread calls it once a
        :data:`LOG_PERIOD_S`: zenoh's callback only counts."""
        total = self.refusals
        if total == self.logged:
            return False
        log.warning(
            "recorder requests refused: %d so far (%d since the last report, %d beyond "
            "the rate bound, %d with the inbox full); the last: %s",
            total,
            total - self.logged,
            self.excess,
            self.busy,
            self.last_refusal or "beyond the rate bound",
        )
        self.logged = total
        return True

    def _log_loop(self) -> None:
        while not self._stop_log.wait(LOG_PERIOD_S):
            self.log_refusals()

    def on_query(self, query: Any) -> None:
        """The queryable's callback: the size (unread), the header tag, the
        stamp (within ``max_age_ns`` of this node's clock), not a request let
        through before, the rate bound, then (the base's) the hand-off
        (module doc). Never blocks beyond a short lock; never raises for
        what arrives.

        Replays: a request let through is remembered until its stamp leaves
        the bound, so a replay of any, however many were captured, is
        refused by the stamp or by the memory, before the rate bound (it
        spends none of it). A request beyond the rate bound is not
        remembered (the memory stays bounded by the rate): it was never
        served, and its replay is one more authentic request, bounded as
        the genuine asker's own."""
        p = query.payload
        n = 0 if p is None else len(p)
        why = self.size_refusal(n)
        if why is None and self._rx_channel is not None:
            # A request is shorter than the header tag's bytes (codecs/FORMAT.md
            # §6.1): its header tag is all the serving thread's tag check
            # would refuse junk by, for a copy of 68 bytes.
            data = p.to_bytes()
            with self._rx_lock:
                try:
                    body = self._rx_channel.open_header(data)
                except AuthError as exc:
                    why = str(exc)
                else:
                    # The stamp is authentic now: a replay older than the
                    # bound, or of a request let through within it, spends
                    # no share of the rate bound either.
                    now_ns = self._now()
                    stamp = REQUEST.unpack_from(body)[4]
                    age = now_ns - stamp
                    key = bytes(body[4 : REQUEST.size])  # run, range, stamp
                    self._forget(now_ns)
                    if abs(age) > self._max_age:
                        why = f"a request stamped {age / 1e9:+.3f} s from this node's clock"
                    elif key in self._seen:
                        why = "a request seen before (a replay)"
        if why is not None:
            with self._rx_lock:
                if n == self._req_len:
                    self._refused_early += 1
                else:
                    self._refused_rx += 1
                self.last_refusal = why
            query.drop()
            return
        now = self._mono()
        with self._rx_lock:
            remember = self._rx_channel is not None
            if remember and key in self._seen:
                # Its twin let through on another of zenoh's threads meanwhile.
                self._refused_early += 1
                self.last_refusal = "a request seen before (a replay)"
                over = True
            else:
                tat = max(self._tat, now)
                over = tat - now > _REQUEST_TAU_NS
                if over:
                    self.excess += 1
                else:
                    self._tat = tat + REQUEST_EVERY_NS
                    if remember:
                        self._seen_fifo.append((stamp, key))
                        self._seen.add(key)
        if over:
            query.drop()
            return
        super().on_query(query)

    def _forget(self, now_ns: int) -> None:
        """Forget the requests let through whose stamp has left the bound
        (oldest let through first; with the lock held)."""
        fifo, limit = self._seen_fifo, now_ns - self._max_age
        while fifo and fifo[0][0] < limit:
            self._seen.discard(fifo.popleft()[1])

    def size_refusal(self, n: int) -> str | None:
        return None if n == self._req_len else f"a request of {n} bytes"

    def serve(self, query: zenoh.Query) -> None:
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        ch = self._channel
        try:
            # Header first (codecs/FORMAT.md §6.1): a request is shorter than
            # the header tag's bytes, so every check below reads authentic
            # bytes, and a replay is refused before the body's MAC.
            body: Any = ch.open_header(data) if ch is not None else data
        except AuthError as exc:
            self.refuse(str(exc))
            return
        magic, run, first, last, t_ns = REQUEST.unpack(body)
        if magic not in (REQUEST_MAGIC, EVENTS_MAGIC):
            self.refuse("not a recorder request")
            return
        age = self._now() - t_ns
        if abs(age) > self._max_age:
            self.refuse(f"a request stamped {age / 1e9:+.3f} s from this node's clock")
            return
        if first < 1 or last < first or last - first >= MAX_REQUEST_LOOPS:
            self.refuse(f"a range of loops {first}..{last}")
            return
        request = (t_ns, run, first, last)  # a stamp is never reused: the kind need not be in
        if ch is not None:  # without tags a replay cannot be told from a request
            if request in self._served:
                self.refuse(f"a request for loops {first}..{last} served before (a replay)")
                return
            try:
                ch.check_body(data)
            except AuthError as exc:
                self.refuse(str(exc))
                return
            self._served.append(request)
        if magic == EVENTS_MAGIC:
            self._serve_events(query, run, first, last, t_ns)
            return
        rec = self.recorder
        div = self._div
        asked = set(range(first + (-first) % div, last + 1, div))  # the telemetry loops
        sent: set[int] = set()
        dropped: set[int] = set()
        not_run: set[int] = set()
        if run == rec.run:
            # The newest loops may still be in the recorder's buffer: give
            # its writer (one interval, normally) to put them in a file.
            deadline = time.monotonic() + WRITE_WAIT_S
            while rec.written_loop < min(last, rec.loop) and time.monotonic() < deadline:
                time.sleep(0.005)
            with rec.lock:
                # This run's segments from the first whose frames reach the
                # range (a DROPPED record may sit after the range's last
                # frame); size as written (the newest one is still growing).
                ours = [s for s in rec.segments if s.run == run and s.first]
                todo = [(s.path, s.size) for s in ours if s.last >= first]
                oldest = ours[0].first if ours else 0
            self._send(query, todo, first, last, sent, dropped)
            # A loop between the oldest and the newest recorded, neither
            # recorded nor dropped, never ran: the CN's scheduler skipped
            # its period (an overrun), so there never was such telemetry.
            if oldest:
                top = rec.written_loop
                not_run = {n for n in asked - sent - dropped if oldest <= n <= top}
        not_held = len(asked - sent - not_run)
        self._end(query, run, t_ns, len(sent), not_held, len(not_run))
        self.served += 1

    def _end(self, query: zenoh.Query, run: int, t_ns: int, *totals: int) -> None:
        """The ``END`` reply (:data:`~.format.REPLY_DONE`): ``totals``, the
        request's stamp ``t_ns``, tagged under ``run`` (codecs/FORMAT.md §12)."""
        body = REPLY_DONE.pack(REPLY_END, *totals, t_ns)
        ch = self._end_ch
        if ch is not None and ch.run is not None:
            ch.run.set(run)
            body = bytes(ch.seal(body))
        self._reply(query, body)

    def _send(
        self,
        query: zenoh.Query,
        todo: list[tuple[Any, int]],
        first: int,
        last: int,
        sent: set[int],
        dropped: set[int],
    ) -> None:
        """Reply with every recorded frame of ``first..last``, in chunks,
        paced; note the loops sent and those the recorder said it dropped."""

        def want(typ: int, loop: int) -> bool:
            return typ in (FRAME, DROPPED) and loop >= first

        start = time.monotonic()
        out = bytearray([REPLY_FRAMES])
        nbytes = 0
        records = itertools.chain.from_iterable(
            scan_segment(path, lambda _t: None, limit=size, want=want) for path, size in todo
        )
        for r in records:
            if r.type == DROPPED:
                c = counts(r.payload)
                if c is not None:
                    dropped.update(range(max(c[0], first), min(c[1], last) + 1))
                continue
            if r.loop > last:  # past the range, and past any DROPPED record of it
                break
            if len(out) > 1 and len(out) + REPLY_LEN.size + len(r.payload) > REPLY_BYTES:
                nbytes += self._reply(query, out)
                self._pace(start, nbytes)
                out = bytearray([REPLY_FRAMES])
            out += REPLY_LEN.pack(len(r.payload))
            out += r.payload
            sent.add(r.loop)
        if len(out) > 1:
            nbytes += self._reply(query, out)
            self._pace(start, nbytes)
        self.frames_sent += len(sent)

    def _serve_events(self, query: zenoh.Query, run: int, first: int, last: int, t_ns: int) -> None:
        """Answer an events request: the ``EVENT`` records of run ``run``
        filed under loops ``first..last``, tagged, in paced chunks of
        :data:`~.format.REPLY_EVENTS`; then ``END`` with the events sent and
        the loops of the range this recorder does not hold (before its
        oldest, after its newest written, or another run's)."""
        rec = self.recorder
        sent = 0
        held = 0
        if run == rec.run:
            deadline = time.monotonic() + WRITE_WAIT_S
            while rec.written_loop < min(last, rec.loop) and time.monotonic() < deadline:
                time.sleep(0.005)
            with rec.lock:
                ours = [s for s in rec.segments if s.run == run and s.first]
                todo = [(s.path, s.size) for s in ours if s.last >= first]
                oldest = ours[0].first if ours else 0
            ch = self._events
            if ch is not None and ch.run is not None:
                ch.run.set(run)  # tagged as the node tagged them: for this run
            start = time.monotonic()
            out = bytearray([REPLY_EVENTS])
            nbytes = 0
            records = itertools.chain.from_iterable(
                scan_segment(
                    path,
                    lambda _t: None,
                    limit=size,
                    # The first frame past the range ends the scan.
                    want=lambda typ, loop: (
                        (typ == EVENT and loop >= first) or (typ == FRAME and loop > last)
                    ),
                )
                for path, size in todo
            )
            for r in records:
                if r.loop > last:
                    break
                body = bytes(ch.seal(r.payload)) if ch is not None else r.payload
                if len(out) > 1 and len(out) + REPLY_LEN.size + len(body) > REPLY_BYTES:
                    nbytes += self._reply(query, out)
                    self._pace(start, nbytes)
                    out = bytearray([REPLY_EVENTS])
                out += REPLY_LEN.pack(len(body))
                out += body
                sent += 1
            if len(out) > 1:
                nbytes += self._reply(query, out)
                self._pace(start, nbytes)
            if oldest:
                held = max(0, min(last, rec.written_loop) - max(first, oldest) + 1)
        self.events_sent += sent
        self._end(query, run, t_ns, sent, last - first + 1 - held, 0)
        self.served += 1

    def _reply(self, query: zenoh.Query, payload: bytes | bytearray) -> int:
        # A reply travels with its query's QoS (zenoh 1.x): the ground asks
        # at the lowest priority, with DROP congestion control.
        query.reply(self._key, bytes(payload))
        return len(payload)

    def _pace(self, start: float, nbytes: int) -> None:
        """Sleep until ``nbytes`` since ``start`` is within ``serve_bps``."""
        ahead = nbytes / self._bps - (time.monotonic() - start)
        if ahead > 0:
            time.sleep(ahead)

    def close(self) -> None:
        """Undeclare the queryable and stop the thread (after the request in
        hand, if any). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.queryable.undeclare()
        self.stop_serving()
        self._stop_log.set()
        self._logger.join(timeout=2)
        self.log_refusals()  # what the last period refused
