"""A live node's health: the sampling thread, the zenoh probe and the loop's window.

:class:`NodeHealth` is the zenoh runtime's :class:`~zplatform.core.health.HealthPort`
(:mod:`zplatform.core.health` has the elements and the contract). It runs one
thread, ``health``, which once per health period samples the process and the
host through psutil (:class:`ResourceSampler`), latches the threads past their
deadline (and logs, once per stall, where every Python thread of the process
stands: :func:`thread_stacks`), and probes zenoh with a query nobody answers,
whose finalisation on zenoh's thread checks in for ``zenoh``.

Contract: the loop thread's calls never block: :meth:`NodeHealth.note` and
:meth:`NodeHealth.overran` are one compare or add per loop,
:meth:`NodeHealth.kick` one flag test (it lets the thread sample in the loop's
slack), and :meth:`NodeHealth.take` packs the window figures and stalled
threads into the staging block, resets the window and returns the block for
the logic's one copy. The sampling thread packs each sample in one call; it
samples on its own every two periods when the loop stops kicking.

When and how it samples, and what that costs: docs/architecture.md#health.
"""

from __future__ import annotations

import gc
import logging
import math
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import zenoh

from ..config import Mission
from ..core.health import BLOCK_SIZE, LOOP_FIELDS, SAMPLED, Heartbeat, Liveness, stalled_names
from ..runtime.queries import ask, replies
from ..runtime.transport import KeySpace

__all__ = ["NodeHealth", "ResourceSampler", "Sample", "thread_stacks"]

log = logging.getLogger("zplatform.health")

Sample = tuple[float, float, float, float, float, float]
"""``(cpu_pct, sys_cpu_pct, rss_mb, mem_free_mb, disk_free_mb, cpu_temp_c)``."""

_MIB = 1024.0 * 1024.0
_NAN = math.nan
# Chips whose readings are the CPU's (x86 coretemp/k10temp, a Raspberry Pi's
# cpu_thermal, other SoCs); without any, the hottest sensor the host has.
_CPU_CHIPS = ("coretemp", "k10temp", "zenpower", "cpu_thermal", "cpu-thermal", "soc_thermal")


def thread_stacks() -> str:
    """Where every Python thread of this process stands now: per thread its
    name, ident and stack, innermost call last (a thread running native code,
    zenoh's, shows the Python call that entered it). Takes the GIL, allocates:
    for a rare diagnostic (a stalled thread), never the loop thread's."""
    names = {t.ident: t.name for t in threading.enumerate()}
    parts = []
    for ident, frame in sys._current_frames().items():
        stack = "".join(traceback.format_stack(frame)).rstrip()
        parts.append(f"thread {names.get(ident, '(not a threading.Thread)')} ({ident}):\n{stack}")
    return "\n".join(parts)


class ResourceSampler:
    """Reads what a node's health reports about its process and host (psutil).

    :meth:`sample` blocks for the reads (a few hundred microseconds; file
    reads under ``/proc`` and ``/sys``) and never raises: a reading that
    fails is NaN. Not for the loop thread.
    """

    def __init__(self, disk_path: str) -> None:
        import psutil

        self._psutil = psutil
        self.disk_path = disk_path
        self._proc = psutil.Process()
        # cpu_percent(None) measures since the last call: prime both.
        self._proc.cpu_percent(None)
        psutil.cpu_percent(None)
        # A host without a temperature sensor does not grow one: ask once
        # (a scan of /sys/class/hwmon, the costliest read of a sample).
        self._temps: Callable[[], dict[str, list[Any]]] | None = getattr(
            psutil, "sensors_temperatures", None
        )
        if self._temps is not None and math.isnan(self._temperature()):
            self._temps = None

    def sample(self) -> Sample:
        ps = self._psutil
        try:
            cpu = float(self._proc.cpu_percent(None))
            rss = self._proc.memory_info().rss / _MIB
        except (ps.Error, OSError):
            cpu = rss = _NAN
        try:
            sys_cpu = float(ps.cpu_percent(None))
            avail = ps.virtual_memory().available / _MIB
        except OSError:
            sys_cpu = avail = _NAN
        try:
            disk = ps.disk_usage(self.disk_path).free / _MIB
        except OSError:
            disk = _NAN
        return (cpu, sys_cpu, rss, avail, disk, self._temperature())

    def _temperature(self) -> float:
        if self._temps is None:
            return _NAN
        try:
            chips = self._temps()
        except (OSError, RuntimeError):
            return _NAN
        cpu = [e.current for name, es in chips.items() if name in _CPU_CHIPS for e in es]
        every = cpu or [e.current for es in chips.values() for e in es]
        return float(max(every)) if every else _NAN


class NodeHealth:
    """A live node's :class:`~zplatform.core.health.HealthPort` (module doc).

    Construction adds the ``health`` heartbeat (and ``zenoh``, with a
    ``session``) to ``liveness`` and builds the sampler; :meth:`start` starts
    the thread and the gc hook; :meth:`close` stops them (idempotent).
    :meth:`note`, :meth:`overran` and :meth:`take` are the loop thread's
    (cheap, allocation-free but for :meth:`take`'s few scalars); the rest
    the owner's. ``sampler`` and ``clock`` are injectable for tests.
    """

    def __init__(
        self,
        mission: Mission,
        node: str,
        liveness: Liveness,
        *,
        session: zenoh.Session | None = None,
        sampler: Callable[[], Sample] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        cfg = mission.health
        if cfg is None:
            raise ValueError("the mission has no health: section")
        self.node = node
        self._period_ns = round(1e9 / cfg.rate_hz)
        self._clock = clock
        self._liveness = liveness
        self.heartbeat = liveness.add(Heartbeat("health", clock))
        self._sample = sampler or ResourceSampler(cfg.disk_path).sample
        self._staging = bytearray(BLOCK_SIZE)
        self._view = memoryview(self._staging)
        self.samples = 0
        """Samples taken (``<node>_health_seq``)."""
        self.sample_ns = 0
        """How long the last sample took (ns), for the benchmark."""
        self._latched = 0
        self._told = 0  # the stalled threads whose stall was logged with the stacks
        # The loop's window (loop thread), gc's (whichever thread collects).
        self._late_max = 0
        self._overruns = 0
        self._gc_max = 0
        self._gc_count = 0
        self._gc_t0 = 0
        self._stop = threading.Event()
        self._go = threading.Event()
        self._due = False
        self._thread: threading.Thread | None = None
        self._sampler_ident = -1
        self._probe: Any = None
        self._held: Any = None
        self.zenoh_heartbeat: Heartbeat | None = None
        if session is not None:
            keys = KeySpace(mission.vehicle)
            self._session = session
            self._probe_key = keys.health_probe(node)
            self.zenoh_heartbeat = liveness.add(Heartbeat("zenoh", clock))
            # Session-local: no peer learns of it or routes a query to it.
            self._probe = session.declare_queryable(
                self._probe_key,
                zenoh.handlers.Callback(self._hold, indirect=False),
                allowed_origin=zenoh.Locality.SESSION_LOCAL,
            )
            self._probe_cb = replies(_ignore, self._probe_done)
            self._probe_timeout_s = min(0.1, self._period_ns / 4e9)
        SAMPLED.pack_into(self._staging, 0, _NAN, _NAN, _NAN, _NAN, _NAN, _NAN, 0)

    # -- the owner's ------------------------------------------------------------
    def start(self) -> None:
        """Start the health thread and the gc hook (idempotent)."""
        if self._thread is not None:
            return
        gc.callbacks.append(self._on_gc)
        # Fresh from now: the node may have spent seconds starting up.
        self.heartbeat.beat()
        if self.zenoh_heartbeat is not None:
            self.zenoh_heartbeat.beat()
        self._thread = threading.Thread(target=self._run, name="health", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread, remove the gc hook, undeclare the probe (idempotent)."""
        self._stop.set()
        self._go.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        if self._probe is not None:
            self._probe.undeclare()
            self._probe = None
            self._held = None
        self._liveness.remove(self.heartbeat)
        if self.zenoh_heartbeat is not None:
            self._liveness.remove(self.zenoh_heartbeat)

    # -- the loop thread's -------------------------------------------------------
    def note(self, lateness_ns: int) -> None:
        """This loop started ``lateness_ns`` after its scheduled start."""
        if lateness_ns > self._late_max:
            self._late_max = lateness_ns

    def overran(self, n: int = 1) -> None:
        """``n`` loops overran their period."""
        self._overruns += n

    def take(self, t_ns: int) -> memoryview:
        """Pack the window (lateness, overruns, gc, stalled threads) into the
        block, start a new window, return the block (the HealthPort call)."""
        now = self._clock()
        stalled = self._latched | self._liveness.stalled(now)
        self._latched = 0
        LOOP_FIELDS.pack_into(
            self._staging,
            SAMPLED.size,
            self._late_max / 1e6,
            min(self._overruns, 0xFFFF_FFFF),
            self._gc_max / 1e6,
            min(self._gc_count, 0xFFFF_FFFF),
            stalled & 0xFFFF,
        )
        self._late_max = self._overruns = self._gc_max = self._gc_count = 0
        self._due = True
        return self._view

    def kick(self) -> None:
        """The loop's work is done: after a health loop, wake the sampling
        thread now, in the loop's slack (module doc). One flag test otherwise."""
        if self._due:
            self._due = False
            self._go.set()

    # -- the health thread and zenoh's ---------------------------------------------
    def _run(self) -> None:
        self._sampler_ident = threading.get_ident()
        hb = self.heartbeat
        clock = self._clock
        on_its_own = 2 * self._period_ns / 1e9  # the loop stopped kicking
        stop, go = self._stop, self._go
        while not stop.is_set():  # the first sample at once, then per kick
            hb.beat()
            t0 = clock()
            try:
                values = self._sample()
            except Exception as exc:  # a sampler bug must not end the thread
                log.warning("%s health sample failed: %s: %s", self.node, type(exc).__name__, exc)
                values = (_NAN, _NAN, _NAN, _NAN, _NAN, _NAN)
            self.samples += 1
            SAMPLED.pack_into(self._staging, 0, *values, self.samples & 0xFFFF_FFFF)
            self.sample_ns = clock() - t0
            stalled = self._liveness.stalled(clock())
            self._latched |= stalled
            if stalled & ~self._told:
                # A thread past its deadline: where it waits is what its
                # event cannot say (a lock, a peer, zenoh's call). Once per
                # stall; a thread that checks in again may be told again.
                log.warning(
                    "%s: thread(s) %s past their deadline; the process's threads now:\n%s",
                    self.node,
                    ", ".join(stalled_names(stalled & ~self._told)),
                    thread_stacks(),
                )
            self._told = stalled
            if self._probe is not None:
                try:
                    # Session-local, DROP, target ALL, a timeout: the one way
                    # zplatform asks (zplatform.runtime.queries); never blocks this thread.
                    ask(
                        self._session,
                        self._probe_key,
                        self._probe_cb,
                        timeout_s=self._probe_timeout_s,
                        local_only=True,
                    )
                except zenoh.ZError as exc:  # the session is closing
                    log.debug("%s zenoh probe not sent: %s", self.node, exc)
            go.wait(on_its_own)
            go.clear()

    def _hold(self, query: zenoh.Query) -> None:
        # Keep the newest probe unanswered, so zenoh's timer finalises it on
        # its own thread.
        self._held = query

    def _probe_done(self) -> None:
        # Only zenoh's timer counts: dropping an older probe here (the health
        # thread) finalises it too, and that proves nothing about zenoh.
        if threading.get_ident() != self._sampler_ident:
            assert self.zenoh_heartbeat is not None
            self.zenoh_heartbeat.beat()

    def _on_gc(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._gc_t0 = time.perf_counter_ns()
            return
        d = time.perf_counter_ns() - self._gc_t0
        self._gc_count += 1
        if d > self._gc_max:
            self._gc_max = d


def _ignore(reply: zenoh.Reply) -> None:
    pass  # the probe's answer is zenoh's timeout; its finalisation is the check-in
