"""The serial board protocol, version 1: framing, CRC and message layouts.

``docs/serial-protocol.md`` is the specification (byte by byte, with a worked
example); this module is its Python implementation, shared by the host
(:class:`~zplatform.boards.serialboard.SerialBoard`) and the simulated device
(:mod:`zplatform.boards.serial_sim`). ``firmware/serial_board/serial_board.c``
is the C reference of the device side.

A frame on the wire is ``COBS(body) 0x00`` where ``body`` is::

    version:u8  type:u8  seq:u16le  payload[...]  crc:u16le

and ``crc`` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection,
no final xor) over ``version .. payload``.

Encoding (:func:`encode_into`) writes into a caller's preallocated buffer
and allocates nothing but Python ints; decoding (:class:`Deframer`) runs on
the I/O thread and may allocate.
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Callable

__all__ = [
    "ERR_BAD_CRC",
    "ERR_BAD_LENGTH",
    "ERR_BAD_TYPE",
    "ERR_BAD_VERSION",
    "ERR_NOT_READY",
    "MAX_ANALOG",
    "MAX_BODY",
    "MAX_DIGITAL",
    "MAX_WIRE",
    "MSG_ERROR",
    "MSG_HELLO",
    "MSG_HELLO_ACK",
    "MSG_INPUTS",
    "MSG_READ",
    "MSG_WRITE",
    "VERSION",
    "Deframer",
    "FrameError",
    "cobs_decode",
    "cobs_encode_into",
    "crc16",
    "encode_into",
    "parse_body",
]

VERSION = 1

# Message types. Host -> device below 0x80, device -> host from 0x80 (0x7F is
# ERROR, from the device, kept out of the reply range so a host can tell an
# error from a reply by type alone).
MSG_HELLO = 0x01  # payload: empty
MSG_WRITE = 0x02  # payload: u64 digital outputs, A x f32 volts
MSG_READ = 0x03  # payload: empty
MSG_ERROR = 0x7F  # payload: u8 code, u8 type of the offending frame
MSG_HELLO_ACK = 0x81  # payload: u8 digital pins D, u8 analog pins A, u16 watchdog ms
MSG_INPUTS = 0x82  # payload: u64 digital levels, A x f32 volts

ERR_BAD_CRC = 1
ERR_BAD_VERSION = 2
ERR_BAD_TYPE = 3
ERR_BAD_LENGTH = 4
ERR_NOT_READY = 5

MAX_DIGITAL = 64  # one u64 bitmask
MAX_ANALOG = 16
HEADER = struct.Struct("<BBH")
CRC = struct.Struct("<H")
MAX_BODY = HEADER.size + 8 + 4 * MAX_ANALOG + CRC.size  # 78
# COBS adds one byte per 254 (and one at the start), plus the 0x00 delimiter.
MAX_WIRE = MAX_BODY + MAX_BODY // 254 + 2


class FrameError(ValueError):
    """Bytes between two delimiters that are not a valid frame body."""


def crc16(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``crc16(b"123456789") == 0x29B1``).

    ``binascii.crc_hqx`` is this CRC (the XMODEM polynomial, unreflected) with
    the initial value as argument, computed in C.
    """
    return binascii.crc_hqx(data, crc)


def cobs_encode_into(src: bytearray, n: int, dst: bytearray) -> int:
    """COBS-encode ``src[:n]`` into ``dst`` followed by one 0x00; return the length.

    ``dst`` must hold ``n + n // 254 + 2`` bytes. Allocates nothing.
    """
    code_at = 0
    code = 1
    out = 1
    for i in range(n):
        b = src[i]
        if b == 0:
            dst[code_at] = code
            code_at = out
            out += 1
            code = 1
        else:
            dst[out] = b
            out += 1
            code += 1
            if code == 0xFF:
                dst[code_at] = code
                code_at = out
                out += 1
                code = 1
    dst[code_at] = code
    dst[out] = 0
    return out + 1


def cobs_decode(src: bytes | bytearray) -> bytearray:
    """Decode one COBS block (without its 0x00 delimiter); FrameError if malformed."""
    out = bytearray()
    i = 0
    n = len(src)
    while i < n:
        code = src[i]
        if code == 0:
            raise FrameError("zero byte inside a COBS block")
        end = i + code
        if end > n:
            raise FrameError("COBS block runs past the frame end")
        chunk = src[i + 1 : end]
        if 0 in chunk:
            raise FrameError("zero byte inside a COBS block")
        out += chunk
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return out


def encode_into(
    raw: bytearray,
    dst: bytearray,
    msg_type: int,
    seq: int,
    payload_len: int,
) -> int:
    """Finish a frame whose payload the caller already packed at ``raw[4:4+payload_len]``.

    Writes the header and CRC into ``raw``, COBS-encodes it into ``dst`` with
    the trailing delimiter and returns the number of bytes of ``dst`` to send.
    ``raw`` holds at least :data:`MAX_BODY` bytes, ``dst`` :data:`MAX_WIRE`.
    """
    HEADER.pack_into(raw, 0, VERSION, msg_type, seq & 0xFFFF)
    end = HEADER.size + payload_len
    CRC.pack_into(raw, end, crc16(memoryview(raw)[:end]))
    return cobs_encode_into(raw, end + CRC.size, dst)


def parse_body(body: bytearray) -> tuple[int, int, int, bytearray]:
    """Check a decoded body; return ``(version, type, seq, payload)``.

    Raises FrameError for a body too short, too long or with a bad CRC. The
    version is returned, not checked: the caller decides what to do with a
    peer of another version (the header layout is the same in every version).
    """
    if len(body) < HEADER.size + CRC.size:
        raise FrameError(f"frame of {len(body)} bytes is shorter than header and CRC")
    if len(body) > MAX_BODY:
        raise FrameError(f"frame of {len(body)} bytes exceeds {MAX_BODY}")
    end = len(body) - CRC.size
    (want,) = CRC.unpack_from(body, end)
    got = crc16(memoryview(body)[:end])
    if got != want:
        raise FrameError(f"bad CRC {want:#06x}, computed {got:#06x}")
    version, msg_type, seq = HEADER.unpack_from(body, 0)
    return version, msg_type, seq, body[HEADER.size : end]


class Deframer:
    """Splits a byte stream into frame bodies; tolerates garbage and partial frames.

    :meth:`feed` takes whatever the port returned (any split, any garbage)
    and calls ``on_body(body)`` for every complete COBS block between two
    0x00 delimiters, or ``on_bad(reason)`` for one that does not decode or
    overflows :data:`MAX_WIRE` (then everything up to the next 0x00 is
    dropped). Empty blocks (two delimiters in a row) are ignored: a sender
    may start with a 0x00 to end any partial frame the receiver holds.
    :meth:`reset` drops a partial frame (after a reconnect). Not thread-safe:
    one reader thread owns it.
    """

    def __init__(self, on_body: Callable[[bytearray], None], on_bad: Callable[[str], None]) -> None:
        self._buf = bytearray()
        self._overflow = False
        self._on_body = on_body
        self._on_bad = on_bad

    def reset(self) -> None:
        self._buf.clear()
        self._overflow = False

    def feed(self, data: bytes | bytearray) -> None:
        start = 0
        n = len(data)
        while start < n:
            z = data.find(0, start)
            if z < 0:
                self._append(data, start, n)
                return
            self._append(data, start, z)
            start = z + 1
            if self._overflow:
                self._overflow = False
                self._buf.clear()
                continue
            if not self._buf:
                continue
            block = self._buf
            self._buf = bytearray()
            try:
                body = cobs_decode(block)
            except FrameError as exc:
                self._on_bad(str(exc))
                continue
            self._on_body(body)

    def _append(self, data: bytes | bytearray, start: int, end: int) -> None:
        if self._overflow or start == end:
            return
        if len(self._buf) + (end - start) > MAX_WIRE:
            self._overflow = True
            self._buf.clear()
            self._on_bad(f"no delimiter within {MAX_WIRE} bytes")
            return
        self._buf += data[start:end]
