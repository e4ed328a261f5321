"""Where a sync's time goes: every hop of every DN exchange, stamped on one clock.

The CN (in this process) and each DN process stamp ``CLOCK_MONOTONIC`` (one
clock for every process on a host) at each hop of the exchange, per loop
and DN:

===========  ==========================================================
``issued``   CN loop thread, just before ``session.get`` for this DN (the
             wildcard query: for every DN)
``arrive``   DN, zenoh's thread: the query handed to the loop's queue
``serve``    DN loop thread: the query taken from the queue
``replied``  DN loop thread: ``query.reply`` returned
``back``     CN, zenoh's thread: the reply handed to the loop's queue
``taken``    CN loop thread: the reply taken from the queue
===========  ==========================================================

Reported per hop (the difference of consecutive stamps): p50/p99 over the
run, and the same over the loops whose sync missed its deadline, so a
lever can be aimed at the hop that costs the time. The stamps are taken
through the sync's public trace hook (:data:`zplatform.runtime.sync.SyncTrace`,
``ControlNode(sync_trace=...)``, ``DeviceNode(sync_trace=...)``), in the
traced processes only: the nodes run as shipped, and untraced nodes pay
nothing for the hook.

The mission is configs/led_test.yaml on free ports (``--ground`` adds its
ground node, as in ``bench.reliability``), or ``--bare N``: ``bench.sync``'s
mission with N DNs. Variants for levers: ``--lowlatency auto|true|false``
(the mission's ``transport.lowlatency``), ``--sync-query
auto|wildcard|per_node`` (``transport.sync_query``), ``--pin cn=0,dn=1``
(nodes' ``cpu``), ``--zenoh-priority P`` (every thread of the CN and DNs but
the loop thread at SCHED_FIFO P, the loop threads at the mission's 20),
``--env K=V`` (set in this process
before its first session, and inherited by every child: ``ZENOH_RUNTIME``
and the like).

Run ``python -m bench.sync_trace [--quick] [--seconds S] [--ground] ...``.
Blocks about ``--seconds`` (default 30, ``--quick`` 5) plus start-up.
"""

from __future__ import annotations

import atexit
import itertools
import json
import os
import queue
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from bench.common import bench_argparser, summarize
from bench.common import write_result as _write

LOWLATENCY_ARG: dict[str, bool | str] = {"auto": "auto", "true": True, "false": False}
HOPS = ["issued", "arrive", "serve", "replied", "back", "taken"]
_MAX = 1 << 17  # loops traced per process (a 20 min run at 100 Hz)


class _Stamps:
    """Preallocated per-loop stamps for one node; ``dump`` writes them as JSON."""

    def __init__(self, width: int) -> None:
        self.t: npt.NDArray[np.int64] = np.zeros((_MAX, width), np.int64)

    def set(self, loop: int, col: int, ns: int) -> None:
        if 0 < loop < _MAX:
            self.t[loop, col] = ns

    def dump(self, path: str) -> None:
        rows = np.nonzero(self.t.any(axis=1))[0]
        Path(path).write_text(json.dumps({"loops": rows.tolist(), "t": self.t[rows].tolist()}))


_PRIO_ENV = "ZP_TRACE_ZENOH_PRIORITY"


def _split_priorities() -> None:
    """With ``ZP_TRACE_ZENOH_PRIORITY=P``: when a node promotes its threads to
    SCHED_FIFO, every thread but the calling (loop) thread gets P instead
    (:func:`zplatform.runtime.process.split_thread_priorities`)."""
    p = os.environ.get(_PRIO_ENV)
    if not p:
        return
    from zplatform.runtime.process import split_thread_priorities

    split_thread_priorities(int(p))


def dn_main(argv: list[str]) -> None:
    """``dn <mission> <name> <out.json> [--no-realtime]``: a DN process
    (``zplatform node MISSION NAME``'s) with its hops stamped."""
    from zplatform.core.auth import load_keys
    from zplatform.mission.load import load_mission
    from zplatform.node.device import DeviceNode
    from zplatform.runtime.process import StopFlag, setup_logging

    _split_priorities()

    mission_path, name, out, *extra = argv
    if set(extra) - {"--no-realtime"}:
        raise SystemExit(f"sync_trace dn: unknown options {extra}")
    st = _Stamps(3)  # arrive, serve, replied
    atexit.register(st.dump, out)
    arrivals: queue.SimpleQueue[int] = queue.SimpleQueue()
    mono = time.monotonic_ns
    served = [0, 0]  # this query's arrive and serve stamps

    def trace(hop: str, loop: int) -> None:
        t = mono()
        if hop == "arrive":  # zenoh's thread: queries are served in this order
            arrivals.put(t)
        elif hop == "serve":
            served[0] = arrivals.get_nowait()
            served[1] = t
        else:  # "replied", with the loop the query carried
            st.set(loop, 0, served[0])
            st.set(loop, 1, served[1])
            st.set(loop, 2, t)

    setup_logging()
    mission = load_mission(mission_path)
    node = DeviceNode(
        mission, name, stop=StopFlag(), keys=load_keys(mission, name), sync_trace=trace
    )
    try:
        node.start()
        node.run(realtime="--no-realtime" not in extra)
    finally:
        node.close()
        st.dump(out)


class _CnTrace:
    """The in-process CN's :data:`~zplatform.runtime.sync.SyncTrace`: issued, back,
    taken per DN and loop. ``logic`` is set once the node is built (stamps
    of loop 0, the warm-up, are not kept)."""

    def __init__(self, n_dn: int) -> None:
        self.st = _Stamps(3 * n_dn)
        self.logic: Any = None
        self._back = [0] * n_dn  # zenoh's thread: the newest reply's hand-off per DN
        self._mono = time.monotonic_ns

    def __call__(self, hop: str, i: int) -> None:
        t = self._mono()
        if hop == "back":
            self._back[i] = t
            return
        logic = self.logic
        if logic is None:
            return
        loop = int(logic.loop)
        if hop == "issued":
            self.st.set(loop, 3 * i, t)
        else:  # "taken"
            self.st.set(loop, 3 * i + 1, self._back[i])
            self.st.set(loop, 3 * i + 2, t)


def _hops(
    cn: dict[int, list[int]], dns: list[dict[int, list[int]]], misses: set[int]
) -> dict[str, dict[str, Any]]:
    """Per-hop durations (us) over all loops, and over the missed ones."""
    names = [f"{a}->{b}" for a, b in itertools.pairwise(HOPS)] + ["sync_total"]
    per: dict[str, list[float]] = {n: [] for n in names}
    per_miss: dict[str, list[float]] = {n: [] for n in names}
    for loop, row in cn.items():
        for i, dn in enumerate(dns):
            d = dn.get(loop)
            issued, back, taken = row[3 * i : 3 * i + 3]
            if d is None or not (issued and back and taken and all(d)):
                continue
            t = [issued, d[0], d[1], d[2], back, taken]
            vals = [(b - a) / 1e3 for a, b in itertools.pairwise(t)] + [(taken - issued) / 1e3]
            for n, v in zip(names, vals, strict=True):
                per[n].append(v)
                if loop in misses:
                    per_miss[n].append(v)
    out: dict[str, dict[str, Any]] = {}
    for n in names:
        a = np.array(per[n]) if per[n] else np.zeros(0)
        m = np.array(per_miss[n]) if per_miss[n] else np.zeros(0)
        out[n] = {
            "p50_us": round(float(np.median(a)), 1) if a.size else None,
            "p99_us": round(float(np.percentile(a, 99)), 1) if a.size else None,
            "max_us": round(float(a.max()), 1) if a.size else None,
            "missed_loops_p50_us": round(float(np.median(m)), 1) if m.size else None,
            "n": int(a.size),
        }
    return out


def run(
    seconds: float,
    *,
    ground: bool,
    bare: int | None,
    lowlatency: bool | str,
    sync_query: str | None = None,
    pin: str = "",
    priority: int = 20,
    env: dict[str, str],
) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    from bench.cluster import BenchCluster, SyncSamples, make_mission
    from bench.reliability import _finish_child, _spawn_child, _wait_ready, led_mission
    from bench.sync import PRIORITY

    os.environ.update(env)
    _split_priorities()
    with tempfile.TemporaryDirectory(prefix="zp-trace-") as tmp:
        tmpdir = Path(tmp)
        if bare:
            mpath = make_mission(
                tmpdir / "m.yaml",
                n_dn=bare,
                lowlatency=lowlatency,
                sync_query=sync_query,
                priority=PRIORITY,
            )
        else:
            mpath = led_mission(tmpdir / "m.yaml", lowlatency=lowlatency, sync_query=sync_query)
        if pin:  # "cn=0,dn=1": the node (or every dnX for "dn") on that CPU
            doc = yaml.safe_load(mpath.read_text())
            for item in pin.split(","):
                who, cpu = item.split("=")
                for name, spec in doc["nodes"].items():
                    if name == who or (who == "dn" and name.startswith("dn")):
                        spec["cpu"] = int(cpu)
            mpath.write_text(yaml.safe_dump(doc, sort_keys=False))
        n_dn = sum(1 for n in yaml.safe_load(mpath.read_text())["nodes"] if n.startswith("dn"))
        tracer = _CnTrace(n_dn)
        with BenchCluster(mpath, realtime=priority > 0, trace_dir=tmpdir, cn_trace=tracer) as c:
            m = c.mission
            tracer.logic = c.cn.logic
            st = tracer.st
            gpath = tmpdir / "gn.json"
            gn = _spawn_child(["ground", str(mpath), str(gpath)]) if ground else None
            try:
                c.start(timeout_s=60.0)
                if gn is not None:
                    _wait_ready(gn, "ground node")
                loops = max(1, round(seconds * m.loop_hz))
                samples = SyncSamples(loops)
                c.run(loops, samples)
            finally:
                if gn is not None:
                    _finish_child(gn, gpath)
        dn_rows = []
        for dn in m.device_nodes:
            doc = json.loads((tmpdir / f"{dn}.trace.json").read_text())
            dn_rows.append({int(k): v for k, v in zip(doc["loops"], doc["t"], strict=True)})
        rows = np.nonzero(st.t.any(axis=1))[0]
        cn_rows = {int(r): st.t[r].tolist() for r in rows}
    n = samples.count
    dur = samples.duration_ns[:n]
    missed_idx = np.nonzero((dur >= m.sync_timeout_ns) | (samples.replied[:n] < n_dn))[0]
    first = min(cn_rows) if cn_rows else 0
    misses = {first + int(k) for k in missed_idx}
    params: dict[str, Any] = {
        "mission": f"bench.sync bare, {bare} DNs" if bare else "configs/led_test.yaml",
        "ground": ground,
        "lowlatency": lowlatency,
        "sync_query": sync_query,
        "wildcard": c.cn.sync.wildcard,
        "pin": pin,
        "zenoh_thread_priority": os.environ.get(_PRIO_ENV),
        "env": env,
        "seconds": seconds,
        "loops": n,
        "missed_loops": len(misses),
        "clock": "CLOCK_MONOTONIC in every process (one host)",
    }
    variant = summarize(dur.tolist(), deadline_ns=m.sync_timeout_ns)
    variant["hops"] = _hops(cn_rows, dn_rows, misses)
    return params, {"trace": variant}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args_list = sys.argv[1:] if argv is None else argv
    if args_list[:1] == ["dn"]:
        dn_main(args_list[1:])
        return {}
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "sync_trace")
    parser.add_argument("--seconds", type=float, default=None)
    parser.add_argument("--ground", action="store_true")
    parser.add_argument("--bare", type=int, default=None)
    parser.add_argument("--lowlatency", choices=["auto", "true", "false"], default="false")
    parser.add_argument(
        "--sync-query",
        choices=["auto", "wildcard", "per_node"],
        default=None,
        help="transport.sync_query (default: the mission's own)",
    )
    parser.add_argument("--pin", default="", help="CPU per node: cn=0,dn=1 (dn: every DN)")
    parser.add_argument("--priority", type=int, default=None, help="SCHED_FIFO (0: off)")
    parser.add_argument(
        "--zenoh-priority",
        type=int,
        default=None,
        help="SCHED_FIFO priority of every thread but the loop thread (nodes' own is 20)",
    )
    parser.add_argument("--env", action="append", default=[])
    args = parser.parse_args(args_list)
    seconds = args.seconds if args.seconds is not None else (5.0 if args.quick else 30.0)
    env = dict(kv.split("=", 1) for kv in args.env)
    if args.zenoh_priority is not None:
        env[_PRIO_ENV] = str(args.zenoh_priority)
    from bench.sync import PRIORITY, inherit_fifo

    prio = PRIORITY if args.priority is None else args.priority
    sched = inherit_fifo(prio)
    params, variants = run(
        seconds,
        ground=args.ground,
        bare=args.bare,
        lowlatency=LOWLATENCY_ARG[args.lowlatency],
        sync_query=args.sync_query,
        pin=args.pin,
        priority=prio,
        env=env,
    )
    params["scheduling"] = sched
    params["quick"] = bool(args.quick)
    doc = _write("sync_trace", params, variants, args.json)
    v = variants["trace"]
    print(f"sync p50 {v['p50_us']} us p99 {v['p99_us']} us, missed loops {params['missed_loops']}")
    for hop, h in v["hops"].items():
        print(
            f"  {hop:18s} p50 {h['p50_us']!s:>8} p99 {h['p99_us']!s:>8} max {h['max_us']!s:>8}"
            f"  (missed loops p50 {h['missed_loops_p50_us']})"
        )
    return doc


if __name__ == "__main__":
    main()
