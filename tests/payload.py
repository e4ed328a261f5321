"""Stand-ins for what zenoh hands a callback in in-process intake tests: a
payload, a query (what the server did with it kept), a session to declare a
queryable on; and :func:`deliver`, which plays zenoh's callback and the
server's thread for a query server (the archive's, the flight recorder's)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Protocol


class Bytes:
    """A payload as zenoh hands it over: the length for free; ``to_bytes``
    counted (class-wide), so a test can tell a frame was refused unread."""

    copies = 0

    def __init__(self, data: bytes) -> None:
        self._data = data

    def __len__(self) -> int:
        return len(self._data)

    def to_bytes(self) -> bytes:
        Bytes.copies += 1
        return self._data


class FakeQuery:
    """A zenoh query as a queryable's callback gets one: its payload (a
    :class:`Bytes`), and what the server did with it: its replies, its error
    replies, whether it was finalised unanswered (``dropped``)."""

    def __init__(self, payload: bytes) -> None:
        self.payload = Bytes(payload)
        self.replies: list[bytes] = []
        self.errors: list[bytes] = []
        self.dropped = False

    def __enter__(self) -> FakeQuery:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def reply(self, key: str, payload: bytes | bytearray) -> None:
        self.replies.append(bytes(payload))

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(bytes(payload))

    def drop(self) -> None:
        self.dropped = True


class FakeSession:
    """A zenoh session a server declares its queryable on: nothing is
    declared, and nothing calls the handler (the test does)."""

    def declare_queryable(self, key: str, handler: object, **kw: object) -> Any:
        return SimpleNamespace(undeclare=lambda: None)


class QueryServer(Protocol):
    """A server whose zenoh callback admits queries into ``_pending`` for its
    thread to serve (ArchiveServer, RecorderServer)."""

    _pending: Any

    def on_query(self, query: Any) -> None: ...

    def serve(self, item: Any) -> Any: ...


def deliver(server: QueryServer, *payloads: bytes) -> list[FakeQuery]:
    """Hand ``payloads`` to ``server``'s zenoh callback (all in hand at
    once), then serve what it admitted, in order, on this thread (the
    server's own thread closed: no timing); the queries, replies in."""
    qs = [FakeQuery(p) for p in payloads]
    for q in qs:
        server.on_query(q)
    while server._pending:
        server.serve(server._pending.popleft())
    return qs
