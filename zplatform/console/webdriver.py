"""The console process of a web session: textual's WebDriver, bound to its server.

The web server (:mod:`.web`) starts one ``zplatform ground MISSION --console``
process per browser session, with ``TEXTUAL_DRIVER`` naming
:class:`ConsoleWebDriver` and :data:`~zplatform.runtime.process.PARENT_ENV`
holding the server's PID; they talk over the console's stdin and stdout
(textual's web-driver packets).

Contract: the console ends when its session does, however it ends: the
server says quit, stdin closes, stdout breaks, or the server process dies
(SIGTERM by ``PR_SET_PDEATHSIG``, Linux); each time the app exits and its
Link closes its zenoh sessions. Whichever came first, a console that has not
exited :data:`EXIT_GRACE_S` later exits hard (``os._exit``) from a thread of
its own, since textual can spin instead of exiting. Every such end leaves one
line on stderr: why it ended, and whether it closed or was cut short.

Why each end needs its own handling (textual's driver would leave a headless
console holding the mission key): docs/architecture.md#ground.
"""

from __future__ import annotations

import asyncio
import ctypes
import os
import signal
import sys
import threading
import time
from typing import Any

from textual import messages
from textual.app import App
from textual.drivers.web_driver import WebDriver

from ..runtime.process import PARENT_ENV

__all__ = ["EXIT_GRACE_S", "ConsoleWebDriver", "die_with_parent"]

# Time a console has to exit cleanly once its session ends (Link.close waits up
# to 5 s for a command awaiting its verdict); then the process exits hard.
EXIT_GRACE_S = 10.0

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent: int) -> bool:
    """Have the kernel send this process SIGTERM when ``parent`` dies (Linux).

    Returns False when ``parent`` is already gone (this process was
    re-parented before the request took effect), else True; on systems
    without ``prctl`` it only makes that check. The signal follows the death
    of the parent *thread* that started this process: the web server starts
    consoles from its event loop's thread, which lives as long as it does.
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"prctl(PR_SET_PDEATHSIG): {os.strerror(err)}")
    return os.getppid() == parent


def _say(text: str) -> None:
    """One line on the real stderr (textual redirects ``sys.stderr`` while it runs)."""
    err = sys.__stderr__
    if err is not None:
        try:
            err.write(f"zplatform ground: {text}\n")
            err.flush()
        except (OSError, ValueError):
            pass


class ConsoleWebDriver(WebDriver):
    """textual's WebDriver for a console its web server owns (see the module doc).

    Once the console is ending, its screen writes are dropped (a broken
    stdout ends it instead of raising); end of stdin ends the console instead
    of only its input.
    """

    def __init__(self, app: App[Any], **kw: Any) -> None:
        super().__init__(app, **kw)
        # WebDriver writes every packet through this one callable (typed as
        # the functools.partial of os.write it was).
        self._write = self._send  # type: ignore[assignment]
        self._gone: str | None = None  # why the console is ending, once it is
        self._lock = threading.Lock()
        parent = os.environ.get(PARENT_ENV, "")
        if parent.isdigit() and not die_with_parent(int(parent)):
            # Nothing is open yet (the Link starts when the app mounts).
            _say(f"the web console's server (pid {parent}) is gone before it started")
            os._exit(1)

    def _send(self, data: bytes) -> None:
        if self._gone is not None:
            return
        view = memoryview(data)
        try:
            while view:  # a signal can cut a pipe write short
                view = view[os.write(self.fileno, view) :]
        except OSError as exc:
            self.end_session(f"its screen pipe broke ({exc.strerror})")

    def start_application_mode(self) -> None:
        super().start_application_mode()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):  # replacing textual's own handlers
            loop.add_signal_handler(sig, self.end_session, f"it got {signal.Signals(sig).name}")

    def on_meta(self, packet_type: str, payload: dict[str, object]) -> None:
        if packet_type == "quit":
            self.end_session("the browser session ended")
        else:
            super().on_meta(packet_type, payload)

    def run_input_thread(self) -> None:
        super().run_input_thread()
        if not self.exit_event.is_set():  # end of file, not the app's own exit
            self.end_session("its stdin closed (the server ended or died)")

    def end_session(self, why: str) -> None:
        """End the console: ask the app to exit; exit hard if it has not within the grace.

        Thread-safe and idempotent (the first reason stays); returns at once.
        """
        with self._lock:
            if self._gone is not None:
                return
            self._gone = why
        self._app.post_message(messages.ExitApp())
        threading.Thread(target=self._last_resort, name="console-exit", daemon=True).start()

    def _last_resort(self) -> None:
        # A deadline, not a wait for a peer: a clean exit ends this daemon thread first.
        time.sleep(EXIT_GRACE_S)
        _say(f"web console cut short: not closed {EXIT_GRACE_S:.0f} s after {self._gone}")
        os._exit(1)

    def close(self) -> None:
        # The app has unmounted (its Link closed its sessions) when textual calls this.
        super().close()
        if self._gone is not None:
            _say(f"web console closed: {self._gone}")
