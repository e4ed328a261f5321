"""The serial board: a microcontroller behind a serial port (pyserial).

The host side of docs/serial-protocol.md (:mod:`zplatform.boards.wire`). One
I/O thread per board owns the port: it opens it, does the HELLO handshake,
reads and deframes everything the device sends, and on any port error closes
it and reopens with exponential backoff (a USB serial adapter pulled and
plugged back in comes back under the same path). The loop thread only writes
one WRITE frame per :meth:`SerialBoard.step` and waits, at most
``reply_timeout_ms``, for the INPUTS frame with the same sequence number.

Threads: :meth:`~SerialBoard.step`, the pin methods, :meth:`~SerialBoard.safe`
and :meth:`~SerialBoard.health` belong to the loop thread; the I/O thread
hands the latest INPUTS over as one immutable tuple (an atomic reference
swap) and signals it with an Event. Under a lock both threads take briefly,
they decide whether an INPUTS answers the WRITE being waited for (an answer
to an earlier WRITE is counted late, never latched) and which port is the
link (a write failure seen by the loop takes the link down at once, and the
I/O thread reopens it; a failure on a replaced port never takes down its
successor).
"""

from __future__ import annotations

import importlib.util
import struct
import threading
import time
from typing import Annotated, Any, NoReturn

import msgspec
from msgspec import Meta

from ..core.components import decode_component_config
from ..core.health import Heartbeat
from ..errors import ConfigError
from . import wire
from .base import BoardError, BoardHealth, HealthCounters, PinCounts, check_pin

__all__ = ["SerialBoard", "SerialBoardConfig", "round_trip_ms"]


class SerialBoardConfig(msgspec.Struct, forbid_unknown_fields=True):
    """The `board:` mapping of `driver: serial`: a microcontroller on a
    serial port speaking the framed, CRC-checked protocol of
    docs/serial-protocol.md (needs the `serial` extra). The link is opened
    in the background and re-opened when lost; the loop never waits on it
    longer than `reply_timeout_ms`.
    """

    port: Annotated[
        str, Meta(description="The serial device: `/dev/serial/by-id/...`, `/dev/ttyACM0`.")
    ]
    baudrate: Annotated[
        int,
        Meta(
            ge=300,
            le=12_000_000,
            description="Line speed. USB CDC-ACM ignores it and answers within a USB frame or "
            "two; a real UART must be fast enough for `reply_timeout_ms` (checked at load: "
            "at 115200 baud a WRITE and its INPUTS alone take 2.8 ms or more).",
        ),
    ] = 921_600
    digital_pins: Annotated[
        int,
        Meta(
            ge=0,
            le=wire.MAX_DIGITAL,
            description="Digital pins the devices may use; the device must announce at least "
            "as many in its HELLO_ACK.",
        ),
    ] = 8
    analog_pins: Annotated[
        int,
        Meta(
            ge=0,
            le=wire.MAX_ANALOG,
            description="Analog pins the devices may use (announced like `digital_pins`).",
        ),
    ] = 0
    reply_timeout_ms: Annotated[
        float,
        Meta(
            gt=0,
            le=50,
            description="How long a loop's step waits for the device's INPUTS (ms); longer "
            "than the frames' time on the wire.",
        ),
    ] = 2.0
    handshake_timeout_ms: Annotated[
        float,
        Meta(gt=0, le=10_000, description="How long a HELLO waits for its HELLO_ACK (ms)."),
    ] = 500.0
    reconnect_min_ms: Annotated[
        float,
        Meta(gt=0, le=60_000, description="First wait before re-opening a lost link (ms)."),
    ] = 50.0
    reconnect_max_ms: Annotated[
        float,
        Meta(
            gt=0,
            le=60_000,
            description="Longest wait between re-open attempts (ms); the wait doubles up to it.",
        ),
    ] = 2_000.0
    safe_after: Annotated[
        int,
        Meta(
            ge=1,
            description="Consecutive failed steps (3 = 30 ms at 100 Hz, so one late reply on a "
            "loaded host does not glitch the outputs) after which the board forces the safe "
            "values on every write until the device answers again.",
        ),
    ] = 3
    exclusive: Annotated[
        bool, Meta(description="Lock the port (flock) against a second opener.")
    ] = True
    safe_digital: Annotated[
        dict[int, bool],
        Meta(description="Safe level per digital pin (others: off)."),
    ] = msgspec.field(default_factory=dict)
    safe_analog: Annotated[
        dict[int, float],
        Meta(description="Safe voltage per analog pin (others: 0 V)."),
    ] = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        wire_ms = round_trip_ms(self.baudrate, self.analog_pins)
        if self.reply_timeout_ms <= wire_ms:
            raise ValueError(
                f"reply_timeout_ms {self.reply_timeout_ms} is shorter than the {wire_ms:.2f} ms "
                f"that a WRITE and its INPUTS take on the wire at {self.baudrate} baud; "
                "raise the baud rate or the timeout"
            )
        if self.reconnect_min_ms > self.reconnect_max_ms:
            raise ValueError("reconnect_min_ms must not exceed reconnect_max_ms")
        for pin in self.safe_digital:
            if not 0 <= pin < self.digital_pins:
                raise ValueError(f"safe_digital pin {pin} out of range 0..{self.digital_pins - 1}")
        for pin in self.safe_analog:
            if not 0 <= pin < self.analog_pins:
                raise ValueError(f"safe_analog pin {pin} out of range 0..{self.analog_pins - 1}")


def round_trip_ms(baudrate: int, analog_pins: int) -> float:
    """Time on the wire of one WRITE and its INPUTS (8N1: 10 bits a byte), no stuffing.

    Each frame is COBS(4 + 8 + 4A + 2) + 0x00 = 16 + 4A bytes.
    """
    frame_bytes = 4 + 8 + 4 * analog_pins + 2 + 2
    return 2 * frame_bytes * 10 * 1000.0 / baudrate


_U64 = struct.Struct("<Q")
_HELLO_ACK = struct.Struct("<BBH")


class SerialBoard(PinCounts):
    """A board behind a serial port speaking protocol v1 (see the module docstring).

    Construction validates ``config`` (:class:`SerialBoardConfig`; ConfigError
    naming ``where``) and touches no hardware. :meth:`open` starts the I/O
    thread and returns at once; it does not wait for the device (use
    :meth:`wait_connected`). Until the handshake is done, and whenever the
    link is down, :meth:`step` raises :class:`BoardError`.

    :meth:`step` sends the outputs set since the last step (the safe values
    instead while the board is safed) in one WRITE and waits up to
    ``reply_timeout_ms`` for the device's INPUTS, which it latches for the
    ``get_*`` methods; it never blocks longer and allocates no buffers. So
    outputs set in loop *n* reach the device at the start of loop *n + 1*,
    and what a pin reads is the device's report of that moment (an output
    pin reads back its real level one loop after it was set).
    """

    def __init__(
        self,
        config: dict[str, Any] | None = None,
        *,
        where: str = "$.board",
        serial_factory: Any = None,
    ) -> None:
        cfg = decode_component_config(SerialBoardConfig, dict(config or {}), where)
        if serial_factory is None and importlib.util.find_spec("serial") is None:
            raise ConfigError(
                "driver 'serial' needs pyserial: pip install 'zplatform[serial]'",
                f"{where}.driver",
            )
        self.config = cfg
        self._factory = serial_factory
        self._n_dig = cfg.digital_pins
        self._n_ana = cfg.analog_pins
        self._timeout_s = cfg.reply_timeout_ms / 1000.0
        self._safe_mask = sum(1 << p for p, v in cfg.safe_digital.items() if v)
        self._safe_ana = [float(cfg.safe_analog.get(p, 0.0)) for p in range(wire.MAX_ANALOG)]
        # Outputs as the devices set them, and what the last INPUTS reported.
        self._dout = self._safe_mask
        self._aout = list(self._safe_ana)
        self._din = 0
        self._ain: tuple[float, ...] = (0.0,) * wire.MAX_ANALOG
        # Preallocated frame buffers of the loop thread.
        self._raw = bytearray(wire.MAX_BODY)
        self._tx = bytearray(wire.MAX_WIRE)
        self._txview = memoryview(self._tx)
        self._seq = 0
        self._faulted = False
        self.counters = HealthCounters()
        # Shared with the I/O thread; _want and _port change under _lock.
        self._lock = threading.Lock()
        self._want = -1  # seq of the WRITE awaiting its INPUTS
        self._rx: tuple[int, int, tuple[float, ...]] = (-1, 0, self._ain)
        self._reply = threading.Event()
        self._connected = threading.Event()
        self._port: Any = None  # set by the I/O thread once linked
        self._dev_analog = 0  # the device's analog pin count (fixes WRITE's length)
        self._write_struct = struct.Struct("<Q")
        self._link_error = "not connected yet"
        self._hello: tuple[int, int, int] | None = None  # (version, D, A) of HELLO_ACK
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._opened = False
        self.heartbeat = Heartbeat("board")
        """The I/O thread's check-in (zplatform.core.health): beats per read (at
        least every 50 ms), idle while it waits to reconnect."""

    # -- the Board protocol ------------------------------------------------------

    def set_digital(self, pin: int, value: bool) -> None:
        check_pin("digital", pin, self._n_dig)
        if value:
            self._dout |= 1 << pin
        else:
            self._dout &= ~(1 << pin)

    def get_digital(self, pin: int) -> bool:
        check_pin("digital", pin, self._n_dig)
        return bool((self._din >> pin) & 1)

    def set_analog(self, pin: int, volts: float) -> None:
        self._aout[check_pin("analog", pin, self._n_ana)] = float(volts)

    def get_analog(self, pin: int) -> float:
        return self._ain[check_pin("analog", pin, self._n_ana)]

    def step(self, t_ns: int) -> None:
        """Flush the outputs and latch the inputs; BoardError on any failure.

        Blocks at most ``reply_timeout_ms``. A failure counts in
        :meth:`health` and, after ``safe_after`` in a row, safes the board.
        """
        if not self._opened:
            self._fail("board is not open")
        port = self._port
        if port is None:
            self._fail(f"link down: {self._link_error}")
        seq = (self._seq + 1) & 0xFFFF
        self._seq = seq
        with self._lock:
            self._want = seq
            self._reply.clear()
        n = self._pack_write(seq, self._faulted)
        try:
            sent = port.write(self._txview[:n])
        except Exception as exc:
            # The port is broken: the link is down from now on (health says
            # so at once), and the I/O thread reopens it.
            message = f"write failed: {type(exc).__name__}: {exc}"
            self._link_down(port, message)
            self._fail(message)
        if sent != n:
            self._fail(f"write accepted {sent} of {n} bytes (device not reading?)")
        self.counters.frames_sent += 1
        if not self._reply.wait(self._timeout_s):
            self.counters.timeouts += 1
            self._fail(f"no INPUTS for WRITE seq {seq} within {self.config.reply_timeout_ms} ms")
        rx = self._rx
        self._din = rx[1]
        self._ain = rx[2]
        self.counters.consecutive_errors = 0
        self._faulted = False

    # -- the ManagedBoard extras -------------------------------------------------

    def open(self) -> None:
        """Start the I/O thread (idempotent; returns at once, never raises for the port)."""
        if self._opened:
            return
        self._stop.clear()
        self._opened = True
        self._thread = threading.Thread(
            target=self._run, name=f"serialboard:{self.config.port}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Send the safe values if linked, stop the I/O thread, close the port (idempotent)."""
        if not self._opened:
            return
        self.safe()
        self._opened = False
        self._stop.set()
        port = self._port
        if port is not None and hasattr(port, "cancel_read"):
            try:
                port.cancel_read()
            except Exception:
                pass
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def safe(self) -> None:
        """Set every output to its safe value and, if linked, send them now.

        Never blocks (the write is non-blocking, the reply is not awaited) and
        never raises: a failed write is recorded as ``last_error``.
        """
        self._dout = self._safe_mask
        self._aout[:] = self._safe_ana
        port = self._port
        if port is None:
            return
        self._seq = (self._seq + 1) & 0xFFFF
        with self._lock:
            self._want = self._seq  # its INPUTS is latched by the next step, not counted late
        n = self._pack_write(self._seq, True)
        try:
            port.write(self._txview[:n])
            self.counters.frames_sent += 1
        except Exception as exc:
            self.counters.last_error = f"safe write failed: {type(exc).__name__}: {exc}"

    def health(self) -> BoardHealth:
        """A snapshot of the counters (allocates one small struct)."""
        connected = self._port is not None
        c = self.counters
        return c.snapshot(
            ok=self._opened and connected and c.consecutive_errors == 0 and not self._faulted,
            connected=connected,
            safe_active=self._faulted,
        )

    def wait_connected(self, timeout: float) -> bool:
        """Block until the handshake is done (True) or ``timeout`` seconds pass (False)."""
        return self._connected.wait(timeout)

    # -- loop thread helpers -------------------------------------------------------

    def _link_down(self, port: Any, message: str) -> None:
        """Take the link down if ``port`` is still it, and wake the I/O
        thread's read so that it closes the port and reopens it."""
        with self._lock:
            if self._port is not port:
                return  # the I/O thread already dropped it (and may have a new one)
            self._port = None
            self._connected.clear()
            self._link_error = f"{self.config.port}: {message}"
        cancel = getattr(port, "cancel_read", None)
        if cancel is not None:
            try:
                cancel()
            except Exception:
                pass

    def _fail(self, message: str) -> NoReturn:
        self.counters.failed(message)
        if self.counters.consecutive_errors >= self.config.safe_after:
            self._faulted = True
        raise BoardError(message)

    def _pack_write(self, seq: int, safe: bool) -> int:
        raw = self._raw
        if safe:
            _U64.pack_into(raw, 4, self._safe_mask)
            aout = self._safe_ana
        else:
            _U64.pack_into(raw, 4, self._dout)
            aout = self._aout
        n_ana = self._dev_analog
        off = 12
        for i in range(n_ana):
            # pins the mission does not use are sent as their safe value (0 V)
            struct.pack_into("<f", raw, off, aout[i] if i < self._n_ana else 0.0)
            off += 4
        return wire.encode_into(raw, self._tx, wire.MSG_WRITE, seq, 8 + 4 * n_ana)

    # -- the I/O thread ------------------------------------------------------------

    def _open_port(self) -> Any:
        factory = self._factory
        if factory is None:
            import serial

            factory = serial.Serial
        # timeout: how long a read may wait, so the thread notices close();
        # write_timeout=0: writes never block the loop (they return what fit).
        # exclusive: an advisory lock (flock), so a second node or a terminal
        # program cannot share the port and steal replies.
        return factory(
            self.config.port,
            baudrate=self.config.baudrate,
            timeout=0.05,
            write_timeout=0,
            exclusive=self.config.exclusive,
        )

    def _run(self) -> None:
        try:
            self._io()
        finally:
            self.heartbeat.idle()

    def _io(self) -> None:
        backoff = self.config.reconnect_min_ms / 1000.0
        first = True
        deframer = wire.Deframer(self._on_body, self._on_bad)
        hb = self.heartbeat
        while not self._stop.is_set():
            hb.beat()
            try:
                port = self._open_port()
            except Exception as exc:
                self._link_error = f"cannot open {self.config.port}: {exc}"
                hb.idle()  # waiting to reconnect is not a stall
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.config.reconnect_max_ms / 1000.0)
                continue
            try:
                self._handshake(port, deframer)
            except Exception as exc:
                self._link_error = f"handshake with {self.config.port} failed: {exc}"
                _close_quietly(port)
                hb.idle()
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.config.reconnect_max_ms / 1000.0)
                continue
            backoff = self.config.reconnect_min_ms / 1000.0
            if not first:
                self.counters.reconnects += 1
            first = False
            with self._lock:
                self._port = port
                self._connected.set()
            try:
                # Until stopped, or until the loop thread took the link down
                # after a failed write (it cancels this read to say so).
                while not self._stop.is_set() and self._port is port:
                    hb.beat()
                    data = port.read(port.in_waiting or 1)
                    if data:
                        deframer.feed(data)
            except Exception as exc:
                self._link_error = f"{self.config.port} lost: {type(exc).__name__}: {exc}"
            with self._lock:
                if self._port is port:
                    self._port = None
                    self._connected.clear()
            _close_quietly(port)

    def _handshake(self, port: Any, deframer: wire.Deframer) -> None:
        """Send HELLO, await HELLO_ACK; sets ``_dev_analog``. Raises on failure."""
        deframer.reset()
        self._hello = None
        raw = bytearray(wire.MAX_BODY)
        tx = bytearray(wire.MAX_WIRE)
        n = wire.encode_into(raw, tx, wire.MSG_HELLO, 0, 0)
        # A leading 0x00 ends any partial frame the device may hold.
        port.write(b"\x00" + bytes(tx[:n]))
        deadline = time.monotonic() + self.config.handshake_timeout_ms / 1000.0
        while self._hello is None:
            self.heartbeat.beat()
            if time.monotonic() > deadline:
                raise BoardError(f"no HELLO_ACK within {self.config.handshake_timeout_ms} ms")
            data = port.read(port.in_waiting or 1)
            if data:
                deframer.feed(data)
        version, n_dig, n_ana = self._hello
        if version != wire.VERSION:
            raise BoardError(f"device speaks protocol v{version}, host v{wire.VERSION}")
        if n_dig < self._n_dig or n_ana < self._n_ana or n_ana > wire.MAX_ANALOG:
            raise BoardError(
                f"device has {n_dig} digital / {n_ana} analog pins; the mission needs "
                f"{self._n_dig} / {self._n_ana}"
            )
        self._dev_analog = n_ana

    def _on_bad(self, reason: str) -> None:
        self.counters.bad_frames += 1

    def _on_body(self, body: bytearray) -> None:
        try:
            version, msg_type, seq, payload = wire.parse_body(body)
        except wire.FrameError:
            self.counters.bad_frames += 1
            return
        self.counters.frames_received += 1
        if msg_type == wire.MSG_HELLO_ACK and len(payload) == _HELLO_ACK.size:
            n_dig, n_ana, _watchdog = _HELLO_ACK.unpack_from(payload, 0)
            self._hello = (version, n_dig, n_ana)
        elif msg_type == wire.MSG_ERROR:
            self.counters.device_errors += 1
            if version != wire.VERSION:  # a device refusing our version says its own
                self._hello = (version, 0, 0)
        elif version != wire.VERSION:
            self.counters.bad_frames += 1
        elif msg_type == wire.MSG_INPUTS and len(payload) == 8 + 4 * self._dev_analog:
            (dmask,) = _U64.unpack_from(payload, 0)
            ana = struct.unpack_from(f"<{self._dev_analog}f", payload, 8)
            rx = (seq, dmask, ana + (0.0,) * (wire.MAX_ANALOG - len(ana)))
            # Checked and handed over in one step under the lock: a step that
            # begins meanwhile (a new _want) can never latch this one's inputs.
            with self._lock:
                if seq != self._want:
                    self.counters.late_replies += 1
                    return
                self._rx = rx
                self._reply.set()
        else:
            self.counters.bad_frames += 1


def _close_quietly(port: Any) -> None:
    try:
        port.close()
    except Exception:
        pass
