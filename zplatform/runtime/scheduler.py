"""Periodic loops and real-time set-up (the thesis, ch. 4.12, made Pythonic).

Holds :class:`PeriodicLoop` (a step function on absolute deadlines:
deadline *k* is ``start_ns + k * period_ns``, so the loop never drifts),
:func:`setup_realtime` (SCHED_FIFO, CPU affinity and locked memory for the
*calling thread*, with a graceful fallback, :class:`RealtimeStatus`) and
:class:`GcGuard` (the cyclic garbage collector kept out of the loop). Rate
groups are :mod:`zplatform.control.rategroups` (sans-IO, apart from this OS-facing module).

Contract: :meth:`PeriodicLoop.run` blocks the calling thread until the step
returns ``False``, ``max_loops`` steps ran, :meth:`PeriodicLoop.stop` is
called (from any thread or a signal handler) or the step or a hook raises
(the exception propagates unchanged). On overrun it skips the passed periods,
never bursts, and calls ``on_overrun``; ``k`` is a period index. Inside the
loop it allocates no containers, formats no strings and logs nothing;
:meth:`~PeriodicLoop.stats` and :meth:`~PeriodicLoop.lateness_ns` may be read
from any thread (without a lock: fields may be one loop apart).

Deadlines, the spin wait, the skip policy: docs/architecture.md#drivers.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from types import TracebackType

import msgspec
import numpy as np
import numpy.typing as npt

from zplatform.errors import SchedulerError

from ..control.rategroups import check_int

__all__ = [
    "GcGuard",
    "LoopStats",
    "PeriodicLoop",
    "RealtimeStatus",
    "setup_realtime",
]

_log = logging.getLogger("zplatform.scheduler")

# --------------------------------------------------------------------------- periodic loop


class LoopStats(msgspec.Struct, frozen=True, gc=False):
    """A frozen snapshot of a :class:`PeriodicLoop`'s counters.

    The counters cover the current run, or the last one once it has returned.
    """

    period_ns: int
    """The loop's period."""
    loops: int
    """Steps run."""
    overruns: int
    """Steps that ended past the next deadline."""
    skipped_periods: int
    """Periods whose step was never run because an overrun had passed their deadline."""
    max_lateness_ns: int
    """Largest start lateness (step start time minus its deadline) seen."""
    max_overrun_ns: int
    """Largest overrun lateness (step end time minus the next deadline) seen; 0 if none."""
    recorded: int
    """Start latenesses held in the ring (what :meth:`PeriodicLoop.lateness_ns` returns)."""
    running: bool
    """Whether a run is in progress."""


class PeriodicLoop:
    """Run a step function every ``period_ns`` on absolute deadlines.

    ``clock`` returns integer nanoseconds on a monotonic time base and
    ``sleep`` sleeps for float seconds; both default to the real ones and are
    injectable so tests can drive the loop with a fake clock. ``spin_ns`` is
    how long before each deadline the loop stops sleeping and busy-waits on
    ``clock`` (0 disables spinning). ``on_overrun(k, lateness_ns)`` is called
    when step ``k`` ends past deadline ``k+1``; ``slack_hook(slack_ns)`` is
    called after each step that ended in time, with the ns left until the next
    deadline (plug :meth:`GcGuard.on_slack` in here). ``record`` sets how many
    of the latest start latenesses are kept for :meth:`lateness_ns`
    (0 = off); the ring is allocated here, once.

    Raises :class:`SchedulerError` for a period that is not a positive int, a
    negative ``spin_ns`` or ``record``, or hooks that are not callable.
    """

    def __init__(
        self,
        period_ns: int,
        *,
        clock: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], None] = time.sleep,
        spin_ns: int = 200_000,
        on_overrun: Callable[[int, int], None] | None = None,
        slack_hook: Callable[[int], None] | None = None,
        record: int = 0,
    ) -> None:
        self._period_ns = check_int("period_ns", period_ns, minimum=1)
        self._spin_ns = check_int("spin_ns", spin_ns, minimum=0)
        record = check_int("record", record, minimum=0)
        if not callable(clock):
            raise SchedulerError(f"clock must be callable, got {clock!r}")
        if not callable(sleep):
            raise SchedulerError(f"sleep must be callable, got {sleep!r}")
        if on_overrun is not None and not callable(on_overrun):
            raise SchedulerError(f"on_overrun must be callable or None, got {on_overrun!r}")
        if slack_hook is not None and not callable(slack_hook):
            raise SchedulerError(f"slack_hook must be callable or None, got {slack_hook!r}")
        self._clock = clock
        self._sleep = sleep
        self._on_overrun = on_overrun
        self._slack_hook = slack_hook
        # The ring of start latenesses: preallocated, written in place, never resized.
        self._ring: npt.NDArray[np.int64] = np.zeros(record, dtype=np.int64)
        self._ring_pos = 0  # next slot to write
        self._ring_count = 0  # samples written this run (may exceed the capacity)
        self._run_lock = threading.Lock()
        self._stop_requested = False
        self._running = False
        self._loops = 0
        self._overruns = 0
        self._skipped = 0
        self._max_lateness = 0
        self._max_overrun = 0

    @property
    def period_ns(self) -> int:
        """The loop's period in nanoseconds."""
        return self._period_ns

    @property
    def record_capacity(self) -> int:
        """How many start latenesses the ring keeps (0 = recording off)."""
        return int(self._ring.shape[0])

    def stop(self) -> None:
        """Ask the loop to end after the step in progress.

        Thread-safe and safe from a signal handler: it only sets a flag. A
        stop requested while no run is in progress makes the next ``run``
        return before its first step; each ``run`` clears the request when it
        returns.
        """
        self._stop_requested = True

    def stats(self) -> LoopStats:
        """Return a frozen snapshot of the counters (callable from any thread)."""
        return LoopStats(
            period_ns=self._period_ns,
            loops=self._loops,
            overruns=self._overruns,
            skipped_periods=self._skipped,
            max_lateness_ns=self._max_lateness,
            max_overrun_ns=self._max_overrun,
            recorded=min(self._ring_count, self._ring.shape[0]),
            running=self._running,
        )

    def lateness_ns(self) -> npt.NDArray[np.int64]:
        """Return a copy of the recorded start latenesses, oldest first.

        At most ``record`` samples (the latest ones); empty when recording is
        off. Each sample is the time the step was called minus its deadline.
        """
        capacity = self._ring.shape[0]
        count = self._ring_count
        pos = self._ring_pos
        if count <= capacity:
            return self._ring[:count].copy()
        return np.concatenate((self._ring[pos:], self._ring[:pos]))

    def run(
        self,
        step: Callable[[int, int], bool | None],
        *,
        max_loops: int | None = None,
        start_ns: int | None = None,
    ) -> LoopStats:
        """Call ``step(k, deadline_ns)`` at each deadline until told to stop; block meanwhile.

        Deadline ``k`` is ``start_ns + k * period_ns``; ``start_ns`` defaults
        to the clock at entry, so step 0 runs at once. Given a ``start_ns`` in
        the past (a shared epoch, say), the loop joins at the first deadline
        not yet passed, with that deadline's ``k``; those earlier periods are
        not counted as skipped. The loop ends when the step returns ``False``
        (``None`` and ``True`` continue), after ``max_loops`` steps, or after
        :meth:`stop`. Overruns are skipped, not caught up (module docstring).

        Returns the final statistics. The counters and the lateness ring are
        reset when the run starts. Raises :class:`SchedulerError` for a
        negative ``max_loops`` or if this loop is already running; whatever
        the step or a hook raises propagates.
        """
        if max_loops is not None:
            check_int("max_loops", max_loops, minimum=0)
        if start_ns is not None and (isinstance(start_ns, bool) or not isinstance(start_ns, int)):
            raise SchedulerError(f"start_ns must be an int or None, got {start_ns!r}")
        if not callable(step):
            raise SchedulerError(f"step must be callable, got {step!r}")
        if not self._run_lock.acquire(blocking=False):
            raise SchedulerError("PeriodicLoop.run() is already in progress on this loop")
        try:
            self._loops = 0
            self._overruns = 0
            self._skipped = 0
            self._max_lateness = 0
            self._max_overrun = 0
            self._ring_pos = 0
            self._ring_count = 0
            self._running = True
            self._run(step, -1 if max_loops is None else max_loops, start_ns)
        finally:
            self._running = False
            self._stop_requested = False
            self._run_lock.release()
        return self.stats()

    def _run(
        self, step: Callable[[int, int], bool | None], max_loops: int, start: int | None
    ) -> None:
        # The hot loop. Everything it touches is bound to a local first; the
        # only attribute reads per loop are the stop flag (it must be seen
        # across threads) and the counter stores that make stats() live.
        period = self._period_ns
        spin = self._spin_ns
        clock = self._clock
        sleep = self._sleep
        on_overrun = self._on_overrun
        slack_hook = self._slack_hook
        ring = self._ring
        capacity = ring.shape[0]
        pos = 0
        count = 0
        loops = 0
        max_lateness = 0

        now = clock()
        if start is None:
            start = now
            k = 0
        elif now <= start:
            k = 0
        else:
            # Join at the first deadline not yet passed: ceil((now - start) / period).
            k = -((start - now) // period)

        while loops != max_loops:
            if self._stop_requested:
                return
            deadline = start + k * period
            # Wait: sleep until spin ns before the deadline, then busy-wait the rest.
            # The loop also covers a sleep that returns early.
            now = clock()
            while now < deadline:
                if deadline - now > spin:
                    sleep((deadline - now - spin) * 1e-9)
                now = clock()
            if self._stop_requested:
                return

            lateness = now - deadline
            if lateness > max_lateness:
                max_lateness = lateness
                self._max_lateness = lateness
            if capacity:
                ring[pos] = lateness
                pos += 1
                if pos == capacity:
                    pos = 0
                count += 1
                self._ring_pos = pos
                self._ring_count = count

            result = step(k, deadline)
            loops += 1
            self._loops = loops
            if result is False:
                return

            end = clock()
            next_deadline = deadline + period
            if end > next_deadline:
                # Overrun: skip to the first deadline not before `end` (module docstring).
                overrun = end - next_deadline
                next_k = -((start - end) // period)  # ceil((end - start) / period)
                self._overruns += 1
                self._skipped += next_k - k - 1
                if overrun > self._max_overrun:
                    self._max_overrun = overrun
                if on_overrun is not None:
                    on_overrun(k, overrun)
                k = next_k
            else:
                k += 1
                if slack_hook is not None:
                    slack_hook(next_deadline - end)


# --------------------------------------------------------------------------- real-time set-up


class RealtimeStatus(msgspec.Struct, frozen=True):
    """What :func:`setup_realtime` obtained.

    ``priority`` is the SCHED_FIFO priority in effect (``None`` unless
    ``fifo``); ``cpu_affinity`` is the calling thread's CPU set after set-up
    (``None`` where the platform cannot tell); ``notes`` holds one line per
    step that fell back, with the reason.
    """

    fifo: bool
    priority: int | None
    cpu_affinity: tuple[int, ...] | None
    memory_locked: bool
    notes: tuple[str, ...]


_MCL_CURRENT = 1
_MCL_FUTURE = 2


def _mlockall() -> None:
    """Lock current and future pages in RAM; raise ``OSError`` if refused or unsupported."""
    name = ctypes.util.find_library("c")
    if name is None:
        raise OSError("libc not found")
    libc = ctypes.CDLL(name, use_errno=True)
    mlockall = getattr(libc, "mlockall", None)
    if mlockall is None:
        raise OSError("mlockall not available in libc")
    if mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{type(exc).__name__}: {exc.strerror}"
    return f"{type(exc).__name__}: {exc}"


def setup_realtime(
    *,
    priority: int | None = None,
    cpu: int | Iterable[int] | None = None,
    lock_memory: bool = False,
) -> RealtimeStatus:
    """Give the calling thread real-time scheduling, where the system allows it.

    Each requested step is tried in turn: SCHED_FIFO at ``priority`` (the
    thesis runs the loop thread at 2-12, below its init thread and the IRQ
    threads), CPU affinity to ``cpu`` (one CPU or several), and, with
    ``lock_memory``, ``mlockall(MCL_CURRENT | MCL_FUTURE)``. A step the
    process is not permitted to take, or that the platform lacks, is recorded
    in :attr:`RealtimeStatus.notes` with the reason, and the others still
    run; if any step fell back, one warning naming them all is logged on
    ``zplatform.runtime.scheduler``. It never raises for lack of permission.

    Raises :class:`SchedulerError` only for misuse: a priority outside the
    SCHED_FIFO range, or a negative or empty CPU set. The IRQ-thread
    priorities of thesis 4.12.1 are system configuration, not done here.
    With ``MCL_FUTURE``, later allocations beyond ``RLIMIT_MEMLOCK`` fail, so
    lock memory only in a process sized for it.
    """
    notes: list[str] = []
    fifo = False
    fifo_priority: int | None = None
    memory_locked = False

    cpus: tuple[int, ...] | None = None
    if cpu is not None:
        cpus = (cpu,) if isinstance(cpu, int) else tuple(cpu)
        if not cpus:
            raise SchedulerError("cpu must name at least one CPU")
        for c in cpus:
            check_int("cpu", c, minimum=0)

    if priority is not None:
        check_int("priority", priority, minimum=1)
        setscheduler = getattr(os, "sched_setscheduler", None)
        policy = getattr(os, "SCHED_FIFO", None)
        if setscheduler is None or policy is None:
            notes.append("SCHED_FIFO: not supported on this platform")
        else:
            lo = os.sched_get_priority_min(policy)
            hi = os.sched_get_priority_max(policy)
            if not lo <= priority <= hi:
                raise SchedulerError(f"SCHED_FIFO priority must be in [{lo}, {hi}], got {priority}")
            try:
                setscheduler(0, policy, os.sched_param(priority))
            except OSError as exc:
                notes.append(f"SCHED_FIFO priority {priority}: {_reason(exc)}")
            else:
                fifo = True
                fifo_priority = priority

    if cpus is not None:
        setaffinity = getattr(os, "sched_setaffinity", None)
        if setaffinity is None:
            notes.append("CPU affinity: not supported on this platform")
        else:
            try:
                setaffinity(0, cpus)
            except OSError as exc:
                notes.append(f"CPU affinity {list(cpus)}: {_reason(exc)}")

    if lock_memory:
        try:
            _mlockall()
        except OSError as exc:
            notes.append(f"mlockall: {_reason(exc)}")
        else:
            memory_locked = True

    affinity: tuple[int, ...] | None = None
    getaffinity = getattr(os, "sched_getaffinity", None)
    if getaffinity is not None:
        try:
            affinity = tuple(sorted(getaffinity(0)))
        except OSError:
            affinity = None

    if notes:
        _log.warning("real-time set-up fell back: %s", "; ".join(notes))
    return RealtimeStatus(
        fifo=fifo,
        priority=fifo_priority,
        cpu_affinity=affinity,
        memory_locked=memory_locked,
        notes=tuple(notes),
    )


# --------------------------------------------------------------------------- garbage collector


# Python's default generation-0 threshold, read once at import.
_GEN0_TRIGGER = max(1, gc.get_threshold()[0])


class GcGuard:
    """Keep the cyclic garbage collector out of the loop.

    :meth:`freeze_after_startup` (call it once the node is built, before the
    loop) collects everything, moves the survivors to the permanent
    generation with ``gc.freeze()`` so collections never scan them again, and
    disables automatic collection. From then on the loop collects only when
    it can afford to: pass :meth:`on_slack` as the loop's ``slack_hook``, and
    generation 0 is collected after any step that left at least
    ``threshold_ns`` before the next deadline. :meth:`restore` undoes the
    freeze and puts automatic collection back as it was.

    Only generation 0 is ever collected in the loop: a cycle that becomes
    garbage after surviving one young collection waits for :meth:`restore`
    or an explicit full ``gc.collect()`` at a quiet time. Reference counting
    still frees all acyclic garbage at once, so a loop that allocates no
    cycles loses nothing. Usable as a context manager (freeze on entry,
    restore on exit).
    """

    def __init__(self, threshold_ns: int = 1_000_000) -> None:
        self.threshold_ns = check_int("threshold_ns", threshold_ns, minimum=0)
        self.collections = 0
        """Generation-0 collections run by :meth:`collect_in_slack`."""
        self._was_enabled: bool | None = None

    @property
    def frozen(self) -> bool:
        """Whether :meth:`freeze_after_startup` is in effect."""
        return self._was_enabled is not None

    def freeze_after_startup(self) -> None:
        """Collect all generations, freeze the survivors, disable automatic collection."""
        if self._was_enabled is None:
            self._was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()

    def collect_in_slack(self, budget_ns_left: int, threshold_ns: int) -> bool:
        """Collect generation 0 if ``budget_ns_left >= threshold_ns`` and there is
        work (as many new objects as Python's own gen-0 trigger); return whether it did.

        The count check costs ~50 ns; collecting every loop would spend tens
        of microseconds on an empty generation.
        """
        if budget_ns_left >= threshold_ns and gc.get_count()[0] >= _GEN0_TRIGGER:
            gc.collect(0)
            self.collections += 1
            return True
        return False

    def on_slack(self, slack_ns: int) -> None:
        """The :class:`PeriodicLoop` ``slack_hook``: collect with this guard's threshold."""
        self.collect_in_slack(slack_ns, self.threshold_ns)

    def restore(self) -> None:
        """Unfreeze and put automatic collection back as it was before the freeze.

        Enables the collector if it was enabled then (or if no freeze was done).
        """
        gc.unfreeze()
        if self._was_enabled is None or self._was_enabled:
            gc.enable()
        self._was_enabled = None

    def __enter__(self) -> GcGuard:
        self.freeze_after_startup()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.restore()
