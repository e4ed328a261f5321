"""Telemetry latency (thesis R8, <= 30 ms): CN put to ground decode, small and large missions.

For each mission, a zplatform cluster (DN processes, the CN's real loop in
this process, auth on) plus a ground child (``python -m bench.reliability
ground``: the platform's ``GroundLink`` as node ``gn``). The
latency of each snapshot is the ground's node clock at decode, plus its
clock-sync offset to the CN (measured against the CN's clock server at
start, as a DN does), minus the CN's node clock read just before its
``put`` (the ``tm.put`` trace point, :mod:`zplatform.trace`): the figure
holds across hosts. ``same_host_*`` is the same on
``CLOCK_MONOTONIC`` (one host only), a check of the clock-sync term.

Missions (variants): ``led_test`` (configs/led_test.yaml), ``thesis_200``
(configs/thesis_200.yaml: 100 sensors + 100 actuators) and generated
``elements_<N>_3dn`` missions (mixed-type elements as in
:mod:`bench.bandwidth`; 10k, and 100k without ``--quick``), all at 100 Hz
with every snapshot sent. Figures: ``p50_us``, ``p99_us``, ``max_us``,
``msgs`` (snapshots decoded), ``tm_bytes`` (one snapshot as sent),
``lost`` (snapshots never decoded), ``deadline_miss_rate`` (lost or over 30 ms).
Target: p99 < 2 ms (``params.targets``).

``--intra-host iox|zenoh|both`` runs each mission with its telemetry to the
(same-host) ground over iceoryx2 (``transport.intra_host: auto``: zenoh
still carries every frame, the ground takes each once, by the path that
brought it first) and/or over zenoh alone (``zenoh``), as variants
``<mission>_iox`` / ``<mission>_zenoh``; the default (``mission``) runs each
mission as it is written. ``tm_iox``: snapshots the ground took over
iceoryx2, ``tm_duplicates``: copies it dropped (the other path's).

Blocks ``--seconds`` per mission and path (quick 5, full 30) plus start-up.
Run ``python -m bench.telemetry_latency [--quick] [--intra-host both] [--json PATH]``.
"""

from __future__ import annotations

import os
import secrets
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bench.bandwidth import element_extra
from bench.cluster import BenchCluster, make_mission
from bench.common import (
    REPO_ROOT,
    TmPutStamps,
    bench_argparser,
    free_port,
    summarize,
    write_result,
)
from bench.reliability import _finish_child, _spawn_child, _wait_ready
from bench.sync import PRIORITY, inherit_fifo
from zplatform import trace
from zplatform.config import relocate_mission

TM_DEADLINE_MS = 30.0
TARGET_P99_US = 2000.0


#: ``--intra-host`` choices: the ``transport.intra_host`` each variant runs with.
INTRA_HOST = {"iox": "auto", "zenoh": "zenoh"}


def mission_copy(src: Path, dst: Path, intra_host: str | None = None) -> Path:
    """``src`` with every endpoint on a free loopback port (gn added if
    missing) and, when given, ``transport.intra_host``."""
    doc = yaml.safe_load(src.read_text())
    relocate_mission(doc, src)  # the copy finds the mission's code from anywhere
    if intra_host is not None:
        doc.setdefault("transport", {})["intra_host"] = intra_host
    nodes = doc["nodes"]
    nodes.setdefault("gn", {})
    ports = {n: free_port() for n in nodes}
    cn_ep = f"tcp/127.0.0.1:{ports['cn']}"
    for n, spec in nodes.items():
        spec["listen"] = [f"tcp/127.0.0.1:{ports[n]}"]
        if n != "cn":
            spec["connect"] = [cn_ep]
    dst.write_text(yaml.safe_dump(doc, sort_keys=False))
    return dst


def generated(path: Path, n_elements: int, n_dn: int = 3, intra_host: str | None = None) -> Path:
    """A bandwidth-style mission of ``n_elements`` mixed elements, with a ground node."""
    tmp = make_mission(
        path.with_suffix(".raw.yaml"),
        n_dn=n_dn,
        region_bytes=1,
        priority=PRIORITY,
        extra=element_extra(n_elements, n_dn),
        name=f"elements_{n_elements}",
    )
    return mission_copy(tmp, path, intra_host)


def run_mission(mpath: Path, seconds: float, priority: int) -> dict[str, Any]:
    """One mission for ``seconds``: per-snapshot put->decode latency (blocks that long)."""
    tmpdir = mpath.parent
    gn_out = tmpdir / f"{mpath.stem}.gn.json"
    with BenchCluster(mpath, realtime=priority > 0) as c:
        cn = c.cn
        loops = max(1, round(seconds * c.mission.loop_hz))
        ground = _spawn_child(["ground", str(mpath), str(gn_out)])
        try:
            c.start(timeout_s=300.0)
            _wait_ready(ground, "ground node")
            tm_bytes = len(cn.logic.telemetry())
            stamps = TmPutStamps(cn.clock.now_ns)
            put_ns, put_mono = stamps.ns, stamps.mono
            trace.install(stamps)
            try:
                c.run(loops)
            finally:
                trace.uninstall()
            summary = cn.summary()
        finally:
            gn = _finish_child(ground, gn_out)
    rx = dict(zip(gn.get("seq", []), gn.get("rx_cn_ns", []), strict=False))
    rxm = dict(zip(gn.get("seq", []), gn.get("rx_mono", []), strict=False))
    lat = [rx[k] - put_ns[k] for k in put_ns if k in rx]
    latm = np.array([rxm[k] - put_mono[k] for k in put_mono if k in rxm], np.int64)
    lost = sum(1 for k in put_ns if k not in rx)
    dl = round(TM_DEADLINE_MS * 1e6)
    fig = summarize(lat, dl)
    late = sum(1 for x in lat if x >= dl)
    fig["deadline_miss_rate"] = (late + lost) / max(1, len(put_ns))
    fig["lost"] = lost
    fig["puts"] = len(put_ns)
    fig["tm_bytes"] = tm_bytes
    fig["ground_clock_offset_ns"] = gn.get("offset_ns")
    fig["tm_bad"] = gn.get("bad")
    fig["tm_iox"] = gn.get("iox")
    fig["tm_duplicates"] = gn.get("duplicates")
    fig["tm_fallbacks"] = gn.get("fallbacks")
    if latm.size:
        p50, p99 = np.percentile(latm, [50.0, 99.0])
        fig["same_host_p50_us"] = round(float(p50) / 1e3, 2)
        fig["same_host_p99_us"] = round(float(p99) / 1e3, 2)
    fig["sync_missed"] = int(sum(summary.missed.values()))
    fig["rate_hz_measured"] = round(float(summary.rate_hz), 2)
    return fig


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "telemetry_latency")
    parser.add_argument("--seconds", type=float, default=None)
    parser.add_argument("--priority", type=int, default=PRIORITY)
    parser.add_argument(
        "--intra-host",
        choices=("mission", "iox", "zenoh", "both"),
        default="mission",
        help="the ground's telemetry path (module doc); default: as each mission says",
    )
    args = parser.parse_args(argv)
    paths: list[str | None] = (
        [None]
        if args.intra_host == "mission"
        else ["iox", "zenoh"]
        if args.intra_host == "both"
        else [args.intra_host]
    )
    os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
    seconds = args.seconds or (5.0 if args.quick else 30.0)
    sched = inherit_fifo(args.priority)
    counts = [10_000] if args.quick else [10_000, 100_000]
    variants: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="zp-tm-") as tmp:
        d = Path(tmp)
        for p in paths:
            mode = INTRA_HOST[p] if p is not None else None
            sfx = f"_{p}" if p is not None else ""
            plan: list[tuple[str, Path]] = [
                (
                    f"led_test{sfx}",
                    mission_copy(
                        REPO_ROOT / "configs" / "led_test.yaml", d / f"led{sfx}.yaml", mode
                    ),
                ),
                (
                    f"thesis_200{sfx}",
                    mission_copy(
                        REPO_ROOT / "configs" / "thesis_200.yaml", d / f"t200{sfx}.yaml", mode
                    ),
                ),
            ]
            for name, path in plan:
                print(f"running {name} ({seconds:.0f} s) ...", flush=True)
                variants[name] = run_mission(path, seconds, args.priority)
            for n in counts:
                name = f"elements_{n}_3dn{sfx}"
                print(f"running {name} ({seconds:.0f} s) ...", flush=True)
                try:
                    variants[name] = run_mission(
                        generated(d / f"e{n}{sfx}.yaml", n, intra_host=mode),
                        seconds,
                        args.priority,
                    )
                except Exception as exc:  # reported, not hidden
                    variants[name] = {"error": repr(exc)[:300]}
    worst = max(
        (v["p99_us"] for v in variants.values() if v.get("p99_us") is not None), default=None
    )
    params: dict[str, Any] = {
        "rate_hz": 100.0,
        "seconds": seconds,
        "quick": bool(args.quick),
        "scheduling": sched,
        "auth": "on",
        "intra_host": args.intra_host,
        "clock": "CN node clock at put -> ground node clock at decode + clock-sync offset",
        "thesis": "R8: telemetry within 30 ms (requirement)",
        "targets": [
            {
                "name": f"telemetry p99 < 2 ms ({k})",
                "value": v.get("p99_us"),
                "limit": TARGET_P99_US,
                "unit": "us",
                "met": None if v.get("p99_us") is None else bool(v["p99_us"] < TARGET_P99_US),
            }
            for k, v in variants.items()
        ],
        "worst_p99_us": worst,
    }
    return write_result("telemetry_latency", params, variants, args.json)


if __name__ == "__main__":
    main()
