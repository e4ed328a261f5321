"""CCSDS downlink from live telemetry: record as space packets, decode to CSV."""

from __future__ import annotations

import subprocess
import sys
from itertools import pairwise
from pathlib import Path

import pytest

from tests.budget import LINK_ALIVE
from zplatform.cli.main import main
from zplatform.telemetry.logs import read_csv

from .harness import CONFIGS, ROOT, Cluster

pytest.importorskip("spacepackets")
pytestmark = pytest.mark.timeout(120)


def _record(mission: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """`zplatform ccsds MISSION --record OUT` for 1.5 s."""
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "zplatform",
            "ccsds",
            str(mission),
            "--record",
            str(out),
            "--duration",
            "1.5",
            *extra,
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_record_and_decode_live_downlink(tmp_path: Path) -> None:
    """Every other snapshot (divisor 2) goes down and decodes without a refusal."""
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn")
        c.advance(5)
        down = tmp_path / "down.bin"
        r = _record(c.path, down, "--divisor", "2")
        assert r.returncode == 0, r.stderr
    out = tmp_path / "down.csv"
    assert main(["ccsds", str(c.path), "--decode", str(down), "--out", str(out)]) == 0
    rows = read_csv(out)
    assert len(rows) > 10  # of ~75 in 1.5 s: enough steps to see the divisor
    loops = [int(x["cn_loop"]) for x in rows]
    steps = [b - a for a, b in pairwise(loops)]
    # Divisor 2 over the snapshots received: every other one goes down; a
    # telemetry frame lost on the way to the recorder (DROP, a busy box)
    # only lengthens a step and shifts the phase.
    assert all(s >= 2 for s in steps), steps
    assert sum(s == 2 for s in steps) >= LINK_ALIVE * len(steps), steps
    assert all(int(x["rx_time_ns"]) == int(x["cn_time_ns"]) for x in rows)


def test_the_control_node_sends_its_own_radio_downlink(tmp_path: Path) -> None:
    """`downlink: {ccsds: true, divisor: 5}`: the CN packs every 5th snapshot;
    the ground records the packets and decodes them to the same values the
    telemetry carried."""
    src = tmp_path / "radio.yaml"
    src.write_text((CONFIGS / "minimal.yaml").read_text() + "downlink: {ccsds: true, divisor: 5}\n")
    with Cluster(src, tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn")
        c.advance(5)
        down = tmp_path / "radio.bin"
        r = _record(c.path, down)
        assert r.returncode == 0, r.stderr
        assert "from the CN's downlink" in r.stdout
    out = tmp_path / "radio.csv"
    assert main(["ccsds", str(c.path), "--decode", str(down), "--out", str(out)]) == 0
    rows = read_csv(out)
    assert len(rows) > 5  # of ~30 in 1.5 s: enough steps to see the divisor
    loops = [int(x["cn_loop"]) for x in rows]
    steps = [b - a for a, b in pairwise(loops)]
    # Decimated on the vehicle: one snapshot in every 5 the CN offers it. A
    # loop the CN skipped (an overrun on a busy host) is no snapshot, so a
    # step may be longer than 5 loops, never shorter.
    assert min(steps) >= 5, steps
    # A packet lost on the way (DROP, a busy box) is a longer step, no more.
    assert sum(s == 5 for s in steps) >= LINK_ALIVE * len(steps), steps
    assert all(int(x["heartbeat"]) >= 0 and x["cn_state"] == "IDLE" for x in rows)
