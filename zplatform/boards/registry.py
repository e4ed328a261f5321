"""Choosing a node's board from the mission: :func:`make_board`, :func:`check_board`.

A node's ``board:`` mapping is ``{driver: NAME, ...the driver's own config}``.
``driver`` defaults to ``sim``, so the mappings written before drivers
existed (``{digital_pins: 4, physics: ...}``) still mean a
:class:`~zplatform.boards.SimBoard`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import msgspec

from ..core.components import decode_component_config, load_component_class
from ..errors import ConfigError
from .base import Board, BoardHealth
from .sim import SimBoard

__all__ = [
    "BUILTIN_DRIVERS",
    "board_health",
    "check_board",
    "close_board",
    "make_board",
    "open_board",
    "safe_board",
]

BUILTIN_DRIVERS = ("sim", "serial", "gpiod", "world")
_BOARD_METHODS = ("step", "set_digital", "get_digital", "set_analog", "get_analog")


def _split(spec: Mapping[str, Any] | None, where: str) -> tuple[str, dict[str, Any]]:
    if spec is None:
        spec = {}
    if not isinstance(spec, Mapping):
        raise ConfigError(f"board must be a mapping, got {type(spec).__name__}", where)
    config = dict(spec)
    driver = config.pop("driver", "sim")
    if not isinstance(driver, str) or not driver:
        raise ConfigError(
            f"driver must be one of {list(BUILTIN_DRIVERS)} or 'package.module:Class'",
            f"{where}.driver",
        )
    if driver not in BUILTIN_DRIVERS and ":" not in driver:
        raise ConfigError(
            f"unknown board driver {driver!r}; expected one of {list(BUILTIN_DRIVERS)} "
            "or 'package.module:Class'",
            f"{where}.driver",
        )
    return driver, config


def _load_class(driver: str, where: str, pythonpath: Sequence[str]) -> type[Any]:
    # The one class loader of the platform (controllers, devices, boards).
    return load_component_class(driver, object, where, pythonpath=pythonpath)


def make_board(
    spec: Mapping[str, Any] | None, *, where: str, pythonpath: Sequence[str] = ()
) -> Board:
    """Build (not open) the board a node's ``board:`` mapping asks for.

    ``where`` is the mapping's YAML path (``$.nodes.dn0.board``); every
    ConfigError names a path under it. Built-in drivers touch no hardware
    here: call ``open()`` before the first loop and ``close()`` after the
    last (:func:`open_board` / :func:`close_board` do nothing for a board
    without them).

    A ``package.module:Class`` driver is called as ``Class(config, where=where)``
    with the mapping minus ``driver`` (a plain dict); it should decode it
    into its own typed config (``decode_component_config``) and raise
    ConfigError, and must not touch hardware before ``open()``. The result
    must satisfy :class:`~zplatform.boards.Board` (ConfigError otherwise).
    ``pythonpath``: the mission's code directories, for a team's driver
    class or a physics hook (:func:`~zplatform.core.components.mission_code_path`).
    """
    driver, config = _split(spec, where)
    if driver == "sim":
        return SimBoard(config, where=where, pythonpath=pythonpath)
    if driver == "world":
        raise ConfigError(
            "driver 'world' is a port onto the mission's vehicle world: build it with "
            "zplatform.boards.world.node_board(mission, node)",
            f"{where}.driver",
        )
    if driver == "serial":
        from .serialboard import SerialBoard

        return SerialBoard(config, where=where)
    if driver == "gpiod":
        from .gpio import GpiodBoard

        return GpiodBoard(config, where=where)
    cls = _load_class(driver, f"{where}.driver", pythonpath)
    try:
        board = cls(config, where=where)
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(
            f"board class {driver!r} failed to build: {type(exc).__name__}: {exc}", where
        ) from exc
    if not isinstance(board, Board):
        raise ConfigError(
            f"{driver!r} does not implement zplatform.boards.Board "
            "(digital_pins, analog_pins, step, get/set_digital, get/set_analog)",
            f"{where}.driver",
        )
    return board


def check_board(
    spec: Mapping[str, Any] | None, where: str, *, pythonpath: Sequence[str] = ()
) -> None:
    """Validate a ``board:`` mapping at mission load, opening no hardware.

    Built-in drivers are built and dropped (their constructors are pure).
    For a ``package.module:Class`` driver the class is imported and checked
    for the Board methods and, if it has a ``Config`` attribute that is a
    ``msgspec.Struct`` type, the config is decoded into it; the class itself
    is not instantiated, since a
    team's constructor may not be pure. Raises ConfigError with the path.
    """
    driver, config = _split(spec, where)
    if driver == "world":
        return  # checked against the mission's world (zplatform.world.checks.check_config)
    if driver in BUILTIN_DRIVERS:
        make_board(spec, where=where, pythonpath=pythonpath)
        return
    cls = _load_class(driver, f"{where}.driver", pythonpath)
    missing = [m for m in _BOARD_METHODS if not callable(getattr(cls, m, None))]
    if missing:
        raise ConfigError(
            f"{driver!r} does not implement zplatform.boards.Board (no {', '.join(missing)})",
            f"{where}.driver",
        )
    cfg_type = getattr(cls, "Config", None)
    if isinstance(cfg_type, type) and issubclass(cfg_type, msgspec.Struct):
        decode_component_config(cfg_type, config, where)


def open_board(board: Board) -> None:
    """``board.open()`` if the board has a life cycle (every built-in has); else nothing.

    Raises what ``open`` raises (:class:`~zplatform.boards.BoardError` for
    absent hardware). For the node runtime, before loop 1.
    """
    fn = getattr(board, "open", None)
    if callable(fn):
        fn()


def close_board(board: Board) -> None:
    """``board.close()`` if the board has one (safes the outputs first); never raises."""
    fn = getattr(board, "close", None)
    if callable(fn):
        try:
            fn()
        except Exception:
            pass


def safe_board(board: Board) -> None:
    """``board.safe()`` if the board has one; never raises (safing must not fail the loop)."""
    fn = getattr(board, "safe", None)
    if callable(fn):
        try:
            fn()
        except Exception:
            pass


def board_health(board: Board) -> BoardHealth:
    """``board.health()``, or an ``ok`` snapshot for a board without one."""
    fn = getattr(board, "health", None)
    if callable(fn):
        health: BoardHealth = fn()
        return health
    return _ALWAYS_OK


_ALWAYS_OK = BoardHealth(ok=True)
