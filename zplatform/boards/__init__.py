"""I/O boards behind one contract: ``sim`` (reference), ``serial``, ``gpiod``, or a team's own.

Choosing a board
----------------
A device node's ``board:`` mapping in the mission names a driver; the other
keys are that driver's typed config (a ``msgspec.Struct`` with
``forbid_unknown_fields``), so a typo fails at load with its YAML path
(``... - at `$.nodes.dn0.board.port```)::

    board: {digital_pins: 4, physics: "pkg.mod:fn"}     # driver: sim (the default)
    board: {driver: serial, port: /dev/serial/by-id/usb-..., digital_pins: 8, analog_pins: 2}
    board: {driver: gpiod, chip: /dev/gpiochip0, inputs: {0: 17}, outputs: {1: 27}}
    board: {driver: "team.boards:AdcHat", spi_bus: 0}  # Class(config_dict, where=path)

:func:`make_board` builds one (no hardware touched), :func:`check_board`
validates one at mission load. The node runtime then calls
:func:`open_board` before loop 1 and :func:`close_board` after the last.

The contract
------------
Every board satisfies :class:`Board`; the managed ones (every built-in)
also :class:`ManagedBoard`. :class:`SimBoard` (``sim``) is the reference
implementation.

``digital_pins``, ``analog_pins``
    Pin counts, fixed at construction (devices check pin numbers against them).
``open()``
    Acquire the hardware (request GPIO lines; start the serial I/O thread).
    Idempotent. Raises :class:`BoardError` if the hardware is absent or
    refuses (``gpiod``); the serial board never raises here, it keeps
    reconnecting in the background and :meth:`step` reports the link.
``close()``
    Apply :meth:`safe`, then release the hardware. Idempotent, never raises.
``step(t_ns)``
    Once per loop, before the sensors: flush the outputs set since the last
    step and latch the inputs, so every ``get_*`` in a loop sees one
    consistent sample. On the 100 Hz hot path: bounded time (the serial
    board waits at most ``reply_timeout_ms``, 2 ms by default), no buffers
    allocated. Raises :class:`BoardError` when it could not talk to the
    hardware (timeout, link down, kernel error); the inputs then keep their
    last latched values, the failure is counted in :meth:`health`, and after
    ``safe_after`` consecutive failures the board forces its safe values on
    every write until the hardware answers again.
``set_digital(pin, value)``, ``set_analog(pin, volts)``
    Record an output; it reaches the hardware at the next :meth:`step` (the
    simulator applies it at once). ControlError for a pin out of range.
``get_digital(pin)``, ``get_analog(pin)``
    The latched input. An output pin reads back its level as the hardware
    reported it (sim: at once; serial and gpiod: from the last step).
``safe()``
    Drive every output to its safe value now (configured per driver; off and
    0 V by default). Never blocks beyond a non-blocking write, never raises.
    The device loop calls it when the board fails (a :class:`BoardError` from
    ``step``) and wherever the node's safing rules say so.
``health()``
    A frozen :class:`BoardHealth` snapshot: ``ok``, ``connected``,
    ``safe_active``, ``consecutive_errors``, ``last_error`` and counters
    (frames sent/received/bad, timeouts, reconnects, device errors).

The device loop's side (:class:`~zplatform.loop.DeviceLogic`): count a
:class:`BoardError` from ``step`` in ``dnX_errors`` (it already counts any
exception there) and call :func:`safe_board` on it. For the drivers with a
link (``serial``, ``gpiod``: :data:`zplatform.config.BOARD_LINK_DRIVERS`) it
also copies the board's ``counters`` (a :class:`HealthCounters`, read in
place: no allocation) into the telemetry elements ``dnX_board_*`` after
every step, and the node's summary carries :func:`board_health` at exit.

Drivers: :class:`SerialBoard` (``serialboard``, needs ``pyserial``, the
``serial`` extra) and :class:`GpiodBoard` (``gpio``, needs ``gpiod``, the
``gpio`` extra) import their libraries only when used, so this package
imports without them. ``python -m zplatform.boards.serial_sim`` is a
simulated serial device behind a pty, for tests and bench setups. The
``world`` driver (a port onto the mission's vehicle world process) and
:func:`~zplatform.boards.world.node_board`, which builds a device node's
board from the mission, are :mod:`zplatform.boards.world` (not imported
here: it needs the mission's types).

Errors::

    ZPlatformError
    └── BoardError        a board could not open, latch or flush (this package)
"""

from __future__ import annotations

from .base import Board, BoardError, BoardHealth, HealthCounters, ManagedBoard
from .gpio import GpiodBoard, GpiodBoardConfig
from .registry import (
    BUILTIN_DRIVERS,
    board_health,
    check_board,
    close_board,
    make_board,
    open_board,
    safe_board,
)
from .serialboard import SerialBoard, SerialBoardConfig
from .sim import Physics, SimBoard, SimBoardConfig

__all__ = [
    "BUILTIN_DRIVERS",
    "Board",
    "BoardError",
    "BoardHealth",
    "GpiodBoard",
    "GpiodBoardConfig",
    "HealthCounters",
    "ManagedBoard",
    "Physics",
    "SerialBoard",
    "SerialBoardConfig",
    "SimBoard",
    "SimBoardConfig",
    "board_health",
    "check_board",
    "close_board",
    "make_board",
    "open_board",
    "safe_board",
]
