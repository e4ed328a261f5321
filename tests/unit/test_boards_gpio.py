"""Tests of the gpiod board: the pin -> line mapping against a fake chip, and
one run on a real (gpio-sim) chip where the kernel offers one."""

from __future__ import annotations

import enum
import glob
import os
import sys
import types
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.drive import run_dn_loop
from zplatform import DataVector, Layout, decode_mission
from zplatform.boards import BoardError, close_board, make_board, open_board
from zplatform.boards.gpio import GpiodBoard
from zplatform.control.loop import DeviceLogic
from zplatform.errors import ControlError

WHERE = "$.nodes.dn0.board"

# -- a fake libgpiod v2 module: the surface GpiodBoard uses ------------------------


class Value(enum.Enum):
    INACTIVE = 0
    ACTIVE = 1


class Direction(enum.Enum):
    AS_IS = 1
    INPUT = 2
    OUTPUT = 3


class Bias(enum.Enum):
    AS_IS = 1
    UNKNOWN = 2
    DISABLED = 3
    PULL_UP = 4
    PULL_DOWN = 5


@dataclass
class LineSettings:
    direction: Direction = Direction.AS_IS
    bias: Bias = Bias.AS_IS
    active_low: bool = False
    output_value: Value = Value.INACTIVE


class FakeChip:
    """Physical line levels of one chip; active_low applied like the kernel does."""

    def __init__(self, path: str, lines: int = 32) -> None:
        self.path = path
        self.physical = [False] * lines
        self.settings: dict[int, LineSettings] = {}
        self.released = False
        self.fail = False
        self.set_calls = 0

    def logical(self, offset: int) -> bool:
        return self.physical[offset] is not self.settings[offset].active_low


class FakeRequest:
    def __init__(self, chip: FakeChip) -> None:
        self.chip = chip

    def get_values(self, offsets: list[int]) -> list[Value]:
        if self.chip.fail:
            raise OSError(5, "Input/output error")
        return [Value.ACTIVE if self.chip.logical(o) else Value.INACTIVE for o in offsets]

    def set_values(self, values: dict[int, Value]) -> None:
        if self.chip.fail:
            raise OSError(5, "Input/output error")
        self.chip.set_calls += 1
        for o, v in values.items():
            s = self.chip.settings[o]
            assert s.direction is Direction.OUTPUT, f"line {o} is not an output"
            self.chip.physical[o] = (v is Value.ACTIVE) is not s.active_low

    def release(self) -> None:
        self.chip.released = True


def fake_gpiod(chips: dict[str, FakeChip]) -> Any:
    def request_lines(path: str, config: dict[Any, LineSettings], consumer: str) -> FakeRequest:
        if path not in chips:
            raise FileNotFoundError(2, "No such file or directory", path)
        chip = chips[path]
        for key, s in config.items():
            for o in key if isinstance(key, tuple) else (key,):
                chip.settings[o] = s
                if s.direction is Direction.OUTPUT:
                    chip.physical[o] = (s.output_value is Value.ACTIVE) is not s.active_low
        return FakeRequest(chip)

    line = types.SimpleNamespace(Value=Value, Direction=Direction, Bias=Bias)
    return types.SimpleNamespace(request_lines=request_lines, LineSettings=LineSettings, line=line)


CFG = {
    "chip": "/dev/gpiochip7",
    "inputs": {0: 17, 1: 22},
    "outputs": {3: 27, 4: 5},
    "active_low": [1, 4],
    "bias": "pull-up",
    "safe": {4: True},
}


@pytest.fixture
def chip() -> FakeChip:
    return FakeChip("/dev/gpiochip7")


@pytest.fixture
def board(chip: FakeChip) -> GpiodBoard:
    b = GpiodBoard(dict(CFG), where=WHERE, gpiod_module=fake_gpiod({chip.path: chip}))
    b.open()
    return b


def test_lines_are_requested_as_mapped(chip: FakeChip, board: GpiodBoard) -> None:
    s = chip.settings
    assert sorted(s) == [5, 17, 22, 27]
    assert s[17].direction is Direction.INPUT and s[17].bias is Bias.PULL_UP
    assert s[22].active_low and not s[17].active_low
    assert s[27].direction is Direction.OUTPUT and s[27].output_value is Value.INACTIVE
    # outputs start at their safe value: pin 4 safe on, active low -> line 5 physically low
    assert s[5].output_value is Value.ACTIVE and chip.physical[5] is False
    assert board.digital_pins == 5 and board.analog_pins == 0


def test_step_writes_outputs_then_latches_every_line(chip: FakeChip, board: GpiodBoard) -> None:
    chip.physical[17] = True  # pin 0 high
    chip.physical[22] = True  # pin 1 active low: physically high reads off
    board.set_digital(3, True)
    board.set_digital(4, False)
    assert chip.physical[27] is False  # nothing reaches the chip before step
    board.step(0)
    assert chip.physical[27] is True and chip.physical[5] is True  # pin 4 off, active low
    assert board.get_digital(0) is True and board.get_digital(1) is False
    assert board.get_digital(3) is True and board.get_digital(4) is False  # read back
    chip.physical[17] = False
    assert board.get_digital(0) is True  # latched until the next step
    board.step(1)
    assert board.get_digital(0) is False
    assert board.health().ok and board.health().frames_sent == 2


@pytest.mark.parametrize("pin", [2, 5, -1])
def test_unmapped_pins_raise(board: GpiodBoard, pin: int) -> None:
    with pytest.raises(ControlError):
        board.get_digital(pin)


def test_inputs_cannot_be_driven_and_no_analog(board: GpiodBoard) -> None:
    with pytest.raises(ControlError, match="input"):
        board.set_digital(0, True)
    with pytest.raises(ControlError):
        board.get_analog(0)


def test_kernel_error_is_a_board_error_and_safe_applies(chip: FakeChip, board: GpiodBoard) -> None:
    board.set_digital(3, True)
    board.step(0)
    chip.fail = True
    with pytest.raises(BoardError, match="Input/output error"):
        board.step(1)
    h = board.health()
    assert not h.ok and h.consecutive_errors == 1 and "gpiochip7" in h.last_error
    chip.fail = False
    board.safe()
    assert chip.physical[27] is False and chip.physical[5] is False  # pin 3 off, pin 4 safe on
    board.step(2)
    assert board.health().ok
    board.close()
    board.close()
    assert chip.released


def test_open_fails_cleanly_without_the_chip() -> None:
    b = GpiodBoard({"chip": "/dev/nochip", "outputs": {0: 1}}, gpiod_module=fake_gpiod({}))
    with pytest.raises(BoardError, match="/dev/nochip"):
        b.open()


MISSION = """
mission: gpiotest
nodes:
  cn: {}
  dn0:
    board: {driver: gpiod, chip: /dev/gpiochip7, inputs: {0: 17}, outputs: {1: 27}}
regions:
  cn_to_dn0:
    - {name: led_cmd, type: bool}
  dn0_to_cn:
    - {name: led_fb, type: bool}
    - {name: button, type: bool}
devices:
  - {name: led, class: 'zplatform.control.devices:DigitalOutput', node: dn0,
     config: {pin: 1, command: led_cmd, feedback: led_fb}}
  - {name: button, class: 'zplatform.control.devices:DigitalInput', node: dn0,
     config: {pin: 0, element: button}}
"""


def test_device_node_drives_a_gpio_board_from_the_mission(
    chip: FakeChip, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The board imports gpiod at open(): the fake stands in for the module.
    monkeypatch.setitem(sys.modules, "gpiod", fake_gpiod({chip.path: chip}))
    mission = decode_mission(MISSION)
    board = make_board(mission.nodes["dn0"].board, where=WHERE)
    logic = DeviceLogic(mission, "dn0", board=board)
    open_board(board)
    chip.physical[17] = True
    cn = DataVector(Layout.for_node(mission, "cn"))
    cn.handle("led_cmd").set(True)  # the CN commands it
    for loop in range(1, 4):
        run_dn_loop(logic, loop, loop * 10_000_000, cn)
    assert chip.physical[27] is True
    assert bool(logic.dv.handle("button").get()) and bool(logic.dv.handle("led_fb").get())
    assert logic.dv.handle("dn0_errors").get() == 0
    close_board(board)
    assert chip.released and chip.physical[27] is False


def test_a_gpio_nodes_link_elements_count_io_cycles_and_failed_steps(
    chip: FakeChip, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A gpiod board has no link to time out: its dnX_board_* elements count
    I/O cycles (one write and one read per step) and dnX_board_ok says
    whether the last step's ioctls succeeded; the rest stay 0."""
    monkeypatch.setitem(sys.modules, "gpiod", fake_gpiod({chip.path: chip}))
    mission = decode_mission(MISSION)
    logic = DeviceLogic(mission, "dn0")  # the mission's own board
    assert isinstance(logic.board, GpiodBoard) and logic.board_link
    open_board(logic.board)
    dv = logic.dv

    def link() -> dict[str, int]:
        names = ("ok", "sent", "received", "timeouts", "late", "bad_frames", "reconnects")
        return {n: int(dv.get(f"dn0_board_{n}")) for n in names}

    for loop in (1, 2):
        run_dn_loop(logic, loop, loop * 10_000_000)
    quiet = {"timeouts": 0, "late": 0, "bad_frames": 0, "reconnects": 0}
    assert link() == {"ok": 1, "sent": 2, "received": 2, **quiet}
    chip.fail = True
    run_dn_loop(logic, 3, 30_000_000)
    assert link() == {"ok": 0, "sent": 2, "received": 2, **quiet}
    assert dv.get("dn0_errors") == 1
    chip.fail = False
    run_dn_loop(logic, 4, 40_000_000)
    assert link() == {"ok": 1, "sent": 3, "received": 3, **quiet}
    close_board(logic.board)


# -- a real chip: gpio-sim through configfs (root and the gpio-sim module) --------------

CONFIGFS = Path("/sys/kernel/config/gpio-sim")


def _real_chip_reason() -> str | None:
    if not glob.glob("/dev/gpiochip*") and not CONFIGFS.is_dir():
        return "no /dev/gpiochip* and no gpio-sim configfs (/sys/kernel/config/gpio-sim)"
    if not CONFIGFS.is_dir():
        return "gpio-sim configfs unavailable (modprobe gpio-sim; mount configfs)"
    if not os.access(CONFIGFS, os.W_OK):
        return "gpio-sim configfs is not writable (needs root)"
    try:
        import gpiod  # noqa: F401
    except ImportError:
        return "gpiod (libgpiod v2 bindings) not installed"
    return None


@pytest.mark.skipif(_real_chip_reason() is not None, reason=str(_real_chip_reason()))
@pytest.mark.timeout(30)
def test_real_chip_through_gpio_sim() -> None:
    """A gpio-sim chip of 8 lines: line 0 an input pulled up by the simulator, line 1 an output."""
    dev = CONFIGFS / f"zplatform-{uuid.uuid4().hex[:8]}"
    bank = dev / "bank0"
    bank.mkdir(parents=True)
    try:
        (bank / "num_lines").write_text("8")
        (dev / "live").write_text("1")
        chip_name = (bank / "chip_name").read_text().strip()
        dev_name = (dev / "dev_name").read_text().strip()
        sysfs = Path("/sys/devices/platform") / dev_name / chip_name
        (sysfs / "sim_gpio0" / "pull").write_text("pull-up")
        board = GpiodBoard({"chip": f"/dev/{chip_name}", "inputs": {0: 0}, "outputs": {1: 1}})
        board.open()
        try:
            board.set_digital(1, True)
            board.step(0)
            assert board.get_digital(0) is True
            assert (sysfs / "sim_gpio1" / "value").read_text().strip() == "1"
            (sysfs / "sim_gpio0" / "pull").write_text("pull-down")
            board.step(1)
            assert board.get_digital(0) is False
        finally:
            board.close()
        assert (sysfs / "sim_gpio1" / "value").read_text().strip() == "0"  # safed on close
    finally:
        (dev / "live").write_text("0")
        bank.rmdir()
        dev.rmdir()
