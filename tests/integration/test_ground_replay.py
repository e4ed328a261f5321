"""Issue 18's telemetry replay, live: the ground believes only fresh telemetry
of the run it follows, and reports only the verdicts the control node gave.

Run 1 of recovery_igniter (real node processes) is recorded by a plain zenoh
subscriber, no key needed: ARM #1, LAUNCH #2, then ABORT #3 accepted. During
run 2 that recording is published on ``rocket/cn/telemetry`` over and over
while the operator sends ABORT with ``zplatform cmd`` (a real process), then
an ABORT the new state refuses. The replaying peer dials the ground node,
and the tools (``cmd`` and the test's own ground) dial it: every link is
made by the test, none left to zenoh's gossip, and the test waits for them
by the ground's liveliness token and the tools' refusals, never a sleep.
Before the fix the ground took the old run's epoch and numbers from the
replay and printed ``ABORT #3: ACCEPTED`` while
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
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
import zenoh

from zplatform.ground.link import GroundLink
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import KeySpace, free_port, wait_for_nodes, zenoh_config
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


def _tools_mission(path: Path, attacker_ep: str) -> Path:
    """A copy of the mission at ``path`` that names ``attacker_ep`` among the
    ground node's endpoints: a tool of it (which dials every node's
    endpoints) dials the attacker too. The nodes run the original."""
    raw = yaml.safe_load(path.read_text())
    raw["nodes"]["gn"]["listen"] = [*raw["nodes"]["gn"]["listen"], attacker_ep]
    out = path.with_name("tools.yaml")
    out.write_text(yaml.safe_dump(raw, sort_keys=False))
    return out


def _wait_until(link: GroundLink, pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Take ``link``'s input until ``pred`` holds (AssertionError at ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        link.next(0.1)


def _cmd(path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", "cmd", str(path), *args, "--timeout", "20"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


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

            # The attacker: run 1's telemetry on the telemetry key, over and
            # over. Every link it has is one the test makes, none left to
            # zenoh's gossip (which linked it to the ground in about half the
            # runs): it dials the ground node, and listens on a port of its
            # own that the test's tools dial (a copy of the mission that
            # names it among the ground's endpoints).
            attacker_ep = f"tcp/127.0.0.1:{free_port()}"
            cfg = zenoh_config(c.mission, None)
            cfg.insert_json5("connect/endpoints", json.dumps(c.mission.nodes["gn"].listen))
            cfg.insert_json5("listen/endpoints", json.dumps([attacker_ep]))
            cfg.insert_json5("scouting/gossip/enabled", "false")
            attacker = zenoh.open(cfg)
            pub = attacker.declare_publisher("rocket/cn/telemetry")
            # The ground node's token reached the attacker over their link,
            # after its telemetry subscriber (declared first): every frame
            # put from now on reaches the ground.
            wait_for_nodes(attacker, KeySpace(c.mission.vehicle), ["gn"], 30)
            tools = _tools_mission(c.path, attacker_ep)
            seen = GroundLink(load_mission(tools), events=False)

            def replay() -> None:
                while not stop.is_set():
                    for frame in recording:
                        if stop.wait(0.002):
                            return
                        pub.put(frame)

            th = threading.Thread(target=replay, daemon=True)
            th.start()
            try:
                # The test's own ground, a tool of the copy: it dials the
                # attacker, and refuses what the attacker replays.
                _wait_until(
                    seen, lambda: seen.logic.counters.refused["stale"] > 0, 30, "a stale refusal"
                )
                r = _cmd(tools, "abort")
                assert r.returncode == 0, r.stdout + r.stderr
                assert r.stdout.splitlines()[0].startswith("ABORT #3: ACCEPTED"), r.stdout
                _state(c, "ABORTED")  # it was: the control node accepted it
                # ABORTED refuses ABORT: the tool says so, with the CN's reason.
                r = _cmd(tools, "abort")
                assert r.returncode == 1, r.stdout + r.stderr
                assert r.stdout.startswith("ABORT #4: REJECTED_NOT_ALLOWED: not allowed in state "
                                           "ABORTED"), r.stdout  # fmt: skip
                assert "ACCEPTED" not in r.stdout
                c.advance(20)
                assert int(c.tm.get("cn_epoch")) == epoch
                _wait_until(seen, lambda: seen.logic.received > 0, 30, "a genuine snapshot")
                assert int(seen.dv.get_name("cn_epoch")) == epoch  # nothing replayed taken
            finally:
                stop.set()
                th.join(5)
                seen.close()
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
