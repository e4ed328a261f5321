"""One loop for sim and live (docs/architecture.md#the-loop): the same mission and script give
the same states at the same loop numbers and the same verdicts under ``up``
(five processes) and ``sim``; and a live run recorded with ``up --record``
replays bit for bit through the lockstep runner."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.live_runs import LED_DURATION_S
from zplatform import load_mission
from zplatform.control.uplink import load_commands
from zplatform.sim.lockstep import LockstepRunner, replay
from zplatform.telemetry.logs import CsvLogger, read_csv

ROOT = Path(__file__).resolve().parents[2]
LED_YAML = ROOT / "configs" / "led_test.yaml"
DURATION_S = LED_DURATION_S


def state_changes(rows: list[dict[str, str]]) -> list[tuple[int, str]]:
    """``(loop, state)`` of the first row and every row whose state changed."""
    out: list[tuple[int, str]] = []
    for r in rows:
        if not out or out[-1][1] != r["cn_state"]:
            out.append((int(r["cn_loop"]), r["cn_state"]))
    return out


@pytest.fixture(params=["shm", "zenoh"])
def live_run(request: pytest.FixtureRequest) -> Path:
    """The LED platform's scripted run under ``up`` (tests/live_runs.py: 9 s,
    LAUNCH at 0.5 s, ABORT at 8.5 s), logged and recorded; made once a
    session, other tests read it too. By sync path: ``shm``, the shipped
    file (``transport.intra_host: auto``: its nodes share this host, so
    their syncs take shared memory, docs/architecture.md#intra-host), and
    ``zenoh``, pinned to zenoh. The first proves its path from the log."""
    if request.param == "zenoh":
        run: Path = request.getfixturevalue("led_live_run_zenoh")
    else:
        run = request.getfixturevalue("led_live_run")
    rows = read_csv(run / "live.csv")
    dns = [k.removesuffix("_sync_path") for k in rows[0] if k.endswith("_sync_path")]
    assert dns
    if request.param == "zenoh":
        assert all(r[f"{dn}_sync_path"] == "zenoh" for dn in dns for r in rows)
        return run
    # Every device node's syncs took shared memory, and each time a link
    # left it (a stall on a loaded box: zplatform.runtime.sync.FALL_AFTER
    # loops in a row without a reply) the commander said so in an event.
    events = [json.loads(line) for line in (run / "live.events.jsonl").read_text().splitlines()]
    for dn in dns:
        path = [r[f"{dn}_sync_path"] for r in rows]
        assert set(path) <= {"shm", "zenoh"} and "shm" in path, (dn, set(path))
        first = path.index("shm")
        left = sum(a == "shm" and b == "zenoh" for a, b in itertools.pairwise(path[first:]))
        told = sum(
            e["id"] == "sync_fallback" and e["text"].startswith(f"cn: {dn}'s sync") for e in events
        )
        assert left <= told, (dn, left, told)
    return run


def test_sim_equals_live(live_run: Path, tmp_path: Path) -> None:
    mission = load_mission(live_run / "mission.yaml")
    runner = LockstepRunner(mission, commands=load_commands(live_run / "led.commands"))
    with CsvLogger(tmp_path / "sim.csv", runner.control.layout) as log:
        res = runner.run(DURATION_S, log=log)
    live = read_csv(live_run / "live.csv")
    sim = read_csv(tmp_path / "sim.csv")
    up = json.loads((live_run / "up.json").read_text())

    # Both start at loop 1 and run the same loops.
    assert int(live[0]["cn_loop"]) == int(sim[0]["cn_loop"]) == 1
    assert up["loops"] == res.loops == DURATION_S * 100
    live_verdicts = [(c["command"], c["seq"], c["status"], c["loop"]) for c in up["commands"]]
    sim_verdicts = [(c.command, c.seq, c.status, c.loop) for c in res.commands]
    lost = sum(up["missed"].values()) + sum(up["late"].values())
    # The ground node sends a scripted command when telemetry shows the loop
    # before it is due; a ground the box runs late (it is an ordinary
    # process) lands it a loop or more later, and the verdict says which.
    late_commands = sum(
        max(0, a[3] - b[3]) for a, b in zip(live_verdicts, sim_verdicts, strict=True)
    )
    if lost == 0 and up["telemetry_gaps"] == 0 and late_commands == 0:
        # Nothing was lost or late live: the runs must agree loop for loop.
        assert state_changes(live) == state_changes(sim)
        assert live_verdicts == sim_verdicts
    else:
        # A lost sync delays data by a loop, a late command what follows
        # it: same sequence, shifts bounded by what was lost or late
        # (stated, not hidden).
        ls, ss = state_changes(live), state_changes(sim)
        bound = lost + late_commands + up["telemetry_gaps"]
        assert [s for _, s in ls] == [s for _, s in ss]
        assert all(abs(a - b) <= bound for (a, _), (b, _) in zip(ls, ss, strict=True)), (
            ls,
            ss,
            bound,
        )
        assert [v[:3] for v in live_verdicts] == [v[:3] for v in sim_verdicts]
    assert [s for _, s in state_changes(sim)] == ["A", "B", "C", "D", "E"]
    assert [v[2] for v in sim_verdicts] == ["ACCEPTED", "ACCEPTED"]


def test_live_run_replays_bit_for_bit(live_run: Path, tmp_path: Path) -> None:
    up = json.loads((live_run / "up.json").read_text())
    res = replay(live_run / "rec", LED_YAML)  # the shipped file: the copy ran on other ports
    assert res.complete and res.dropped_loops == 0
    assert res.first_difference is None
    assert res.identical
    assert res.loops == up["loops"]
    assert res.first_loop == 1
    assert res.final_state == up["final_state"] == "E"
    # The CLI says the same, and exits 0.
    proc = subprocess.run(
        [
            *(sys.executable, "-m", "zplatform", "replay", str(live_run / "rec")),
            *("--mission", str(LED_YAML)),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "bit-identical" in proc.stdout


def test_replay_names_the_first_difference(live_run: Path, tmp_path: Path) -> None:
    """A tampered recording is caught, with its loop and element."""
    import shutil

    from zplatform.sim.replay_recording import RECORD_FILE, RecordReader

    rec = tmp_path / "rec"
    shutil.copytree(live_run / "rec", rec)
    reader = RecordReader(rec)
    data = bytearray((rec / RECORD_FILE).read_bytes())
    # Flip the last byte of a loop's telemetry frame (its data): the first
    # recorded loop from 500 with one (a loop the box skipped is not recorded).
    target = next(r for r in reader.loops() if r.loop >= 500 and r.telemetry is not None)
    assert target.telemetry is not None
    at = data.find(target.telemetry)
    data[at + len(target.telemetry) - 1] ^= 0x01
    (rec / RECORD_FILE).write_bytes(data)
    res = replay(rec, LED_YAML)
    assert not res.identical
    assert res.first_difference is not None and res.first_difference.loop == target.loop
