"""The Data Synchronization Protocol, both ends (thesis 3.3, 4.3): transport only.

What a frame means, which reply counts, what is late, stale or bad: all of
that is :mod:`zplatform.control.loop`'s, shared with the lockstep runner. These
classes only move the frames: :class:`ControlSync` (the CN: one get per DN on
``{vehicle}/dnX/to_cn``, or one wildcard get with a bundle, at the top of
every loop, replies handed to ``ControlLogic.reply`` until none is pending or
the deadline passed), :class:`DeviceSync` (a DN: waits for the CN's query,
the loop trigger, and answers at once), :class:`ProbeSync` (failover probes).
On one host the same frames may take iceoryx2 shared memory instead
(``transport.intra_host``: :class:`ShmLink`, :meth:`DeviceSync.attach_shm`),
through the same intakes, falling back to zenoh: docs/architecture.md#intra-host.

Contract: zenoh callbacks only check and hand off (:mod:`zplatform.control.intake`:
size, one tag check, a stamp compare, a counter, each constant time); the
loop thread does the work and gets the very bytes the intake checked. Queries
use DROP congestion control. A forged or replayed trigger gets no reply; the
CN takes a reply only from the DN's own zenoh session (or over a link, once
checked). Detail: docs/architecture.md#drivers.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from .. import trace as tracer
from ..config import Mission
from ..control.fencing import ask_nonce, screen_reply
from ..control.handoff import Handoff, Mailbox, Waker
from ..control.intake import CnRefusals, ProbeIntake, ReplyCheck, TriggerIntake
from ..control.loop import ControlLogic, DeviceLogic
from ..core.auth import Channel
from ..core.codec import BundleEncoder
from ..errors import IntraHostError
from .intrahost import (
    IntraHostClient,
    IntraHostServer,
    LinkState,
    intra_host_mode,
    mission_link_sizes,
    remove_stale,
    sync_link_names,
)
from .queries import UNANSWERED_LOOPS, ReplyCap, Unanswered, ask, declare_querier, replies
from .transport import KeySpace, is_matching

__all__ = [
    "PATH_SHM",
    "PATH_ZENOH",
    "REPIN_AFTER",
    "RETRY_LOOPS",
    "ControlSync",
    "DeviceSync",
    "ProbeSync",
    "ShmLink",
    "ShmQuery",
    "SyncTrace",
    "TapPublisher",
    "open_shm_links",
    "open_shm_server",
]

log = logging.getLogger("zplatform.sync")
_DROP = zenoh.CongestionControl.DROP
_NO_PAYLOAD = zenoh.ZBytes(b"")
_ERR_MAX = 512  # longest error reply read: a DN's is "dnX: reason"
REPIN_AFTER = 3
"""Loops in a row a DN's known session must miss before the CN checks
replies from other sessions for one of the DN's (a restarted DN)."""
PATH_ZENOH = 0
"""``dnX_sync_path``: the trigger came over zenoh."""
PATH_SHM = 1
"""``dnX_sync_path``: the trigger came over the intra-host link (iceoryx2)."""
RETRY_LOOPS = 100
"""Loops a link stays on zenoh after it fell back (or found no shared-memory
peer) before the CN tries shared memory again (:class:`ShmLink`)."""
RETRY_MAX_LOOPS = 1000
"""The longest wait between tries: a link whose tries keep failing doubles
its wait each time up to this."""
FALL_AFTER = 2
"""Loops in a row a verified link must lose to a timeout before it falls
back to zenoh. One late reply is the box's scheduling (zenoh's path would
have lost the same loop, and at a higher cost per exchange); two in a row
is a stall. A refused reply, or no server, falls back at once."""

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
    """A put that costs (almost) nothing when nobody subscribes.

    A matching listener keeps ``matching`` current from zenoh's thread; the
    loop reads one bool and skips the put when no subscriber matches. That
    matters for large frames: zenoh-python 1.10 copies a payload into a
    ``ZBytes`` before zenoh looks for a subscriber, so an unguarded put of a
    whole 100,000-element vector costs a 325 KB copy for nobody
    (``python -m bench.frame_trace``, ``tm.put``).

    ``exact``: when the listener says nobody matches, ask zenoh's routing
    state itself (``matching_status``, under a microsecond) before skipping,
    so that no put is lost to the listener's lag after a subscriber came
    (the telemetry a ground logs from loop 1 on). Without it (taps for
    tools) a put in that lag may be skipped.
    """

    def __init__(self, session: zenoh.Session, key: str, *, exact: bool = False) -> None:
        self.pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self.matching = is_matching(self.pub)
        self._exact = exact
        self._listener = self.pub.declare_matching_listener(
            zenoh.handlers.Callback(self._on_matching, indirect=False)
        )

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self.matching = bool(status.matching)

    def wanted(self) -> bool:
        """Whether a put now would go (:meth:`put`'s test; never blocks)."""
        return self.matching or (self._exact and is_matching(self.pub))

    def put(self, payload: bytes | bytearray) -> None:
        """Publish ``payload`` if anyone subscribes (never blocks: DROP)."""
        if self.matching or (self._exact and is_matching(self.pub)):
            self.pub.put(payload)

    def undeclare(self) -> None:
        self._listener.undeclare()
        self.pub.undeclare()


class _ShmWaker(Waker):
    """A mailbox waker that wakes a DN's loop thread blocked in its
    intra-host listener (:meth:`DeviceSync.attach_shm`) instead of a lock."""

    __slots__ = ("_wake",)

    def __init__(self, wake: Callable[[], None]) -> None:
        super().__init__()
        self._wake = wake

    def notify(self) -> None:
        self._wake()


class ShmLink:
    """The CN's end of one DN's intra-host link and its path (module doc of
    :mod:`zplatform.runtime.intrahost`; docs/architecture.md#intra-host).

    The loop thread asks :meth:`try_shm` each loop: whether this loop's
    trigger goes over shared memory. A link starts on *probation*: its first
    exchange (the start-up's warm-up, a loop no DN runs) must bring back a
    reply that passes the sync's intake (tag, run, the loop asked: the loop
    number and stamp are the fresh nonce, the tag proves the DN's key);
    only then is the link *verified* and the flight's loops take it. Any
    miss (no server, no reply in the deadline, a reply the intake refuses)
    puts the link back on zenoh from the next loop (no server: from this
    one, the trigger goes over zenoh at once), except a verified link's
    timeout, which falls back only when :data:`FALL_AFTER` loops in a row
    time out (one late reply is scheduling, not a stalled link). It is
    tried again after :data:`RETRY_LOOPS` loops on probation; a try that
    loses its loop doubles the wait up to :data:`RETRY_MAX_LOOPS`. So a
    failed link costs the loop within its deadline, a stalled one
    :data:`FALL_AFTER` loops, and a try at most one loop per wait. Path
    changes of a verified link are queued in :attr:`changes`
    for the driver to event. Not thread-safe: the loop thread."""

    def __init__(self, dn: str, client: IntraHostClient, *, pinned: bool = False) -> None:
        self.dn = dn
        self.client = client
        self.pinned = pinned
        self.on_shm = False
        """Whether the link is verified and the loops take it."""
        self.tries = 0
        """Exchanges tried on probation (counters never reset)."""
        self.fallbacks = 0
        """Times a verified link fell back to zenoh."""
        self.refused = 0
        """Replies over the link the intake refused."""
        self.changes: list[tuple[str, str]] = []
        """``(path, why)`` of each change not yet evented (the driver drains it)."""
        self._loops = 0
        self._retry_at = 0
        self._failed = 0  # tries in a row that lost their loop
        self._late = 0  # a verified link's loops in a row lost to a timeout
        self._told_no_peer = False

    def try_shm(self) -> bool:
        """Whether this loop's trigger goes over shared memory (once a loop)."""
        self._loops += 1
        if self.on_shm:
            return True
        if self._loops >= self._retry_at:
            self.tries += 1
            return True
        return False

    def no_peer(self, why: str) -> None:
        """The trigger could not go (no server, no sample): zenoh carries it
        this loop; tried again after :data:`RETRY_LOOPS` (nothing was lost)."""
        self._retry_at = self._loops + RETRY_LOOPS
        if self.on_shm:
            self._late = 0
            self._fall(why)
        elif self.pinned and not self._told_no_peer:
            self._told_no_peer = True  # once: a DN on another host stays peerless
            self.changes.append(("zenoh", f"pinned to shm, but {why}"))

    def missed(self, why: str, *, timeout: bool = False) -> None:
        """The trigger went but no valid reply came back: this loop is lost.
        ``timeout``: no reply came in the deadline (a verified link stays
        until :data:`FALL_AFTER` in a row); otherwise the reply was refused."""
        if self.on_shm:
            if timeout:
                self._late += 1
                if self._late < FALL_AFTER:
                    return  # the next loop tries the link again
                why = f"{why}, {self._late} loops in a row"
            self._late = 0
            self._failed = 0
            self._fall(why)
        else:
            self._failed += 1
        # The first try after a fallback comes RETRY_LOOPS later; each
        # further failed one doubles the wait, up to RETRY_MAX_LOOPS.
        wait = RETRY_LOOPS << min(max(self._failed - 1, 0), 10)
        self._retry_at = self._loops + min(wait, max(RETRY_MAX_LOOPS, RETRY_LOOPS))
        # A DN killed with SIGKILL leaves its server in iceoryx2's state: the
        # CN's client would find it connected and wait out each try. Rare
        # (once per failed try), so the directory scan is affordable here.
        try:
            remove_stale()
        except Exception:  # a scan that fails leaves the next try to time out
            pass

    def took(self) -> None:
        """A reply over the link passed the intake."""
        self._late = 0
        if not self.on_shm:
            self.on_shm = True
            self._failed = 0
            self._told_no_peer = False
            self.changes.append(("shm", "its reply passed the intake"))

    def _fall(self, why: str) -> None:
        self.on_shm = False
        self.fallbacks += 1
        self.changes.append(("zenoh", why))

    def close(self) -> None:
        self.client.close()


class ShmQuery:
    """The handle of a trigger that came over shared memory, served like a
    ``zenoh.Query`` by :class:`DeviceSync` (``with``, :meth:`reply`,
    :meth:`reply_err`) on the loop thread that owns ``server``."""

    __slots__ = ("_lent", "server")

    def __init__(self, server: IntraHostServer) -> None:
        self.server = server
        self._lent: memoryview | None = None

    def __enter__(self) -> ShmQuery:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def lend(self, n: int) -> memoryview | None:
        """A writable view of a loaned reply of ``n`` bytes to encode the reply
        in (``DeviceLogic.trigger(into=...)``); None when the client has gone
        or no sample is free (the reply is then copied in, or goes nowhere)."""
        self._lent = view = self.server.reply(n)
        return view

    def reply(self, key: object, payload: bytes | bytearray | memoryview) -> None:
        """Send ``payload`` back over the link (``key`` is zenoh's, unused): the
        loan :meth:`lend` gave as it is, any other frame copied into a loaned
        sample (one copy). A client that has gone gets nothing."""
        lent, self._lent = self._lent, None
        if lent is not None and payload is lent:
            self.server.send()
        else:
            self.server.respond(payload)

    def reply_err(self, payload: bytes) -> None:
        """No error replies over shared memory: the CN counts the loop as
        missed (the DN counted the refusal in ``dnX_bad_frames``); an error
        reply there would carry no tag, so any local process could pin one
        on the DN."""


class ControlSync:
    """The CN end: query every DN with its frame, hand replies to the loop.

    Not thread-safe: call :meth:`sync` from the loop thread only. Blocks for
    at most ``timeout_ns`` (plus scheduling latency). ``checks``: one
    :class:`~zplatform.control.intake.ReplyCheck` per DN, in ``dns`` order (module
    doc: replies from a session not known to be the DN's). ``trace``: a
    :data:`SyncTrace` for benchmarks (None: no tracing). ``shm``: one
    :class:`ShmLink` (or None) per DN, in ``dns`` order: the DNs whose link
    takes a loop get its trigger over shared memory and their replies,
    each through its check, wait up to the same deadline; the others (and a
    link with no peer, in the same loop) go over zenoh, one query each
    (the wildcard only while no link takes shared memory). The sync closes
    the links. ``unanswered``: loops a live DN may go without a reply before
    its querier is declared again (:class:`~.queries.Unanswered`; a control
    node's: :func:`~.queries.unanswered_loops` of its DNs' watchdog).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dns: Sequence[str],
        timeout_ns: int,
        query_timeout_s: float,
        *,
        checks: Sequence[ReplyCheck],
        wildcard: bool = False,
        monotonic: Callable[[], int] = time.monotonic_ns,
        trace: SyncTrace | None = None,
        shm: Sequence[ShmLink | None] = (),
        unanswered: int = UNANSWERED_LOOPS,
    ) -> None:
        if len(checks) != len(dns):
            raise ValueError(f"one reply check per device node: {len(checks)} for {len(dns)}")
        if shm and len(shm) != len(dns):
            raise ValueError(f"one intra-host link (or None) per device node: {len(shm)}")
        # The intra-host links (ShmLink; None: zenoh only), and this loop's
        # use of them: which DNs' triggers went over shared memory.
        self.shm: tuple[ShmLink | None, ...] = tuple(shm) if shm else (None,) * len(dns)
        self._has_shm = any(link is not None for link in self.shm)
        self._sent_shm: list[int] = []
        # :meth:`lend`'s choice per DN for the coming sync (None: not made,
        # the sync asks the link), the loans it handed out (the triggers are
        # encoded straight into them), and the frames the sync sends
        # (the logic's, a lent one swapped for its copy if its send failed).
        self._chosen: list[bool | None] = [None] * len(dns)
        self._lent: list[memoryview | None] = [None] * len(dns)
        self._out: list[bytearray | memoryview] = [bytearray() for _ in dns]
        self.session = session
        self._trace = trace
        self.dns = list(dns)
        self._checks = tuple(checks)
        # Who answers for each DN (zenoh.ZenohId, module doc), and whether
        # replies from other sessions are checked (nobody known yet, or the
        # known one has gone quiet). The loop thread decides `_open`; zenoh's
        # thread pins a session whose reply passed the check.
        self._zids: list[Any] = [None] * len(dns)
        self._open = [True] * len(dns)
        self._quiet = [0] * len(dns)
        self._got = [False] * len(dns)
        self._max_len = tuple(c.max_len for c in checks)
        self._count_lock = threading.Lock()
        self._foreign = 0  # replies from no DN's session (zenoh's thread, under the lock)
        self._oversize = 0  # replies from a DN's session longer than any frame of it
        self.wildcard = wildcard and bool(dns)
        self.timeout_ns = timeout_ns
        self._mono = monotonic
        self._query_timeout = query_timeout_s
        self._keys = [keys.dn_to_cn(dn) for dn in dns]
        self._taps = [TapPublisher(session, keys.cn_to_dn(dn)) for dn in dns]
        self._q: Handoff[tuple[int, bytes | None]] = Handoff()
        # Wildcard: one get on {vehicle}/*/to_cn with every DN's frame in a
        # bundle; a reply says whose it is by its key, and counts only from
        # the session that answers for that DN (as per DN). An error reply
        # has no key: it names its DN ("dnX: reason"), and counts as that
        # DN's only from that session too; any other is foreign. A peer
        # whose queryable matches the wildcard cannot pin errors on a DN.
        self._all = keys.sync_all
        self._bundle = BundleEncoder()
        self._index = {k: i for i, k in enumerate(self._keys)}
        self._names = {dn.encode(): i for i, dn in enumerate(self.dns)}
        # Issued vs finalised queries (zenoh calls `drop` once per query when
        # it is done): lets start-up wait until no warm-up reply can still come.
        self._issued = 0
        self._finalised = 0
        self._idle = threading.Event()
        self._idle.set()
        self._build_callbacks()
        self.duration_ns = 0
        """How long the last :meth:`sync` took."""
        # A live DN whose queries get no reply at all, loop after loop, has
        # lost its route in zenoh (zenoh#2517): its querier is declared again
        # (zplatform.runtime.queries.Unanswered). `_heard` is set on zenoh's thread
        # by any reply for the DN (cleared by each watch), `_alive` by its
        # liveliness token.
        self._heard = [False] * len(dns)
        self._alive = [False] * len(dns)
        self.unanswered = Unanswered(len(dns), unanswered)
        self._recovered: list[int] = []
        self._recovered_n = 0  # recoveries since the last take_refusals (the loop's count)
        self._queriers = [
            declare_querier(session, self._keys[i], timeout_s=query_timeout_s)
            for i in range(len(self._keys))
        ]
        self._all_querier = (
            declare_querier(session, self._all, timeout_s=query_timeout_s)
            if self.wildcard
            else None
        )
        self._alive_index = {keys.alive(dn): i for i, dn in enumerate(self.dns)}
        self._alive_sub = session.liveliness().declare_subscriber(
            keys.all_alive, zenoh.handlers.Callback(self._on_alive, indirect=False), history=True
        )

    def _on_alive(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: one flag per DN, read by the loop.
        i = self._alive_index.get(str(sample.key_expr))
        if i is not None:
            self._alive[i] = sample.kind == zenoh.SampleKind.PUT

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
        take, error = self._take, self._error

        def handoff(reply: zenoh.Reply) -> None:
            # zenoh's thread: who answered, then the bytes (module doc).
            ok = reply.ok
            if ok is not None:
                tr = tracer.tracer
                if tr is None:
                    take(i, reply, ok.payload)
                else:
                    _traced_take(tr, take, i, reply, ok.payload)
                return
            err = reply.err
            if err is not None and error(err.payload) is not None:
                self._dn_error(i, reply)

        trace = self._trace
        if trace is None:
            return handoff

        def traced(reply: zenoh.Reply) -> None:
            trace("back", i)
            handoff(reply)

        return traced

    def _take(self, i: int, reply: zenoh.Reply, payload: zenoh.ZBytes) -> None:
        """Hand DN ``i``'s reply to the loop if it comes from DN ``i``'s
        session, or passes the check while that one is quiet (which then
        makes its session DN ``i``'s); else count it."""
        rid = reply.replier_id
        zid = rid.zid if rid is not None else None
        if zid is not None and zid == self._zids[i]:
            self._heard[i] = True
            if len(payload) > self._max_len[i]:
                with self._count_lock:
                    self._oversize += 1
                return
            self._q.put((i, payload.to_bytes()))
            return
        if not self._open[i] or zid is None:
            with self._count_lock:
                self._foreign += 1
            return
        data = self._checks[i].check(payload, None)  # size, tag, the loop asked: counted if not
        if data is not None:
            self._heard[i] = True
            self._zids[i] = zid
            self._q.put((i, data))

    @staticmethod
    def _error(payload: zenoh.ZBytes) -> bytes | None:
        """An error reply's text, or None for zenoh's own timeout (a period
        after a miss the loop has counted already). Bounded: one longer than
        :data:`_ERR_MAX` bytes is not read (``b"?"``: no DN's)."""
        n = len(payload)
        if n == 7 and payload.to_bytes() == b"Timeout":
            return None
        return payload.to_bytes()[:_ERR_MAX] if n <= _ERR_MAX else b"?"

    def _dn_error(self, i: int, reply: zenoh.Reply) -> None:
        """An error reply for DN ``i``: the DN refusing its trigger when it
        comes from DN ``i``'s session, else foreign."""
        rid = reply.replier_id
        if rid is not None and self._zids[i] is not None and rid.zid == self._zids[i]:
            self._heard[i] = True
            self._q.put((i, None))
        else:
            with self._count_lock:
                self._foreign += 1

    def _handoff_any(self, reply: zenoh.Reply) -> None:
        # zenoh's thread: whose reply it is by its key (or an error's name).
        ok = reply.ok
        if ok is not None:
            i = self._index.get(str(ok.key_expr))
            if i is None:
                with self._count_lock:
                    self._foreign += 1
                return
            if self._trace is not None:
                self._trace("back", i)
            tr = tracer.tracer
            if tr is None:
                self._take(i, reply, ok.payload)
            else:
                _traced_take(tr, self._take, i, reply, ok.payload)
            return
        err = reply.err
        if err is None:
            return
        reason = self._error(err.payload)
        if reason is None:
            return
        j = self._names.get(reason.split(b":", 1)[0])
        if j is not None:
            self._dn_error(j, reply)
        else:
            with self._count_lock:
                self._foreign += 1

    def take_refusals(self, out: CnRefusals) -> None:
        """Write the sync replies refused since the last call into ``out``
        (its ``reply_*`` fields; then zeroed), and the queriers declared again
        since (``query_recovered``: the loop counts them in
        ``cn_query_recoveries``). The loop thread, once a loop."""
        size = bad = stale = unchecked = 0
        for c in self._checks:
            s, b, st = c.take_counts()
            size += s
            bad += b
            stale += st
            unchecked += c.took_unchecked
        with self._count_lock:
            foreign, oversize = self._foreign, self._oversize
            self._foreign = self._oversize = 0
        out.reply_size, out.reply_bad, out.reply_stale = size + oversize, bad, stale
        out.reply_foreign = foreign
        out.reply_unchecked = unchecked
        out.query_recovered, self._recovered_n = self._recovered_n, 0

    def begin(
        self,
        logic: ControlLogic,
        loop: int,
        t_ns: int,
        *,
        final: bool = False,
        standby: bool | None = None,
    ) -> list[bytearray | memoryview]:
        """``logic.begin`` with each trigger that goes over shared memory this
        loop encoded straight into its loaned sample (:meth:`lend`): what the
        driver hands :meth:`sync` next. Blocks never; raises what
        ``logic.begin`` raises."""
        into = self.lend(logic.trigger_lengths)
        return logic.begin(loop, t_ns, final=final, standby=standby, into=into)

    def lend(self, lengths: Sequence[int]) -> list[memoryview | None] | None:
        """Choose each DN's path for the coming :meth:`sync` now
        (:meth:`ShmLink.try_shm`, once a loop) and lend a writable view of a
        loaned shared-memory sample of ``lengths[i]`` bytes (the trigger's
        length, ``ControlLogic.trigger_lengths``) for each DN whose trigger
        goes over its link, for ``ControlLogic.begin(into=...)`` to encode
        and tag the trigger in: the sync then sends the sample as it is, and
        the frame is never copied (docs/architecture.md#intra-host). None in
        place of a view: the DN's frame is the logic's own (zenoh carries it,
        or a tap subscribes to it, which reads it after the send, so it is
        copied into a loan at the send as before). Returns None when no DN
        has a link. Valid for the next :meth:`sync` only; never blocks."""
        if not self._has_shm:
            return None
        lent, chosen, taps = self._lent, self._chosen, self._taps
        for i, link in enumerate(self.shm):
            lent[i] = None
            if link is None:
                continue
            go = chosen[i] = link.try_shm()
            if not go or taps[i].matching:
                continue
            buf = link.client.trigger(lengths[i])
            if buf is None:
                link.no_peer("no sample to lend (the DN holds them all)")
                chosen[i] = False
                continue
            lent[i] = buf
        return lent

    def sync(
        self,
        frames: Sequence[bytearray | memoryview],
        logic: ControlLogic,
        *,
        warmup: bool = False,
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
        got = self._got
        for i, check in enumerate(self._checks):
            check.expect(logic.loop, logic.t_ns)
            got[i] = False
        if self._has_shm:
            out = self._out
            for i in range(n):
                out[i] = frames[i]
            zenoh_too = self._send_shm(out, logic)
            frames = out
        else:
            zenoh_too = n
        if warmup:
            callbacks = self._counted
            issued = (1 if self.wildcard and zenoh_too == n else zenoh_too) if zenoh_too else 0
            if issued:
                self._idle.clear()
                self._issued += issued
        tr = tracer.tracer
        if self.wildcard and zenoh_too == n:
            if trace is not None:
                for i in range(n):
                    trace("issued", i)
            if tr is not None:
                for i in range(n):
                    tr.mark("sync.issued", i, len(frames[i]))
            ask(
                self.session,
                self._all,
                self._any_counted if warmup else self._any,
                payload=self._bundle.pack(frames),  # frames of no loan: none went
                timeout_s=self._query_timeout,
            )
            if tr is not None:
                for i in range(n):
                    tr.mark("sync.sent", i)
        elif zenoh_too:
            sent_shm = self._sent_shm
            for i in range(n):
                if i in sent_shm:
                    continue
                # zplatform.runtime.queries.ask: DROP (on a link that stopped draining,
                # a cut cable, a BLOCKing get would freeze the CN's loop for
                # seconds; a dropped query is a missed sync, counted like any
                # other: tests/faults, cable cut) and target ALL (a peer's
                # "complete" queryable on dnX/to_cn cannot take the trigger).
                if trace is not None:
                    trace("issued", i)
                if tr is not None:
                    tr.mark("sync.issued", i, len(frames[i]))
                frame = frames[i]
                ask(
                    self.session,
                    self._keys[i],
                    callbacks[i],
                    # Only a caller's own view (never a loan: a lent frame
                    # zenoh carries was swapped for the logic's copy) is copied.
                    payload=frame if type(frame) is not memoryview else bytes(frame),
                    timeout_s=self._query_timeout,
                )
                if tr is not None:
                    tr.mark("sync.sent", i)
        # The taps after the queries: tools may wait, the DNs may not. A
        # trigger encoded into its loan has gone with it: nobody subscribed
        # when it was lent (a tap that came since misses this one).
        taps = self._taps
        lent = self._lent
        for i in range(n):
            frame = frames[i]
            if lent[i] is None:
                taps[i].put(frame if type(frame) is not memoryview else bytes(frame))
            else:
                lent[i] = None
        if self._sent_shm:
            self._collect_shm(logic, deadline, trace)
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
            if trace is not None:
                trace("taken", i)
            if tr is not None:
                tr.mark("sync.taken", i)
            if reply(i, payload):
                got[i] = True
        end = self._mono()
        self.duration_ns = end - start
        self._watch(got)
        return end > deadline + (self.timeout_ns // 2 if logic.pending else 0)

    def _send_shm(self, frames: list[bytearray | memoryview], logic: ControlLogic) -> int:
        """Send the triggers of the DNs whose link takes shared memory this
        loop (:meth:`lend`'s choice, else :meth:`ShmLink.try_shm`); returns
        how many DNs zenoh carries. A trigger encoded into its loan
        (:meth:`lend`) goes as it is; any other is copied into a loan (the one
        copy). A link without a peer (or a sample to lend) hands its trigger
        back to zenoh in the same loop, a lent one re-encoded in the logic's
        buffer (``ControlLogic.trigger_frame``, the same bytes): nothing is lost."""
        sent = self._sent_shm
        sent.clear()
        trace = self._trace
        tr = tracer.tracer
        chosen, lent = self._chosen, self._lent
        for i, link in enumerate(self.shm):
            if link is None:
                continue
            go, chosen[i] = chosen[i], None
            if go is None:
                go = link.try_shm()
            if not go:
                continue
            frame = frames[i]
            client = link.client
            buf = lent[i]
            if buf is None:
                buf = client.trigger(len(frame))
                if buf is None:
                    link.no_peer("no sample to lend (the DN holds them all)")
                    continue
                buf[:] = frame  # the one copy of the trigger into shared memory
            elif frame is not buf:
                buf[:] = frame  # a caller that did not encode into the loan
                lent[i] = None  # its frame is its own: the tap may read it
            if trace is not None:
                trace("issued", i)
            if tr is not None:
                tr.mark("sync.issued", i, len(frame))
            if not client.send():
                link.no_peer(
                    "no shared-memory server"
                    if client.state is LinkState.NO_PEER
                    else "the send failed"
                )
                if lent[i] is not None:
                    # The loan went with the send: zenoh needs the frame's bytes.
                    lent[i] = None
                    frames[i] = logic.trigger_frame(i)
                continue
            if tr is not None:
                tr.mark("sync.sent", i)
            sent.append(i)
        return len(self.dns) - len(sent)

    def _collect_shm(self, logic: ControlLogic, deadline: int, trace: SyncTrace | None) -> None:
        """Each reply over shared memory, through DN ``i``'s intake
        (:class:`~zplatform.control.intake.ReplyCheck`: size, tag, the loop
        asked), to ``logic.reply``, waiting at most until ``deadline``."""
        got, checks = self._got, self._checks
        tr = tracer.tracer
        for i in self._sent_shm:
            link = self.shm[i]
            assert link is not None
            client = link.client
            t_end = time.monotonic() + (deadline - self._mono()) / 1e9
            reply = client.collect(t_end)
            if reply is None:
                link.missed("no reply within the deadline", timeout=True)
                continue
            if trace is not None:
                trace("taken", i)
            if tr is not None:  # as zenoh's reply path marks them (bench.frame_trace)
                tr.mark("sync.back", i, len(reply))
                tr.mark("sync.shm", i)
                tr.mark("sync.taken", i)
            # Checked in place (size, tag, the loop asked), no copy; the
            # logic decodes it from shared memory into the Data Vector (the
            # reply's one copy), then the sample goes back.
            data = checks[i].check_view(reply, None)  # refused: counted there
            if data is None:
                client.release()
                link.refused += 1
                link.missed("a reply the intake refused")
                continue
            link.took()
            self._heard[i] = True
            applied = logic.reply(i, data)
            client.release()
            if applied:
                got[i] = True

    def take_path_changes(self, out: list[tuple[str, str, str]]) -> None:
        """Append ``(dn, path, why)`` for each link that changed its path
        since the last call (the loop thread, once a loop; the driver
        events them)."""
        if self._has_shm:
            for link in self.shm:
                if link is not None and link.changes:
                    for path, why in link.changes:
                        out.append((link.dn, path, why))
                    link.changes.clear()

    def paths(self) -> list[str]:
        """Each DN's link's path now: ``shm`` or ``zenoh``."""
        return ["shm" if link is not None and link.on_shm else "zenoh" for link in self.shm]

    def _watch(self, got: list[bool]) -> None:
        """After a sync: a DN whose known session answered keeps it alone;
        one quiet for :data:`REPIN_AFTER` loops lets others be checked. A
        live DN that sent no reply at all for
        :data:`~zplatform.runtime.queries.UNANSWERED_LOOPS` loops gets its querier
        declared again (:meth:`take_recoveries`)."""
        heard, alive, watch = self._heard, self._alive, self.unanswered
        for i, ok in enumerate(got):
            if ok:
                self._quiet[i] = 0
                self._open[i] = self._zids[i] is None
            else:
                self._quiet[i] += 1
                if self._quiet[i] >= REPIN_AFTER:
                    self._open[i] = True
            # Any reply since the last watch counts, a late one too (it came
            # after the deadline): only silence is a lost route.
            answered, heard[i] = ok or heard[i], False
            if watch.observe(i, answered, alive[i]):
                self._recover(i)

    def _recover(self, i: int) -> None:
        """Declare DN ``i``'s querier again (and the wildcard's): zenoh asks
        the peers for the key's queryables anew (zplatform.runtime.queries). The loop
        thread; rare (at most once per UNANSWERED_LOOPS loops and DN)."""
        self._queriers[i].undeclare()
        self._queriers[i] = declare_querier(
            self.session, self._keys[i], timeout_s=self._query_timeout
        )
        if self._all_querier is not None:
            self._all_querier.undeclare()
            self._all_querier = declare_querier(
                self.session, self._all, timeout_s=self._query_timeout
            )
        self._recovered.append(i)
        self._recovered_n += 1

    def take_recoveries(self, out: list[tuple[str, int]]) -> None:
        """Append ``(dn, recoveries so far)`` for each querier declared again
        since the last call to ``out`` (the loop thread, once a loop; the
        driver events them)."""
        if self._recovered:
            for i in self._recovered:
                out.append((self.dns[i], self.unanswered.recoveries[i]))
            self._recovered.clear()

    def quiesce(self, logic: ControlLogic, timeout_s: float) -> bool:
        """Wait until every warm-up query issued so far is finalised, then hand any
        reply still queued to ``logic.reply``. Returns False on timeout. Not
        for the loop: start-up uses it so warm-up replies never land in
        flight counters."""
        ok = self._idle.wait(timeout_s)
        q = self._q
        while not q.empty():
            i, payload = q.get_nowait()
            logic.reply(i, payload)
        return ok

    def close(self) -> None:
        for link in self.shm:
            if link is not None:
                link.close()
        for t in self._taps:
            t.undeclare()
        for q in self._queriers:
            q.undeclare()
        if self._all_querier is not None:
            self._all_querier.undeclare()
        self._alive_sub.undeclare()


class DeviceSync:
    """The DN end: the CN's query is the loop trigger.

    ``intake``: the node's :class:`~zplatform.control.intake.TriggerIntake` (module
    doc): zenoh's callback admits a query only if its trigger verifies and
    is newer than every one before; any other is dropped unanswered and
    counted. :meth:`wait` blocks until an admitted query is there (or the
    timeout passes), answers it at once with :meth:`DeviceLogic.trigger`'s
    reply (an error reply for one the logic refuses) and returns whether it
    started a loop (``logic.triggered``). If admitted queries piled up while
    this node was not scheduled (at most
    :data:`~zplatform.control.intake.BACKLOG`; older ones are let go unanswered),
    every one but the newest is answered with ``may_run=False``: like the
    CN's scheduler, a stalled DN skips missed loops and never runs a burst
    of old ones. Each :meth:`wait` also hands the intake's refusals to the
    logic (:meth:`DeviceLogic.refused`). ``trace``: a :data:`SyncTrace` for
    benchmarks (None: no tracing). ``shm``: the intra-host link's server
    (:meth:`attach_shm`; closed by :meth:`close`); ``path``: the Data
    Vector handle of ``dnX_sync_path``, set before each trigger is served.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dn: str,
        now_ns: Callable[[], int],
        *,
        intake: TriggerIntake[zenoh.Query],
        probes: ProbeIntake[zenoh.Query] | None = None,
        trace: SyncTrace | None = None,
        shm: IntraHostServer | None = None,
        path: Any = None,
    ) -> None:
        self.dn = dn
        self._now = now_ns
        self._trace = trace
        self._key = keys.dn_to_cn(dn)
        self._err_prefix = f"{dn}: ".encode()
        self.intake = intake
        self._authentic = intake.authenticates
        box = intake.box
        assert box is not None
        self._box = box
        self._tap = TapPublisher(session, self._key)
        self.reply: bytearray | None = None
        """The last reply frame sent, the logic's own buffer: valid until the
        next query is served. None: an error reply, or a reply encoded straight
        into its shared-memory sample (gone with it; see :attr:`keep_reply`)."""
        self.keep_reply = False
        """Whether :attr:`reply` must hold every reply (a flight recorder keeps
        them): replies over shared memory are then framed in the logic's
        buffer and copied into their sample, as a tap's are."""
        admit = intake.admit

        def handoff(query: zenoh.Query) -> None:
            # zenoh's thread: the intake's checks; a refused query is
            # released here, unanswered (zenoh finalises it at once).
            tr = tracer.tracer
            if tr is not None:
                tr.mark("dn.arrive")
            p = query.payload
            if admit(p if p is not None else _NO_PAYLOAD, query):
                if tr is not None:
                    tr.mark("dn.admitted")
                if trace is not None:
                    trace("arrive", 0)

        self.queryable = session.declare_queryable(
            self._key, zenoh.handlers.Callback(handoff, indirect=False)
        )
        # A redundant mission's probes (zplatform.control.fencing): their own intake
        # (size, tag, freshness, the asker's rate bound: zplatform.control.intake.ProbeIntake),
        # waking the same wait as the triggers.
        self.probes = probes
        self._probe_q: zenoh.Queryable[Any] | None = None
        self._ready: Callable[[], object] = box.__len__
        if probes is not None:
            pbox = probes.box
            assert pbox is not None
            self._pbox = pbox
            self._probe_key = keys.probe(dn)
            padmit = probes.admit

            def on_probe(query: zenoh.Query) -> None:
                # zenoh's thread: the intake's checks; a refused question is
                # released here, unanswered.
                p = query.payload
                padmit(p if p is not None else _NO_PAYLOAD, query)

            self.on_probe: Callable[[zenoh.Query], None] = on_probe
            """The probe queryable's callback (what zenoh's thread runs per question)."""
            self._probe_q = session.declare_queryable(
                self._probe_key, zenoh.handlers.Callback(on_probe, indirect=False)
            )
            self._ready = lambda: len(box) or len(pbox)
        # ``path``: the DataVector handle of ``dnX_sync_path``, set to the
        # path each served trigger came by (it goes back in the reply).
        self._path = path
        self.shm: IntraHostServer | None = None
        if shm is not None:
            self.attach_shm(shm)

    def attach_shm(self, server: IntraHostServer) -> None:
        """Take triggers over the intra-host link ``server`` too (module doc
        of :mod:`zplatform.runtime.intrahost`): :meth:`wait` then blocks in
        its event listener, which zenoh's admitted triggers and probe
        questions wake as well (their mailboxes' waker notifies it), so a
        trigger over shared memory costs the loop thread one wake-up. Its
        triggers pass the same intake (:meth:`~zplatform.control.intake.Intake.check`:
        size, tag, run, newer than every trigger by either path) and are
        answered over it (:class:`ShmQuery`). Call before the loop runs."""
        wake = server.waker()
        waker = _ShmWaker(wake)
        self._box.waker = waker
        if self.probes is not None:
            self._pbox.waker = waker
        self._shm_query = ShmQuery(server)
        self.shm = server

    def detach_shm(self) -> IntraHostServer | None:
        """Stop taking triggers over the intra-host link (the loop thread,
        between two :meth:`wait`); returns its server, not closed."""
        server, self.shm = self.shm, None
        waker = Waker()
        self._box.waker = waker
        if self.probes is not None:
            self._pbox.waker = waker
        return server

    def _wait_shm(self, logic: DeviceLogic, server: IntraHostServer, deadline: float) -> bool:
        """:meth:`wait` with the intra-host link: the newest zenoh trigger
        or, when none is queued, the link's, then block in its listener."""
        box = self._box
        # The handle is zenoh's Query for zenoh's triggers; none here.
        check: Callable[[memoryview, Any], memoryview | None] = self.intake.check_view
        item: tuple[zenoh.Query | ShmQuery, bytes | memoryview] | None
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if self.probes is not None:
                while (probe := self._pbox.pop()) is not None:
                    self._answer(probe, logic)
            item = box.pop()
            if item is None:
                view = server.poll()
                if view is None:
                    server.block(left)
                    continue
                # Checked in place, no copy; the server holds the sample
                # until its next wait, so the logic's run() copies the
                # trigger's data from it into the Data Vector (its one copy).
                data = check(view, None)  # refused: counted, unanswered
                if data is None:
                    continue
                if self._trace is not None:
                    self._trace("arrive", 0)
                item = (self._shm_query, data)
            while (newer := box.pop()) is not None:  # a backlog: answer, keep the newest
                self._serve(item, logic, may_run=False)
                item = newer
            self._serve(item, logic, may_run=True)
            if logic.triggered:
                return True

    def wait(self, logic: DeviceLogic, timeout_s: float) -> bool:
        """Serve queries until one starts a loop (True) or ``timeout_s`` passes.
        Probe questions that arrive meanwhile are answered first."""
        box = self._box
        deadline = time.monotonic() + timeout_s
        try:
            if self.shm is not None:
                return self._wait_shm(logic, self.shm, deadline)
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                if self.probes is not None:
                    if not box.waker.wait(self._ready, left):
                        return False
                    while (probe := self._pbox.pop()) is not None:
                        self._answer(probe, logic)
                    item = box.pop()
                    if item is None:
                        continue
                else:
                    item = box.get(left)
                    if item is None:
                        return False
                while (newer := box.pop()) is not None:  # a backlog: answer, keep the newest
                    self._serve(item, logic, may_run=False)
                    item = newer
                self._serve(item, logic, may_run=True)
                if logic.triggered:
                    return True
        finally:
            size, bad, stale = self.intake.take_counts()
            now = self._now()
            logic.refused(size, bad, stale, now, unchecked=self.intake.took_unchecked)
            if self.probes is not None:
                size, bad, stale = self.probes.take_counts()
                logic.probes_refused(
                    size, bad, stale, self.probes.excess, now, unchecked=self.probes.took_unchecked
                )

    def _answer(self, item: tuple[zenoh.Query, bytes], logic: DeviceLogic) -> None:
        """Answer one probe question (:meth:`DeviceLogic.probe`)."""
        query, data = item
        with query:
            reply = logic.probe(data, self._now())
            if reply is None:
                query.reply_err(self._err_prefix + logic.reject_reason.encode())
            else:
                query.reply(self._probe_key, reply)

    def _serve(
        self,
        item: tuple[zenoh.Query | ShmQuery, bytes | memoryview],
        logic: DeviceLogic,
        *,
        may_run: bool,
    ) -> None:
        trace = self._trace
        if trace is not None:
            trace("serve", 0)
        tr = tracer.tracer
        if tr is not None:
            tr.mark("dn.serve")
        query, data = item
        path = self._path
        if path is not None:
            path.set(PATH_SHM if type(query) is ShmQuery else PATH_ZENOH)
        # Over shared memory the reply is framed and tagged straight in its
        # loaned sample (no copy), unless someone reads it after it went: a
        # tap subscriber, or the flight recorder (keep_reply).
        into = None
        if type(query) is ShmQuery and not self.keep_reply and not self._tap.matching:
            into = query.lend(logic.reply_length)
        with query:
            # The intake checked this payload's tag already (module doc).
            reply = logic.trigger(
                data, self._now(), may_run=may_run, authentic=self._authentic, into=into
            )
            self.reply = reply if isinstance(reply, bytearray) else None
            if reply is None:
                # "dnX: reason": a wildcard query's error replies carry no key.
                query.reply_err(self._err_prefix + logic.reject_reason.encode())
            else:
                query.reply(self._key, reply)
        if trace is not None:
            trace("replied", logic.last_loop)
        if tr is not None:
            tr.mark("dn.replied", logic.last_loop)
        if reply is not None and into is None:
            self._tap.put(reply if isinstance(reply, bytearray) else bytes(reply))

    def close(self) -> None:
        self.queryable.undeclare()
        server = self.detach_shm()
        if server is not None:
            server.close()
        if self._probe_q is not None:
            self._probe_q.undeclare()
        self._tap.undeclare()


def _traced_take(
    tr: tracer.Tracer,
    take: Callable[[int, zenoh.Reply, zenoh.ZBytes], None],
    i: int,
    reply: zenoh.Reply,
    payload: zenoh.ZBytes,
) -> None:
    """``take`` with the trace points of a reply (:mod:`zplatform.trace`)."""
    tr.mark("sync.back", i, len(payload))
    if payload.as_shm() is not None:
        tr.mark("sync.shm", i)
    take(i, reply, payload)
    tr.mark("sync.queued", i)


def _ignore(reply: zenoh.Reply) -> None:
    pass


class ProbeSync:
    """A control node's probe rounds (:mod:`zplatform.control.fencing`): one question
    per device node on ``{vehicle}/dnX/probe``, the replies handed to the
    caller's ``answer`` on the calling thread until every device node
    answered or ``timeout_ns`` passed. Every query goes through
    :func:`zplatform.runtime.queries.ask` (every queryable on the key, DROP, a
    timeout: an impostor declaring a "complete" probe queryable cannot take
    the question, a congested link cannot block the asker). Replies wait in
    a bounded mailbox (a peer answering many times cannot grow memory); the
    caller checks each one (tag, nonce). With ``screens`` (each device node's
    ``probe_dnX_to_cn`` channel, this object's own), zenoh's callback
    screens each reply first (:func:`~zplatform.control.fencing.screen_reply`:
    header tag, node, the question's nonce): junk and replies to other
    questions, from however many peers, never push a device node's reply out
    of the mailbox (issue 25; counted in :attr:`screened`). Not thread-safe:
    one thread asks."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        dns: Sequence[str],
        timeout_ns: int,
        screens: Sequence[Channel | None] | None = None,
    ) -> None:
        self.session = session
        self._keys = [keys.probe(dn) for dn in dns]
        self.timeout_ns = timeout_ns
        self._box: Mailbox[tuple[int, bytes]] = Mailbox(4 * max(len(dns), 1))
        box = self._box
        self._nonces = [b""] * len(dns)  # each question's, for the screen
        self._screen_lock = threading.Lock()  # the screens' channels: zenoh's threads
        self.screened = 0
        """Replies the screen refused (zenoh's threads write it)."""

        # One reply per replier per question is read (a DN answers once): a
        # peer flooding answers cannot push the DN's out of the mailbox.
        self._caps = [ReplyCap(1) for _ in dns]

        def make(i: int) -> Callable[[zenoh.Reply], None]:
            cap = self._caps[i]
            screen = screens[i] if screens is not None else None

            def on_reply(reply: zenoh.Reply) -> None:  # zenoh's thread: hand off
                ok = reply.ok
                if ok is None or len(ok.payload) > _ERR_MAX:
                    return
                data = ok.payload.to_bytes()
                if screen is not None:
                    with self._screen_lock:
                        if not screen_reply(screen, data, i, self._nonces[i]):
                            self.screened += 1
                            return
                if cap.admit(reply):
                    box.put((i, data))

            return on_reply

        self._callbacks = [replies(make(i)) for i in range(len(dns))]
        self._drop: zenoh.handlers.Callback[zenoh.Reply] = replies(_ignore)

    def round(self, asks: Sequence[bytes], answer: Callable[[int, bytes], bool]) -> int:
        """Send ``asks[i]`` to device node ``i``; hand each reply to
        ``answer(i, payload)`` until every node's was taken (``answer``
        returned True) or the deadline passed; returns how many were taken."""
        box = self._box
        box.drain([])  # replies to an earlier round: late, not this one's
        timeout_s = max(self.timeout_ns / 1e9, 0.005)
        for i, question in enumerate(asks):
            self._caps[i].reset()
            self._nonces[i] = ask_nonce(question)  # one reference swap: read by the screen
            # Every queryable on dnX/probe (a peer that declares a "complete"
            # one cannot take the question from the DN); `answer` takes only
            # the DN's (tag, nonce).
            ask(
                self.session,
                self._keys[i],
                self._callbacks[i],
                payload=question,
                timeout_s=timeout_s,
            )
        n = len(asks)
        taken = [False] * n
        deadline = time.monotonic_ns() + self.timeout_ns
        got = 0
        while got < n:
            left = deadline - time.monotonic_ns()
            if left <= 0:
                break
            item = box.get(left / 1e9)
            if item is None:
                break
            i, payload = item
            if not taken[i] and answer(i, payload):
                taken[i] = True
                got += 1
        return got

    def send(self, frames: Sequence[bytes | None]) -> None:
        """Send each question that is not None (a RELEASE), answers unread."""
        for i, f in enumerate(frames):
            if f is not None:
                ask(self.session, self._keys[i], self._drop, payload=f, timeout_s=0.05)


def open_shm_links(mission: Mission, cn: str = "cn") -> list[ShmLink | None]:
    """The CN's intra-host links, one per DN (None: that DN's sync stays on
    zenoh), or ``[]`` when ``transport.intra_host`` resolves to zenoh
    (:func:`~zplatform.runtime.intrahost.intra_host_mode`). Each starts on
    probation (:class:`ShmLink`). A link that cannot open (shared memory too
    small, iceoryx2 refused) is logged and left to zenoh under ``auto``;
    under ``shm`` the IntraHostError is raised (the operator asked for it)."""
    if intra_host_mode(mission) == "zenoh":
        return []
    links: list[ShmLink | None] = []
    try:
        for dn in mission.device_nodes:
            mode = intra_host_mode(mission, dn)
            if mode == "zenoh":
                links.append(None)
                continue
            try:
                client = IntraHostClient(
                    sync_link_names(mission, dn, cn),
                    *mission_link_sizes(mission, dn),
                    deadline_s=mission.sync_timeout_ns / 1e9,
                )
            except IntraHostError as exc:
                if mode == "shm":
                    raise
                log.warning("%s's sync stays on zenoh: %s", dn, exc)
                links.append(None)
                continue
            links.append(ShmLink(dn, client, pinned=mode == "shm"))
    except BaseException:
        for link in links:
            if link is not None:
                link.close()
        raise
    return links if any(link is not None for link in links) else []


def open_shm_server(mission: Mission, dn: str, cn: str = "cn") -> IntraHostServer | None:
    """A DN's end of its intra-host link (None: zenoh only; as
    :func:`open_shm_links`, an IntraHostError only under ``shm``)."""
    mode = intra_host_mode(mission, dn)
    if mode == "zenoh":
        return None
    try:
        return IntraHostServer(sync_link_names(mission, dn, cn), *mission_link_sizes(mission, dn))
    except IntraHostError as exc:
        if mode == "shm":
            raise
        log.warning("%s's sync stays on zenoh: %s", dn, exc)
        return None
