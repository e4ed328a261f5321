"""A new user's own mission: a YAML file in a directory of its own with its
Python package next to it, run from another directory without PYTHONPATH.

The flight verbs (check, sim, up) find the package through the mission's
``pythonpath`` (default: the mission file's directory); the ground verbs
(tap, cmd, log, xtce) work from a ground station's copy of the mission file
that has no code next to it at all, because they import none.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.integration.harness import zp_side_by_side
from tests.unit.test_mission_code import team_mission, write_code
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import free_port
from zplatform.security.pki import ensure_mission_pki

pytestmark = pytest.mark.timeout(240)

PKG = "hotfire_team_it"  # spawned processes only: this process never imports it


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    return env


def _zp(cwd: Path, *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        cwd=cwd,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _on_free_ports(path: Path) -> None:
    doc = yaml.safe_load(path.read_text())
    ports = {n: free_port() for n in doc["nodes"]}
    for name, node in doc["nodes"].items():
        node["listen"] = [f"tcp/127.0.0.1:{ports[name]}"]
        node["connect"] = [] if name == "cn" else [f"tcp/127.0.0.1:{ports['cn']}"]
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def test_a_team_mission_runs_without_pythonpath_and_the_ground_needs_only_the_file(
    tmp_path: Path,
) -> None:
    team, ground, cwd = tmp_path / "team", tmp_path / "ground", tmp_path / "cwd"
    for d in (team, ground, cwd):
        d.mkdir()
    write_code(team, PKG)
    mission = team_mission(team, PKG)
    _on_free_ports(mission)
    # The ground station's copy: the same file, no code beside it.
    ground_copy = ground / mission.name
    ground_copy.write_text(mission.read_text())

    script = tmp_path / "fire.commands"
    script.write_text("at 0.1 arm\nat 0.2 launch\n")
    summary = tmp_path / "sim.json"
    # The verbs that need no running mission, side by side (each a process).
    check, check_ground, sim, xtce = zp_side_by_side(
        ("check", str(mission)),
        ("check", str(ground_copy)),
        ("sim", str(mission), "--duration", "1", "--commands", str(script),
         "--log", str(tmp_path / "sim.csv"), "--summary", str(summary)),
        ("xtce", str(ground_copy), "--out", str(tmp_path / "x.xml")),
        cwd=cwd, base_env=_env(),
    )  # fmt: skip
    assert check.returncode == 0, check.stderr
    # A flight verb without the code fails at load, clearly, in one line.
    r = check_ground
    assert r.returncode == 2
    assert r.stderr.startswith("zplatform: error: cannot import module 'hotfire_team_it'"), r.stderr
    assert "at `$.controllers[0].class`" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert sim.returncode == 0, sim.stderr
    assert json.loads(summary.read_text())["final_state"] == "FIRE"
    assert xtce.returncode == 0, xtce.stderr

    # The mission's PKI, as `zplatform keygen` makes it (`up` would too, but
    # the ground verbs below start beside it and must find it there).
    ensure_mission_pki(load_mission(ground_copy, code=False))
    up = subprocess.Popen(
        [
            *(sys.executable, "-m", "zplatform", "up", str(mission)),
            *("--duration", "90", "--quiet", "--summary", str(tmp_path / "up.json")),
        ],
        cwd=cwd,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # The ground verbs, from the code-less copy: the first telemetry...
        tm = "rocket/cn/telemetry"
        r = _zp(cwd, "tap", str(ground_copy), tm, "--count", "1", "--json", "--timeout", "90",
                timeout=120)  # fmt: skip
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout.splitlines()[0])["values"]["cn_state"] == "SAFE"
        # ...a hazardous command, armed and fired...
        r = _zp(cwd, "cmd", str(ground_copy), "launch", "--arm")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "LAUNCH" in r.stdout and r.stdout.count("ACCEPTED") == 2, r.stdout
        # ...whose effect the flight code (the Valve controller) shows.
        r = _zp(cwd, "tap", str(ground_copy), tm, "--count", "1", "--json", "--timeout", "30")
        assert r.returncode == 0, r.stderr
        values = json.loads(r.stdout.splitlines()[0])["values"]
        assert values["cn_state"] == "FIRE" and values["valve_cmd"] is True, values
        assert values["pressure"] == pytest.approx(1.5)  # the team's physics, on dn0
        out = tmp_path / "log.csv"
        r = _zp(cwd, "log", str(ground_copy), "--out", str(out), "--duration", "1")
        assert r.returncode == 0, r.stderr
        assert len(out.read_text().splitlines()) > 10
        up.send_signal(signal.SIGINT)  # the operator's Ctrl-C: a clean stop
        _, err = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
    assert up.returncode == 0, err[-3000:]
    assert json.loads((tmp_path / "up.json").read_text())["final_state"] == "FIRE"
