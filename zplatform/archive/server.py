"""The archive over zenoh: the ground node answers queries on ``{vehicle}/archive/query``.

Every frame is tagged with the telemetry channel's key (every role that may
read telemetry holds it) and bound to the serving *session*: a random word
:class:`ArchiveServer` draws when it starts, carried as the tag's run word
(codecs/FORMAT.md §6.1), so an ask or an answer recorded in an earlier
session never verifies again. An asker learns the session by a *hello*
answered statelessly with the session and a cookie; its ask carries the
cookie and a fresh nonce, taken once while the cookie is young (the
protocol and the per-asker bounds: :class:`ArchiveServer`). An ask is of
one *kind* (:data:`KINDS`): a telemetry query, the run list, or a run's
events. Answers are Arrow IPC stream chunks, each tagged, echoing the ask's
nonce, paced.
:class:`ArchiveAsk` is the asker's side.

Contract: neither side raises for what the peer sends; a bad frame is
refused and counted (``refused``: junk or a bad tag; ``stale``: another
session's frame, an expired cookie, a replay). The key's row:
zplatform/security/keyspace.py.
"""

from __future__ import annotations

import secrets
import struct
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import msgspec
import pyarrow as pa
import zenoh

from ..control.handoff import QueryWorker
from ..core.auth import RUN_LEN, TAG_LEN, AuthError, Channel, Run, RunError
from ..errors import ArchiveError
from .query import Archive, Query
from .store import RunInfo

__all__ = [
    "ASK",
    "EVENTS",
    "HELLO",
    "KINDS",
    "MAX_ASK",
    "MAX_PENDING",
    "QUERY",
    "REPLY",
    "REPLY_BACKLOG",
    "REPLY_BACKLOG_BYTES",
    "RUNS",
    "RUNS_SCHEMA",
    "SESSION_BODY",
    "ArchiveAsk",
    "ArchiveServer",
    "EventsAsk",
    "RunsAsk",
    "ask_payload",
    "hello_payload",
    "remote_query",
    "runs_from_table",
]

ASK_MAGIC = b"ZAQ3"
HELLO_MAGIC = b"ZAH2"
_NONCE_AT = 12
"""Where every version's ask and hello carry their nonce (after the magic
and a u64: ZAQ1's stamp, ZAQ2's and ZAQ3's asker, ZAH2's asker): what a
version error reply echoes, the one field read of a foreign frame."""
VERSION_ERROR_EVERY_NS = 1_000_000_000
"""At most one version error reply (an ask or hello of another version,
:class:`ArchiveServer`) per this much time; more are refused unanswered."""
ASK = struct.Struct("<4sQQqB")  # magic, asker, nonce, cookie, kind
HELLO = struct.Struct("<4sQQ")  # magic, asker, nonce
MAX_ASK = 4096
"""Most bytes of an ask's JSON query."""
REPLY = struct.Struct("<BQII")  # kind, nonce, index, count
SESSION_BODY = struct.Struct("<Qq")  # a SESSION reply's data: session, cookie
DATA, ERROR, SESSION = 1, 2, 3
CHUNK = 32 * 1024
"""Bytes of the answer per reply (under zenoh's unfragmented batch)."""
MAX_PENDING = 8
"""Asks and hellos in hand (waiting or being served); more are dropped, counted."""
REMEMBERED = 4096
"""Most asks whose cookie has not expired kept at once; an ask past it is
refused with a reason (the older ones are never forgotten early)."""
ASKERS = 1024
"""Askers whose byte bucket is kept (the least recently served one is let go)."""
REPLY_BACKLOG = 1 << 16
"""Replies an ask's mailbox holds waiting for the asking thread, at most."""
REPLY_BACKLOG_BYTES = 32 << 20
"""Bytes of replies an ask's mailbox holds, at most (a thousand chunks: the
asking thread checks them far faster than a station paces them); more are
refused in zenoh's callback, counted (:attr:`ArchiveAsk.dropped`)."""
RESEND_AFTER_S = 0.5
"""How long an asker waits on a silent station (no reply, its get not ended)
before it sends its hello again (:func:`remote_query`), then twice as long
each time: a hello or its answer zenoh DROPped on a congested link costs
that wait, not the whole timeout."""
MAX_SENDS = 3
"""Gets an asker sends for one hello, at most (each takes a place in a busy
station's inbox until it is answered)."""
HELLOS_KEPT = 256
"""Hellos (asker word and nonce) a server keeps, to refuse a replay of one
in zenoh's callback before it takes a place in the inbox (stale): a
replayer needs more captured hellos than this to have any answered twice."""
QUERY, RUNS, EVENTS = 1, 2, 3
KINDS = {QUERY: "query", RUNS: "runs", EVENTS: "events"}
"""An ask's kind byte: what its JSON body is and what is answered."""


class RunsAsk(msgspec.Struct, forbid_unknown_fields=True):
    """The run list's ask (kind :data:`RUNS`; its JSON is ``{}``): answered
    with :meth:`Archive.runs` as rows (:data:`RUNS_SCHEMA`)."""


class EventsAsk(msgspec.Struct, forbid_unknown_fields=True):
    """A run's events (kind :data:`EVENTS`): :meth:`Archive.events` of
    ``run`` (None: the last), ``severity`` names only (None: every one)."""

    run: int | None = None
    severity: list[str] | None = None


Ask = Query | RunsAsk | EventsAsk
_KIND_OF: dict[type, int] = {Query: QUERY, RunsAsk: RUNS, EventsAsk: EVENTS}
_DECODERS: dict[int, msgspec.json.Decoder[Any]] = {
    QUERY: msgspec.json.Decoder(Query),
    RUNS: msgspec.json.Decoder(RunsAsk),
    EVENTS: msgspec.json.Decoder(EventsAsk),
}
_NARROW = {
    QUERY: "narrow the range, ask fewer elements or aggregate",
    RUNS: "the run list is longer than archive.serve_max_bytes (read it where the archive is)",
    EVENTS: "ask fewer severities",
}
"""What an asker may do about an answer over the station's bound, per kind."""
RUNS_SCHEMA = pa.schema(
    [
        ("run", pa.int64()),
        ("mission", pa.string()),
        ("vehicle", pa.string()),
        ("layout_id", pa.int64()),
        ("start_ns", pa.int64()),
        ("end_ns", pa.int64()),
        ("first_loop", pa.int64()),
        ("last_loop", pa.int64()),
        ("loops", pa.int64()),
        ("states", pa.list_(pa.string())),
        ("final_state", pa.string()),
        ("outcome", pa.string()),
        ("events", pa.int64()),
        ("commands", pa.list_(pa.string())),
        ("in_order", pa.bool_()),
        ("group_columns", pa.int64()),
        ("version", pa.int64()),
    ]
)
"""The run list's answer: one row per :class:`~.store.RunInfo`, its fields."""


def runs_table(runs: list[RunInfo]) -> pa.Table:
    """``runs`` as rows of :data:`RUNS_SCHEMA` (the answer to a :data:`RUNS` ask)."""
    return pa.Table.from_pylist([msgspec.to_builtins(r) for r in runs], schema=RUNS_SCHEMA)


def runs_from_table(table: pa.Table) -> list[RunInfo]:
    """The run records a :data:`RUNS` answer holds. ArchiveError when a row
    is not a run record (a station of another version)."""
    try:
        return [msgspec.convert(row, RunInfo) for row in table.to_pylist()]
    except msgspec.ValidationError as exc:
        raise ArchiveError(f"the station's run list is not one this version reads: {exc}") from None


def hello_payload(channel: Channel | None, asker: int, nonce: int) -> bytes:
    """A hello: :data:`HELLO`, tagged in no run (the asker knows no session yet)."""
    body = HELLO.pack(HELLO_MAGIC, asker, nonce)
    if channel is None:
        return body
    run, channel.run = channel.run, None
    try:
        return bytes(channel.seal(body))
    finally:
        channel.run = run


def ask_payload(
    channel: Channel | None,
    query: Ask,
    cookie: int,
    nonce: int,
    *,
    asker: int = 0,
    kind: int | None = None,
) -> bytes:
    """An ask: :data:`ASK` (its kind byte: ``query``'s type's, or ``kind``)
    and the query's JSON, tagged in ``channel``'s run (the session its hello
    taught, :meth:`ArchiveAsk.on_reply`)."""
    k = _KIND_OF[type(query)] if kind is None else kind
    body = ASK.pack(ASK_MAGIC, asker, nonce, cookie, k) + msgspec.json.encode(query)
    return bytes(channel.seal(body)) if channel is not None else body


class ArchiveServer(QueryWorker):
    """Answers archive queries (module doc).

    An asker learns the
    session as the ground and the tools learn the vehicle's run: a *hello*
    (:data:`HELLO`: magic, asker, a fresh nonce; tagged in no run) is answered
    statelessly with a ``SESSION`` reply (the session and a cookie, the server's
    monotonic clock, echoing the nonce; tagged in the session). The ask
    (:data:`ASK`: magic, asker, a fresh nonce, the cookie, its kind, then
    as JSON a :class:`~.query.Query` (kind :data:`QUERY`), :class:`RunsAsk`
    (:data:`RUNS`) or :class:`EventsAsk` (:data:`EVENTS`)) is tagged in the
    session; the server takes
    it only while its cookie is younger than ``max_age_ns`` and its (cookie,
    asker, nonce) is not one it took (each kept until its cookie expires: never
    forgotten early), so a recorded ask cannot be replayed later in the same
    session either.

    :class:`ArchiveServer`'s zenoh callback checks the size, then the
    header tag (a channel of its own, any run's: junk is refused there,
    counted, and never takes a place in the inbox, issue 25), refuses as
    stale an ask of another session, with an expired cookie or answered
    before (all within the header tag's bytes), hands the rest to a
    bounded inbox (:data:`MAX_PENDING`; more are dropped unanswered,
    counted ``busy``) and counts an ask under its asker word (tagged in the
    session: a keyless peer that read a station's asker word cannot spend
    that station's bound). Its
    thread checks the tag, the session, the cookie, runs the query, and replies
    with the answer as an Arrow IPC stream in chunks (:data:`REPLY`: kind, the
    ask's nonce, index, count), each tagged, paced to ``serve_bps``. Per asker
    (the asker word, a random u64 each :class:`ArchiveAsk`'s station draws):
    at most ``per_asker`` asks in hand, and at most ``asker_bps`` bytes of
    answers per second (a bucket holding ``max_bytes``); an ask past either
    bound is answered with one ``ERROR`` reply saying which and why, as is an
    answer over ``max_bytes`` and a refused query (never cut silently).
    :class:`ArchiveAsk` is the asker's side: it learns the session, then checks
    each reply (tag in the session, nonce, index) and puts the table together.

    An ask or hello of another version (magic ``ZAQn``/``ZAHn`` not this
    one's) whose tag checks (any run) is answered with one ``ERROR`` reply
    naming both versions, its body never parsed (the nonce echoed from
    where every version carries it), at most one a
    :data:`VERSION_ERROR_EVERY_NS` (more: refused unanswered, counted).

    ``open_archive``: the archive to read (called in the serving thread by
    the first ask, then kept until :meth:`close`; called again while it raises); ``channel``: the
    telemetry channel (its own instance: this server binds it to its
    session), None without authentication; ``now_ns``: the clock of the
    cookies (monotonic); ``max_age_ns``: how old a cookie an ask may carry
    when served; ``per_asker``/``asker_bps``: the bounds per asker (None:
    ``MAX_PENDING`` and ``serve_bps``); ``session``: the session word (None:
    random)."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        open_archive: Callable[[], Archive],
        channel: Channel | None,
        *,
        now_ns: Callable[[], int] = time.monotonic_ns,
        max_age_ns: int,
        serve_bps: int,
        max_bytes: int,
        per_asker: int | None = None,
        asker_bps: int | None = None,
        session_word: int | None = None,
    ) -> None:
        self._open, self._channel, self._now = open_archive, channel, now_ns
        self._max_age, self._bps, self._max_bytes, self._key = (
            max_age_ns,
            serve_bps,
            max_bytes,
            key_expr,
        )
        self._per_asker = per_asker if per_asker is not None else MAX_PENDING
        self._asker_bps = asker_bps if asker_bps is not None else serve_bps
        word = session_word if session_word is not None else secrets.randbits(64)
        self.session = Run(word or 1)
        """The session this server's frames are bound to (module doc)."""
        tag = TAG_LEN if channel is not None else 0
        self._max_len = ASK.size + MAX_ASK + tag
        self._min_len = HELLO.size + tag
        self._served: dict[tuple[int, int, int], None] = {}  # (cookie, asker, nonce)
        self._in_hand: dict[int, int] = {}  # asker -> tagged asks in hand (zenoh's thread counts)
        self._counted: dict[int, int] = {}  # id() of an ask counted in _in_hand -> its asker
        self._over: set[int] = set()  # id() of asks taken past their asker's bound
        # zenoh's thread checks an ask's header tag (to count it under its
        # asker) with a channel of its own: it never waits on the serving
        # thread's MACs (a reply's seal covers a whole Arrow chunk).
        self._rx_channel = channel.twin() if channel is not None else None
        if self._rx_channel is not None:
            self._rx_channel.run = None  # the header tag of any run (_tagged_asker)
        self._rx_lock = threading.Lock()  # zenoh's threads may call back at once
        self._refused_early = 0  # by their header tag, on zenoh's threads (in `refused`)
        # The last HELLOS_KEPT hellos' asker and nonce (a ring, and as a set).
        self._hellos_ring = [b""] * HELLOS_KEPT
        self._hellos_at = 0
        self._hellos_seen: set[bytes] = set()
        self._version_error_ns: int | None = None
        self._buckets: OrderedDict[int, tuple[float, int]] = OrderedDict()
        self._closed = False
        # Opened by the first ask, then kept: one DuckDB connection (and its
        # cache of the files' footers) for every query, not one per query.
        self._archive: Archive | None = None
        self.served = 0
        """Queries answered (with rows, or with an error saying why)."""
        self._stale_checked = 0  # the serving thread's
        self._stale_early = 0  # zenoh's threads' (_tagged_asker)
        self.hellos = 0
        """Hellos answered (each with the session)."""
        self.over_bound = 0
        """Asks refused (answered with the reason) past their asker's bound."""
        self.other_version = 0
        """Asks and hellos of another version (answered with one error reply
        at most once a VERSION_ERROR_EVERY_NS, else refused unanswered)."""
        super().__init__("archive-serve", MAX_PENDING, (zenoh.ZError,))
        self.queryable = session.declare_queryable(
            key_expr, zenoh.handlers.Callback(self.on_query, indirect=False)
        )

    @property
    def stale(self) -> int:
        """Asks refused unanswered as stale: another session's, an expired
        cookie, one taken before (a replay)."""
        return self._stale_checked + self._stale_early

    @property
    def refused(self) -> int:
        """Frames dropped unanswered because they did not check (stale ones included)."""
        return self._refused_rx + self._refused_early + self._refused_checked + self.stale

    def size_refusal(self, n: int) -> str | None:
        return None if self._min_len <= n <= self._max_len else f"an ask of {n} bytes"

    # zenoh's thread: the size, the header tag (any run's: junk never takes
    # a place in the inbox), an ask's session to count it under its asker,
    # the inbox's bound; hand off, nothing more.
    def on_query(self, query: Any) -> None:
        p = query.payload
        n = 0 if p is None else len(p)
        why = self.size_refusal(n)
        if why is not None:
            self._refused_rx += 1
            self.last_refusal = why
            query.drop()
            return
        with self._cv:
            if len(self._pending) >= self._capacity:  # full of authentic frames already
                self.busy += 1
                query.drop()
                return
        asker = self._tagged_asker(p.to_bytes())
        if asker is None:  # junk: refused, counted, spending no place in the inbox
            query.drop()
            return
        if asker < 0:
            asker = None  # a hello, another version's, another session's: counted under none
        with self._cv:
            if len(self._pending) >= self._capacity:  # filled meanwhile
                self.busy += 1
                query.drop()
                return
            if asker is not None:
                k = self._in_hand.get(asker, 0)
                if k >= self._per_asker:
                    self._over.add(id(query))  # answered with the reason once checked
                else:
                    self._in_hand[asker] = k + 1
                    self._counted[id(query)] = asker
            self._pending.append(query)
            self._cv.notify()

    def _tagged_asker(self, data: bytes) -> int | None:
        """Zenoh's thread (its own channel, under its own lock): None, the
        frame refused and counted, when it can never be served: its header
        tag checks in no run (junk), or it is an ask of another session, or
        whose cookie expired, or answered before, or a hello among the last
        :data:`HELLOS_KEPT` (stale: all within the header tag's bytes, so no
        MAC over the body). Else the asker word
        of an ask of the session, which counts against its asker's bound,
        or -1 for any other frame (a hello, another version's), counted
        under none. The serving thread checks it all again."""
        ch = self._rx_channel
        if ch is not None:
            with self._rx_lock:
                try:
                    ch.open_header(data)  # unbound: any run's whose header tag checks
                except AuthError as exc:
                    self._refused_early += 1
                    self.last_refusal = str(exc)
                    return None
        if ch is not None and data[:4] == HELLO_MAGIC and len(data) == HELLO.size + TAG_LEN:
            # A hello is answered statelessly: a replay of one seen lately
            # (asker and nonce, within the header tag's bytes) is refused
            # here, never in hand (HELLOS_KEPT; the one copy is its 16 bytes).
            key = data[4 : HELLO.size]
            with self._rx_lock:
                seen = self._hellos_seen
                if key in seen:
                    self._stale_early += 1
                    self.last_refusal = "a hello seen before (a replay)"
                    return None
                ring, at = self._hellos_ring, self._hellos_at
                seen.discard(ring[at])
                ring[at] = key
                seen.add(key)
                self._hellos_at = (at + 1) % HELLOS_KEPT
            return -1
        if data[:4] != ASK_MAGIC or len(data) < ASK.size:
            return -1
        _, asker, nonce, cookie, _ = ASK.unpack_from(data, 0)
        if ch is not None:
            age = self._now() - cookie
            if (
                Channel.run_of(data) != self.session.epoch
                or not 0 <= age <= self._max_age
                or (cookie, asker, nonce) in self._served  # one lookup: safe beside the writer
            ):
                with self._rx_lock:
                    self._stale_early += 1
                    self.last_refusal = "an ask of another session, an expired cookie or a replay"
                return None
        return int(asker)

    def _stale(self, why: str) -> None:
        self._stale_checked += 1
        self.last_refusal = why

    def _open_frame(self, data: bytes, bound: bool, *, body: bool = True) -> Any:
        """``data``'s frame (its tag checked: in the session when ``bound``,
        any run when not); None when refused (counted). ``body`` False: its
        header tag only (codecs/FORMAT.md §6.1: an ask's fixed fields are
        within its bytes), :meth:`_body_ok` to follow."""
        ch = self._channel
        if ch is None:
            return data
        try:
            ch.run = self.session if bound else None
            frame = ch.open_header(data)
            if body:
                ch.check_body(data)
            return bytes(frame)
        except RunError:
            self._stale("an ask of another session (an earlier one's, replayed, or none)")
        except AuthError as exc:
            self.refuse(str(exc))
        return None

    def _body_ok(self, data: bytes) -> bool:
        """Whether the MAC over all of ``data``, whose header tag
        :meth:`_open_frame` checked, checks too (refused, counted, if not)."""
        ch = self._channel
        if ch is None:
            return True
        try:
            ch.check_body(data)
        except AuthError as exc:
            self.refuse(str(exc))
            return False
        return True

    def serve(self, query: Any) -> None:
        with self._cv:
            over = id(query) in self._over
            self._over.discard(id(query))
            asker = self._counted.pop(id(query), None)  # the word zenoh's thread counted
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        try:
            self._serve(query, data, over)
        finally:
            if asker is not None:
                with self._cv:
                    k = self._in_hand.get(asker, 1) - 1
                    if k > 0:
                        self._in_hand[asker] = k
                    else:
                        self._in_hand.pop(asker, None)

    def _serve(self, query: Any, data: bytes, over: bool) -> None:
        if data[:4] == HELLO_MAGIC and len(data) == HELLO.size + (
            TAG_LEN if self._channel is not None else 0
        ):
            body = self._open_frame(data, bound=False)
            if body is None:
                return
            _, _, nonce = HELLO.unpack_from(body, 0)
            self.hellos += 1
            cookie = SESSION_BODY.pack(self.session.epoch, self._now())
            self._reply(query, SESSION, nonce, 0, 1, cookie)
            return
        if len(data) < ASK.size or data[:4] != ASK_MAGIC:
            # Junk, a hello of a wrong length, or another version's ask or
            # hello: its tag decides which count.
            if self._open_frame(data, bound=False) is None:
                return
            head = data[:4]
            other = head[:3] in (ASK_MAGIC[:3], HELLO_MAGIC[:3]) and head not in (
                ASK_MAGIC,
                HELLO_MAGIC,
            )
            if other and len(data) >= _NONCE_AT + 8:
                self._other_version(query, data)
            else:
                self.refuse("not an archive ask or hello")
            return
        # Header first: the cookie and the replay are told from the header
        # tag's bytes, before the MAC over the ask's body.
        body = self._open_frame(data, bound=True, body=False)
        if body is None:
            return
        _, asker, nonce, cookie, kind = ASK.unpack_from(body, 0)
        age = self._now() - cookie
        if not 0 <= age <= self._max_age:
            self._stale(f"an ask whose session cookie is {age / 1e9:+.3f} s old")
            return
        if (cookie, asker, nonce) in self._served:
            self._stale("an ask answered before (a replay)")
            return
        if not self._body_ok(data):
            return
        self._forget(self._now())
        if len(self._served) >= REMEMBERED:
            self.refuse(f"{REMEMBERED} asks in the last {self._max_age / 1e9:g} s")
            return
        self._served[(cookie, asker, nonce)] = None
        if over:
            self.over_bound += 1
            self._error(
                query,
                nonce,
                f"this asker has {self._per_asker} queries in hand already, the most this "
                "station serves at once per asker (archive.serve_per_asker): wait for them",
            )
            return
        try:
            decoder = _DECODERS.get(kind)
            if decoder is None:
                known = ", ".join(f"{k} {n}" for k, n in KINDS.items())
                raise ArchiveError(
                    f"an ask of kind {kind}, which this station does not serve ({known})"
                )
            q = decoder.decode(body[ASK.size :])
            if self._archive is None:
                self._archive = self._open()
            if isinstance(q, RunsAsk):
                table = runs_table(self._archive.runs())
            elif isinstance(q, EventsAsk):
                table = self._archive.events(q.run, severity=q.severity)
            else:
                table = self._archive.query(q)
            sink = pa.BufferOutputStream()
            with pa.ipc.new_stream(sink, table.schema) as w:
                w.write_table(table)
            answer = sink.getvalue().to_pybytes()
            if len(answer) > self._max_bytes:
                raise ArchiveError(
                    f"the answer holds {len(answer)} bytes, more than this station serves "
                    f"({self._max_bytes}): {_NARROW[kind]}"
                )
            wait = self._take(asker, len(answer))
            if wait > 0:
                self.over_bound += 1
                raise ArchiveError(
                    f"the answer holds {len(answer)} bytes, more than this asker may take now "
                    f"({self._asker_bps} bytes/s per asker, archive.serve_asker_bps): ask "
                    f"again in {wait:.1f} s"
                )
        except (ArchiveError, msgspec.DecodeError, msgspec.ValidationError) as exc:
            self._error(query, nonce, str(exc))
            return
        count = max(1, -(-len(answer) // CHUNK))
        start, sent = time.monotonic(), 0
        for i in range(count):
            if i == count - 1:
                self.served += 1  # before the last chunk, likewise
            sent += self._reply(query, DATA, nonce, i, count, answer[i * CHUNK : (i + 1) * CHUNK])
            ahead = sent / self._bps - (time.monotonic() - start)
            if ahead > 0:
                time.sleep(ahead)  # the serving thread paces; zenoh's thread never waits

    def _other_version(self, query: Any, data: bytes) -> None:
        """An authentic ask or hello of another version: one error reply
        naming both (rate bounded), echoing its nonce; nothing else read."""
        self.other_version += 1
        what = "ask" if data[:3] == ASK_MAGIC[:3] else "hello"
        version = data[3:4].decode("ascii", "replace")
        why = (
            f"archive {what} version {version} not served; this ground serves "
            f"{ASK_MAGIC.decode()} (asks) and {HELLO_MAGIC.decode()} (hellos): use a zplatform "
            "of the ground's version"
        )
        now = self._now()
        last = self._version_error_ns
        if last is not None and 0 <= now - last < VERSION_ERROR_EVERY_NS:
            self.refuse(f"{why} (more than one such reply a second: refused unanswered)")
            return
        self._version_error_ns = now
        self.last_refusal = why
        (nonce,) = struct.unpack_from("<Q", data, _NONCE_AT)
        self._error(query, nonce, why)

    def _error(self, query: Any, nonce: int, why: str) -> None:
        self.served += 1  # before the reply: an asker that has it finds it counted
        self._reply(query, ERROR, nonce, 0, 1, why.encode()[:CHUNK])

    def _forget(self, now: int) -> None:
        """Let go of the asks whose cookie expired (a replay of one is refused by its age)."""
        served = self._served
        while served:
            key = next(iter(served))
            if now - key[0] <= self._max_age:
                break
            del served[key]

    def _take(self, asker: int, n: int) -> float:
        """Take ``n`` bytes from ``asker``'s bucket (``asker_bps``, holding at
        most ``max_bytes``): 0 when taken, else the seconds until they are there."""
        now = self._now() / 1e9
        cap = max(self._max_bytes, self._asker_bps)
        t, level = self._buckets.pop(asker, (now, cap))
        level = min(cap, level + int((now - t) * self._asker_bps))
        if len(self._buckets) >= ASKERS:
            self._buckets.popitem(last=False)
        if level < n:
            self._buckets[asker] = (now, level)
            return (n - level) / self._asker_bps
        self._buckets[asker] = (now, level - n)
        return 0.0

    def _reply(self, query: Any, kind: int, nonce: int, i: int, n: int, data: bytes) -> int:
        frame = REPLY.pack(kind, nonce, i, n) + data
        ch = self._channel
        if ch is not None:
            ch.run = self.session
            out = bytes(ch.seal(frame))
        else:
            out = frame
        query.reply(self._key, out)
        return len(out)

    def close(self) -> None:
        """Undeclare the queryable, stop the thread (after the query in hand)."""
        if self._closed:
            return
        self._closed = True
        self.queryable.undeclare()
        self.stop_serving()
        if self._archive is not None and not self._worker.is_alive():
            # (a thread still in a query past stop_serving's wait keeps it)
            self._archive.close()
            self._archive = None


class ArchiveAsk:
    """One ask's replies, checked and put together (module doc).

    ``channel``: the telemetry channel (this ask's own instance: it is bound
    to the session the hello's answer teaches), None without authentication;
    ``nonce``: the ask's (its hello's is :attr:`hello_nonce`, random);
    ``asker``: the station's word (random by default). :meth:`hello` and
    :meth:`ask` make the two frames to send, :meth:`on_reply` takes every
    reply."""

    def __init__(self, channel: Channel | None, nonce: int, *, asker: int | None = None) -> None:
        self._channel, self.nonce = channel, nonce
        self.asker = asker if asker is not None else secrets.randbits(64)
        self.hello_nonce = secrets.randbits(64)
        # Every hello sent (a re-sent one has a nonce of its own: the station
        # refuses a hello it has seen): the answer to any of them teaches.
        self._hellos = {self.hello_nonce}
        self.session: int | None = None
        """The session learned (None: no hello answered yet)."""
        self.cookie = 0
        self._chunks: dict[int, bytes] = {}
        self._count: int | None = None
        self.error: str | None = None
        self._refused = 0
        self.max_len = REPLY.size + CHUNK + (TAG_LEN if channel is not None else 0)
        if channel is not None:
            channel.run = None  # until the session is learned: any run's answer to the hello
        # zenoh's callback's (screen): a channel of its own, unbound (the run
        # word is compared with the session here), under one lock.
        self._rx = channel.twin() if channel is not None else None
        self._rx_lock = threading.Lock()
        self.screened = 0
        """Replies refused in zenoh's callback (:meth:`screen`)."""
        self.dropped = 0
        """Screened replies refused because the mailbox held :data:`REPLY_BACKLOG`
        replies or :data:`REPLY_BACKLOG_BYTES` bytes (:func:`remote_query`)."""

    @property
    def refused(self) -> int:
        """Replies refused: a bad tag, another session's, another ask's, a
        repeated or impossible index; in zenoh's callback (:attr:`screened`)
        or after."""
        return self._refused + self.screened

    def screen(self, payload: bytes) -> bool:
        """Whether a reply may take a place in the ask's mailbox (issue 25):
        zenoh's callback calls it first. Its size, its header tag (the
        first bytes: the reply's header, constant time), the session learned
        (before it: any), then the header's nonce (the hello's, then the
        ask's), kind and index. Thread-safe; copies nothing; never raises."""
        with self._rx_lock:
            ok = self._screen(payload)
            if not ok:
                self.screened += 1
            return ok

    def _screen(self, payload: bytes) -> bool:
        ch = self._rx
        tag = TAG_LEN if ch is not None else 0
        if not REPLY.size + tag <= len(payload) <= self.max_len:
            return False
        session = self.session
        if ch is not None:
            try:
                ch.open_header(payload, any_run=True)
            except AuthError:
                return False
            word = int.from_bytes(payload[-TAG_LEN : -TAG_LEN + RUN_LEN], "little")
            if session is not None and word != session:
                return False
        kind, nonce, i, n = REPLY.unpack_from(payload, 0)
        if session is None:
            return nonce in self._hellos and kind in (SESSION, ERROR) and (i, n) == (0, 1)
        return nonce == self.nonce and kind in (DATA, ERROR) and i < n <= self.max_chunks

    def hello(self) -> bytes:
        """This ask's hello (module doc)."""
        return hello_payload(self._channel, self.asker, self.hello_nonce)

    def hello_again(self) -> bytes:
        """A hello to send again, under a fresh nonce (the station refuses a
        hello it has seen); the answer to any hello of this ask teaches."""
        self.hello_nonce = secrets.randbits(64)
        self._hellos.add(self.hello_nonce)
        return self.hello()

    def ask(self, query: Ask) -> bytes:
        """The ask of ``query`` (its kind: its type) in the session learned.
        ArchiveError before one is."""
        if self.session is None:
            raise ArchiveError("no session yet: the station has not answered the hello")
        return ask_payload(self._channel, query, self.cookie, self.nonce, asker=self.asker)

    def on_reply(self, payload: bytes) -> bool:
        """Take one reply (the hello's, then the ask's); True when admitted. Never raises."""
        if not REPLY.size <= len(payload) <= self.max_len:
            self._refused += 1
            return False
        try:
            body = bytes(self._channel.open(payload)) if self._channel is not None else payload
        except AuthError:  # RunError included: another session's
            self._refused += 1
            return False
        if len(body) < REPLY.size:
            self._refused += 1
            return False
        kind, nonce, i, n = REPLY.unpack_from(body, 0)
        if self.session is None:
            word = int.from_bytes(payload[-TAG_LEN : -TAG_LEN + RUN_LEN], "little")
            return self._on_session(body, word, kind, nonce, i, n)
        ok = nonce == self.nonce and kind in (DATA, ERROR) and i < n
        ok = ok and (self._count is None or n == self._count) and i not in self._chunks
        ok = ok and n <= self.max_chunks and self.error is None
        if not ok:
            self._refused += 1
            return False
        if kind == ERROR:
            self.error = body[REPLY.size :].decode("utf-8", "replace")
            return True
        self._count = n
        self._chunks[i] = body[REPLY.size :]
        return True

    def _on_session(self, body: bytes, word: int, kind: int, nonce: int, i: int, n: int) -> bool:
        if kind == ERROR and nonce in self._hellos and (i, n) == (0, 1):
            # The station's one error reply to the hello, tagged (any run:
            # no session is known yet): a ground of another version says so.
            if self.error is None:
                self.error = body[REPLY.size :].decode("utf-8", "replace")
            return True
        ok = kind == SESSION and nonce in self._hellos and (i, n) == (0, 1)
        ok = ok and len(body) == REPLY.size + SESSION_BODY.size
        if not ok:
            self._refused += 1
            return False
        session, cookie = SESSION_BODY.unpack_from(body, REPLY.size)
        ch = self._channel
        if ch is not None:
            if session == 0 or word != session:  # tagged in the session it names
                self._refused += 1
                return False
            ch.run = Run(session)  # from now on: only this session's answers
        self.session, self.cookie = session, cookie
        return True

    max_chunks = 1 << 20
    """Most chunks an answer may claim (32 GiB: far past any station's bound)."""

    @property
    def done(self) -> bool:
        return self.error is not None or (
            self._count is not None and len(self._chunks) == self._count
        )

    def table(self) -> pa.Table:
        """The answer. ArchiveError: the station's reason, or what is missing."""
        if self.error is not None:
            raise ArchiveError(f"the station refused the query: {self.error}")
        if not self.done:
            got = len(self._chunks)
            raise ArchiveError(
                f"the answer is incomplete: {got} of {self._count or '?'} chunk(s) came"
            )
        data = b"".join(self._chunks[i] for i in range(len(self._chunks)))
        try:
            return pa.ipc.open_stream(data).read_all()
        except pa.ArrowException as exc:
            raise ArchiveError(f"the answer is not an Arrow stream: {exc}") from None


def remote_query(
    session: zenoh.Session,
    key_expr: str,
    channel: Channel | None,
    query: Ask,
    *,
    nonce: int,
    timeout_s: float,
    now_ns: int | None = None,
    asker: int | None = None,
) -> pa.Table:
    """Ask the station(s) serving ``key_expr`` for ``query`` (a telemetry
    query, the run list or a run's events, :data:`KINDS`): a hello, then
    the ask in the session it teaches (module doc); blocks up to
    ``timeout_s`` for each, the hello sent again to a silent station
    (:func:`_ask_station`, docs/archive.md). ``channel``: the telemetry
    channel, this call's
    (its run is set to the session); ``now_ns``: unused (the freshness is
    the station's cookie; kept for callers of the first version);
    ``asker``: the station's word (random by default). The replies come
    through a bounded mailbox (zenoh's thread only hands off). ArchiveError:
    no answer, a refusal (its reason), or an incomplete one."""
    del now_ns
    asker_ = ArchiveAsk(channel, nonce, asker=asker)
    _ask_station(
        session,
        key_expr,
        asker_,
        asker_.hello(),
        timeout_s,
        lambda: asker_.session is not None or asker_.error is not None,
        asker_.hello_again,
    )
    if asker_.error is not None:
        raise ArchiveError(f"the station refused the hello: {asker_.error}")
    if asker_.session is None:
        raise ArchiveError(
            f"no station answered on {key_expr} within {timeout_s:g} s"
            + _foreign(asker_.refused, "hello", HELLO_MAGIC)
        )
    # Sent once: a copy would be refused as a replay once the first is
    # served, so a slow station (its first DuckDB query on a busy host)
    # would count a genuine asker's copies among its replays.
    _ask_station(session, key_expr, asker_, asker_.ask(query), timeout_s, lambda: asker_.done)
    if asker_.error is None and asker_._count is None:
        raise ArchiveError(
            f"no station answered the ask on {key_expr} within {timeout_s:g} s (the station "
            f"refuses an ask it cannot check, or of another session)"
            + _foreign(asker_.refused, "ask", ASK_MAGIC)
        )
    return asker_.table()


def _foreign(refused: int, what: str, magic: bytes) -> str:
    """What a missing answer may mean: replies that were not this version's
    (or not for this ask), or a station of another version, which answers
    nothing (an older ground) or one error reply (a newer one)."""
    said = f"; {refused} reply(s) refused (another station's, another version's, or forged)"
    return (said if refused else "") + (
        f"; a ground of another zplatform version does not answer this one's {what} "
        f"({magic.decode()}): use a zplatform of the ground's version"
    )


def _ask_station(
    session: zenoh.Session,
    key_expr: str,
    asker: ArchiveAsk,
    payload: bytes,
    timeout_s: float,
    done: Callable[[], object],
    again: Callable[[], bytes] | None = None,
) -> None:
    """Gets of ``payload``, their replies fed to ``asker`` until ``done()``,
    every get ended, or ``timeout_s`` (and a second for the last get's end).
    Zenoh's callback screens each reply (:meth:`ArchiveAsk.screen`) before
    the mailbox, which holds at most :data:`REPLY_BACKLOG` replies and
    :data:`REPLY_BACKLOG_BYTES` bytes (more refused, counted in
    :attr:`ArchiveAsk.dropped`): junk never takes a genuine reply's place.

    ``again``: what to send when the station stays silent (no reply, no get
    ended) for :data:`RESEND_AFTER_S`, then twice as long each time, at
    most :data:`MAX_SENDS` gets in all, each ending with the first's
    deadline: a get or its answer DROPped on the way costs that wait, not
    the whole timeout. A station that answers, or ends a get unanswered
    (no station, or a refusal), is not asked again. Every get shares one
    mailbox, so a slow answer to the first is taken as well."""
    from ..control.handoff import Mailbox
    from ..runtime.queries import ask, replies

    # The replies, then one b"" per get ended (a reply is never empty: screened).
    box: Mailbox[bytes] = Mailbox(REPLY_BACKLOG + MAX_SENDS)
    lock = threading.Lock()
    held = [0, 0]  # replies, bytes in the mailbox (zenoh's thread adds, this one takes)

    def on_reply(reply: zenoh.Reply) -> None:
        ok = reply.ok  # screen, hand off only
        if ok is None:
            return
        data = ok.payload.to_bytes()
        if not asker.screen(data):
            return
        with lock:
            if held[0] >= REPLY_BACKLOG or held[1] + len(data) > REPLY_BACKLOG_BYTES:
                asker.dropped += 1
                return
            held[0] += 1
            held[1] += len(data)
        box.put(data)

    deadline = time.monotonic() + timeout_s

    def send(data: bytes) -> None:
        ask(
            session,
            key_expr,
            replies(on_reply, lambda: box.put(b"")),
            payload=data,
            timeout_s=max(0.001, deadline - time.monotonic()),
        )

    send(payload)
    sent, ended = 1, 0
    heard = time.monotonic()  # the last reply or get ended
    quiet_s = RESEND_AFTER_S
    end = deadline + 1.0
    while not done() and ended < sent:
        now = time.monotonic()
        if now >= end:
            break
        wake = end
        if again is not None and sent < MAX_SENDS and ended == 0 and now < deadline:
            if now - heard >= quiet_s:
                send(again())
                sent += 1
                heard, quiet_s = now, 2 * quiet_s
                continue
            wake = min(wake, heard + quiet_s)
        item = box.get(max(0.0, wake - now))
        if item is None:
            continue  # its wait ran out: look again
        heard = time.monotonic()
        if not item:
            ended += 1
            continue
        with lock:
            held[0] -= 1
            held[1] -= len(item)
        asker.on_reply(item)
