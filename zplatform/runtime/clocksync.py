"""Clock synchronisation between each DN and the CN (thesis 4.9), NTP-style.

The CN serves ``{vehicle}/cn/clock`` (:class:`ClockServer` around the
sans-IO :class:`ClockResponder`; ``t2`` read in zenoh's callback, the reply
sent from the server thread). A DN's sans-IO end is :class:`ClockLink`: per
exchange a tagged query with a fresh nonce, asked of every queryable and
DROPped rather than blocked; the first reply whose tag checks and whose
nonce is the exchange's is taken, any other refused and counted, and an
exchange without one is a counted timeout. It never waits past its timeout.

The exchange is also how a node learns the control node's *run*
(:class:`zplatform.core.auth.Run`) from a frame that cannot be a replay: the
reply names the run, is tagged under its key and echoes the asker's nonce.
A query names the asker's run (the server refuses another run's, unanswered)
or none (a *hello*, answered statelessly like a SYN cookie); the ground and
tools send a *run hello* (:class:`RunAsker`, downlink key). The fastest
``keep_fraction`` of many exchanges give the offset (:func:`estimator_for`:
``node_clock`` or zenoh's timestamps, the default). Formulas and measured
accuracy: docs/architecture.md#the-clock-exchange; wire: codecs/FORMAT.md §6.3.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import secrets
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import zenoh

from ..config import ClockConfig, Mission
from ..control.handoff import Mailbox
from ..core.auth import (
    NO_RUN,
    TAG_LEN,
    AuthError,
    Channel,
    KeySet,
    Run,
    RunError,
    channel,
    new_run_epoch,
)
from ..core.health import Heartbeat
from ..errors import ClockSyncError
from . import queries
from .queries import ReplyCap, ask
from .transport import KeySpace

__all__ = [
    "ESTIMATORS",
    "HELLO_KEPT",
    "ClockEstimate",
    "ClockEstimator",
    "ClockLink",
    "ClockResponder",
    "ClockServer",
    "Estimator",
    "ExchangeTimeout",
    "RunAsker",
    "ZenohTimestampsError",
    "estimate_offset",
    "estimate_offset_zenoh",
    "estimator_for",
    "learn_run",
]

log = logging.getLogger("zplatform.clocksync")

# codecs/FORMAT.md §6.3: magic, version, the DN's index, the nonce, then times.
_QUERY = struct.Struct("<2sBB16sq")
PEER_INDEX = 0xFE
"""The index a control node asks the commander's clock with (the standby)."""
_REPLY = struct.Struct("<2sBB16sqqq")
_Q_MAGIC, _R_MAGIC, _VERSION = b"ZQ", b"ZR", 1
NONCE_LEN = 16
# codecs/FORMAT.md §6.3: the run hello (magic, version, nonce) and its answer
# (magic, version, the nonce echoed, the run).
RUN_HELLO = struct.Struct("<2sB16s")
RUN_ANSWER = struct.Struct("<2sB16sQ")
_H_MAGIC, _A_MAGIC = b"ZH", b"ZA"
QUERY_SPAN_NS = 86_400 * 10**9
"""How far apart a clock query's stamp and the CN's clock, or a reply's
times and its query's, may be: a day. A host clock that is merely not
synchronised (a zone set wrong is hours off) is nearer; a stamp beyond is a
key holder's or a broken clock's, refused (:class:`ClockResponder`,
:class:`ClockLink`)."""
RELEARN_S = 1.0
"""At most one hello exchange this often on a genuine trigger of another run
(the control node may have started a new one, zplatform.core.auth.Run): a
device node's re-sync thread, live, and the lockstep runner, in virtual time
(a replay of an earlier run's triggers costs one exchange series this often,
never more)."""
RESYNC_EXCHANGES = 50
"""Exchanges of one in-flight measurement (a device node's re-sync, or a
re-learning of the run on a cue, at most once a :data:`RELEARN_S`)."""
ASK_SLACK = 8
"""Queries a clock asker may send beyond its series at once (the run
learned with a few hellos, :func:`learn_run`)."""
FRESH_NS = 2_000_000_000
"""How much older than its asker's newest a clock query may look
(:class:`ClockResponder`: its stamp against the CN's clock, compared with
the asker's newest answered): more than an exchange's timeout (1 s), so a
genuine query late in transit is still fresh; a replay older than this is
refused, whatever the nonces remembered."""
DRIFT_PPM = 1000
"""How fast an asker's clock may drift from the CN's (parts per million),
which its freshness reference follows: far beyond any quartz's."""


DRIFT_EXCHANGES_MIN = 50
"""The fewest exchanges of a device node's second start-up series, the one
that measures its corrected clock's residual (:func:`drift_exchanges`)."""


def drift_exchanges(clock: ClockConfig) -> int:
    """Exchanges of a device node's residual series at start-up (after the
    offset's ``clock.exchanges``): a quarter of those, at least
    :data:`DRIFT_EXCHANGES_MIN`."""
    return max(DRIFT_EXCHANGES_MIN, clock.exchanges // 4)


def ask_bound(clock: ClockConfig) -> tuple[int, int]:
    """``(burst, every_ns)``: the per-asker rate bound of a clock server
    (:class:`ClockResponder`): two start-ups (a node restarted right after
    it started), each its offset's series (``clock.exchanges``) and its
    residual's (:func:`drift_exchanges`), and an in-flight series
    (:data:`RESYNC_EXCHANGES`) at once, then one query every ``every_ns``:
    an in-flight series every re-sync period (``clock.resync_s``) or, on
    cues, every :data:`RELEARN_S`, whichever is sooner (a start-up series
    is back in 4 s by default). A node restarted a third time within that
    finds its start-up series cut short (``ClockSyncError``) and starts
    when it is back."""
    period_s = min(clock.resync_s, RELEARN_S) if clock.resync_s > 0 else RELEARN_S
    burst = 2 * (clock.exchanges + drift_exchanges(clock)) + RESYNC_EXCHANGES + ASK_SLACK
    return burst, round(period_s * 1e9 / RESYNC_EXCHANGES)


def answered_kept(clock: ClockConfig) -> int:
    """Nonces of the queries it answered a :class:`ClockResponder` keeps per
    asker: every query the rate bound (:func:`ask_bound`) lets it answer in
    twice :data:`FRESH_NS`, so a replay young enough to be fresh is always
    one of them (refused as answered before), and an older one is stale."""
    burst, every_ns = ask_bound(clock)
    return burst + 2 * FRESH_NS // every_ns + 1


@dataclass(frozen=True, slots=True)
class ClockEstimate:
    """Result of :func:`estimate_offset` (ns; ``offset_ns`` = CN - DN).

    ``estimator``: which estimator produced it (``node_clock`` or ``zenoh_ts``).
    """

    offset_ns: int
    delay_ns: int
    exchanges: int
    kept: int
    spread_ns: int
    estimator: str = "node_clock"


class ZenohTimestampsError(ClockSyncError):
    """The CN answered, but zenoh's timestamps cannot give the offset.

    Raised by :func:`estimate_offset_zenoh` where :func:`estimate_offset`
    would have succeeded: the replies lack zenoh's four timestamps (the CN's
    zenoh does not stamp), or zenoh's clock and the node clock disagree over
    the exchanges (a host clock stepped). ``node_estimate``: what
    :func:`estimate_offset` gives from the same exchanges' node-clock times
    (None when they are too few), which :class:`ClockEstimator` returns
    instead of asking a second series.
    """

    def __init__(self, message: str, node_estimate: ClockEstimate | None = None) -> None:
        super().__init__(message)
        self.node_estimate = node_estimate


class _Payload(Protocol):
    """What :meth:`ClockLink.screen` and :meth:`RunAsker.screen` read:
    ``zenoh.ZBytes`` (its length is free, ``to_bytes`` copies)."""

    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


class ClockLink:
    """A DN's end of the clock exchange (module doc), sans-IO.

    :meth:`query` frames one query with a fresh nonce; :meth:`check` takes
    one reply and returns the CN's times if it is the answer to that query.
    ``keys``: the DN's keys (None: the mission does not authenticate, and
    the nonce alone binds a reply to its query). Counts what it refuses:
    :attr:`refused_bad` (a bad tag, or not a reply: a peer without the key)
    and :attr:`refused_other` (authentic, but for another exchange: a
    replay, or a reply late beyond its exchange), and the exchanges that
    got no valid answer in time, :attr:`timeouts` (a silent, slow or
    unreachable clock; a flood from peers without the key). Not thread-safe: one
    estimating thread at a time; the counters may be read from any thread.
    """

    def __init__(
        self, mission: Mission, dn: str, keys: KeySet | None, run: Run | None = None
    ) -> None:
        self.dn = dn
        # run: where the run learned goes (the node's, which its channels are
        # bound to); _asking: the run the next query names (module doc).
        self.run = run if run is not None else Run()
        self._asking = Run()
        self._answered = False
        if dn in mission.control_nodes:
            # A control node that does not command (the standby) sets its clock
            # by the commander's, over the link between the two.
            self.index = PEER_INDEX
            self._seal = channel(keys, "clock_peer_to_cn", self._asking)
            self._open = channel(keys, "clock_cn_to_peer", self.run)
        else:
            self.index = mission.device_nodes.index(dn)
            self._seal = channel(keys, f"clock_{dn}_to_cn", self._asking)
            self._open = channel(keys, f"clock_cn_to_{dn}", self.run)
        # What check() refused (the estimating thread's) and what screen()
        # refused (zenoh's threads'): one writer each, summed when read.
        self._bad = self._other = 0
        self._screened_bad = self._screened_other = 0
        self.timeouts = 0
        # screen()'s: zenoh's threads, a channel and a lock of their own.
        self._screen = self._open.twin() if self._open is not None else None
        self._screen_lock = threading.Lock()
        self._sent = (b"", 0)  # the last query's nonce and stamp

    def query(self, t1: int) -> tuple[bytes, bytes]:
        """``(payload, nonce)`` of a new query stamped ``t1`` (this node's clock),
        naming the run this node knows if the last query was answered, else
        none (a hello, module doc)."""
        nonce = secrets.token_bytes(NONCE_LEN)
        self._sent = (nonce, t1)
        self._asking.set(self.run.epoch if self._answered else NO_RUN)
        self._answered = False
        body = _QUERY.pack(_Q_MAGIC, _VERSION, self.index, nonce, t1)
        seal = self._seal
        return (bytes(seal.seal(body)) if seal is not None else body), nonce

    def screen(self, payload: _Payload, nonce: bytes) -> bytes | None:
        """The bytes of ``payload`` (a reply's, ``zenoh.ZBytes``) when it may
        be the CN's reply to the query with ``nonce``: its length (unread),
        its header tag (any run) and the nonce echoed, all within the header
        tag's bytes (no MAC over the body); else None, counted in
        :attr:`refused_bad` or :attr:`refused_other` (and :attr:`screened`).
        For zenoh's reply callback, before the hand-off
        (thread-safe: a channel and a lock of its own; never raises):
        junk never takes a place a genuine reply needs. :meth:`check`
        decides."""
        ch = self._screen
        n = len(payload)
        with self._screen_lock:
            if n != _REPLY.size + (TAG_LEN if ch is not None else 0):
                self._screened_bad += 1
                return None
            raw = payload.to_bytes()
            if ch is None:
                return raw  # without tags, junk cannot be told: check() judges
            try:
                body = ch.open_header(raw, any_run=True)
            except AuthError:
                self._screened_bad += 1
                return None
            if body[4 : 4 + NONCE_LEN] != nonce:
                self._screened_other += 1  # authentic: another exchange's (a replay)
                return None
        return raw

    def check(self, raw: bytes, nonce: bytes) -> tuple[int, int, int] | None:
        """``(t1, t2, t3)`` of the CN's reply to the query with ``nonce``;
        None (counted) for anything else. The times are checked too: ``t1``
        must be the query's own (for the last query made), the CN's ``t2``
        no later than its ``t3``, both within :data:`QUERY_SPAN_NS` of
        ``t1``; an authentic reply with other times (a key holder's, a CN
        clock gone wrong) is refused in :attr:`refused_other`. The reply
        may name any run (its tag is checked under that run's key): taken, it
        is this node's run from then on (:attr:`run`, module doc)."""
        ch = self._open
        try:
            body = ch.open_header(raw, any_run=True) if ch is not None else memoryview(raw)
            if len(body) != _REPLY.size:
                raise AuthError(f"{len(body)} bytes, not a clock reply")
            # The nonce is within the header tag's bytes (codecs/FORMAT.md
            # §6.1): a reply to another query (a replay) is refused before
            # the body's MAC.
            if body[4 : 4 + NONCE_LEN] != nonce:
                self._other += 1
                return None
            if ch is not None:
                ch.check_body(raw)
        except AuthError:
            self._bad += 1
            return None
        magic, version, index, echo, t1, t2, t3 = _REPLY.unpack(body)
        if magic != _R_MAGIC or version != _VERSION or index != self.index:
            self._bad += 1
            return None
        if echo != nonce or not _believable(t1, t2, t3, self._sent, nonce):
            self._other += 1
            return None
        if self._open is not None and echo == self._sent[0]:
            # Authentic and the answer to this node's latest, fresh, query:
            # the run it names is the control node's now.
            self.run.set(Channel.run_of(raw))
            self._answered = True
        return t1, t2, t3

    @property
    def refused_bad(self) -> int:
        """Replies refused for a bad tag or not a reply (module doc)."""
        return self._bad + self._screened_bad

    @property
    def refused_other(self) -> int:
        """Authentic replies refused as another exchange's (module doc)."""
        return self._other + self._screened_other

    @property
    def screened(self) -> int:
        """Of those, the replies :meth:`screen` refused in zenoh's callback."""
        return self._screened_bad + self._screened_other

    @property
    def refused(self) -> int:
        return self.refused_bad + self.refused_other

    def forget(self) -> None:
        """Make the next query a hello (module doc): the run may have changed."""
        self._answered = False


def _reference(ref: tuple[int, int] | None, t2: int) -> int | None:
    """A freshness reference ``(skew, at)`` as it stands at ``t2``: lowered
    by the drift :data:`DRIFT_PPM` allows since ``at`` (None: none yet)."""
    if ref is None:
        return None
    skew, at = ref
    return skew - max(t2 - at, 0) * DRIFT_PPM // 1_000_000


def _believable(t1: int, t2: int, t3: int, sent: tuple[bytes, int], nonce: bytes) -> bool:
    """Whether a reply's times can be the CN's answer to the query sent."""
    if sent[0] == nonce and t1 != sent[1]:
        return False
    return t2 <= t3 and abs(t2 - t1) <= QUERY_SPAN_NS and t3 - t2 <= QUERY_SPAN_NS


HELLO_BURST = 16
"""Run hellos (:class:`RunAsker`) a clock server answers at once; then one
every :data:`HELLO_EVERY_NS`. The ground and tools ask once at start, then
at most once a :data:`RELEARN_S`. The bound counts only authentic hellos
not answered before (:class:`ClockResponder`: after the header tag and the
nonces of :data:`HELLO_KEPT`), so junk never spends it."""
HELLO_EVERY_NS = 50_000_000
_HELLO_TAU_NS = (HELLO_BURST - 1) * HELLO_EVERY_NS
HELLO_KEPT = 65_536
"""Nonces of the authentic run hellos a clock server saw last (answered,
or refused by the rate bound) that it keeps, a preallocated ring (512 KiB
of references; about 5 MB with its set once full): a hello carrying one of
them (a replay) is refused, counted stale, and spends nothing of the bound
(:class:`ClockResponder`). Cycling replays past it takes more distinct
captured hellos than that, i.e. as many of the askers' (re-)learnings,
each at most one a :data:`RELEARN_S`: 18 hours of provoking one asker
(with 256, four minutes)."""


_Checked = tuple[int, bytes, int, int]
"""A clock query :meth:`ClockResponder.check` passed: ``(index, nonce, t1, t2)``."""


class ClockResponder:
    """The CN's end of the clock exchange (module doc), sans-IO: answers a
    DN's query if its tag checks with that DN's link key, it is stamped
    within :data:`QUERY_SPAN_NS` of the CN's clock, and, with keys, per
    asker (a DN, or the standby), it is

    * fresh: its stamp ``t1`` less the CN's receive time ``t2`` (the
      asker's clock against the CN's) is at most :data:`FRESH_NS` below
      that of the asker's newest answered query (a reference that follows
      a drift of :data:`DRIFT_PPM`), or, for an asker whose clock is
      corrected (within ``clock.offset_bound_ms`` of the CN's), below that
      of its newest such query: a replay ages with the CN's clock, a
      genuine query does not; the one step of a DN's clock, its
      correction at start-up, brings it in bounds (counted in :attr:`stale`);
    * none of the last :func:`answered_kept` nonces it carried (a replay
      young enough to look fresh; also :attr:`stale`);
    * within its rate bound (:func:`ask_bound`: two start-up series and
      an in-flight one at once, then one series a re-sync period; after
      the checks above, so replays use none of it): the excess is refused
      (:attr:`ask_excess`).

    Refused queries go unanswered and are counted in :attr:`refused` too.
    Limit: an asker whose clock runs ahead of the CN's by more than the
    bound before its correction has, for as long as it ran ahead, one
    window (the bound and :data:`FRESH_NS` wide) in which a replay of its
    start-up series looks corrected: the nonces and the rate bound then
    hold it. And an asker restarted in the same run with its clock behind
    the CN's by more than the bound and :data:`FRESH_NS` (uncorrected, its
    queries look older than its newest) is refused until its reference
    drifts down to it: such a node restarts once the control node's run
    does, or with its host clock set. ``keys``: the CN's keys
    (None: the mission does not authenticate, and only the stamp is
    checked). ``run``: the control node's run (its ``cn_epoch``; None: a
    new run of its own): a query must name it or none (a hello, module doc);
    one naming another run is refused before its MAC. The reply names it.
    :meth:`answer` is :meth:`check` (the query: what zenoh's callback does,
    :class:`ClockServer`) then :meth:`reply` (the stamped reply: the
    server's thread). Not thread-safe: one thread (or one lock) checks, one
    replies; the two share no channel."""

    def __init__(
        self,
        mission: Mission,
        keys: KeySet | None,
        run: Run | None = None,
        *,
        mono_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        dns = mission.device_nodes
        self._mono = mono_ns
        self._hello_tat = -(1 << 63)
        self.hello_excess = 0
        """Authentic run hellos, not seen before, refused by their rate bound
        (also in :attr:`refused`)."""
        # The nonces of the last HELLO_KEPT authentic hellos, oldest first
        # from _hello_at, and the same as a set (b"": no nonce yet).
        self._hello_ring = [b""] * HELLO_KEPT
        self._hello_at = 0
        self._hello_seen: set[bytes] = set()
        self.run = run if run is not None else Run(new_run_epoch(time.time_ns()))
        r = self.run
        # Queries are opened unbound (a hello names no run; the run is checked
        # first, in answer), replies sealed in the run.
        self._open: list[Channel | None] = [channel(keys, f"clock_{dn}_to_cn") for dn in dns]
        self._seal: list[Channel | None] = [channel(keys, f"clock_cn_to_{dn}", r) for dn in dns]
        # The other control node of a redundant mission asks as PEER_INDEX.
        self._peer = (
            (channel(keys, "clock_peer_to_cn"), channel(keys, "clock_cn_to_peer", r))
            if mission.standby is not None
            else None
        )
        self._auth = keys is not None
        # The run hello (RunAsker): any holder of the downlink key asks, in no run.
        self._hello_open = channel(keys, "run_hello")
        self._hello_seal = channel(keys, "run_answer", r)
        self.hellos = 0
        """Run hellos answered."""
        # Per asker (a DN's index, or the peer last): the nonces answered,
        # oldest first, and the same as a set.
        askers = len(dns) + 1
        self._answered: list[deque[bytes]] = [deque() for _ in range(askers)]
        self._seen: list[set[bytes]] = [set() for _ in range(askers)]
        self._kept = answered_kept(mission.clock)
        burst, self._every = ask_bound(mission.clock)
        self._tau = (burst - 1) * self._every
        self._in_sync = round(mission.clock.offset_bound_ms * 1e6)
        # Per asker: the rate bound's theoretical arrival time (on the CN's
        # clock, t2: virtual in lockstep), and the freshness references, the
        # newest skew (t1 - t2) answered and when (t2), of any query and of
        # one in bounds (a corrected clock); None: none answered yet.
        self._tat = [-(1 << 63)] * askers
        self._ref: list[tuple[int, int] | None] = [None] * askers
        self._ref_sync: list[tuple[int, int] | None] = [None] * askers
        self.stale = 0
        """Authentic queries refused as replays: not fresh, or answered before;
        and run hellos seen before (also in :attr:`refused`)."""
        self.ask_excess = 0
        """Authentic fresh queries refused beyond their asker's rate bound
        (also in :attr:`refused`)."""
        self.refused = 0
        """Queries refused (malformed, an unknown DN, a bad tag, stamped out
        of bounds, replayed)."""
        self.reason = ""
        """Why the last query was refused."""

    @property
    def sizes(self) -> frozenset[int]:
        """The lengths a query or a run hello can have: any other is refused unread."""
        tag = TAG_LEN if self._auth else 0
        return frozenset({_QUERY.size + tag, RUN_HELLO.size + tag})

    def refuse(self, reason: str) -> None:
        """Count a query refused before :meth:`check` (its size, unread)."""
        self.refused += 1
        self.reason = reason

    def answer(self, raw: bytes, t2: int, t3: int) -> bytes | None:
        """The reply to query ``raw`` received at ``t2``, sent at ``t3``; None
        (counted, :attr:`reason` set) for a query to refuse: :meth:`check`
        then :meth:`reply`."""
        ok = self.check(raw, t2)
        if ok is None or isinstance(ok, bytes):
            return ok
        return self.reply(ok, t3)

    def check(self, raw: bytes, t2: int) -> bytes | _Checked | None:
        """Check query ``raw`` received at ``t2`` (class doc): None (counted,
        :attr:`reason` set) to refuse it; a run hello's whole answer
        (bytes); or ``(index, nonce, t1, t2)`` of a clock query to answer with
        :meth:`reply`. Costs a length, a few compares, a header tag and,
        for a fresh query, one MAC over its 28 bytes; allocates the copy's view and the nonce. Not
        thread-safe with itself (the caller's lock); :meth:`reply` may run
        on another thread meanwhile (they share no channel)."""
        want = _QUERY.size + (TAG_LEN if self._auth else 0)
        if len(raw) == RUN_HELLO.size + (TAG_LEN if self._auth else 0) and raw[:2] == _H_MAGIC:
            return self._answer_hello(raw)
        try:
            if len(raw) != want or raw[:3] != _Q_MAGIC + bytes((_VERSION,)):
                raise AuthError(f"{len(raw)} bytes: not a clock query of version {_VERSION}")
            index = raw[3]
            if index == PEER_INDEX and self._peer is not None:
                ch = self._peer[0]
            elif index < len(self._open):
                ch = self._open[index]
            else:
                raise AuthError(f"no device node number {index}")
            if ch is not None:
                asked = Channel.run_of(raw)
                if asked not in (NO_RUN, self.run.epoch):
                    raise RunError(
                        f"a query of run {asked}, not of this run ({self.run.epoch}): "
                        "an earlier run's, replayed"
                    )
            # A query is shorter than the header tag's bytes (codecs/FORMAT.md
            # §6.1): its header tag makes it all authentic, and a replay is
            # refused below before the body's MAC.
            body = ch.open_header(raw) if ch is not None else memoryview(raw)
        except AuthError as exc:
            self.refused += 1
            self.reason = str(exc)
            return None
        _, _, _, nonce, t1 = _QUERY.unpack(body)
        if abs(t1 - t2) > QUERY_SPAN_NS:
            self.refused += 1
            self.reason = f"a query stamped {(t1 - t2) / 1e9:+.0f} s from this clock"
            return None
        if self._auth:
            asker = -1 if index == PEER_INDEX else index
            skew = t1 - t2
            ref = _reference(self._ref[asker], t2)
            sync = _reference(self._ref_sync[asker], t2)
            in_sync = abs(skew) <= self._in_sync
            if not (
                ref is None
                or skew >= ref - FRESH_NS
                or (in_sync and (sync is None or skew >= sync - FRESH_NS))
            ):
                self.refused += 1
                self.stale += 1
                self.reason = (
                    f"a query {(ref - skew) / 1e9:.3f} s older than its asker's newest (a replay)"
                )
                return None
            seen = self._seen[asker]
            if nonce in seen:
                self.refused += 1
                self.stale += 1
                self.reason = "a query answered before (a replay)"
                return None
            if ch is not None:
                try:
                    ch.check_body(raw)
                except AuthError as exc:
                    self.refused += 1
                    self.reason = str(exc)
                    return None
            tat = max(self._tat[asker], t2)
            if tat - t2 > self._tau:
                self.refused += 1
                self.ask_excess += 1
                self.reason = "clock queries beyond their asker's rate bound"
                return None
            self._tat[asker] = tat + self._every
            self._ref[asker] = (skew if ref is None else max(skew, ref), t2)
            if in_sync:
                self._ref_sync[asker] = (skew if sync is None else max(skew, sync), t2)
            answered = self._answered[asker]
            if len(answered) >= self._kept:
                seen.discard(answered.popleft())
            answered.append(nonce)
            seen.add(nonce)
        return index, nonce, t1, t2

    def reply(self, checked: _Checked, t3: int) -> bytes:
        """The reply, sent at ``t3``, to a query :meth:`check` passed
        (``checked``: what it returned), sealed in this run."""
        index, nonce, t1, t2 = checked
        seal = (
            self._peer[1] if index == PEER_INDEX and self._peer is not None else self._seal[index]
        )
        reply = _REPLY.pack(_R_MAGIC, _VERSION, index, nonce, t1, t2, t3)
        return bytes(seal.seal(reply)) if seal is not None else reply

    def _answer_hello(self, raw: bytes) -> bytes | None:
        """The answer to a run hello (:class:`RunAsker`): this run, the nonce
        echoed; None (counted, :attr:`reason` set) to refuse it. In order:
        the header tag and the version (junk: refused, spending nothing);
        with keys, its nonce among the last :data:`HELLO_KEPT` seen (a
        replay: refused, counted :attr:`stale`), then the MAC, then the
        nonce is kept (answered or not: a ground's next hello has a new
        one); then the rate bound (:data:`HELLO_BURST`, GCRA, one
        integer), which only those reach (:attr:`hello_excess`).

        What a replayer of captured hellos can still do: holding N of them,
        N at most :data:`HELLO_KEPT`, have each answered once, until
        :data:`HELLO_KEPT` others were seen since (it pushes none out with
        its own replays): one pass, which keeps the bound spent for
        ``(N - HELLO_BURST) * HELLO_EVERY_NS`` at most (50 ms a captured
        hello), then a ground's hello (one a :data:`RELEARN_S`) finds the
        bound free. Holding more, it can cycle them and keep the bound
        spent for as long as it replays: that takes more than
        :data:`HELLO_KEPT` distinct hellos, i.e. a watcher of the link for
        as many of a ground's (re-)learnings, at most one a
        :data:`RELEARN_S` (18 hours of provoking them with another run's
        telemetry), and it delays only the learning of the run, never the
        loop. A new control node run (a new responder) starts with an
        empty ring."""
        ch = self._hello_open
        try:
            # A hello is shorter than the header tag's bytes (codecs/FORMAT.md
            # §6.1): its header tag makes it all authentic, the nonce too.
            body = ch.open_header(raw, any_run=True) if ch is not None else memoryview(raw)
            if body[2] != _VERSION:
                raise AuthError(f"a run hello of version {body[2]}, not {_VERSION}")
        except AuthError as exc:
            self.refused += 1
            self.reason = str(exc)
            return None
        _, _, nonce = RUN_HELLO.unpack(body)
        if ch is not None:  # without tags a replay cannot be told from a hello
            seen = self._hello_seen
            if nonce in seen:
                self.refused += 1
                self.stale += 1
                self.reason = "a run hello seen before (a replay)"
                return None
            try:
                ch.check_body(raw)
            except AuthError as exc:
                self.refused += 1
                self.reason = str(exc)
                return None
            ring, at = self._hello_ring, self._hello_at
            seen.discard(ring[at])
            ring[at] = nonce
            seen.add(nonce)
            self._hello_at = (at + 1) % HELLO_KEPT
        now = self._mono()
        tat = max(self._hello_tat, now)
        if tat - now > _HELLO_TAU_NS:
            self.hello_excess += 1
            self.refused += 1
            self.reason = "run hellos beyond their rate bound"
            return None
        self._hello_tat = tat + HELLO_EVERY_NS
        self.hellos += 1
        answer = RUN_ANSWER.pack(_A_MAGIC, _VERSION, nonce, self.run.epoch)
        seal = self._hello_seal
        return bytes(seal.seal(answer)) if seal is not None else answer


class RunAsker:
    """The ground's end of the run hello (module doc), sans-IO: how a ground
    or a tool learns the commander's run from an answer that cannot be a
    replay. :meth:`hello` frames a hello with a fresh nonce (the one
    awaited from then on); :meth:`check` takes one answer and, when it is
    the answer to that hello (tag under the ``run_answer`` key of the run
    it names, the nonce echoed, the run in the body the tag's), binds
    :attr:`run` to it and returns True; anything else is refused and
    counted: :attr:`refused_bad` (a bad tag, not an answer) or
    :attr:`refused_other` (authentic, but not the answer awaited: a replay,
    or late). One answer per hello. ``keys``: the asker's keys (the
    downlink's; None: the mission does not authenticate, and the nonce
    alone binds an answer). Not thread-safe: one thread asks and checks;
    the counters may be read from any thread."""

    def __init__(self, keys: KeySet | None, run: Run | None = None) -> None:
        self.run = run if run is not None else Run()
        self._seal = channel(keys, "run_hello")
        self._open = channel(keys, "run_answer", self.run)
        # screen()'s: zenoh's threads, a channel and a lock of their own.
        self._screen = self._open.twin() if self._open is not None else None
        self._screen_lock = threading.Lock()
        self.screened = 0
        """Answers :meth:`screen` refused (zenoh's threads write it)."""
        self._nonce = b""
        self.refused_bad = 0
        self.refused_other = 0
        self.learned = 0
        """Answers taken (the first, then one per re-learning)."""

    def hello(self) -> bytes:
        """A new hello's payload (a fresh nonce; an earlier hello's answer is
        refused from now on)."""
        self._nonce = secrets.token_bytes(NONCE_LEN)
        body = RUN_HELLO.pack(_H_MAGIC, _VERSION, self._nonce)
        seal = self._seal
        return bytes(seal.seal(body)) if seal is not None else body

    def screen(self, payload: _Payload) -> bytes | None:
        """The bytes of ``payload`` (a reply's, ``zenoh.ZBytes``) when it may
        be the answer to the latest hello: its length (unread), then its
        header tag (any run) and the hello's nonce echoed, both within the
        header tag's bytes (no MAC over the body); else None. For zenoh's
        reply callback, before the hand-off (thread-safe; never raises,
        never blocks beyond a short lock): junk and answers to other hellos
        are refused there (counted in :attr:`screened`), so a flood of them
        never displaces the answer in a bounded mailbox. :meth:`check`
        decides."""
        ch = self._screen
        n = len(payload)
        with self._screen_lock:
            if n != RUN_ANSWER.size + (TAG_LEN if ch is not None else 0):
                self.screened += 1
                return None
            raw = payload.to_bytes()  # 59 bytes at most
            if ch is None:
                return raw  # without tags, junk cannot be told: check() judges
            nonce = self._nonce  # one attribute read: hello() may set the next
            try:
                body = ch.open_header(raw, any_run=True)
            except AuthError:
                self.screened += 1
                return None
            if not nonce or body[3 : 3 + NONCE_LEN] != nonce:
                self.screened += 1
                return None
        return raw

    def check(self, raw: bytes | bytearray | memoryview) -> bool:
        """Whether ``raw`` is the answer to the latest hello (class doc);
        binds :attr:`run` to its run when it is. Never raises for ``raw``."""
        ch = self._open
        try:
            body = ch.open_header(raw, any_run=True) if ch is not None else memoryview(raw)
            if len(body) != RUN_ANSWER.size:
                raise AuthError(f"{len(body)} bytes, not a run answer")
            # An answer is shorter than the header tag's bytes: its nonce is
            # authentic already, and an answer to another hello (a replay)
            # is refused before the body's MAC.
            if not self._nonce or body[3 : 3 + NONCE_LEN] != self._nonce:
                self.refused_other += 1
                return False
            if ch is not None:
                ch.check_body(raw)
        except AuthError:
            self.refused_bad += 1
            return False
        magic, version, echo, run = RUN_ANSWER.unpack(body)
        if magic != _A_MAGIC or version != _VERSION:
            self.refused_bad += 1
            return False
        tagged = Channel.run_of(raw) if ch is not None else run
        if not self._nonce or echo != self._nonce or run != tagged or run == NO_RUN:
            self.refused_other += 1
            return False
        self._nonce = b""  # one answer per hello
        self.run.set(run)
        self.learned += 1
        return True


CLOCK_BACKLOG = 64
"""Clock queries the CN's clock server holds while its thread is busy: the
askers (every DN, the standby) ask one at a time, so a full backlog is a
flood; a query past it is dropped unanswered and counted."""


LOG_PERIOD_S = 1.0
"""At most one log line of refused clock queries this often (:class:`ClockServer`)."""


class ClockServer:
    """The CN's clock queryable. Runs its own reply thread; ``close()`` stops it.

    Each query is checked by a :class:`ClockResponder` (``mission``,
    ``auth``: the CN's keys, ``run``: its run) *in zenoh's callback*: its
    size unread, then (one copy, of 52 bytes at most) magic, run, tag and
    nonce, under a short lock. A refused one is dropped unanswered (zenoh
    finalises it at once: no error reply, no hand-off), counted
    (:attr:`refused`), and logged by the reply thread at most once a
    second (:data:`LOG_PERIOD_S`) with the count and the last reason. So a
    keyless flood costs the commander zenoh's own dispatch and a few
    microseconds per query, and never wakes a Python thread of its own,
    which under the GIL would hold the control loop (a busy thread keeps
    the GIL for up to the switch interval each time the loop wants it
    back). Only checked queries wait for the thread, at most
    :data:`CLOCK_BACKLOG`: one past that is dropped unanswered (counted in
    :attr:`dropped` and in :attr:`refused`). The thread stamps ``t3``,
    replies, and checks in through :attr:`heartbeat` (``clock``,
    :mod:`zplatform.core.health`): idle while it waits, beating while it
    serves."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        now_ns: Callable[[], int],
        mission: Mission,
        auth: KeySet | None,
        *,
        run: Run | None = None,
    ) -> None:
        self._now = now_ns
        self.heartbeat = Heartbeat("clock")
        self._q: queue.Queue[tuple[zenoh.Query, bytes | _Checked] | None] = queue.Queue(
            CLOCK_BACKLOG
        )
        self.dropped = 0
        """Checked queries dropped unanswered by a full backlog (zenoh's callback writes)."""
        self._key = keys.clock
        self._responder = ClockResponder(mission, auth, run)
        self._sizes = self._responder.sizes
        self._lock = threading.Lock()  # the responder's checks: zenoh's threads
        self.served = 0
        self.queryable = session.declare_queryable(
            self._key, zenoh.handlers.Callback(self.on_query, indirect=False)
        )
        self._thread = threading.Thread(target=self._serve, name="clock-server", daemon=True)
        self._thread.start()

    @property
    def refused(self) -> int:
        return self._responder.refused + self.dropped

    def on_query(self, query: zenoh.Query) -> None:
        # zenoh's thread (class doc): check, then hand a checked query to the
        # thread or drop it. Never blocks beyond the lock; never raises for
        # what arrives.
        t2 = self._now()
        p = query.payload
        n = len(p) if p is not None else 0
        responder = self._responder
        with self._lock:
            if n not in self._sizes:  # unread
                responder.refuse(f"{n} bytes: not a clock query of version {_VERSION}")
                ok = None
            else:
                ok = responder.check(p.to_bytes() if p is not None else b"", t2)
        if ok is None:  # a flood: the query goes, unanswered (zenoh finalises it)
            query.drop()
            return
        try:
            self._q.put_nowait((query, ok))
        except queue.Full:
            with self._lock:
                self.dropped += 1
            query.drop()

    def _serve(self) -> None:
        hb = self.heartbeat
        responder = self._responder
        logged = 0
        next_log = 0.0
        while True:
            hb.idle()
            try:
                item = self._q.get(timeout=LOG_PERIOD_S)
                idle = False
            except queue.Empty:
                item, idle = None, True
            now = time.monotonic()
            if self.refused != logged and now >= next_log:
                # At most one line a LOG_PERIOD_S, however many were refused.
                log.warning(
                    "clock queries refused: %d so far (%d since the last report); the last: %s",
                    self.refused,
                    self.refused - logged,
                    responder.reason or "a full backlog",
                )
                logged = self.refused
                next_log = now + LOG_PERIOD_S
            if idle:
                continue
            if item is None:
                return
            hb.beat()
            query, checked = item
            with query:
                # A run hello's answer is whole (nothing to stamp).
                reply = (
                    checked if isinstance(checked, bytes) else responder.reply(checked, self._now())
                )
                # DROP: a reply takes its query's QoS (zenoh 1.x ignores a
                # reply's own), and the DNs ask DROP (zplatform.runtime.queries), so a
                # DN's stalled link never holds the clock server.
                query.reply(self._key, reply)
            self.served += 1

    def close(self) -> None:
        self.queryable.undeclare()
        while True:  # room for the stop mark (what still waits is let go)
            try:
                self._q.put_nowait(None)
                break
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self._q.get_nowait()
        self._thread.join(timeout=2)


@dataclass(frozen=True, slots=True)
class Exchange:
    """The times of one clock exchange (ns): ``t1`` query sent, ``t2`` / ``t3``
    the CN's receive and reply times, ``t4_cb`` read in zenoh's reply
    callback, ``t4`` read by the waiting thread after the hand-off;
    ``stamps``: zenoh's four time points when the query was instrumented."""

    t1: int
    t2: int
    t3: int
    t4_cb: int
    t4: int
    stamps: list[int]


CLOCK_REPLIERS_MAX = 8
"""Replies an exchange reads at most (one per replier,
:class:`~zplatform.runtime.queries.ReplyCap`):
a peer flooding replies cannot keep the asking thread reading."""


def _exchange(
    session: zenoh.Session,
    keys: KeySpace,
    link: ClockLink,
    now_ns: Callable[[], int],
    timeout_s: float,
    instrumentation: zenoh.TimestampInstrumentation | None = None,
) -> Exchange | None:
    """One exchange: the times of the first reply that is this query's
    answer (:meth:`ClockLink.check`), or None (counted in
    :attr:`ClockLink.timeouts`) when none came within ``timeout_s``. Every
    queryable on the clock key is asked (:func:`~zplatform.runtime.queries.ask`: a
    rogue cannot hide the CN, a congested link drops the query rather than
    block); each replier's first reply is checked, in arrival order, at most
    :data:`CLOCK_REPLIERS_MAX` of them, and the exchange ends at the first
    valid one. Never waits past ``timeout_s``, whatever the peers do."""
    # (payload, t4 read in the callback, zenoh's stamps); None: the query ended.
    replies: Mailbox[tuple[bytes, int, list[int]] | None] = Mailbox(CLOCK_REPLIERS_MAX + 1)
    cap = ReplyCap(1)  # the CN answers a query once: more from one replier is a flood

    def on_reply(r: zenoh.Reply) -> None:
        t4 = now_ns()  # in zenoh's thread, before any hand-off
        ok = r.ok
        if ok is None:
            return
        # The screen first (length, header tag, this query's nonce): junk and
        # replies to other queries, from however many peers, never take a
        # place among the CLOCK_REPLIERS_MAX read (issue 25).
        data = link.screen(ok.payload, nonce)
        if data is None or not cap.admit(r):
            return
        stack = getattr(ok, "timestamp_stack", None)
        stamps: list[int] = []
        if stack is not None:
            for rec in stack.records[:4]:
                ts = rec.timestamp()
                if isinstance(ts, bytes | bytearray):
                    continue
                stamps.append(ts.get_time_as_ntp64().as_nanos())
        replies.put((data, t4, stamps))

    t1 = now_ns()
    payload, nonce = link.query(t1)
    ask(
        session,
        keys.clock,
        queries.replies(on_reply, lambda: replies.put(None)),
        payload=payload,
        timeout_s=timeout_s,
        instrumentation=instrumentation,
    )
    deadline = time.monotonic() + timeout_s
    for _ in range(CLOCK_REPLIERS_MAX):
        left = deadline - time.monotonic()
        item = replies.get(left) if left > 0 else None
        if item is None:  # the deadline passed, or the query ended unanswered
            break
        t4 = now_ns()
        raw, t4_cb, stamps = item
        got = link.check(raw, nonce)
        if got is not None:  # the CN's answer to this very query
            _, t2, t3 = got
            return Exchange(t1, t2, t3, t4_cb, t4, stamps)
    link.timeouts += 1
    return None


def learn_run(
    session: zenoh.Session,
    keys: KeySpace,
    now_ns: Callable[[], int],
    link: ClockLink,
    *,
    tries: int = 3,
    timeout_s: float = 1.0,
) -> bool:
    """Ask the control node's run with hellos (:meth:`ClockLink.forget`, module
    doc) until one is answered, at most ``tries`` exchanges: True when one
    was (the run it names is ``link.run`` now), False when none was (each
    counted in ``link``). Measures nothing: a device node that never
    re-measures its clock (``clock.resync_s: 0``) still follows a control
    node that starts a new run. Blocks at most ``tries * timeout_s``."""
    for _ in range(tries):
        link.forget()
        if _exchange(session, keys, link, now_ns, timeout_s) is not None:
            return True
    return False


ADAPT_AFTER = 8
"""Exchanges after which a series' timeout follows their round trips
(:class:`ExchangeTimeout`)."""
ADAPT_FACTOR = 20
ADAPT_FLOOR_S = 0.1


class ExchangeTimeout:
    """The timeout of a clock series' next exchange: the caller's
    ``timeout_s`` for the first :data:`ADAPT_AFTER` exchanges, then
    :data:`ADAPT_FACTOR` times their median round trip, at least
    :data:`ADAPT_FLOOR_S`, never more than ``timeout_s``.

    Why: a clock reply goes DROP (its query's QoS), and one dropped on a
    busy link left its exchange waiting out the whole timeout (1 s), which
    at start-up delayed every node of the mission by it (seen in about one
    start in six; the control node had served the query). A reply later
    than twenty median round trips is no sample the estimate keeps (it
    keeps the fastest). An exchange left unanswered counts as a round trip
    of the time it waited (:meth:`missed`): a host that turns slow after
    the first answers, so that most exchanges go unanswered, brings the
    median, and the timeout, back up to ``timeout_s`` within as many
    misses as there were answers; one lost reply among many does not move
    it. Sans-IO; allocates one list of at most ``exchanges``."""

    __slots__ = ("_cap", "_rtts")

    def __init__(self, timeout_s: float) -> None:
        self._cap = timeout_s
        self._rtts: list[int] = []

    def answered(self, t1_ns: int, t4_ns: int) -> None:
        """An exchange answered: its round trip on the asker's clock."""
        self._rtts.append(max(0, t4_ns - t1_ns))

    def missed(self, waited_s: float) -> None:
        """An exchange unanswered after ``waited_s``: at least that long a trip."""
        self._rtts.append(int(waited_s * 1e9))

    def next_s(self) -> float:
        """The next exchange's timeout (s)."""
        n = len(self._rtts)
        if n < ADAPT_AFTER:
            return self._cap
        rtts = sorted(self._rtts)
        median_ns = rtts[n // 2] if n % 2 else (rtts[n // 2 - 1] + rtts[n // 2]) / 2
        return min(self._cap, max(ADAPT_FLOOR_S, ADAPT_FACTOR * median_ns / 1e9))


def estimate_offset(
    session: zenoh.Session,
    keys: KeySpace,
    now_ns: Callable[[], int],
    link: ClockLink,
    *,
    exchanges: int = 200,
    keep_fraction: float = 0.1,
    timeout_s: float = 1.0,
) -> ClockEstimate:
    """Measure the CN-minus-local clock offset over ``exchanges`` round trips.

    Each exchange is :class:`ClockLink`'s (authenticated, nonce-bound);
    replies it refuses and exchanges left unanswered are counted there.
    Blocks for the exchanges (about 0.3 ms each on loopback), each at most
    ``timeout_s`` whatever the peers do (:func:`_exchange`), and after a
    few at most twenty times their median round trip
    (:class:`ExchangeTimeout`, floored at 0.1 s), and stops early
    once half of them can no longer get a valid reply. Raises
    ClockSyncError when fewer than half the exchanges get a valid reply
    (the CN's clock server is unreachable, or only peers without the key
    answer).
    """
    samples: list[tuple[int, int]] = []
    missed = 0
    timeout = ExchangeTimeout(timeout_s)
    for _ in range(exchanges):
        wait_s = timeout.next_s()
        x = _exchange(session, keys, link, now_ns, wait_s)
        if x is None:
            timeout.missed(wait_s)
            missed += 1
            if missed > exchanges - exchanges // 2:
                break  # half can no longer answer: stop asking a silent clock
            continue
        timeout.answered(x.t1, x.t4)
        t1, t2, t3, t4 = x.t1, x.t2, x.t3, x.t4
        samples.append((((t2 - t1) + (t3 - t4)) // 2, (t4 - t1) - (t3 - t2)))
    if len(samples) < exchanges // 2:
        raise ClockSyncError(
            f"clock sync got {len(samples)} of {exchanges} valid replies from {keys.clock}"
            + _refusals(link)
        )
    return _fastest(samples, keep_fraction)


def _refusals(link: ClockLink) -> str:
    if not link.refused:
        return ""
    return (
        f" ({link.refused_bad} replies refused for a bad tag, {link.refused_other} for "
        "another exchange: a peer without the key answers?)"
    )


def _fastest(samples: list[tuple[int, int]], keep_fraction: float) -> ClockEstimate:
    """The estimate from ``(offset, delay)`` samples: the median offset of the
    fastest ``keep_fraction`` (at least 3), which the network delayed least."""
    samples.sort(key=lambda s: s[1])
    kept = samples[: max(3, int(len(samples) * keep_fraction))]
    offsets = sorted(o for o, _ in kept)
    return ClockEstimate(
        offset_ns=offsets[len(offsets) // 2],
        delay_ns=kept[len(kept) // 2][1],
        exchanges=len(samples),
        kept=len(kept),
        spread_ns=offsets[-1] - offsets[0],
    )


def estimate_offset_zenoh(
    session: zenoh.Session,
    keys: KeySpace,
    now_ns: Callable[[], int],
    link: ClockLink,
    *,
    exchanges: int = 200,
    keep_fraction: float = 0.1,
    timeout_s: float = 1.0,
    max_inversion_ns: int = 100_000,
) -> ClockEstimate:
    """The same estimate as :func:`estimate_offset`, from zenoh's own four time points.

    Each exchange is a query to the CN's :class:`ClockServer` with zenoh 1.10's
    ``TimestampInstrumentation`` (send and receive records, docs/architecture.md#zenoh): the
    reply carries ``t1z..t4z``, stamped by zenoh on the host clocks of both
    sides at the moments the query and the reply cross zenoh. Per exchange::

        offset_z = ((t2z - t1z) + (t3z - t4z)) / 2     # zenoh clocks, CN - DN
        delay_z  = (t4z - t1z) - (t3z - t2z)

    the fastest ``keep_fraction`` by ``delay_z`` are kept and their median
    ``offset_z`` is the zenoh-clock offset. It is mapped into node time with
    each side's node-minus-zenoh clock difference, bracketed over all the
    exchanges by the node-clock reads next to zenoh's stamps (a read *before*
    a stamp gives a lower bound, one *after* it an upper bound)::

        map_cn in [max(t3 - t3z), min(t2 - t2z)]   # t3 read before reply, t2 after receive
        map_dn in [max(t1 - t1z), min(t4 - t4z)]   # t1 read before get, t4 after receive
        offset = offset_z + mid(map_cn) - mid(map_dn)   # CN node - DN node

    (``t1..t4`` are the node-clock times of :func:`estimate_offset`'s
    exchange, from the unchanged :class:`ClockServer`.) Averaging each
    exchange's two mapping terms instead would cancel zenoh's stamps and
    give back :func:`estimate_offset` exactly; the brackets keep only the
    tightest reads, so Python's callback and thread hand-off latency drops
    out of both the network part and the mapping. ``spread_ns`` is the sum
    of the two bracket widths plus the kept offsets' spread. It assumes each
    side's node clock and zenoh clock run at the same rate during the
    exchanges (a 100 ppm drift over 200 exchanges moves the DN's mapping by
    about 6 us).

    Blocks for the exchanges, each at most ``timeout_s`` (less after a
    few, :class:`ExchangeTimeout`), and stops early once half of
    them can no longer get a valid reply (as :func:`estimate_offset`).
    Raises ClockSyncError when fewer than half of them get a valid reply
    (the CN's clock server is unreachable), and its subclass
    :class:`ZenohTimestampsError` where :func:`estimate_offset` would have
    succeeded: when at least half got a valid reply but fewer
    than half of the replies carried zenoh's four timestamps, or when a
    bracket is inverted by more than ``max_inversion_ns`` (its lower bound
    above its upper bound: zenoh's clock, the host's real-time clock, was
    stepped during the exchanges, and the mapping is unknown; a small
    inversion is what a rate difference over the exchanges gives).
    """
    ti = zenoh.TimestampInstrumentationBuilder().set_send(True).set_receive(True).build()
    samples: list[tuple[int, int]] = []
    # Every answered exchange's node-clock sample, as estimate_offset takes
    # it: where zenoh's stamps cannot give the offset, these do, and no
    # second series is asked (one start-up stays within the clock server's
    # rate bound for its asker, ask_bound).
    node: list[tuple[int, int]] = []
    first_t1 = last_t4 = 0  # the answered exchanges' span, for the error's words
    answered = 0  # valid replies to their own exchange, stamped or not
    cn_lo, cn_hi, dn_lo, dn_hi = -(1 << 63), 1 << 63, -(1 << 63), 1 << 63
    missed = 0
    timeout = ExchangeTimeout(timeout_s)
    for _ in range(exchanges):
        wait_s = timeout.next_s()
        x = _exchange(session, keys, link, now_ns, wait_s, ti)
        if x is None:
            timeout.missed(wait_s)
            missed += 1
            if missed > exchanges - exchanges // 2:
                break  # half can no longer answer: stop asking a silent clock
            continue
        timeout.answered(x.t1, x.t4)
        answered += 1
        if answered == 1:
            first_t1 = x.t1
        last_t4 = x.t4
        node.append((((x.t2 - x.t1) + (x.t3 - x.t4)) // 2, (x.t4 - x.t1) - (x.t3 - x.t2)))
        if len(x.stamps) != 4:
            continue
        t1, t2, t3, t4 = x.t1, x.t2, x.t3, x.t4_cb
        t1z, t2z, t3z, t4z = x.stamps
        cn_lo, cn_hi = max(cn_lo, t3 - t3z), min(cn_hi, t2 - t2z)
        dn_lo, dn_hi = max(dn_lo, t1 - t1z), min(dn_hi, t4 - t4z)
        samples.append((((t2z - t1z) + (t3z - t4z)) // 2, (t4z - t1z) - (t3z - t2z)))

    def by_node() -> ClockEstimate | None:  # only when zenoh's stamps cannot serve
        return _fastest(node, keep_fraction) if len(node) >= exchanges // 2 else None

    if len(samples) < exchanges // 2:
        if answered >= exchanges // 2:
            raise ZenohTimestampsError(
                f"zenoh-timestamp clock sync: {keys.clock} answered {answered} of "
                f"{exchanges} exchanges, but only {len(samples)} replies carried zenoh's "
                "four timestamps (does the CN's zenoh stamp instrumented queries?)",
                by_node(),
            )
        raise ClockSyncError(
            f"zenoh-timestamp clock sync got {len(samples)} of {exchanges} "
            f"instrumented replies from {keys.clock}" + _refusals(link)
        )
    inversion = max(cn_lo - cn_hi, dn_lo - dn_hi)
    if inversion > max_inversion_ns:
        side = "CN" if cn_lo - cn_hi >= dn_lo - dn_hi else "DN"
        raise ZenohTimestampsError(
            f"zenoh-timestamp clock sync: the {side}'s zenoh clock and node clock "
            f"disagree by {inversion / 1e3:.1f} us over the exchanges' "
            f"{(last_t4 - first_t1) / 1e9:.1f} s (a host clock stepped, or slewed over a "
            "long series?): zenoh's times cannot be mapped into node time",
            by_node(),
        )
    est = _fastest(samples, keep_fraction)
    map_cn = (cn_lo + cn_hi) // 2
    map_dn = (dn_lo + dn_hi) // 2
    return dataclasses.replace(
        est,
        offset_ns=est.offset_ns + map_cn - map_dn,
        spread_ns=est.spread_ns + abs(cn_hi - cn_lo) + abs(dn_hi - dn_lo),
        estimator="zenoh_ts",
    )


class Estimator(Protocol):
    """The signature :func:`estimate_offset` and :func:`estimate_offset_zenoh` share."""

    def __call__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        now_ns: Callable[[], int],
        link: ClockLink,
        *,
        exchanges: int = ...,
        keep_fraction: float = ...,
        timeout_s: float = ...,
    ) -> ClockEstimate: ...


#: ``clock.estimator`` names (:class:`~zplatform.config.ClockConfig`) to functions.
ESTIMATORS: dict[str, Estimator] = {
    "zenoh_ts": estimate_offset_zenoh,
    "node_clock": estimate_offset,
}


class ClockEstimator:
    """The mission's offset estimator, called like :func:`estimate_offset`.

    Made by :func:`estimator_for`. ``primary`` is the chosen function;
    ``fallback`` (``zenoh_ts`` only: :func:`estimate_offset`) is what a call
    gives instead when the primary raises :class:`ZenohTimestampsError`, i.e.
    when the CN answered but zenoh's timestamps could not give the offset
    (the CN's zenoh does not stamp; a host clock stepped during the
    exchanges): the node-clock estimate of the same exchanges the error
    carries, else a series of its own (a primary that carries none). The
    same exchanges, because a second series of every start-up
    that fell back (seen under a CPU hog) spent the clock server's rate
    bound for the asker (:func:`ask_bound`): a device node restarted soon
    after found its series refused and could not start. The fallback is per
    call: the next call tries ``zenoh_ts`` again. A WARNING is logged when
    calls start falling back, an INFO line when ``zenoh_ts`` works again;
    ``fallbacks`` counts them, and the estimate's ``estimator`` field names
    the one that produced it. Any other
    ClockSyncError (the CN unreachable: fewer than half the exchanges
    answered) is raised as is, with no second attempt.
    """

    def __init__(self, name: str, primary: Estimator, fallback: Estimator | None = None) -> None:
        self.name = name
        self.primary = primary
        self.fallback = fallback
        self.fallbacks = 0
        self._falling_back = False

    def __repr__(self) -> str:
        return f"ClockEstimator({self.name!r})"

    def __call__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        now_ns: Callable[[], int],
        link: ClockLink,
        *,
        exchanges: int = 200,
        keep_fraction: float = 0.1,
        timeout_s: float = 1.0,
    ) -> ClockEstimate:
        def run(fn: Estimator) -> ClockEstimate:
            return fn(
                session,
                keys,
                now_ns,
                link,
                exchanges=exchanges,
                keep_fraction=keep_fraction,
                timeout_s=timeout_s,
            )

        if self.fallback is None:
            return run(self.primary)
        try:
            est = run(self.primary)
        except ZenohTimestampsError as exc:
            self.fallbacks += 1
            if not self._falling_back:
                log.warning("%s; falling back to the node-clock estimator", exc)
                self._falling_back = True
            if exc.node_estimate is not None:  # the same exchanges, by the node clock
                return exc.node_estimate
            try:
                return run(self.fallback)
            except ClockSyncError as exc2:
                raise ClockSyncError(f"{exc2} (after the {self.name} estimator: {exc})") from exc2
        if self._falling_back:
            log.info("the %s clock estimator works again", self.name)
            self._falling_back = False
        return est


def estimator_for(clock: ClockConfig) -> ClockEstimator:
    """The offset estimator ``clock.estimator`` names (default ``zenoh_ts``).

    ``zenoh_ts``: :func:`estimate_offset_zenoh`, falling back to
    :func:`estimate_offset` with a warning when the CN answers without usable
    zenoh timestamps (:class:`ClockEstimator`); ``node_clock``:
    :func:`estimate_offset` alone. Either raises ClockSyncError when the CN
    does not answer.
    """
    if clock.estimator == "zenoh_ts":
        return ClockEstimator("zenoh_ts", estimate_offset_zenoh, fallback=estimate_offset)
    return ClockEstimator(clock.estimator, ESTIMATORS[clock.estimator])
