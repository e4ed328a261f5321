"""The thesis-sized mission (configs/thesis_200.yaml: 100 sensors + 100 actuators).

In ``sim`` (lockstep, every loop checked through the ground's CSV) and
briefly under ``zplatform up`` as real processes (auth on, free ports).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.budget import assert_every_loop_counted, assert_telemetry_counted
from zplatform import load_mission
from zplatform.sim.lockstep import LockstepRunner
from zplatform.telemetry.logs import CsvLogger, read_csv

ROOT = Path(__file__).resolve().parents[2]
YAML = ROOT / "configs" / "thesis_200.yaml"


def _elements() -> tuple[list[str], list[str]]:
    m = load_mission(YAML)
    sensors = [
        e.name
        for r, es in m.regions.items()
        if r.endswith("_to_cn")
        for e in es
        if re.fullmatch(r"s\d{3}_[ad]in", e.name)
    ]
    actuators = [
        e.name
        for r, es in m.regions.items()
        if r.startswith("cn_to_")
        for e in es
        if re.fullmatch(r"a\d{3}_[ad]out", e.name)
    ]
    return sensors, actuators


def test_thesis_200_has_100_sensors_and_100_actuators() -> None:
    sensors, actuators = _elements()
    assert len(sensors) == 100 and len(actuators) == 100
    assert len(load_mission(YAML).devices) == 200


def test_thesis_200_sim_moves_every_element(tmp_path: Path) -> None:
    m = load_mission(YAML)
    runner = LockstepRunner(m)
    log = tmp_path / "tm.csv"
    with CsvLogger(log, runner.control.layout) as logger:
        res = runner.run(2.0, log=logger)
    assert res.loops == 200 and res.errors == 0
    assert sum(res.missed.values()) == 0 and res.loop_overruns == 0
    assert res.telemetry_received == 200
    rows = read_csv(log)
    sensors, actuators = _elements()
    # Every sensor and every actuator changes during the run (sine / square waves
    # through the CN's Mirror), and analog commands follow gain 0.5 of a sensor.
    for name in [*sensors, *actuators]:
        assert len({r[name] for r in rows}) > 1, name
    for r in rows[5:]:
        for a in actuators:
            if a.endswith("_aout"):
                assert abs(float(r[a])) <= 0.5 + 1e-6


@pytest.mark.timeout(180)
def test_thesis_200_runs_under_up(tmp_path: Path) -> None:
    summary = tmp_path / "summary.json"
    log = tmp_path / "tm.csv"
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "zplatform",
            "up",
            str(YAML),
            "--free-ports",
            "--duration",
            "3",
            "--log",
            str(log),
            "--summary",
            str(summary),
            "--quiet",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=170,
    )
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    s = json.loads(summary.read_text())
    assert s["errors"] == 0
    assert s["loops"] == 300
    assert_every_loop_counted(s)
    assert_telemetry_counted(s)
    assert len(read_csv(log)) == s["telemetry_received"]
