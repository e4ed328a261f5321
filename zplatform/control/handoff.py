"""Hand-offs from zenoh's threads (or any producer) to one consumer thread,
with waits that always end.

A zenoh callback only hands data off; the loop thread waits for it with a
deadline. Every timed wait in zplatform goes through :class:`Waker` (a
:class:`Mailbox`, a :class:`Handoff`), never through
``queue.SimpleQueue.get(timeout=...)``: on CPython 3.11 that call can block
**forever** when a signal handler (a node's SIGTERM, ``faulthandler``) runs
while it waits and the deadline passes meanwhile: it recomputes a negative
wait, which the lock layer takes as "no timeout". A device node was seen
stuck there at ``up``'s stop, its stop flag set and never looked at
again; ``tests/unit/test_handoff.py`` reproduces the trap with a slow
signal handler. :class:`Waker` waits with ``threading.Lock.acquire(timeout=)``,
which re-checks its deadline after a signal and gives up when it has passed.

Nothing here allocates per item beyond the item itself: the wake token is
one preallocated lock held or released, not an object put in a queue.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

__all__ = ["Handoff", "Mailbox", "QueryWorker", "Waker"]

T = TypeVar("T")


class Waker:
    """Wakes one consumer thread that waits on one or more mailboxes.

    A producer's :meth:`notify` releases the wake lock only when the
    consumer said it is about to wait (``_waiting``), and the consumer holds
    that lock whenever it says so: so there is at most one wake-up
    outstanding, however many producers notify, and a release never meets
    an unheld lock. Thread-safe for any number of producers and **one**
    consumer (the thread that calls :meth:`wait`).
    """

    __slots__ = ("_lock", "_token", "_waiting")

    def __init__(self) -> None:
        self._token = threading.Lock()
        self._token.acquire()  # held: no wake-up outstanding
        self._lock = threading.Lock()
        self._waiting = False

    def notify(self) -> None:
        """Called after an item was put (any thread; never blocks)."""
        with self._lock:
            if self._waiting:
                self._waiting = False
                self._token.release()

    def wait(self, ready: Callable[[], object], timeout_s: float) -> bool:
        """Until ``ready()`` (a non-blocking check, e.g. "an item is there")
        is true, at most ``timeout_s`` seconds; returns ``ready()``'s last
        value. Ends by its deadline even when signal handlers run
        meanwhile (module doc)."""
        if ready() or timeout_s <= 0:
            return bool(ready())
        deadline = time.monotonic() + timeout_s
        token = self._token
        while True:
            token.acquire(False)  # a wake-up whose item was taken already
            with self._lock:
                self._waiting = True
            ok = bool(ready())  # anything put before `_waiting` was set is seen here
            left = deadline - time.monotonic()
            if ok or left <= 0 or not token.acquire(timeout=left):
                break
        with self._lock:
            self._waiting = False
        return ok or bool(ready())


class Mailbox(Generic[T]):
    """A bounded hand-off from zenoh's threads to one consumer thread.

    :meth:`put` never blocks beyond a short lock; when ``capacity`` items are
    waiting, the oldest is let go (counted in :attr:`dropped`). The
    consumer pops the oldest first (:meth:`get`, :meth:`pop`) or takes all
    (:meth:`drain`). ``waker``: shared with other mailboxes the consumer
    waits on together (a new one by default)."""

    __slots__ = ("_has", "_items", "_lock", "capacity", "dropped", "waker")

    def __init__(self, capacity: int, waker: Waker | None = None) -> None:
        if capacity < 1:
            raise ValueError(f"a mailbox holds at least one item, not {capacity}")
        self.capacity = capacity
        self.waker = waker if waker is not None else Waker()
        self._items: deque[T] = deque()
        self._lock = threading.Lock()
        self._has = self._items.__len__  # bound once: the waits' readiness check
        self.dropped = 0
        """Items let go because the mailbox was full (since construction)."""

    def put(self, item: T) -> None:
        with self._lock:
            if len(self._items) >= self.capacity:
                self._items.popleft()  # released: a zenoh query is finalised
                self.dropped += 1
            self._items.append(item)
        self.waker.notify()

    def pop(self) -> T | None:
        """The oldest item, or None at once."""
        with self._lock:
            return self._items.popleft() if self._items else None

    def get(self, timeout_s: float) -> T | None:
        """The oldest item, waiting up to ``timeout_s`` for one; None if none came."""
        if self.waker.wait(self._has, timeout_s):
            return self.pop()
        return None

    def drain(self, into: list[T]) -> None:
        """Append every waiting item to ``into``, oldest first."""
        with self._lock:
            into.extend(self._items)
            self._items.clear()

    def __len__(self) -> int:
        return len(self._items)


class Handoff(Generic[T]):
    """An unbounded FIFO from any number of producers to one consumer, a
    drop-in for ``queue.SimpleQueue`` whose timed :meth:`get` always ends
    (module doc). Items may be None (an end marker).

    For hand-offs whose volume the consumer bounds itself (one reply per
    query it sent, one job per request); a flood-facing key takes a
    :class:`Mailbox`."""

    __slots__ = ("_has", "_items", "_waker")

    def __init__(self) -> None:
        self._items: deque[T] = deque()
        self._waker = Waker()
        self._has = self._items.__len__

    def put(self, item: T) -> None:
        """Append ``item`` (never blocks)."""
        self._items.append(item)  # deque.append is atomic
        self._waker.notify()

    def get(self, timeout: float | None = None) -> T:
        """The oldest item, waiting up to ``timeout`` seconds (None: for
        ever). Raises ``queue.Empty`` when none came in time."""
        if timeout is None:
            while not self._waker.wait(self._has, 3600.0):
                pass
        elif not self._waker.wait(self._has, timeout):
            raise queue.Empty
        return self._items.popleft()

    def get_nowait(self) -> T:
        """The oldest item; ``queue.Empty`` when there is none."""
        try:
            return self._items.popleft()
        except IndexError:
            raise queue.Empty from None

    def empty(self) -> bool:
        return not self._items

    def __len__(self) -> int:
        return len(self._items)


class QueryWorker:
    """One thread that serves the queries of one queryable, handed off by
    zenoh's callback (the gap-fill and archive servers' shared base).

    :meth:`on_query` is the queryable's callback: on zenoh's thread it checks
    only the payload's size (:meth:`size_refusal`: refused ones are dropped
    unanswered, counted and named in :attr:`last_refusal`) and hands the
    query off; with ``capacity`` queries in hand (waiting or being served)
    one more is dropped unanswered and counted in :attr:`busy`. Never
    blocks. The thread serves them in order with :meth:`serve` (a
    subclass's; an exception of ``lost``, the asker gone mid-answer, is
    noted, never raised), the query finalised after it. :meth:`stop_serving`
    stops the thread after the query in hand and drops what waits
    (idempotent). Queries are duck-typed: ``payload``, ``drop()`` and use as
    a context manager, as zenoh's are."""

    def __init__(self, name: str, capacity: int, lost: tuple[type[BaseException], ...]) -> None:
        self._capacity = capacity
        self._lost = lost
        self._pending: deque[Any] = deque()
        self._cv = threading.Condition()
        self._stop = False
        self._refused_rx = 0  # counted on zenoh's thread
        self._refused_checked = 0  # counted on the serving thread
        self.busy = 0
        """Queries dropped unanswered because ``capacity`` were in hand."""
        self.last_refusal = ""
        self._worker = threading.Thread(target=self._serve_loop, name=name, daemon=True)
        self._worker.start()

    @property
    def refused(self) -> int:
        """Queries dropped unanswered because they did not check."""
        return self._refused_rx + self._refused_checked

    def size_refusal(self, n: int) -> str | None:
        """Why a payload of ``n`` bytes is refused unread (None: it is not)."""
        raise NotImplementedError

    def serve(self, query: Any) -> None:
        """Answer one query (the serving thread)."""
        raise NotImplementedError

    def refuse(self, why: str) -> None:
        """Count a query the serving thread refused, and say why."""
        self._refused_checked += 1
        self.last_refusal = why

    # zenoh's thread: check the size, hand off, nothing more.
    def on_query(self, query: Any) -> None:
        p = query.payload
        why = self.size_refusal(0 if p is None else len(p))
        if why is not None:
            self._refused_rx += 1
            self.last_refusal = why
            query.drop()
            return
        with self._cv:
            if len(self._pending) >= self._capacity:
                self.busy += 1
                query.drop()
                return
            self._pending.append(query)
            self._cv.notify()

    def _serve_loop(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                query = self._pending[0]
            try:
                with query:
                    self.serve(query)
            except self._lost as exc:  # the asker went away mid-answer
                self.last_refusal = f"a reply failed: {exc}"
            finally:
                with self._cv:
                    self._pending.popleft()

    def stop_serving(self) -> None:
        with self._cv:
            if self._stop:
                return
            self._stop = True
            self._cv.notify()
        self._worker.join(timeout=5)
        with self._cv:
            while self._pending:  # asked too late: finalised unanswered
                self._pending.popleft().drop()
