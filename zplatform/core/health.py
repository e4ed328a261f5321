"""What a node keeps about itself: health in telemetry and thread liveness.

Holds the health elements' layout and limits (:data:`METRICS`,
:func:`health_divisor`), thread liveness (:class:`Heartbeat`, one per thread,
and :class:`Liveness`, which says as a bit mask of :data:`THREAD_NAMES` which
threads are past their deadline), and the sans-IO copy of a node's health
block into its Data Vector (:class:`HealthBlock`, :class:`HealthPort`,
:class:`HealthInput`, :class:`FakeHealth` for tests).

Contract: nothing here samples a host or blocks (the live sampler is
:mod:`zplatform.node.health`); ``Heartbeat.beat``/``idle`` are single stores,
safe from any thread; on health loops the loop copies the whole block in one
copy and emits ``thread_stalled`` / ``thread_resumed`` events from the loop,
so the events are as deterministic as the block. Without a port the elements
keep their initial values (NaN readings, zero counters), so a ``sim`` is
byte-identical run to run.

The element table, a thread's contract and the thread names:
docs/architecture.md#health.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Protocol

from ..config import HEALTH_METRICS as METRICS
from ..config import THREAD_NAMES, HealthMetric, health_elements
from ..errors import ConfigError
from .events import EV, EventLog

if TYPE_CHECKING:
    from ..config import Mission
    from .datavector import DataVector

__all__ = [
    "BLOCK_SIZE",
    "LOOP_FIELDS",
    "METRICS",
    "SAMPLED",
    "THREAD_NAMES",
    "FakeHealth",
    "HealthBlock",
    "HealthInput",
    "HealthMetric",
    "HealthPort",
    "Heartbeat",
    "Liveness",
    "check_config",
    "health_divisor",
    "health_elements",
    "stalled_names",
    "thread_deadlines_ns",
]

SAMPLED = struct.Struct("<6fI")
"""The health thread's fields, at the start of the block: cpu_pct ... health_seq."""
LOOP_FIELDS = struct.Struct("<fIfIH")
"""The loop's fields, after :data:`SAMPLED`: late_max_ms ... threads_stalled."""
BLOCK_SIZE = SAMPLED.size + LOOP_FIELDS.size
"""Bytes of one node's health block."""
_NAN = float("nan")
_METRIC_NAMES = tuple(m.name for m in METRICS)
_READINGS = _METRIC_NAMES[:6]  # the sampled readings: NaN until the first sample


def health_divisor(mission: Mission) -> int:
    """Loops per health sample: ``loop_hz / health.rate_hz``, rounded, at least 1."""
    assert mission.health is not None
    return max(1, round(mission.loop_hz / mission.health.rate_hz))


def thread_deadlines_ns(mission: Mission) -> dict[str, int]:
    """Every thread name's check-in deadline (ns): ``health.deadlines_ms`` over
    the defaults (ms): ``loop`` 1000; ``zenoh`` and ``health`` three health
    periods, at least 2000; ``clock`` 3000 (a DN's re-sync exchange may wait
    1 s for a reply); the rest 2000. A mission without ``health:`` gets the
    defaults at 2 Hz (its watchdog still uses them)."""
    cfg = mission.health
    rate = cfg.rate_hz if cfg is not None else 2.0
    slow = max(2000.0, 3000.0 / rate)
    ms = {name: 2000.0 for name in THREAD_NAMES}
    ms.update(loop=1000.0, zenoh=slow, health=slow, clock=3000.0)
    if cfg is not None:
        ms.update(cfg.deadlines_ms)
    return {name: round(v * 1e6) for name, v in ms.items()}


def stalled_names(mask: int) -> list[str]:
    """The thread names of a ``threads_stalled`` mask, in bit order (unknown
    bits as ``bit<i>``)."""
    out = []
    i = 0
    while mask:
        if mask & 1:
            out.append(THREAD_NAMES[i] if i < len(THREAD_NAMES) else f"bit{i}")
        mask >>= 1
        i += 1
    return out


def check_config(mission: Mission) -> None:
    """The ``health`` section against the mission (ConfigError with the YAML
    path): the rate at most the loop rate, deadlines only for known threads,
    limits only for known metrics, each range in order."""
    cfg = mission.health
    if cfg is None:
        return
    if cfg.rate_hz > mission.loop_hz:
        raise ConfigError(
            f"health rate {cfg.rate_hz:g} Hz is above the loop rate {mission.loop_hz:g} Hz",
            "$.health.rate_hz",
        )
    if not cfg.disk_path or "\x00" in cfg.disk_path:
        raise ConfigError("disk_path must be a non-empty directory path", "$.health.disk_path")
    for name in cfg.deadlines_ms:
        if name not in THREAD_NAMES:
            raise ConfigError(
                f"no thread named {name!r}; threads: {', '.join(THREAD_NAMES)}",
                f"$.health.deadlines_ms.{name}",
            )
    for name, lim in cfg.limits.items():
        w = f"$.health.limits.{name}"
        if name not in _METRIC_NAMES:
            raise ConfigError(
                f"no health element {name!r}; elements: {', '.join(_METRIC_NAMES)}", w
            )
        for band in ("yellow", "red"):
            lo, hi = getattr(lim, band) or (None, None)
            if lo is not None and hi is not None and lo > hi:
                raise ConfigError(f"{band} range [{lo}, {hi}] is not [lo, hi]", f"{w}.{band}")


# -- liveness ---------------------------------------------------------------------


_IDLE = -1


class Heartbeat:
    """One thread's check-in (module doc: the contract).

    :meth:`beat` stores the time (thread-safe: one attribute store), :meth:`idle`
    marks the thread as waiting for outside work. Built checked in. ``clock``
    must be the one its :class:`Liveness` reads (monotonic ns).
    """

    __slots__ = ("_clock", "_t", "name")

    def __init__(self, name: str, clock: Callable[[], int] = time.monotonic_ns) -> None:
        if name not in THREAD_NAMES:
            raise ValueError(f"no thread named {name!r}; threads: {', '.join(THREAD_NAMES)}")
        self.name = name
        self._clock = clock
        self._t = clock()

    def beat(self) -> None:
        """Check in: the thread made progress now."""
        self._t = self._clock()

    def beat_at(self, now_ns: int) -> None:
        """Check in at ``now_ns``, a time just read from this heartbeat's clock
        (a loop that has read it already saves a read)."""
        self._t = now_ns

    def idle(self) -> None:
        """The thread is about to wait for outside work (or ends): not stalled
        until it beats again."""
        self._t = _IDLE

    def age_ns(self, now_ns: int) -> int:
        """How long since the last check-in; -1 while idle."""
        t = self._t
        return -1 if t == _IDLE else now_ns - t


class Liveness:
    """A node's heartbeats and their deadlines (module doc).

    ``deadlines_ns``: each thread name's deadline (:func:`thread_deadlines_ns`).
    :meth:`add` and :meth:`remove` from the node's set-up and tear-down;
    :meth:`stalled` from any thread (it reads, never writes). Allocates
    nothing per call.
    """

    def __init__(self, deadlines_ns: Mapping[str, int]) -> None:
        self.deadlines_ns = dict(deadlines_ns)
        self._watched: tuple[tuple[Heartbeat, int, int], ...] = ()

    def add(self, hb: Heartbeat) -> Heartbeat:
        """Watch ``hb`` (its deadline by its name); returns it. ValueError for
        a second heartbeat of one name."""
        if any(h.name == hb.name for h, _, _ in self._watched):
            raise ValueError(f"thread {hb.name!r} already has a heartbeat")
        bit = 1 << THREAD_NAMES.index(hb.name)
        self._watched = (*self._watched, (hb, bit, self.deadlines_ns[hb.name]))
        return hb

    def remove(self, hb: Heartbeat) -> None:
        """Stop watching ``hb`` (its thread is gone for good)."""
        self._watched = tuple(w for w in self._watched if w[0] is not hb)

    @property
    def names(self) -> tuple[str, ...]:
        """The watched threads' names, in the order they were added."""
        return tuple(hb.name for hb, _, _ in self._watched)

    def stalled(self, now_ns: int) -> int:
        """The bit mask of watched threads not checked in within their deadline."""
        mask = 0
        for hb, bit, deadline in self._watched:
            t = hb._t
            if t != _IDLE and now_ns - t > deadline:
                mask |= bit
        return mask


# -- the block, the port, the loop's side -------------------------------------------


class HealthPort(Protocol):
    """Where a node's logic takes its health block on health loops.

    :meth:`take` is called on the loop thread, in the loop's order, only on
    health loops (``loop % health_divisor == 0``); it returns the node's
    whole block (:data:`BLOCK_SIZE` bytes, layout :data:`SAMPLED` then
    :data:`LOOP_FIELDS`), which the logic copies at once. It must not block,
    raise, or allocate beyond a few scalars.
    """

    def take(self, t_ns: int) -> bytes | bytearray | memoryview: ...


class HealthBlock:
    """Where ``node``'s health elements sit in ``dv`` (contiguous, block order)."""

    def __init__(self, dv: DataVector, node: str) -> None:
        specs = [dv.layout.element(f"{node}_{m.name}") for m in METRICS]
        self.offset = specs[0].offset
        if specs[-1].offset + specs[-1].size - self.offset != BLOCK_SIZE:
            raise AssertionError(f"{node}'s health elements are not one block")  # config bug
        self.end = self.offset + BLOCK_SIZE


class HealthInput:
    """A node logic's side of health (module doc): on health loops, copy the
    block a :class:`HealthPort` gives into the Data Vector and name the threads
    whose stalled bit changed (``thread_stalled`` / ``thread_resumed``).

    Sans-IO: everything it writes comes from the port, so a replay that feeds
    the recorded blocks reproduces it. Not thread-safe (the loop thread).
    """

    def __init__(self, mission: Mission, node: str, dv: DataVector, events: EventLog) -> None:
        self.node = node
        self.divisor = health_divisor(mission)
        self._buf = dv.buf
        block = HealthBlock(dv, node)
        self._a, self._b = block.offset, block.end
        self._stalled = dv.handle(f"{node}_threads_stalled")
        self._deadline_ms = {n: v / 1e6 for n, v in thread_deadlines_ns(mission).items()}
        self._events = events
        self._last = 0
        self.port: HealthPort | None = None

    def apply(self, block: bytes | bytearray | memoryview, t_ns: int) -> None:
        """Copy ``block`` (:data:`BLOCK_SIZE` bytes) in; event the stalled-bit changes."""
        self._buf[self._a : self._b] = block
        mask = self._stalled.get()
        if mask != self._last:
            self._changed(self._last, mask, t_ns)
            self._last = mask

    def _changed(self, old: int, new: int, t_ns: int) -> None:
        # Allocates (names, text): only when a thread's state changed.
        for name in stalled_names(new & ~old):
            self._events.emit(
                EV.THREAD_STALLED,
                t_ns,
                node=self.node,
                thread=name,
                deadline_ms=self._deadline_ms.get(name, math.nan),
            )
        for name in stalled_names(old & ~new):
            self._events.emit(EV.THREAD_RESUMED, t_ns, node=self.node, thread=name)


class FakeHealth:
    """A deterministic :class:`HealthPort` for the lockstep runner and tests:
    the values :meth:`set` gave (readings NaN, the loop's figures 0 until
    then), the threads :meth:`stall` named, and ``health_seq`` counting the
    samples taken (as a live node's would)."""

    def __init__(self, **values: float) -> None:
        self._values: dict[str, float] = dict.fromkeys(_READINGS, _NAN)
        self._loop: dict[str, float] = dict.fromkeys(_METRIC_NAMES[7:11], 0.0)
        self._stalled = 0
        self._seq = 0
        self._block = bytearray(BLOCK_SIZE)
        self.set(**values)

    def set(self, **values: float) -> None:
        """Set metrics by name (``cpu_pct=97.0``); KeyError for an unknown one."""
        for k, v in values.items():
            if k in self._values:
                self._values[k] = float(v)
            elif k in self._loop:
                self._loop[k] = float(v)
            else:
                raise KeyError(f"no health metric {k!r} (threads: stall())")

    def stall(self, *threads: str) -> None:
        """Report ``threads`` stalled from the next sample on (none: all clear)."""
        mask = 0
        for t in threads:
            mask |= 1 << THREAD_NAMES.index(t)
        self._stalled = mask

    def take(self, t_ns: int) -> bytearray:
        self._seq += 1
        v, lp = self._values, self._loop
        SAMPLED.pack_into(self._block, 0, *v.values(), self._seq)
        LOOP_FIELDS.pack_into(
            self._block,
            SAMPLED.size,
            lp["late_max_ms"],
            int(lp["overruns_recent"]),
            lp["gc_max_ms"],
            int(lp["gc_count"]),
            self._stalled,
        )
        return self._block
