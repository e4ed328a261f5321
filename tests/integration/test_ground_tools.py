"""Ground tools against a running mission: tap, ground prompt, log, plot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from zplatform.cli import main

from .harness import CONFIGS, ROOT, Cluster

pytestmark = pytest.mark.timeout(180)


def _zp(
    *args: str, stdin: str | None = None, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        cwd=ROOT,
        input=stdin,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_tap_ground_and_log(tmp_path: Path) -> None:
    """A tap sees every node's keys decoded; the ground prompt sends a command; log writes CSV."""
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn")
        c.advance(10)
        r = _zp("tap", str(c.path), "--count", "40", "--json", "--timeout", "30")
        assert r.returncode == 0, r.stderr
        keys = {json.loads(line)["key"] for line in r.stdout.splitlines()}
        # Telemetry from the CN and the DN's tap put, each decoded to values.
        assert {"rocket/cn/telemetry", "rocket/dn0/to_cn"} <= keys, keys
        sample = next(json.loads(x) for x in r.stdout.splitlines() if '"rocket/dn0/to_cn"' in x)
        assert "dn0_loop" in sample["values"]

        r = _zp("ground", str(c.path), "--watch", "heartbeat", stdin="launch\nquit\n")
        assert r.returncode == 0, r.stderr
        assert "LAUNCH #1: ACCEPTED" in r.stdout, r.stdout
        c.wait_for(lambda dv: dv.get_name("cn_state") == "RUN", 30, "state RUN")

        out = tmp_path / "log.csv"
        r = _zp("log", str(c.path), "--out", str(out), "--duration", "1")
        assert r.returncode == 0, r.stderr
        assert len(out.read_text().splitlines()) > 50


def test_plot_writes_png(tmp_path: Path) -> None:
    """`zplatform plot` draws numeric and enum columns from a CSV log."""
    pytest.importorskip("matplotlib")
    csv_path = tmp_path / "sim.csv"
    assert (
        main(
            [
                "sim",
                str(CONFIGS / "led_test.yaml"),
                "--duration",
                "16",
                "--commands",
                str(CONFIGS / "led_test.commands"),
                "--log",
                str(csv_path),
            ]
        )
        == 0
    )
    png = tmp_path / "p.png"
    assert main(["plot", str(csv_path), "cn_state", "led_a_fb", "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["plot", str(csv_path), "nope", "--out", str(png)]) == 2
