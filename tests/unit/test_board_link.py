"""A device node's board link in telemetry (``dnX_board_*``) and in its summary.

Which nodes get the elements (a serial or gpiod board only, so every other
mission keeps its layout), what the loop writes into them after each board
step (a serial board over an in-memory port with the protocol's simulated
device behind it: timeouts, late replies, bad frames, device errors and a
reconnect injected one at a time), saturation, nothing kept per loop, and
the summary's board line."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.drive import run_dn_loop
from tests.serial_port import MemoryPort
from zplatform import DataVector, Layout, RegionCodec, SimBoard, decode_mission, load_mission
from zplatform.boards import BoardHealth, HealthCounters, board_health, wire
from zplatform.boards.serialboard import SerialBoard
from zplatform.cli.supervisor import format_board_lines
from zplatform.config import (
    BOARD_LINK_COUNTERS,
    Mission,
    NodeConfig,
    board_link_elements,
    platform_elements,
)
from zplatform.control.loop import DeviceLogic
from zplatform.errors import ConfigError
from zplatform.sim.lockstep import LockstepRunner
from zplatform.telemetry.summary import DnSummary, RunSummary, read_summary, write_summary

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
WAIT_S = 30.0  # a hang detector, not a speed limit
PERIOD_NS = 10_000_000
LINK = ["dn0_board_ok", *(f"dn0_board_{s}" for s, _, _ in BOARD_LINK_COUNTERS)]
U32_MAX = 0xFFFF_FFFF

MISSION = """
mission: boardlink
nodes:
  cn: {}
  dn0:
    board: {driver: serial, port: /dev/memory, digital_pins: 8, reply_timeout_ms: 50,
            reconnect_min_ms: 5, reconnect_max_ms: 20, safe_after: 1}
  dn1: {}
regions:
  dn1_to_cn:
    - {name: dn1_board_ok, type: bool, doc: "a sim board's node may use the name"}
"""


# -- which nodes get the elements --------------------------------------------------


@pytest.mark.parametrize(
    ("board", "reported"),
    [
        ({}, False),
        ({"driver": "sim", "digital_pins": 4}, False),
        ({"driver": "world"}, False),
        ({"driver": "team.boards:AdcHat"}, False),
        ({"driver": "serial", "port": "/dev/ttyACM0"}, True),
        ({"driver": "gpiod", "outputs": {0: 1}}, True),
    ],
)
def test_only_a_serial_or_gpiod_board_adds_link_elements(
    board: dict[str, Any], reported: bool
) -> None:
    """The elements come from the board's driver alone (the board is never
    built), in dnX_to_cn, ok first and then the counters in order."""
    nodes = {"cn": NodeConfig(), "dn0": NodeConfig(board=board)}
    m = Mission(mission="m", nodes=nodes, regions={})
    names = [e.name for e in platform_elements(m)["dn0_to_cn"] if "_board_" in e.name]
    assert names == (LINK if reported else [])
    assert [e.name for e in board_link_elements(m, "dn0")] == names
    types = {e.name: e.type for e in board_link_elements(m, "dn0")}
    assert all(types[n] == ("bool" if n == "dn0_board_ok" else "u32") for n in names)


def test_shipped_missions_keep_their_layout_but_the_hil_one_adds_dn0s_link() -> None:
    """Only flight_hil (dn0 on a serial board) has board link elements, and
    its layout is the flight's plus exactly those: nothing else moved."""
    for path in sorted(CONFIGS.glob("*.yaml")):
        m = load_mission(path)
        names = [n for n in Layout.for_node(m, "cn").elements if "_board_" in n]
        assert names == (LINK if path.stem == "flight_hil" else []), path.name

    def layout(name: str) -> list[tuple[str, str, str]]:
        lay = Layout.for_node(load_mission(CONFIGS / f"{name}.yaml"), "cn")
        return [(s.region, n, s.type_text) for n, s in lay.elements.items()]

    hil = layout("flight_hil")
    assert [e for e in hil if e[1] not in LINK] == layout("flight")
    at = [i for i, e in enumerate(hil) if e[1] in LINK]
    assert at == list(range(at[0], at[0] + len(LINK)))  # one block
    assert {hil[i][0] for i in at} == {"dn0_to_cn"}


def test_declaring_a_link_element_of_a_serial_node_is_a_duplicate() -> None:
    mine = "dn1_to_cn:\n    - {name: dn1_board_ok"
    text = MISSION.replace(mine, "dn0_to_cn:\n    - {name: dn0_board_ok")
    assert text != MISSION
    with pytest.raises(ConfigError, match="duplicate element name 'dn0_board_ok'") as exc:
        decode_mission(text)
    assert exc.value.path == "$.regions.dn0_to_cn[0].name"  # the user's, not the platform's


# -- what the loop writes ----------------------------------------------------------


class Node:
    """DeviceLogic of MISSION's dn0 on a SerialBoard over MemoryPorts."""

    def __init__(self) -> None:
        self.mission = decode_mission(MISSION)
        self.ports: list[MemoryPort] = []
        cfg = {k: v for k, v in self.mission.nodes["dn0"].board.items() if k != "driver"}
        self.board = SerialBoard(cfg, where="$.nodes.dn0.board", serial_factory=self._port)
        self.logic = DeviceLogic(self.mission, "dn0", board=self.board)
        self.cn = DataVector(Layout.for_node(self.mission, "cn"))
        self.loop = 0

    def _port(self, *args: Any, **kwargs: Any) -> MemoryPort:
        p = MemoryPort()
        self.ports.append(p)
        return p

    def run(self) -> None:
        self.loop += 1
        run_dn_loop(self.logic, self.loop, self.loop * PERIOD_NS, self.cn)

    def link(self) -> dict[str, Any]:
        """The link elements as the node's own vector has them now."""
        return {n.removeprefix("dn0_board_"): self.logic.dv.handle(n).get() for n in LINK}


@pytest.fixture
def node() -> Iterator[Node]:
    n = Node()
    n.board.open()
    try:
        assert n.board.wait_connected(WAIT_S), n.board.health()
        yield n
    finally:
        n.board.close()


def zeros(**counts: int) -> dict[str, int]:
    return {s: counts.get(s, 0) for s, _, _ in BOARD_LINK_COUNTERS}


def test_a_serial_nodes_link_elements_follow_its_board(node: Node) -> None:
    """Each fault injected on the link shows in its element after the run
    that met it; dnX_board_ok says whether that run's step succeeded."""
    assert node.logic.board_link
    assert node.link() == {"ok": False, **zeros()}  # before the first run
    for _ in range(3):
        node.run()
    # 3 WRITEs answered; the HELLO_ACK is one more frame received
    assert node.link() == {"ok": True, **zeros(sent=3, received=4)}

    port = node.ports[0]
    port.hold = True  # the device stops answering
    node.run()
    assert node.link() == {"ok": False, **zeros(sent=4, received=4, timeouts=1)}
    assert node.logic.dv.handle("dn0_errors").get() == 1

    port.hold = False
    port.release()  # the abandoned WRITE's answer comes after all
    node.run()
    assert node.link() == {"ok": True, **zeros(sent=5, received=6, timeouts=1, late=1)}

    # a frame whose CRC fails, and an ERROR from the device, before the next answer
    error = port.device.error(wire.ERR_BAD_TYPE, 0, 0x42)
    corrupt = bytearray(error)
    corrupt[3] ^= 0x40
    assert 0 not in corrupt[:-1]  # still one frame, only its CRC is wrong
    port.deliver(bytes(corrupt) + error)
    node.run()
    expect = zeros(sent=6, received=8, timeouts=1, late=1, bad_frames=1, device_errors=1)
    assert node.link() == {"ok": True, **expect}

    port.fail_writes = True  # the adapter breaks: the link is reopened
    node.run()
    assert not node.link()["ok"]
    assert node.board.wait_connected(WAIT_S), node.board.health()
    node.run()
    link = node.link()
    assert link["ok"] and link["reconnects"] == 1 and len(node.ports) == 2, link
    assert link["timeouts"] == 1 and link["late"] == 1 and link["bad_frames"] == 1, link

    # the counters are the board's own, and reach the CN with the next reply
    h = board_health(node.board)
    assert (h.frames_sent, h.frames_received) == (link["sent"], link["received"])
    node.loop += 1
    reply = node.logic.step(
        RegionCodec(node.cn, "cn_to_dn0").encode(node.loop, node.loop * PERIOD_NS),
        node.loop * PERIOD_NS,
    )
    assert reply is not None
    RegionCodec(node.cn, "dn0_to_cn").apply(reply)
    assert {n.removeprefix("dn0_board_"): node.cn.get(n) for n in LINK} == link


def test_the_counters_saturate_at_the_u32_maximum() -> None:
    """A board's counts are unbounded ints; the elements stick at their
    maximum, as every platform counter does, and never wrap."""
    n = Node()  # never opened: every step fails ("not open")
    n.board.counters.timeouts = 2**40
    n.board.counters.frames_sent = U32_MAX
    n.board.counters.bad_frames = U32_MAX - 1
    n.run()
    link = n.link()
    assert link["ok"] is False
    assert (link["timeouts"], link["sent"], link["bad_frames"]) == (U32_MAX, U32_MAX, U32_MAX - 1)


class CountingBoard(SimBoard):
    """A sim board with a link's counters: every step is a frame each way."""

    def __init__(self) -> None:
        super().__init__({"digital_pins": 8})
        self.counters = HealthCounters()

    def step(self, t_ns: int) -> None:
        super().step(t_ns)
        self.counters.frames_sent += 1
        self.counters.frames_received += 1


def test_writing_the_link_keeps_nothing_per_loop() -> None:
    """No snapshot per loop: the counters are read in place, so thousands of
    loops leave no blocks behind (what the monitors' test checks too)."""
    n = Node()
    board = CountingBoard()
    n.logic = DeviceLogic(n.mission, "dn0", board=board)
    for _ in range(100):
        n.run()
    before = sys.getallocatedblocks()
    for _ in range(3000):
        n.run()
    assert sys.getallocatedblocks() - before < 20
    assert n.link() == {"ok": True, **zeros(sent=3100, received=3100)}


def test_a_board_without_counters_reports_only_its_steps() -> None:
    """The lockstep runner's port onto the world (what flight_hil's dn0 steps
    in a sim) keeps no link counters: they stay 0, so two sims of the HIL
    mission are identical, and dnX_board_ok is true while it steps."""
    mission = load_mission(CONFIGS / "flight_hil.yaml")
    runs = []
    for _ in range(2):
        r = LockstepRunner(mission)
        r.run(0.5)
        dv = r.control.dv
        runs.append(bytes(dv.buf))
        assert {n: dv.get(n) for n in LINK} == {
            "dn0_board_ok": True,
            **{f"dn0_board_{s}": 0 for s, _, _ in BOARD_LINK_COUNTERS},
        }
    assert runs[0] == runs[1]


# -- the summary -------------------------------------------------------------------


def test_the_summary_carries_the_board_and_up_prints_a_troubled_one(tmp_path: Path) -> None:
    clean = BoardHealth(ok=True, frames_sent=500, frames_received=501)
    bad = BoardHealth(
        ok=False,
        connected=False,
        errors=4,
        last_error="link down: /dev/ttyACM0 lost",
        frames_sent=900,
        frames_received=880,
        timeouts=3,
        reconnects=1,
        late_replies=2,
    )
    nodes: dict[str, Any] = {}
    for name, board in (("dn0", bad), ("dn1", clean), ("dn2", None)):
        s = DnSummary(
            node=name, loops=1, clock_offset_ns=0, clock_drift_ns=0, bad_frames=0, errors=0,
            stale_queries=0, board=board,
        )  # fmt: skip
        write_summary(tmp_path / f"{name}.json", s)
        nodes[name] = read_summary(tmp_path / f"{name}.json", DnSummary)
        assert nodes[name] == s
    assert nodes["dn2"].board is None
    run = RunSummary(
        mission="m", loops=10, duration_s=0.1, rate_hz=100.0, loop_overruns=0,
        sync_overruns=0, missed={}, late={}, bad_frames=0, telemetry_received=10,
        telemetry_gaps=0, commands=[], errors=0, final_state="IDLE", nodes=nodes,
        exit_codes={},
    )  # fmt: skip
    assert format_board_lines(run) == [
        "zplatform up: dn0's board: 3 timeouts, 1 reconnect, 0 bad frames, 2 late replies, "
        "0 device errors (900 frames sent, 880 received; link down at the end); "
        "last error: link down: /dev/ttyACM0 lost"
    ]
