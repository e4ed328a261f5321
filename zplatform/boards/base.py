"""The board contract's types: :class:`Board`, :class:`ManagedBoard`,
:class:`BoardHealth`, :class:`BoardError`.

The contract is stated once in :mod:`zplatform.boards` (the package
docstring); this module holds its types so that drivers and the device loop
share them without importing each other.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import msgspec

from ..errors import ControlError, ZPlatformError

__all__ = [
    "Board",
    "BoardError",
    "BoardHealth",
    "HealthCounters",
    "ManagedBoard",
    "PinCounts",
    "check_pin",
]


def check_pin(kind: str, pin: int, count: int) -> int:
    """``pin``, when it is one of the board's ``count`` pins of ``kind``
    (``digital``, ``analog``); else ControlError naming both. Every board's pin
    methods use this one rule (a constant-time compare, no allocation)."""
    if not 0 <= pin < count:
        raise ControlError(f"{kind} pin {pin} out of range (board has {count})")
    return pin


class PinCounts:
    """The pin counts of :class:`Board`, one implementation for every driver:
    a driver sets ``_n_dig`` and ``_n_ana`` in its constructor and inherits
    ``digital_pins`` and ``analog_pins`` (plain reads, no allocation)."""

    _n_dig: int
    _n_ana: int

    @property
    def digital_pins(self) -> int:
        return self._n_dig

    @property
    def analog_pins(self) -> int:
        return self._n_ana


@runtime_checkable
class Board(Protocol):
    """An I/O board: digital and analog pins, numbered from 0.

    ``digital_pins`` / ``analog_pins`` are the pin counts (devices check their
    pin numbers against them at construction). Every pin method raises
    :class:`~zplatform.errors.ControlError` for a pin out of range. ``step``
    is called once per loop before the sensors run.
    """

    @property
    def digital_pins(self) -> int: ...

    @property
    def analog_pins(self) -> int: ...

    def step(self, t_ns: int) -> None: ...

    def set_digital(self, pin: int, value: bool) -> None: ...

    def get_digital(self, pin: int) -> bool: ...

    def set_analog(self, pin: int, volts: float) -> None: ...

    def get_analog(self, pin: int) -> float: ...


class BoardError(ZPlatformError):
    """A board could not latch its inputs or flush its outputs this loop.

    Raised by :meth:`ManagedBoard.step` (a timeout, a link that is down, a
    kernel error on a GPIO request) and by :meth:`ManagedBoard.open` (the
    hardware is absent or refuses). The device loop counts it in
    ``dnX_errors`` and goes on; the board has already recorded it in
    :meth:`ManagedBoard.health`.
    """


class BoardHealth(msgspec.Struct, frozen=True, gc=False):
    """A snapshot of a board's health (trio's statistics objects: frozen, cheap).

    ``ok``: open, linked, and the last step succeeded. ``connected``: the
    link to the hardware is up (always true for boards without a link).
    ``safe_active``: the outputs are forced to their safe values because of
    errors (the serial board holds them until the device answers again).
    Counters only grow, over the board object's life (close and open keep
    them). ``frames_*`` count link frames (serial) or I/O cycles (gpiod: one
    write and one read per step); ``late_replies`` are answers that came
    after their step gave up on them.
    """

    ok: bool
    connected: bool = True
    safe_active: bool = False
    consecutive_errors: int = 0
    errors: int = 0
    last_error: str = ""
    frames_sent: int = 0
    frames_received: int = 0
    bad_frames: int = 0
    timeouts: int = 0
    reconnects: int = 0
    device_errors: int = 0
    late_replies: int = 0


class HealthCounters:
    """The mutable counters behind :class:`BoardHealth` (one writer per counter).

    Drivers with an I/O thread let the thread own the receive-side counters
    (``frames_received``, ``bad_frames``, ``reconnects``, ``device_errors``,
    ``late_replies``) and the loop thread own the rest, so no lock is needed:
    each attribute has a single writer and reads of an int are atomic.

    A driver exposes its counters as its ``counters`` attribute: the device
    loop reads them there in place after every step (the telemetry
    elements ``dnX_board_*``), which allocates nothing, where
    :meth:`snapshot` builds a struct.
    """

    __slots__ = (
        "bad_frames",
        "consecutive_errors",
        "device_errors",
        "errors",
        "frames_received",
        "frames_sent",
        "last_error",
        "late_replies",
        "reconnects",
        "timeouts",
    )

    def __init__(self) -> None:
        self.consecutive_errors = 0
        self.errors = 0
        self.last_error = ""
        self.frames_sent = 0
        self.frames_received = 0
        self.bad_frames = 0
        self.timeouts = 0
        self.reconnects = 0
        self.device_errors = 0
        self.late_replies = 0

    def failed(self, message: str) -> None:
        """Record one failed step (``message`` becomes ``last_error``)."""
        self.consecutive_errors += 1
        self.errors += 1
        self.last_error = message

    def snapshot(self, *, ok: bool, connected: bool, safe_active: bool) -> BoardHealth:
        return BoardHealth(
            ok=ok,
            connected=connected,
            safe_active=safe_active,
            consecutive_errors=self.consecutive_errors,
            errors=self.errors,
            last_error=self.last_error,
            frames_sent=self.frames_sent,
            frames_received=self.frames_received,
            bad_frames=self.bad_frames,
            timeouts=self.timeouts,
            reconnects=self.reconnects,
            device_errors=self.device_errors,
            late_replies=self.late_replies,
        )


@runtime_checkable
class ManagedBoard(Board, Protocol):
    """A :class:`Board` with a life cycle, a safe state and health.

    See :mod:`zplatform.boards` for the full contract of each method.
    """

    def open(self) -> None: ...

    def close(self) -> None: ...

    def safe(self) -> None: ...

    def health(self) -> BoardHealth: ...
