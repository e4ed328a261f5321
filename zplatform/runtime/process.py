"""What every node main shares: stop signals, RT set-up, logging.

Event publishing, which the ground node shares too, is
:class:`zplatform.runtime.transport.EventPublisher`.

Kept apart from the per-node mains so each main reads as its loop.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from types import FrameType

from .scheduler import RealtimeStatus, setup_realtime

__all__ = [
    "PARENT_ENV",
    "STOP_PIPE_ENV",
    "StopFlag",
    "realtime_setup",
    "setup_logging",
]

# Set by `zplatform up` for its children: if that process goes away (even by
# SIGKILL, which it cannot forward), the node stops by itself.
PARENT_ENV = "ZPLATFORM_PARENT_PID"
STOP_PIPE_ENV = "ZPLATFORM_STOP_ON_STDIN_EOF"
"""Set to ``1`` by a supervisor that holds the write end of the node's stdin:
closing it stops the node like SIGTERM (:class:`StopFlag`)."""

log = logging.getLogger("zplatform.node")


class StopFlag:
    """Set by SIGTERM/SIGINT (or by code); the loop checks it once per loop.

    The handler only sets a flag: whatever the loop is doing finishes, the
    node then closes its session cleanly and exits 0.
    """

    def __init__(self, install: bool = True) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        if install and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._on_signal)
            signal.signal(signal.SIGINT, self._on_signal)
        if install and os.environ.get(STOP_PIPE_ENV) == "1":
            # A second way to be stopped, which no signal disposition can
            # lose: `up` closes the node's stdin as it sends SIGTERM (a DN
            # was seen, 1 run in 16 beside a CPU hog, looping on after its
            # SIGTERM until the grace ran out).
            threading.Thread(target=self._watch_stdin, name="stop-pipe", daemon=True).start()
        parent = os.environ.get(PARENT_ENV)
        if install and parent and parent.isdigit():
            threading.Thread(
                target=self._watch_parent, args=(int(parent),), name="parent-watch", daemon=True
            ).start()

    def _watch_parent(self, parent: int) -> None:
        while not self.event.wait(0.5):
            if os.getppid() != parent:
                log.warning("parent process %d is gone; stopping", parent)
                self.event.set()
                return

    def _watch_stdin(self) -> None:
        try:
            while os.read(0, 4096):
                pass  # nothing is ever written; only the end matters
        except OSError:
            pass
        if not self.event.is_set():
            log.info("the supervisor closed this node's stdin; stopping")
            self.event.set()

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self.signal = signum
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def set(self) -> None:
        self.event.set()


def realtime_setup(priority: int | None, cpu: int | None) -> RealtimeStatus:
    """Apply SCHED_FIFO/affinity when configured; falls back with a log line.

    The loop thread alone is not enough on zenoh: replies are received and
    handed over by zenoh's own threads, so every thread of the process that
    exists now (the session is open) gets the same policy.
    """
    status = setup_realtime(priority=priority, cpu=cpu)
    for note in status.notes:
        log.info("realtime: %s", note)
    if status.fifo and priority is not None:
        promoted = _promote_threads(priority)
        log.info("realtime: SCHED_FIFO %d on %d threads", priority, promoted)
    return status


_other_priority: int | None = None


def split_thread_priorities(others: int | None) -> None:
    """Benchmarks (``bench/sync_trace.py``): when :func:`realtime_setup`
    promotes a node's threads to SCHED_FIFO, every thread but the calling
    (loop) thread gets priority ``others`` instead of the loop's (None: the
    loop's, the default). Process-wide; call before the node starts."""
    global _other_priority
    _other_priority = others


def _promote_threads(priority: int) -> int:
    n = 0
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return 0
    me = threading.get_native_id()
    others = priority if _other_priority is None else _other_priority
    for tid in tids:
        prio = priority if tid == me else others
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(prio))
            n += 1
        except OSError:
            pass
    return n


LOG_LEVEL_ENV = "ZPLATFORM_LOG_LEVEL"
"""A node's log level when not ``--verbose`` (``WARNING`` under ``up --quiet``);
default ``INFO``."""


STATUS_LINE_ENV = "ZPLATFORM_STATUS_LINE"
"""Set by ``up`` when it redraws a status line in place on the terminal the
nodes share: each log line then starts by clearing that line."""

CLEAR_LINE = "\r\x1b[K"
"""Carriage return and erase-to-end-of-line: what a log line starts with
beside ``up``'s status line (:data:`STATUS_LINE_ENV`)."""


def log_format() -> str:
    """The nodes' log line format: :data:`CLEAR_LINE` first when ``up``'s
    status line shares the terminal (stderr a terminal and
    :data:`STATUS_LINE_ENV` set), so the line never runs into the status."""
    clear = CLEAR_LINE if os.environ.get(STATUS_LINE_ENV) and sys.stderr.isatty() else ""
    return clear + "%(asctime)s %(name)s %(levelname)s %(message)s"


def setup_logging(verbose: bool = False) -> None:
    """Log to stderr: DEBUG with ``verbose``, else :data:`LOG_LEVEL_ENV` or INFO."""
    level = os.environ.get(LOG_LEVEL_ENV, "INFO").upper()
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.getLevelNamesMapping().get(level, logging.INFO),
        format=log_format(),
        stream=sys.stderr,
    )
