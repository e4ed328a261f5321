"""The thesis-sized mission's logic: 100 sensors, 100 actuators (configs/thesis_200.yaml).

* :func:`waves` (board physics): drives every analog input pin with a slow
  sine (one phase per pin) and every digital input pin with a square wave,
  so each loop's sensor values change.
* :class:`Mirror` (CN controller): each actuator command follows its paired
  sensor (``analog``: ``command = gain * sensor``; ``digital``: ``command =
  sensor``). Safed, every command goes to 0 / off.

Everything a loop does is a few hundred element reads and writes: the mission
exercises the platform's bookkeeping at the thesis' size, not any physics.
"""

from __future__ import annotations

import math

import msgspec

from zplatform.boards import SimBoard
from zplatform.control.controllers import Controller
from zplatform.core.datavector import DataVector

__all__ = ["Mirror", "waves"]


def waves(board: SimBoard, t_ns: int) -> None:
    """Sine on every analog input (1 Hz, phase by pin), 2 Hz square on every digital one."""
    t = t_ns / 1e9
    for pin in range(board.analog_pins):
        board.inject_analog(pin, math.sin(2 * math.pi * t + pin))
    for pin in range(board.digital_pins):
        board.inject_digital(pin, int(2 * t + pin) % 2 == 1)


class Mirror(Controller):
    """Actuator commands follow their paired sensors."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        analog: list[tuple[str, str]] = msgspec.field(default_factory=list)
        digital: list[tuple[str, str]] = msgspec.field(default_factory=list)
        gain: float = 1.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        c = self.config
        self._a = tuple(
            (
                self.input(s, f"analog[{i}][0]", kinds=("float",)),
                self.output(o, f"analog[{i}][1]", kinds=("float",)),
            )
            for i, (s, o) in enumerate(c.analog)
        )
        self._d = tuple(
            (
                self.input(s, f"digital[{i}][0]", kinds=("bool",)),
                self.output(o, f"digital[{i}][1]", kinds=("bool",)),
            )
            for i, (s, o) in enumerate(c.digital)
        )
        self._gain = c.gain

    def run_enabled(self, t_ns: int) -> None:
        g = self._gain
        for s, o in self._a:
            o.set(g * s.get())
        for s, o in self._d:
            o.set(bool(s.get()))

    def run_safed(self, t_ns: int) -> None:
        for _, o in self._a:
            o.set(0.0)
        for _, o in self._d:
            o.set(False)
