"""A board for the health tests (not collected: no ``test_`` prefix).

``tests.integration.health_boards:HangBoard`` is a simulated board with an
I/O thread of its own that checks in (``heartbeat``, zplatform.core.health) every
20 ms, until the file ``hang_file`` names exists: then the thread hangs (it
blocks until the board is closed), as a thread stuck in a driver would.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import msgspec

from zplatform.boards import SimBoard
from zplatform.core.health import Heartbeat


class HangBoard(SimBoard):
    """A :class:`SimBoard` plus an I/O thread that hangs on request (module doc)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        hang_file: str
        digital_pins: int = 16
        analog_pins: int = 8

    def __init__(self, config: dict[str, Any] | None = None, *, where: str = "$.board") -> None:
        cfg = dict(config or {})
        self.hang_file = Path(cfg.pop("hang_file"))
        super().__init__(cfg, where=where)
        self.heartbeat = Heartbeat("board")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._io, name="board", daemon=True)
            self._thread.start()

    def _io(self) -> None:
        hb = self.heartbeat
        while not self._stop.wait(0.02):
            if self.hang_file.exists():
                self._stop.wait()  # hung: no check-in until the node closes the board
                break
            hb.beat()
        hb.idle()

    def close(self) -> None:
        super().close()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
