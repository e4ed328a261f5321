"""Issue 18's telemetry replay, live: the ground believes only fresh telemetry
of the run it follows, and reports only the verdicts the control node gave.

Run 1 of recovery_igniter (real node processes) is recorded by a plain zenoh
subscriber, no key needed: ARM #1, LAUNCH #2, then ABORT #3 accepted. During
run 2 that recording is published on ``rocket/cn/telemetry`` over and over
while the operator sends ABORT with ``zplatform cmd`` (a real process), then
an ABORT the new state refuses. Before the fix the ground took the old run's
epoch and numbers from the replay and printed ``ABORT #3: ACCEPTED`` while
the control node refused the request and stayed ARMED, and the ground node
logged the replayed rows as real.

The mission runs on plain links (``security.transport: plain``): under the
default mutual TLS the recorder and the replaying peer, holding no
certificate, get no session at all (tests/integration/test_secure_transport.py),
and the ground's own checks are what this test is about.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from zplatform.ground.link import GroundLink
from zplatform.runtime.transport import free_port, zenoh_config
from zplatform.telemetry.logs import read_csv

from .harness import CONFIGS, ROOT, Cluster

pytestmark = pytest.mark.timeout(240)

MISSION = CONFIGS / "recovery_igniter.yaml"


def _state(c: Cluster, state: str) -> None:
    c.wait_for(lambda dv: dv.get_name("cn_state") == state, 30, f"state {state}")


def _record_run_1(tmp: Path) -> list[bytes]:
    """Run 1's telemetry around its ABORT #3, as a passive subscriber got it."""
    tmp.mkdir()
    with Cluster(MISSION, tmp, transport="plain") as c:
        for n in ("dn0", "dn1", "cn"):
            c.spawn(n)
        tap = zenoh.open(zenoh_config(c.mission, None))
        got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        sub = tap.declare_subscriber(
            "rocket/cn/telemetry",
            zenoh.handlers.Callback(lambda s: got.put(s.payload.to_bytes()), indirect=False),
        )
        op = GroundLink(c.mission, commands=True)
        try:
            _state(c, "SAFE")
            assert [o.status for o in op.command("launch", armed=True)] == ["ACCEPTED"] * 2
            _state(c, "ARMED")
            c.advance(50)
            (abort,) = op.command("abort")
            assert (abort.seq, abort.status) == (3, "ACCEPTED")
            c.advance(50)
        finally:
            op.close()
            sub.undeclare()
            tap.close()
    frames = []
    while not got.empty():
        frames.append(got.get())
    return frames


def _cmd(path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", "cmd", str(path), *args, "--timeout", "20"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


# With the soaks (-m slow): its attacker reaches the test's ground only if
# zenoh's gossip connects them, which failed in about half the runs (on
# 6fd940c too): then nothing is replayed and the check cannot hold. The
# refusal itself is asserted in process (tests/faults/test_keyspace_faults.py,
# test_a_fresh_ground_refuses_a_run_that_just_ended); the fix is to connect
# the attacker to the ground explicitly (the closing note).
@pytest.mark.slow
def test_a_replayed_run_is_refused_and_verdicts_are_the_control_nodes(tmp_path: Path) -> None:
    recording = _record_run_1(tmp_path / "run1")
    assert len(recording) > 80
    (tmp_path / "run2").mkdir()
    with Cluster(MISSION, tmp_path / "run2", transport="plain") as c:
        for n in ("dn0", "dn1"):
            c.spawn(n)
        c.spawn("gn", "--log", str(c.tmp / "gn.csv"))
        c.spawn("cn")
        op = GroundLink(c.mission, commands=True)
        stop = threading.Event()
        try:
            _state(c, "SAFE")
            epoch = int(c.tm.get("cn_epoch"))
            assert [o.status for o in op.command("launch", armed=True)] == ["ACCEPTED"] * 2
            _state(c, "ARMED")

            # The attacker: run 1's telemetry on the telemetry key, over and over,
            # from a peer that listens too, so gossip brings every tool to it.
            cfg = zenoh_config(c.mission, None)
            cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port()}"]))
            attacker = zenoh.open(cfg)
            pub = attacker.declare_publisher("rocket/cn/telemetry")

            def replay() -> None:
                while not stop.is_set():
                    for frame in recording:
                        if stop.wait(0.002):
                            return
                        pub.put(frame)

            th = threading.Thread(target=replay, daemon=True)
            th.start()
            try:
                r = _cmd(c.path, "abort")
                assert r.returncode == 0, r.stdout + r.stderr
                assert r.stdout.splitlines()[0].startswith("ABORT #3: ACCEPTED"), r.stdout
                _state(c, "ABORTED")  # it was: the control node accepted it
                # ABORTED refuses ABORT: the tool says so, with the CN's reason.
                r = _cmd(c.path, "abort")
                assert r.returncode == 1, r.stdout + r.stderr
                assert r.stdout.startswith("ABORT #4: REJECTED_NOT_ALLOWED: not allowed in state "
                                           "ABORTED"), r.stdout  # fmt: skip
                assert "ACCEPTED" not in r.stdout
                c.advance(20)  # this test's own ground, under the replay too
                assert c.rx.logic.counters.refused["stale"] > 0
                assert int(c.tm.get("cn_epoch")) == epoch
            finally:
                stop.set()
                th.join(5)
                pub.undeclare()
                attacker.close()
        finally:
            op.close()
        c.procs["gn"].terminate()
        assert c.procs["gn"].wait(30) == 0, c.log("gn")
    gn = json.loads((tmp_path / "run2" / "gn.json").read_text())
    assert gn["telemetry_refused"]["stale"] > 0, gn
    rows = read_csv(tmp_path / "run2" / "gn.csv")
    assert rows and {int(r["cn_epoch"]) for r in rows} == {epoch}  # nothing replayed was logged
    loops = [int(r["cn_loop"]) for r in rows]
    assert loops == sorted(set(loops))
