"""Tests of zplatform.control.devices: SimBoard, the physics hook, the shipped drivers,
DeviceSet failure handling and the device node's loop order."""

from __future__ import annotations

import textwrap

import msgspec
import pytest

from tests.drive import run_dn_loop
from zplatform import DataVector, Layout, decode_mission
from zplatform.boards import Board, SimBoard
from zplatform.config import Mission, parse_mission
from zplatform.control.controllers import Controller
from zplatform.control.devices import (
    Actuator,
    AnalogInput,
    Device,
    DeviceSet,
    DigitalOutput,
    Sensor,
)
from zplatform.control.loop import DeviceLogic
from zplatform.core.events import EventLog, Severity
from zplatform.errors import ConfigError, ControlError

PERIOD = 10_000_000
HERE = __name__

# -- helpers importable by "module:name" ----------------------------------------

physics_calls: list[tuple[int, int]] = []


def ramp(board: SimBoard, t_ns: int) -> None:
    """Physics: analog pin 0 reads the time since start in seconds."""
    assert board.start_ns is not None
    physics_calls.append((id(board), t_ns))
    board.inject_analog(0, (t_ns - board.start_ns) / 1e9)


def broken_physics(board: SimBoard, t_ns: int) -> None:
    raise RuntimeError("physics bug")


class TypedParams(msgspec.Struct, forbid_unknown_fields=True):
    gain: float = 1.0


def typed(board: SimBoard, t_ns: int) -> None:
    board.inject_analog(0, board.params.gain)


typed.Params = TypedParams  # type: ignore[attr-defined]


class Flaky(Sensor):
    """A sensor that raises while ``fail`` is set."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        element: str

    config: Config

    def bind(self, dv: DataVector) -> None:
        self.out = self.output(self.config.element, "element", kinds=("float",))
        self.fail = False
        self.runs = 0

    def run(self, t_ns: int) -> None:
        self.runs += 1
        if self.fail:
            raise OSError("bus error")
        self.out.set(1.0)


class PlainDevice(Device):
    def run(self, t_ns: int) -> None:
        pass


class HandleBind(Sensor):
    """A team's bind that takes a handle by a name the vector lacks, directly."""

    def bind(self, dv: DataVector) -> None:
        self.out = dv.handle("no_such_element")

    def run(self, t_ns: int) -> None:
        pass


class Follow(Controller):
    """DN controller: command = (sensor reading > 0.5)."""

    def bind(self, dv: DataVector) -> None:
        self.inp = self.input("volts")
        self.cmd = self.output("cmd")

    def run_enabled(self, t_ns: int) -> None:
        self.cmd.set(self.inp.get() > 0.5)

    def run_safed(self, t_ns: int) -> None:
        self.cmd.set(False)


BASE = """
mission: devtest
nodes:
  cn: {}
  dn0: {board: {digital_pins: 4, analog_pins: 2%s}}
regions:
  cn_to_dn0:
    - {name: led_cmd, type: bool}
  dn0_to_cn:
    - {name: led_fb, type: bool}
    - {name: volts, type: f64}
    - {name: temp, type: f32}
    - {name: cmd, type: bool}
    - {name: button, type: bool}
"""


def mission(
    devices: str = "", controllers: str = "", board: str = "", *, check: bool = True
) -> Mission:
    """The mission of BASE with these sections; ``check=False``: schema only
    (for tests of what DeviceSet itself refuses)."""
    text = BASE % board
    if devices:
        text += "devices:\n" + textwrap.indent(textwrap.dedent(devices), "  ")
    if controllers:
        text += "controllers:\n" + textwrap.indent(textwrap.dedent(controllers), "  ")
    return decode_mission(text) if check else parse_mission(text)


def devset(m: Mission, board: Board | None = None) -> tuple[DeviceSet, DataVector, EventLog]:
    dv = DataVector(Layout.for_node(m, "dn0"))
    ev = EventLog("dn0")
    board = board if board is not None else SimBoard(m.nodes["dn0"].board)
    return DeviceSet(m, "dn0", dv, board, ev), dv, ev


LED = "- {name: led, class: 'zplatform.control.devices:DigitalOutput', node: dn0, config: {pin: 2, command: led_cmd, feedback: led_fb}}\n"  # noqa: E501


# -- SimBoard -------------------------------------------------------------------


def test_simboard_digital_reads_back_output_unless_injected() -> None:
    b = SimBoard({"digital_pins": 3})
    assert b.digital_pins == 3 and b.analog_pins == 8
    b.set_digital(1, True)
    assert b.get_digital(1) is True
    b.inject_digital(1, False)  # stuck low
    assert b.get_digital(1) is False
    assert b.output_digital(1) is True
    b.inject_digital(1, None)
    assert b.get_digital(1) is True


def test_simboard_analog_and_injection() -> None:
    b = SimBoard({"analog_pins": 2})
    b.set_analog(0, 1.5)
    assert b.get_analog(0) == 1.5
    b.inject_analog(1, 3.25)
    assert b.get_analog(1) == 3.25
    b.inject_analog(1, None)
    assert b.get_analog(1) == 0.0


@pytest.mark.parametrize("pin", [-1, 4, 100])
def test_simboard_pins_out_of_range_raise(pin: int) -> None:
    b = SimBoard({"digital_pins": 4, "analog_pins": 4})
    for call in (
        lambda: b.set_digital(pin, True),
        lambda: b.get_digital(pin),
        lambda: b.set_analog(pin, 1.0),
        lambda: b.get_analog(pin),
        lambda: b.inject_digital(pin, True),
        lambda: b.inject_analog(pin, 1.0),
    ):
        with pytest.raises(ControlError, match="out of range"):
            call()


def test_simboard_is_a_board() -> None:
    assert isinstance(SimBoard(), Board)


def test_simboard_config_errors_name_the_path() -> None:
    with pytest.raises(ConfigError) as ei:
        SimBoard({"digital_pin": 3}, where="$.nodes.dn0.board")
    assert ei.value.path == "$.nodes.dn0.board"
    assert "digital_pin" in str(ei.value)
    with pytest.raises(ConfigError) as ei:
        SimBoard({"analog_pins": -1}, where="$.nodes.dn0.board")
    assert ei.value.path == "$.nodes.dn0.board.analog_pins"
    with pytest.raises(ConfigError, match="cannot import physics module") as ei:
        SimBoard({"physics": "no_such_zp_mod:f"}, where="$.b")
    assert ei.value.path == "$.b.physics"
    with pytest.raises(ConfigError, match="no function 'nope'"):
        SimBoard({"physics": f"{HERE}:nope"})


def test_physics_params_are_typed_when_the_hook_declares_them() -> None:
    b = SimBoard({"physics": f"{HERE}:typed", "params": {"gain": 2.5}})
    assert isinstance(b.params, TypedParams)
    b.step(0)
    assert b.get_analog(0) == 2.5
    with pytest.raises(ConfigError) as ei:
        SimBoard({"physics": f"{HERE}:typed", "params": {"gian": 2.5}}, where="$.nodes.dn0.board")
    assert ei.value.path == "$.nodes.dn0.board.params"


def test_physics_hook_runs_once_per_step_with_the_loop_time() -> None:
    physics_calls.clear()
    b = SimBoard({"physics": f"{HERE}:ramp"})
    assert b.start_ns is None
    for k in range(3):
        b.step(5 * PERIOD + k * PERIOD)
    assert b.start_ns == 5 * PERIOD
    assert physics_calls == [(id(b), 5 * PERIOD + k * PERIOD) for k in range(3)]
    assert b.get_analog(0) == pytest.approx(0.02)


# -- drivers ----------------------------------------------------------------------


def test_digital_output_sets_pin_and_reads_back_feedback() -> None:
    m = mission(LED)
    board = SimBoard(m.nodes["dn0"].board)
    ds, dv, _ = devset(m, board)
    dv.set("led_cmd", True)
    ds.run_actuators(0, 0)
    assert board.output_digital(2) is True
    assert dv.get("led_fb") is True
    # a pin that does not follow (stuck low): the feedback tells the truth
    board.inject_digital(2, False)
    ds.run_actuators(1, 0)
    assert dv.get("led_fb") is False
    board.inject_digital(2, None)
    dv.set("led_cmd", False)
    ds.run_actuators(2, 0)
    assert board.output_digital(2) is False and dv.get("led_fb") is False


def test_digital_output_invert() -> None:
    m = mission(LED.replace("feedback: led_fb", "feedback: led_fb, invert: true"))
    board = SimBoard(m.nodes["dn0"].board)
    ds, dv, _ = devset(m, board)
    dv.set("led_cmd", True)
    ds.run_actuators(0, 0)
    assert board.output_digital(2) is False  # active low
    assert dv.get("led_fb") is True


def test_digital_and_analog_inputs_with_calibration() -> None:
    m = mission(
        "- {name: btn, class: 'zplatform.control.devices:DigitalInput', node: dn0,"
        " config: {pin: 0, element: button, invert: true}}\n"
        "- {name: therm, class: 'zplatform.control.devices:AnalogInput', node: dn0,"
        " config: {pin: 1, element: temp, scale: 100.0, offset: -50.0}}\n"
    )
    board = SimBoard(m.nodes["dn0"].board)
    ds, dv, _ = devset(m, board)
    board.inject_digital(0, False)
    board.inject_analog(1, 0.75)
    ds.run_sensors(0, 0)
    assert dv.get("button") is True
    assert dv.get("temp") == pytest.approx(25.0)
    assert all(isinstance(d, Sensor) for d in ds.devices)


def test_analog_output_scales_and_clamps() -> None:
    m = mission(
        "- {name: dac, class: 'zplatform.control.devices:AnalogOutput', node: dn0,"
        " config: {pin: 1, command: volts, scale: 2.0, offset: 1.0, max_volts: 5.0}}\n"
    )
    board = SimBoard(m.nodes["dn0"].board)
    ds, dv, _ = devset(m, board)
    dv.set("volts", 7.0)
    ds.run_actuators(0, 0)
    assert board.get_analog(1) == 3.0
    dv.set("volts", 100.0)
    ds.run_actuators(1, 0)
    assert board.get_analog(1) == 5.0
    assert isinstance(ds.devices[0], Actuator)


@pytest.mark.parametrize(
    ("device", "path", "match"),
    [
        (LED.replace("pin: 2", "pin: 4"), "$.devices[0].config.pin", "digital pin 4 out of range"),
        (LED.replace("pin: 2", "pin: -1"), "$.devices[0].config.pin", "Expected `int` >= 0"),
        (LED.replace("command: led_cmd", "command: nope"), "$.devices[0].config.command", "nope"),
        (
            LED.replace("feedback: led_fb", "feedback: led_cmd"),
            "$.devices[0].config.feedback",
            "does not write",
        ),
        (LED.replace("feedback: led_fb", "feedbak: led_fb"), "$.devices[0].config", "feedbak"),
        (
            LED.replace("command: led_cmd", "command: volts"),
            "$.devices[0].config.command",
            "expected bool",
        ),
        (
            LED.replace("zplatform.control.devices:DigitalOutput", f"{HERE}:PlainDevice"),
            "$.devices[0].class",
            "must subclass",
        ),
        (
            LED.replace(
                "zplatform.control.devices:DigitalOutput",
                "zplatform.control.controllers:Controller",
            ),
            "$.devices[0].class",
            "is not a zplatform.control.devices.Device subclass",
        ),
    ],
)
def test_device_config_errors_name_the_path(device: str, path: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as ei:
        mission(device)  # refused at load ...
    assert ei.value.path == path
    m = mission(device, check=False)
    with pytest.raises(ConfigError, match=match) as ei:  # ... and by the set itself
        devset(m)
    assert ei.value.path == path


def test_a_device_that_raises_in_bind_names_its_yaml_path_and_class() -> None:
    """Anything a device's constructor raises (here the Data Vector's own
    error for an unknown name) comes out naming ``$.devices[i]`` and the class."""
    dev = f"- {{name: gauge, class: '{HERE}:HandleBind', node: dn0}}\n"
    for build in (lambda: mission(LED + dev), lambda: devset(mission(LED + dev, check=False))):
        with pytest.raises(ControlError) as ei:
            build()
        assert ei.value.path == "$.devices[1]"
        assert str(ei.value).startswith(
            f"device 'gauge' ({HERE}:HandleBind) failed to build: DataVectorError: "
        )
        assert "no_such_element" in str(ei.value)


def test_analog_input_pin_checked_against_board() -> None:
    m = mission(
        "- {name: a, class: 'zplatform.control.devices:AnalogInput', node: dn0,"
        " config: {pin: 2, element: temp}}\n",
        check=False,
    )
    with pytest.raises(ConfigError, match="analog pin 2 out of range"):
        devset(m)


# -- DeviceSet ----------------------------------------------------------------------


FLAKY = (
    f"- {{name: flaky, class: '{HERE}:Flaky', node: dn0, config: {{element: volts}}}}\n"
    "- {name: therm, class: 'zplatform.control.devices:AnalogInput', node: dn0,"
    " config: {pin: 1, element: temp}}\n"
)


def test_failing_device_is_counted_reported_once_per_streak_and_loop_goes_on() -> None:
    m = mission(FLAKY)
    board = SimBoard(m.nodes["dn0"].board)
    ds, dv, ev = devset(m, board)
    flaky = ds.devices[0]
    assert isinstance(flaky, Flaky)
    flaky.fail = True
    board.inject_analog(1, 0.5)
    for k in range(5):
        ds.run_sensors(k, k * PERIOD)
    assert dv.get("dn0_errors") == 5
    assert dv.get("temp") == 0.5  # the next device still ran
    events = ev.drain()
    assert [(Severity(e.severity).name, e.id) for e in events] == [("WARNING_HI", "device_failed")]
    assert "OSError: bus error" in events[0].text
    flaky.fail = False
    ds.run_sensors(5, 5 * PERIOD)
    flaky.fail = True
    ds.run_sensors(6, 6 * PERIOD)
    assert dv.get("dn0_errors") == 6
    assert len(ev.drain()) == 1  # a new streak, a new event


def test_device_rate_groups() -> None:
    m = mission(
        FLAKY.replace("config: {element: volts}}", "config: {element: volts}, rate_divisor: 4}")
    )
    ds, _, _ = devset(m)
    for k in range(8):
        ds.run_sensors(k, 0)
    flaky = ds.devices[0]
    assert isinstance(flaky, Flaky)
    assert flaky.runs == 2


def test_device_logic_order_board_sensors_controllers_actuators() -> None:
    """A reading reaches the actuator in the same loop (thesis 5.2.3, DN reaction time)."""
    m = mission(
        "- {name: meter, class: 'zplatform.control.devices:AnalogInput', node: dn0,"
        " config: {pin: 0, element: volts}}\n"
        "- {name: out, class: 'zplatform.control.devices:DigitalOutput', node: dn0,"
        " config: {pin: 1, command: cmd, feedback: button}}\n",
        controllers=(
            f"- {{name: follow, class: '{HERE}:Follow', node: dn0, initial_mode: enabled}}\n"
        ),
        board=f", physics: '{HERE}:ramp'",
    )
    logic = DeviceLogic(m, "dn0")
    t0 = 100 * PERIOD
    fired_at = None
    for k in range(1, 101):  # loop 1 at t0
        run_dn_loop(logic, k, t0 + (k - 1) * PERIOD)
        if fired_at is None and logic.dv.get("button"):
            fired_at = k
    # physics says volts > 0.5 from 0.51 s after loop 1 (loop 52); the pin
    # follows in that same loop
    assert fired_at == 52
    assert logic.dv.get("dn0_loop") == 100
    assert logic.dv.get("dn0_time_ns") == t0 + 99 * PERIOD
    assert logic.dv.get("dn0_errors") == 0


def test_device_logic_counts_a_broken_board_and_goes_on() -> None:
    m = mission(FLAKY, board=f", physics: '{HERE}:broken_physics'")
    logic = DeviceLogic(m, "dn0")
    for k in range(1, 4):
        run_dn_loop(logic, k, k * PERIOD)
    assert logic.dv.get("dn0_errors") == 3
    assert logic.dv.get("dn0_loop") == 3
    assert [e.id for e in logic.events.drain()] == ["board_failed"]


def test_device_logic_refuses_a_non_device_node() -> None:
    with pytest.raises(ConfigError, match="not a device node"):
        DeviceLogic(mission(), "cn")


def test_check_config_validates_boards_and_devices() -> None:
    from zplatform.control.devices import check_config

    check_config(mission(LED))
    with pytest.raises(ConfigError) as ei:
        check_config(mission(LED, board=", bogus: 1"))
    assert ei.value.path == "$.nodes.dn0.board"
    with pytest.raises(ConfigError):
        check_config(mission(LED.replace("pin: 2", "pin: 9")))


def test_digital_output_class_is_exported() -> None:
    assert issubclass(DigitalOutput, Actuator) and issubclass(AnalogInput, Sensor)
