"""The standby control node on real processes (issue 21): kill -9, SIGSTOP, restart.

The flight mission (``configs/flight.yaml``) with both control nodes, its
device nodes and its vehicle world as processes on loopback. Each case
faults whichever control node commands at that moment (on a busy box the
standby may have taken over once already) and checks what happened: a new
term in command, no device node safed, ``zplatform cmd`` answered by the
new commander, and, from the device nodes' own flight recorders, no loop
driven by two terms. How fast the takeover is, is ``bench.failover``'s.
The full flights (kill -9 and SIGSTOP at several points of a flight, the
network partitions) run with the soaks: ``-m slow``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.integration.harness import CONFIGS, ROOT, Cluster
from tests.terms import driven_terms, two_term_loops
from tests.waits import wait_until
from zplatform.recorder import RECORDER_DIR_ENV

FLIGHT = CONFIGS / "flight.yaml"
NODES = ("world", "dn0", "dn1", "cn", "cn_b")
pytestmark = pytest.mark.timeout(240)


def zp(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )


def _ready(c: Cluster) -> tuple[str, int]:
    """Wait until the standby follows; the commander and its term."""
    c.wait_for(lambda dv: bool(dv.get("cn_standby_ready")), 60, "the standby following")
    return c.tm.get_name("cn_commander"), int(c.tm.get("cn_term"))


def _no_safing(c: Cluster) -> None:
    dv = c.tm
    assert not dv.get("dn0_safed") and not dv.get("dn1_safed"), c.log("dn0") + c.log("dn1")
    for dn in ("dn0", "dn1"):
        assert "dn_safed:" not in c.log(dn), c.log(dn)[-2000:]


def _one_term_per_loop(c: Cluster, root: Path, terms: set[int]) -> None:
    driven = driven_terms(c.mission, root)
    assert driven, "the device nodes recorded nothing"
    assert two_term_loops(driven) == []
    assert {t for by in driven.values() for t in by.values()} >= terms


def test_a_killed_commander_is_replaced_then_rejoins_as_the_standby(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """kill -9 of the commander on the pad: the standby takes command in the
    next term, no device node safes, ``zplatform cmd`` works unchanged
    (answered by the new commander); the killed node, started again, does
    not start over: it finds the run going on and follows as the standby."""
    root = tmp_path / "rec"
    monkeypatch.setenv(RECORDER_DIR_ENV, str(root))
    with Cluster(FLIGHT, tmp_path) as c:
        for n in NODES:
            # Both control nodes record their loops (the standby once it commands).
            extra = ("--record", str(tmp_path / f"loops-{n}")) if n in ("cn", "cn_b") else ()
            c.spawn(n, *extra)
        commander, term = _ready(c)
        assert zp("cmd", str(c.path), "noop").returncode == 0
        c.kill(commander)
        c.wait_for(lambda dv: int(dv.get("cn_term")) > term, 30, "a new term in command")
        new = c.tm.get_name("cn_commander")
        assert new != commander
        c.advance(30)
        _no_safing(c)
        r = zp("cmd", str(c.path), "noop")
        assert r.returncode == 0 and "ACCEPTED" in r.stdout, r.stdout + r.stderr
        # Restarted, the old commander rejoins the running flight as the standby.
        now = int(c.tm.get("cn_term"))
        c.spawn(commander)
        c.wait_for(lambda dv: bool(dv.get("cn_standby_ready")), 60, "it follows again")
        c.advance(20)
        assert int(c.tm.get("cn_term")) == now and c.tm.get_name("cn_commander") == new
        assert c.tm.get_name("cn_state") == "SAFE"
        assert "follows as the standby" in c.log(commander)
    _one_term_per_loop(c, root, {term, now})
    # The new commander's recording starts at the takeover and replays bit for bit.
    r = zp("replay", str(tmp_path / f"loops-{new}"), "--mission", str(c.path))
    assert r.returncode == 0 and "identical" in r.stdout, r.stdout + r.stderr


def test_a_stopped_commander_is_replaced_and_stands_down_when_continued(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGSTOP of the commander for one second: the standby takes over; the
    stopped node, continued with its old state, learns of the newer term
    before its next loop and stands down; no loop is driven by two terms."""
    root = tmp_path / "rec"
    monkeypatch.setenv(RECORDER_DIR_ENV, str(root))
    with Cluster(FLIGHT, tmp_path) as c:
        for n in NODES:
            c.spawn(n)
        commander, term = _ready(c)
        p = c.procs[commander]
        os.kill(p.pid, signal.SIGSTOP)
        try:
            c.wait_for(lambda dv: int(dv.get("cn_term")) > term, 30, "a new term in command")
            c.advance(100)  # a second of the new term while it is stopped
        finally:
            os.kill(p.pid, signal.SIGCONT)
        c.advance(50)
        assert p.poll() is None  # it runs on, as the standby
        assert c.tm.get_name("cn_commander") != commander
        _no_safing(c)
        c.advance(10)
        assert "stands down" in c.log(commander), c.log(commander)[-2000:]
    _one_term_per_loop(c, root, {term, term + 1})


def test_a_run_with_an_end_ends_there_after_a_takeover(tmp_path: Path) -> None:
    """Both control nodes run with ``--duration`` (as ``up --duration`` runs
    them): the commander stopped for a second is replaced, and the run
    still ends at its planned loop: the new commander flags it final and
    exits, and the node that stood down stops following there and exits
    (before, neither ever ended and ``up --duration`` hung)."""
    loops = 1000  # 10 s: the fault at most halfway, with room for a busy host's start
    with Cluster(FLIGHT, tmp_path) as c:
        for n in NODES:
            extra = ("--duration", str(loops / c.mission.loop_hz)) if n in ("cn", "cn_b") else ()
            c.spawn(n, *extra)
        commander, term = _ready(c)
        assert int(c.tm.get("cn_loop")) < loops // 2, "the run is too near its end to fault"
        p = c.procs[commander]
        os.kill(p.pid, signal.SIGSTOP)
        try:
            c.wait_for(lambda dv: int(dv.get("cn_term")) > term, 30, "a new term in command")
        finally:
            os.kill(p.pid, signal.SIGCONT)
        seen = 0
        deadline = time.monotonic() + 120.0  # generous: a busy host
        while c.procs["cn"].poll() is None or c.procs["cn_b"].poll() is None:
            if c.rx.next(0.2) is not None:
                seen = max(seen, int(c.tm.get("cn_loop")))
            # The new commander's final loop is the first at or after the end
            # (a loaded box may make it skip a few).
            assert seen <= loops + 10, f"loop {seen} after the run's last, {loops}"
            assert time.monotonic() < deadline, "the control nodes did not end the run"
        assert c.procs["cn"].returncode == 0, c.log("cn")[-3000:]
        assert c.procs["cn_b"].returncode == 0, c.log("cn_b")[-3000:]
        assert seen > loops // 2
        assert "stands down" in c.log(commander), c.log(commander)[-2000:]


def test_a_control_node_restarted_in_flight_resumes_and_the_flight_deploys(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """recovery_igniter (no standby): the control node killed while ARMED and
    started again a second later does not come up in SAFE at loop 1 with a
    new run: it resumes the run from its own flight recorder (the same
    epoch, ARMED, loop numbers going on by time), says so (``cn_resumed``),
    and the flight deploys."""
    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp_path / "rec"))
    with Cluster(CONFIGS / "recovery_igniter.yaml", tmp_path) as c:
        for n in ("world", "dn0", "dn1", "cn"):
            c.spawn(n)
        c.advance(20)
        r = zp("cmd", str(c.path), "launch", "--arm")
        assert r.returncode == 0, r.stdout + r.stderr
        c.wait_for(lambda dv: dv.get_name("cn_state") == "ARMED", 30, "ARMED")
        c.advance(50)
        epoch, loop = int(c.tm.get("cn_epoch")), int(c.tm.get("cn_loop"))
        c.kill("cn")
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_loop")) > loop + 5, 60, "the run going on")
        assert int(c.tm.get("cn_epoch")) == epoch
        assert c.tm.get_name("cn_state") in ("ARMED", "FIRE", "DEPLOYED")
        # Its log says so (read until the line is there: a busy host may show
        # the resumed loops in telemetry before the node's log line lands).
        wait_until(lambda: "resumed the run in flight" in c.log("cn"), 30, "cn's resumed line")
        c.wait_for(lambda dv: dv.get_name("cn_state") == "DEPLOYED", 60, "DEPLOYED")
        assert c.tm.get_name("cn_fault") == "NONE"
