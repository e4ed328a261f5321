"""Live runs that several tests read, each made once per session.

:func:`led_script_run`: the LED platform (configs/led_test.yaml, on free
ports) under ``zplatform up`` with a command script, logged, summarised and
recorded. tests/system/test_sim_equals_live.py compares it with ``sim`` and
replays it; tests/system/test_processes.py checks each state's LEDs in its
log; tests/system/test_last_loop.py checks how it ended;
tests/system/test_archive_live.py queries its ground archive. Each asserts
something else about the same run (tests/system/conftest.py makes it once,
``led_live_run``).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

from zplatform.runtime.transport import rewrite_endpoints

ROOT = Path(__file__).resolve().parents[1]
LED_YAML = ROOT / "configs" / "led_test.yaml"

# The thesis' script (configs/led_test.commands: LAUNCH at 1 s, ABORT at
# 14 s, in a 20 s run) less the time it only waits: LAUNCH at 0.5 s reaches
# D at 7.54 s, so ABORT at 8.5 s still walks A..E (a second of D: its LED
# flashes on and off), and E holds for half a second.
LED_SCRIPT = "at 0.5 launch\nat 8.5 abort\n"
LED_DURATION_S = 9


def led_script_run(tmp: Path, intra_host: str | None = None) -> Path:
    """Run led_test under ``up`` for :data:`LED_DURATION_S` with
    :data:`LED_SCRIPT` in ``tmp``: ``mission.yaml`` (the copy on free ports),
    ``led.commands``, ``live.csv`` and ``live.events.jsonl`` (the ground's
    log), ``up.json`` (the run's summary), ``rec/`` (the recording),
    ``archive/led_test/`` (the ground node's archive: a directory of its
    own, so no other test's ground node holds it).
    ``intra_host``: the copy's ``transport.intra_host`` (None: the file's,
    ``auto``: its nodes on this host sync over shared memory).
    Returns ``tmp``; fails unless ``up`` exits 0."""
    mission = tmp / "mission.yaml"
    rewrite_endpoints(LED_YAML, mission)
    if intra_host is not None:
        raw = yaml.safe_load(mission.read_text())
        raw.setdefault("transport", {})["intra_host"] = intra_host
        mission.write_text(yaml.safe_dump(raw, sort_keys=False))
    (tmp / "led.commands").write_text(LED_SCRIPT)
    proc = subprocess.run(
        [
            *(sys.executable, "-m", "zplatform", "up", str(mission)),
            *("--duration", str(LED_DURATION_S), "--commands", str(tmp / "led.commands")),
            *("--log", str(tmp / "live.csv"), "--summary", str(tmp / "up.json")),
            *("--record", str(tmp / "rec"), "--quiet"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=150,
        env={**os.environ, "ZPLATFORM_ARCHIVE_DIR": str(tmp / "archive")},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return tmp
