"""The node runtime as real processes on loopback (issue: node runtime)."""

from __future__ import annotations

import json
import os
import queue
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
import zenoh

from tests.budget import (
    assert_every_loop_counted,
    assert_kept_syncing,
    assert_telemetry_counted,
    later_than_now,
    sync_counts,
)
from tests.waits import wait_until
from zplatform.core.auth import load_keys
from zplatform.core.codec import encode_frame
from zplatform.core.events import Event, EventReader
from zplatform.telemetry.logs import read_csv

from .harness import CONFIGS, ROOT, Cluster

pytestmark = pytest.mark.timeout(180)


def test_minimal_mission_runs_at_rate(tmp_path: Path) -> None:
    """`zplatform up minimal`: its loops on the period grid, a CSV row per
    snapshot received, every loop and every snapshot accounted for."""
    csv_path = tmp_path / "tm.csv"
    summary_path = tmp_path / "summary.json"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "zplatform",
            "up",
            str(CONFIGS / "minimal.yaml"),
            "--free-ports",
            "--duration",
            "3",
            "--log",
            str(csv_path),
            "--summary",
            str(summary_path),
            "--quiet",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads(summary_path.read_text())
    assert s["loops"] == 300
    # Loop n starts at t1 + (n - 1) periods: 299 periods from the first loop
    # to the last, more only when the box held the CN past a whole period,
    # and then the overrun is counted.
    periods = round(s["duration_s"] * 100)
    assert periods == 299 or (periods > 299 and s["loop_overruns"] > 0), s
    assert_every_loop_counted(s)
    assert s["final_state"] == "IDLE"
    assert s["errors"] == 0
    rows = read_csv(csv_path)
    assert len(rows) == s["telemetry_received"]
    # Every snapshot the ground received is a row; every loop number it did
    # not receive is a counted gap (DROP telemetry may lose one on a busy box).
    loops = [int(row["cn_loop"]) for row in rows]
    assert loops == sorted(set(loops))
    assert len(set(range(loops[0], loops[-1] + 1)) - set(loops)) == s["telemetry_gaps"]
    assert_telemetry_counted(s)


def test_killed_device_node_is_missed_and_rejoins(tmp_path: Path) -> None:
    """A DN killed mid-run: every loop is a miss for it while the others keep
    syncing and the CN keeps looping; respawned, it rejoins and syncs again."""
    dns = ("dn0", "dn1", "dn2")
    with Cluster(CONFIGS / "led_test.yaml", tmp_path) as c:
        for n in (*dns, "cn"):
            c.spawn(n)
        c.advance(50)
        c.kill("dn1")
        c.wait_for(later_than_now(), 60, "a loop after the kill")
        # From here on dn1 answers nothing: its replies are frozen.
        before = sync_counts(c.tm, dns)
        rx_dead = before["rx_dn1"]
        c.advance(100)  # the CN kept its loop going while dn1 was gone
        after = sync_counts(c.tm, dns)
        assert after["cn_loop"] - before["cn_loop"] >= 100
        assert after["rx_dn1"] == rx_dead
        assert after["missed_dn1"] - before["missed_dn1"] == after["rx_dn0"] - before["rx_dn0"] + (
            after["missed_dn0"] - before["missed_dn0"]
        ), "every loop the CN ran was a miss for the dead dn1"
        # The others are unaffected: they kept answering.
        assert_kept_syncing(before, after, ("dn0", "dn2"))
        c.spawn("dn1")
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn1")) >= rx_dead + 50, 120, "dn1 rejoins")
        rejoined = sync_counts(c.tm, dns)
        c.advance(100)
        # dn1 syncs again, as the others do.
        assert_kept_syncing(rejoined, sync_counts(c.tm, dns), dns)
        assert int(c.tm.get("dn1_loop")) > 0


def test_bad_frames_are_counted_never_applied(tmp_path: Path) -> None:
    """Wrong-layout frames and random bytes to a DN key and to the CN: counted, not applied."""
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn")
        c.advance(20)
        s = c.session
        v = c.mission.vehicle
        events: queue.SimpleQueue[Event] = queue.SimpleQueue()
        reader = EventReader(c.mission, load_keys(c.mission, "tool"))
        sub = s.declare_subscriber(
            f"{v}/*/events",
            lambda sample: events.put(
                reader.read(str(sample.key_expr), sample.payload.to_bytes())[0]
            ),
        )
        rng = random.Random(7)
        junk = [bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 64))) for _ in range(5)]
        wrong_layout = encode_frame(0xDEADBEEF, 10**6, 0, b"\x00" * 4)
        # To the DN's sync key (as if we were a CN with another mission).
        for payload in [*junk, wrong_layout]:
            replies = s.get(f"{v}/dn0/to_cn", payload=payload, timeout=2.0)
            for _ in replies:
                pass
        # To the CN's ground-command key (BLOCK: a put's default, DROP, may
        # lose one on a busy box, and then the count could not be exact).
        for payload in [*junk, wrong_layout]:
            s.put(f"{v}/gn/to_cn", payload, congestion_control=zenoh.CongestionControl.BLOCK)
        n = len(junk) + 1
        c.wait_for(
            lambda dv: int(dv.get("dn0_bad_frames")) >= n and int(dv.get("cn_bad_frames")) >= n,
            60,
            "bad frames counted",
        )
        assert int(c.tm.get("dn0_bad_frames")) == n
        assert int(c.tm.get("cn_bad_frames")) == n
        # Nothing was applied: the setpoint and the command state are untouched.
        assert c.tm.get("dn0_setpoint") == 0.0
        assert c.tm.get_name("cn_cmd_status") == "NONE"
        # The loop kept running and dn0 kept syncing.
        before = sync_counts(c.tm, ("dn0",))
        c.advance(50)
        assert_kept_syncing(before, sync_counts(c.tm, ("dn0",)), ("dn0",))
        # The rejections were logged as events by the node that rejected
        # them: together (at most one event a second, so a flood cannot
        # multiply them), each event saying how many.
        seen: dict[str, int] = {}
        while len(seen) < 2 or min(seen.values()) < n:
            e = events.get(timeout=60)
            if e.id == "bad_frame":
                seen[e.node] = seen.get(e.node, 0) + int(e.text.split()[0])
        assert seen == {"cn": n, "dn0": n}
        sub.undeclare()


@pytest.mark.parametrize("skew_ms", [50.0, -30.0])
def test_clock_sync_measures_injected_offset(tmp_path: Path, skew_ms: float) -> None:
    """A DN clock skewed on purpose is measured within 1 ms of the injected offset."""
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0", env={"ZPLATFORM_CLOCK_SKEW_NS": str(int(skew_ms * 1e6))})
        c.spawn("cn")
        c.advance(10)
        measured_ms = int(c.tm.get("dn0_clock_offset_ns")) / 1e6
        # offset = CN - DN: a DN ahead by +50 ms is corrected by -50 ms.
        assert abs(measured_ms + skew_ms) < 1.0, measured_ms
        # The default estimator did the measuring: no fallback to node_clock.
        log = c.log("dn0")
        assert "(zenoh_ts estimator," in log and "falling back" not in log, log[-3000:]


def test_clock_sync_with_the_node_clock_estimator(tmp_path: Path) -> None:
    """`clock: {estimator: node_clock}` starts the DN on the node-clock
    estimator, which measures the injected offset too."""
    src = yaml.safe_load((CONFIGS / "minimal.yaml").read_text())
    src["clock"] = {"estimator": "node_clock"}
    (tmp_path / "node_clock.yaml").write_text(yaml.safe_dump(src, sort_keys=False))
    with Cluster(tmp_path / "node_clock.yaml", tmp_path) as c:
        assert c.mission.clock.estimator == "node_clock"
        c.spawn("dn0", env={"ZPLATFORM_CLOCK_SKEW_NS": str(40_000_000)})
        c.spawn("cn")
        c.advance(10)
        assert abs(int(c.tm.get("dn0_clock_offset_ns")) + 40_000_000) < 1_000_000
        assert abs(int(c.tm.get("dn0_clock_drift_ns"))) < 1_000_000
        log = c.log("dn0")
        assert "(node_clock estimator," in log and "residual" in log, log[-3000:]


def test_a_skew_beyond_the_bound_is_corrected_and_the_residual_checked(tmp_path: Path) -> None:
    """The bound (100 ms, thesis 4.9) is about the error left after the
    correction: a DN 250 ms ahead is corrected, its residual is measured and
    reported, and the mission flies."""
    with Cluster(CONFIGS / "minimal.yaml", tmp_path) as c:
        c.spawn("dn0", env={"ZPLATFORM_CLOCK_SKEW_NS": str(250_000_000)})
        c.spawn("cn")
        c.advance(20)
        assert abs(int(c.tm.get("dn0_clock_offset_ns")) + 250_000_000) < 1_000_000
        assert abs(int(c.tm.get("dn0_clock_drift_ns"))) < 1_000_000
        assert c.tm.get_name("cn_fault") == "NONE"


def test_cn_refuses_a_residual_beyond_the_bound() -> None:
    from zplatform.errors import NodeError
    from zplatform.node.control import check_clocks

    check_clocks({"dn0": -250_000_000}, {"dn0": 40_000}, 100.0)  # corrected: fine
    with pytest.raises(NodeError, match=r"dn0's clock, corrected by -250\.000 ms, is still off"):
        check_clocks({"dn0": -250_000_000}, {"dn0": 120_000_000}, 100.0)


def _up(path: Path, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "zplatform", "up", str(path), "--quiet", *extra],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


def test_up_flies_on_when_a_device_node_dies(tmp_path: Path) -> None:
    """`zplatform up`: a DN's death does not end the flight: the CN keeps its
    loop, latches DN_LOST; Ctrl-C then ends the run non-zero, naming the DN,
    with every child reaped (issue 9, defect 9)."""
    import psutil

    from zplatform.ground.link import GroundLink
    from zplatform.mission.load import load_mission
    from zplatform.runtime.transport import rewrite_endpoints

    path = tmp_path / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)
    up = _up(path, "--summary", str(tmp_path / "s.json"))
    rx = GroundLink(load_mission(path), events=False)
    try:
        while rx.logic.received < 20:
            assert up.poll() is None, up.stdout.read().decode()[-2000:]  # type: ignore[union-attr]
            rx.next(1.0)
        children = psutil.Process(up.pid).children()
        assert len(children) == 3  # dn0, gn, cn
        dn0 = next(p for p in children if "dn0" in p.cmdline())
        dn0.kill()
        deadline = time.monotonic() + 30
        while rx.dv.get_name("cn_fault") != "DN_LOST":
            assert time.monotonic() < deadline, "DN_LOST never latched"
            assert up.poll() is None, up.stdout.read().decode()[-2000:]  # type: ignore[union-attr]
            rx.next(1.0)
        loop = int(rx.dv.get("cn_loop"))
        while int(rx.dv.get("cn_loop")) < loop + 50:  # still flying
            rx.next(1.0)
        up.send_signal(signal.SIGINT)
        rc = up.wait(timeout=60)
        out = up.stdout.read().decode()  # type: ignore[union-attr]
        assert rc == 1, out
        assert "node dn0 died" in out and "carries on" in out
        s = json.loads((tmp_path / "s.json").read_text())
        assert s["nodes"]["cn"]["fault"] == "DN_LOST"
        _, alive = psutil.wait_procs(children, timeout=15)
        assert not alive, alive
    finally:
        rx.close()
        if up.poll() is None:
            up.kill()


def test_up_reports_a_dead_control_node(tmp_path: Path) -> None:
    """`zplatform up`: when the CN is killed the run ends with a message, a
    non-zero exit and a summary filled from its last telemetry."""
    import psutil

    from zplatform.runtime.transport import rewrite_endpoints

    path = tmp_path / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)
    up = _up(path, "--summary", str(tmp_path / "s.json"), "--log", str(tmp_path / "tm.csv"))
    try:
        # The ground log fills once the CN flies: wait on it, not on time.
        def logged() -> bool:  # a file `up`'s ground writes; failing at once if `up` ended
            assert up.poll() is None, up.stdout.read().decode()[-2000:]  # type: ignore[union-attr]
            p = tmp_path / "tm.csv"
            return p.exists() and p.read_text().count("\n") > 50

        wait_until(logged, 60, "50 rows of telemetry logged", poll_s=0.2)
        children = psutil.Process(up.pid).children()
        cn = next(p for p in children if p.cmdline()[-1:] != [] and " cn " in " ".join(p.cmdline()))
        cn.kill()
        rc = up.wait(timeout=60)
        out = up.stdout.read().decode()  # type: ignore[union-attr]
        assert rc == 1, out
        assert "control node died" in out
        s = json.loads((tmp_path / "s.json").read_text())
        assert s["loops"] > 50 and s["final_state"] == "IDLE", s
        _, alive = psutil.wait_procs(children, timeout=15)
        assert not alive, alive
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()


def test_stalled_device_node_skips_missed_loops(tmp_path: Path) -> None:
    """A DN frozen for ~30 loops answers the queued queries as stale and runs none of them.

    Over zenoh (``intra_host: zenoh``): the backlog is zenoh's queries. On
    shared memory the first frozen loop's trigger is lost there and the
    link falls back, so one query fewer queues (tests/integration/test_shm_sync.py)."""
    import signal

    src = tmp_path / "minimal_zenoh.yaml"
    raw = yaml.safe_load((CONFIGS / "minimal.yaml").read_text())
    raw.setdefault("transport", {})["intra_host"] = "zenoh"
    src.write_text(yaml.safe_dump(raw, sort_keys=False))
    with Cluster(src, tmp_path) as c:
        dn = c.spawn("dn0")
        c.spawn("cn")
        c.advance(20)
        os.kill(dn.pid, signal.SIGSTOP)
        try:
            c.advance(30)
        finally:
            os.kill(dn.pid, signal.SIGCONT)
        rx = int(c.tm.get("cn_rx_dn0"))
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 20, 30, "dn0 back in sync")
        cn_loop = int(c.tm.get("cn_loop"))
        dn.terminate()
        assert dn.wait(timeout=30) == 0
        s = json.loads((tmp_path / "dn0.json").read_text())
        # The backlog was answered (stale) rather than run as a burst of loops.
        assert s["stale_queries"] >= 15, s
        assert s["loops"] <= cn_loop - 15, (s, cn_loop)


def test_up_with_a_script_and_no_duration_ends_after_the_last_verdict(tmp_path: Path) -> None:
    """`up --commands FILE` without `--duration` runs on past the script's
    last verdict (the ground node's script_done event), then stops by
    itself: every node stopped cleanly, exit 0. How long past it is
    ``--settle`` (1 s here; the default, SETTLE_S with at least
    MIN_DURATION_S in all, is tests/unit/test_supervisor.py's, on a clock of
    its own)."""
    from zplatform.runtime.transport import rewrite_endpoints

    settle_s = 1.0
    path = tmp_path / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)
    script = tmp_path / "s.commands"
    script.write_text("at 0.2 noop\nat 0.4 noop\n")
    log = tmp_path / "tm.csv"
    up = subprocess.Popen(
        [sys.executable, "-m", "zplatform", "up", str(path), "--commands", str(script),
         "--settle", str(settle_s), "--summary", str(tmp_path / "s.json"), "--log", str(log)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        out, _ = up.communicate(timeout=120)  # it ends by itself
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
    text = out.decode()
    assert up.returncode == 0, text[-3000:]
    assert "the script's last verdict came" in text and "stopping" in text
    s = json.loads((tmp_path / "s.json").read_text())
    assert [c["status"] for c in s["commands"]] == ["ACCEPTED", "ACCEPTED"]
    assert s["exit_codes"] == {"dn0": 0, "gn": 0, "cn": 0}
    # settle_s past the last verdict: the CN's loops (scheduled times, so a
    # skipped period on a busy host does not count against it) ran that long.
    verdict_s = s["commands"][-1]["t_ns"] / 1e9
    assert s["duration_s"] >= verdict_s + settle_s - 0.1, (s["duration_s"], verdict_s)
    events = (tmp_path / "tm.events.jsonl").read_text()
    assert '"id": "script_done"' in events
