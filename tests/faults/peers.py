"""Minimal zenoh peers for the fault suite: a config builder and a tiny CLI.

The CLI runs inside network namespaces (``ip netns exec``), where the test
process cannot open sessions itself::

    python -m tests.faults.peers serve --listen tcp/10.77.0.1:7447
        declares queryable ``faults/echo`` (replies with the query payload),
        then prints ``ready`` and serves until stdin closes.
    python -m tests.faults.peers probe --connect tcp/10.77.0.1:7447
        for every line read on stdin, sends one ``get`` (timeout = the line as
        a number of seconds, default 0.2) and prints ``ok <payload>`` or
        ``none``; exits when stdin closes.

Both use the same settings as the platform's nodes where they matter here:
peer mode, no scouting, connect retry every 50-200 ms, a 1 s lease, no
shared memory.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

import zenoh

ECHO_KEY = "faults/echo"


def peer_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    *,
    lease_ms: int = 1000,
    lowlatency: bool = False,
) -> zenoh.Config:
    c = zenoh.Config()
    if lowlatency:  # as zplatform.runtime.transport sets it (QoS off: zenoh refuses the pair)
        c.insert_json5("transport/unicast/lowlatency", "true")
        c.insert_json5("transport/unicast/qos/enabled", "false")
    for key, value in (
        ("mode", "peer"),
        ("listen/endpoints", list(listen)),
        ("connect/endpoints", list(connect)),
        ("scouting/multicast/enabled", False),
        ("scouting/gossip/enabled", False),
        ("connect/timeout_ms", -1),
        ("connect/exit_on_failure", False),
        ("connect/retry", {"period_init_ms": 50, "period_max_ms": 200}),
        ("transport/link/tx/lease", lease_ms),
        ("transport/shared_memory/enabled", False),
    ):
        c.insert_json5(key, json.dumps(value))
    return c


def echo(query: zenoh.Query) -> None:
    """Reply to ``query`` with its own payload, then let go of it (DESIGN §8)."""
    with query:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        query.reply(query.key_expr, payload)


def get_once(session: zenoh.Session, timeout_s: float, payload: bytes = b"") -> bytes | None:
    """One ``get`` on :data:`ECHO_KEY`; the first ok payload, or None."""
    out: bytes | None = None
    for r in session.get(
        ECHO_KEY,
        payload=payload,
        timeout=timeout_s,
        consolidation=zenoh.ConsolidationMode.NONE,
    ):
        if r.ok is not None and out is None:
            out = r.ok.payload.to_bytes()
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.faults.peers")
    ap.add_argument("role", choices=["serve", "probe"])
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--lease-ms", type=int, default=1000)
    a = ap.parse_args(argv)
    s = zenoh.open(peer_config(a.listen, a.connect, lease_ms=a.lease_ms))
    try:
        if a.role == "serve":
            q = s.declare_queryable(ECHO_KEY, echo)
            print("ready", flush=True)
            for _ in sys.stdin:
                pass
            q.undeclare()
        else:
            for n, line in enumerate(sys.stdin, 1):
                timeout = float(line.strip() or 0.2)
                got = get_once(s, timeout, str(n).encode())
                print("none" if got is None else f"ok {got.decode()}", flush=True)
    finally:
        s.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
