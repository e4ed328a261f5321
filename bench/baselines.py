"""Baselines for every latency benchmark: the sync exchange without the platform.

The exchange is the zplatform sync step (docs/architecture.md#the-loop): every loop, one
requester (the CN) sends ``size`` bytes to each of ``n_responders`` processes
(the DNs). Each responder answers with ``size`` bytes. The requester waits for
all the replies, up to a deadline. There are two transports:

* ``raw_udp``: Python UDP sockets on loopback, the thesis' transport;
* ``raw_zenoh``: a bare zenoh ``get``/``reply`` on one key per responder, with
  ``ConsolidationMode.NONE``. The request bytes travel in the query payload and
  the answer in the reply payload. ``lowlatency=True`` turns on
  ``transport/unicast/lowlatency`` (with QoS off) on both ends.

What is measured, per loop: the time (``time.perf_counter_ns``) from just before
the first request is sent until the last reply of that loop has been received
and its bytes copied out. If a loop misses its deadline, it is recorded as the
deadline value and also counted in ``missed``. Loops are paced at ``rate_hz``
against absolute deadlines: the requester sleeps until the next start time,
and an overrun loop makes the next one start at once. Warm-up loops run before
the measurement and are not recorded.

What blocks: ``run_baseline`` blocks for about ``duration_s`` plus the start-up
of the children (about 0.1-0.5 s each). The responders block in
``recvfrom`` (UDP) or ``Queryable.recv`` (zenoh). Readiness is deterministic
and never uses a sleep. A UDP responder sends a ``ready`` datagram. A zenoh
responder declares a liveliness token, and then one warm-up query to each
responder must get a reply. Children run in their own process groups, and
they are stopped (SIGTERM, then SIGKILL) on every exit path, exceptions
included. A responder also exits by itself if its parent dies.

Run ``python -m bench.baselines [--quick] [--json PATH]``. The children run as
``python -m bench.baselines responder --kind udp|zenoh ...``.
"""

from __future__ import annotations

import json
import os
import queue
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, TypedDict

import zenoh

from bench.common import (
    bench_argparser,
    free_port,
    spawn,
    summarize,
    terminate_all,
    write_result,
)

#: Frame header at the front of every request and reply: loop sequence (u64), responder index (u32).
HEADER = struct.Struct("<QI")
READY = b"ready"
KEY_PREFIX = "bench/baseline"
#: Loops run before measuring (not recorded): connection set-up, caches, SHM pools.
WARMUP_LOOPS = 20
#: How long start-up may take (children to start and become ready) before giving up.
STARTUP_TIMEOUT_S = 30.0


class BaselineResult(TypedDict):
    """Per-loop round-trip times in ns (a missed loop counts as the deadline) and the miss count."""

    samples_ns: list[int]
    missed: int


class BaselineError(RuntimeError):
    """A baseline could not start or run (a responder died or never became ready)."""


# ----------------------------------------------------------------------------- zenoh config


def zenoh_config(
    *, listen_port: int | None, connect_port: int | None, lowlatency: bool
) -> zenoh.Config:
    """A loopback peer config: no multicast, no gossip (the requester is the hub), 1 s lease,
    no tx batching (as zplatform's nodes).

    Also makes ``open`` return at once and reconnects quickly (see ZENOH_API.md §1).
    """
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5(
        "listen/endpoints",
        json.dumps([f"tcp/127.0.0.1:{listen_port}"] if listen_port is not None else []),
    )
    c.insert_json5(
        "connect/endpoints",
        json.dumps([f"tcp/127.0.0.1:{connect_port}"] if connect_port is not None else []),
    )
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    c.insert_json5("scouting/delay", "0")
    c.insert_json5(
        "connect/retry", "{period_init_ms: 50, period_max_ms: 200, period_increase_factor: 2}"
    )
    c.insert_json5("transport/link/tx/lease", "1000")
    # Same transport tuning as zplatform's nodes (no tx batching), so the
    # baseline isolates the platform's own cost, not a config difference.
    c.insert_json5("transport/link/tx/queue/batching/enabled", "false")
    if lowlatency:
        c.insert_json5("transport/unicast/lowlatency", "true")
        c.insert_json5("transport/unicast/qos/enabled", "false")
    return c


def _key(index: int) -> str:
    return f"{KEY_PREFIX}/rsp{index}/to_cn"


def _token_key(index: int) -> str:
    return f"{KEY_PREFIX}/rsp{index}/alive"


# ----------------------------------------------------------------------------- responders


def _exit_when_orphaned() -> None:
    """Start a daemon thread that exits this process when its parent dies (a check every 0.5 s)."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(0)

    threading.Thread(target=watch, name="orphan-watch", daemon=True).start()


def _make_reply(size: int) -> bytearray:
    return bytearray(max(size, HEADER.size))


def udp_responder(index: int, requester_port: int, size: int) -> None:
    """Serve UDP requests forever: block in ``recvfrom``, reply ``size`` bytes echoing the sequence.

    The responder binds an ephemeral port and announces itself with a ``ready``
    datagram (``ready`` + header) sent to the requester. The requester learns the
    responder's address from that datagram.
    """
    _exit_when_orphaned()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    dest = ("127.0.0.1", requester_port)
    sock.sendto(READY + HEADER.pack(0, index), dest)
    reply = _make_reply(size)
    buf = bytearray(65536)
    while True:
        n, addr = sock.recvfrom_into(buf)
        if n < HEADER.size:
            continue
        seq, _ = HEADER.unpack_from(buf)
        HEADER.pack_into(reply, 0, seq, index)
        sock.sendto(reply, addr)


def zenoh_responder(index: int, requester_port: int, size: int, lowlatency: bool) -> None:
    """Serve zenoh queries forever: block in ``Queryable.recv``, reply ``size`` bytes.

    The responder connects to the requester's listener and declares its
    queryable, then its liveliness token, which is the readiness signal.
    It releases each ``Query`` right after replying (``with query:``).
    """
    _exit_when_orphaned()
    session = zenoh.open(
        zenoh_config(listen_port=None, connect_port=requester_port, lowlatency=lowlatency)
    )
    key = _key(index)
    queryable = session.declare_queryable(key)
    token = session.liveliness().declare_token(_token_key(index))
    reply = _make_reply(size)
    try:
        while True:
            query = queryable.recv()
            with query:
                payload = query.payload
                req = payload.to_bytes() if payload is not None else b""
                seq = HEADER.unpack_from(req)[0] if len(req) >= HEADER.size else 0
                HEADER.pack_into(reply, 0, seq, index)
                query.reply(key, bytes(reply))
    finally:
        token.undeclare()
        session.close()


# ----------------------------------------------------------------------------- requester


def _pace(rate_hz: float, duration_s: float, step: Callable[[int], None]) -> None:
    """Call ``step(loop)`` at ``rate_hz`` against absolute start times for ``duration_s``.

    Blocks by sleeping until each loop's start time. An overrun loop is not
    made up: the next loop starts at once and later ones keep to the grid.
    """
    period_ns = round(1e9 / rate_hz)
    loops = max(1, round(duration_s * rate_hz))
    t0 = time.perf_counter_ns() + period_ns
    for i in range(loops):
        start = t0 + i * period_ns
        delay = start - time.perf_counter_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
        step(i)


def _responder_args(kind: str, index: int, port: int, size: int, *, lowlatency: bool) -> list[str]:
    args = ["-m", "bench.baselines", "responder", "--kind", kind, "--index", str(index)]
    args += ["--port", str(port), "--size", str(size)]
    return [*args, "--lowlatency"] if lowlatency else args


def _check_alive(procs: Sequence[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        rc = p.poll()
        if rc is not None:
            raise BaselineError(f"responder pid {p.pid} exited with {rc} during start-up")


def _run_udp(
    n_responders: int, size: int, rate_hz: float, duration_s: float, deadline_ns: int
) -> BaselineResult:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        for i in range(n_responders):
            procs.append(spawn(_responder_args("udp", i, port, size, lowlatency=False)))
        # Readiness: one "ready" datagram per responder; its source address is the responder's.
        addrs: dict[int, tuple[str, int]] = {}
        buf = bytearray(65536)
        give_up = time.monotonic() + STARTUP_TIMEOUT_S
        while len(addrs) < n_responders:
            _check_alive(procs)
            if time.monotonic() > give_up:
                raise BaselineError(f"only {len(addrs)}/{n_responders} UDP responders ready")
            sock.settimeout(0.5)
            try:
                n, addr = sock.recvfrom_into(buf)
            except TimeoutError:
                continue
            if bytes(buf[: len(READY)]) == READY and n >= len(READY) + HEADER.size:
                _, idx = HEADER.unpack_from(buf, len(READY))
                addrs[idx] = addr
        dests = [addrs[i] for i in range(n_responders)]
        request = bytearray(max(size, HEADER.size))
        samples: list[int] = []
        missed = 0
        measuring = False

        def step(loop: int) -> None:
            nonlocal missed
            seq = loop + 1 if not measuring else WARMUP_LOOPS + loop + 1
            pending = set(range(n_responders))
            t_start = time.perf_counter_ns()
            t_deadline = t_start + deadline_ns
            for i, dest in enumerate(dests):
                HEADER.pack_into(request, 0, seq, i)
                sock.sendto(request, dest)
            while pending:
                remaining = t_deadline - time.perf_counter_ns()
                if remaining <= 0:
                    break
                sock.settimeout(remaining / 1e9)
                try:
                    n, _ = sock.recvfrom_into(buf)
                except TimeoutError:
                    break
                if n >= HEADER.size:
                    rseq, idx = HEADER.unpack_from(buf)
                    if rseq == seq:
                        _ = bytes(buf[:n])  # copy out, as the platform would
                        pending.discard(idx)
            t_end = time.perf_counter_ns()
            if not measuring:
                return
            if pending or t_end - t_start > deadline_ns:
                samples.append(deadline_ns)
                missed += 1
            else:
                samples.append(t_end - t_start)

        _pace(rate_hz, WARMUP_LOOPS / rate_hz, step)
        measuring = True
        _pace(rate_hz, duration_s, step)
        return {"samples_ns": samples, "missed": missed}
    finally:
        terminate_all(procs)
        sock.close()


def _run_zenoh(
    n_responders: int,
    size: int,
    rate_hz: float,
    duration_s: float,
    deadline_ns: int,
    lowlatency: bool,
    wildcard: bool = False,
) -> BaselineResult:
    procs: list[subprocess.Popen[bytes]] = []
    port = free_port()
    session = zenoh.open(zenoh_config(listen_port=port, connect_port=None, lowlatency=lowlatency))
    try:
        # Replies (and None when a query finalises) land on one queue, pushed from
        # zenoh's own thread (indirect=False: no Python thread per query).
        inbox: queue.SimpleQueue[zenoh.Reply | None] = queue.SimpleQueue()

        def on_final() -> None:
            inbox.put(None)

        callback = zenoh.handlers.Callback(inbox.put, on_final, indirect=False)
        tokens: queue.SimpleQueue[zenoh.Sample] = queue.SimpleQueue()
        live = session.liveliness().declare_subscriber(
            f"{KEY_PREFIX}/*/alive",
            zenoh.handlers.Callback(tokens.put, indirect=False),
            history=True,
        )
        for i in range(n_responders):
            procs.append(spawn(_responder_args("zenoh", i, port, size, lowlatency=lowlatency)))
        # Readiness 1: every responder's liveliness token.
        ready: set[str] = set()
        wanted = {_token_key(i) for i in range(n_responders)}
        give_up = time.monotonic() + STARTUP_TIMEOUT_S
        while not wanted <= ready:
            _check_alive(procs)
            if time.monotonic() > give_up:
                raise BaselineError(f"liveliness: only {sorted(ready)} of {sorted(wanted)}")
            try:
                sample = tokens.get(timeout=0.5)
            except queue.Empty:
                continue
            if sample.kind == zenoh.SampleKind.PUT:
                ready.add(str(sample.key_expr))
        # Readiness 2: a successful query to each responder.
        keys = [_key(i) for i in range(n_responders)]
        for key in keys:
            while True:
                _check_alive(procs)
                if time.monotonic() > give_up:
                    raise BaselineError(f"no reply from {key}")
                replies = session.get(
                    key,
                    payload=HEADER.pack(0, 0),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=1.0,
                )
                if any(r.ok is not None for r in replies):
                    break
        live.undeclare()

        request = bytearray(max(size, HEADER.size))
        # wildcard: one query to every responder at once, carrying every
        # responder's frame (each reads its own slice), as one get per loop.
        wide = bytearray(len(request) * n_responders)
        wild_key = f"{KEY_PREFIX}/*/to_cn"
        timeout_s = max(deadline_ns / 1e9, 0.001)
        samples: list[int] = []
        missed = 0
        measuring = False

        def step(loop: int) -> None:
            nonlocal missed
            seq = loop + 1 if not measuring else WARMUP_LOOPS + loop + 1
            pending = set(range(n_responders))
            t_start = time.perf_counter_ns()
            t_deadline = t_start + deadline_ns
            if wildcard:
                for i in range(n_responders):
                    HEADER.pack_into(wide, i * len(request), seq, i)
                session.get(
                    wild_key,
                    callback,
                    payload=bytes(wide),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=timeout_s,
                )
            for i, key in enumerate(keys if not wildcard else ()):
                HEADER.pack_into(request, 0, seq, i)
                session.get(
                    key,
                    callback,
                    payload=bytes(request),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=timeout_s,
                )
            while pending:
                remaining = t_deadline - time.perf_counter_ns()
                if remaining <= 0:
                    break
                try:
                    item = inbox.get(timeout=remaining / 1e9)
                except queue.Empty:
                    break
                if item is None or item.ok is None:
                    continue  # a query finalised, or a timeout error from a late loop
                data = item.ok.payload.to_bytes()
                if len(data) >= HEADER.size:
                    rseq, idx = HEADER.unpack_from(data)
                    if rseq == seq:
                        pending.discard(idx)
            t_end = time.perf_counter_ns()
            if not measuring:
                return
            if pending or t_end - t_start > deadline_ns:
                samples.append(deadline_ns)
                missed += 1
            else:
                samples.append(t_end - t_start)

        _pace(rate_hz, WARMUP_LOOPS / rate_hz, step)
        measuring = True
        _pace(rate_hz, duration_s, step)
        return {"samples_ns": samples, "missed": missed}
    finally:
        terminate_all(procs)
        session.close()


def run_baseline(
    kind: str,
    n_responders: int,
    size: int,
    rate_hz: float,
    duration_s: float,
    deadline_ns: int,
    lowlatency: bool = False,
    wildcard: bool = False,
) -> BaselineResult:
    """Spawn ``n_responders`` responders and run ``rate_hz`` × ``duration_s`` timed loops.

    ``kind`` is ``"udp"`` or ``"zenoh"``. ``lowlatency`` and ``wildcard`` (one
    query per loop to every responder, carrying every responder's frame,
    instead of one get each) apply to zenoh only.
    Blocks for the whole run and returns the per-loop times (ns) of all replies,
    with each missed loop recorded as ``deadline_ns``, and the count of missed
    loops. Raises :class:`BaselineError` if the responders never become ready.
    """
    if n_responders < 1:
        raise ValueError("n_responders must be >= 1")
    if rate_hz <= 0 or duration_s <= 0 or deadline_ns <= 0:
        raise ValueError("rate_hz, duration_s and deadline_ns must be > 0")
    if kind == "udp":
        return _run_udp(n_responders, size, rate_hz, duration_s, deadline_ns)
    if kind == "zenoh":
        return _run_zenoh(
            n_responders, size, rate_hz, duration_s, deadline_ns, lowlatency, wildcard
        )
    raise ValueError(f"unknown baseline kind {kind!r} (udp|zenoh)")


# ----------------------------------------------------------------------------- CLI


def _responder_main(argv: list[str]) -> None:
    import argparse

    p = argparse.ArgumentParser(prog="python -m bench.baselines responder")
    p.add_argument("--kind", choices=["udp", "zenoh"], required=True)
    p.add_argument("--index", type=int, required=True)
    p.add_argument("--port", type=int, required=True, help="the requester's port")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--lowlatency", action="store_true")
    a = p.parse_args(argv)
    if a.kind == "udp":
        udp_responder(a.index, a.port, a.size)
    else:
        zenoh_responder(a.index, a.port, a.size, a.lowlatency)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run raw_udp, raw_zenoh and raw_zenoh_lowlatency with 1 and 3 responders; write the result."""
    args_list = sys.argv[1:] if argv is None else argv
    if args_list[:1] == ["responder"]:
        _responder_main(args_list[1:])
        return {}
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "baselines")
    parser.add_argument("--size", type=int, default=256, help="request and reply bytes")
    parser.add_argument("--rate", type=float, default=100.0, help="loop rate (Hz)")
    parser.add_argument("--deadline-us", type=int, default=2000, help="per-loop deadline")
    args = parser.parse_args(args_list)
    duration_s = 5.0 if args.quick else 30.0
    deadline_ns = args.deadline_us * 1000
    params = {
        "size_bytes": args.size,
        "rate_hz": args.rate,
        "duration_s": duration_s,
        "deadline_us": args.deadline_us,
        "warmup_loops": WARMUP_LOOPS,
        "responders": [1, 3],
        "quick": bool(args.quick),
    }
    variants: dict[str, dict[str, Any]] = {}
    plan = [
        ("raw_udp", "udp", False),
        ("raw_zenoh", "zenoh", False),
        ("raw_zenoh_lowlatency", "zenoh", True),
    ]
    for n in (1, 3):
        for name, kind, ll in plan:
            label = f"{name}_{n}dn"
            print(f"running {label} ({duration_s:.0f} s) ...", flush=True)
            res = run_baseline(kind, n, args.size, args.rate, duration_s, deadline_ns, ll)
            fig = summarize(res["samples_ns"], deadline_ns)
            fig["missed"] = res["missed"]
            fig["responders"] = n
            variants[label] = fig
    return write_result("baselines", params, variants, args.json)


if __name__ == "__main__":
    main()
