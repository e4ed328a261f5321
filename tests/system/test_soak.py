"""Long soaks, opt-in: `./scripts/test.sh -m slow`.

The thesis' verification ran the platform for twice the mission time and
required 99.999 % network reliability (ch. 2.2, 5.2.1). This run holds
the LED mission at 100 Hz as real processes and requires that reliability
(missed syncs over all sync exchanges), no loop overrun, no error and
no gap in the ground's telemetry.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.budget import THESIS_RELIABILITY
from zplatform.runtime.transport import rewrite_endpoints

ROOT = Path(__file__).resolve().parents[2]
MINUTES = float(os.environ.get("ZPLATFORM_SOAK_MINUTES", "10"))


@pytest.mark.slow
@pytest.mark.timeout(int(MINUTES * 60 + 300))
def test_led_mission_soak_has_no_misses(tmp_path: Path) -> None:
    """LED mission for ZPLATFORM_SOAK_MINUTES (10) at the thesis' 99.999 % reliability."""
    path = tmp_path / "mission.yaml"
    rewrite_endpoints(ROOT / "configs" / "led_test.yaml", path)
    summary_path = tmp_path / "summary.json"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "zplatform",
            "up",
            str(path),
            "--duration",
            str(MINUTES * 60),
            "--commands",
            str(ROOT / "configs" / "led_test.commands"),
            "--summary",
            str(summary_path),
            "--quiet",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=MINUTES * 60 + 240,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads(summary_path.read_text())
    loops = round(MINUTES * 60 * 100)
    assert s["loops"] == loops
    lost = sum(s["missed"].values())  # a late reply is its miss's answer, not another loss
    assert 1 - lost / (loops * 3) >= THESIS_RELIABILITY, (s["missed"], s["late"])
    assert s["loop_overruns"] == 0
    assert s["telemetry_received"] == loops and s["telemetry_gaps"] == 0
    assert s["errors"] == 0 and s["final_state"] == "E"
