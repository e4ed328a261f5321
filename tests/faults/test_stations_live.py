"""Stations over routers and a WAN, live, in network namespaces (issue 29).

Three namespaces on one bridge: the vehicle LAN (``zplatform node`` cn and
dn0), the pad (its router, ``zplatform router --name pad``, connected to the
CN; the pad station's ``cmd`` is its client) and the control room (its
router, connected to the pad router through the WAN relay,
bench/wan.py, 80 ms each way and 1 % of chunks lost; the room's and
the viewers' lounge's ``cmd`` are clients of the room router). Mutual TLS
and the generated access control throughout, the mission's own PKI and key
files from ``zplatform keygen``.

Every step is one ``zplatform cmd`` process naming its operator and station;
a verdict proves the telemetry reached that station (``cmd`` waits for it)
and the request reached the CN:

* a viewer in the lounge, two routers and the WAN away, is refused
  (REJECTED_VIEW_ONLY);
* the pad's operator takes the lock and hands it to the flight director in
  the control room, who commands with it; the pad is then refused
  (REJECTED_NOT_HOLDER);
* the flight director's LAUNCH is two-person: armed, it waits until range
  safety approves its ARM from the lounge, then is accepted;
* range safety aborts from the view-only lounge (ACCEPTED);
* the flight director at a prompt in the control room takes the lock: the
  station renews it, so for two leases and more every request of the pad
  is refused naming fd@room; the prompt is killed, and once the lease has
  run out (the CN's ``cmd_lock`` event says so) the pad takes the lock.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.faults.netns import NetnsHost

ROOT = Path(__file__).resolve().parents[2]
CN, DN, GN, PAD, ROOM, WAN = 7447, 7448, 7449, 7500, 7600, 7700
LEASE_S = 10


def _mission(veh: str, pad: str, room: str) -> str:
    return f"""
mission: stations
vehicle: rocket
loop_hz: 50
sync_timeout_ms: 5
security: {{transport: mtls}}
commands: {{hazardous: [LAUNCH]}}
transport: {{gossip_scouting: false, multicast_scouting: false}}
nodes:
  cn:  {{listen: ['tcp/{veh}:{CN}']}}
  dn0: {{listen: ['tcp/{veh}:{DN}'], connect: ['tcp/{veh}:{CN}']}}
  gn:  {{listen: ['tcp/{veh}:{GN}'], connect: ['tcp/{veh}:{CN}']}}
regions:
  cn:
    - {{name: heartbeat, type: u32, initial: 0}}
  cn_to_dn0:
    - {{name: dn0_setpoint, type: f32, initial: 0.0}}
  dn0_to_cn:
    - {{name: dn0_measurement, type: f32, initial: 0.0}}
state_machine:
  initial: IDLE
  states:
    IDLE:
      transitions:
        - {{element: cn_cmd, op: "==", value: LAUNCH, to: RUN}}
    RUN:
      transitions:
        - {{element: cn_cmd, op: "==", value: ABORT, to: SAFE}}
    SAFE: {{}}
ground:
  lease_s: {LEASE_S}
  stations:
    - {{name: pad, connect: ['tcp/{pad}:{PAD}']}}
    - {{name: room, connect: ['tcp/{room}:{ROOM}']}}
    - {{name: lounge, may: view, connect: ['tcp/{room}:{ROOM}']}}
  operators:
    - {{name: pat, roles: [operator]}}
    - {{name: fd, roles: [flight_director]}}
    - {{name: rso, roles: [range_safety]}}
    - {{name: vic, roles: [viewer]}}
  two_person: [LAUNCH]
  routers:
    - {{name: pad, listen: ['tcp/{pad}:{PAD}'], connect: ['tcp/{veh}:{CN}']}}
    - {{name: room, listen: ['tcp/{room}:{ROOM}'], connect: ['tcp/127.0.0.1:{WAN}']}}
"""


def _ready(p: subprocess.Popen[str], what: str) -> None:
    assert p.stdout is not None
    line = p.stdout.readline().strip()
    assert line.startswith("READY"), f"{what} did not start: {line!r} (exit {p.poll()})"


# With the soaks (-m slow): 23-44 s of namespaces, routers and a WAN; the
# default suite keeps the routers in process (tests/integration/test_routers.py)
# and the authority rules in lockstep (tests/unit/test_stations_lockstep.py).
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_stations_through_two_routers_and_a_wan(
    netns_hosts: Callable[..., list[NetnsHost]], tmp_path: Path
) -> None:
    veh, pad, room = netns_hosts(3)
    path = tmp_path / "stations.yaml"
    path.write_text(_mission(veh.addr, pad.addr, room.addr))
    # The key files keygen writes, as on a deployment's hosts: no master key
    # (tests/conftest.py sets one for every other test's processes).
    env = {
        "XDG_CONFIG_HOME": str(tmp_path / "config"),
        "PYTHONPATH": str(ROOT),
        "ZPLATFORM_KEY": "",
    }
    zp = [sys.executable, "-m", "zplatform"]
    kg = subprocess.run(
        [*zp, "keygen", str(path)],
        env=dict(os.environ, **env),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert kg.returncode == 0, kg.stderr
    node = [*zp, "node", str(path)]
    veh.popen([*node, "dn0", "--no-realtime"], log=tmp_path / "dn0.log", env=env, cwd=ROOT)
    veh.popen(
        [*node, "cn", "--duration", "240", "--ground-wait", "0", "--no-realtime"],
        log=tmp_path / "cn.log",
        env=env,
        cwd=ROOT,
    )
    router = [*zp, "router", str(path), "--name"]
    _ready(pad.popen([*router, "pad"], pipe_stdio=True, env=env, cwd=ROOT), "the pad router")
    wan = [sys.executable, "-m", "bench.wan", f"127.0.0.1:{WAN}", f"{pad.addr}:{PAD}"]
    _ready(room.popen([*wan, "--seed", "29"], pipe_stdio=True, env=env, cwd=ROOT), "the WAN")
    _ready(room.popen([*router, "room"], pipe_stdio=True, env=env, cwd=ROOT), "the room router")

    def cmd(host: NetnsHost, who: str, *words: str) -> tuple[int, str]:
        op, st = who.split("@")
        r = host.run(
            [
                "env",
                *(f"{k}={v}" for k, v in env.items()),
                *zp,
                "cmd",
                str(path),
                *words,
                "--operator",
                op,
                "--station",
                st,
                "--timeout",
                "60",
            ],
            timeout=180,
        )
        return r.returncode, (r.stdout + r.stderr).strip()

    rc, out = cmd(room, "vic@lounge", "noop")
    assert rc == 1 and "by vic@lounge: REJECTED_VIEW_ONLY" in out, out
    rc, out = cmd(pad, "pat@pad", "lock")
    assert rc == 0 and "by pat@pad: ACCEPTED" in out, out
    as_fd = ["--operator", "fd", "--station", "room"]
    rc, out = cmd(pad, "pat@pad", "handover", "fd")
    assert rc == 0 and "by pat@pad: ACCEPTED" in out, out
    rc, out = cmd(room, "fd@room", "noop")
    assert rc == 0 and "by fd@room: ACCEPTED" in out, out
    rc, out = cmd(pad, "pat@pad", "noop")
    assert rc == 1 and "REJECTED_NOT_HOLDER" in out and "fd@room" in out, out
    # A two-person LAUNCH: fd's `cmd launch --arm` waits after its ARM until
    # range safety approves it from the lounge, then goes.
    launch = room.popen(
        [*zp, "cmd", str(path), "launch", "--arm", "--timeout", "60", *as_fd],
        pipe_stdio=True,
        env=env,
        cwd=ROOT,
    )
    assert launch.stdout is not None
    waiting = launch.stdout.readline()
    assert "waiting for a second operator's approval" in waiting, waiting
    arm = waiting.split("#", 1)[1].split()[0]
    rc, out = cmd(room, "rso@lounge", "approve", arm)
    assert rc == 0 and "by rso@lounge: ACCEPTED" in out, out
    rest = launch.stdout.read()
    assert launch.wait(timeout=60) == 0, rest
    assert f"ARM #{arm} by fd@room: ACCEPTED" in rest
    assert f"LAUNCH #{int(arm) + 2} by fd@room: ACCEPTED" in rest, rest
    rc, out = cmd(room, "rso@lounge", "abort")
    assert rc == 0 and "by rso@lounge: ACCEPTED" in out, out

    # The control room's station at a prompt keeps the lock while alive.
    prompt = room.popen(
        [*zp, "ground", str(path), "--prompt", "--interval", "3600", *as_fd],
        pipe_stdio=True,
        env=env,
        cwd=ROOT,
    )
    assert prompt.stdin is not None and prompt.stdout is not None
    prompt.stdin.write("lock\n")
    prompt.stdin.flush()
    for line in prompt.stdout:
        if line.startswith("LOCK #"):
            assert "by fd@room: ACCEPTED" in line, line
            break
    locked = time.monotonic()
    refused = 0
    while time.monotonic() - locked < 2 * LEASE_S:
        rc, out = cmd(pad, "pat@pad", "lock")
        assert rc == 1 and "REJECTED_NOT_HOLDER" in out and "fd@room holds" in out, out
        refused += 1
    os.killpg(prompt.pid, signal.SIGKILL)  # the station dies: no more renewals
    for _ in range(30):
        rc, out = cmd(pad, "pat@pad", "lock")
        if rc == 0:
            break
        assert "REJECTED_NOT_HOLDER" in out, out
    assert rc == 0 and "by pat@pad: ACCEPTED" in out, out
    assert refused >= 2
    cn_log = (tmp_path / "cn.log").read_text()
    assert "fd@room's command lock expired" in cn_log, cn_log[-3000:]
