"""Live: the ground node archives a run under ``up``, and ``zplatform archive
query`` gives back the ground's CSV log row for row."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
from pathlib import Path

from tests.live_runs import LED_YAML, ROOT


def _zp(run_dir: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", "archive", str(run_dir / "mission.yaml"), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_archive_query_equals_the_grounds_csv_log(led_live_run: Path) -> None:
    d = led_live_run
    arch = d / "archive" / "led_test"
    with (d / "live.csv").open() as f:
        logged = list(csv.reader(f))
    header, rows = logged[0], logged[1:]
    epoch = rows[0][header.index("cn_epoch")]
    assert {r[header.index("cn_epoch")] for r in rows} == {epoch}  # one run

    runs = _zp(d, "--dir", str(arch), "runs", "--json")
    assert runs.returncode == 0, runs.stderr
    (run,) = json.loads(runs.stdout)
    assert (run["run"], run["loops"], run["outcome"]) == (int(epoch), len(rows), "ended")
    assert run["states"] == ["A", "B", "C", "D", "E"]
    assert any("LAUNCH" in c for c in run["commands"])

    # Every element the CSV has (an array of at most 16 items is one column
    # per item there, and in the query's CSV alike).
    q = _zp(d, "--dir", str(arch), "query", "--run", epoch, "--elements", "*")
    assert q.returncode == 0, q.stderr
    assert q.stderr == ""  # no damage skipped
    got = list(csv.reader(io.StringIO(q.stdout)))
    assert got[0] == header
    assert got[1:] == rows

    ev = _zp(d, "--dir", str(arch), "events", "--run", epoch)
    assert ev.returncode == 0, ev.stderr
    archived = [json.loads(line) for line in ev.stdout.splitlines()]
    logged_events = [
        json.loads(line) for line in (d / "live.events.jsonl").read_text().splitlines()
    ]
    # The events file also has the ground's own events from before the first
    # snapshot (tm_joined...): the archive gives them to the run that follows.
    key = lambda e: (e["node"], e["seq"], e["t_ns"])  # noqa: E731
    assert sorted(map(key, archived)) == sorted(map(key, logged_events))
    assert LED_YAML.exists()
