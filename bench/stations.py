"""Stations through routers (issue 29): a command's round trip, and the CN's
CPU for telemetry fan-out, direct and through zenoh routers.

One host, loopback, plain TCP (the routers' TLS and access control are
tested, not timed here): ``zplatform node`` cn and dn0 (100 Hz), two
``zplatform router`` processes (``r1`` connected to the CN, ``r2`` to
``r1``), and stations in this process (:class:`~zplatform.ground.link.GroundLink`
with an operator's signer; keys from one ``ZPLATFORM_KEY``).

* ``rtt_0``/``rtt_1``/``rtt_2``: a NOOP from a station reaching the vehicle
  through 0, 1 or 2 routers (``direct``: a peer of every node; ``pad``: a
  client of ``r1``; ``room``: a client of ``r2``), from submitting it to the
  verdict shown (a later telemetry snapshot echoing it and the CN's event
  naming the operator: what the operator sees), after a LOCK. ``raw_0``..
  ``raw_2``: a zenoh get on the CN's clock queryable (a run hello) from the
  same station session, the same path's bare round trip. ``ratio`` of each
  path: median command round trip over median raw round trip; ``added_ms``:
  their difference (the loop phase, at most one 10 ms period, plus the
  telemetry and event). Samples alternate command and get.
* ``fanout_direct_N``/``fanout_router_N``: the CN process's CPU (utime +
  stime from ``/proc``, per second of wall time) while ``N`` telemetry
  subscribers (zenoh sessions in this process) take every snapshot, either
  connected to the CN (peers) or clients of ``r1``. With a router the CN
  sends each snapshot once whatever ``N``.

Run it under ``flock /tmp/zplatform-bench.lock`` so benchmarks never overlap:
``flock /tmp/zplatform-bench.lock .venv/bin/python -m bench.stations``.
Blocks about a minute (``--quick``: about 20 s).
"""

from __future__ import annotations

import os
import secrets
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from zplatform.core.auth import KEY_ENV
from zplatform.ground.identity import station_signer
from zplatform.ground.link import GroundLink
from zplatform.mission.load import load_mission
from zplatform.runtime.clocksync import RunAsker
from zplatform.runtime.process import LOG_LEVEL_ENV
from zplatform.runtime.transport import open_session, zenoh_config

from .common import bench_argparser, free_port, spawn, summarize, terminate_all, write_result

BENCH = "stations"


def _mission(cn: int, dn: int, r1: int, r2: int) -> str:
    return f"""
mission: bench_stations
vehicle: rocket
loop_hz: 100
sync_timeout_ms: 2
security: {{transport: plain}}
transport: {{gossip_scouting: false, multicast_scouting: false}}
nodes:
  cn:  {{listen: ['tcp/127.0.0.1:{cn}']}}
  dn0: {{listen: ['tcp/127.0.0.1:{dn}'], connect: ['tcp/127.0.0.1:{cn}']}}
  gn:  {{connect: ['tcp/127.0.0.1:{cn}']}}
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
    IDLE: {{}}
ground:
  lease_s: 3600
  stations:
    - {{name: direct}}
    - {{name: pad, connect: ['tcp/127.0.0.1:{r1}']}}
    - {{name: room, connect: ['tcp/127.0.0.1:{r2}']}}
  operators:
    - {{name: fd, roles: [flight_director]}}
  routers:
    - {{name: r1, listen: ['tcp/127.0.0.1:{r1}'], connect: ['tcp/127.0.0.1:{cn}']}}
    - {{name: r2, listen: ['tcp/127.0.0.1:{r2}'], connect: ['tcp/127.0.0.1:{r1}']}}
"""


def _cpu_s(pid: int) -> float:
    """User plus system CPU seconds of process ``pid`` so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wait_ready(p: Any, what: str) -> None:
    """A router prints READY once its session is open."""
    assert p.stdout is not None
    line = p.stdout.readline().decode().strip()
    if line != "READY":
        raise RuntimeError(f"{what} did not start: {line!r}")


def _rtt(mission: Any, station: str, n: int) -> tuple[list[int], list[int]]:
    """``n`` command round trips and ``n`` raw gets from ``station`` (ns)."""
    link = GroundLink(mission, commands=True, signer=station_signer(mission, "fd", station))
    try:
        (lock,) = link.command("lock", timeout_s=60)
        if not lock.accepted:
            raise RuntimeError(f"LOCK from {station}: {lock.status} {lock.reason}")
        asker = RunAsker(link.link_keys)
        cmds: list[int] = []
        raws: list[int] = []
        for _ in range(n):
            t0 = time.monotonic_ns()
            (o,) = link.command("noop", timeout_s=30)
            cmds.append(time.monotonic_ns() - t0)
            if not o.accepted:
                raise RuntimeError(f"NOOP from {station}: {o.status} {o.reason}")
            t0 = time.monotonic_ns()
            got = [r for r in link.ns.session.get(link.keys.clock, payload=asker.hello()) if r.ok]
            raws.append(time.monotonic_ns() - t0)
            if not got:
                raise RuntimeError(f"no answer to a run hello from {station}")
        return cmds, raws
    finally:
        link.close()


def _fanout(
    mission: Any, cn_pid: int, via: list[str] | None, n: int, window_s: float
) -> dict[str, Any]:
    """The CN's CPU while ``n`` subscribers take telemetry (module doc)."""
    counts = [0] * n
    lock = threading.Lock()
    sessions: list[zenoh.Session] = []
    started = threading.Event()

    def counter(i: int) -> Any:
        def on(_s: zenoh.Sample) -> None:
            with lock:
                counts[i] += 1
            started.set()

        return on

    key = f"{mission.vehicle}/cn/telemetry"
    try:
        for i in range(n):
            cfg = zenoh_config(mission, None, via=via) if via else zenoh_config(mission, None)
            s = open_session(cfg)
            s.declare_subscriber(key, counter(i))
            sessions.append(s)
        # Every subscriber takes snapshots before the window opens.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                if all(counts):
                    break
            time.sleep(0.05)
        with lock:
            if not all(counts):
                raise RuntimeError(f"a subscriber never got telemetry: {counts}")
            before = list(counts)
        c0, t0 = _cpu_s(cn_pid), time.monotonic()
        time.sleep(window_s)
        c1, t1 = _cpu_s(cn_pid), time.monotonic()
        with lock:
            got = [a - b for a, b in zip(counts, before, strict=True)]
        return {
            "subscribers": n,
            "cn_cpu_pct": round(100 * (c1 - c0) / (t1 - t0), 2),
            "snapshots_per_subscriber": got,
            "window_s": round(t1 - t0, 2),
        }
    finally:
        for s in sessions:
            s.close()


def main(argv: list[str] | None = None) -> int:
    args = bench_argparser(__doc__ or "").parse_args(argv)
    n = 10 if args.quick else 100
    window = 3.0 if args.quick else 10.0
    os.environ.setdefault(KEY_ENV, secrets.token_hex(32))  # every process's keys, one master
    os.environ[LOG_LEVEL_ENV] = "WARNING"  # the nodes' per-command log lines, off
    tmp = Path(tempfile.mkdtemp(prefix="bench-stations-"))
    path = tmp / "mission.yaml"
    path.write_text(_mission(free_port(), free_port(), free_port(), free_port()))
    mission = load_mission(path, code=False)
    node = ["-m", "zplatform", "node", str(path)]
    procs = [spawn([*node, "dn0", "--no-realtime"])]
    cn = spawn([*node, "cn", "--ground-wait", "0", "--no-realtime", "--duration", "3600"])
    procs.append(cn)
    variants: dict[str, dict[str, Any]] = {}
    try:
        for name in ("r1", "r2"):
            p = subprocess.Popen(
                [sys.executable, "-m", "zplatform", "router", str(path), "--name", name],
                stdout=subprocess.PIPE,
                process_group=0,
            )
            procs.append(p)
            _wait_ready(p, f"router {name}")
        for hops, station in enumerate(("direct", "pad", "room")):
            cmds, raws = _rtt(mission, station, n)
            c, r = statistics.median(cmds), statistics.median(raws)
            variants[f"rtt_{hops}"] = {
                **summarize(cmds),
                "routers": hops,
                "ratio": round(c / r, 2),
                "added_ms": round((c - r) / 1e6, 2),
            }
            variants[f"raw_{hops}"] = {**summarize(raws), "routers": hops}
        assert mission.ground is not None
        r1 = list(mission.ground.routers[0].listen)
        for kind, via in (("direct", None), ("router", r1)):
            for subs in (1, 4):
                variants[f"fanout_{kind}_{subs}"] = _fanout(mission, cn.pid, via, subs, window)
    finally:
        terminate_all(procs)
    fan = {k: v["cn_cpu_pct"] for k, v in variants.items() if k.startswith("fanout")}
    params = {
        "loop_hz": 100,
        "commands_per_path": n,
        "fanout_window_s": window,
        "cn_cpu_4_over_1_direct": round(fan["fanout_direct_4"] / fan["fanout_direct_1"], 2),
        "cn_cpu_4_over_1_router": round(fan["fanout_router_4"] / fan["fanout_router_1"], 2),
    }
    write_result(BENCH, params, variants, args.json)
    for k, v in variants.items():
        if k.startswith("fanout"):
            got = v["snapshots_per_subscriber"]
            print(f"{k:<18} CN CPU {v['cn_cpu_pct']:6.2f} %  snapshots {got}")
        elif k.startswith("rtt"):
            print(f"{k:<18} ratio to raw {v['ratio']:.2f}, added {v['added_ms']:.2f} ms")
    print(
        f"CN CPU, 4 subscribers over 1: direct {params['cn_cpu_4_over_1_direct']}x, "
        f"through a router {params['cn_cpu_4_over_1_router']}x"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
