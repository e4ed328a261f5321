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

A stamp is taken by wrapping the object that does the step (a stand-in
that stamps around the named method and passes everything else through),
in the traced processes only: the nodes' code runs as shipped, and each
stamp costs well under a microsecond against the tens of microseconds a
325 KB step takes. A step the code no longer has (a tag checked once
instead of twice) is simply not stamped, and its hop merges into the next.

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
from collections.abc import Callable
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
    "dn.admitted": (0, "the bytes into the mailbox, by reference"),
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
    "tm.put": (0, "none when nobody subscribes (skipped); else ZBytes(bytearray), 1"),
}


class _Spy:
    """Stands in for ``target``: each method named in ``stamps`` calls its
    ``(before, after)`` callables (either None) around the real call; every
    other attribute is the target's. For objects with ``__slots__`` (codecs,
    channels), whose methods cannot be replaced on the instance."""

    def __init__(
        self,
        target: Any,
        stamps: dict[str, tuple[Callable[[], None] | None, Callable[[], None] | None]],
    ) -> None:
        object.__setattr__(self, "_target", target)
        for name, (pre, post) in stamps.items():
            object.__setattr__(self, name, _stamped(getattr(target, name), pre, post))

    def __getattr__(self, name: str) -> Any:
        return getattr(object.__getattribute__(self, "_target"), name)


def _stamped(
    fn: Callable[..., Any], pre: Callable[[], None] | None, post: Callable[[], None] | None
) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        if pre is not None:
            pre()
        out = fn(*args, **kwargs)
        if post is not None:
            post()
        return out

    return call


_MAX = 1 << 14  # loops kept per process (160 s at 100 Hz)


# -- the device node's process ---------------------------------------------------------


def dn_main(argv: list[str]) -> None:
    """``dn <mission> <name> <out.json> [--no-realtime]``: a DN process
    (``zplatform node MISSION NAME``'s) with every step stamped (module doc)."""
    from zplatform.auth import load_keys
    from zplatform.codec import frame_stamp
    from zplatform.intake import TriggerIntake
    from zplatform.mission import load_mission
    from zplatform.node.device import DeviceNode
    from zplatform.node.runtime import StopFlag, setup_logging

    mission_path, name, out, *extra = argv
    if set(extra) - {"--no-realtime"}:
        raise SystemExit(f"frame_trace dn: unknown options {extra}")
    rows: npt.NDArray[np.int64] = np.zeros((_MAX, len(DN_MARKS) + len(DN_SPANS)), np.int64)
    col = {m: k for k, m in enumerate((*DN_MARKS, *DN_SPANS))}
    mono = time.monotonic_ns
    zt = threading.local()  # zenoh's thread: this query's intake stamps and loop
    intake_lock = threading.Lock()
    by_loop: dict[int, list[int]] = {}  # admitted queries' intake stamps, by the loop they carry
    cur = [0] * rows.shape[1]  # the query being served (loop thread)
    serving = [False, 0]  # between serve and replied; the loop last replied to

    def dump() -> None:
        used = np.nonzero(rows.any(axis=1))[0]
        Path(out).write_text(json.dumps({"loops": used.tolist(), "t": rows[used].tolist()}))

    atexit.register(dump)

    # The intake (zenoh's thread), patched on the class in this process only:
    # admit's entry and exit; _frame runs just after the payload's copy out of
    # zenoh, _fresh just after the tag (and reads the loop the query carries:
    # queries admitted before the loop ran, or let go from a full mailbox,
    # are never matched to another's serve).
    admit0, frame0, fresh0 = TriggerIntake.admit, TriggerIntake._frame, TriggerIntake._fresh

    def admit(self: Any, payload: Any, handle: Any) -> bool:
        s = zt.s = [0] * 4
        zt.loop = 0
        s[0] = mono()
        ok = bool(admit0(self, payload, handle))
        s[3] = mono()
        if ok and zt.loop:
            with intake_lock:
                if len(by_loop) > 64:  # queries never served (a backlog let go)
                    by_loop.clear()
                by_loop[zt.loop] = s
        return ok

    def frame(self: Any, data: bytes) -> Any:
        zt.s[1] = mono()
        return frame0(self, data)

    def fresh(self: Any, body: memoryview, handle: Any) -> bool:
        zt.s[2] = mono()
        zt.loop = frame_stamp(body)[0]
        return bool(fresh0(self, body, handle))

    TriggerIntake.admit = admit  # type: ignore[method-assign]
    TriggerIntake._frame = frame  # type: ignore[method-assign]
    TriggerIntake._fresh = fresh  # type: ignore[method-assign]

    def stamp(mark: str) -> Callable[[], None]:
        k = col[mark]

        def at() -> None:
            cur[k] = mono()

        return at

    def trace(hop: str, loop: int) -> None:
        t = mono()
        if hop == "serve":
            for k in range(len(cur)):
                cur[k] = 0
            cur[col["serve"]] = t
            serving[0] = True
        elif hop == "replied":
            cur[col["replied"]] = t
            serving[0], serving[1] = False, loop
            with intake_lock:
                s = by_loop.pop(loop, None)
            if s is not None and 0 < loop < _MAX:
                cur[:4] = s
                rows[loop] = cur

    apply0 = [0]

    def apply_start() -> None:
        apply0[0] = mono()

    def apply_end() -> None:
        # In the trigger (before the reply): a mark on the chain too; in
        # run(), after the reply: the span only, on the row just written.
        t = mono()
        if serving[0]:
            cur[col["applied"]] = t
            cur[col["dn.apply"]] = t - apply0[0]
        elif 0 < serving[1] < _MAX:
            rows[serving[1], col["dn.apply"]] = t - apply0[0]

    setup_logging()
    mission = load_mission(mission_path)
    node = DeviceNode(
        mission, name, stop=StopFlag(), keys=load_keys(mission, name), sync_trace=trace
    )
    logic: Any = node.logic
    # The logic's own codecs and channels: stand-ins stamping after each step.
    if logic._open is not None:  # checked again, or stripped (checked by the intake)
        opened = (None, stamp("opened"))
        logic._open = _Spy(logic._open, {"open": opened, "strip": opened})
    logic._in = _Spy(
        logic._in, {"check": (None, stamp("decoded")), "write": (apply_start, apply_end)}
    )
    logic._out = _Spy(logic._out, {"encode": (None, stamp("encoded"))})
    if logic._seal is not None:
        logic._seal = _Spy(logic._seal, {"seal_tail": (None, stamp("sealed"))})
    try:
        node.start()
        node.run(realtime="--no-realtime" not in extra)
    finally:
        node.close()
        dump()


# -- the control node (this process) ---------------------------------------------------


class _CnStamps:
    """The in-process CN's stamps: the chain marks per loop and DN, the spans
    per loop (and DN, for the queries' framing). Loop thread and zenoh's
    threads; zenoh's stamps wait per DN until the loop thread takes the reply."""

    def __init__(self, n_dn: int) -> None:
        self.n_dn = n_dn
        self.chain: npt.NDArray[np.int64] = np.zeros((_MAX, n_dn, len(CN_MARKS)), np.int64)
        self.spans: npt.NDArray[np.int64] = np.zeros((_MAX, n_dn, len(SPANS)), np.int64)
        self.reply_len = [0] * n_dn
        self.query_len = [0] * n_dn
        self.logic: Any = None
        self._col = {m: k for k, m in enumerate(CN_MARKS)}
        self._zen = [[0, 0] for _ in range(n_dn)]  # back, queued
        self._last = 0  # the DN whose query was issued last
        self._t0: dict[str, int] = {}
        self._mono = time.monotonic_ns

    def _loop(self) -> int:
        logic = self.logic
        loop = int(logic.loop) if logic is not None else 0
        return loop if 0 < loop < _MAX else 0

    def __call__(self, hop: str, i: int) -> None:
        """The sync's own :data:`~zplatform.sync.SyncTrace` hook."""
        t = self._mono()
        if hop == "back":
            self._zen[i][0] = t
            return
        loop = self._loop()
        if hop == "issued":
            self._last = i
            self.chain[loop, i, 0] = t
        elif hop == "taken":
            row = self.chain[loop, i]
            row[2], row[3] = self._zen[i]
            row[4] = t

    def mark(self, mark: str, i: int | None = None) -> Callable[[], None]:
        """A stamp of chain mark ``mark`` (loop thread) for DN ``i`` (None:
        the DN issued last)."""
        k = self._col[mark]

        def at() -> None:
            self.chain[self._loop(), self._last if i is None else i, k] = self._mono()

        return at

    def queued(self, i: int) -> Callable[[], None]:
        def at() -> None:
            self._zen[i][1] = self._mono()

        return at

    def span(self, name: str, i: int = 0) -> tuple[Callable[[], None], Callable[[], None]]:
        """``(start, end)`` of span ``name`` (loop thread), for DN ``i``."""
        k = SPANS.index(name)

        def start() -> None:
            self._t0[name] = self._mono()

        def end() -> None:
            self.spans[self._loop(), i, k] = self._mono() - self._t0[name]

        return start, end


def instrument_cn(cn: Any, st: _CnStamps) -> None:
    """Put the stand-ins into the CN's logic, sync and telemetry publisher."""
    logic, sync = cn.logic, cn.sync
    st.logic = logic
    n = st.n_dn
    logic._to_dn = tuple(
        _Spy(c, {"encode": st.span("cn.encode", i)}) for i, c in enumerate(logic._to_dn)
    )
    if logic._seal_to_dn[0] is not None:
        logic._seal_to_dn = tuple(
            _Spy(c, {"seal_tail": st.span("cn.seal", i)}) for i, c in enumerate(logic._seal_to_dn)
        )
    if logic._open_from_dn[0] is not None:
        logic._open_from_dn = tuple(
            _Spy(c, {"open": (None, st.mark("opened", i))})
            for i, c in enumerate(logic._open_from_dn)
        )
    logic._from_dn = tuple(
        _Spy(c, {"check": (None, st.mark("decoded", i)), "write": (None, st.mark("applied", i))})
        for i, c in enumerate(logic._from_dn)
    )
    logic._tm = _Spy(logic._tm, {"encode": st.span("tm.encode")})
    if logic._seal_tm is not None:
        logic._seal_tm = _Spy(logic._seal_tm, {"seal_tail": st.span("tm.seal")})
    cn._tm_pub = _Spy(cn._tm_pub, {"put": st.span("tm.put")})
    sync.session = _Spy(sync.session, {"get": (None, st.mark("sent"))})
    # The reply hand-off (zenoh's thread): its end, after the payload's copy.
    take = sync._take
    ends = [st.queued(i) for i in range(n)]

    def timed_take(i: int, reply: Any, payload: Any) -> None:
        st.reply_len[i] = len(payload)
        take(i, reply, payload)
        ends[i]()

    sync._take = timed_take
    sync._build_callbacks()


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
            mpath,
            realtime=priority > 0,
            trace_dir=tmpdir,
            cn_trace=st,
            trace_module="bench.frame_trace",
        ) as c:
            m = c.mission
            instrument_cn(c.cn, st)
            c.start(timeout_s=300.0)
            c.run(loops, samples)
            st.query_len = [len(f) for f in c.cn.logic._frames]  # the last loop's, as sent
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
