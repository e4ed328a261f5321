"""``zplatform up`` starts the stations the mission marks ``start`` (issue 29).

A mission with ``ground:`` whose station ``pad`` is marked ``start: true``
(as operator ``fd``) and ``room`` is not: ``up`` runs ``pad`` as a station
process of its own (``zplatform station``), writing into its own directory,
and its status line shows it; ``room`` is not started. fd takes the command
lock from the pad (``zplatform cmd``, which then exits): the station keeps
it, for two leases and more by the CN's own clock. The station is
killed: ``up`` reports it with its restart to come, restarts it, and the
status line shows it up again; the restarted station appends to its
events log (what the first process wrote is kept), and the vehicle flies
on (the CN's loop keeps counting, no fault); Ctrl-C then ends the run
non-zero (a child died, the supervisor's policy), every child reaped.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

from tests.waits import wait_until
from zplatform.ground.link import GroundLink
from zplatform.mission.load import load_mission
from zplatform.node.ground import station_dir
from zplatform.runtime.transport import rewrite_endpoints

from .harness import CONFIGS, ROOT

pytestmark = pytest.mark.timeout(180)

LEASE_S = 3
FD_AT_PAD = ["--operator", "fd", "--station", "pad", "--timeout", "30"]


class _Lines:
    """``up``'s stdout, read in a thread (the pipe never fills)."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.lines: list[str] = []
        self._lock = threading.Lock()
        assert proc.stdout is not None
        self._out = proc.stdout
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for raw in self._out:
            with self._lock:
                self.lines.append(raw.decode(errors="replace").rstrip("\n"))

    def find(self, text: str) -> str | None:
        with self._lock:
            return next((ln for ln in reversed(self.lines) if text in ln), None)

    def text(self) -> str:
        self._t.join(timeout=30)
        with self._lock:
            return "\n".join(self.lines)


def _mission(tmp: Path) -> Path:
    path = tmp / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)
    doc = yaml.safe_load(path.read_text())
    doc["mission"] = "stations_up"
    doc["ground"] = {
        "stations": [
            {"name": "pad", "start": True, "operator": "fd"},
            {"name": "room"},
        ],
        "operators": [{"name": "fd", "roles": ["flight_director"]}],
        "lease_s": LEASE_S,
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_up_starts_a_station_shows_it_and_flies_on_when_it_dies(tmp_path: Path) -> None:
    import psutil

    path = _mission(tmp_path)
    m = load_mission(path)
    up = subprocess.Popen(
        [sys.executable, "-m", "zplatform", "up", str(path), "--summary", str(tmp_path / "s.json")],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    out = _Lines(up)
    rx = GroundLink(m, events=False)
    try:

        def running(text: str) -> str | None:  # failing at once if `up` ended
            assert up.poll() is None, out.text()[-3000:]
            return out.find(text)

        line = wait_until(lambda: running("stations pad=up"), 90, "the status line's station")
        assert "room" not in line  # not marked start: not started
        kids = psutil.Process(up.pid).children()
        stations = [p for p in kids if "station" in p.cmdline()]
        d = station_dir(m, "pad")
        assert len(stations) == 1 and stations[0].cmdline()[-3:] == ["pad", "--dir", str(d)]
        # Its own directory: its events log, beside (not in) the ground's archive.
        wait_until(lambda: (d / "events.jsonl").exists(), 30, "the station's events log")
        assert d.parent.name == "stations_up.stations"

        lock = subprocess.run(
            [sys.executable, "-m", "zplatform", "cmd", str(path), "lock", *FD_AT_PAD],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=90,
        )
        assert lock.returncode == 0 and "LOCK #1 by fd@pad: ACCEPTED" in lock.stdout, lock
        dv = rx.dv

        def snapshot() -> tuple[int, int, str]:  # the CN's time, the lock's end, its holder
            while rx.next(1.0) is None:
                assert up.poll() is None, out.text()[-3000:]
            return (
                int(dv.get("cn_time_ns")),
                int(dv.get("cn_lock_until_ns")),
                dv.get_name("cn_lock_holder"),
            )

        t, until, holder = snapshot()
        while holder != "fd":  # the LOCK's loop
            t, until, holder = snapshot()
        t_lock = t
        while t < t_lock + 2 * LEASE_S * 10**9:  # the station renews it, lease after lease
            t, until, holder = snapshot()
            assert holder == "fd" and until > t, (holder, until, t)
        assert int(dv.get("cn_cmd_seq")) >= 3  # renewals: LOCKs after the first

        events = d / "events.jsonl"
        written = events.read_bytes()
        written = written[: written.rfind(b"\n") + 1]  # its whole lines
        assert written, "the station logged no event before its kill"
        stations[0].kill()
        said = wait_until(lambda: running("node station:pad died (exit code -9)"), 30, "the report")
        assert "; restart 1 in " in said, said
        wait_until(lambda: running("station:pad is up again"), 90, "the station's restart")
        wait_until(lambda: running("stations pad=up(1 restart)"), 30, "the status line's restart")
        again = [p for p in psutil.Process(up.pid).children() if "station" in p.cmdline()]
        assert len(again) == 1 and again[0].pid != stations[0].pid
        assert events.read_bytes().startswith(written)  # appended to: nothing lost
        loop = int(rx.dv.get("cn_loop"))
        while int(rx.dv.get("cn_loop")) < loop + 100:  # the vehicle flies on
            assert up.poll() is None, out.text()[-3000:]
            rx.next(1.0)
        assert rx.dv.get_name("cn_fault") == "NONE"
        up.send_signal(signal.SIGINT)
        rc = up.wait(timeout=90)
        text = out.text()
        assert rc == 1, text[-3000:]  # a child died: reported, the run ends non-zero
        s = json.loads((tmp_path / "s.json").read_text())
        assert s["loops"] > 100 and s["final_state"] == "IDLE", s
        assert "station:pad" not in s["nodes"]  # a station is no node of the summary
        _, alive = psutil.wait_procs([*kids, *again], timeout=15)
        assert not alive, alive
    finally:
        rx.close()
        if up.poll() is None:
            up.kill()
            up.wait()
