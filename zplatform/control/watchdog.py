"""The watchdog plug-in: a node's loop strokes a watchdog while its threads are alive.

A node whose mission entry has ``watchdog:``
(:class:`~zplatform.config.WatchdogConfig`) strokes, from its loop thread,
every ``interval_ms``: ``kind: systemd`` (sd_notify ``WATCHDOG=1`` to
``$NOTIFY_SOCKET``; ``READY=1`` when the loop starts, ``STOPPING=1`` on a clean
stop) or ``kind: device`` (a byte to ``/dev/watchdog``; ``V``, the magic close,
on a clean stop). Each stroke first asks the node's
:class:`~zplatform.core.health.Liveness` whether every watched thread checked in;
while one has not, it withholds the stroke (``watchdog_withheld``) so the
watchdog resets the host, and resumes if they recover (``watchdog_resumed``).

Contract: :class:`Watchdog` runs on the loop thread and never blocks: one
compare per loop, and every ``interval_ms`` the liveness check and one
non-blocking write (a stroke that cannot be written is counted in
:attr:`Watchdog.errors`, never waited for). A systemd watchdog without
``$NOTIFY_SOCKET`` is an error at start, not a warning.

The operator's view: docs/missions.md#health-monitors-and-the-watchdog.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import socket
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

from ..core.events import EV, EventLog
from ..core.health import THREAD_NAMES, Liveness, stalled_names
from ..errors import ConfigError, NodeError

if TYPE_CHECKING:
    from ..config import Mission, WatchdogConfig

__all__ = ["NOTIFY_SOCKET", "Watchdog", "check_config"]

log = logging.getLogger("zplatform.watchdog")

NOTIFY_SOCKET = "NOTIFY_SOCKET"
"""The environment variable systemd names its notification socket in."""
_STROKE = b"\0"
_MAGIC_CLOSE = b"V"


def check_config(mission: Mission) -> None:
    """Every node's ``watchdog`` (ConfigError with the YAML path): known
    thread names, a device path for ``kind: device``."""
    for name, node in mission.nodes.items():
        wd = node.watchdog
        if wd is None:
            continue
        w = f"$.nodes.{name}.watchdog"
        if name == "gn":
            raise ConfigError("the ground node runs no flight loop to stroke a watchdog", w)
        for i, t in enumerate(wd.threads or ()):
            if t not in THREAD_NAMES:
                raise ConfigError(
                    f"no thread named {t!r}; threads: {', '.join(THREAD_NAMES)}",
                    f"{w}.threads[{i}]",
                )
        if wd.kind == "device" and (not wd.device or "\x00" in wd.device):
            raise ConfigError("a device watchdog needs its device path", f"{w}.device")


class Watchdog:
    """One node's watchdog (module doc).

    Build, :meth:`open` before the loop (NodeError when the device cannot be
    opened or systemd's socket is not there), :meth:`stroke` from the loop
    thread every loop, :meth:`close` after it. Not thread-safe: the loop
    thread only. ``environ`` and ``clock`` are injectable for tests.
    """

    def __init__(
        self,
        cfg: WatchdogConfig,
        node: str,
        liveness: Liveness,
        events: EventLog,
        *,
        environ: Mapping[str, str] = os.environ,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.cfg = cfg
        self.node = node
        self._liveness = liveness
        self._events = events
        self._environ = environ
        self._clock = clock
        names = cfg.threads if cfg.threads is not None else THREAD_NAMES
        self._watched = sum(1 << THREAD_NAMES.index(n) for n in names)
        self._interval = round(cfg.interval_ms * 1e6)
        self._next = 0
        self._fd = -1
        self._sock: socket.socket | None = None
        self._addr: str | bytes = ""
        self.strokes = 0
        """Strokes written."""
        self.errors = 0
        """Strokes that could not be written (a full socket, a device error)."""
        self.withheld = False
        """Whether strokes are withheld now (a watched thread is stalled)."""

    @property
    def consequence(self) -> str:
        if self.cfg.kind == "systemd":
            return "systemd acts when the unit's WatchdogSec runs out"
        return f"{self.cfg.device} resets the host when its timeout runs out"

    def open(self) -> None:
        """Open the device or systemd's socket (and tell systemd READY=1).
        NodeError naming what is missing. Blocks only to open the device (a
        FIFO blocks until its reader opens it)."""
        if self.cfg.kind == "systemd":
            path = self._environ.get(NOTIFY_SOCKET, "")
            if not path:
                raise NodeError(
                    f"{self.node}: watchdog kind systemd, but ${NOTIFY_SOCKET} is not set (is "
                    "the node run by a systemd unit with WatchdogSec= and NotifyAccess=?)"
                )
            self._addr = "\0" + path[1:] if path.startswith("@") else path
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
            usec = self._environ.get("WATCHDOG_USEC", "")
            if usec.isdigit() and self._interval * 2 > int(usec) * 1000:
                log.warning(
                    "%s: watchdog interval %g ms is more than half of WatchdogSec (%g ms)",
                    self.node,
                    self.cfg.interval_ms,
                    int(usec) / 1000,
                )
            self._send(b"READY=1")
        else:
            try:
                fd = os.open(self.cfg.device, os.O_WRONLY | os.O_CLOEXEC)
            except OSError as exc:
                raise NodeError(
                    f"{self.node}: cannot open watchdog device {self.cfg.device}: {exc.strerror}"
                ) from exc
            flags = fcntl.fcntl(fd, fcntl.F_GETFL)
            fcntl.fcntl(fd, fcntl.F_SETFL, flags | os.O_NONBLOCK)
            self._fd = fd
        self._next = 0

    def stroke(self, now_ns: int, t_ns: int) -> None:
        """Stroke if ``interval_ms`` has passed since the last check and every
        watched thread is alive at ``now_ns`` (the liveness clock); else
        withhold (module doc). ``t_ns``: the loop's time, for the events."""
        if now_ns < self._next:
            return
        self._next = now_ns + self._interval
        stalled = self._liveness.stalled(now_ns) & self._watched
        if stalled:
            if not self.withheld:
                self.withheld = True
                self._events.emit(
                    EV.WATCHDOG_WITHHELD,
                    t_ns,
                    node=self.node,
                    threads=", ".join(stalled_names(stalled)),
                    consequence=self.consequence,
                )
            return
        if self.withheld:
            self.withheld = False
            self._events.emit(EV.WATCHDOG_RESUMED, t_ns, node=self.node)
        self._write(_STROKE if self._sock is None else b"WATCHDOG=1")

    def _write(self, data: bytes) -> None:
        if self._sock is not None:
            self._send(data)
            return
        try:
            os.write(self._fd, data)
            self.strokes += 1
        except OSError:
            self.errors += 1

    def _send(self, data: bytes) -> None:
        assert self._sock is not None
        try:
            self._sock.sendto(data, self._addr)
            if data == b"WATCHDOG=1":
                self.strokes += 1
        except OSError:
            self.errors += 1

    def close(self, *, clean: bool = True) -> None:
        """Release the watchdog (idempotent). ``clean``: an orderly stop, so
        disarm it (``V`` to the device, ``STOPPING=1`` to systemd); otherwise
        leave it to fire."""
        if self._sock is not None:
            if clean:
                self._send(b"STOPPING=1")
            self._sock.close()
            self._sock = None
        if self._fd >= 0:
            if clean:
                with contextlib.suppress(OSError):
                    os.write(self._fd, _MAGIC_CLOSE)
            os.close(self._fd)
            self._fd = -1
