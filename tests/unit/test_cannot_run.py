"""A device node that answers the CN's triggers but can run none of them
safes itself, says why, and the CN latches DN_SAFED (zplatform.control.loop,
zplatform.control.faults); in lockstep, with the real frames of both sides.

The case is the rogue clock's (issue: a DN whose clock was "corrected" by a
peer without the key finds every real trigger stale): before, it answered
every trigger, ran none, never safed, and the CN saw a healthy link.
"""

from __future__ import annotations

from pathlib import Path

from zplatform.config import Mission
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import Uplink
from zplatform.core.auth import KeySet
from zplatform.core.codec import RegionCodec
from zplatform.core.datavector import DataVector, Layout
from zplatform.mission.load import load_mission
from zplatform.world.model import World

ROOT = Path(__file__).resolve().parents[2]
IGN = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
LED = load_mission(ROOT / "configs" / "led_test.yaml")
MASTER = bytes.fromhex("3f8a1c9e27d45b60f1e83a97c2d0456b8e19f7a3c5d2e0b4a6918f3c7e25d0b1")
PERIOD = IGN.period_ns
T0 = 1_700_000_000_000_000_000
EPOCH = 77
MS = 1_000_000


class Flight:
    """The CN and every DN of a mission, each DN on a clock ``skew`` ns off
    the CN's (as after a wrong correction), with the live runtime's stale
    rule (a trigger older than a period does not run)."""

    def __init__(self, mission: Mission, skew: dict[str, int]) -> None:
        keys = KeySet.from_master(mission, MASTER)
        self.cn = ControlLogic(mission, keys=keys.for_node("cn"), epoch=EPOCH)
        # A mission with a vehicle world: its boards in this process (as sim).
        world = World(mission) if mission.world is not None else None
        self.dns = [
            DeviceLogic(
                mission,
                dn,
                keys=keys.for_node(dn),
                stale_after_ns=PERIOD,
                board=world.board(dn) if world is not None and dn in world.nodes else None,
            )
            for dn in mission.device_nodes
        ]
        self.skew = [skew.get(d.node, 0) for d in self.dns]
        self.up = Uplink(mission, keys.for_node("gn"))
        self.loop = 0
        self.events: list[tuple[int, str, str, str]] = []  # (loop, node, id, text)
        self.ran = [0] * len(self.dns)
        self._seq = 0

    def step(self, *commands: str) -> None:
        """One loop per command request (one request a loop), or one loop."""
        requests = []
        for c in commands:
            self._seq += 1
            t = T0 + self.loop * PERIOD
            requests.append(bytes(self.up.frame(c, self._seq, 0, 0.0, t, EPOCH)))
        for grounds in [[r] for r in requests] or [[]]:
            self._loop(grounds)

    def _loop(self, grounds: list[bytes]) -> None:
        self.loop += 1
        t = T0 + (self.loop - 1) * PERIOD
        frames = self.cn.begin(self.loop, t)
        for i, dn in enumerate(self.dns):
            now = t + self.skew[i]
            self.cn.reply(i, dn.trigger(bytes(frames[i]), now))
            if dn.triggered:
                dn.run(now)
                self.ran[i] += 1
        self.cn.finish(grounds)
        for log in (self.cn.events, *(d.events for d in self.dns)):
            for e in log.drain():
                self.events.append((self.loop, e.node, e.id, e.text))

    def state(self) -> str:
        return self.cn.dv.get_name("cn_state")

    def fault(self) -> str:
        return self.cn.dv.get_name("cn_fault")


def test_a_dn_whose_triggers_are_all_stale_safes_and_the_cn_latches_dn_safed() -> None:
    f = Flight(IGN, {"dn0": 30 * MS})  # dn0's clock 30 ms ahead: every trigger stale
    f.step("ARM", "LAUNCH")
    assert f.state() == "ARMED"
    watchdog = IGN.faults.dn_watchdog_loops
    while f.fault() == "NONE" and f.loop < 100:
        f.step()
    assert f.ran[0] == 0 and f.ran[1] == f.loop  # dn0 answered every trigger and ran none
    safed = [e for e in f.events if e[1] == "dn0" and e[2] == "dn_safed"]
    assert len(safed) == 1
    loop, _, _, text = safed[0]
    assert watchdog <= loop <= watchdog + 2, safed
    assert "none could run" in text and "stale" in text and "clock off" in text
    dv = f.dns[0].dv
    assert dv.get("dn0_safed") is True and dv.get_name("dn0_safed_why") == "CANNOT_RUN"
    # The CN sees it in dn0's next reply: a fault, not a healthy link, and the
    # mission answers it (ARMED -> ABORTED), visibly.
    assert f.fault() == "DN_SAFED" and f.loop <= loop + 2
    assert f.cn.dv.get_name("dn0_safed_why") == "CANNOT_RUN"
    faults = [e for e in f.events if e[2] == "fault"]
    assert len(faults) == 1 and "dn0 safed itself" in faults[0][3]
    f.step()
    assert f.state() == "ABORTED"
    assert f.dns[1].dv.get("dn1_safed") is False  # dn1 ran throughout


def test_a_dn_whose_clock_is_behind_refuses_triggers_ahead_and_safes() -> None:
    """Stamped beyond its window ahead (the clock bound plus a period): bad
    frames, answered with an error; the DN safes itself all the same, and
    the CN, which gets no reply, latches DN_LOST."""
    f = Flight(LED, {"dn0": -500 * MS})
    for _ in range(60):
        f.step()
    assert f.ran[0] == 0
    assert f.dns[0].dv.get_name("dn0_safed_why") == "CANNOT_RUN"
    assert any(e[1] == "dn0" and "ahead" in e[3] and e[2] == "dn_safed" for e in f.events)
    assert f.fault() == "DN_LOST"


def test_a_replayed_trigger_cannot_trip_it() -> None:
    """One authentic trigger captured and replayed at a DN that runs the real
    ones: none of the replays is newer, and the stamps do not advance."""
    keys = KeySet.from_master(LED, MASTER)
    cn = ControlLogic(LED, keys=keys.for_node("cn"), epoch=1)
    dn = DeviceLogic(LED, "dn0", keys=keys.for_node("dn0"), stale_after_ns=PERIOD)
    captured = bytes(cn.begin(1, T0)[0])
    cn.finish()
    assert dn.step(captured, T0) is not None and dn.triggered == 1
    for k in range(2, 500):
        t = T0 + (k - 1) * PERIOD
        real = bytes(cn.begin(k, t)[0])
        cn.finish()
        for _ in range(5):  # a flood between two real triggers
            assert dn.trigger(captured, t) is not None and not dn.triggered
        dn.step(real, t)
        assert dn.triggered == k
    assert dn.safed is False and dn.dv.get_name("dn0_safed_why") == "NONE"


def test_the_warm_up_and_a_cn_stall_are_no_dn_safed_fault() -> None:
    """Loop 0 (the CN's warm-up) never counts; a DN its watchdog safed while
    the CN stalled re-enables when the CN is back, and that is no fault (a
    stall that long is DN_LOST's to judge)."""
    f = Flight(LED, {})
    t = T0 - 10 * PERIOD
    for _ in range(50):  # warm-up queries, answered, never run
        frames = f.cn.begin(0, t)
        f.cn.reply(0, f.dns[0].trigger(bytes(frames[0]), t))
        assert not f.dns[0].triggered
    f.cn.reset_sync_counters()
    for _ in range(20):
        f.step()
    assert f.dns[0].safed is False
    # The CN stalls 300 ms: the DN's watchdog safes it; then the CN is back.
    f.dns[0].watchdog(T0 + (f.loop - 1) * PERIOD + 300 * MS)
    assert f.dns[0].dv.get_name("dn0_safed_why") == "CN_LOST"
    f.loop += 30
    for _ in range(40):
        f.step()
    assert f.dns[0].safed is False and f.fault() == "NONE"


def test_a_dn_safed_by_the_run_s_end_that_cannot_run_the_next_run_says_so() -> None:
    """Safed by the CN's last loop (an activity), then a new CN whose
    triggers it cannot run: the reason becomes CANNOT_RUN, told once."""
    keys = KeySet.from_master(LED, MASTER)
    dn = DeviceLogic(LED, "dn0", keys=keys.for_node("dn0"), stale_after_ns=PERIOD)
    cn = DataVector(Layout.for_node(LED, "cn"))
    codec = RegionCodec(cn, "cn_to_dn0")
    seal = keys.channel("cn_to_dn0")
    cn.set("dn0_final", True)
    dn.step(bytes(seal.seal(codec.encode(1, T0))), T0)
    assert dn.dv.get_name("dn0_safed_why") == "RUN_ENDED"
    # The node knows it (its clock re-sync rests between runs: nobody serves it).
    assert dn.run_ended
    cn.set("dn0_final", False)
    t = T0 + 2_000 * MS  # a new run, 2 s later; this node 50 ms off
    for k in range(1, 40):
        dn.trigger(bytes(seal.seal(codec.encode(k, t))), t + 50 * MS)
        t += PERIOD
    assert dn.dv.get_name("dn0_safed_why") == "CANNOT_RUN"
    assert not dn.run_ended  # a new run is under way
    told = [e for e in dn.events.drain() if e.id == "dn_safed"]
    assert len(told) == 1 and "none could run" in told[0].text


def test_a_burst_of_late_triggers_after_a_stall_is_no_cannot_run() -> None:
    """A DN descheduled for 300 ms is handed the triggers that piled up one
    by one, each stale: their stamps span 300 ms, but they are served
    within a millisecond here. Its watchdog safes it (CN_LOST), then it runs
    the fresh ones and re-enables; the CN sees no DN_SAFED."""
    f = Flight(LED, {})
    for _ in range(20):
        f.step()
    dn, cn = f.dns[0], f.cn
    stalled = []
    for _ in range(30):  # the CN runs on; dn0 serves nothing meanwhile
        f.loop += 1
        t = T0 + (f.loop - 1) * PERIOD
        stalled.append((f.loop, bytes(cn.begin(f.loop, t)[0])))
        cn.finish()
    wake = T0 + f.loop * PERIOD + 2 * MS
    for k, (_, frame) in enumerate(stalled):  # each alone, as zenoh hands them over
        dn.trigger(frame, wake + k * 20_000)
        assert not dn.triggered
    assert dn.dv.get_name("dn0_safed_why") == "CN_LOST"
    for _ in range(30):
        f.step()
    assert dn.safed is False and f.fault() == "NONE"
