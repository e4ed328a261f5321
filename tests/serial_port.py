"""An in-memory serial port with the protocol's simulated device behind it,
for tests of the serial board without a pty, a process or timing luck (not
collected: no ``test_`` prefix)."""

from __future__ import annotations

import errno
import threading
from typing import Any

from zplatform import SimBoard
from zplatform.boards import wire
from zplatform.boards.serial_sim import SimDevice

__all__ = ["MemoryPort"]


class MemoryPort:
    """A serial port in memory with a SimDevice behind it.

    Every WRITE/HELLO written is answered by the device into the read buffer,
    unless ``hold`` is set: then INPUTS replies wait in :attr:`held` until
    :meth:`release`. :meth:`deliver` adds bytes of the test's own (garbage,
    an ERROR frame) ahead of the next answer. ``fail_writes`` makes writes
    raise as a broken port's do while reads go on blocking quietly, as a
    half-dead USB adapter may. ``read`` blocks up to its timeout for data and
    returns early on :meth:`cancel_read`, like pyserial's."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.device = SimDevice(SimBoard({"digital_pins": 8}), watchdog_ms=0)
        self._deframer = wire.Deframer(self._on_body, lambda reason: None)
        self._buf = bytearray()
        self._cond = threading.Condition()
        self._cancelled = False
        self.closed = False
        self.hold = False
        self.held: list[bytes] = []
        self.fail_writes = False
        self.writes: list[int] = []  # seq of every WRITE the device took

    @property
    def in_waiting(self) -> int:
        with self._cond:
            return len(self._buf)

    def write(self, data: Any) -> int:
        if self.fail_writes:
            raise OSError(errno.EIO, "Input/output error")
        self._deframer.feed(bytes(data))
        return len(data)

    def _on_body(self, body: bytearray) -> None:
        _, msg_type, seq, _ = wire.parse_body(bytearray(body))
        reply = self.device.handle(body, 0)
        if msg_type == wire.MSG_WRITE:
            self.writes.append(seq)
        if self.hold and msg_type == wire.MSG_WRITE:
            self.held.append(reply)
        else:
            self.deliver(reply)

    def deliver(self, data: bytes) -> None:
        """Put ``data`` in the read buffer, as if the device had sent it (a
        test's garbage or ERROR frame goes before the next answer)."""
        with self._cond:
            self._buf += data
            self._cond.notify_all()

    def release(self) -> None:
        held, self.held = self.held, []
        for r in held:
            self.deliver(r)

    def read(self, n: int) -> bytes:
        with self._cond:
            self._cond.wait_for(lambda: self._buf or self._cancelled or self.closed, 0.05)
            if self.closed:
                raise OSError(errno.EBADF, "port closed")
            self._cancelled = False
            out = bytes(self._buf[:n])
            del self._buf[:n]
            return out

    def cancel_read(self) -> None:
        with self._cond:
            self._cancelled = True
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()
