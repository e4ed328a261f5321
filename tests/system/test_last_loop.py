"""A run's end is not a lost control node: the CN flags its last loop
(``dnX_final``) and every DN safes its actuators as the run's end, quietly;
only a CN that vanishes makes them safe themselves with a warning
(tests/unit/test_worst_day.py covers both in the sans-IO loop)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from zplatform.telemetry.logs import read_csv

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.timeout(240)


def _ended_cleanly(tm: Path, events_file: Path, summary: Path) -> None:
    """No dn_safed warning after the last loop, every DN safed as the run's end."""
    # The run's end is no lost control node: no dn_safed warning after the
    # last loop (before it, a DN the loaded machine starved of triggers for
    # the watchdog's time is safed, legitimately, and re-enabled).
    last_t = int(read_csv(tm)[-1]["cn_time_ns"])
    events = [json.loads(line) for line in events_file.read_text().splitlines()]
    late = [e for e in events if e["id"] == "dn_safed" and e["t_ns"] >= last_t]
    assert late == [], late
    # Every DN's actuators are at their safe values because the run ended.
    s = json.loads(summary.read_text())
    dns = {n: v for n, v in s["nodes"].items() if n.startswith("dn")}
    assert dns and all(v is not None for v in dns.values()), s["nodes"]
    for name, dn in dns.items():
        assert dn["safed_why"].startswith("the control node's run ended"), (name, dn)


def test_a_clean_up_ends_with_the_dns_safed_and_no_warning(tmp_path: Path) -> None:
    """recovery_igniter, half a second under `up` (the run's end is what counts)."""
    tm, summary = tmp_path / "tm.csv", tmp_path / "s.json"
    mission = ROOT / "configs" / "recovery_igniter.yaml"
    r = subprocess.run(
        [
            *(sys.executable, "-m", "zplatform", "up", str(mission)),
            *("--free-ports", "--duration", "0.5", "--quiet", "--no-realtime"),
            *("--log", str(tm), "--summary", str(summary)),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    _ended_cleanly(tm, tmp_path / "tm.events.jsonl", summary)


def test_the_led_platform_s_scripted_run_ends_with_the_dns_safed_and_no_warning(
    led_live_run: Path,
) -> None:
    """led_test: the session's scripted run under `up` (tests/live_runs.py),
    which other tests read too, ended the same way."""
    d = led_live_run
    _ended_cleanly(d / "live.csv", d / "live.events.jsonl", d / "up.json")


def test_a_stopped_cn_runs_one_more_loop_flagged_final(tmp_path: Path) -> None:
    """SIGTERM to the CN (Ctrl-C under `up`): it runs one more loop, flagged
    final, then stops; the DN, still running, safes as the run's end."""
    import queue
    import signal

    import zenoh

    from tests.integration.harness import CONFIGS, Cluster
    from zplatform.core.auth import load_keys
    from zplatform.core.events import EventReader
    from zplatform.runtime.transport import KeySpace

    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        sub = c.session.declare_subscriber(
            KeySpace(c.mission.vehicle).events("dn0"),
            zenoh.handlers.Callback(lambda s: got.put(s.payload.to_bytes()), indirect=False),
        )
        c.spawn("dn0")
        cn = c.spawn("cn")
        c.advance(20)
        cn.send_signal(signal.SIGTERM)
        assert cn.wait(timeout=60) == 0, c.log("cn")[-3000:]
        # The DN's events until it safes as the run's end (a dn_safed warning
        # before it is a stall of the loaded machine, legitimately).
        reader = EventReader(c.mission, load_keys(c.mission, "tool"))
        key = KeySpace(c.mission.vehicle).events("dn0")
        while (e := reader.read(key, got.get(timeout=60))[0]).id != "dn_safed_run_ended":
            pass
        assert e.severity_name == "ACTIVITY_HI", e
        sub.undeclare()
        dn = c.procs["dn0"]
        dn.send_signal(signal.SIGTERM)
        assert dn.wait(timeout=60) == 0, c.log("dn0")[-3000:]
    s = json.loads((tmp_path / "dn0.json").read_text())
    assert s["safed_why"].startswith("the control node's run ended"), s
