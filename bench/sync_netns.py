"""The sync step across network namespaces (one "host" per node) beside loopback.

``bench.sync`` runs every node on 127.0.0.1. Here the same cluster (3 DNs,
256 B regions, 100 Hz, 2 ms deadline, auth on, SCHED_FIFO 20 from the
mission) runs twice in one invocation:

* ``zplatform_3dn_loopback``: every node in the root namespace, on loopback;
* ``zplatform_3dn_netns``: each node in its own network namespace, joined
  by veth pairs on a bridge (:class:`tests.faults.netns.NetnsLab`), so every
  frame crosses a real (virtual) Ethernet link and the kernel's bridge, and
  zenoh's shared-memory shortcut between same-host peers cannot apply.

In both, the CN is a child process (``python -m bench.sync_netns cn ...``,
inside the CN's namespace for ``netns``) running the real
:meth:`ControlNode.run` with a hook that records each loop's
``ControlSync.duration_ns``; a missed loop counts as the deadline, as in
:mod:`bench.sync`. Figures: ``p50_us``, ``p99_us``, ``max_us``,
``deadline_miss_rate``, ``msgs``, plus ``missed``/``late`` per the CN and
``ratio_netns_vs_loopback`` (p50) in params.

Needs root and iproute2 (``ip netns``); elsewhere it writes a result whose
``params.skipped`` says why. Blocks for about 2 × (``--seconds`` + start-up).
Run ``python -m bench.sync_netns [--quick] [--json PATH]``.
"""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bench.cluster import make_mission
from bench.common import REPO_ROOT, bench_argparser, summarize, terminate_all, write_result

PORT = 7447
N_DN = 3
RATE_HZ = 100.0
DEADLINE_MS = 2.0
REGION_BYTES = 256


def cn_main(argv: list[str]) -> None:
    """``cn <mission> <loops> <out.json>``: the CN's real loop; per-loop sync figures to JSON."""
    from zplatform.core.auth import load_keys
    from zplatform.mission.load import load_mission
    from zplatform.node.control import ControlNode
    from zplatform.runtime.process import StopFlag

    path, loops, out = argv[0], int(argv[1]), argv[2]
    m = load_mission(path)
    cn = ControlNode(m, stop=StopFlag(install=False), keys=load_keys(m, "cn"))
    try:
        cn.wait_ready(120.0, ground_wait_s=0)
        dur = np.zeros(loops, np.int64)
        replied = np.zeros(loops, np.int64)
        n = [0]
        step = cn.step

        def hooked(k: int, dl: int) -> bool:
            go = step(k, dl)
            i = n[0]
            if i < loops:
                dur[i] = cn.sync.duration_ns
                replied[i] = len(cn.logic.dns) - cn.logic.pending
                n[0] = i + 1
            return go

        cn.step = hooked  # type: ignore[method-assign,assignment]
        cn.run(max_loops=loops, realtime=True)
        s = cn.summary()
        got = n[0]
        deadline = m.sync_timeout_ns
        ok = (replied[:got] == len(m.device_nodes)) & (dur[:got] < deadline)
        fig = summarize(np.where(ok, dur[:got], deadline).tolist(), deadline)
        fig["max_raw_us"] = round(float(dur[:got].max()) / 1e3, 2) if got else None
        fig["missed"] = int(sum(s.missed.values()))
        fig["late"] = int(sum(s.late.values()))
        fig["loop_overruns"] = int(s.loop_overruns)
        fig["rate_hz_measured"] = round(float(s.rate_hz), 2)
        Path(out).write_text(json.dumps(fig))
    finally:
        cn.close()


def _mission(path: Path, cn_addr: str, dn_addrs: list[str]) -> Path:
    make_mission(
        path,
        n_dn=N_DN,
        loop_hz=RATE_HZ,
        sync_timeout_ms=DEADLINE_MS,
        region_bytes=REGION_BYTES,
        priority=20,
    )
    doc = yaml.safe_load(path.read_text())
    cn_ep = f"tcp/{cn_addr}:{PORT}"
    doc["nodes"]["cn"]["listen"] = [cn_ep]
    for i, a in enumerate(dn_addrs):
        doc["nodes"][f"dn{i}"]["listen"] = [f"tcp/{a}:{PORT + 1 + i}"]
        doc["nodes"][f"dn{i}"]["connect"] = [cn_ep]
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _run(
    tmp: Path, name: str, loops: int, prefixes: list[list[str]], addrs: list[str]
) -> dict[str, Any]:
    """Run the cluster with node ``i`` started under ``prefixes[i]`` (``ip netns exec ...``)."""
    mpath = _mission(tmp / f"{name}.yaml", addrs[0], addrs[1:])
    out = tmp / f"{name}.json"
    procs: list[subprocess.Popen[bytes]] = []
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    try:
        for i in range(N_DN):
            with open(tmp / f"{name}.dn{i}.log", "ab") as log:
                procs.append(
                    subprocess.Popen(
                        [
                            *prefixes[i + 1],
                            sys.executable,
                            "-m",
                            "zplatform",
                            "node",
                            str(mpath),
                            f"dn{i}",
                        ],
                        stdout=log,
                        stderr=subprocess.STDOUT,
                        cwd=REPO_ROOT,
                        env=env,
                        start_new_session=True,
                    )
                )
        with open(tmp / f"{name}.cn.log", "ab") as log:
            cn = subprocess.Popen(
                [
                    *prefixes[0],
                    sys.executable,
                    "-m",
                    "bench.sync_netns",
                    "cn",
                    str(mpath),
                    str(loops),
                    str(out),
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=REPO_ROOT,
                env=env,
                start_new_session=True,
            )
        procs.append(cn)
        cn.wait(timeout=loops / RATE_HZ + 180)
    finally:
        terminate_all(procs)
    if not out.exists():
        logs = "".join(
            f"--- {p.name}\n{p.read_text(errors='replace')[-1500:]}"
            for p in sorted(tmp.glob(f"{name}.*.log"))
        )
        raise RuntimeError(f"{name}: the CN wrote no result\n{logs}")
    fig: dict[str, Any] = json.loads(out.read_text())
    return fig


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args_list = sys.argv[1:] if argv is None else argv
    if args_list[:1] == ["cn"]:
        cn_main(args_list[1:])
        return {}
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "sync_netns")
    parser.add_argument("--seconds", type=float, default=None)
    args = parser.parse_args(args_list)
    os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
    seconds = args.seconds or (10.0 if args.quick else 30.0)
    loops = round(seconds * RATE_HZ)
    params: dict[str, Any] = {
        "rate_hz": RATE_HZ,
        "deadline_us": DEADLINE_MS * 1e3,
        "region_bytes": REGION_BYTES,
        "n_dn": N_DN,
        "seconds": seconds,
        "quick": bool(args.quick),
        "auth": "on",
        "scheduling": "SCHED_FIFO 20 (mission priority) in every node",
    }
    variants: dict[str, dict[str, Any]] = {}
    sys.path.insert(0, str(REPO_ROOT))
    from tests.faults.netns import NetnsLab, netns_unavailable

    why = netns_unavailable()
    with tempfile.TemporaryDirectory(prefix="zp-netns-") as t:
        tmp = Path(t)
        print(f"running zplatform_3dn_loopback ({seconds:.0f} s) ...", flush=True)
        variants["zplatform_3dn_loopback"] = _run(
            tmp, "loopback", loops, [[] for _ in range(N_DN + 1)], ["127.0.0.1"] * (N_DN + 1)
        )
        if why is None:
            print(f"running zplatform_3dn_netns ({seconds:.0f} s) ...", flush=True)
            with NetnsLab(N_DN + 1) as lab:
                variants["zplatform_3dn_netns"] = _run(
                    tmp,
                    "netns",
                    loops,
                    [["ip", "netns", "exec", h.ns] for h in lab.hosts],
                    [h.addr for h in lab.hosts],
                )
            params["topology"] = "one namespace per node, veth pairs on a bridge (10.77.0.0/24)"
        else:
            params["skipped"] = f"netns variant skipped: {why}"
    lo = variants["zplatform_3dn_loopback"].get("p50_us")
    ns = variants.get("zplatform_3dn_netns", {}).get("p50_us")
    params["ratio_netns_vs_loopback_p50"] = round(ns / lo, 3) if ns and lo else None
    return write_result("sync_netns", params, variants, args.json)


if __name__ == "__main__":
    main()
