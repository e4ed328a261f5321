"""Devices: sensor and actuator drivers on the device nodes (thesis 000, ch. 4.7).

A :class:`Device` connects the Data Vector to an I/O :class:`Board` (the
thesis' FPGA interface). A :class:`Sensor` reads the board, converts
electrical to engineering units, calibrates and writes the Data Vector; an
:class:`Actuator` reads the Data Vector and drives the board. Devices have no
mode: an actuator is safed by safing the controller that feeds it.

Each loop of a device node runs, in order (:class:`DeviceSet` and
:class:`~zplatform.loop.DeviceLogic`): the board's :meth:`Board.step`
(latch inputs; the simulated board's physics), the sensors, the node's
controllers, the actuators. A device that raises is counted in
``dnX_errors`` and reported by a ``WARNING_HI`` event (``EV.DEVICE_FAILED``)
once per failure streak;
the loop goes on and the device runs again next loop.

:class:`SimBoard` is the board of the lockstep runner and of tests: pins held
in lists, an optional physics hook (``physics: "module:function"`` in the
node's ``board`` config, called as ``function(board, t_ns)`` once per loop
before the sensors) that decides what the sensors see, and ``inject_*`` to
force an input (a stuck pin, a given voltage) from a test.

Shipped drivers: :class:`DigitalOutput` (the thesis' LED driver: sets a pin
from a command element and reads the pin back into a feedback element, which
proves the pin really changed), :class:`DigitalInput`, :class:`AnalogInput`
(``volts * scale + offset``) and :class:`AnalogOutput`.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Annotated, Any, Protocol, runtime_checkable

import msgspec
from msgspec import Meta

from .components import (
    Component,
    Streak,
    component_indices,
    decode_component_config,
    errors_element,
    load_component_class,
    load_function,
)
from .config import ComponentConfig, Mission
from .datavector import DataVector
from .errors import ConfigError, ControlError, SchedulerError, ZPlatformError
from .events import EV, EventLog
from .rategroups import RateGroups

__all__ = [
    "Actuator",
    "AnalogInput",
    "AnalogOutput",
    "Board",
    "Device",
    "DeviceSet",
    "DigitalInput",
    "DigitalOutput",
    "Sensor",
    "SimBoard",
    "SimBoardConfig",
    "check_config",
]


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


class SimBoardConfig(msgspec.Struct, forbid_unknown_fields=True):
    """The ``board:`` mapping of a node that runs on a :class:`SimBoard`.

    ``physics`` names a ``"module:function"`` called as ``function(board,
    t_ns)`` once per loop; ``params`` is its data (read as
    ``board.params``). If the function has a ``Params`` attribute (a
    ``msgspec.Struct`` type), ``params`` is decoded into it at construction,
    so a typo fails at load with its YAML path.
    """

    digital_pins: Annotated[int, Meta(ge=0, le=65_536)] = 16
    analog_pins: Annotated[int, Meta(ge=0, le=65_536)] = 8
    physics: str | None = None
    params: dict[str, Any] = msgspec.field(default_factory=dict)


Physics = Callable[["SimBoard", int], None]


class SimBoard:
    """A simulated I/O board: pins in lists, inputs injectable, optional physics.

    A digital pin reads back what was last set on it unless an input is
    injected (:meth:`inject_digital`); the same for analog pins. ``config`` is
    the node's ``board`` mapping (:class:`SimBoardConfig`); construction
    raises ConfigError naming ``where`` for a bad one. ``start_ns`` is the
    time of the first :meth:`step` (``None`` before), for physics that model
    time since start.
    """

    def __init__(self, config: dict[str, Any] | None = None, *, where: str = "$.board") -> None:
        cfg = decode_component_config(SimBoardConfig, dict(config or {}), where)
        self.config = cfg
        self._n_dig = cfg.digital_pins
        self._n_ana = cfg.analog_pins
        self._dout: list[bool] = [False] * cfg.digital_pins
        self._din: list[bool | None] = [None] * cfg.digital_pins
        self._aout: list[float] = [0.0] * cfg.analog_pins
        self._ain: list[float | None] = [None] * cfg.analog_pins
        self._physics: Physics | None = (
            load_function(cfg.physics, f"{where}.physics", args=("board", "t_ns"), what="physics")
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

    @property
    def digital_pins(self) -> int:
        return self._n_dig

    @property
    def analog_pins(self) -> int:
        return self._n_ana

    def step(self, t_ns: int) -> None:
        """Advance the simulated world to ``t_ns`` (calls the physics hook)."""
        if self.start_ns is None:
            self.start_ns = t_ns
        self.steps += 1
        if self._physics is not None:
            self._physics(self, t_ns)

    def _dpin(self, pin: int) -> int:
        if not 0 <= pin < self._n_dig:
            raise ControlError(f"digital pin {pin} out of range (board has {self._n_dig})")
        return pin

    def _apin(self, pin: int) -> int:
        if not 0 <= pin < self._n_ana:
            raise ControlError(f"analog pin {pin} out of range (board has {self._n_ana})")
        return pin

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

    def health(self) -> Any:
        """Always ok: a :class:`zplatform.boards.BoardHealth` (typed Any here:
        ``zplatform.boards`` imports this module)."""
        from .boards.base import BoardHealth

        return BoardHealth(ok=True)


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
                f"{self.name}: digital pin {pin} out of range; node {self.node}'s board has "
                f"{self.board.digital_pins}",
                f"{self.where}.config.{field}",
            )
        return pin

    def analog_pin(self, pin: int, field: str = "pin") -> int:
        """Check an analog pin number against the board (ConfigError)."""
        if not 0 <= pin < self.board.analog_pins:
            raise ConfigError(
                f"{self.name}: analog pin {pin} out of range; node {self.node}'s board has "
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
    the board's own safe state (:func:`zplatform.boards.safe_board`)."""

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
        pin: Pin
        command: str
        feedback: str | None = None
        invert: bool = False
        safe: bool = False  # the level ("on" terms) a lost control node leaves

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
        pin: Pin
        element: str
        invert: bool = False

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
        pin: Pin
        element: str
        scale: float = 1.0
        offset: float = 0.0

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
        pin: Pin
        command: str
        scale: float = 1.0
        offset: float = 0.0
        min_volts: float = -10.0
        max_volts: float = 10.0
        safe_volts: float = 0.0  # what a lost control node leaves on the pin

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
        for i in component_indices(mission, "devices", node):
            c = mission.devices[i]
            where = f"$.devices[{i}]"
            cls = load_component_class(c.cls, Device, f"{where}.class")
            if not issubclass(cls, Sensor | Actuator):
                raise ConfigError(
                    f"{c.cls!r} must subclass zplatform.devices.Sensor or Actuator",
                    f"{where}.class",
                )
            try:
                dev: Device = cls(c, dv, board, where=where)
            except ZPlatformError:
                raise
            except Exception as exc:
                raise ControlError(
                    f"device {c.name!r} ({c.cls}) failed to build: {type(exc).__name__}: {exc}"
                ) from exc
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
    from .datavector import Layout
    from .world import node_board  # the boards package (under it) imports this module

    for node in mission.device_nodes:
        board = node_board(mission, node)
        if not component_indices(mission, "devices", node):
            continue
        dv = DataVector(Layout.for_node(mission, node))
        DeviceSet(mission, node, dv, board)
