"""The camera mission: a 4 MB frame per loop from a DN camera to a CN image
controller through a bulk channel, in sim and as processes (shared memory)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.waits import wait_until
from zplatform import LockstepRunner, load_mission
from zplatform.cli.registry import running
from zplatform.telemetry.logs import CsvLogger, read_csv

ROOT = Path(__file__).resolve().parents[2]
CAMERA = ROOT / "configs" / "camera.yaml"


def test_camera_in_sim_frames_reach_the_controller_a_loop_later(tmp_path: Path) -> None:
    r = LockstepRunner(load_mission(CAMERA))
    with CsvLogger(tmp_path / "c.csv", r.control.layout) as log:
        r.run(1.0, log=log)
    rows = read_csv(tmp_path / "c.csv")
    assert rows[0]["image_mean"] == "0.0"  # nothing published before loop 1
    # frame k (taken in loop k) is the controller's input in loop k + 1
    assert [int(x["frame_count"]) for x in rows[:3]] == [0, 1, 2]
    means = {float(x["image_mean"]) for x in rows[1:]}
    assert len(means) > 1  # the pattern moves frame by frame


# Six seconds of 4 MB frames: with the soaks (-m slow). Bulk channels over
# shared memory between processes stay in the default suite
# (tests/integration/test_bulk_shm.py, tests/integration/test_bulk_iox.py).
@pytest.mark.slow
def test_camera_frames_go_through_shared_memory_between_processes(tmp_path: Path) -> None:
    """As processes on one host the frames travel through shared memory,
    never copied: iceoryx2 to the CN's reader, zenoh's to a tool's `tap`;
    the readers' counters in telemetry and `tap` both say so."""
    csv, summary = tmp_path / "tm.csv", tmp_path / "s.json"
    up = subprocess.Popen(
        [
            *(sys.executable, "-m", "zplatform", "up", str(CAMERA), "--free-ports"),
            *("--duration", "6", "--log", str(csv), "--summary", str(summary), "--quiet"),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # `up` registers the run as "camera" before it starts the nodes: tap
        # then reaches it by name (the remapped mission has free ports).
        def registered() -> bool:  # the registry file `up` writes; failing if `up` ended
            assert up.poll() is None, "up ended"
            return any(e.name == "camera" and e.pid == up.pid for e in running())

        wait_until(registered, 60, "up to register the run", poll_s=0.05)
        tap = subprocess.run(
            [
                *(sys.executable, "-m", "zplatform", "tap", "camera", "rocket/dn0/bulk/frame"),
                *("--count", "3", "--json", "--timeout", "60"),
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=90,
        )
        _, err = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
    assert up.returncode == 0, err[-3000:]
    assert tap.returncode == 0, tap.stderr
    samples = [json.loads(line) for line in tap.stdout.splitlines()]
    assert len(samples) == 3
    assert all(s["via"] == "shm" and s["bulk"]["bytes"] == 4194304 + 32 for s in samples), samples
    # Tagged by dn0 for its reader (link bulk-frame-cn); the tool holds no
    # bulk key, so the tap shows them unverified (the CN's reader checks).
    assert all(s["verified"] is False for s in samples), samples
    rows = read_csv(csv)
    last = rows[-1]
    assert int(last["bulk_frame_published"]) >= 500, last  # about one 4 MB frame per loop
    assert int(last["bulk_frame_copied"]) == 0, last  # never a silent copy
    assert int(last["bulk_frame_bad"]) == 0, last
    assert int(last["bulk_frame_stale"]) == 0, last
    # Every frame the CN's reader saw came through shared memory, and every
    # frame it did not take before the next one came is counted superseded
    # (how many depends on when the box ran the CN's loop, not on the code).
    # In a loop whose own dn0 reply arrived (the row after its previous
    # loop's, one reply more: its published count is current; a reply that
    # came late is refused while dn0 still publishes that loop's frame) the
    # two sides agree up to the frame dn0 publishes after replying; a reader
    # that lost or double-counted frames would drift without bound.
    fresh = next(
        b
        for a, b in zip(rows[-2::-1], rows[::-1], strict=False)
        if int(b["cn_loop"]) == int(a["cn_loop"]) + 1
        and int(b["cn_rx_dn0"]) == int(a["cn_rx_dn0"]) + 1
    )
    published = int(fresh["bulk_frame_published"])
    taken = int(fresh["bulk_frame_iox"]) + int(fresh["bulk_frame_shm"])
    seen = taken + int(fresh["bulk_frame_missed"])
    assert -1 <= published - seen <= 10, fresh
    # Between processes of one host the CN's reader takes iceoryx2 (after at
    # most its first frames over zenoh's shared memory, before the switch),
    # and the tap above still got its frames over zenoh.
    assert int(fresh["bulk_frame_iox"]) > int(fresh["bulk_frame_shm"]), fresh
    assert float(last["image_mean"]) > 100.0
    assert json.loads(summary.read_text())["loops"] == 600
