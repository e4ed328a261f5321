"""The Linux GPIO board: digital lines of a gpiochip through libgpiod v2 (``gpiod``).

The mission maps board pin numbers to line offsets of one chip::

    board:
      driver: gpiod
      chip: /dev/gpiochip0
      inputs: {0: 17, 1: 22}      # board pin -> line offset
      outputs: {2: 27}
      active_low: [0]             # board pins whose level is inverted by the kernel
      bias: pull-up               # for the inputs: as-is, pull-up, pull-down, disabled
      safe: {2: false}            # safe value per output pin (default off)

``gpiod`` is imported at :meth:`GpiodBoard.open`, not at import, so the rest
of zplatform works without it; a module object with the same surface can be
injected for tests (``gpiod_module=``).
"""

from __future__ import annotations

import importlib
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from ..core.components import decode_component_config
from ..errors import ControlError
from .base import BoardError, BoardHealth, HealthCounters, PinCounts

__all__ = ["GpiodBoard", "GpiodBoardConfig"]

MAX_PIN = 255


class GpiodBoardConfig(msgspec.Struct, forbid_unknown_fields=True):
    """The `board:` mapping of `driver: gpiod`: digital lines of one Linux
    gpiochip through libgpiod v2 (needs the `gpio` extra). Board pins map to
    line offsets; the board has no analog pins, and its `digital_pins` is
    the highest mapped pin + 1 (an unmapped pin in between is refused like
    one out of range).
    """

    chip: Annotated[str, Meta(description="The GPIO chip device.")] = "/dev/gpiochip0"
    inputs: Annotated[
        dict[int, Annotated[int, Meta(ge=0)]],
        Meta(description="Input pins: board pin (0-255) -> line offset."),
    ] = msgspec.field(default_factory=dict)
    outputs: Annotated[
        dict[int, Annotated[int, Meta(ge=0)]],
        Meta(description="Output pins: board pin (0-255) -> line offset."),
    ] = msgspec.field(default_factory=dict)
    active_low: Annotated[
        list[int],
        Meta(description="Board pins whose level the kernel inverts."),
    ] = msgspec.field(default_factory=list)
    bias: Annotated[
        Literal["as-is", "pull-up", "pull-down", "disabled"],
        Meta(description="Bias of the input lines."),
    ] = "as-is"
    safe: Annotated[
        dict[int, bool],
        Meta(description="Safe level per output pin (others: off); outputs start at it."),
    ] = msgspec.field(default_factory=dict)
    consumer: Annotated[
        str, Meta(description="The consumer name the lines are requested under.")
    ] = "zplatform"

    def __post_init__(self) -> None:
        for kind, pins in (("inputs", self.inputs), ("outputs", self.outputs)):
            for pin in pins:
                if not 0 <= pin <= MAX_PIN:
                    raise ValueError(f"{kind}: board pin {pin} out of range 0..{MAX_PIN}")
        both = sorted(set(self.inputs) & set(self.outputs))
        if both:
            raise ValueError(f"board pins {both} are both inputs and outputs")
        offsets = list(self.inputs.values()) + list(self.outputs.values())
        dup = sorted({o for o in offsets if offsets.count(o) > 1})
        if dup:
            raise ValueError(f"line offsets {dup} are mapped to more than one pin")
        unknown = sorted(set(self.active_low) - set(self.inputs) - set(self.outputs))
        if unknown:
            raise ValueError(f"active_low pins {unknown} are not mapped")
        not_out = sorted(set(self.safe) - set(self.outputs))
        if not_out:
            raise ValueError(f"safe pins {not_out} are not outputs")


_BIAS = {"as-is": "AS_IS", "pull-up": "PULL_UP", "pull-down": "PULL_DOWN", "disabled": "DISABLED"}


class GpiodBoard(PinCounts):
    """Digital inputs and outputs on one gpiochip (see the module docstring).

    Construction validates ``config`` (:class:`GpiodBoardConfig`, ConfigError
    naming ``where``) and touches nothing. :meth:`open` requests every mapped
    line in one request, outputs starting at their safe values; it raises
    :class:`BoardError` when ``gpiod`` is missing or the chip refuses.
    :meth:`step` writes every output (one ``set_values``) and then reads
    every line (one ``get_values``): two ioctls, a few microseconds,
    BoardError if the kernel fails them. Levels are logical (``active_low``
    applied by the kernel).
    """

    def __init__(
        self,
        config: dict[str, Any] | None = None,
        *,
        where: str = "$.board",
        gpiod_module: Any = None,
    ) -> None:
        cfg = decode_component_config(GpiodBoardConfig, dict(config or {}), where)
        self.config = cfg
        self._gpiod = gpiod_module
        mapped = list(cfg.inputs) + list(cfg.outputs)
        self._n_dig = max(mapped) + 1 if mapped else 0
        self._n_ana = 0  # gpiod lines are digital only
        # pin -> index into the latched levels; -1 for a pin that is not mapped
        self._in_pins = sorted(cfg.inputs)
        self._out_pins = sorted(cfg.outputs)
        self._all_pins = self._in_pins + self._out_pins
        self._offsets = [cfg.inputs[p] for p in self._in_pins] + [
            cfg.outputs[p] for p in self._out_pins
        ]
        self._index = [-1] * self._n_dig
        for i, pin in enumerate(self._all_pins):
            self._index[pin] = i
        self._is_out = [False] * self._n_dig
        for pin in self._out_pins:
            self._is_out[pin] = True
        self._safe = {p: bool(cfg.safe.get(p, False)) for p in self._out_pins}
        self._levels = [False] * len(self._all_pins)
        self._want = dict(self._safe)  # pin -> commanded output
        self._values: dict[int, Any] = {}  # offset -> gpiod Value, reused every step
        self._active: Any = None
        self._inactive: Any = None
        self._req: Any = None
        self.counters = HealthCounters()

    def _pin(self, pin: int) -> int:
        if not 0 <= pin < self._n_dig or self._index[pin] < 0:
            raise ControlError(
                f"digital pin {pin} is not mapped on gpiod board {self.config.chip} "
                f"(inputs {self._in_pins}, outputs {self._out_pins})"
            )
        return pin

    def set_digital(self, pin: int, value: bool) -> None:
        if not self._is_out[self._pin(pin)]:
            raise ControlError(f"digital pin {pin} is an input on gpiod board {self.config.chip}")
        self._want[pin] = bool(value)

    def get_digital(self, pin: int) -> bool:
        return self._levels[self._index[self._pin(pin)]]

    def set_analog(self, pin: int, volts: float) -> None:
        raise ControlError(f"analog pin {pin} out of range (gpiod board has 0)")

    def get_analog(self, pin: int) -> float:
        raise ControlError(f"analog pin {pin} out of range (gpiod board has 0)")

    def open(self) -> None:
        """Request the lines (idempotent); BoardError if gpiod or the chip fails."""
        if self._req is not None:
            return
        gp = self._gpiod
        if gp is None:
            try:
                gp = importlib.import_module("gpiod")
            except ImportError as exc:
                raise BoardError(
                    "driver 'gpiod' needs the libgpiod v2 bindings: pip install 'zplatform[gpio]'"
                ) from exc
            self._gpiod = gp
        line = gp.line
        self._active, self._inactive = line.Value.ACTIVE, line.Value.INACTIVE
        cfg = self.config
        low = set(cfg.active_low)
        bias = getattr(line.Bias, _BIAS[cfg.bias])
        settings: dict[Any, Any] = {}
        for pin in self._in_pins:
            settings[cfg.inputs[pin]] = gp.LineSettings(
                direction=line.Direction.INPUT, bias=bias, active_low=pin in low
            )
        for pin in self._out_pins:
            settings[cfg.outputs[pin]] = gp.LineSettings(
                direction=line.Direction.OUTPUT,
                active_low=pin in low,
                output_value=self._active if self._safe[pin] else self._inactive,
            )
        try:
            self._req = gp.request_lines(cfg.chip, config=settings, consumer=cfg.consumer)
        except Exception as exc:
            self.counters.failed(f"cannot request lines on {cfg.chip}: {exc}")
            raise BoardError(
                f"cannot request lines {self._offsets} on {cfg.chip}: {type(exc).__name__}: {exc}"
            ) from exc
        self._want = dict(self._safe)
        self._values = {
            cfg.outputs[p]: self._active if v else self._inactive for p, v in self._want.items()
        }

    def close(self) -> None:
        """Apply :meth:`safe`, release the lines (idempotent, never raises)."""
        if self._req is None:
            return
        self.safe()
        try:
            self._req.release()
        except Exception:
            pass
        self._req = None

    def step(self, t_ns: int) -> None:
        """Write the outputs, then read every line; BoardError on a kernel error."""
        req = self._req
        if req is None:
            self.counters.failed("board is not open")
            raise BoardError(f"gpiod board {self.config.chip} is not open")
        outputs = self.config.outputs
        values = self._values
        act, inact = self._active, self._inactive
        for pin, v in self._want.items():
            values[outputs[pin]] = act if v else inact
        try:
            if values:
                req.set_values(values)
            levels = req.get_values(self._offsets)
        except Exception as exc:
            msg = f"gpio I/O on {self.config.chip} failed: {type(exc).__name__}: {exc}"
            self.counters.failed(msg)
            raise BoardError(msg) from exc
        lv = self._levels
        for i, v in enumerate(levels):
            lv[i] = v == act
        self.counters.consecutive_errors = 0
        self.counters.frames_sent += 1
        self.counters.frames_received += 1

    def safe(self) -> None:
        """Set every output to its safe value and write them now if open (never raises)."""
        self._want.update(self._safe)
        req = self._req
        if req is None or not self._values:
            return
        outputs = self.config.outputs
        for pin, v in self._safe.items():
            self._values[outputs[pin]] = self._active if v else self._inactive
        try:
            req.set_values(self._values)
        except Exception as exc:
            self.counters.last_error = f"safe write failed: {type(exc).__name__}: {exc}"

    def health(self) -> BoardHealth:
        c = self.counters
        opened = self._req is not None
        return c.snapshot(
            ok=opened and c.consecutive_errors == 0, connected=opened, safe_active=False
        )
