"""Smoke tests of the flight benches (slow suite): they run and their results render."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import flight_loop, flight_validation, report

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def test_flight_loop_smoke(tmp_path: Path) -> None:
    out = tmp_path / "flight_loop.json"
    flight_loop.main(["--quick", "--json", str(out)])
    doc = json.loads(out.read_text())
    v = doc["variants"]
    assert v["flight_logic_step"]["msgs"] == 2000 and v["flight_ekf"]["cpu_pct"] > 0
    assert v["flight_airbrakes"]["msgs"] > 0  # ran in COAST
    assert "flight_loop" in report.build_report(tmp_path, tmp_path / "R.md", None)


def test_flight_validation_smoke(tmp_path: Path) -> None:
    pytest.importorskip("rocketpy")
    out = tmp_path / "flight_validation.json"
    flight_validation.main(["--json", str(out)])
    doc = json.loads(out.read_text())
    assert all(t["met"] for t in doc["params"]["targets"]), doc["params"]["targets"]
    assert "**Targets**" in report.build_report(tmp_path, tmp_path / "R.md", None)
