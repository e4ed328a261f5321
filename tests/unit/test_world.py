"""The vehicle world (zplatform.world.model): one physical state behind several nodes' boards.

A toy physics here: a "lamp" that is lit only while both nodes' switches are
on (two switches in series, like a chute's igniter circuit), whose
brightness both nodes read on an analog pin, and a step counter.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from tests.drive import run_dn_loop
from zplatform import LockstepRunner, World, decode_mission
from zplatform.boards import BoardError
from zplatform.boards.world import WorldLink, node_board
from zplatform.control.loop import DeviceLogic
from zplatform.errors import ConfigError
from zplatform.sim.world_server import serve
from zplatform.world.checks import check_config as check_world

HERE = __name__


def lamp(world: Any, t_ns: int) -> None:
    """Toy physics: lit iff dn0 pin 0 and dn1 pin 0 are both on."""
    b = world.boards
    lit = b["dn0"].output_digital(0) and b["dn1"].output_digital(0)
    world.state["calls"] = world.state.get("calls", 0) + 1
    for n in ("dn0", "dn1"):
        b[n].inject_analog(0, 5.0 if lit else 0.0)
        b[n].inject_digital(1, lit)


def checked(world: Any, t_ns: int) -> None:
    """Toy physics with a load-time check of its params."""


def _check_board_named(world: Any) -> None:
    if world.params["board"] not in world.boards:
        raise ValueError(f"no board {world.params['board']!r}")


checked.check = _check_board_named  # type: ignore[attr-defined]


def mission_text(port: int = 7499, board: str = "{driver: world}", world: str = "") -> str:
    return f"""
mission: lamp
nodes:
  cn: {{listen: ["tcp/127.0.0.1:7490"]}}
  dn0: {{listen: ["tcp/127.0.0.1:7491"], connect: ["tcp/127.0.0.1:7490"], board: {board}}}
  dn1: {{listen: ["tcp/127.0.0.1:7492"], connect: ["tcp/127.0.0.1:7490"], board: {{driver: world}}}}
world:
  physics: "{HERE}:lamp"
  listen: "127.0.0.1:{port}"
  boards:
    dn0: {{digital_pins: 2, analog_pins: 1}}
    dn1: {{digital_pins: 2, analog_pins: 1}}
{world}
regions:
  cn:
    - {{name: both, type: bool}}
  cn_to_dn0:
    - {{name: sw0, type: bool}}
  dn0_to_cn:
    - {{name: lit0, type: f32}}
  cn_to_dn1:
    - {{name: sw1, type: bool}}
  dn1_to_cn:
    - {{name: lit1, type: f32}}
devices:
  - {{name: s0, class: "zplatform.control.devices:DigitalOutput",
     node: dn0, config: {{pin: 0, command: sw0}}}}
  - {{name: l0, class: "zplatform.control.devices:AnalogInput",
     node: dn0, config: {{pin: 0, element: lit0}}}}
  - {{name: s1, class: "zplatform.control.devices:DigitalOutput",
     node: dn1, config: {{pin: 0, command: sw1}}}}
  - {{name: l1, class: "zplatform.control.devices:AnalogInput",
     node: dn1, config: {{pin: 0, element: lit1}}}}
"""


def test_the_world_advances_once_per_time_and_both_nodes_share_it() -> None:
    m = decode_mission(mission_text())
    world = World(m)
    b0, b1 = world.board("dn0"), world.board("dn1")
    b0.step(10)
    b1.step(10)  # same time: the physics does not run twice
    assert world.state["calls"] == 1
    b0.set_digital(0, True)
    b0.step(20)
    assert b1.get_analog(0) == 0.0  # one switch is not enough
    b1.set_digital(0, True)
    b1.step(30)
    assert b0.get_analog(0) == 5.0 and b1.get_analog(0) == 5.0
    assert b0.get_digital(1) and world.state["calls"] == 3
    b0.safe()  # a safed node opens its switch: the world sees it
    b0.step(40)
    assert b1.get_analog(0) == 0.0


def test_the_world_boards_have_the_pins_the_world_section_gives() -> None:
    text = mission_text().replace("dn1: {digital_pins: 2, analog_pins: 1}", "dn1: {}")
    world = World(decode_mission(text.replace("pin: 0, command: sw1", "pin: 7, command: sw1")))
    assert (world.boards["dn1"].digital_pins, world.boards["dn1"].analog_pins) == (8, 8)


def test_lockstep_runs_the_world_in_process() -> None:
    m = decode_mission(mission_text())
    r = LockstepRunner(m)
    assert r.world is not None and set(r.world.nodes) == {"dn0", "dn1"}
    r.control.dv.set("sw0", True)
    r.control.dv.set("sw1", True)
    r.run(0.05)
    assert r.control.dv.get("lit0") == 5.0 and r.control.dv.get("lit1") == 5.0
    assert r.world.state["calls"] == r.loop  # once per loop, not once per node


@pytest.mark.parametrize(
    ("text", "path", "match"),
    [
        (mission_text().replace("world:", "wurld:", 1), "$", "wurld"),
        (
            mission_text(port=0).replace("127.0.0.1:0", "10.0.0.1:7499"),
            "$.world.listen",
            "loopback",
        ),
        (mission_text().replace(f"{HERE}:lamp", "os:getcwd"), "$.world.physics", "signature"),
        (
            mission_text().replace("dn1: {digital_pins", "dn7: {digital_pins"),
            "$.world.boards.dn7",
            "not a device node",
        ),
        (mission_text(board="{driver: world, port: x}"), "$.nodes.dn0.board.port", "no other"),
        (
            mission_text(world="  serve_serial: {dn0: /tmp/x}"),
            "$.world.serve_serial.dn0",
            "driver: serial",
        ),
    ],
)
def test_bad_worlds_are_refused_with_their_path(text: str, path: str, match: str) -> None:
    with pytest.raises(ConfigError) as exc:
        decode_mission(text)
    assert exc.value.path.startswith(path), exc.value
    assert match in str(exc.value)


def test_the_physics_checks_its_params_at_load() -> None:
    text = mission_text().replace(f"{HERE}:lamp", f"{HERE}:checked")
    decode_mission(text.replace("boards:\n", "params: {board: dn1}\n  boards:\n", 1))
    with pytest.raises(ConfigError, match="no board 'dn9'") as exc:
        decode_mission(text.replace("boards:\n", "params: {board: dn9}\n  boards:\n", 1))
    assert exc.value.path == "$.world.params"


def test_a_world_board_without_a_world_is_refused() -> None:
    text = mission_text()
    text = text[: text.index("world:")] + text[text.index("regions:") :]
    with pytest.raises(ConfigError, match="needs a world section") as exc:
        decode_mission(text)
    assert exc.value.path == "$.nodes.dn0.board.driver"


@pytest.fixture
def world_process() -> Iterator[Any]:
    """serve() in a thread on a free port (the live world process's loop)."""
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    m = decode_mission(mission_text(port=port))
    stop = threading.Event()
    ready = threading.Event()
    t = threading.Thread(target=serve, args=(m,), kwargs={"stop": stop, "ready": ready.set})
    t.start()
    assert ready.wait(10)
    yield m
    stop.set()
    t.join(10)


def test_live_boards_share_the_world_process(world_process: Any) -> None:
    """Two device nodes' WorldLink boards on one world process: outputs
    reach it when set, each node latches the inputs the world pushes."""
    import time

    from zplatform import DataVector, Layout

    m = world_process
    d0, d1 = DeviceLogic(m, "dn0"), DeviceLogic(m, "dn1")
    assert isinstance(d0.board, WorldLink) and isinstance(node_board(m, "dn1"), WorldLink)
    cn = DataVector(Layout.for_node(m, "cn"))
    loop = 0

    def until(pred: Any, what: str, nodes: tuple[DeviceLogic, ...] = (d0, d1)) -> None:
        nonlocal loop
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            loop += 1
            for d in nodes:
                run_dn_loop(d, loop, loop * 10_000_000, cn)
            if pred():
                return
        raise AssertionError(f"timed out waiting for {what}")

    for d in (d0, d1):
        d.board.open()  # type: ignore[attr-defined]
        # the world pushes inputs once it has heard from a board: wait for them
        deadline = time.monotonic() + 10
        while d.board.health().frames_received == 0:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, "no inputs from the world"
            try:
                d.board.step(0)
            except BoardError:
                pass
    until(lambda: True, "a loop")
    assert d0.dv.get("lit0") == 0.0  # both switches open
    cn.set("sw0", True)
    until(lambda: True, "a loop")
    assert d1.dv.get("lit1") == 0.0  # one switch is not enough
    cn.set("sw1", True)
    until(lambda: d0.dv.get("lit0") == 5.0 and d1.dv.get("lit1") == 5.0, "the lamp lit")
    d1.safe(0, "test")  # dn1 safes (and stops): its switch opens in the world
    until(lambda: d0.dv.get("lit0") == 0.0, "the lamp out after dn1 safed", (d0,))
    assert int(d0.dv.get("dn0_errors")) == 0 and int(d1.dv.get("dn1_errors")) == 0
    for d in (d0, d1):
        d.board.close()  # type: ignore[attr-defined]


def test_a_link_without_a_world_fails_its_step_and_is_counted() -> None:
    m = decode_mission(mission_text(port=7498))
    link = WorldLink(m, "dn0", where="$.nodes.dn0.board")
    with pytest.raises(BoardError, match="not open"):
        link.step(0)
    link.open()
    for _ in range(2):
        with pytest.raises(BoardError, match=r"no inputs|not there"):
            link.step(0)
    h = link.health()
    assert not h.ok and h.errors == 3
    link.close()
    check_world(m)  # the mission itself is fine
