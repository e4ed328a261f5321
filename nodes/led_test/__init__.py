"""Controllers of the LED platform system test (the thesis, ch. 5.1.3.1).

* :class:`StateLedController` (CN): lights the LED of the current state.
* :class:`SequentialLedController` (CN): in state C, lights dn1's LEDs one
  per ``step_s`` (LED0 at once, LED4 after ``4 * step_s``), cumulatively.
* :class:`FlashController` (dn2): flashes one LED with period ``period_s``
  (on for the first half of each period), timed from when it was enabled.

Every one drives command elements only; the
:class:`~zplatform.control.devices.DigitalOutput` devices on the DNs set the pins and
read them back into the ``*_fb`` elements. Safed, every LED is commanded off.
"""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

from zplatform.control.controllers import Controller
from zplatform.core.datavector import DataVector, Handle
from zplatform.errors import ConfigError

__all__ = ["FlashController", "SequentialLedController", "StateLedController"]

_BOOL = ("bool", "int")


class StateLedController(Controller):
    """Lights the LED mapped to the current ``cn_state``; all others off.

    ``leds`` maps state names to LED command elements; states not listed
    light nothing.
    """

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        leds: dict[str, str]

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._state = self.input("cn_state", kinds=("enum",))
        names = self._state.spec.enum or ()
        pairs: list[tuple[int, Handle]] = []
        for state, element in self.config.leds.items():
            if state not in names:
                raise ConfigError(
                    f"{state!r} is not a state; states: {list(names)}",
                    f"{self.where}.config.leds.{state}",
                )
            pairs.append((names.index(state), self.output(element, f"leds.{state}", kinds=_BOOL)))
        self._leds = tuple(pairs)

    def run_enabled(self, t_ns: int) -> None:
        state = self._state.get()
        for index, led in self._leds:
            led.set(index == state)

    def run_safed(self, t_ns: int) -> None:
        for _, led in self._leds:
            led.set(False)


class SequentialLedController(Controller):
    """Turns LED ``i`` on ``i * step_s`` after being enabled (LED0 at once), cumulatively."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        leds: Annotated[list[str], Meta(min_length=1)]
        step_s: Annotated[float, Meta(gt=0)] = 1.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._leds = tuple(
            self.output(e, f"leds[{i}]", kinds=_BOOL) for i, e in enumerate(self.config.leds)
        )
        self._step_ns = round(self.config.step_s * 1e9)

    def run_enabled(self, t_ns: int) -> None:
        lit = (t_ns - self.enabled_at_ns) // self._step_ns  # LEDs 0..lit are on
        for i, led in enumerate(self._leds):
            led.set(i <= lit)

    def run_safed(self, t_ns: int) -> None:
        for led in self._leds:
            led.set(False)


class FlashController(Controller):
    """Flashes ``led``: on for the first half of every ``period_s``, from enable time."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        led: str
        period_s: Annotated[float, Meta(gt=0)] = 1.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._led = self.output(self.config.led, "led", kinds=_BOOL)
        self._period_ns = round(self.config.period_s * 1e9)
        self._half_ns = self._period_ns // 2

    def run_enabled(self, t_ns: int) -> None:
        self._led.set((t_ns - self.enabled_at_ns) % self._period_ns < self._half_ns)

    def run_safed(self, t_ns: int) -> None:
        self._led.set(False)
