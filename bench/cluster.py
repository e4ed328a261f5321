"""A zplatform cluster for benchmarks: DNs as processes, the CN in-process.

:func:`make_mission` writes a mission YAML with N device nodes on free
loopback ports and regions of a chosen size. :class:`BenchCluster` spawns the
DNs (``python -m zplatform node``), builds a
:class:`~zplatform.node.control.ControlNode` in this process, waits for the
DNs (liveliness plus warm-up sync, never sleeps), and runs the CN's real loop
with a hook called after every loop, so a benchmark can read the CN's Data
Vector and the sync statistics of that loop. Every child is killed on close.
"""

from __future__ import annotations

import os
import secrets
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from zplatform.config import Mission
from zplatform.core.auth import KEY_ENV, KEY_FILE_ENV, load_keys
from zplatform.mission.load import load_mission
from zplatform.node.control import ControlNode
from zplatform.runtime.process import PARENT_ENV, StopFlag
from zplatform.runtime.scheduler import PeriodicLoop
from zplatform.runtime.sync import SyncTrace
from zplatform.runtime.transport import free_port

from .common import REPO_ROOT, terminate_all

__all__ = ["BenchCluster", "make_mission"]


def make_mission(
    path: Path,
    *,
    n_dn: int,
    loop_hz: float = 100.0,
    sync_timeout_ms: float = 2.0,
    region_bytes: int = 256,
    lowlatency: bool | str = False,
    sync_query: str | None = None,
    priority: int | None = None,
    controllers: list[dict[str, Any]] | None = None,
    devices: list[dict[str, Any]] | None = None,
    extra: dict[str, list[dict[str, Any]]] | None = None,
    name: str = "bench",
    transport: str | None = None,
    mac: str | None = None,
) -> Path:
    """Write a benchmark mission to ``path`` and return it.

    Each ``cn_to_dnX`` and ``dnX_to_cn`` region is padded with a ``u8``
    array so its size is ``region_bytes`` (at least the platform elements).
    ``extra`` appends elements to regions by name. ``transport``: the
    mission's ``security.transport`` (default: the mission default, plain
    here: a benchmark mission has no hazardous command). ``mac``: the
    mission's ``security.mac`` (else the mission default).
    """
    ports = {n: free_port() for n in ["cn", *[f"dn{i}" for i in range(n_dn)]]}
    cn_ep = f"tcp/127.0.0.1:{ports['cn']}"
    nodes: dict[str, Any] = {"cn": {"listen": [cn_ep]}}
    for i in range(n_dn):
        nodes[f"dn{i}"] = {"listen": [f"tcp/127.0.0.1:{ports[f'dn{i}']}"], "connect": [cn_ep]}
    if priority is not None:
        for n in nodes.values():
            n["priority"] = priority
    regions: dict[str, list[dict[str, Any]]] = {"cn": [{"name": "bench_pad", "type": "u8"}]}
    # dnX_to_cn carries 49 B of platform elements; cn_to_dnX none.
    for i in range(n_dn):
        down = max(1, region_bytes)
        up = max(1, region_bytes - 49)
        regions[f"cn_to_dn{i}"] = [{"name": f"down_pad_{i}", "type": f"u8[{down}]"}]
        regions[f"dn{i}_to_cn"] = [{"name": f"up_pad_{i}", "type": f"u8[{up}]"}]
    for region, elements in (extra or {}).items():
        regions.setdefault(region, []).extend(elements)
    doc: dict[str, Any] = {
        "mission": name,
        "vehicle": "bench",
        "loop_hz": loop_hz,
        "sync_timeout_ms": sync_timeout_ms,
        "transport": {"lowlatency": lowlatency},
        "clock": {"exchanges": 50, "resync_s": 0},
        # Health is on by default; a bench mission sizes its regions to the
        # byte and compares with raw transports, so it runs without (its
        # cost is bench.health's to measure).
        "health": None,
        "nodes": nodes,
        "regions": regions,
    }
    if controllers:
        doc["controllers"] = controllers
    if devices:
        doc["devices"] = devices
    if sync_query is not None:  # else the mission default (per_node)
        doc["transport"]["sync_query"] = sync_query
    if transport is not None:
        doc.setdefault("security", {})["transport"] = transport
    if mac is not None:
        doc.setdefault("security", {})["mac"] = mac
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class BenchCluster:
    """DN processes plus an in-process CN. Use as a context manager.

    ``realtime``: apply SCHED_FIFO/affinity from the mission (and pass
    ``--no-realtime`` to the DNs otherwise). ``trace_dir``: run each DN under
    ``trace_module`` (default :mod:`bench.sync_trace`; :mod:`bench.frame_trace`
    for large frames), whose ``dn`` entry point writes ``<dn>.trace.json``
    there on exit.
    ``cn_trace``: the in-process CN's sync trace hook
    (:data:`zplatform.runtime.sync.SyncTrace`).
    """

    def __init__(
        self,
        mission_path: Path,
        *,
        realtime: bool = True,
        dn_env: dict[str, dict[str, str]] | None = None,
        log_dir: Path | None = None,
        trace_dir: Path | None = None,
        cn_trace: SyncTrace | None = None,
        trace_module: str = "bench.sync_trace",
    ) -> None:
        self.path = mission_path
        self.mission: Mission = load_mission(mission_path)
        self.realtime = realtime
        self.procs: list[subprocess.Popen[bytes]] = []
        self.log_dir = log_dir or mission_path.parent
        # Measured as shipped: authenticated. This process's key, or a
        # run's own; the DN processes and the in-process CN share it.
        if not (os.environ.get(KEY_ENV) or os.environ.get(KEY_FILE_ENV)):
            os.environ[KEY_ENV] = secrets.token_hex(32)
        keys = load_keys(self.mission, "cn")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env[PARENT_ENV] = str(os.getpid())
        for dn in self.mission.device_nodes:
            e = dict(env, **(dn_env or {}).get(dn, {}))
            args = [sys.executable, "-m", "zplatform", "node", str(mission_path), dn]
            if trace_dir is not None:  # the same node, its hops stamped
                out = str(trace_dir / f"{dn}.trace.json")
                args = [sys.executable, "-m", trace_module, "dn", *args[4:], out]
            if not realtime:
                args.append("--no-realtime")
            with open(self.log_dir / f"{dn}.log", "ab") as log:
                self.procs.append(
                    subprocess.Popen(
                        args, stdout=log, stderr=subprocess.STDOUT, env=e, cwd=REPO_ROOT
                    )
                )
        self.cn = ControlNode(
            self.mission, stop=StopFlag(install=False), keys=keys, sync_trace=cn_trace
        )

    def start(self, timeout_s: float = 60.0) -> dict[str, int]:
        """Wait for every DN (clock-synced, answering); returns clock offsets."""
        return self.cn.wait_ready(timeout_s, ground_wait_s=0)  # benches run no ground node

    def run(
        self,
        loops: int,
        on_loop: Callable[[int, ControlNode], None] | None = None,
        *,
        record: int = 0,
    ) -> PeriodicLoop:
        """Run the CN's real loop for ``loops`` loops; ``on_loop(loop, cn)`` after each.

        Returns the PeriodicLoop (its ``stats()`` and ``lateness_ns()``).
        """
        cn = self.cn
        hook = None
        if on_loop is not None:

            def hook(loop: int, deadline_ns: int, started_ns: int) -> None:
                on_loop(loop, cn)

        return cn.run(max_loops=loops, realtime=self.realtime, record=record, on_loop=hook)

    def close(self) -> None:
        try:
            self.cn.close()
        finally:
            terminate_all(self.procs)

    def __enter__(self) -> BenchCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SyncSamples:
    """Per-loop sync figures for :meth:`BenchCluster.run`'s hook: how long the
    CN's sync step took and how many DNs had answered. Preallocated; the hook
    runs on the loop thread and only stores two ints."""

    def __init__(self, loops: int) -> None:
        self.loops = loops
        self.duration_ns: npt.NDArray[np.int64] = np.zeros(loops, np.int64)
        self.replied: npt.NDArray[np.int64] = np.zeros(loops, np.int64)
        self.count = 0

    def __call__(self, loop: int, cn: ControlNode) -> None:
        i = self.count
        if i < self.loops:
            self.duration_ns[i] = cn.sync.duration_ns
            self.replied[i] = len(cn.logic.dns) - cn.logic.pending
            self.count = i + 1
