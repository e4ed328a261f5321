"""Ground tools against a running mission: tap, ground prompt, log, cmd, plot."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from zplatform.cli.main import main

from .harness import CONFIGS, ROOT, Cluster, zp_side_by_side

pytestmark = pytest.mark.timeout(180)


def _zp(
    *args: str, stdin: str | None = None, timeout: float = 60, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        cwd=ROOT,
        input=stdin,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=dict(os.environ, **(env or {})),
    )


def test_tap_ground_and_log(tmp_path: Path) -> None:
    """A tap sees every node's keys decoded; the ground prompt sends a command; log writes CSV.
    Tools that do not depend on each other run side by side (each is a process)."""
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn")
        c.advance(10)
        r, g = zp_side_by_side(
            ("tap", str(c.path), "--count", "40", "--json", "--timeout", "30"),
            ("ground", str(c.path), "--watch", "heartbeat"),
            stdins={1: "launch\nquit\n"},
        )
        assert r.returncode == 0, r.stderr
        keys = {json.loads(line)["key"] for line in r.stdout.splitlines()}
        # Telemetry from the CN and the DN's tap put, each decoded to values.
        assert {"rocket/cn/telemetry", "rocket/dn0/to_cn"} <= keys, keys
        sample = next(json.loads(x) for x in r.stdout.splitlines() if '"rocket/dn0/to_cn"' in x)
        assert "dn0_loop" in sample["values"]

        assert g.returncode == 0, g.stderr
        assert "LAUNCH #1: ACCEPTED" in g.stdout, g.stdout
        c.wait_for(lambda dv: dv.get_name("cn_state") == "RUN", 30, "state RUN")

        # A ground host whose clock is 5 s ahead of the vehicle's believes no
        # snapshot (each looks 5 s old: a replay, for all it knows) and says
        # what to do; widening the bound is one way. (The skewed cmd never
        # joins, so it sends nothing: the wide one's NOOP is #2 either way.)
        # A quiet key of a running mission is not a dead mission.
        skewed = {"ZPLATFORM_CLOCK_SKEW_NS": str(5_000_000_000)}
        wide = {**skewed, "ZPLATFORM_TELEMETRY_MAX_AGE_MS": "10000"}
        r, w, q = zp_side_by_side(
            ("cmd", str(c.path), "noop", "--timeout", "2"),
            ("cmd", str(c.path), "noop"),
            ("tap", str(c.path), "rocket/nothing/here", "--timeout", "1"),
            envs={0: skewed, 1: wide},
        )
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stdout + r.stderr
        assert "no acceptable telemetry within 2 s" in r.stderr and "stale" in r.stderr
        assert "synchronise it (chrony, NTP)" in r.stderr
        assert "ZPLATFORM_TELEMETRY_MAX_AGE_MS" in r.stderr
        assert w.returncode == 0 and "NOOP #2: ACCEPTED" in w.stdout, w.stdout + w.stderr
        assert q.returncode == 1, q.stdout + q.stderr
        assert "the mission is running (nodes alive: cn, dn0) but nothing was published on " \
            "rocket/nothing/here within 1 s" in q.stderr  # fmt: skip

        out = tmp_path / "log.csv"
        r = _zp("log", str(c.path), "--out", str(out), "--duration", "1")
        assert r.returncode == 0, r.stderr
        rows = len(out.read_text().splitlines()) - 1
        assert rows > 50
        # It says what it logged, and where (telemetry travels with DROP
        # congestion control: a busy host may lose a snapshot, counted as a gap).
        m = re.fullmatch(
            r"logged (\d+) snapshot\(s\) \(loops \d+\.\.\d+\), \d+ gap\(s\), 0 bad or refused "
            r"-> (\S+); (\d+) event\(s\) -> (\S+)\n",
            r.stdout,
        )
        assert m is not None, r.stdout
        assert int(m[1]) == rows and m[2] == str(out)
        assert m[4] == str(tmp_path / "log.events.jsonl")


def test_cmd_and_prompt_arm_in_one_step_and_give_every_reason(tmp_path: Path) -> None:
    """Protected WRITEs and hazardous commands: refused unarmed before anything
    is sent, ARM n then COMMAND n+1 in one step (`cmd --arm`, `armed ...` at
    the prompt); every verdict prints its reason."""
    with Cluster(CONFIGS / "recovery_igniter.yaml", tmp_path) as c:
        for n in ("dn0", "dn1", "cn"):
            c.spawn(n)
        c.wait_for(lambda dv: dv.get_name("cn_state") == "SAFE", 30, "state SAFE")
        path = str(c.path)
        r, launch = zp_side_by_side(  # side by side: two processes
            ("cmd", path, "write", "safety0_mode", "safed"), ("cmd", path, "launch")
        )
        assert r.returncode == 2, r.stdout + r.stderr
        assert (
            "safety0_mode is protected (commands.protected): send it as ARM n, then WRITE n+1 "
            "(--arm)" in r.stderr
        )
        r = launch
        assert r.returncode == 2 and "LAUNCH is hazardous" in r.stderr, r.stdout + r.stderr
        c.advance(5)
        assert int(c.tm.get("cn_cmd_seq")) == 0 and int(c.tm.get("cn_cmd_rejects")) == 0

        r = _zp("cmd", path, "write", "safety0_mode", "safed", "--arm")
        assert r.returncode == 0, r.stdout + r.stderr
        assert r.stdout.splitlines() == [
            "ARM #1: ACCEPTED",
            "WRITE #2: ACCEPTED (safety0_mode = safed)",
        ]
        c.wait_for(lambda dv: dv.get_name("safety0_mode") == "safed", 10, "safety0 safed")

        script = "\n".join(
            [
                "write safety0_mode enabled",  # protected: refused, how to arm it said
                "armed write safety0_mode enabled",
                "armed launch",
                "armed write safety0_mode safed",  # ARMED refuses ARM: the WRITE is not sent
                "noop",
                "quit",
            ]
        )
        r = _zp("ground", path, "--prompt", stdin=script + "\n", timeout=120)
        assert r.returncode == 0, r.stdout + r.stderr
        out = r.stdout
        assert "refused: safety0_mode is protected (commands.protected): send it as ARM n, " \
            "then WRITE n+1 (armed write safety0_mode enabled)" in out  # fmt: skip
        for line in (
            "ARM #3: ACCEPTED",
            "WRITE #4: ACCEPTED (safety0_mode = enabled)",
            "ARM #5: ACCEPTED",
            "LAUNCH #6: ACCEPTED",
            "ARM #7: REJECTED_NOT_ALLOWED: not allowed in state ARMED",
            "WRITE: not sent (ARM was not accepted)",
            "NOOP #8: ACCEPTED",
        ):
            assert line in out.splitlines(), (line, out)
        # The status line never shows a made-up rate: "-" until two snapshots give one.
        status = [x for x in out.splitlines() if x.startswith("loop ")]
        assert status and "0.0 Hz" not in status[0] and " - Hz" in status[0], status[:2]


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
