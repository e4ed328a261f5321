"""Named trace points in the loop and its drivers: a zero-cost hook for benchmarks.

The platform's hot paths call points by name (:data:`POINTS`: a sync issued,
a reply taken, telemetry encoded) through the module-level :data:`tracer`,
None by default (every flight node), so a point costs one module attribute
load and an ``is None`` test::

    tr = trace.tracer
    if tr is not None:
        tr.mark("cn.encoded", i)

Contract: :func:`install` puts a tracer in (any object with
:meth:`Tracer.mark`, called on whichever thread reaches the point, loop
thread or zenoh's; it must return at once, never block, never raise);
:func:`uninstall` takes it out. The supplied :class:`Ring` records
``(name, n, v, t_ns)`` into preallocated arrays, overwriting the oldest
record when full: nothing grows per record.

Every point, where and on which thread: docs/testing.md#trace-points.
"""

from __future__ import annotations

import itertools
import time
from array import array
from collections.abc import Callable
from typing import Protocol

__all__ = ["POINTS", "Ring", "Tracer", "install", "tracer", "uninstall"]

POINTS = (
    "cn.encode",
    "cn.encoded",
    "cn.sealed",
    "sync.issued",
    "sync.sent",
    "sync.back",
    "sync.shm",
    "sync.queued",
    "sync.taken",
    "cn.opened",
    "cn.decoded",
    "cn.applied",
    "tm.encode",
    "tm.encoded",
    "tm.sealed",
    "tm.put",
    "tm.sent",
    "dn.arrive",
    "dn.admitted",
    "dn.serve",
    "dn.opened",
    "dn.decoded",
    "dn.encoded",
    "dn.sealed",
    "dn.replied",
    "dn.apply",
    "dn.applied",
)
"""Every trace point's name (module doc), in the order an exchange reaches them."""


class Tracer(Protocol):
    """What :func:`install` takes."""

    def mark(self, name: str, n: int = 0, v: int = 0) -> None:
        """Point ``name`` reached (one of :data:`POINTS`), with its index
        ``n`` and value ``v`` (module doc). Any thread; returns at once,
        never blocks, never raises."""


tracer: Tracer | None = None
"""The installed tracer, or None (the default: no tracing)."""


def install(t: Tracer) -> None:
    """Make ``t`` the process's tracer (replacing any). Points reached from
    now on call ``t.mark``."""
    global tracer
    tracer = t


def uninstall() -> None:
    """No tracer: every point is one ``is None`` test again."""
    global tracer
    tracer = None


class Ring:
    """A :class:`Tracer` keeping the last ``capacity`` records in preallocated
    arrays (``clock``: ``CLOCK_MONOTONIC`` ns by default). Any thread: each
    mark claims its own slot (``next`` on an :func:`itertools.count`, atomic
    under the GIL), so marks from the loop's and zenoh's threads never share
    one; a record read while it is being written may be half of it, so
    :meth:`records` is for after the run."""

    def __init__(
        self, capacity: int = 1 << 16, clock: Callable[[], int] = time.monotonic_ns
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, not {capacity}")
        self.capacity = capacity
        self._names: list[str] = [""] * capacity
        self._n = array("q", bytes(8 * capacity))
        self._v = array("q", bytes(8 * capacity))
        self._t = array("q", bytes(8 * capacity))
        self._clock = clock
        self._seq = itertools.count()
        self.count = 0
        """Records made (more than ``capacity``: the oldest were overwritten)."""

    def mark(self, name: str, n: int = 0, v: int = 0) -> None:
        t = self._clock()
        j = next(self._seq)
        k = j % self.capacity
        self._t[k] = t
        self._names[k] = name
        self._n[k] = n
        self._v[k] = v
        if j >= self.count:
            self.count = j + 1

    def records(self) -> list[tuple[str, int, int, int]]:
        """The kept records, oldest first: ``(name, n, v, t_ns)``. Allocates
        (after a run, not in a hot path)."""
        c, cap = self.count, self.capacity
        out = []
        for j in range(max(0, c - cap), c):
            k = j % cap
            out.append((self._names[k], self._n[k], self._v[k], self._t[k]))
        return out
