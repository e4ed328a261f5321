"""Bulk transfer between two processes on this host: shared memory or not.

For each size (1 KB, 64 KB, 1 MB, 4 MB, 16 MB) these variants run side by
side in one run, in interleaved rounds (every round visits every size and
variant), each as its own sender process and receiver process:

* ``zplatform_shm``: :class:`zplatform.runtime.bulk.NodeBulk`, shared memory on:
  one copy into the pool, then on the receiver ``bytes(shm)`` and a copy into
  the reader's preallocated array (:meth:`BulkReader.wait`);
* ``zplatform_shm_view``: the same processes, ``wait(copy=False)``: the
  receiver stops at a read-only view over the received bytes (one copy out);
* ``zplatform``: the same code with shared memory off in both sessions;
* ``raw_zenoh_shm``: bare zenoh: ``ShmProvider.alloc`` (``BlockOn``,
  ``GarbageCollect``), ``ZShmMut[:] = bytes``, ``put``; receiver: a direct
  callback doing ``payload.to_bytes()``;
* ``raw_zenoh``: ``put(bytearray)`` and ``to_bytes()``, shared memory off;
* ``iceoryx2``: iceoryx2's Python bindings (the zero-copy IPC reference):
  ``loan_slice_uninit``, one ``memmove`` in, ``send`` plus an event
  ``notify``; the receiver waits on the event listener and copies the
  sample's memory view into a preallocated array (one copy out);
* ``copy``: ``np.copyto`` of the same size in one process (the floor).

Both zenoh sessions are built by :func:`zplatform.runtime.transport.zenoh_config`
from one two-node mission (loopback TCP, shared memory per variant).

Latency is one way: the sender writes ``time.monotonic_ns()`` into the
payload header just before its copy in, the receiver reads the clock once
the data is in its array (same host, same clock). Samples are paced (a
period per size well above the latency), so no queueing is measured. Figures
per ``<variant>_<size>``: ``p50_us``, ``p99_us``, ``max_us``, ``msgs``, and
from a separate burst (back-to-back sends) ``throughput_MBps`` (bytes that
reached the receiver's array over first send to last receive) and
``delivered`` (fraction of the burst that arrived: latest-wins readers and
DROP congestion control lose samples under a burst, by design). zplatform
variants add ``via_shm`` (fraction of samples that came through shared
memory) and ``dropped`` (pool exhausted past the deadline).

Targets (reported in ``params.targets``, not asserted): 4 MB under 1 ms p50;
at 1 MB at least 3x lower p50 than without shared memory; within 2x of
iceoryx2.

Run ``python -m bench.shm [--quick] [--json PATH]``; results go to
``bench/results/shm.json``. Blocks about 3 minutes (``--quick``: about 40 s).
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import struct
import sys
import threading
import time
from typing import Any

import numpy as np

from bench.common import (
    Child,
    bench_argparser,
    commands,
    free_port,
    say,
    summarize,
    two_node_mission,
    write_result,
)

SIZES = {
    "1KB": 1 << 10,
    "64KB": 64 << 10,
    "256KB": 256 << 10,
    "1MB": 1 << 20,
    "4MB": 4 << 20,
    "16MB": 16 << 20,
}
LAT_N = {"1KB": 2000, "64KB": 2000, "256KB": 1000, "1MB": 1000, "4MB": 400, "16MB": 120}
PERIOD_S = {"1KB": 0.001, "64KB": 0.001, "256KB": 0.002, "1MB": 0.003, "4MB": 0.008, "16MB": 0.03}
BURST_N = {"1KB": 5000, "64KB": 2000, "256KB": 600, "1MB": 300, "4MB": 100, "16MB": 30}
# Sync-frame sizes for the query round trip (raw zenoh get/reply, shm on/off).
RTT_SIZES = {"1KB": 1 << 10, "4KB": 4 << 10, "16KB": 16 << 10, "64KB": 64 << 10, "256KB": 256 << 10}
RTT_N = 1000
ROUNDS = 4
VARIANTS = ("zplatform_shm", "zplatform", "raw_zenoh_shm", "raw_zenoh", "iceoryx2")
TS = struct.Struct("<q")  # raw/iceoryx2 header: sender monotonic ns at offset 0
IOX_BUFFER = 8  # iceoryx2 subscriber queue (its default, 2, loses most of a burst)


def _channels() -> list[Any]:
    from zplatform.runtime.bulk import BulkChannelConfig

    # The header is 32 bytes: shrink the array so a sample is exactly the size.
    return [
        BulkChannelConfig(name=f"s{n}", node="dn0", type=f"u8[{n - 32}]", readers=["cn"])
        for n in SIZES.values()
    ]


# -- sender ------------------------------------------------------------------


class _Sender:
    def __init__(self, variant: str, mission_text: str) -> None:
        self.variant = variant
        self.src = {n: bytearray(os.urandom(n)) for n in SIZES.values()}
        self.drops = 0
        if variant.startswith("zplatform"):
            from zplatform.mission.load import decode_mission
            from zplatform.runtime.bulk import NodeBulk
            from zplatform.runtime.transport import NodeSession

            m = decode_mission(mission_text)
            shm = variant == "zplatform_shm"
            self.ns = NodeSession(m, "dn0", shared_memory=shm)
            self.bulk = NodeBulk(self.ns.session, m.vehicle, _channels(), "dn0", shared_memory=shm)
            self.writers = {w.channel.sample_bytes: w for w in self.bulk.writers.values()}
            for w in self.writers.values():
                w.array.reshape(-1)[:] = np.frombuffer(self.src[w.channel.sample_bytes], np.uint8)[
                    32:
                ]
            self._wait(lambda: all(w.matching for w in self.writers.values()))
        elif variant.startswith("raw_zenoh"):
            import zenoh

            from zplatform.mission.load import decode_mission
            from zplatform.runtime.transport import is_matching, open_session, zenoh_config

            m = decode_mission(mission_text)
            shm = variant == "raw_zenoh_shm"
            self.session = open_session(zenoh_config(m, "dn0", shared_memory=shm))
            self.pubs = {
                n: self.session.declare_publisher(f"bench/raw/{n}") for n in SIZES.values()
            }
            self.replies = {n: bytes(n) for n in RTT_SIZES.values()}
            self.queryables = [
                self.session.declare_queryable(
                    f"bench/q/{n}", zenoh.handlers.Callback(self._on_query, indirect=False)
                )
                for n in RTT_SIZES.values()
            ]
            self.provider: Any = None
            if shm:
                pool = sum(3 * (-(-n // 4096) * 4096) for n in SIZES.values())
                self.provider = zenoh.shm.ShmProvider.default_backend(pool)
                self.policy = zenoh.shm.BlockOn(zenoh.shm.GarbageCollect())
                for n, b in self.src.items():  # pre-touch the pool, like NodeBulk
                    held = [self.provider.alloc(n) for _ in range(3)]
                    for c in held:
                        c[:] = b
                    del held
                self.provider.garbage_collect()
            self._wait(lambda: all(is_matching(p) for p in self.pubs.values()))
        else:
            import iceoryx2 as iox2

            self.iox = iox2
            node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
            self.node = node
            self.iox_pubs = {}
            for n in SIZES.values():
                svc = (
                    node.service_builder(iox2.ServiceName.new(f"zpbench/{os.getppid()}/{n}"))
                    .publish_subscribe(iox2.Slice[ctypes.c_uint8])
                    .subscriber_max_buffer_size(IOX_BUFFER)
                    .open_or_create()
                )
                ev = (
                    node.service_builder(iox2.ServiceName.new(f"zpbench/{os.getppid()}/{n}/ev"))
                    .event()
                    .open_or_create()
                )
                pub = (
                    svc.publisher_builder()
                    .initial_max_slice_len(n)
                    .allocation_strategy(iox2.AllocationStrategy.PowerOfTwo)
                    .create()
                )
                self.iox_pubs[n] = (svc, ev, pub, ev.notifier_builder().create())

    def _on_query(self, query: Any) -> None:
        # Reply at once, then let go of the query (docs/architecture.md#zenoh).
        with query:
            n = int(str(query.key_expr).rsplit("/", 1)[1])
            query.reply(query.key_expr, self.replies[n])

    @staticmethod
    def _wait(pred: Any) -> None:
        deadline = time.monotonic() + 30
        while not pred():
            if time.monotonic() > deadline:
                raise SystemExit("receiver never matched")
            time.sleep(0.01)

    def send(self, n: int, loop: int) -> None:
        if self.variant.startswith("zplatform"):
            w = self.writers[n]
            if not w.publish(loop, time.monotonic_ns()):
                self.drops += 1
        elif self.variant.startswith("raw_zenoh"):
            b = self.src[n]
            TS.pack_into(b, 0, time.monotonic_ns())
            if self.provider is not None:
                chunk = self.provider.alloc(n, policy=self.policy)
                chunk[:] = b
                self.pubs[n].put(chunk)
            else:
                self.pubs[n].put(b)
        else:
            _svc, _ev, pub, notifier = self.iox_pubs[n]
            b = self.src[n]
            TS.pack_into(b, 0, time.monotonic_ns())
            sample = pub.loan_slice_uninit(n)
            ctypes.memmove(sample.payload().as_ptr(), (ctypes.c_char * n).from_buffer(b), n)
            sample.assume_init().send()
            notifier.notify()

    def run(self, cmd: dict[str, Any]) -> None:
        n, count, period = cmd["size"], cmd["n"], cmd["period"]
        self.drops = 0
        t0 = time.monotonic()
        for i in range(count):
            self.send(n, i)
            if period:
                nxt = t0 + (i + 1) * period
                while (left := nxt - time.monotonic()) > 0:
                    time.sleep(left)
        say({"done": True, "drops": self.drops})


def _sender_main(variant: str, mission_text: str) -> None:
    s = _Sender(variant, mission_text)
    say({"ready": True})
    for cmd in commands():
        if cmd["cmd"] == "quit":
            break
        s.run(cmd)


# -- receiver ----------------------------------------------------------------


class _Receiver:
    def __init__(self, variant: str, mission_text: str) -> None:
        self.variant = variant
        self.dst = {n: np.empty(n, np.uint8) for n in SIZES.values()}
        if variant.startswith("zplatform"):
            from zplatform.mission.load import decode_mission
            from zplatform.runtime.bulk import NodeBulk
            from zplatform.runtime.transport import NodeSession

            m = decode_mission(mission_text)
            shm = variant == "zplatform_shm"
            self.ns = NodeSession(m, "cn", shared_memory=shm)
            self.bulk = NodeBulk(self.ns.session, m.vehicle, _channels(), "cn", shared_memory=shm)
            self.readers = {r.channel.sample_bytes: r for r in self.bulk.readers.values()}
        elif variant.startswith("raw_zenoh"):
            import zenoh

            from zplatform.mission.load import decode_mission
            from zplatform.runtime.transport import open_session, zenoh_config

            m = decode_mission(mission_text)
            self.session = open_session(
                zenoh_config(m, "cn", shared_memory=variant == "raw_zenoh_shm")
            )
            self.lat: list[int] = []
            self.bytes_rx = 0
            self.first_tx: int | None = None
            self.last_rx = 0
            self.shm_rx = 0
            self.event = threading.Event()
            self.want = 0
            self.subs = [
                self.session.declare_subscriber(
                    f"bench/raw/{n}", zenoh.handlers.Callback(self._on_raw, indirect=False)
                )
                for n in SIZES.values()
            ]
        else:
            import iceoryx2 as iox2

            self.iox = iox2
            node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
            self.node = node
            self.iox_subs = {}
            for n in SIZES.values():
                svc = (
                    node.service_builder(iox2.ServiceName.new(f"zpbench/{os.getppid()}/{n}"))
                    .publish_subscribe(iox2.Slice[ctypes.c_uint8])
                    .subscriber_max_buffer_size(IOX_BUFFER)
                    .open_or_create()
                )
                ev = (
                    node.service_builder(iox2.ServiceName.new(f"zpbench/{os.getppid()}/{n}/ev"))
                    .event()
                    .open_or_create()
                )
                sub = svc.subscriber_builder().buffer_size(IOX_BUFFER).create()
                self.iox_subs[n] = (svc, ev, sub, ev.listener_builder().create())

    def _on_raw(self, sample: Any) -> None:
        # Direct callback: the bare-zenoh fast path (no hand-off).
        payload = sample.payload
        if payload.as_shm() is not None:
            self.shm_rx += 1
        data = payload.to_bytes()
        now = time.monotonic_ns()
        (t,) = TS.unpack_from(data, 0)
        self.lat.append(now - t)
        self.bytes_rx += len(data)
        if self.first_tx is None:
            self.first_tx = t
        self.last_rx = now
        if len(self.lat) >= self.want:
            self.event.set()

    def rtt(self, cmd: dict[str, Any]) -> dict[str, Any]:
        """``n`` sync-style round trips: get with a ``size`` payload, reply of ``size``."""
        import zenoh

        n, count = cmd["size"], cmd["n"]
        req = bytes(n)
        out: list[int] = []
        shm = 0
        for _ in range(count):
            t = time.monotonic_ns()
            replies = self.session.get(
                f"bench/q/{n}",
                payload=req,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=1.0,
            )
            for reply in replies:
                if reply.ok is None:
                    break
                payload = reply.ok.payload
                shm += payload.as_shm() is not None
                payload.to_bytes()
                out.append(time.monotonic_ns() - t)
                break
            time.sleep(0.001)
        return {"lat": out, "shm": shm}

    def run(self, cmd: dict[str, Any]) -> dict[str, Any]:
        """Receive up to ``n`` samples of ``size``; stop after ``idle`` s with none."""
        n, count, idle = cmd["size"], cmd["n"], cmd["idle"]
        lat: list[int] = []
        rx_bytes = 0
        first_tx: int | None = None
        last_rx = 0
        shm = 0
        if self.variant.startswith("zplatform"):
            r = self.readers[n]
            copy = not cmd.get("view", False)
            shm0 = r.received_shm
            while len(lat) < count:
                if not r.wait(idle, copy=copy):
                    break
                now = time.monotonic_ns()
                assert r.header is not None
                lat.append(now - r.header.t_ns)
                rx_bytes += n
                first_tx = r.header.t_ns if first_tx is None else first_tx
                last_rx = now
            shm = r.received_shm - shm0
        elif self.variant.startswith("raw_zenoh"):
            # The callback fills the lists; main thread only waits.
            self.lat, self.bytes_rx, self.first_tx, self.last_rx, self.shm_rx = [], 0, None, 0, 0
            self.want = count
            self.event.clear()
            seen = -1
            while len(self.lat) < count and len(self.lat) != seen:
                seen = len(self.lat)
                self.event.wait(idle)
            lat, rx_bytes, first_tx, last_rx, shm = (
                list(self.lat),
                self.bytes_rx,
                self.first_tx,
                self.last_rx,
                self.shm_rx,
            )
        else:
            _svc, _ev, sub, listener = self.iox_subs[n]
            dst = self.dst[n]
            timeout = self.iox.Duration.from_secs_f64(idle)
            while len(lat) < count:
                if not listener.timed_wait(timeout):
                    break
                while (sample := sub.receive()) is not None:
                    mv = sample.payload().as_memory_view()
                    np.copyto(dst, np.frombuffer(mv, np.uint8))
                    now = time.monotonic_ns()
                    (t,) = TS.unpack_from(dst.data, 0)
                    del mv, sample
                    lat.append(now - t)
                    rx_bytes += n
                    first_tx = t if first_tx is None else first_tx
                    last_rx = now
        return {
            "lat": lat,
            "rx_bytes": rx_bytes,
            "span_ns": (last_rx - first_tx) if first_tx is not None else 0,
            "shm": shm,
        }


def _receiver_main(variant: str, mission_text: str) -> None:
    r = _Receiver(variant, mission_text)
    say({"ready": True})
    for cmd in commands():
        if cmd["cmd"] == "quit":
            break
        say(r.rtt(cmd) if cmd["cmd"] == "rtt" else r.run(cmd))


# -- orchestrator ----------------------------------------------------------


def _copy_floor(n: int, count: int) -> list[int]:
    src = np.frombuffer(os.urandom(n), np.uint8)
    dst = np.empty(n, np.uint8)
    out = []
    for _ in range(count):
        t = time.perf_counter_ns()
        np.copyto(dst, src)
        out.append(time.perf_counter_ns() - t)
    return out


def _iceoryx2_version() -> str | None:
    try:
        from importlib import metadata

        return metadata.version("iceoryx2")
    except Exception:
        return None


def main() -> None:
    ap = bench_argparser(__doc__.split("\n")[0] if __doc__ else "bench.shm")
    ap.add_argument("--role", choices=["send", "recv"], help=argparse_hidden())
    ap.add_argument("--variant", help=argparse_hidden())
    ap.add_argument("--sizes", default=",".join(SIZES), help="subset, e.g. 1MB,4MB")
    args = ap.parse_args()
    if args.role:
        mission_text = os.environ["ZP_BENCH_MISSION"]
        (_sender_main if args.role == "send" else _receiver_main)(args.variant, mission_text)
        return

    quick = args.quick
    sizes = [s for s in args.sizes.split(",") if s]
    div = 10 if quick else 1
    rounds = 2 if quick else ROUNDS
    ice = _iceoryx2_version()
    variants = [v for v in VARIANTS if v != "iceoryx2" or ice]
    procs: dict[str, tuple[Child, Child]] = {}
    try:
        for v in variants:
            # A pair of ports per variant.
            mission_text = two_node_mission("bench_shm", free_port(), free_port())
            rx = Child("bench.shm", ["--role", "recv", "--variant", v], mission_text)
            rx.read()
            tx = Child("bench.shm", ["--role", "send", "--variant", v], mission_text)
            tx.read()
            procs[v] = (rx, tx)
        runs = [*variants]
        runs.insert(1, "zplatform_shm_view")
        lat: dict[str, list[int]] = {f"{v}_{s}": [] for v in runs for s in sizes}
        shm_n: dict[str, int] = dict.fromkeys(lat, 0)
        drops: dict[str, int] = dict.fromkeys(lat, 0)
        for rnd in range(rounds):
            for s in sizes:
                n = SIZES[s]
                count = max(20, LAT_N[s] // div // rounds)
                for v in runs:
                    rx, tx = procs["zplatform_shm" if v == "zplatform_shm_view" else v]
                    print(f"round {rnd + 1}/{rounds} {v} {s} x{count}", file=sys.stderr)
                    rx.send(
                        {
                            "cmd": "rx",
                            "size": n,
                            "n": count,
                            "idle": 1.0,
                            "view": v == "zplatform_shm_view",
                        }
                    )
                    tx.send({"cmd": "tx", "size": n, "n": count, "period": PERIOD_S[s]})
                    drops[f"{v}_{s}"] += tx.read()["drops"]
                    res = rx.read()
                    lat[f"{v}_{s}"] += res["lat"]
                    shm_n[f"{v}_{s}"] += res["shm"]
        result: dict[str, dict[str, Any]] = {}
        for s in sizes:
            n = SIZES[s]
            fl = summarize(_copy_floor(n, max(20, LAT_N[s] // div)))
            fl["throughput_MBps"] = round(n / (fl["p50_us"] * 1e-6) / 1e6, 1)
            result[f"copy_{s}"] = fl
            for v in runs:
                key = f"{v}_{s}"
                fig = summarize(lat[key])
                if v.startswith("zplatform") or v == "raw_zenoh_shm":
                    fig["via_shm"] = round(shm_n[key] / max(1, len(lat[key])), 3)
                if v.startswith("zplatform"):
                    fig["dropped"] = drops[key]
                result[key] = fig
        # Burst throughput (after the latency rounds, one burst per size/variant).
        for s in sizes:
            n = SIZES[s]
            count = max(10, BURST_N[s] // div)
            for v in variants:
                rx, tx = procs[v]
                rx.send({"cmd": "rx", "size": n, "n": count, "idle": 0.5})
                tx.send({"cmd": "tx", "size": n, "n": count, "period": 0})
                tx.read()
                res = rx.read()
                fig = result[f"{v}_{s}"]
                span = res["span_ns"]
                fig["throughput_MBps"] = round(res["rx_bytes"] / span * 1e3, 1) if span else None
                fig["delivered"] = round(len(res["lat"]) / count, 3)
        # Sync-frame sizes: query round trip with and without shared memory.
        for s, n in RTT_SIZES.items():
            for v in ("raw_zenoh_shm", "raw_zenoh"):
                rx, _tx = procs[v]
                rx.send({"cmd": "rtt", "size": n, "n": max(50, RTT_N // div)})
                res = rx.read()
                fig = summarize(res["lat"])
                fig["via_shm"] = round(res["shm"] / max(1, len(res["lat"])), 3)
                result[f"sync_rtt_{v}_{s}"] = fig
    finally:
        for rx, tx in procs.values():
            tx.close()
            rx.close()

    def ratio(a: str, b: str) -> float | None:
        pa, pb = result.get(a, {}).get("p50_us"), result.get(b, {}).get("p50_us")
        return round(pa / pb, 2) if pa and pb else None

    checks: dict[str, Any] = {}
    if "4MB" in sizes:
        checks["zplatform_shm_4MB_p50_us"] = result["zplatform_shm_4MB"]["p50_us"]
        checks["4MB_under_1ms"] = (result["zplatform_shm_4MB"]["p50_us"] or math.inf) < 1000
    if "1MB" in sizes:
        checks["1MB_speedup_vs_no_shm"] = ratio("zplatform_1MB", "zplatform_shm_1MB")
    for s in sizes:
        if ice:
            checks[f"{s}_vs_iceoryx2"] = ratio(f"zplatform_shm_{s}", f"iceoryx2_{s}")
    params = {
        "quick": quick,
        "sizes": {s: SIZES[s] for s in sizes},
        "rounds": rounds,
        "period_s": {s: PERIOD_S[s] for s in sizes},
        "iceoryx2": ice or "not installed (pip install iceoryx2): variant skipped",
        "targets": {
            "4MB_p50_us": 1000,
            "1MB_speedup_vs_no_shm": 3.0,
            "vs_iceoryx2_max": 2.0,
        },
        "checks": checks,
        "notes": [
            "latency: one way, sender clock before its copy in to receiver clock after the "
            "data is in its array (zplatform_shm_view: in a read-only view)",
            "throughput_MBps: a back-to-back burst, bytes that reached the receiver's array "
            "over first send to last receive; zplatform readers keep the latest sample only, "
            "so 'delivered' < 1 there by design",
            "sync_rtt_*: get/reply of a payload of that size each way (a sync frame), "
            "raw zenoh, shared memory on (implicit, >= 3 KB) or off",
            "zplatform receivers hand off from zenoh's callback to the reading thread "
            "(BulkReader.wait); raw_zenoh receivers work inside the callback",
        ],
    }
    write_result("shm", params, result, args.json)
    print(json.dumps(checks, indent=1))


def argparse_hidden() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
