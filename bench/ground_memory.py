"""The ground node's memory under peers that flood it and leave.

A ground node (a :class:`~zplatform.ground.link.GroundLink` as ``gn`` of
``configs/minimal.yaml``, free ports, plain TCP: what a keyless peer
reaches) runs in a process of its own. Each cycle, a keyless attacker
peer (a zenoh session of this process, connected to the ground's listen
endpoint only, scouting off) floods ``{vehicle}/dn0/events`` with junk
(half random sizes up to 2,000 bytes, half ``EVENT_MAX``, 4,096 bytes: over
zenoh's 3 KiB shared-memory threshold, as the fault suite's event rows) at ``--rate`` puts a
second for ``--flood-s`` seconds, congestion control BLOCK (every frame
reaches the ground, as in ``tests/faults/keyfloods.py``), and closes its
session; once the ground's session no longer lists the attacker (no sleep:
polled), the ground reports its RSS (``/proc/self/status`` ``VmRSS``).

Variants: ``as_is`` (the ground as ``zenoh_config`` builds it: no shared
memory for the ground node), ``ground_shm`` (the same with zenoh's shared
memory on, as the ground had it before: a raw zenoh session on the ground's
config with a subscriber on the event keys; zenoh maps each same-host peer's 16 MiB pool the
first time that peer sends a payload over 3 KiB, and keeps it mapped after
the peer has gone). ``dn0_queries``: the victim a device node's session
instead (dn0's config as ``zenoh_config`` builds it: shared memory only
where it helps), a queryable on its sync key, the junk in gets: what the
vehicle's nodes pay (``refused``: the queries it took); ``dn0_queries_shm``
the same on a raw session with shared memory on (dn0 before).
``archive``: no flood; the ground node's archive writer
(:class:`~zplatform.archive.ArchiveWriter`, the flight mission's 190-element
vector, in a temporary directory) fed one row group of snapshots (60 s of
them at 100 Hz, ``archive.row_group_s``) per cycle: the growth the flight soak
saw "during a flood", about a minute into every flight, whichever flood
ran then (issue 25; before the fix +33 MB at the first row group, the
allocators keeping what the writes freed). ``rss_mb[0]`` is
taken once the writer's thread has warmed up (the ground's start).
``--process``: the fault suite's attacker (``tests/faults/attacker.py``
``key-put``, a tool's config of the mission) in a process of its own each
cycle, instead of a session of this process.

``python -m bench.ground_memory [--quick] [--cycles N] [--process] [--json PATH]``
(default ``bench/results/ground_memory.json``; ``--quick``, 4 cycles, to the
temporary directory): JSON per
variant: ``rss_mb`` (after start, then after each cycle), ``growth_mb``
(last minus first), ``per_cycle_mb`` (the mean step over the last half of
the cycles), ``sent`` (frames of each flood) and ``refused`` (events the
ground counted as bad).
"""

from __future__ import annotations

import itertools
import json
import os
import random
import secrets
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from bench.common import REPO_ROOT, Child, bench_argparser, next_command, say
from zplatform.ground.link import EVENT_MAX

VARIANTS = (
    "as_is",
    "ground_shm",
    "dn0_queries",
    "dn0_queries_shm",
    "archive",
)


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _mission(tmp: Path) -> Path:
    from zplatform.runtime.transport import rewrite_endpoints

    path = tmp / "minimal.yaml"
    rewrite_endpoints(REPO_ROOT / "configs" / "minimal.yaml", path)
    raw = yaml.safe_load(path.read_text())
    raw.setdefault("security", {})["transport"] = "plain"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def child(mission_path: str, variant: str) -> None:
    """The ground node (module doc); answers ``rss`` (its RSS and counters),
    ``peers`` (the zenoh ids of its peers) and ``quit``."""

    from zplatform.ground.link import GroundLink
    from zplatform.mission.load import load_mission

    m = load_mission(mission_path)
    if variant.startswith("archive"):
        _archive_child(variant)
        return
    if variant in ("ground_shm", "dn0_queries", "dn0_queries_shm"):
        _raw_child(m, variant)
        return
    link = GroundLink(m, node="gn")
    say({"ready": True, "rss_mb": _rss_mb()})
    while True:
        cmd = next_command()
        if cmd["cmd"] == "quit":
            break
        link.next(0.0)  # take what the flood left (refusals counted)
        if cmd["cmd"] == "peers":
            say({"peers": [str(z) for z in link.ns.session.info.peers_zid()]})
        elif cmd["cmd"] == "rss":
            say({"rss_mb": _rss_mb(), "refused": link.logic.counters.bad_events})
    link.close()


def _raw_child(m: Any, variant: str) -> None:
    """A victim that only counts what it takes (protocol as :func:`child`):
    ``dn0_queries``, dn0's session as ``zenoh_config`` builds it with a
    queryable on its sync key that answers nothing; the baselines with
    shared memory forced on (what the nodes had before): ``dn0_queries_shm``
    the same, ``ground_shm`` the ground node's config with a subscriber on
    the event keys."""
    import zenoh

    from zplatform.runtime.transport import open_session, zenoh_config

    node = "gn" if variant == "ground_shm" else "dn0"
    cfg = zenoh_config(m, node)
    if variant.endswith("_shm"):
        cfg.insert_json5("transport/shared_memory/enabled", "true")
    s = open_session(cfg)
    taken = [0]

    def on_frame(_: object) -> None:  # hand off only: counted, never answered
        taken[0] += 1

    handler = zenoh.handlers.Callback(on_frame, indirect=False)
    if node == "gn":
        decl: Any = s.declare_subscriber(f"{m.vehicle}/*/events", handler)
    else:
        decl = s.declare_queryable(f"{m.vehicle}/dn0/to_cn", handler)
    say({"ready": True, "rss_mb": _rss_mb()})
    while (cmd := next_command())["cmd"] != "quit":
        if cmd["cmd"] == "peers":
            say({"peers": [str(z) for z in s.info.peers_zid()]})
        elif cmd["cmd"] == "rss":
            say({"rss_mb": _rss_mb(), "refused": taken[0]})
    decl.undeclare()
    s.close()


def _archive_child(variant: str) -> None:
    """The ground's archive writer alone (module doc): ``cycle`` feeds it
    one row group of snapshots of the flight mission and waits until its
    thread took them; ``rss`` reports; ``quit``."""
    import tempfile

    from zplatform.archive import ArchiveWriter
    from zplatform.core.datavector import DataVector, Layout
    from zplatform.mission.load import load_mission

    m = load_mission(REPO_ROOT / "configs" / "flight.yaml")
    layout = Layout.for_node(m, "cn")
    dv = DataVector(layout)
    with tempfile.TemporaryDirectory(prefix="zplatform-bench-archive-") as root:
        w = ArchiveWriter(m, layout, root)
        group = w.sizing.row_group_rows
        t0, loop = time.time_ns(), 0
        deadline = time.monotonic() + 30.0
        while not w.releases and time.monotonic() < deadline:  # its warm-up: the ground's start
            time.sleep(0.01)
        say({"ready": True, "rss_mb": _rss_mb()})
        while (cmd := next_command())["cmd"] != "quit":
            if cmd["cmd"] == "cycle":
                for _ in range(group):
                    loop += 1
                    dv.set("cn_epoch", 1)
                    dv.set("cn_loop", loop)
                    dv.set("cn_time_ns", t0 + loop * m.period_ns)
                    w.snapshot(t0 + loop * m.period_ns, dv)
                    if loop % 500 == 0:
                        w.flush(60)  # within the hand-off ring's room
                w.flush(60)
                say({"rows": w.rows})
            elif cmd["cmd"] == "rss":
                say({"rss_mb": _rss_mb(), "refused": 0, "releases": w.releases})
        w.close()


def _flood_gets(mission: Path, ep: str, key: str, rate: float, seconds: float) -> int:
    """As :func:`_flood`, with gets (queries) carrying the junk."""
    import zenoh

    from zplatform.runtime.transport import is_matching

    cfg = zenoh.Config()
    cfg.insert_json5("connect/endpoints", json.dumps([ep]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    s = zenoh.open(cfg)
    try:
        querier = s.declare_querier(key, timeout=0.05)
        deadline = time.monotonic() + 10.0
        while not is_matching(querier):  # the node's queryable reached us
            if time.monotonic() > deadline:
                raise RuntimeError(f"the node's queryable never matched on {ep}")
            time.sleep(0.01)
        rng = random.Random(7)
        junk = rng.randbytes(EVENT_MAX)
        noop: zenoh.handlers.Callback[zenoh.Reply] = zenoh.handlers.Callback(
            lambda _r: None, indirect=False
        )
        sent = 0
        t0 = time.monotonic()
        while (now := time.monotonic()) - t0 < seconds:
            while sent < int((now - t0) * rate):
                n = EVENT_MAX if sent % 2 else rng.randrange(0, 2000)
                querier.get(noop, payload=junk[:n])
                sent += 1
            time.sleep(0.001)  # pacing
        querier.undeclare()
        return sent
    finally:
        s.close()


def _flood(mission: Path, ep: str, key: str, rate: float, seconds: float) -> int:
    """One attacker session of this process: connect to ``ep``, flood
    ``key``, close. Returns the frames sent."""
    import zenoh

    from zplatform.runtime.transport import is_matching

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("connect/endpoints", json.dumps([ep]))
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    s = zenoh.open(cfg)
    try:
        pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10.0
        while not is_matching(pub):  # the ground's subscriber reached us
            if time.monotonic() > deadline:
                raise RuntimeError(f"the ground's event subscriber never matched on {ep}")
            time.sleep(0.01)
        rng = random.Random(7)
        junk = rng.randbytes(EVENT_MAX)
        sent = 0
        t0 = time.monotonic()
        while (now := time.monotonic()) - t0 < seconds:
            due = int((now - t0) * rate)
            while sent < due:
                n = EVENT_MAX if sent % 2 else rng.randrange(0, 2000)
                pub.put(junk[:n])
                sent += 1
            time.sleep(0.001)  # pacing
        pub.undeclare()
        return sent
    finally:
        s.close()


def _flood_process(mission: Path, ep: str, key: str, rate: float, seconds: float) -> int:
    """The fault suite's attacker (``tests/faults/attacker.py``, ``key-put``,
    a tool's config of the mission) in a process of its own, connected to
    ``ep`` only. Returns the frames sent."""
    import subprocess

    env = {k: v for k, v in os.environ.items() if not k.startswith("ZPLATFORM_KEY")}
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tests.faults.attacker",
            str(mission),
            "key-put",
            "--key",
            key,
            "--size",
            str(EVENT_MAX),
            "--rate",
            str(rate),
            "--duration",
            str(seconds),
            "--connect",
            ep,
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
        env=env,
    )
    assert p.stdin is not None and p.stdout is not None
    line = p.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"attacker: {line!r}")
    p.stdin.write("go\n")
    p.stdin.flush()
    res = json.loads(p.stdout.readline())
    p.wait(30)
    return int(res["sent"])


def run_variant(
    mission: Path, variant: str, cycles: int, rate: float, flood_s: float, process: bool = False
) -> dict[str, Any]:
    raw = yaml.safe_load(mission.read_text())
    vehicle = raw.get("vehicle", "rocket")
    if variant.startswith("dn0_queries"):
        ep, key = raw["nodes"]["dn0"]["listen"][0], f"{vehicle}/dn0/to_cn"
    else:
        ep, key = raw["nodes"]["gn"]["listen"][0], f"{vehicle}/dn0/events"
    gn = Child("bench.ground_memory", ["--child", str(mission), variant], mission.read_text())
    try:
        first = gn.read()
        assert first.get("ready"), first
        gn.send({"cmd": "rss"})
        rss = [gn.read()["rss_mb"]]
        sent: list[int] = []
        refused = 0
        if variant.startswith("archive"):
            for _ in range(cycles):
                gn.send({"cmd": "cycle"})
                sent.append(int(gn.read()["rows"]))
                gn.send({"cmd": "rss"})
                rss.append(gn.read()["rss_mb"])
        for _ in range(0 if variant.startswith("archive") else cycles):
            flood = _flood_process if process else _flood
            if variant.startswith("dn0_queries"):
                flood = _flood_gets
            n = flood(mission, ep, key, rate, flood_s)
            sent.append(n)
            deadline = time.monotonic() + 30.0
            while True:  # until the ground's session with the attacker is gone
                gn.send({"cmd": "peers"})
                if not gn.read()["peers"]:  # the bench's ground has no other peer
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError("the ground kept the attacker's session for 30 s")
                time.sleep(0.05)
            gn.send({"cmd": "rss"})
            got = gn.read()
            rss.append(got["rss_mb"])
            refused = got["refused"]
    finally:
        gn.close()
    half = rss[len(rss) // 2 :]
    steps = [b - a for a, b in itertools.pairwise(half)]
    return {
        "rss_mb": [round(x, 1) for x in rss],
        "growth_mb": round(rss[-1] - rss[0], 1),
        "per_cycle_mb": round(sum(steps) / len(steps), 2) if steps else None,
        "sent": sent,
        "refused": refused,
    }


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3])
        return
    p = bench_argparser(__doc__.splitlines()[0] if __doc__ else "")
    p.add_argument("--cycles", type=int, default=8)
    p.add_argument("--rate", type=float, default=6000.0, help="puts per second")
    p.add_argument("--flood-s", type=float, default=2.0)
    p.add_argument(
        "--process", action="store_true", help="the fault suite's attacker, a process each cycle"
    )
    p.add_argument("--variant", action="append", default=None, help=", ".join(VARIANTS))
    a = p.parse_args()
    cycles = 4 if a.quick else a.cycles
    os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
    names = list(a.variant or VARIANTS)
    out: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        mission = _mission(Path(tmp))
        for name in names:
            out[name] = run_variant(mission, name, cycles, a.rate, a.flood_s, a.process)
            print(name, json.dumps(out[name]), flush=True)
    params = {"cycles": cycles, "rate": a.rate, "flood_s": a.flood_s, "process": a.process}
    from bench.common import machine_info

    doc = {"bench": "ground_memory", "machine": machine_info(), "params": params, "variants": out}
    # A --quick try-out never overwrites the committed figures.
    if a.json:
        path = Path(a.json)
    elif a.quick:
        path = Path(tempfile.gettempdir()) / "zplatform-bench" / "ground_memory-quick.json"
    else:
        path = REPO_ROOT / "bench" / "results" / "ground_memory.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    print(f"ground_memory -> {path}")


if __name__ == "__main__":
    main()
