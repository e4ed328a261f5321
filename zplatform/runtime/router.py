"""``zplatform router``: a zenoh router between the vehicle and its stations.

A router runs zenoh-python's router mode (one session, ``mode: router``)
with the mission's transport settings, its mutual TLS and access-control
list (:func:`zplatform.security.deploy.access_control`: a router presents
its own identity, ``router-<name>``, and their policy lets it forward only
what stations may send and receive: their subscriptions to telemetry and
events, their requests on ``{vehicle}/gn/to_cn``, run hellos, recorder and
archive queries and their replies, liveliness tokens; never a device node's
key, a sync query, the mirror or a bulk channel). The CN publishes
telemetry once; each router fans it out to its stations (zenoh clients of
it, ``ground.stations[].connect``) and the next router (docs/deployment.md).

Contract: :func:`router_config` is pure but for the deployment's file
checks (DeploymentError for a mission with mutual TLS and no certificate of
the router's own, TransportError for a setting zenoh refuses); :func:`run_router`
blocks until its stop flag is set, printing ``READY`` once the session is
open (what ``up``'s supervisor waits for).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Sequence
from typing import Any

import zenoh

from ..config import Mission, RouterConfig
from ..core.messages import lowlatency_for
from ..errors import TransportError
from ..security.deploy import (
    ROUTER,
    Deployment,
    DeploymentError,
    check_router_certificate,
    require_deployment,
    router_identity,
    tls_nodes,
    zenoh_settings,
)
from .process import StopFlag
from .transport import SESSION_CLOSE_S, open_session

__all__ = ["ROUTER", "find_router", "link_endpoints", "router_config", "run_router"]


def _insert(cfg: zenoh.Config, key: str, value: Any) -> None:
    try:
        cfg.insert_json5(key, json.dumps(value))
    except Exception as exc:  # zenoh raises ZError; keep the key in the message
        raise TransportError(f"zenoh config {key}={value!r} rejected: {exc}") from exc


def find_router(mission: Mission, name: str) -> RouterConfig:
    """The router ``name`` of ``mission``'s ``ground.routers`` (TransportError
    naming those it lists)."""
    routers = mission.ground.routers if mission.ground is not None else []
    for r in routers:
        if r.name == name:
            return r
    listed = ", ".join(r.name for r in routers) or "none"
    raise TransportError(
        f"mission {mission.mission!r} lists no router {name!r} (routers: {listed})"
    )


def link_endpoints(mission: Mission, endpoints: Sequence[str]) -> list[str]:
    """``endpoints`` as the mission's links run them: ``tcp/`` as ``tls/``
    when the mission runs mutual TLS (as its nodes' endpoints)."""
    if not mission.mtls:
        return list(endpoints)
    return ["tls/" + ep[4:] if ep.startswith("tcp/") else ep for ep in endpoints]


def router_config(
    mission: Mission,
    listen: Sequence[str],
    connect: Sequence[str],
    *,
    deployment: Deployment | None = None,
    name: str | None = None,
) -> zenoh.Config:
    """The zenoh config of router ``name`` of ``mission`` listening on
    ``listen`` and connecting to ``connect`` (module doc). The link settings
    are the nodes' (lease, low latency, batching: a link's two ends must
    agree); scouting is off (routers meet by their endpoints, across a WAN);
    ``deployment``: the mission's (the router's own identity,
    :func:`~zplatform.security.deploy.router_identity`, and the ACL).
    DeploymentError when the deployment secures the links and ``name`` is
    None, it has no certificate for the router, or the one it names is
    not the router's own (:func:`~zplatform.security.deploy.check_router_certificate`)."""
    t = mission.transport
    cfg = zenoh.Config()
    _insert(cfg, "mode", "router")
    _insert(cfg, "listen/endpoints", link_endpoints(mission, listen))
    _insert(cfg, "connect/endpoints", link_endpoints(mission, connect))
    _insert(cfg, "connect/timeout_ms", -1)
    _insert(cfg, "connect/exit_on_failure", False)
    _insert(cfg, "connect/retry", {"period_init_ms": 50, "period_max_ms": 1000})
    _insert(cfg, "scouting/multicast/enabled", False)
    _insert(cfg, "scouting/gossip/enabled", False)
    _insert(cfg, "transport/link/tx/lease", t.lease_ms)
    if lowlatency_for(mission):
        _insert(cfg, "transport/unicast/lowlatency", True)
        _insert(cfg, "transport/unicast/qos/enabled", False)
    _insert(cfg, "transport/link/tx/queue/batching/enabled", t.batching)
    if deployment is not None and tls_nodes(mission):
        if name is None:
            raise DeploymentError(
                "a router of a mission with mutual TLS presents its own certificate: name it "
                "(`zplatform router MISSION --name NAME`, a router of ground.routers; "
                "--listen/--connect replace its endpoints)",
                "$.nodes",
            )
        identity = router_identity(name)
        check_router_certificate(deployment, identity)
        for key, value in zenoh_settings(mission, deployment, identity).items():
            _insert(cfg, key, value)
    return cfg


def run_router(
    mission: Mission,
    listen: Sequence[str],
    connect: Sequence[str],
    *,
    stop: StopFlag | None = None,
    name: str | None = None,
) -> int:
    """Run router ``name`` (None: one the mission does not list, which a
    mission with mutual TLS refuses: it has no certificate) until ``stop``
    (SIGTERM, SIGINT, ``up`` closing its stdin). Prints ``READY`` once
    open; returns 0. Raises TransportError when the session cannot open (a
    port in use), DeploymentError for a mission with mutual TLS and no
    certificate of this router's own on this host."""
    if not listen and not connect:
        raise TransportError(f"router {name or 'router'}: give --listen and/or --connect endpoints")
    stop = stop or StopFlag()
    dep = require_deployment(mission)
    session = open_session(router_config(mission, listen, connect, deployment=dep, name=name))
    try:
        print("READY", flush=True)
        while not stop.is_set():
            stop.event.wait(0.5)
    finally:
        _close(session)
    return 0


def _close(session: zenoh.Session) -> None:
    """Close, waiting at most :data:`~.transport.SESSION_CLOSE_S` (as a node does)."""
    closer = threading.Thread(target=session.close, name="zenoh-close", daemon=True)
    closer.start()
    closer.join(SESSION_CLOSE_S)
