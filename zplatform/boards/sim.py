"""The simulated board: :class:`SimBoard`, the reference implementation of the board contract.

:class:`SimBoard` is the board of the lockstep runner, of tests and of every
device node whose ``board:`` mapping names no other driver: pins held in
lists, an optional physics hook (``physics: "module:function"`` in the
node's ``board`` config, called as ``function(board, t_ns)`` once per loop
before the sensors) that decides what the sensors see, and ``inject_*`` to
force an input (a stuck pin, a given voltage) from a test.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Annotated, Any

import msgspec
from msgspec import Meta

from ..core.components import decode_component_config, load_function
from .base import BoardHealth, PinCounts, check_pin

__all__ = ["Physics", "SimBoard", "SimBoardConfig"]


class SimBoardConfig(msgspec.Struct, forbid_unknown_fields=True):
    """The `board:` mapping of `driver: sim` (the default): a simulated board
    whose outputs read back what was set, unless a physics hook decides what
    the inputs see. Every mission runs on it without hardware.
    """

    digital_pins: Annotated[
        int, Meta(ge=0, le=65_536, description="Digital pins, numbered from 0.")
    ] = 16
    analog_pins: Annotated[
        int, Meta(ge=0, le=65_536, description="Analog pins (volts), numbered from 0.")
    ] = 8
    physics: Annotated[
        str | None,
        Meta(
            description="`package.module:function` called as `function(board, t_ns)` once per "
            "loop before the sensors: it reads outputs (`board.output_digital(pin)`), keeps "
            "its state in `board.state` and sets what the inputs read "
            "(`board.inject_analog(pin, volts)`, `board.inject_digital(pin, level)`)."
        ),
    ] = None
    params: Annotated[
        dict[str, Any],
        Meta(
            description="The physics' data, read as `board.params`. When the function has a "
            "`Params` attribute (a `msgspec.Struct` type), `params` is decoded into it at "
            "load, so a typo fails with its YAML path."
        ),
    ] = msgspec.field(default_factory=dict)


Physics = Callable[["SimBoard", int], None]


class SimBoard(PinCounts):
    """A simulated I/O board: pins in lists, inputs injectable, optional physics.

    A digital pin reads back what was last set on it unless an input is
    injected (:meth:`inject_digital`); the same for analog pins. ``config`` is
    the node's ``board`` mapping (:class:`SimBoardConfig`); construction
    raises ConfigError naming ``where`` for a bad one. ``start_ns`` is the
    time of the first :meth:`step` (``None`` before), for physics that model
    time since start. ``pythonpath``: where the physics module is imported
    from (the mission's code directories).
    """

    def __init__(
        self,
        config: dict[str, Any] | None = None,
        *,
        where: str = "$.board",
        pythonpath: Sequence[str] = (),
    ) -> None:
        cfg = decode_component_config(SimBoardConfig, dict(config or {}), where)
        self.config = cfg
        self._n_dig = cfg.digital_pins
        self._n_ana = cfg.analog_pins
        self._dout: list[bool] = [False] * cfg.digital_pins
        self._din: list[bool | None] = [None] * cfg.digital_pins
        self._aout: list[float] = [0.0] * cfg.analog_pins
        self._ain: list[float | None] = [None] * cfg.analog_pins
        self._physics: Physics | None = (
            load_function(
                cfg.physics,
                f"{where}.physics",
                args=("board", "t_ns"),
                what="physics",
                pythonpath=pythonpath,
            )
            if cfg.physics
            else None
        )
        params_type = getattr(self._physics, "Params", None)
        self.params: Any = (
            decode_component_config(params_type, cfg.params, f"{where}.params")
            if isinstance(params_type, type) and issubclass(params_type, msgspec.Struct)
            else cfg.params
        )
        self.start_ns: int | None = None
        self.steps = 0
        self.state: dict[str, Any] = {}  # scratch space for the physics hook

    def step(self, t_ns: int) -> None:
        """Advance the simulated world to ``t_ns`` (calls the physics hook)."""
        if self.start_ns is None:
            self.start_ns = t_ns
        self.steps += 1
        if self._physics is not None:
            self._physics(self, t_ns)

    def _dpin(self, pin: int) -> int:
        return check_pin("digital", pin, self._n_dig)

    def _apin(self, pin: int) -> int:
        return check_pin("analog", pin, self._n_ana)

    def set_digital(self, pin: int, value: bool) -> None:
        self._dout[self._dpin(pin)] = bool(value)

    def get_digital(self, pin: int) -> bool:
        forced = self._din[self._dpin(pin)]
        return self._dout[pin] if forced is None else forced

    def set_analog(self, pin: int, volts: float) -> None:
        self._aout[self._apin(pin)] = float(volts)

    def get_analog(self, pin: int) -> float:
        forced = self._ain[self._apin(pin)]
        return self._aout[pin] if forced is None else forced

    def inject_digital(self, pin: int, value: bool | None) -> None:
        """Force what ``pin`` reads (``None``: release, read back the output)."""
        self._din[self._dpin(pin)] = None if value is None else bool(value)

    def inject_analog(self, pin: int, volts: float | None) -> None:
        """Force the voltage ``pin`` reads (``None``: release)."""
        self._ain[self._apin(pin)] = None if volts is None else float(volts)

    def output_digital(self, pin: int) -> bool:
        """What was last set on ``pin`` (ignores injection): for tests and physics."""
        return self._dout[self._dpin(pin)]

    def output_analog(self, pin: int) -> float:
        """The voltage last set on ``pin`` (ignores injection): for tests and physics."""
        return self._aout[self._apin(pin)]

    # -- the board contract (zplatform.boards): the reference implementation --

    def open(self) -> None:
        """Nothing to acquire (idempotent)."""

    def close(self) -> None:
        """Apply :meth:`safe` (idempotent, never raises)."""
        self.safe()

    def safe(self) -> None:
        """Drive every output to its safe value: digital off, 0 V (injections stay)."""
        for i in range(self._n_dig):
            self._dout[i] = False
        for i in range(self._n_ana):
            self._aout[i] = 0.0

    def health(self) -> BoardHealth:
        """Always ok."""
        return _ALWAYS_OK


_ALWAYS_OK = BoardHealth(ok=True)
