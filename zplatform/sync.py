"""The Data Synchronization Protocol on zenoh, both ends (thesis 3.3, 4.3):
transport only.

What a frame means, which reply counts, what is late, stale or bad: all of
that is :mod:`zplatform.loop`'s, shared with the lockstep runner. These
classes only move the frames.

Control node (:class:`ControlSync`), at the top of every loop::

    for each DN, in parallel:  get {vehicle}/dnX/to_cn  payload = the loop's cn_to_dnX frame
    hand every reply to ControlLogic.reply until none is pending or the deadline passed

or, with ``transport.sync_query`` wildcard (:func:`zplatform.messages.wildcard_sync_for`)::

    get {vehicle}/*/to_cn  payload = a bundle of every DN's frame (codecs/FORMAT.md §6.2)

Each DN takes its own frame from the bundle; a reply is the DN's by its key.
One get instead of one per DN: fewer calls on the loop thread and one
routing pass in zenoh (bench/REPORT.md#sync).

Device node (:class:`DeviceSync`)::

    block on the CN's query (the loop trigger, thesis 3.4.5.3)
    DeviceLogic.trigger(payload) -> reply (or an error reply), at once

Zenoh callbacks only put the sample on a ``queue.SimpleQueue`` (lock-free
put, never blocks); the loop thread does all the work.

Why the query stays open one loop period (not just the sync deadline): a
reply that misses the deadline still arrives and is handed to the next
loop's ``reply``, which counts it late (``cn_late_dnX``) instead of it
vanishing inside zenoh. It is never applied.

Tracing (:data:`SyncTrace`): both ends take an optional ``trace`` callable,
called at each hop of an exchange with the hop's name, so a benchmark
(``python -m bench.sync_trace``) can stamp where a sync's time goes without
touching the classes' insides. Without one (the default, and every flight
node) the hand-offs are the untraced ones and the loop pays one ``is None``
test per query and reply.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from .codec import BundleEncoder
from .loop import ControlLogic, DeviceLogic
from .transport import KeySpace, is_matching

__all__ = ["ControlSync", "DeviceSync", "SyncTrace", "TapPublisher"]

_DROP = zenoh.CongestionControl.DROP
_ALL = zenoh.QueryTarget.ALL
_FOREIGN = -1  # a reply whose key is no DN's: counted as a bad frame

SyncTrace = Callable[[str, int], None]
"""``trace(hop, n)``: one hop of a sync exchange, called where it happens
(stamp the time inside; return at once, never block, never raise).

Control node (:class:`ControlSync`), ``n`` the DN's index:

* ``"issued"``: loop thread, just before the query to DN ``n`` is sent (a
  wildcard query: once per DN, before the one query);
* ``"back"``: zenoh's thread, DN ``n``'s reply being handed to the loop;
* ``"taken"``: loop thread, DN ``n``'s reply taken from the hand-off.

Device node (:class:`DeviceSync`):

* ``"arrive"``: zenoh's thread, a query being handed to the loop (``n`` 0);
* ``"serve"``: loop thread, the query taken from the hand-off (``n`` 0);
* ``"replied"``: loop thread, the reply sent; ``n`` is the CN loop the
  query carried (``DeviceLogic.last_loop``).
"""


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


class ControlSync:
    """The CN end: query every DN with its frame, hand replies to the loop.

    Not thread-safe: call :meth:`sync` from the loop thread only. Blocks for
    at most ``timeout_ns`` (plus scheduling latency). ``trace``: a
    :data:`SyncTrace` for benchmarks (None: no tracing).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dns: Sequence[str],
        timeout_ns: int,
        query_timeout_s: float,
        *,
        wildcard: bool = False,
        monotonic: Callable[[], int] = time.monotonic_ns,
        trace: SyncTrace | None = None,
    ) -> None:
        self.session = session
        self._trace = trace
        self.dns = list(dns)
        self.wildcard = wildcard and bool(dns)
        self.timeout_ns = timeout_ns
        self._mono = monotonic
        self._query_timeout = query_timeout_s
        self._keys = [keys.dn_to_cn(dn) for dn in dns]
        self._taps = [TapPublisher(session, keys.cn_to_dn(dn)) for dn in dns]
        self._q: queue.SimpleQueue[tuple[int, Any]] = queue.SimpleQueue()
        # Wildcard: one get on {vehicle}/*/to_cn with every DN's frame in a
        # bundle; a reply says whose it is by its key. An error reply has no
        # key: it names its DN ("dnX: reason"), and counts as that DN's only
        # if it comes from the zenoh session that answers on dnX's key (the
        # ACL lets only dnX reply there); any other is foreign. A peer whose
        # queryable matches the wildcard cannot pin errors on a DN.
        self._all = keys.sync_all
        self._bundle = BundleEncoder()
        self._index = {k: i for i, k in enumerate(self._keys)}
        self._names = {dn.encode(): i for i, dn in enumerate(self.dns)}
        self._zids: list[Any] = [None] * len(self.dns)  # zenoh.ZenohId per DN, once it answered
        # Issued vs finalised queries (zenoh calls `drop` once per query when
        # it is done): lets start-up wait until no warm-up reply can still come.
        self._issued = 0
        self._finalised = 0
        self._idle = threading.Event()
        self._idle.set()
        self._build_callbacks()
        self._consolidation = zenoh.ConsolidationMode.NONE
        self.duration_ns = 0
        """How long the last :meth:`sync` took."""

    def _build_callbacks(self) -> None:
        # Flight queries have no drop callback: zenoh finalises every query
        # (one more message per DN and loop), and a Python callback there
        # would take the GIL on zenoh's thread for nothing. Warm-up queries
        # count their finalisations so start-up can wait them out.
        handoffs = [self._make_handoff(i) for i in range(len(self.dns))]
        self._callbacks = [zenoh.handlers.Callback(h, indirect=False) for h in handoffs]
        self._counted = [
            zenoh.handlers.Callback(h, self._on_finalised, indirect=False) for h in handoffs
        ]
        self._any = zenoh.handlers.Callback(self._handoff_any, indirect=False)
        self._any_counted = zenoh.handlers.Callback(
            self._handoff_any, self._on_finalised, indirect=False
        )

    def _on_finalised(self) -> None:
        self._finalised += 1  # zenoh's thread is the only writer
        if self._finalised == self._issued:
            self._idle.set()

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

        trace = self._trace
        if trace is None:
            return handoff

        def traced(reply: zenoh.Reply) -> None:
            trace("back", i)
            handoff(reply)

        return traced

    def _handoff_any(self, reply: zenoh.Reply) -> None:
        # zenoh's thread: find whose reply it is, extract the bytes, hand off.
        rid = reply.replier_id
        ok = reply.ok
        if ok is not None:
            key = str(ok.key_expr)
            i = self._index.get(key)
            if i is None:
                self._q.put((_FOREIGN, key))
            else:
                if self._trace is not None:
                    self._trace("back", i)
                if rid is not None:
                    self._zids[i] = rid.zid  # who answers for DN i (a restart changes it)
                self._q.put((i, ok.payload.to_bytes()))
            return
        err = reply.err
        if err is None:
            return
        reason = err.payload.to_bytes()
        if reason == b"Timeout":
            return  # zenoh's own, a period after a miss already counted
        i = self._names.get(reason.split(b":", 1)[0])
        if i is not None and rid is not None and rid.zid == self._zids[i]:
            self._q.put((i, None))
        else:
            self._q.put((_FOREIGN, reason[:64].decode(errors="replace")))

    def sync(
        self, frames: Sequence[bytearray], logic: ControlLogic, *, warmup: bool = False
    ) -> bool:
        """Send each DN its frame and hand replies to ``logic.reply`` until
        none is pending or the deadline passed. Returns whether the step
        overran: with every reply in, any lateness; while waiting for a
        missing DN, waking more than half a deadline late (the thread was
        not scheduled). ``warmup``: a start-up sync, whose queries
        :meth:`quiesce` waits for."""
        start = self._mono()
        deadline = start + self.timeout_ns
        n = len(self.dns)
        callbacks = self._callbacks
        trace = self._trace
        if warmup:
            callbacks = self._counted
            self._idle.clear()
            self._issued += 1 if self.wildcard else n
        if self.wildcard:
            if trace is not None:
                for i in range(n):
                    trace("issued", i)
            self.session.get(
                self._all,
                self._any_counted if warmup else self._any,
                payload=self._bundle.pack(frames),
                target=_ALL,
                consolidation=self._consolidation,
                timeout=self._query_timeout,
                congestion_control=_DROP,
            )
        else:
            for i in range(n):
                # DROP: on a link that stopped draining (a cut cable) a
                # BLOCKing get would freeze the CN's loop for seconds; a
                # dropped query is a missed sync, counted like any other
                # (tests/faults, cable cut).
                if trace is not None:
                    trace("issued", i)
                self.session.get(
                    self._keys[i],
                    callbacks[i],
                    payload=frames[i],
                    consolidation=self._consolidation,
                    timeout=self._query_timeout,
                    congestion_control=_DROP,
                )
        # The taps after the queries: tools may wait, the DNs may not.
        taps = self._taps
        for i in range(n):
            taps[i].put(frames[i])
        q = self._q
        reply = logic.reply
        while logic.pending:
            left = deadline - self._mono()
            if left <= 0:
                break
            try:
                i, payload = q.get(timeout=left / 1e9)
            except queue.Empty:
                break
            if i == _FOREIGN:
                logic.foreign_reply(payload)
            else:
                if trace is not None:
                    trace("taken", i)
                reply(i, payload)
        end = self._mono()
        self.duration_ns = end - start
        return end > deadline + (self.timeout_ns // 2 if logic.pending else 0)

    def quiesce(self, logic: ControlLogic, timeout_s: float) -> bool:
        """Wait until every warm-up query issued so far is finalised, then hand any
        reply still queued to ``logic.reply``. Returns False on timeout. Not
        for the loop: start-up uses it so warm-up replies never land in
        flight counters."""
        ok = self._idle.wait(timeout_s)
        q = self._q
        while not q.empty():
            i, payload = q.get_nowait()
            if i == _FOREIGN:
                logic.foreign_reply(payload)
            else:
                logic.reply(i, payload)
        return ok

    def close(self) -> None:
        for t in self._taps:
            t.undeclare()


class DeviceSync:
    """The DN end: the CN's query is the loop trigger.

    :meth:`wait` blocks until a query arrives (or the timeout passes),
    answers it at once with :meth:`DeviceLogic.trigger`'s reply (an error
    reply for a malformed one) and returns whether it started a loop
    (``logic.triggered``). If queries piled up while this node was not
    scheduled, every one but the newest is answered with ``may_run=False``:
    like the CN's scheduler, a stalled DN skips missed loops and never runs
    a burst of old ones. ``trace``: a :data:`SyncTrace` for benchmarks
    (None: no tracing).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dn: str,
        now_ns: Callable[[], int],
        *,
        trace: SyncTrace | None = None,
    ) -> None:
        self.dn = dn
        self._now = now_ns
        self._trace = trace
        self._key = keys.dn_to_cn(dn)
        self._err_prefix = f"{dn}: ".encode()
        self._q: queue.SimpleQueue[zenoh.Query] = queue.SimpleQueue()
        self._tap = TapPublisher(session, self._key)
        handoff: Callable[[zenoh.Query], None] = self._q.put
        if trace is not None:
            q = self._q

            def handoff(query: zenoh.Query) -> None:
                trace("arrive", 0)
                q.put(query)

        self.queryable = session.declare_queryable(
            self._key, zenoh.handlers.Callback(handoff, indirect=False)
        )

    def wait(self, logic: DeviceLogic, timeout_s: float) -> bool:
        """Serve queries until one starts a loop (True) or ``timeout_s`` passes."""
        q = self._q
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                query = q.get(timeout=left)
            except queue.Empty:
                return False
            while not q.empty():  # a backlog: answer the older query, keep the newest
                self._serve(query, logic, may_run=False)
                query = q.get_nowait()
            self._serve(query, logic, may_run=True)
            if logic.triggered:
                return True

    def _serve(self, query: zenoh.Query, logic: DeviceLogic, *, may_run: bool) -> None:
        trace = self._trace
        if trace is not None:
            trace("serve", 0)
        with query:
            payload = query.payload
            data = payload.to_bytes() if payload is not None else b""
            reply = logic.trigger(data, self._now(), may_run=may_run)
            if reply is None:
                # "dnX: reason": a wildcard query's error replies carry no key.
                query.reply_err(self._err_prefix + logic.reject_reason.encode())
            else:
                query.reply(self._key, reply)
        if trace is not None:
            trace("replied", logic.last_loop)
        if reply is not None:
            self._tap.put(reply)

    def close(self) -> None:
        self.queryable.undeclare()
        self._tap.undeclare()
