"""A ground gateway for the declaration-flood benchmark (tests/faults/decl_flood.py):
a zenoh *router* that tools reach instead of the vehicle's nodes.

    python -m tests.faults.gateway MISSION LISTEN_ENDPOINT [--deployment D]

It opens the ground node's config (``gn``: its certificate and the
mission's access control with ``--deployment``; plain without) as a router
listening on ``LISTEN_ENDPOINT`` and connected to the CN alone (gossip and
multicast scouting off), prints ``ready`` once the CN is its peer, and
closes when stdin ends. Every peer that connects to it is checked by its
own access control; what it forwards to the CN the CN checks as the
ground's.
"""

from __future__ import annotations

import argparse
import json
import sys

from tests.waits import poll_until
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import open_session, zenoh_config
from zplatform.security.deploy import load_deployment


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.faults.gateway")
    p.add_argument("mission")
    p.add_argument("listen")
    p.add_argument("--deployment")
    a = p.parse_args(argv)
    m = load_mission(a.mission)
    dep = load_deployment(a.deployment, m) if a.deployment else None
    cfg = zenoh_config(m, "gn", deployment=dep)
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([a.listen]))
    cfg.insert_json5("connect/endpoints", json.dumps(list(m.nodes["cn"].listen)))
    cfg.insert_json5("scouting/gossip/enabled", "false")
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = open_session(cfg)
    if not poll_until(lambda: list(session.info.peers_zid()), 30):  # the session's own view
        raise SystemExit("gateway: the CN never became a peer")
    print("ready", flush=True)
    sys.stdin.read()
    session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
