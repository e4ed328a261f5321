"""End to end: SerialBoard (pyserial) <-> simulated device process behind a pty.

The device (``python -m zplatform.boards.serial_sim``) owns a pty pair and
points a symlink at its slave side; the host opens the symlink, as it would
open ``/dev/serial/by-id/...`` for a USB serial adapter. A cable pull is the
device process being killed (its pty vanishes: the host's reads fail); a
re-plug is a new device process repointing the same symlink at its new pty,
which is what udev does for a re-enumerated USB device. Readiness is awaited
through the handshake (``wait_connected``), never by sleeping.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("serial")

from tests.drive import run_dn_loop
from zplatform import DataVector, Layout, decode_mission
from zplatform.boards import BoardError, close_board, make_board, open_board
from zplatform.boards.serialboard import SerialBoard
from zplatform.control.loop import DeviceLogic

pytestmark = pytest.mark.timeout(60)


class SimProcess:
    """One simulated device process; killed and reaped by :meth:`stop`."""

    def __init__(self, link: Path, *extra: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "zplatform.boards.serial_sim", "--link", str(link), *extra],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # EOF (test fails) if the process dies
        assert line.startswith("READY "), f"simulator did not start: {line!r}"

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


@pytest.fixture
def sims(tmp_path: Path) -> Iterator[list[SimProcess]]:
    started: list[SimProcess] = []
    yield started
    for s in started:
        s.stop()


def start(sims: list[SimProcess], link: Path, *extra: str) -> SimProcess:
    s = SimProcess(link, *extra)
    sims.append(s)
    return s


# The functional tests are not timing tests: the simulator is a Python process on
# a shared machine, whose round trip over the pty is usually well under 1 ms
# but sometimes above 2 ms. The timeout test below keeps the 2 ms default.
SLACK = {"reply_timeout_ms": 50.0}
INJECT = ("--inject-digital", "4=1", "--inject-analog", "1=1.25")


def test_outputs_inputs_and_garbage(tmp_path: Path, sims: list[SimProcess]) -> None:
    link = tmp_path / "ttyBOARD"
    sim = start(sims, link, *INJECT)
    board = SerialBoard({"port": str(link), "digital_pins": 8, "analog_pins": 2, **SLACK})
    board.open()
    try:
        assert board.wait_connected(10), board.health()
        board.set_digital(0, True)
        board.set_analog(0, 3.5)
        board.step(0)
        assert board.get_digital(0) is True  # output read back from the device
        assert board.get_digital(1) is False
        assert board.get_digital(4) is True  # injected input
        assert board.get_analog(0) == 3.5
        assert board.get_analog(1) == 1.25
        board.set_digital(0, False)
        board.step(1)
        assert board.get_digital(0) is False

        # Garbage, a truncated frame and a bad CRC before the next reply: all
        # skipped and counted, and the reply itself still gets through.
        before = board.health().bad_frames
        sim.signal(signal.SIGUSR1)
        for i in range(20):  # the signal is asynchronous: within a few exchanges
            board.step(2 + i)
            if board.health().bad_frames >= before + 3:
                break
        h = board.health()
        assert h.bad_frames >= before + 3, h
        assert h.ok and h.timeouts == 0 and h.errors == 0, h
    finally:
        board.close()


def test_cable_pull_safes_and_reconnects(tmp_path: Path, sims: list[SimProcess]) -> None:
    link = tmp_path / "ttyBOARD"
    sim = start(sims, link)
    board = SerialBoard(
        {
            "port": str(link),
            "digital_pins": 4,
            "analog_pins": 1,
            "reconnect_min_ms": 10,
            "reconnect_max_ms": 100,
            "safe_after": 1,
            **SLACK,
        }
    )
    board.open()
    try:
        assert board.wait_connected(10)
        board.set_digital(0, True)
        board.step(0)
        assert board.get_digital(0) is True

        sim.stop()  # cable pull
        # The first step after it fails, whichever thread sees the dead port
        # first (the loop thread's write, or the I/O thread's read): the link
        # is down from that step on, never reported connected.
        with pytest.raises(BoardError, match=r"write failed|link down"):
            board.step(1)
        h = board.health()
        assert not h.ok and not h.connected and h.safe_active, h
        assert h.consecutive_errors == 1 and h.errors == 1, h
        with pytest.raises(BoardError, match="link down"):
            board.step(100)

        # Re-plug: a new device on the same path. The host reconnects on its
        # own, handshakes, and its first WRITE carries the safe values.
        start(sims, link)
        assert board.wait_connected(10), board.health()
        board.step(101)
        assert board.get_digital(0) is False  # safe value, although the command is on
        h = board.health()
        assert h.ok and h.reconnects == 1 and not h.safe_active, h
        board.step(102)
        assert board.get_digital(0) is True  # commands flow again
    finally:
        board.close()


def test_timeout_counts_as_error_and_step_stays_bounded(
    tmp_path: Path, sims: list[SimProcess]
) -> None:
    link = tmp_path / "ttyBOARD"
    sim = start(sims, link)
    board = SerialBoard(
        {"port": str(link), "digital_pins": 2, "reply_timeout_ms": 2.0, "safe_after": 1}
    )
    board.open()
    try:
        assert board.wait_connected(10)
        sim.signal(signal.SIGSTOP)  # a hung device: the port stays, no replies
        t0 = time.perf_counter()
        with pytest.raises(BoardError, match="no INPUTS"):
            board.step(1)
        # Bounded by its 2 ms reply timeout, not by anything the hung device
        # holds up (the read timeout, the 500 ms handshake): the bound leaves
        # a busy 2-core box room to run this test's thread late.
        assert time.perf_counter() - t0 < 0.4
        h = board.health()
        assert h.timeouts == 1 and not h.ok and h.safe_active
        sim.signal(signal.SIGCONT)
    finally:
        board.close()


MISSION = """
mission: serialtest
nodes:
  cn: {}
  dn0:
    board: {driver: serial, port: "%s", digital_pins: 8, analog_pins: 2, reply_timeout_ms: 50}
regions:
  cn_to_dn0:
    - {name: led_cmd, type: bool}
  dn0_to_cn:
    - {name: led_fb, type: bool}
    - {name: button, type: bool}
    - {name: volts, type: f64}
devices:
  - {name: led, class: 'zplatform.control.devices:DigitalOutput', node: dn0,
     config: {pin: 0, command: led_cmd, feedback: led_fb}}
  - {name: button, class: 'zplatform.control.devices:DigitalInput', node: dn0,
     config: {pin: 4, element: button}}
  - {name: volts, class: 'zplatform.control.devices:AnalogInput', node: dn0,
     config: {pin: 1, element: volts, scale: 2.0}}
"""


def test_device_node_drives_a_serial_board_from_the_mission(
    tmp_path: Path, sims: list[SimProcess]
) -> None:
    link = tmp_path / "ttyBOARD"
    start(sims, link, *INJECT)
    mission = decode_mission(MISSION % link)
    board = make_board(mission.nodes["dn0"].board, where="$.nodes.dn0.board")
    assert isinstance(board, SerialBoard)
    logic = DeviceLogic(mission, "dn0", board=board)
    open_board(board)
    try:
        assert board.wait_connected(10)
        cn = DataVector(Layout.for_node(mission, "cn"))
        cn.handle("led_cmd").set(True)  # the CN commands it
        for loop in range(1, 4):  # set in loop 1, sent in 2, read back in 2's actuators
            run_dn_loop(logic, loop, loop * 10_000_000, cn)
        assert logic.dv.handle("dn0_errors").get() == 0
        assert logic.dv.handle("led_fb").get() is True or logic.dv.handle("led_fb").get() == 1
        assert bool(logic.dv.handle("button").get())
        assert logic.dv.handle("volts").get() == pytest.approx(2.5)
    finally:
        close_board(board)
    assert os.path.islink(link)


def test_a_second_host_cannot_share_the_port(tmp_path: Path, sims: list[SimProcess]) -> None:
    link = tmp_path / "ttyBOARD"
    start(sims, link)
    first = SerialBoard({"port": str(link), **SLACK})
    second = SerialBoard({"port": str(link), "reconnect_min_ms": 20, **SLACK})
    first.open()
    try:
        assert first.wait_connected(10)
        second.open()
        assert not second.wait_connected(0.3)
        with pytest.raises(BoardError, match="cannot open"):
            second.step(0)
        first.step(0)
        assert first.health().ok
    finally:
        second.close()
        first.close()
