"""Large frames hop by hop: where the 100,000-element sync's time goes, and its copies.

:mod:`bench.sync_trace` stamps the six hand-offs of a small-frame sync; at
``bench.bandwidth``'s 100,000-element point (a 162,596 B frame each way
with 1 DN, 54,268 B with 3) the time is in the work between them: framing,
tags, copies in and out of zenoh. This bench runs that point (the same
generated mission, :func:`bench.bandwidth.element_extra`, every frame
authenticated with ``--mac``) with the DN processes and the in-process CN
stamped at every step of every exchange, on ``CLOCK_MONOTONIC`` (one clock
for every process on a host)::

    CN loop thread   cn.encode, cn.seal        begin(): each DN's query framed, tagged
                     cn.issued -> cn.sent      session.get (payload into zenoh)
    zenoh            cn.sent -> dn.arrive      query to the DN's queryable callback
    DN zenoh thread  dn.copied, dn.verified,   intake: size, payload out of zenoh,
                     dn.admitted               tag, freshness, mailbox
    DN loop thread   dn.serve                  the query taken from the mailbox
                     dn.opened, dn.decoded     DeviceLogic.trigger: tag stripped (the
                                               intake checked it), decode
                     dn.encoded, dn.sealed     the reply framed, tagged
                     dn.replied                query.reply (payload into zenoh), released
                     dn.apply                  the trigger's data into the vector
                                               (DeviceLogic.run, after the reply; a
                                               trigger that applies it before the reply
                                               stamps dn.applied on the chain too)
    zenoh            dn.replied -> cn.back     reply to the CN's callback
    CN zenoh thread  cn.queued                 the payload out of zenoh, handed off
    CN loop thread   cn.taken, cn.opened,      ControlLogic.reply: tag, decode, the
                     cn.decoded, cn.applied    data into the vector
                     tm.encode, tm.seal,       telemetry, after the sync (outside its
                     tm.put                    window, on the same thread)

A stamp is a trace point of the platform's own (:mod:`zplatform.trace`:
``sync.issued``, ``dn.serve``, ``cn.decoded`` and the rest, named in its
module doc), recorded by a tracer this bench installs in the traced
processes only: the nodes' code runs as shipped, each point costs one ``is
None`` test when no tracer is installed, and each stamp well under a
microsecond against the tens of microseconds a 325 KB step takes. The
intake's inner steps (``dn.copied``, ``dn.verified``) have no point (the
intake is one call at the queryable's callback), so their hops merge into
``dn.arrive -> dn.admitted``; a step the code no longer has is simply not
stamped, and its hop merges into the next.

Reported per hop (the difference of consecutive stamps of one exchange):
p50 and p99 over the run, and the payload copies the hop makes
(:data:`COPIES`: counted from the code path, this repository's and
zenoh-python 1.10.2's, where ``ZBytes(bytes | bytearray)`` and
``ZBytes.to_bytes()`` each copy, and zenoh copies a payload over 3,072 B
into its shared-memory pool when the peer is on the same host). Beside
them, the sync step as :mod:`bench.bandwidth` measures it and the raw zenoh
floor moving the same bytes, measured in the same run
(:func:`bench.bandwidth.run_floor`), with their ratio.

``--label`` names the variant (``<label>_<N>el_<D>dn_<mac>``); ``--merge``
keeps the result file's other variants, so a before and an after can sit
side by side (the report tables them together).

Run ``python -m bench.frame_trace [--elements N] [--dns D] [--macs blake3,hmac]
[--seconds S] [--label L] [--merge] [--json PATH]``. Blocks about
``--seconds`` (default 20) per MAC, plus each cluster's start-up (10-20 s
for a 100,000-element mission) and a 10 s floor.
"""

from __future__ import annotations

import atexit
import json
import os
import secrets
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bench.common import RESULTS_DIR, bench_argparser, summarize, write_result

CN_MARKS = ("issued", "sent", "back", "queued", "taken", "opened", "decoded", "applied")
DN_MARKS = (
    "arrive",
    "copied",
    "verified",
    "admitted",
    "serve",
    "opened",
    "decoded",
    "applied",
    "encoded",
    "sealed",
    "replied",
)
#: One exchange's stamps, in the order they happen.
CHAIN = (
    *(f"cn.{m}" for m in CN_MARKS[:2]),
    *(f"dn.{m}" for m in DN_MARKS),
    *(f"cn.{m}" for m in CN_MARKS[2:]),
)
#: Steps timed by their own start and end (not on the exchange's chain).
SPANS = ("cn.encode", "cn.seal", "tm.encode", "tm.seal", "tm.put")
#: The DN's: a column of its rows after :data:`DN_MARKS`.
DN_SPANS = ("dn.apply",)

#: Payload copies per hop, named by the stamp that ends it (or the span):
#: ``(count, what)``, counted from the code path as it is (module doc).
COPIES: dict[str, tuple[int, str]] = {
    "cn.encode": (1, "the region into the encoder's buffer"),
    "cn.seal": (0, "the tag, written in place after the frame"),
    "cn.sent": (1, "ZBytes(bytearray) in session.get"),
    "dn.arrive": (1, "zenoh: into its shared-memory pool"),
    "dn.copied": (1, "ZBytes.to_bytes()"),
    "dn.verified": (0, "tag over a view"),
    # The intake has no inner points (module doc): its hop holds copied and verified.
    "dn.admitted": (1, "the intake: ZBytes.to_bytes(), the tag over a view, into the mailbox"),
    "dn.serve": (0, "wake-up"),
    "dn.opened": (0, "the tag stripped (checked by the intake), a view"),
    "dn.decoded": (0, "msgspec: data is a memoryview into the bytes"),
    "dn.applied": (1, "the data into the vector"),
    "dn.apply": (1, "the trigger's data into the vector (after the reply)"),
    "dn.encoded": (1, "the region into the encoder's buffer"),
    "dn.sealed": (0, "the tag, written in place after the frame"),
    "dn.replied": (1, "ZBytes(bytearray) in query.reply"),
    "cn.back": (1, "zenoh: into its shared-memory pool"),
    "cn.queued": (1, "ZBytes.to_bytes()"),
    "cn.taken": (0, "wake-up"),
    "cn.opened": (0, "tag over a view"),
    "cn.decoded": (0, "msgspec: data is a memoryview into the bytes"),
    "cn.applied": (1, "the data into the vector"),
    "tm.encode": (1, "the whole vector into the encoder's buffer"),
    "tm.seal": (0, "the tag, written in place after the frame"),
    "tm.put": (
        0,
        "none when nobody subscribes (skipped); else ZBytes(bytearray), 1; "
        "and one into an iceoryx2 loan for a ground on the CN's host",
    ),
}


_MAX = 1 << 14  # loops kept per process (160 s at 100 Hz)


# -- the device node's process ---------------------------------------------------------


class _DnStamps:
    """The DN process's :class:`zplatform.trace.Tracer`: its chain marks and
    spans per loop (:data:`DN_MARKS`, :data:`DN_SPANS`), for :func:`dump`.

    zenoh's thread stamps ``dn.arrive`` and ``dn.admitted``; the loop thread
    the rest. A served query takes the intake stamps of the one query
    admitted since the last serve: when none or more than one was (a query
    refused, a backlog let go), its row is not kept, so no query's intake is
    ever matched to another's serve. The intake's own steps (the payload's
    copy out of zenoh, its tag) are inside ``dn.arrive -> dn.admitted``:
    ``dn.copied`` and ``dn.verified`` are not stamped (their hops merge)."""

    def __init__(self) -> None:
        width = len(DN_MARKS) + len(DN_SPANS)
        self.rows: npt.NDArray[np.int64] = np.zeros((_MAX, width), np.int64)
        self.col = {m: k for k, m in enumerate((*DN_MARKS, *DN_SPANS))}
        self.mono = time.monotonic_ns
        self.zt = threading.local()  # zenoh's thread: this query's arrival
        self.lock = threading.Lock()
        self.admitted = [0, 0, 0, 0]  # the last admitted query's intake stamps
        self.n_admitted = 0  # queries admitted since the last serve
        self.cur = [0] * width  # the query being served (loop thread)
        self.matched = False
        self.last = 0  # the loop last replied to
        self.apply0 = 0

    def mark(self, name: str, n: int = 0, v: int = 0) -> None:
        t = self.mono()
        if name == "dn.arrive":
            self.zt.t = t
        elif name == "dn.admitted":
            with self.lock:
                self.admitted[:] = (getattr(self.zt, "t", 0), 0, 0, t)
                self.n_admitted += 1
        elif name == "dn.serve":
            cur = self.cur
            for k in range(len(cur)):
                cur[k] = 0
            with self.lock:
                self.matched = self.n_admitted == 1
                cur[:4] = self.admitted
                self.n_admitted = 0
            cur[self.col["serve"]] = t
        elif name == "dn.replied":
            self.cur[self.col["replied"]] = t
            self.last = n
            if self.matched and 0 < n < _MAX:
                self.rows[n] = self.cur
        elif name == "dn.apply":
            self.apply0 = t
        elif name == "dn.applied":  # in run(), after the reply: on the row just written
            if 0 < self.last < _MAX:
                self.rows[self.last, self.col["dn.apply"]] = t - self.apply0
        elif name.startswith("dn."):  # opened, decoded, encoded, sealed
            c = self.col.get(name[3:])
            if c is not None:
                self.cur[c] = t

    def dump(self, out: str) -> None:
        used = np.nonzero(self.rows.any(axis=1))[0]
        Path(out).write_text(json.dumps({"loops": used.tolist(), "t": self.rows[used].tolist()}))


def dn_main(argv: list[str]) -> None:
    """``dn <mission> <name> <out.json> [--no-realtime]``: a DN process
    (``zplatform node MISSION NAME``'s) with every step stamped (module doc)."""
    from zplatform import trace
    from zplatform.core.auth import load_keys
    from zplatform.mission.load import load_mission
    from zplatform.node.device import DeviceNode
    from zplatform.runtime.process import StopFlag, setup_logging

    mission_path, name, out, *extra = argv
    if set(extra) - {"--no-realtime"}:
        raise SystemExit(f"frame_trace dn: unknown options {extra}")
    st = _DnStamps()
    atexit.register(st.dump, out)
    setup_logging()
    mission = load_mission(mission_path)
    node = DeviceNode(mission, name, stop=StopFlag(), keys=load_keys(mission, name))
    trace.install(st)
    try:
        node.start()
        node.run(realtime="--no-realtime" not in extra)
    finally:
        trace.uninstall()
        node.close()
        st.dump(out)


# -- the control node (this process) ---------------------------------------------------


#: The CN's trace points on the chain: their column in :data:`CN_MARKS`.
CN_POINTS = {"sync.issued": 0, "sync.sent": 1, "cn.opened": 5, "cn.decoded": 6, "cn.applied": 7}
#: A span's end point -> (the span, its start point).
SPAN_POINTS = {
    "cn.encoded": ("cn.encode", "cn.encode"),
    "cn.sealed": ("cn.seal", "cn.encoded"),
    "tm.encoded": ("tm.encode", "tm.encode"),
    "tm.sealed": ("tm.seal", "tm.encoded"),
    "tm.sent": ("tm.put", "tm.put"),
}


class _CnStamps:
    """The in-process CN's :class:`zplatform.trace.Tracer`: the chain marks
    per loop and DN, the spans per loop (and DN, for the queries' framing),
    and the frames' sizes. Loop thread and zenoh's threads; zenoh's stamps
    wait per DN until the loop thread takes the reply."""

    def __init__(self, n_dn: int) -> None:
        self.n_dn = n_dn
        self.chain: npt.NDArray[np.int64] = np.zeros((_MAX, n_dn, len(CN_MARKS)), np.int64)
        self.spans: npt.NDArray[np.int64] = np.zeros((_MAX, n_dn, len(SPANS)), np.int64)
        self.reply_len = [0] * n_dn
        self.query_len = [0] * n_dn
        self.logic: Any = None
        self.zen = [[0, 0] for _ in range(n_dn)]  # back, queued
        self.t0: dict[tuple[str, int], int] = {}  # a span's start, by point and DN
        self.mono = time.monotonic_ns

    def loop(self) -> int:
        logic = self.logic
        loop = int(logic.loop) if logic is not None else 0
        return loop if 0 < loop < _MAX else 0

    def mark(self, name: str, n: int = 0, v: int = 0) -> None:
        t = self.mono()
        if name == "sync.back":  # zenoh's thread
            self.zen[n][0] = t
            self.reply_len[n] = v
            return
        if name == "sync.queued":  # zenoh's thread
            self.zen[n][1] = t
            return
        i = n if name.startswith(("cn.", "sync.")) else 0  # tm.*: n is the loop
        k = CN_POINTS.get(name)
        if k is not None:
            self.chain[self.loop(), i, k] = t
            if name == "sync.issued":
                self.query_len[i] = v
            return
        if name == "sync.taken":
            row = self.chain[self.loop(), i]
            row[2], row[3] = self.zen[i]
            row[4] = t
            return
        end = SPAN_POINTS.get(name)
        if end is not None:
            span, start = end
            self.spans[self.loop(), i, SPANS.index(span)] = t - self.t0.get((start, i), t)
        self.t0[name, i] = t


# -- reduction ---------------------------------------------------------------------------


def _stat(a: npt.NDArray[np.float64]) -> dict[str, Any]:
    if not a.size:
        return {"p50_us": None, "p99_us": None, "n": 0}
    return {
        "p50_us": round(float(np.median(a)), 2),
        "p99_us": round(float(np.percentile(a, 99)), 2),
        "n": int(a.size),
    }


def hop_table(
    cn: dict[int, list[list[int]]],
    spans: dict[int, list[list[int]]],
    dns: list[dict[int, list[int]]],
) -> dict[str, dict[str, Any]]:
    """Per hop (module doc) its p50/p99 in us over every exchange, and its copies.

    ``cn[loop][i]``: the CN's chain stamps for DN ``i`` (:data:`CN_MARKS`);
    ``spans[loop][i]``: its span durations (:data:`SPANS`, ns);
    ``dns[i][loop]``: DN ``i``'s stamps (:data:`DN_MARKS`), then its span
    durations (:data:`DN_SPANS`, ns). An exchange
    counts when both ends stamped its first and last mark; a hop ends at
    each later mark that was stamped, from the last one before it that was.
    """
    per: dict[str, list[float]] = {}
    for loop, by_dn in cn.items():
        for i, row in enumerate(by_dn):
            d = dns[i].get(loop) if i < len(dns) else None
            if d is None:
                continue
            nd = len(DN_MARKS)
            t = [*row[:2], *d[:nd], *row[2:]]
            if not (t[0] and t[-1]):
                continue
            for k, name in enumerate(DN_SPANS):
                if nd + k < len(d) and d[nd + k]:
                    per.setdefault(name, []).append(d[nd + k] / 1e3)
            prev = 0
            for k in range(1, len(t)):
                if not t[k]:
                    continue
                per.setdefault(f"{CHAIN[prev]}->{CHAIN[k]}", []).append((t[k] - t[prev]) / 1e3)
                prev = k
            per.setdefault("exchange", []).append((t[-1] - t[0]) / 1e3)
    for loop, by_dn in spans.items():
        if loop not in cn:
            continue
        for i, row in enumerate(by_dn):
            for k, name in enumerate(SPANS):
                if row[k] and (name.startswith("cn.") or i == 0):
                    per.setdefault(name, []).append(row[k] / 1e3)
    out: dict[str, dict[str, Any]] = {}
    hops = sorted(
        (k for k in per if "->" in k),
        key=lambda k: tuple(CHAIN.index(x) for x in reversed(k.split("->"))),
    )
    for name in [*SPANS[:2], *hops, "exchange", *DN_SPANS, *SPANS[2:]]:
        if name not in per:
            continue
        end = name.split("->")[-1]
        n_copies, what = COPIES.get(end, (0, ""))
        out[name] = {**_stat(np.array(per[name])), "copies": n_copies, "copy": what}
    if "exchange" in out:  # every copy of the exchange's two payloads, framing included
        mine = [*SPANS[:2], *hops, *DN_SPANS]
        out["exchange"]["copies"] = sum(out[h]["copies"] for h in mine if h in out)
        out["exchange"]["copy"] = "all of the exchange's: its hops, the query's framing"
    return out


def _point(
    elements: int, n_dn: int, mac: str, seconds: float, priority: int
) -> tuple[dict[str, Any], int]:
    """One traced cluster; returns its variant and its largest frame (bytes)."""
    from bench.bandwidth import DEADLINE_MS, RATE_HZ, element_extra
    from bench.cluster import BenchCluster, SyncSamples, make_mission
    from zplatform import trace

    with tempfile.TemporaryDirectory(prefix="zp-ftrace-") as tmp:
        tmpdir = Path(tmp)
        mpath = make_mission(
            tmpdir / "m.yaml",
            n_dn=n_dn,
            loop_hz=RATE_HZ,
            sync_timeout_ms=DEADLINE_MS,
            region_bytes=1,
            priority=priority if priority > 0 else None,
            extra=element_extra(elements, n_dn),
            mac=mac,
        )
        st = _CnStamps(n_dn)
        loops = max(1, round(seconds * RATE_HZ))
        samples = SyncSamples(loops)
        with BenchCluster(
            mpath, realtime=priority > 0, trace_dir=tmpdir, trace_module="bench.frame_trace"
        ) as c:
            m = c.mission
            st.logic = c.cn.logic
            trace.install(st)
            try:
                c.start(timeout_s=300.0)
                c.run(loops, samples)
            finally:
                trace.uninstall()
        dn_rows = []
        for dn in m.device_nodes:
            doc = json.loads((tmpdir / f"{dn}.trace.json").read_text())
            dn_rows.append({int(k): v for k, v in zip(doc["loops"], doc["t"], strict=True)})
    used = np.nonzero(st.chain.reshape(_MAX, -1).any(axis=1))[0]
    cn_rows = {int(r): st.chain[r].tolist() for r in used}
    span_rows = {int(r): st.spans[r].tolist() for r in used}
    got = samples.count
    d = samples.duration_ns[:got]
    deadline_ns = m.sync_timeout_ns
    ok = (samples.replied[:got] == n_dn) & (d < deadline_ns)
    fig = summarize(np.where(ok, d, deadline_ns).tolist(), deadline_ns)
    fig.update(
        elements=elements,
        n_dn=n_dn,
        mac=mac,
        missed_loops=int(np.count_nonzero(~ok)),
        frame_bytes_down=st.query_len,
        frame_bytes_up=st.reply_len,
        hops=hop_table(cn_rows, span_rows, dn_rows),
    )
    return fig, max([*st.query_len, *st.reply_len])


def _load(path: Path) -> dict[str, dict[str, Any]]:
    if not path.exists():
        return {}
    doc = json.loads(path.read_text(encoding="utf-8"))
    return dict(doc.get("variants") or {}) if doc.get("bench") == "frame_trace" else {}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args_list = sys.argv[1:] if argv is None else argv
    if args_list[:1] == ["dn"]:
        dn_main(args_list[1:])
        return {}
    from bench.bandwidth import MAC_SHORT, RATE_HZ, mac_suffix, parse_macs, run_floor
    from bench.sync import PRIORITY, inherit_fifo

    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "frame_trace")
    parser.add_argument("--elements", type=int, default=100_000)
    parser.add_argument("--dns", type=int, default=1)
    parser.add_argument("--macs", default=",".join(MAC_SHORT))
    parser.add_argument("--seconds", type=float, default=None)
    parser.add_argument("--label", default="now", help="the variants' name prefix")
    parser.add_argument("--merge", action="store_true", help="keep the file's other variants")
    parser.add_argument("--no-floor", action="store_true")
    parser.add_argument("--priority", type=int, default=PRIORITY)
    args = parser.parse_args(args_list)
    macs = parse_macs(args.macs)
    seconds = args.seconds or (5.0 if args.quick else 20.0)
    os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
    sched = inherit_fifo(args.priority)
    load0 = os.getloadavg()
    variants: dict[str, dict[str, Any]] = {}
    floor_p50: float | None = None
    for mac in macs:
        name = f"{args.label}_{args.elements}el_{args.dns}dn_{mac_suffix(mac)}"
        print(f"tracing {name} ({seconds:.0f} s) ...", flush=True)
        fig, size = _point(args.elements, args.dns, mac, seconds, args.priority)
        if not args.no_floor and floor_p50 is None:
            print(f"  floor raw_zenoh {args.dns}x{size}B ...", flush=True)
            floor = run_floor("zenoh", args.dns, size, RATE_HZ, min(seconds, 10.0))
            floor_p50 = floor["p50_us"]
            variants[f"{args.label}_raw_zenoh_{args.dns}x{size}B"] = {
                **floor,
                "label": args.label,
            }
        fig["label"] = args.label
        fig["loadavg"] = [round(x, 2) for x in os.getloadavg()]
        if floor_p50 and fig.get("p50_us"):
            fig["vs_raw_zenoh_p50"] = round(fig["p50_us"] / floor_p50, 3)
        variants[name] = fig
        for hop, h in fig["hops"].items():
            print(
                f"  {hop:28s} p50 {h['p50_us']!s:>8} p99 {h['p99_us']!s:>8}  copies {h['copies']}"
            )
        print(f"  sync p50 {fig['p50_us']} us, vs raw zenoh {fig.get('vs_raw_zenoh_p50')}")
    path = Path(args.json) if args.json else RESULTS_DIR / "frame_trace.json"
    if args.merge:
        variants = {**_load(path), **variants}
    params: dict[str, Any] = {
        "elements": args.elements,
        "dns": args.dns,
        "macs": macs,
        "seconds": seconds,
        "label": args.label,
        "scheduling": sched,
        "loadavg_at_start": [round(x, 2) for x in load0],
        "loadavg_at_end": [round(x, 2) for x in os.getloadavg()],
        "clock": "CLOCK_MONOTONIC in every process (one host)",
        "copies": "counted from the code path (module doc), per hop",
    }
    return write_result("frame_trace", params, variants, str(path))


if __name__ == "__main__":
    main()
