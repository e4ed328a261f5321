"""A zenoh peer with a chosen identity, driven over stdin, for the TLS/ACL test.

Run inside a namespace::

    python -m tests.faults.tls_probe MISSION [--ca CA --cert CERT --key KEY]

It opens a tool session (listens nowhere, connects to every node's listen
endpoint) presenting ``CERT``/``KEY`` and trusting ``CA``, or with no TLS
settings at all when ``--cert`` is left out, and subscribes to the CN's
telemetry, checked and decoded by the ground's own logic
(:class:`~zplatform.ground.logic.GroundLogic`, with the mission key from the
environment). It prints
``ready``, then answers one JSON request per stdin line with one JSON line:

* ``{"op": "telemetry", "timeout": s, "count": n}``: wait (at most ``s``)
  for ``n`` more snapshots -> ``{"received": total, "new": k,
  "cn_bad_frames": .., "cn_cmd_rejects": .., "dn0_bad_frames": ..}`` (the
  latest snapshot's values; snapshots queued before the request are skipped);
* ``{"op": "get", "key": k, "timeout": s}``: one get with a garbage payload
  -> ``{"ok": n, "err": n, "why": [error reply texts]}``;
* ``{"op": "put", "key": k}``: put a garbage payload -> ``{"done": true}``;
* ``{"op": "peers"}`` -> ``{"peers": n}`` zenoh peers connected now.

Not for flight: the garbage payloads are there to be counted as bad frames
by whoever receives them.
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from typing import Any

import zenoh

from zplatform.core.auth import load_keys
from zplatform.ground.logic import GroundLogic
from zplatform.mission.load import load_mission
from zplatform.runtime.timebase import NodeClock
from zplatform.runtime.transport import KeySpace, open_session, zenoh_config
from zplatform.security.deploy import Deployment, ToolIdentity

# Longer than a tag (32 bytes: run word, header tag and MAC), so a receiver reads it as a
# frame and refuses it for its tag (a command request: a reject), not its size.
GARBAGE = b"\x93intruder\x00not-a-frame".ljust(64, b"\x00")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("mission")
    ap.add_argument("--ca")
    ap.add_argument("--cert")
    ap.add_argument("--key")
    a = ap.parse_args()
    mission = load_mission(a.mission)
    dep = None
    if a.cert:
        # The chosen cert, whatever its common name, as the tool identity.
        dep = Deployment(ca=a.ca, tool=ToolIdentity(cert=a.cert, key=a.key))
    session = open_session(zenoh_config(mission, None, deployment=dep))
    ground = GroundLogic(mission, keys=load_keys(mission, "tool"))
    clock = NodeClock()
    q: queue.SimpleQueue[tuple[bytes, int]] = queue.SimpleQueue()
    sub = session.declare_subscriber(
        KeySpace(mission.vehicle).telemetry,
        zenoh.handlers.Callback(
            lambda s: q.put((s.payload.to_bytes(), clock.now_ns())), indirect=False
        ),
    )

    def next_snapshot(timeout_s: float) -> bool:
        """One queued frame through the ground logic: True when accepted."""
        try:
            payload, rx = q.get(timeout=timeout_s) if timeout_s > 0 else q.get_nowait()
        except queue.Empty:
            return False
        return ground.on_telemetry(payload, rx)

    print("ready", flush=True)
    for line in sys.stdin:
        req = json.loads(line)
        op = req["op"]
        out: dict[str, Any]
        if op == "telemetry":
            # The queue keeps every snapshot (a FIFO): skip the backlog so
            # the values reported are from snapshots taken after the request.
            while not q.empty():
                next_snapshot(0.0)
            deadline = time.monotonic() + float(req["timeout"])
            new = 0
            while new < int(req.get("count", 1)) and (left := deadline - time.monotonic()) > 0:
                if next_snapshot(min(left, 0.2)):
                    new += 1
            out = {"received": ground.received, "new": new}
            if ground.received:
                out.update(
                    cn_bad_frames=int(ground.dv.get("cn_bad_frames")),
                    cn_cmd_rejects=int(ground.dv.get("cn_cmd_rejects")),
                    dn0_bad_frames=int(ground.dv.get("dn0_bad_frames")),
                )
        elif op == "get":
            replies = session.get(
                req["key"],
                payload=GARBAGE,
                timeout=float(req["timeout"]),
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            ok = err = 0
            why = []
            for r in replies:  # ends at the timeout or when every queryable answered
                if r.ok is not None:
                    ok += 1
                else:
                    err += 1
                    why.append(r.err.payload.to_bytes().decode(errors="replace"))
            out = {"ok": ok, "err": err, "why": why}
        elif op == "put":
            session.put(req["key"], GARBAGE)
            out = {"done": True}
        elif op == "peers":
            out = {"peers": len(list(session.info.peers_zid()))}
        else:
            out = {"error": f"unknown op {op!r}"}
        print(json.dumps(out), flush=True)
    sub.undeclare()
    session.close()


if __name__ == "__main__":
    main()
