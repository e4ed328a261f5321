"""The flight mission live (issue 19): ``zplatform up`` of the flight and of its
hardware-in-the-loop twin, each against the lockstep run of
the same file and script (the sim-equals-live rule).

The hardware-in-the-loop run has dn0's IMU, barometer, motor igniter and
chute switches behind the real :class:`~zplatform.boards.SerialBoard`,
talking the serial protocol over a pty to the world process, which plays
the board's firmware with the physics behind its pins.

Both missions fly whole, from the pad to the ground (about a minute each),
with the soaks (``-m slow``). The default suite flies the HIL mission to
burnout:
its nodes as processes, ARM and LAUNCH from ``zplatform cmd``, and the
state machine's lift-off and burnout seen by dn0's IMU through the serial
board (a few seconds of flight, about 15 s in all).
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec.yaml
import pytest

from tests.integration.harness import Cluster
from zplatform import load_mission
from zplatform.control.uplink import load_commands
from zplatform.runtime.transport import rewrite_endpoints
from zplatform.sim.lockstep import LockstepRunner
from zplatform.telemetry.logs import read_csv
from zplatform.telemetry.summary import DnSummary, read_summary

pytest.importorskip("serial")

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
CMDS = CONFIGS / "flight.commands"
DURATION_S = 54  # landed at about 48 s (mission time)
FLIGHT = ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED"]
pytestmark = pytest.mark.timeout(300)


def test_the_hil_mission_is_the_flight_but_for_dn0s_serial_board() -> None:
    """flight_hil.yaml may differ from flight.yaml only in its name, ports,
    dn0's board and the world's serial service (so the HIL run tests the
    mission that flies)."""
    a = msgspec.yaml.decode((CONFIGS / "flight.yaml").read_bytes())
    b = msgspec.yaml.decode((CONFIGS / "flight_hil.yaml").read_bytes())
    assert b["nodes"]["dn0"]["board"]["driver"] == "serial"
    assert b["world"]["serve_serial"] == {"dn0": b["nodes"]["dn0"]["board"]["port"]}
    for doc in (a, b):
        doc.pop("mission")
        doc["world"].pop("listen")
        doc["world"].pop("serve_serial", None)
        for node in doc["nodes"].values():
            node.pop("listen")
            node.pop("connect", None)
            node.get("board", {}).clear()
    assert a == b


def _sim_states(mission_path: Path) -> list[str]:
    r = LockstepRunner(load_mission(mission_path), commands=load_commands(CMDS))
    return r.run(DURATION_S).states


def _changes(rows: list[dict[str, str]]) -> list[str]:
    out: list[str] = []
    for r in rows:
        if not out or out[-1] != r["cn_state"]:
            out.append(r["cn_state"])
    return out


@pytest.fixture(scope="module")
def flown(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """``up`` of a flight mission (``flight`` or ``flight_hil``) with the
    flight script, logged, once a module: the directory of its run."""
    dirs: dict[str, Path] = {}

    def fly(name: str) -> Path:
        if name in dirs:
            return dirs[name]
        tmp = tmp_path_factory.mktemp(name)
        mission = tmp / f"{name}.yaml"
        rewrite_endpoints(CONFIGS / f"{name}.yaml", mission)
        p = subprocess.run(
            [sys.executable, "-m", "zplatform", "up", str(mission), "--duration",
             str(DURATION_S), "--commands", str(CMDS), "--log", str(tmp / "live.csv"),
             "--summary", str(tmp / "up.json"), "--quiet"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=240, check=False,
        )  # fmt: skip
        assert p.returncode == 0, f"{name}: {p.stdout.decode(errors='replace')[-3000:]}"
        dirs[name] = tmp
        return tmp

    return fly


# A whole flight in real time (about a minute) each, with the soaks (-m
# slow; a minute of the default suite's six): the default suite flies both
# in lockstep (tests/system/test_flight.py), the HIL mission live to
# burnout on its pty (below), the flight live through takeovers and
# restarts to its deploy (tests/system/test_failover_live.py), and sim
# against live bit for bit on led_test (tests/system/test_sim_equals_live.py).
@pytest.mark.slow
@pytest.mark.parametrize("name", ["flight", "flight_hil"])
def test_up_lands_under_both_chutes_with_the_states_of_sim(
    flown: Callable[[str], Path], name: str
) -> None:
    tmp = flown(name)
    up = json.loads((tmp / "up.json").read_text())
    rows = read_csv(tmp / "live.csv")
    assert up["final_state"] == "LANDED"
    assert [c["status"] for c in up["commands"]] == ["ACCEPTED"] * 3
    last = rows[-1]
    # both switches of each chute closed together (the two-node agreement)
    assert last["drogue_fired"] == "1" and last["main_fired"] == "1"
    live = _changes(rows)
    assert _sim_states(tmp / f"{name}.yaml") == FLIGHT
    if name == "flight_hil" and live != FLIGHT:
        # The serial link's round trip goes through the pty layer, which a
        # loaded host can stall for longer than the fault limit (25 loops):
        # then the platform latches the board's failure and the mission
        # answers it as configured (ABORTED, recovery on from apogee).
        aborted = next(r for r in rows if r["cn_state"] == "ABORTED")
        assert aborted["cn_fault"] == "CONTROLLER_FAILED", aborted["cn_fault"]
        assert int(aborted["dn0_errors"]) + int(aborted["dn1_errors"]) >= 25
        after = FLIGHT[:4] if "COAST" in live else FLIGHT[:3]  # a fault in COAST or BOOST
        assert live == [*after, "ABORTED", *FLIGHT[4:]]
    else:
        assert live == FLIGHT
    # the IMU's data came through dn0's board (the wire protocol, for HIL)
    accels = {r["dn0_accel_mps2"] for r in rows if r["cn_state"] == "BOOST"}
    assert len(accels) > 10 and max(float(a) for a in accels) > 30.0


def _zp(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        capture_output=True, text=True, cwd=ROOT, timeout=60, check=False,
    )  # fmt: skip


def test_the_hil_mission_lifts_off_and_burns_out_on_dn0s_serial_board(tmp_path: Path) -> None:
    """configs/flight_hil.yaml live, to burnout: the world process serves
    dn0's board on a pty, dn0 runs the real SerialBoard and reports its link
    in telemetry (``dn0_board_*``) and in its summary, dn1 and cn as in
    flight (cn alone: the standby is not needed to fly).
    ``zplatform cmd ... launch --arm`` is accepted; the motor igniter's
    WRITE goes out over the serial link, and lift-off (BOOST) and burnout
    (COAST) come from dn0's IMU read back over it. Every WRITE dn0 sent was
    answered or counted as timed out, and nothing on the link was bad: no
    bad frame, no ERROR from the board, no reconnect, nothing the board
    simulator refused."""
    states: list[str] = []
    boost_g: list[float] = []

    def seen(dv: Any) -> bool:
        s = dv.get_name("cn_state")
        if not states or states[-1] != s:
            states.append(s)
        if s == "BOOST":
            boost_g.append(dv.get("dn0_accel_mps2") / 9.80665)
        return s in ("COAST", "ABORTED")

    with Cluster(CONFIGS / "flight_hil.yaml", tmp_path) as c:
        for n in ("world", "dn0", "dn1", "cn"):
            c.spawn(n)
        c.wait_for(lambda dv: dv.get("dn0_board_received") > 50, 60, "dn0's link up")
        r = _zp("cmd", str(c.path), "launch", "--arm")
        # A pty stalled past the fault limit before the launch latches the
        # fault first: the LAUNCH is then refused for it (refused_while_faulted).
        refused = "a fault is latched" in r.stdout + r.stderr
        assert refused or (r.returncode == 0 and "ACCEPTED" in r.stdout), r.stdout + r.stderr
        if not refused:
            c.wait_for(seen, 30, "burnout")
        seen(c.tm)
        dv = c.tm
        link = {n: int(dv.get(f"dn0_board_{n}")) for n in
                ("ok", "sent", "received", "timeouts", "late", "bad_frames", "device_errors",
                 "reconnects")}  # fmt: skip
        errors = int(dv.get("dn0_errors"))
        fault = dv.get_name("cn_fault")
        # Stopped cleanly, each device node writes its summary.
        for n in ("dn0", "dn1"):
            c.procs[n].terminate()
        for n in ("dn0", "dn1"):
            assert c.procs[n].wait(timeout=30) == 0, c.log(n)[-2000:]
    if fault == "NONE":
        assert states[-3:] == ["ARMED", "BOOST", "COAST"], (states, link)
        assert max(boost_g) > 2.5  # lift-off, as dn0 read it over the wire
        assert link["sent"] > 500, link  # 5 s and more of 100 Hz
    else:  # the pty stalled past the fault limit on a loaded host (as in the slow test)
        assert fault == "CONTROLLER_FAILED" and link["timeouts"] >= 25, (fault, link)
        assert (states[-1] == "ABORTED" and "ARMED" in states) or states == ["SAFE"], states
    # Every WRITE answered (the HELLO_ACK is one more frame) or timed out;
    # a timed-out WRITE's answer may still come, counted late.
    answered = link["received"] - 1 - link["late"]
    assert link["sent"] - link["timeouts"] <= answered <= link["sent"], link
    assert link["bad_frames"] == link["device_errors"] == link["reconnects"] == 0, link
    # dn0 counted every failed step (a timeout, or the link not up yet at start)
    assert errors >= link["timeouts"], (errors, link)
    assert "malformed" not in c.log("world"), c.log("world")[-2000:]
    # dn0's summary (written as it stopped) has its board's counters over the
    # whole run: the telemetry above was a moment of them; dn1's world link
    # reports none.
    dn0 = read_summary(tmp_path / "dn0.json", DnSummary)
    assert dn0 is not None and dn0.board is not None, c.log("dn0")[-2000:]
    b = dn0.board
    assert b.frames_sent >= link["sent"] and b.timeouts >= link["timeouts"], (b, link)
    assert b.bad_frames == b.device_errors == b.reconnects == 0, b
    assert b.errors == dn0.errors, (b, dn0)  # its only errors were the board's failed steps
    dn1 = read_summary(tmp_path / "dn1.json", DnSummary)
    assert dn1 is not None and dn1.board is None
