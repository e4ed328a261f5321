"""The Data Synchronization Protocol on zenoh, both ends (thesis 3.3, 4.3).

Control node (:class:`ControlSync`), at the top of every loop::

    for each DN, in parallel:  get {vehicle}/dnX/to_cn  payload = frame(cn_to_dnX)
    wait until every DN replied or the sync deadline passed
    apply each valid reply's region; count rx / missed / late / bad frames

Device node (:class:`DeviceSync`)::

    block on the CN's query (the loop trigger, thesis 3.4.5.3)
    apply cn_to_dnX, reply at once with frame(dnX_to_cn)

Both ends decode with the region codec before anything touches the Data
Vector. Zenoh callbacks only put the sample on a ``queue.SimpleQueue``
(lock-free put, never blocks); the loop thread does all the work.

Why replies are matched by ``seq``: the zenoh query stays open for one loop
period (not just the sync deadline), so a reply that misses the deadline
still arrives and is *counted* as late (``cn_late_dnX``) at the next sync
instead of vanishing inside zenoh. It is never applied.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from .codec import RegionCodec
from .datavector import DataVector
from .errors import CodecError
from .transport import KeySpace, is_matching

# A query stamped this much later than the last one served, yet with a lower
# loop number, comes from a restarted control node.
_RESTART_NS = 1_000_000_000

__all__ = ["ControlSync", "DeviceSync", "SyncStats", "TapPublisher"]


class TapPublisher:
    """A put for taps that costs (almost) nothing when nobody subscribes.

    A matching listener keeps ``matching`` current from zenoh's thread; the
    loop reads one bool and skips the put when no subscriber matches.
    """

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self.matching = is_matching(self.pub)
        self._listener = self.pub.declare_matching_listener(
            zenoh.handlers.Callback(self._on_matching, indirect=False)
        )

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self.matching = bool(status.matching)

    def put(self, payload: bytes | bytearray) -> None:
        if self.matching:
            self.pub.put(payload)

    def undeclare(self) -> None:
        self._listener.undeclare()
        self.pub.undeclare()


class SyncStats:
    """Per-loop result of :meth:`ControlSync.sync` (reused, not reallocated)."""

    __slots__ = ("duration_ns", "overrun", "replied")

    def __init__(self) -> None:
        self.replied = 0
        self.duration_ns = 0
        self.overrun = False


class ControlSync:
    """The CN end: query every DN with its region, collect replies by a deadline.

    Not thread-safe: call :meth:`sync` from the loop thread only. Blocks for
    at most ``timeout_ns`` (plus scheduling latency).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dv: DataVector,
        dns: list[str],
        timeout_ns: int,
        query_timeout_s: float,
        *,
        monotonic: Callable[[], int] = time.monotonic_ns,
        on_bad: Callable[[str, str], None] | None = None,
    ) -> None:
        self.session = session
        self._on_bad = on_bad
        self.dv = dv
        self.dns = list(dns)
        self.timeout_ns = timeout_ns
        self._mono = monotonic
        self._query_timeout = query_timeout_s
        self._keys = [keys.dn_to_cn(dn) for dn in dns]
        self._out = [RegionCodec(dv, f"cn_to_{dn}") for dn in dns]
        self._in = [RegionCodec(dv, f"{dn}_to_cn") for dn in dns]
        self._rx = [dv.handle(f"cn_rx_{dn}") for dn in dns]
        self._missed = [dv.handle(f"cn_missed_{dn}") for dn in dns]
        self._late = [dv.handle(f"cn_late_{dn}") for dn in dns]
        self._bad = dv.handle("cn_bad_frames")
        self._overruns = dv.handle("cn_sync_overruns")
        self._taps = [TapPublisher(session, keys.cn_to_dn(dn)) for dn in dns]
        self._q: queue.SimpleQueue[tuple[int, Any]] = queue.SimpleQueue()
        self._got = [False] * len(dns)
        # Issued vs finalised queries (zenoh calls `drop` once per query when
        # it is done): lets start-up wait until no warm-up reply can still come.
        self._issued = 0
        self._finalised = 0
        self._idle = threading.Event()
        self._idle.set()
        self._callbacks = [
            zenoh.handlers.Callback(self._make_handoff(i), self._on_finalised, indirect=False)
            for i in range(len(dns))
        ]
        self._consolidation = zenoh.ConsolidationMode.NONE
        self.stats = SyncStats()

    def _on_finalised(self) -> None:
        self._finalised += 1  # zenoh's thread is the only writer
        if self._finalised == self._issued:
            self._idle.set()

    def quiesce(self, timeout_s: float) -> bool:
        """Wait until every query issued so far is finalised, then count any
        reply still queued as late. Returns False on timeout. Not for the loop:
        start-up uses it so warm-up replies never land in flight counters."""
        ok = self._idle.wait(timeout_s)
        self.drain_late()
        return ok

    def _make_handoff(self, i: int) -> Callable[[zenoh.Reply], None]:
        q = self._q

        def handoff(reply: zenoh.Reply) -> None:
            # zenoh's thread: extract the bytes and hand off, nothing more.
            ok = reply.ok
            if ok is not None:
                q.put((i, ok.payload.to_bytes()))
                return
            err = reply.err
            # zenoh's own "Timeout" comes one period after a miss that the
            # loop has already counted; any other error is the DN refusing.
            if err is None or err.payload.to_bytes() != b"Timeout":
                q.put((i, None))

        return handoff

    def sync(self, loop: int, t_ns: int) -> SyncStats:
        """Run one synchronisation for ``loop`` stamped ``t_ns``; see module doc."""
        start = self._mono()
        deadline = start + self.timeout_ns
        got = self._got
        n = len(self.dns)
        self._idle.clear()
        self._issued += n
        for i in range(n):
            got[i] = False
            out = self._out[i].encode(loop, t_ns)
            self.session.get(
                self._keys[i],
                self._callbacks[i],
                payload=out,
                consolidation=self._consolidation,
                timeout=self._query_timeout,
            )
            self._taps[i].put(out)
        pending = n
        q = self._q
        while pending:
            left = deadline - self._mono()
            if left <= 0:
                break
            try:
                i, payload = q.get(timeout=left / 1e9)
            except queue.Empty:
                break
            if payload is None:  # a reply_err: the DN refused the query
                self._bad.bump()
                if self._on_bad is not None:
                    self._on_bad(self.dns[i], "the device node answered with an error")
                continue
            try:
                frame = self._in[i].check(payload)
            except CodecError as exc:
                self._bad.bump()
                if self._on_bad is not None:
                    self._on_bad(self.dns[i], str(exc))
                continue
            if frame.seq != loop or got[i]:
                # an answer to an older loop (or a duplicate): counted, dropped
                self._late[i].bump()
                continue
            self._in[i].apply(payload)
            got[i] = True
            self._rx[i].bump()
            pending -= 1
        for i in range(n):
            if not got[i]:
                self._missed[i].bump()
        end = self._mono()
        st = self.stats
        st.replied = n - pending
        st.duration_ns = end - start
        # An overrun is the step itself running past its deadline: with every
        # reply in, any lateness; while waiting for a missing DN, waking more
        # than half a deadline late (the thread was not scheduled).
        st.overrun = end > deadline + (self.timeout_ns // 2 if pending else 0)
        if st.overrun:
            self._overruns.bump()
        return st

    def drain_late(self) -> None:
        """Count replies that arrived after the last sync's deadline (late)."""
        q = self._q
        while True:
            try:
                i, _ = q.get_nowait()
            except queue.Empty:
                return
            self._late[i].bump()

    def close(self) -> None:
        for t in self._taps:
            t.undeclare()


class DeviceSync:
    """The DN end: the CN's query is the loop trigger.

    :meth:`wait` blocks until a valid query for a *new* loop arrives (or the
    timeout passes), applies its ``cn_to_dnX`` region, replies at once with
    ``dnX_to_cn``, and returns the loop number. Malformed queries are counted
    in ``dnX_bad_frames``, reported to ``on_bad`` and answered with an error; queries for a loop not
    newer than the last one served are answered but not applied, and do not
    trigger a loop.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dv: DataVector,
        dn: str,
        now_ns: Callable[[], int],
        on_bad: Callable[[str], None] | None = None,
        stale_after_ns: int | None = None,
    ) -> None:
        self.dn = dn
        self._on_bad = on_bad
        # A query stamped (CN's synchronized time) more than this long ago
        # belongs to a loop the CN has already closed: answer, do not run it.
        self._stale_after = stale_after_ns
        self.dv = dv
        self._now = now_ns
        self._key = keys.dn_to_cn(dn)
        self._in = RegionCodec(dv, f"cn_to_{dn}")
        self._out = RegionCodec(dv, f"{dn}_to_cn")
        self._bad = dv.handle(f"{dn}_bad_frames")
        self._q: queue.SimpleQueue[zenoh.Query] = queue.SimpleQueue()
        self.last_loop = 0
        self.last_t_ns = 0
        self.stale = 0
        self._tap = TapPublisher(session, self._key)
        self.queryable = session.declare_queryable(
            self._key, zenoh.handlers.Callback(self._q.put, indirect=False)
        )

    def wait(self, timeout_s: float) -> int | None:
        """Block for the next trigger; returns its loop number or None on timeout.

        If queries piled up while this node was not scheduled, every one but
        the newest is answered as stale (the CN counts those replies late),
        and so is any query stamped more than ``stale_after_ns`` ago: like the
        CN's scheduler, a stalled DN skips missed loops and never runs a
        burst of old ones.
        """
        q = self._q
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                query = q.get(timeout=left)
            except queue.Empty:
                return None
            while not q.empty():  # a backlog: answer the older query, keep the newest
                self._serve(query, trigger=False)
                query = q.get_nowait()
            loop = self._serve(query, trigger=True)
            if loop is not None:
                return loop

    def _serve(self, query: zenoh.Query, *, trigger: bool) -> int | None:
        """Check, (maybe) apply and answer one query; the loop number if it triggers."""
        with query:
            payload = query.payload
            data = payload.to_bytes() if payload is not None else b""
            try:
                frame = self._in.check(data)
            except CodecError as exc:
                self._bad.bump()
                query.reply_err(str(exc).encode())
                if self._on_bad is not None:
                    self._on_bad(str(exc))
                return None
            # A lower seq with a later timestamp is a restarted CN, not an
            # old query: follow it rather than stall forever.
            now = self._now()
            new = (
                trigger
                and (frame.seq > self.last_loop or frame.t_ns > self.last_t_ns + _RESTART_NS)
                and (self._stale_after is None or now - frame.t_ns <= self._stale_after)
            )
            if new:
                self._in.apply(data)
                self.last_loop = frame.seq
                self.last_t_ns = frame.t_ns
            else:
                self.stale += 1
            reply = self._out.encode(frame.seq, now)
            query.reply(self._key, reply)
        self._tap.put(reply)
        return frame.seq if new else None

    def close(self) -> None:
        self.queryable.undeclare()
        self._tap.undeclare()
