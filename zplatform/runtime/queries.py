"""Every zenoh query zplatform sends goes through :func:`ask`.

A query is a door a hostile peer can stand behind: asked zenoh's default
way it is held open by a silent peer, captured by an impostor (a queryable
declared ``complete`` takes a ``BEST_MATCHING`` query) or made to block.
:func:`ask` closes those doors in one place: target ALL (the caller takes
only answers that check: tag, nonce, replier), no consolidation, a finite
timeout, congestion control DROP, and a callback that hands each reply off
on zenoh's thread into a bounded :class:`~zplatform.control.handoff.Mailbox`.

Contract: :func:`ask` returns at once and never blocks; the asking thread
waits on its mailbox with its own deadline. A query a live peer's queryable
leaves unanswered loop after loop (zenoh lost the route, eclipse-zenoh/zenoh#2517)
is noticed by :class:`Unanswered` and recovered by declaring the querier
again (:func:`declare_querier`). Why each option: docs/architecture.md#zenoh.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import zenoh

from ..errors import TransportError

__all__ = [
    "CONGESTION",
    "CONSOLIDATION",
    "TARGET",
    "UNANSWERED_LOOPS",
    "QueryFault",
    "ReplyCap",
    "Unanswered",
    "ask",
    "declare_querier",
    "replies",
    "set_fault",
    "unanswered_loops",
]

TARGET = zenoh.QueryTarget.ALL
"""Every queryable on the key is asked (module doc: never ``BEST_MATCHING``)."""
CONSOLIDATION = zenoh.ConsolidationMode.NONE
CONGESTION = zenoh.CongestionControl.DROP


UNANSWERED_LOOPS = 10
"""The most loops in a row a live peer may leave its key's queries without
a single reply before the asker declares its querier on the key again
(:class:`Unanswered`); a control node recovers sooner, by its device nodes'
watchdog (:func:`unanswered_loops`)."""


def unanswered_loops(watchdog_loops: int) -> int:
    """Loops a control node's sync waits for a live device node's reply
    before declaring its querier again: a third of the device nodes'
    watchdog (``faults.dn_watchdog_loops``; 3 of 10), at least one, at most
    :data:`UNANSWERED_LOOPS`. A lost route (zenoh#2517: a peer's session
    closing, such as a flood's attacker leaving) must be recovered, and the
    next trigger arrive, well before the watchdog safes the node: at 10
    loops, the watchdog's own length, the recovery came after dn1 had safed
    ("no valid trigger for 104 ms", issue 25's pad flood run)."""
    return max(1, min(UNANSWERED_LOOPS, watchdog_loops // 3))


class QueryFault(Protocol):
    """A fault for tests (:func:`set_fault`): zenoh losing the route of
    some keys' queries (eclipse-zenoh/zenoh#2517) until a querier on the key
    is declared again."""

    def lost(self, key_expr: str) -> bool:
        """Whether a query on ``key_expr`` is lost now (then never sent)."""
        ...

    def redeclared(self, key_expr: str) -> None:
        """A querier on ``key_expr`` was just declared (:func:`declare_querier`)."""
        ...


_fault: QueryFault | None = None


def set_fault(fault: QueryFault | None) -> None:
    """Install (or, with None, remove) a :class:`QueryFault` in this
    process: tests only. :func:`ask` consults it before each query."""
    global _fault
    _fault = fault


def replies(
    on_reply: Callable[[zenoh.Reply], None], on_done: Callable[[], None] | None = None
) -> zenoh.handlers.Callback[zenoh.Reply]:
    """The handler :func:`ask` takes: ``on_reply`` per reply, ``on_done``
    once when the query is over (every replier done, or the timeout), both
    on zenoh's thread (``indirect=False``). Both must only hand off: no
    blocking, no waiting, into a bounded mailbox. Build it once and reuse it
    where the query repeats (no allocation per query)."""
    return zenoh.handlers.Callback(on_reply, on_done, indirect=False)


def ask(
    session: zenoh.Session,
    key_expr: str,
    handler: zenoh.handlers.Callback[zenoh.Reply],
    *,
    timeout_s: float,
    payload: bytes | bytearray | zenoh.ZBytes | None = None,
    priority: zenoh.Priority | None = None,
    local_only: bool = False,
    instrumentation: zenoh.TimestampInstrumentation | None = None,
) -> None:
    """Send one query on ``key_expr`` (module doc: target ALL, no
    consolidation, ``timeout_s``, DROP) and return at once; never blocks.

    ``handler``: a :func:`replies` callback (anything else is refused).
    ``timeout_s``: finite and positive. ``priority``: zenoh's (its default
    when None). ``local_only``: only this session's own queryables answer
    (``Locality.SESSION_LOCAL``). ``instrumentation``: zenoh's timestamp
    instrumentation (the clock sync). A query DROPped on a congested link
    just gets no reply: the handler's ``drop`` runs at the timeout.

    Raises TransportError for a handler that is not a callback or a timeout
    that is not finite and positive (a programming error); zenoh's ZError
    when the session is closed.
    """
    if not isinstance(handler, zenoh.handlers.Callback):
        raise TransportError(
            f"a query's handler must be a zplatform.runtime.queries.replies callback, not "
            f"{type(handler).__name__}: zenoh's channels block a thread"
        )
    if not (timeout_s > 0 and math.isfinite(timeout_s)):
        raise TransportError(f"a query needs a finite positive timeout, not {timeout_s!r} s")
    fault = _fault
    if fault is not None and fault.lost(key_expr):
        return  # what zenoh#2517 does: the query reaches no queryable
    session.get(
        key_expr,
        handler,
        target=TARGET,
        consolidation=CONSOLIDATION,
        timeout=timeout_s,
        congestion_control=CONGESTION,
        priority=priority,
        payload=payload,
        allowed_destination=zenoh.Locality.SESSION_LOCAL if local_only else None,
        timestamp_instrumentation=instrumentation,
    )


class ReplyCap:
    """At most ``per_replier`` replies from each replier to one query, for an
    ``on_reply`` callback to admit (:meth:`admit`) before it hands a reply
    off: a peer that floods replies to a query fills no more than its own
    share of the asker's mailbox, so the genuine replier's answer still gets
    in, and the asker reads a bounded number of replies per query. Replies
    over the cap are counted (:attr:`dropped`). Repliers are told apart by
    the zenoh session of their replier id (a reply without one counts as
    one anonymous replier). One instance per query; called on zenoh's thread (one query's
    replies arrive on one thread at a time in practice; the counts are
    plain ints, a race costs at most a miscount by one). A reused one
    (a preallocated callback) is :meth:`reset` by the asker before each
    query.
    """

    __slots__ = ("_seen", "dropped", "per_replier")

    def __init__(self, per_replier: int = 1) -> None:
        self.per_replier = per_replier
        self._seen: dict[object, int] = {}
        self.dropped = 0

    def reset(self) -> None:
        """A new query: every replier's share is whole again (any thread)."""
        self._seen = {}  # one reference swap: zenoh's thread sees the old or the new

    def admit(self, reply: zenoh.Reply) -> bool:
        """Whether ``reply`` is within its replier's share (then counted)."""
        rid = getattr(reply, "replier_id", None)
        # By session (its ZenohId): zenoh's EntityGlobalId compares by
        # identity, and one session declaring many queryables gets one share.
        who = getattr(rid, "zid", rid)
        n = self._seen.get(who, 0)
        if n >= self.per_replier:
            self.dropped += 1
            return False
        self._seen[who] = n + 1
        return True


def declare_querier(session: zenoh.Session, key_expr: str, *, timeout_s: float) -> zenoh.Querier:
    """A querier on ``key_expr`` with :func:`ask`'s options (target ALL, no
    consolidation, DROP, ``timeout_s``). Declaring it makes zenoh send its
    peers an interest in the key's queryables (current and future), which
    they answer by declaring them to this session again: how an asker whose
    routes to a live queryable were lost gets them back (undeclare the old
    querier first: zenoh sends the interest for the first querier on a key).
    Blocks briefly on zenoh's state; not for every loop. Raises zenoh's
    ZError when the session is closed."""
    q = session.declare_querier(
        key_expr,
        target=TARGET,
        consolidation=CONSOLIDATION,
        timeout=timeout_s,
        congestion_control=CONGESTION,
    )
    fault = _fault
    if fault is not None:
        fault.redeclared(key_expr)
    return q


class Unanswered:
    """Which targets a live peer leaves without any reply, loop after loop
    (the symptom of eclipse-zenoh/zenoh#2517). Sans-IO: the asker calls
    :meth:`observe` once a loop per target, with whether any reply came for
    it and whether its peer's liveliness token is present; after ``after``
    such loops in a row it returns True once (recover now: declare the
    querier again), counted in :attr:`recoveries`, and counts afresh. A
    target that answers, or whose peer is gone (dead, or cut off: zenoh's
    lease ended its token), resets the count: that is a lost node, not a
    lost route. Allocates nothing per call."""

    __slots__ = ("_quiet", "after", "recoveries")

    def __init__(self, n: int, after: int = UNANSWERED_LOOPS) -> None:
        if after < 1:
            raise TransportError(f"Unanswered needs at least one loop, not {after}")
        self.after = after
        self._quiet = [0] * n
        self.recoveries = [0] * n
        """Recoveries per target so far."""

    def observe(self, i: int, answered: bool, alive: bool) -> bool:
        """One loop of target ``i``; True when it is time to recover it."""
        if answered or not alive:
            self._quiet[i] = 0
            return False
        self._quiet[i] += 1
        if self._quiet[i] < self.after:
            return False
        self._quiet[i] = 0
        self.recoveries[i] += 1
        return True
