"""A simulated serial board device behind a pseudo-terminal (protocol v1).

``python -m zplatform.boards.serial_sim --link PATH [options]`` opens a pty
pair, points the symlink ``PATH`` at its slave side (atomically, like udev's
``/dev/serial/by-id/...`` links) and then behaves as the device side of
docs/serial-protocol.md, in Python, over a :class:`~zplatform.boards.SimBoard`:
pins read back their output unless an input is injected (``--inject-digital
4=1``, ``--inject-analog 0=1.25``). It prints ``READY <slave path>`` once the
link is in place.

Contract: the device safes itself like a firmware would (no valid WRITE for
``--watchdog-ms``: every output off / 0 V). Test hooks: ``SIGUSR1`` makes the
next reply be preceded by garbage, a truncated frame and a frame with a bad
CRC (all of which the host must skip and count); killing the process is a
cable pull. :class:`SimDevice` and :func:`open_pty_link` are also what the
vehicle world process (:mod:`zplatform.sim.world_server`) uses to play a board's
firmware over a pty for hardware in the loop.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import struct
import sys
import time
import tty
from collections.abc import Callable

from . import wire
from .sim import SimBoard

__all__ = ["SimDevice", "main", "open_pty_link", "pump"]

_U64 = struct.Struct("<Q")


class SimDevice:
    """The device side of protocol v1 over a SimBoard, sans I/O.

    :meth:`handle` takes one decoded frame body and returns the reply bytes
    to send (already framed), or ``b""``. :meth:`tick` applies the watchdog.
    ``on_write(now_ns)``, when given, runs after a WRITE's outputs are
    applied and before its INPUTS are sampled (a physics step: what the
    inputs answer then follows the outputs, as on a real board).
    """

    def __init__(
        self,
        board: SimBoard,
        watchdog_ms: int = 200,
        on_write: Callable[[int], None] | None = None,
    ) -> None:
        self.board = board
        self.on_write = on_write
        self.watchdog_ns = watchdog_ms * 1_000_000
        self.ready = False
        self.last_write_ns: int | None = None
        self.safed = 0
        self.writes = 0
        self._raw = bytearray(wire.MAX_BODY)
        self._tx = bytearray(wire.MAX_WIRE)

    def _frame(self, msg_type: int, seq: int, payload: bytes) -> bytes:
        self._raw[4 : 4 + len(payload)] = payload
        n = wire.encode_into(self._raw, self._tx, msg_type, seq, len(payload))
        return bytes(self._tx[:n])

    def error(self, code: int, seq: int, bad_type: int) -> bytes:
        return self._frame(wire.MSG_ERROR, seq, bytes((code, bad_type)))

    def inputs(self, seq: int) -> bytes:
        b = self.board
        mask = 0
        for pin in range(b.digital_pins):
            if b.get_digital(pin):
                mask |= 1 << pin
        ana = [b.get_analog(p) for p in range(b.analog_pins)]
        return self._frame(
            wire.MSG_INPUTS, seq, _U64.pack(mask) + struct.pack(f"<{len(ana)}f", *ana)
        )

    def handle(self, body: bytearray, now_ns: int) -> bytes:
        try:
            version, msg_type, seq, payload = wire.parse_body(body)
        except wire.FrameError:
            # A garbled header cannot be trusted for seq or type: report with 0s.
            return self.error(wire.ERR_BAD_CRC, 0, 0)
        if version != wire.VERSION:
            return self.error(wire.ERR_BAD_VERSION, seq, msg_type)
        b = self.board
        if msg_type == wire.MSG_HELLO:
            if payload:
                return self.error(wire.ERR_BAD_LENGTH, seq, msg_type)
            self.ready = True
            ack = bytes((b.digital_pins, b.analog_pins)) + struct.pack(
                "<H", self.watchdog_ns // 1_000_000
            )
            return self._frame(wire.MSG_HELLO_ACK, seq, ack)
        if msg_type == wire.MSG_WRITE:
            if not self.ready:
                return self.error(wire.ERR_NOT_READY, seq, msg_type)
            if len(payload) != 8 + 4 * b.analog_pins:
                return self.error(wire.ERR_BAD_LENGTH, seq, msg_type)
            (mask,) = _U64.unpack_from(payload, 0)
            for pin in range(b.digital_pins):
                b.set_digital(pin, bool((mask >> pin) & 1))
            for pin, v in enumerate(struct.unpack_from(f"<{b.analog_pins}f", payload, 8)):
                b.set_analog(pin, v)
            self.last_write_ns = now_ns
            self.writes += 1
            if self.on_write is not None:
                self.on_write(now_ns)
            return self.inputs(seq)
        if msg_type == wire.MSG_READ:
            if not self.ready:
                return self.error(wire.ERR_NOT_READY, seq, msg_type)
            return self.inputs(seq)
        return self.error(wire.ERR_BAD_TYPE, seq, msg_type)

    def tick(self, now_ns: int) -> None:
        """Safe every output when the host has been silent for the watchdog period."""
        if (
            self.watchdog_ns
            and self.last_write_ns is not None
            and now_ns - self.last_write_ns > self.watchdog_ns
        ):
            b = self.board
            for pin in range(b.digital_pins):
                b.set_digital(pin, False)
            for pin in range(b.analog_pins):
                b.set_analog(pin, 0.0)
            self.last_write_ns = None
            self.safed += 1


def _garbage() -> bytes:
    """Noise a host must survive: random bytes, a truncated frame, a bad CRC."""
    raw = bytearray(wire.MAX_BODY)
    tx = bytearray(wire.MAX_WIRE)
    n = wire.encode_into(raw, tx, wire.MSG_INPUTS, 0xBEEF, 8)
    truncated = bytes(tx[: n // 2])
    bad = bytearray(raw[: 4 + 8 + 2])
    bad[-1] ^= 0x5A
    m = wire.cobs_encode_into(bad, len(bad), tx)
    return b"\x13\x37\xff\xfe garbage" + b"\x00" + truncated + b"\x00" + bytes(tx[:m])


def _pins(items: list[str], cast: type) -> dict[int, object]:
    out: dict[int, object] = {}
    for item in items:
        pin, _, value = item.partition("=")
        out[int(pin)] = cast(float(value)) if cast is bool else cast(value)
    return out


def open_pty_link(link: str) -> tuple[int, int]:
    """Open a pty pair in raw mode and point the symlink ``link`` at its slave
    side (atomically); returns ``(master, slave)`` file descriptors.

    The slave fd is meant to stay open for the process's life, so that reads
    on the master never see EIO between two host sessions.
    """
    master, slave = os.openpty()
    # Raw mode on the slave: no echo, no line discipline, before the host opens it.
    tty.setraw(slave)
    tmp = f"{link}.{os.getpid()}.tmp"
    os.symlink(os.ttyname(slave), tmp)
    os.replace(tmp, link)
    return master, slave


def pump(master: int, deframer: wire.Deframer, out: list[bytes]) -> None:
    """Read what the host sent on pty ``master`` (ready to read), feed it to
    ``deframer`` (whose callbacks append replies to ``out``), write the
    replies. A read error (the host side closed) reads as nothing."""
    try:
        data = os.read(master, 4096)
    except OSError:
        data = b""
    deframer.feed(data)
    if out:
        os.write(master, b"".join(out))
        out.clear()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m zplatform.boards.serial_sim")
    ap.add_argument("--link", required=True, help="symlink to point at the pty's slave side")
    ap.add_argument("--digital", type=int, default=8)
    ap.add_argument("--analog", type=int, default=2)
    ap.add_argument("--watchdog-ms", type=int, default=200)
    ap.add_argument("--inject-digital", action="append", default=[], metavar="PIN=0|1")
    ap.add_argument("--inject-analog", action="append", default=[], metavar="PIN=VOLTS")
    args = ap.parse_args(argv)

    board = SimBoard({"digital_pins": args.digital, "analog_pins": args.analog})
    for pin, v in _pins(args.inject_digital, bool).items():
        board.inject_digital(pin, bool(v))
    for pin, v in _pins(args.inject_analog, float).items():
        board.inject_analog(pin, float(v))  # type: ignore[arg-type]
    device = SimDevice(board, args.watchdog_ms)

    master, slave = open_pty_link(args.link)

    noise = [False]
    signal.signal(signal.SIGUSR1, lambda *_: noise.__setitem__(0, True))
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    print(f"READY {os.ttyname(slave)}", flush=True)

    out: list[bytes] = []

    def on_body(body: bytearray) -> None:
        reply = device.handle(body, time.monotonic_ns())
        if reply:
            if noise[0]:
                noise[0] = False
                out.append(_garbage())
            out.append(reply)

    def on_bad(reason: str) -> None:
        out.append(device.error(wire.ERR_BAD_CRC, 0, 0))

    deframer = wire.Deframer(on_body, on_bad)
    while True:
        ready, _, _ = select.select([master], [], [], 0.02)
        if ready:
            pump(master, deframer, out)
        device.tick(time.monotonic_ns())


if __name__ == "__main__":
    sys.exit(main())
