"""I/O boards behind one contract: ``sim`` (reference), ``serial``, ``gpiod``, or a team's own.

Holds the contract's types (:class:`Board`, :class:`ManagedBoard`,
:class:`BoardHealth`, :class:`BoardError`, from :mod:`.base`), the reference
:class:`SimBoard`, and the life cycle: :func:`make_board` builds a board from a
node's ``board:`` mapping (typed config; a typo fails at load with its YAML
path, no hardware touched), :func:`check_board` validates one at mission load,
:func:`open_board` / :func:`close_board` run before loop 1 and after the last,
:func:`safe_board` safes one that failed.

Contract, in short: ``step(t_ns)`` once per loop flushes outputs and latches
inputs in bounded time without allocating, and raises :class:`BoardError` when
the hardware did not answer (inputs keep their last values; after
``safe_after`` failures the outputs go safe); ``safe()`` and ``close()`` never
raise. :class:`SerialBoard` and :class:`GpiodBoard` import their libraries
only when used, so this package imports without them; the ``world`` driver is
:mod:`zplatform.boards.world` (not imported here: it needs the mission's types).

The whole contract, method by method: docs/architecture.md#boards.
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
