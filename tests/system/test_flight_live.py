"""The flight mission live (issue 19): ``zplatform up`` of the flight and of its
hardware-in-the-loop twin, side by side, each against the lockstep run of
the same file and script (the sim-equals-live rule).

The hardware-in-the-loop run has dn0's IMU, barometer, motor igniter and
chute switches behind the real :class:`~zplatform.boards.SerialBoard`,
talking the serial protocol over a pty to the world process, which plays
the board's firmware with the physics behind its pins.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import msgspec.yaml
import pytest

from zplatform import load_mission
from zplatform.lockstep import LockstepRunner
from zplatform.telemetry import read_csv
from zplatform.transport import rewrite_endpoints
from zplatform.uplink import load_commands

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
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``up`` of flight.yaml and of flight_hil.yaml, at the same time, each
    with the flight script, logged."""
    procs = {}
    dirs = {}
    for name in ("flight", "flight_hil"):
        tmp = tmp_path_factory.mktemp(name)
        mission = tmp / f"{name}.yaml"
        rewrite_endpoints(CONFIGS / f"{name}.yaml", mission)
        dirs[name] = tmp
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", "zplatform", "up", str(mission), "--duration",
             str(DURATION_S), "--commands", str(CMDS), "--log", str(tmp / "live.csv"),
             "--summary", str(tmp / "up.json"), "--quiet"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        )  # fmt: skip
    for name, p in procs.items():
        out, _ = p.communicate(timeout=240)
        assert p.returncode == 0, f"{name}: {out.decode(errors='replace')[-3000:]}"
    return dirs


# Two whole flights in real time (about a minute): with the soaks (-m
# slow). The default suite flies the same mission in lockstep
# (tests/system/test_flight.py) and runs sim against live on led_test
# (tests/system/test_sim_equals_live.py).
@pytest.mark.slow
@pytest.mark.parametrize("name", ["flight", "flight_hil"])
def test_up_lands_under_both_chutes_with_the_states_of_sim(
    runs: dict[str, Path], name: str
) -> None:
    tmp = runs[name]
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
