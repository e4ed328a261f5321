"""The archive over zenoh: the ground node answers queries on ``{vehicle}/archive/query``.

An ask is :data:`ASK` (magic, stamp, nonce) then a :class:`~.query.Query` as
JSON, tagged with the telemetry channel's key (every role that may read
telemetry holds it: the ground, a tool). :class:`ArchiveServer`'s zenoh
callback only checks the size and hands the query to a bounded inbox
(:data:`MAX_PENDING`; more are dropped unanswered, counted); its thread checks
the tag, a stamp within the clock bound, none of the last :data:`REMEMBERED`
served, runs the query, and replies with the answer as an Arrow IPC stream in
chunks (:data:`REPLY`: kind, the ask's nonce, index, count), each tagged,
paced to ``serve_bps``. An answer over ``max_bytes`` is one ``ERROR`` reply
saying so (never cut silently); so is a refused query (its reason).
:class:`ArchiveAsk` is the asker's side: it checks each reply (tag, nonce,
index) and puts the table together.

Contract: neither side raises for what the peer sends; a bad frame is
refused and counted (``refused``). The key's row: zplatform/security/keyspace.py.
"""

from __future__ import annotations

import struct
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import msgspec
import pyarrow as pa
import zenoh

from ..control.handoff import QueryWorker
from ..core.auth import TAG_LEN, AuthError, Channel
from ..errors import ArchiveError
from .query import Archive, Query

__all__ = [
    "ASK",
    "MAX_ASK",
    "MAX_PENDING",
    "REPLY",
    "ArchiveAsk",
    "ArchiveServer",
    "ask_payload",
    "remote_query",
]

ASK_MAGIC = b"ZAQ1"
ASK = struct.Struct("<4sqQ")  # magic, t_ns, nonce
MAX_ASK = 4096
"""Most bytes of an ask's JSON query."""
REPLY = struct.Struct("<BQII")  # kind, nonce, index, count
DATA, ERROR = 1, 2
CHUNK = 32 * 1024
"""Bytes of the answer per reply (under zenoh's unfragmented batch)."""
MAX_PENDING = 2
REMEMBERED = 64
_QUERY = msgspec.json.Decoder(Query)


def ask_payload(channel: Channel | None, query: Query, t_ns: int, nonce: int) -> bytes:
    """An ask: :data:`ASK` and the query's JSON, tagged."""
    body = ASK.pack(ASK_MAGIC, t_ns, nonce) + msgspec.json.encode(query)
    return bytes(channel.seal(body)) if channel is not None else body


class ArchiveServer(QueryWorker):
    """Answers archive queries (module doc). ``open_archive``: the archive
    to read (called in the serving thread, per query); ``channel``: the
    telemetry channel (its own instance), None without authentication."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        open_archive: Callable[[], Archive],
        channel: Channel | None,
        *,
        now_ns: Callable[[], int],
        max_age_ns: int,
        serve_bps: int,
        max_bytes: int,
    ) -> None:
        self._open, self._channel, self._now = open_archive, channel, now_ns
        self._max_age, self._bps, self._max_bytes, self._key = (
            max_age_ns,
            serve_bps,
            max_bytes,
            key_expr,
        )
        self._max_len = ASK.size + MAX_ASK + (TAG_LEN if channel is not None else 0)
        self._min_len = ASK.size + (TAG_LEN if channel is not None else 0)
        self._served: deque[tuple[int, int]] = deque(maxlen=REMEMBERED)
        self._closed = False
        self.served = 0
        """Queries answered (with rows, or with an error saying why)."""
        super().__init__("archive-serve", MAX_PENDING, (zenoh.ZError,))
        self.queryable = session.declare_queryable(
            key_expr, zenoh.handlers.Callback(self.on_query, indirect=False)
        )

    def size_refusal(self, n: int) -> str | None:
        return None if self._min_len <= n <= self._max_len else f"an ask of {n} bytes"

    def serve(self, query: Any) -> None:
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        ch = self._channel
        try:
            body: Any = bytes(ch.open(data)) if ch is not None else data
        except AuthError as exc:
            self.refuse(str(exc))
            return
        magic, t_ns, nonce = ASK.unpack_from(body, 0)
        if magic != ASK_MAGIC:
            self.refuse("not an archive ask")
            return
        age = self._now() - t_ns
        if abs(age) > self._max_age:
            self.refuse(f"an ask stamped {age / 1e9:+.3f} s from this node's clock")
            return
        if ch is not None:
            if (t_ns, nonce) in self._served:
                self.refuse("an ask answered before (a replay)")
                return
            self._served.append((t_ns, nonce))
        try:
            q = _QUERY.decode(body[ASK.size :])
            with self._open() as a:
                table = a.query(q)
            sink = pa.BufferOutputStream()
            with pa.ipc.new_stream(sink, table.schema) as w:
                w.write_table(table)
            answer = sink.getvalue().to_pybytes()
            if len(answer) > self._max_bytes:
                raise ArchiveError(
                    f"the answer holds {len(answer)} bytes, more than this station serves "
                    f"({self._max_bytes}): narrow the range, ask fewer elements or aggregate"
                )
        except (ArchiveError, msgspec.DecodeError, msgspec.ValidationError) as exc:
            self.served += 1  # before the reply: an asker that has it finds it counted
            self._reply(query, ERROR, nonce, 0, 1, str(exc).encode()[:CHUNK])
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

    def _reply(self, query: Any, kind: int, nonce: int, i: int, n: int, data: bytes) -> int:
        frame = REPLY.pack(kind, nonce, i, n) + data
        out = bytes(self._channel.seal(frame)) if self._channel is not None else frame
        query.reply(self._key, out)
        return len(out)

    def close(self) -> None:
        """Undeclare the queryable, stop the thread (after the query in hand)."""
        if self._closed:
            return
        self._closed = True
        self.queryable.undeclare()
        self.stop_serving()


class ArchiveAsk:
    """One ask's replies, checked and put together (module doc)."""

    def __init__(self, channel: Channel | None, nonce: int) -> None:
        self._channel, self.nonce = channel, nonce
        self._chunks: dict[int, bytes] = {}
        self._count: int | None = None
        self.error: str | None = None
        self.refused = 0
        """Replies refused: a bad tag, another ask's, a repeated or impossible index."""
        self.max_len = REPLY.size + CHUNK + (TAG_LEN if channel is not None else 0)

    def on_reply(self, payload: bytes) -> bool:
        """Take one reply; True when admitted. Never raises."""
        if not REPLY.size <= len(payload) <= self.max_len:
            self.refused += 1
            return False
        try:
            body = bytes(self._channel.open(payload)) if self._channel is not None else payload
        except AuthError:
            self.refused += 1
            return False
        if len(body) < REPLY.size:
            self.refused += 1
            return False
        kind, nonce, i, n = REPLY.unpack_from(body, 0)
        ok = nonce == self.nonce and kind in (DATA, ERROR) and i < n
        ok = ok and (self._count is None or n == self._count) and i not in self._chunks
        ok = ok and n <= self.max_chunks and self.error is None
        if not ok:
            self.refused += 1
            return False
        if kind == ERROR:
            self.error = body[REPLY.size :].decode("utf-8", "replace")
            return True
        self._count = n
        self._chunks[i] = body[REPLY.size :]
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
    query: Query,
    *,
    now_ns: int,
    nonce: int,
    timeout_s: float,
) -> pa.Table:
    """Ask the station(s) serving ``key_expr`` for ``query``; blocks up to
    ``timeout_s``. The replies come through a bounded mailbox (zenoh's
    thread only hands off). ArchiveError: no answer, a refusal (its
    reason), or an incomplete one."""
    from ..control.handoff import Mailbox
    from ..runtime.queries import ask, replies

    box: Mailbox[bytes | None] = Mailbox(1 << 16)

    def on_reply(reply: zenoh.Reply) -> None:
        ok = reply.ok
        if ok is not None:
            box.put(ok.payload.to_bytes())

    asker = ArchiveAsk(channel, nonce)
    ask(
        session,
        key_expr,
        replies(on_reply, lambda: box.put(None)),
        payload=ask_payload(channel, query, now_ns, nonce),
        timeout_s=timeout_s,
    )
    deadline = time.monotonic() + timeout_s + 1.0
    while not asker.done and (left := deadline - time.monotonic()) > 0:
        item = box.get(left)
        if item is None:
            break
        asker.on_reply(item)
    if asker.error is None and asker._count is None:
        raise ArchiveError(
            f"no station answered on {key_expr} within {timeout_s:g} s"
            + (f" ({asker.refused} reply(s) refused)" if asker.refused else "")
        )
    return asker.table()
