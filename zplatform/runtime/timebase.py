"""The node clock: ns since the epoch, monotonic and linear (thesis 4.10).

The thesis reads ``CLOCK_REALTIME`` and forbids anything from stepping it
after start. We get the same guarantee without trusting the host: the clock
is *anchored* once (one ``CLOCK_REALTIME`` reading, taken between two
``CLOCK_MONOTONIC`` readings close together, plus the offset measured by
clock sync) and then advanced only by ``CLOCK_MONOTONIC``. An NTP step, a
time-zone change or ``date -s`` after start cannot move it.

* :class:`NodeClock` is the real one. ``apply_offset`` may be called until
  :meth:`NodeClock.lock` (the loop's start); after that the clock never
  jumps (thesis 4.10.1). ``skew_ns`` is the test hook that shifts the anchor
  on purpose, to prove clock sync measures it.
* :class:`VirtualClock` is the lockstep runner's: time moves only when told.

Both refuse to start when an ``i64`` ns count would overflow within a year
(thesis 4.10.2; for ``i64`` ns that is the year 2262).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

from ..errors import TimebaseError

__all__ = ["I64_MAX", "YEAR_NS", "NodeClock", "VirtualClock", "check_overflow"]

I64_MAX = (1 << 63) - 1
YEAR_NS = 366 * 24 * 3600 * 1_000_000_000
SKEW_ENV = "ZPLATFORM_CLOCK_SKEW_NS"


def check_overflow(now_ns: int) -> None:
    """Raise TimebaseError if ``now_ns`` is negative or within a year of i64 overflow."""
    if now_ns < 0:
        raise TimebaseError(f"clock reads {now_ns} ns, before the epoch")
    if now_ns > I64_MAX - YEAR_NS:
        raise TimebaseError(
            f"clock reads {now_ns} ns: an i64 ns count would overflow within a year"
        )


ANCHOR_TRIES = 8
ANCHOR_TIGHT_NS = 50_000


def _anchor(realtime: Callable[[], int], monotonic: Callable[[], int]) -> tuple[int, int]:
    """A ``(realtime, monotonic)`` pair read at (nearly) the same instant.

    Each try reads the realtime clock between two monotonic reads; the pair
    is the realtime reading and the midpoint of the two, off by at most half
    their gap. The tightest of up to :data:`ANCHOR_TRIES` tries is kept (the
    first within :data:`ANCHOR_TIGHT_NS` ends the search): a process the
    scheduler preempts between two reads (a loaded host: 100 ms was seen)
    would otherwise anchor its clock that far from the realtime clock."""
    best: tuple[int, int, int] | None = None
    for _ in range(ANCHOR_TRIES):
        m0 = monotonic()
        r = realtime()
        m1 = monotonic()
        if best is None or m1 - m0 < best[0]:
            best = (m1 - m0, r, (m0 + m1) // 2)
        if best[0] <= ANCHOR_TIGHT_NS:
            break
    assert best is not None
    return best[1], best[2]


class NodeClock:
    """Epoch ns, advanced by the monotonic clock after one anchoring read.

    ``now_ns()`` never blocks, never goes backwards and runs at the
    monotonic clock's rate. Construction raises :class:`TimebaseError` when
    the anchor is within a year of overflow.

    ``skew_ns`` (or the ``ZPLATFORM_CLOCK_SKEW_NS`` environment variable)
    shifts the anchor: a test hook that makes a node's clock wrong on
    purpose. ``realtime``/``monotonic`` are injectable for tests.
    """

    __slots__ = ("_base", "_locked", "_mono", "_offset", "skew_ns")

    def __init__(
        self,
        *,
        skew_ns: int | None = None,
        realtime: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if skew_ns is None:
            env = os.environ.get(SKEW_ENV, "")
            try:
                skew_ns = int(env) if env else 0
            except ValueError:
                raise TimebaseError(f"{SKEW_ENV}={env!r} is not an integer") from None
        self.skew_ns = skew_ns
        self._mono = monotonic
        realtime_at, mono0 = _anchor(realtime, monotonic)
        anchor = realtime_at + skew_ns
        check_overflow(anchor)
        self._base = anchor - mono0
        self._offset = 0
        self._locked = False

    def now_ns(self) -> int:
        """Synchronised epoch time in ns (monotonic, linear)."""
        return self._base + self._mono()

    def at(self, monotonic_ns: int) -> int:
        """This clock's time at the instant ``monotonic_ns`` of the monotonic
        clock it runs on (a scheduler deadline, say). Pure arithmetic."""
        return self._base + monotonic_ns

    def monotonic_at(self, node_ns: int) -> int:
        """The monotonic clock's reading at this clock's time ``node_ns`` (the
        inverse of :meth:`at`: a schedule in node time, as a scheduler's)."""
        return node_ns - self._base

    @property
    def offset_ns(self) -> int:
        """The clock-sync correction applied so far (ns added to the anchor)."""
        return self._offset

    @property
    def locked(self) -> bool:
        return self._locked

    def apply_offset(self, offset_ns: int) -> None:
        """Shift the clock by ``offset_ns`` (clock sync's estimate), before the loop.

        Raises TimebaseError once :meth:`lock` was called (the clock must stay
        linear while loops run) or if the result would overflow.
        """
        if self._locked:
            raise TimebaseError(
                "the clock is locked: offsets are applied before the loop starts (thesis 4.10.1)"
            )
        check_overflow(self.now_ns() + offset_ns)
        self._base += offset_ns
        self._offset += offset_ns

    def lock(self) -> None:
        """Freeze the anchor; from now on the clock only advances."""
        self._locked = True


class VirtualClock:
    """A clock that moves only when :meth:`advance` or :meth:`set` says so."""

    __slots__ = ("_now",)

    def __init__(self, start_ns: int = 1_700_000_000_000_000_000) -> None:
        check_overflow(start_ns)
        self._now = start_ns

    def now_ns(self) -> int:
        return self._now

    def advance(self, ns: int) -> int:
        """Move forward by ``ns`` (>= 0); returns the new time."""
        if ns < 0:
            raise TimebaseError("a virtual clock does not go backwards")
        check_overflow(self._now + ns)  # before moving: a refused advance leaves it
        self._now += ns
        return self._now

    def set(self, now_ns: int) -> None:
        if now_ns < self._now:
            raise TimebaseError("a virtual clock does not go backwards")
        check_overflow(now_ns)
        self._now = now_ns
