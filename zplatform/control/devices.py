"""Devices: sensor and actuator drivers on the device nodes (the thesis, ch. 4.7).

A :class:`Device` connects the Data Vector to an I/O
:class:`~zplatform.boards.Board` (the thesis' FPGA interface): a
:class:`Sensor` reads the board, converts to engineering units and writes
the Data Vector; an :class:`Actuator` reads the Data Vector and drives the
board. Devices have no mode: an actuator is safed by safing the controller
that feeds it. Shipped drivers: :class:`DigitalOutput` (the thesis' LED
driver, with read-back feedback), :class:`DigitalInput`,
:class:`AnalogInput` (``volts * scale + offset``) and :class:`AnalogOutput`.

Contract: :class:`DeviceSet` runs on the device node's loop thread, in order
(with :class:`~zplatform.control.loop.DeviceLogic`): the board's step, the sensors,
the node's controllers, the actuators. A device that raises is counted in
``dnX_errors`` and evented once per failure streak (``device_failed``); the
loop goes on. Boards live in :mod:`zplatform.boards` (this module imports
them, never the reverse).

Writing your own: docs/mission-reference.md#your-own-controllers-devices-boards-and-physics.
"""

from __future__ import annotations

import abc
from typing import Annotated, ClassVar

import msgspec
from msgspec import Meta

from ..boards import Board
from ..boards.world import node_board
from ..config import ComponentConfig, Mission
from ..core.components import (
    Component,
    Streak,
    build_component,
    component_indices,
    errors_element,
    load_component_class,
    mission_code_path,
)
from ..core.datavector import DataVector
from ..core.events import EV, EventLog
from ..errors import ConfigError, SchedulerError
from .rategroups import RateGroups

__all__ = [
    "Actuator",
    "AnalogInput",
    "AnalogOutput",
    "Device",
    "DeviceSet",
    "DigitalInput",
    "DigitalOutput",
    "Sensor",
    "check_config",
]


class Device(Component):
    """Base class of sensor and actuator drivers (thesis Figure 17).

    Contract: :meth:`run` takes the loop's timestamp, must not block or do
    I/O other than through ``self.board``, and may raise (the
    :class:`DeviceSet` counts it). Subclass :class:`Sensor` or
    :class:`Actuator`, not this class.
    """

    def __init__(
        self, spec: ComponentConfig, dv: DataVector, board: Board, *, where: str = "$"
    ) -> None:
        self.board = board
        super().__init__(spec, dv, where=where)

    @abc.abstractmethod
    def run(self, t_ns: int) -> None:
        """One loop of the driver."""

    def digital_pin(self, pin: int, field: str = "pin") -> int:
        """Check a digital pin number against the board (ConfigError)."""
        if not 0 <= pin < self.board.digital_pins:
            raise ConfigError(
                f"digital pin {pin} out of range; node {self.node}'s board has "
                f"{self.board.digital_pins}",
                f"{self.where}.config.{field}",
            )
        return pin

    def analog_pin(self, pin: int, field: str = "pin") -> int:
        """Check an analog pin number against the board (ConfigError)."""
        if not 0 <= pin < self.board.analog_pins:
            raise ConfigError(
                f"analog pin {pin} out of range; node {self.node}'s board has "
                f"{self.board.analog_pins}",
                f"{self.where}.config.{field}",
            )
        return pin


class Sensor(Device):
    """A device that reads the board and writes the Data Vector (runs before controllers)."""


class Actuator(Device):
    """A device that reads the Data Vector and drives the board (runs after controllers).

    :meth:`safe` drives the output to its declared safe value: a device node
    that lost its control node calls it (and on a clean exit). Subclasses
    that drive hardware must override it; the default leaves the output to
    the board's own safe state (:func:`zplatform.boards.safe_board`), and
    ``zplatform check`` warns about it (:mod:`zplatform.mission.safety`).

    ``pyrotechnic``: the output fires something that cannot be undone (an
    igniter, a pyro cutter). A class that always does sets it True; a
    generic driver may take it from its config instead (``DigitalOutput``'s
    ``pyrotechnic: true``). ``zplatform check`` warns about a mission with a
    pyrotechnic output and no hazardous command."""

    pyrotechnic: ClassVar[bool] = False

    def safe(self, t_ns: int) -> None:
        """Drive the output to its safe value now. Must not block."""


Pin = Annotated[int, Meta(ge=0)]


class DigitalOutput(Actuator):
    """Sets a digital pin from ``command`` and reads it back into ``feedback``.

    The thesis' LED driver: the feedback element is the pin's actual level
    read from the board after setting it, so control logic can verify that
    the pin changed. ``invert`` for active-low outputs (command and feedback
    stay in "on" terms).
    """

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        pin: Annotated[Pin, Meta(description="The board's digital pin.")]
        command: Annotated[
            str,
            Meta(description="Element that commands the pin (bool, int or enum: non-zero is on)."),
        ]
        feedback: Annotated[
            str | None,
            Meta(
                description="Element (bool or int, in this node's `dnX_to_cn`) that receives "
                "the pin's level read back from the board."
            ),
        ] = None
        invert: Annotated[
            bool,
            Meta(description='Active low: command and feedback stay in "on" terms.'),
        ] = False
        safe: Annotated[
            bool,
            Meta(description='The level (in "on" terms) a device node that lost its CN leaves.'),
        ] = False
        # The pin fires something that cannot be undone (an igniter): the
        # mission then needs hazardous commands (zplatform.mission.safety).
        pyrotechnic: Annotated[
            bool,
            Meta(
                description="The pin fires something that cannot be undone (an igniter); "
                "`zplatform check` warns when such a mission has no hazardous command."
            ),
        ] = False

    config: Config

    def bind(self, dv: DataVector) -> None:
        cfg = self.config
        self._pin = self.digital_pin(cfg.pin)
        self._cmd = self.input(cfg.command, "command", kinds=("bool", "int", "enum"))
        self._fb = (
            self.output(cfg.feedback, "feedback", kinds=("bool", "int"))
            if cfg.feedback is not None
            else None
        )
        self._inv = cfg.invert

    def run(self, t_ns: int) -> None:
        inv = self._inv
        self.board.set_digital(self._pin, bool(self._cmd.get()) is not inv)
        if self._fb is not None:
            self._fb.set(self.board.get_digital(self._pin) is not inv)

    def safe(self, t_ns: int) -> None:
        inv = self._inv
        self.board.set_digital(self._pin, self.config.safe is not inv)
        if self._fb is not None:
            self._fb.set(self.board.get_digital(self._pin) is not inv)


class DigitalInput(Sensor):
    """Reads a digital pin into ``element`` (``invert`` for active-low inputs)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        pin: Annotated[Pin, Meta(description="The board's digital pin.")]
        element: Annotated[
            str, Meta(description="Element (bool or int, in this node's `dnX_to_cn`) to write.")
        ]
        invert: Annotated[bool, Meta(description="Active low: a low pin reads `true`.")] = False

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._pin = self.digital_pin(self.config.pin)
        self._out = self.output(self.config.element, "element", kinds=("bool", "int"))
        self._inv = self.config.invert

    def run(self, t_ns: int) -> None:
        self._out.set(self.board.get_digital(self._pin) is not self._inv)


class AnalogInput(Sensor):
    """Reads an analog pin: ``element = volts * scale + offset`` (a linear calibration)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        pin: Annotated[Pin, Meta(description="The board's analog pin.")]
        element: Annotated[
            str, Meta(description="Float element (in this node's `dnX_to_cn`) to write.")
        ]
        scale: Annotated[float, Meta(description="Engineering units per volt.")] = 1.0
        offset: Annotated[float, Meta(description="Engineering units at 0 V.")] = 0.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._pin = self.analog_pin(self.config.pin)
        self._out = self.output(self.config.element, "element", kinds=("float",))
        self._scale = self.config.scale
        self._offset = self.config.offset

    def run(self, t_ns: int) -> None:
        self._out.set(self.board.get_analog(self._pin) * self._scale + self._offset)


class AnalogOutput(Actuator):
    """Drives an analog pin: ``volts = (command - offset) / scale``, clamped to [lo, hi]."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        pin: Annotated[Pin, Meta(description="The board's analog pin.")]
        command: Annotated[
            str, Meta(description="Element (float or int) holding the commanded value.")
        ]
        scale: Annotated[float, Meta(description="Engineering units per volt (not 0).")] = 1.0
        offset: Annotated[float, Meta(description="Engineering units at 0 V.")] = 0.0
        min_volts: Annotated[float, Meta(description="Lowest voltage driven.")] = -10.0
        max_volts: Annotated[float, Meta(description="Highest voltage driven.")] = 10.0
        safe_volts: Annotated[
            float,
            Meta(
                description="What a device node that lost its CN leaves on the pin (within "
                "`min_volts`..`max_volts`)."
            ),
        ] = 0.0

        def __post_init__(self) -> None:
            if self.scale == 0.0:
                raise ValueError("scale must not be 0")
            if self.min_volts > self.max_volts:
                raise ValueError("min_volts must not exceed max_volts")
            if not self.min_volts <= self.safe_volts <= self.max_volts:
                raise ValueError("safe_volts must lie within [min_volts, max_volts]")

    config: Config

    def bind(self, dv: DataVector) -> None:
        cfg = self.config
        self._pin = self.analog_pin(cfg.pin)
        self._cmd = self.input(cfg.command, "command", kinds=("float", "int"))
        self._scale, self._offset = cfg.scale, cfg.offset
        self._lo, self._hi = cfg.min_volts, cfg.max_volts

    def run(self, t_ns: int) -> None:
        v = (self._cmd.get() - self._offset) / self._scale
        self.board.set_analog(self._pin, min(max(v, self._lo), self._hi))

    def safe(self, t_ns: int) -> None:
        self.board.set_analog(self._pin, self.config.safe_volts)


class _DevSlot:
    __slots__ = ("device", "streak")

    def __init__(self, device: Device) -> None:
        self.device = device
        self.streak = Streak()


class DeviceSet:
    """One device node's sensors and actuators, built from the mission.

    Construction imports each ``class`` (a :class:`Sensor` or
    :class:`Actuator` subclass), decodes its config, checks its pins against
    ``board`` and binds its handles; ConfigError names ``$.devices[i]...``.
    :meth:`run_sensors` and :meth:`run_actuators` run the devices due on the
    loop (rate groups), in configuration order, and never raise for a
    device's exception: it is counted in ``dnX_errors`` and reported by one
    ``WARNING_HI`` event (``EV.DEVICE_FAILED``) per failure streak.
    """

    def __init__(
        self,
        mission: Mission,
        node: str,
        dv: DataVector,
        board: Board,
        events: EventLog | None = None,
    ) -> None:
        self.node = node
        self.dv = dv
        self.board = board
        self.events = events
        self.devices: list[Device] = []
        self._sensors: RateGroups[_DevSlot] = RateGroups()
        self._actuators: RateGroups[_DevSlot] = RateGroups()
        self._errors = dv.handle(errors_element(node))
        code = mission_code_path(mission)
        for i in component_indices(mission, "devices", node):
            c = mission.devices[i]
            where = f"$.devices[{i}]"
            cls = load_component_class(c.cls, Device, f"{where}.class", pythonpath=code)
            if not issubclass(cls, Sensor | Actuator):
                raise ConfigError(
                    f"{c.cls!r} must subclass zplatform.control.devices.Sensor or Actuator",
                    f"{where}.class",
                )
            dev: Device = build_component("device", c, where, cls, c, dv, board)
            dev.events = events
            groups = self._sensors if isinstance(dev, Sensor) else self._actuators
            try:
                groups.add(_DevSlot(dev), c.rate_divisor, c.rate_phase)
            except SchedulerError as exc:
                raise ConfigError(str(exc), f"{where}.rate_phase") from exc
            self.devices.append(dev)

    def __len__(self) -> int:
        return len(self.devices)

    def run_sensors(self, loop: int, t_ns: int) -> None:
        """Run the sensors due on ``loop``."""
        self._run(self._sensors, loop, t_ns)

    def run_actuators(self, loop: int, t_ns: int) -> None:
        """Run the actuators due on ``loop``."""
        self._run(self._actuators, loop, t_ns)

    def safe_actuators(self, t_ns: int) -> None:
        """Every actuator's :meth:`Actuator.safe`, whatever its rate group; a
        failure is counted and reported like a run's, and the others still go."""
        for g in self._actuators:
            s = g.member
            try:
                assert isinstance(s.device, Actuator)
                s.device.safe(t_ns)
            except Exception as exc:
                self._failed(s, exc, t_ns)

    def _run(self, group: RateGroups[_DevSlot], loop: int, t_ns: int) -> None:
        for s in group.due(loop):
            try:
                s.device.run(t_ns)
            except Exception as exc:
                self._failed(s, exc, t_ns)
                continue
            s.streak.ok()

    def _failed(self, s: _DevSlot, exc: Exception, t_ns: int) -> None:
        self._errors.bump()
        if s.streak.fail() == 1 and self.events is not None:
            d = s.device
            self.events.emit(
                EV.DEVICE_FAILED, t_ns, name=d.name, exc_type=type(exc).__name__, exc=exc
            )


def check_config(mission: Mission) -> None:
    """Build every device node's devices on a scratch vector and its board
    (built from the mission, not opened).

    Raises ConfigError with the YAML path of the first bad device class,
    config field, pin or element name, or board config.
    """
    from ..core.datavector import Layout

    for node in mission.device_nodes:
        board = node_board(mission, node)
        if not component_indices(mission, "devices", node):
            continue
        dv = DataVector(Layout.for_node(mission, node))
        DeviceSet(mission, node, dv, board)
