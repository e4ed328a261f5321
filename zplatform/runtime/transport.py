"""Zenoh transport: session config, the key space, readiness, event publishing.

Every node is a zenoh *peer*; its ``zenoh.Config`` is built here from the
mission alone (endpoints, scouting, lease, low latency, shared memory), so
one file runs on one host or across hosts. A tool (``tap``, ``cmd``, ``log``)
listens nowhere and connects to every node. TLS and access control come
from the deployment (:mod:`zplatform.security.deploy`). One dialer per pair: zenoh
ids are ordered by the connect lists (:func:`dial_ranks`, :func:`zid_for`),
a node dials every node below it and scouting autoconnects only to a lower
id, so no two nodes dial each other (eclipse-zenoh/zenoh#2806).

Contract: :func:`zenoh_config` is pure but for the random part of the zenoh
id; opening a :class:`NodeSession` blocks on zenoh and raises
:class:`~zplatform.errors.TransportError` (or a deployment error) when it
cannot; its close waits at most :data:`SESSION_CLOSE_S`. Readiness is
explicit: liveliness tokens on ``{vehicle}/{node}/alive`` and
:func:`wait_for_nodes` (TransportError naming the missing ones at its
timeout). :class:`EventPublisher` puts any node's events. docs/architecture.md#zenoh.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import secrets
import socket
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
import zenoh

from ..config import STANDBY, Mission, relocate_mission
from ..control.handoff import Handoff
from ..core.events import EventLog, Severity, encode_event
from ..core.messages import lowlatency_for, shared_memory_for
from ..errors import TransportError
from ..security.deploy import Deployment, check_tool_may_command, require_deployment, zenoh_settings
from ..security.keyspace import key_of

if TYPE_CHECKING:
    from ..core.auth import Channel
    from ..recorder.writer import FlightRecorder

__all__ = [
    "EventPublisher",
    "KeySpace",
    "NodeSession",
    "apply_deployment",
    "dial_below",
    "dial_ranks",
    "dials",
    "free_port",
    "is_matching",
    "open_session",
    "rewrite_endpoints",
    "wait_for_nodes",
    "zenoh_config",
    "zid_for",
]


@dataclass(frozen=True, slots=True)
class KeySpace:
    """The keys of docs/architecture.md#key-space for one vehicle prefix,
    each built from its row of :data:`zplatform.security.keyspace.KEYSPACE` (the one
    table of the key space; a key without a row cannot be built). Builds
    a new string per call: take keys once, when declaring."""

    vehicle: str

    def dn_to_cn(self, dn: str) -> str:
        return key_of("dn_to_cn", self.vehicle, dn=dn)

    @property
    def sync_all(self) -> str:
        """The wildcard sync query's key: every ``dnX/to_cn`` at once."""
        return key_of("sync_all", self.vehicle)

    def cn_to_dn(self, dn: str) -> str:
        return key_of("cn_to_dn", self.vehicle, dn=dn)

    @property
    def telemetry(self) -> str:
        return key_of("telemetry", self.vehicle)

    @property
    def downlink(self) -> str:
        """CCSDS space packets of the radio downlink (one sample per packet)."""
        return key_of("downlink", self.vehicle)

    @property
    def gn_to_cn(self) -> str:
        return key_of("gn_to_cn", self.vehicle)

    @property
    def recorder(self) -> str:
        """The CN's flight recorder: a queryable answering gap-fill requests."""
        return key_of("recorder", self.vehicle)

    @property
    def archive(self) -> str:
        """The ground archive: the ground node's queryable answering archive queries."""
        return key_of("archive", self.vehicle)

    def events(self, node: str) -> str:
        return key_of("events", self.vehicle, node=node)

    @property
    def all_events(self) -> str:
        return key_of("all_events", self.vehicle)

    @property
    def clock(self) -> str:
        return key_of("clock", self.vehicle)

    def alive(self, node: str) -> str:
        return key_of("alive", self.vehicle, node=node)

    def standby(self, node: str) -> str:
        """A control node's liveliness token while it follows as a ready standby."""
        return key_of("standby", self.vehicle, cn=node)

    def health_probe(self, node: str) -> str:
        """The node's own zenoh probe (zplatform.node.health): local to its session."""
        return key_of("health_probe", self.vehicle, node=node)

    @property
    def all_alive(self) -> str:
        return key_of("all_alive", self.vehicle)

    def region(self, region: str) -> str:
        """The key a region travels on (docs/architecture.md#key-space): ``cn_to_dnX`` ->
        ``cn/to_dnX``, ``dnX_to_cn`` -> ``dnX/to_cn``, ``gn_to_cn`` -> ``gn/to_cn``."""
        src, sep, dst = region.partition("_to_")
        if not sep or not src or not dst:
            raise TransportError(f"{region!r} is not a sync region (src_to_dst)")
        if region == "gn_to_cn":
            return self.gn_to_cn
        if src == "cn":
            return self.cn_to_dn(dst)
        if dst == "cn":
            return self.dn_to_cn(src)
        raise TransportError(f"{region!r} is not a sync region (cn_to_dnX, dnX_to_cn, gn_to_cn)")

    @property
    def everything(self) -> str:
        return key_of("everything", self.vehicle)

    @property
    def mirror(self) -> str:
        """The commanding control node's whole Data Vector, every loop, for the
        standby (zplatform.control.failover)."""
        return key_of("mirror", self.vehicle)

    def probe(self, dn: str) -> str:
        """A device node's probe queryable (zplatform.control.fencing)."""
        return key_of("probe", self.vehicle, dn=dn)

    def bulk(self, owner: str, channel: str) -> str:
        """A bulk channel's samples (zplatform.runtime.bulk)."""
        return key_of("bulk", self.vehicle, owner=owner, channel=channel)


def _insert(cfg: zenoh.Config, key: str, value: Any) -> None:
    try:
        cfg.insert_json5(key, json.dumps(value))
    except Exception as exc:  # zenoh raises ZError; keep the key in the message
        raise TransportError(f"zenoh config {key}={value!r} rejected: {exc}") from exc


def dial_ranks(mission: Mission) -> dict[str, int]:
    """Each node's place in the mission's dialing order, 1 to ``len(nodes)``:
    a node ranks above every node it connects to (an endpoint in its
    ``connect`` that is another node's ``listen``), nodes the connect lists
    leave unordered by name. Pure.

    Why: two peers that dial each other can leave their zenoh session split
    after one of them stalls (eclipse-zenoh/zenoh#2806); with each node's
    zenoh id ordered by this rank (:func:`zid_for`) and gossip's
    ``autoconnect_strategy`` ``greater-zid``, zenoh's own dialing goes the
    way the connect lists go, so every pair is dialed one way only
    (docs/architecture.md#failover). Raises TransportError, naming the
    nodes, when the connect lists dial in a circle (a pair both ways).
    """
    owner = {ep: name for name, n in mission.nodes.items() for ep in n.listen}
    targets = {
        name: {owner[ep] for ep in n.connect if ep in owner and owner[ep] != name}
        for name, n in mission.nodes.items()
    }
    ranks: dict[str, int] = {}
    while len(ranks) < len(targets):
        ready = sorted(n for n, t in targets.items() if n not in ranks and t <= ranks.keys())
        if not ready:
            left = sorted(n for n in targets if n not in ranks)
            both = [
                f"{a} and {b}"
                for a in left
                for b in sorted(targets[a])
                if a < b and a in targets[b]
            ]
            what = ", ".join(both) if both else f"{left} (in a circle)"
            raise TransportError(
                f"mission {mission.mission!r}: nodes {what} connect to each other; "
                "let one node of each pair connect to the other, never both ways"
            )
        ranks[ready[0]] = len(ranks) + 1
    return ranks


_RANK_MAX = 255  # the zenoh id's lowest byte


def zid_for(rank: int, high: int | None = None) -> str:
    """A fresh zenoh id (hex, at most 32 digits) that orders by ``rank`` (1..255)
    under zenoh's ``greater-zid`` rule: zenoh compares ids by their
    little-endian bytes (``uhlc::ID`` derives ``Ord`` over ``to_le_bytes``),
    so the rank goes in the lowest byte, first compared; the other 15 bytes
    are random, so a restarted node is a new peer to zenoh (never merged
    into its old session). ``high``: those 15 bytes (tests), else random.
    Raises TransportError for a rank out of range."""
    if not 1 <= rank <= _RANK_MAX:
        raise TransportError(f"a mission has at most {_RANK_MAX} nodes (zenoh id rank {rank})")
    rest = secrets.randbits(120) if high is None else high & ((1 << 120) - 1)
    return f"{rest << 8 | rank:x}"  # zenoh refuses leading zeros


def dial_below(mission: Mission, node: str, connect: list[str]) -> list[str]:
    """The listen endpoints of every node ranked below ``node``
    (:func:`dial_ranks`) that ``connect`` does not hold: where a mission
    with scouting on (every pair meets) has ``node`` dial by itself. Gossip
    alone is not enough: it tells a newcomer only the peers its introducer
    knows at that moment, so two nodes that join together may never link,
    and with ``greater-zid`` only the higher one may dial. Pure."""
    ranks = dial_ranks(mission)
    return [
        ep
        for other, n in mission.nodes.items()
        if ranks[other] < ranks[node]
        for ep in n.listen
        if ep not in connect
    ]


def dials(mission: Mission) -> set[tuple[str, str]]:
    """Every ``(a, b)``: node ``a``'s zenoh dials node ``b`` in the session
    configs :func:`zenoh_config` builds (its connect list; with scouting on,
    every node below it that listens, :func:`dial_below`, as scouting's
    ``greater-zid`` autoconnect also would). Pure; for checks and tests: no
    pair is in both directions."""
    ranks = dial_ranks(mission)
    owner = {ep: name for name, n in mission.nodes.items() for ep in n.listen}
    out = {
        (name, owner[ep])
        for name, n in mission.nodes.items()
        for ep in n.connect
        if ep in owner and owner[ep] != name
    }
    if mission.transport.gossip_scouting or mission.transport.multicast_scouting:
        out |= {
            (a, b)
            for a in mission.nodes
            for b, nb in mission.nodes.items()
            if a != b and nb.listen and ranks[a] > ranks[b]
        }
    return out


GROUND_NODE = "gn"
"""The ground node's name: its session never takes shared memory (:func:`zenoh_config`)."""


def zenoh_config(
    mission: Mission,
    node: str | None,
    *,
    lowlatency: bool | None = None,
    shared_memory: bool | None = None,
    deployment: Deployment | None = None,
    via: list[str] | None = None,
) -> zenoh.Config:
    """A peer config for ``node`` (``None``: a tool connecting to every node).

    ``via`` (a tool only): a station's router endpoints
    (``ground.stations[].connect``): the tool is then a zenoh *client* of
    that router alone, and reaches the vehicle through it
    (:mod:`zplatform.runtime.router`); ``tcp/`` runs as ``tls/`` in a mission
    with mutual TLS.

    ``lowlatency``/``shared_memory`` override the mission's transport section
    (benchmark variants); the ground node's (:data:`GROUND_NODE`) shared
    memory is off whatever they say. ``deployment``: TLS and access control
    (:func:`apply_deployment`); this function never reads the environment,
    and without a deployment the config of an mTLS mission presents no
    certificate (so it can open no link: what an unknown peer gets).
    Raises TransportError if zenoh rejects a setting, DeploymentError if the
    deployment has no identity for ``node``.
    """
    t = mission.transport
    cfg = zenoh.Config()
    if via is not None and node is not None:
        raise TransportError(f"node {node!r} connects by its own endpoints, not through a router")
    _insert(cfg, "mode", "peer" if via is None else "client")
    listen: list[str] = []
    connect: list[str]
    if via is not None:
        connect = ["tls/" + ep[4:] if mission.mtls and ep.startswith("tcp/") else ep for ep in via]
    elif node is None:
        connect = [ep for n in mission.nodes.values() for ep in n.listen]
    else:
        if node not in mission.nodes:
            raise TransportError(f"no node {node!r} in mission {mission.mission!r}")
        listen = list(mission.nodes[node].listen)
        connect = list(mission.nodes[node].connect)
        if t.gossip_scouting or t.multicast_scouting:
            connect += dial_below(mission, node, connect)
    _insert(cfg, "listen/endpoints", listen)
    _insert(cfg, "connect/endpoints", connect)
    # Keep retrying connects: peers start in any order. A short retry period
    # lets a restarted node rejoin in ms instead of ~1 s (bench/ZENOH_API.md).
    _insert(cfg, "connect/timeout_ms", -1)
    _insert(cfg, "connect/exit_on_failure", False)
    _insert(cfg, "connect/retry", {"period_init_ms": 50, "period_max_ms": 200})
    _insert(cfg, "scouting/multicast/enabled", t.multicast_scouting)
    _insert(cfg, "scouting/gossip/enabled", t.gossip_scouting)
    # One dialer per pair (dial_ranks): zenoh's gossip dials only a peer of
    # a lower id, and a node's id orders by its rank in the connect lists. A
    # tool listens nowhere: nobody dials it, whatever its (random) id.
    one_way = {"peer": {"to_peer": "greater-zid"}}
    _insert(cfg, "scouting/gossip/autoconnect_strategy", one_way)
    _insert(cfg, "scouting/multicast/autoconnect_strategy", one_way)
    if node is not None:
        _insert(cfg, "id", zid_for(dial_ranks(mission)[node]))
        # A node's open does not wait for the nodes it dials: it waits for
        # the peers it needs by liveliness (wait_for_nodes), and zenoh's wait
        # cost each start-up its scouting delay (500 ms) whenever a dialed
        # node was not listening yet, as at every `up`. A tool keeps the
        # wait: it sends at once, to nodes already running.
        _insert(cfg, "open/return_conditions/connect_scouted", False)
    _insert(cfg, "transport/link/tx/lease", t.lease_ms)
    ll = lowlatency_for(mission) if lowlatency is None else lowlatency
    if ll:
        # lowlatency needs QoS off (zenoh refuses the pair otherwise).
        _insert(cfg, "transport/unicast/lowlatency", True)
        _insert(cfg, "transport/unicast/qos/enabled", False)
    _insert(cfg, "transport/link/tx/queue/batching/enabled", t.batching)
    # Only where it helps (core.messages.shared_memory_for): zenoh maps a
    # same-host peer's whole shared-memory pool (16 MiB) the first time that
    # peer sends a payload over 3 KiB, and keeps it mapped after the peer has
    # gone; a keyless peer that connects, puts 4 KiB of junk on an event key,
    # and leaves, over and over, grew a node by 16-19 MB each time
    # (bench.ground_memory). Never for the ground node, whatever the
    # override: it reads no bulk channel and sits on another host in flight.
    if shared_memory is None:
        shm = t.shared_memory and shared_memory_for(mission, node)
    else:
        shm = shared_memory
    if node == GROUND_NODE:
        shm = False
    _insert(cfg, "transport/shared_memory/enabled", shm)
    if deployment is not None:
        apply_deployment(cfg, mission, node, deployment)
    return cfg


def apply_deployment(
    cfg: zenoh.Config, mission: Mission, node: str | None, deployment: Deployment
) -> None:
    """Add the deployment's zenoh pieces for ``node`` to ``cfg``: mutual TLS
    with the node's cert (or the tool's, for ``None``) and the access-control
    list (:func:`zplatform.security.deploy.zenoh_settings`). Nothing for a mission
    without tls endpoints."""
    for key, value in zenoh_settings(mission, deployment, node).items():
        _insert(cfg, key, value)


def open_session(cfg: zenoh.Config) -> zenoh.Session:
    """Open a zenoh session; raises TransportError (e.g. a port in use)."""
    try:
        return zenoh.open(cfg)
    except Exception as exc:
        raise TransportError(f"cannot open zenoh session: {exc}") from exc


SESSION_CLOSE_S = 3.0
"""The longest :meth:`NodeSession.close` waits for zenoh's session close."""

_left_open = 0
_log = logging.getLogger("zplatform.transport")


def sessions_left_open() -> int:
    """Sessions whose close did not finish within :data:`SESSION_CLOSE_S`
    in this process (a node process then ends with ``os._exit``, see
    ``zplatform node``)."""
    return _left_open


class NodeSession:
    """A node's zenoh session plus its liveliness token. Context manager.

    ``close()`` undeclares the token first so peers see the node leave at
    once, then closes the session; it is idempotent. It blocks at most
    :data:`SESSION_CLOSE_S` for zenoh's close (a mutual-TLS close handshake
    on a busy host can take zenoh's own 10 s timeout, eclipse-zenoh/zenoh
    issue 2675, longer than the stop grace ``up`` gives a node); a close
    still under way then is left running, logged, and counted by
    :func:`sessions_left_open`, so that a node process can end without it.

    ``deployment``: TLS and access control; when not given, the mission's
    own (:func:`zplatform.security.deploy.require_deployment`): DeploymentError, and
    no session, for an mTLS mission without one or with one that does not fit.
    ``commands``: the session will put operator commands; a tool's
    (``node`` None) then needs a deployment whose tool may command, else
    DeploymentError before anything opens (the nodes' access control would
    drop every request without a word).
    """

    def __init__(
        self,
        mission: Mission,
        node: str | None,
        *,
        announce: bool = True,
        deployment: Deployment | None = None,
        commands: bool = False,
        **overrides: Any,
    ) -> None:
        self.mission = mission
        self.node = node
        self.keys = KeySpace(mission.vehicle)
        dep = deployment if deployment is not None else require_deployment(mission)
        if commands and node is None and dep is not None and mission.mtls:
            check_tool_may_command(dep)
        self.session = open_session(zenoh_config(mission, node, deployment=dep, **overrides))
        self._token: zenoh.LivelinessToken | None = None
        self._closed = False
        if announce:
            self.announce()

    def announce(self) -> None:
        """Declare this node's liveliness token (once it is ready to serve)."""
        if self.node is not None and self._token is None:
            self._token = self.session.liveliness().declare_token(self.keys.alive(self.node))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:  # already gone with the session: nothing to do
                pass
        closer = threading.Thread(target=self.session.close, name="zenoh-close", daemon=True)
        closer.start()
        closer.join(SESSION_CLOSE_S)
        if closer.is_alive():
            global _left_open
            _left_open += 1
            _log.warning(
                "%s: zenoh's session close did not finish within %g s; left to the process's exit",
                self.node or "tool",
                SESSION_CLOSE_S,
            )

    def __enter__(self) -> NodeSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventPublisher:
    """Publishes a node's events on ``{vehicle}/{node}/events``.

    Call :meth:`flush` once per loop: it costs one int compare when nothing
    was emitted, and events are rare (state changes, verdicts, failures).
    Events are also written to the node's log (stderr) for the operator.
    ``seal``: the node's ``events_<node>`` channel, which tags each record
    (None: the mission does not authenticate). Given a ``recorder`` (the
    node's flight recorder), each record is also kept on board, untagged:
    the recorder's own checksums guard it there.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        events: EventLog,
        seal: Channel | None,
        recorder: FlightRecorder | None = None,
    ) -> None:
        self.events = events
        self._seal = seal
        self.recorder = recorder
        # DROP: a subscriber on a stalled link must never block the loop
        # that flushes events; each event is also in this node's own log.
        self._pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self._seen = 0

    def flush(self) -> None:
        if self.events.emitted == self._seen:
            return
        self._seen = self.events.emitted
        seal = self._seal
        rec = self.recorder
        for e in self.events.drain():
            record = encode_event(e)
            self._pub.put(bytes(seal.seal(record)) if seal is not None else record)
            if rec is not None:
                rec.event(record)
            _event_log.log(_LEVELS.get(e.severity, logging.INFO), "%s %s: %s", e.node, e.id, e.text)

    def undeclare(self) -> None:
        self.flush()
        self._pub.undeclare()


_event_log = logging.getLogger("zplatform.node")
"""Where published events are also logged: the node's own log."""

_LEVELS: dict[int, int] = {
    Severity.DIAGNOSTIC: logging.DEBUG,
    Severity.ACTIVITY_LO: logging.INFO,
    Severity.ACTIVITY_HI: logging.INFO,
    Severity.COMMAND: logging.INFO,
    Severity.WARNING_LO: logging.WARNING,
    Severity.WARNING_HI: logging.ERROR,
    Severity.FATAL: logging.CRITICAL,
}


def wait_for_nodes(
    session: zenoh.Session,
    keys: KeySpace,
    nodes: Iterable[str],
    timeout_s: float,
    stop: threading.Event | None = None,
    *,
    any_of: bool = False,
) -> set[str]:
    """Block until every node in ``nodes`` has a liveliness token (``any_of``:
    until at least one has, as a device node waits for whichever control
    node runs).

    Returns the set of alive nodes among ``nodes``. Raises TransportError
    naming the missing nodes when ``timeout_s`` passes (or ``stop`` is set)
    first.
    """
    want = set(nodes)
    alive: set[str] = set()
    q: Handoff[tuple[str, bool]] = Handoff()

    def on_sample(s: zenoh.Sample) -> None:  # hand off only
        q.put((str(s.key_expr), s.kind == zenoh.SampleKind.PUT))

    def done() -> bool:
        return bool(want & alive) if any_of else want <= alive

    sub = session.liveliness().declare_subscriber(
        keys.all_alive, zenoh.handlers.Callback(on_sample, indirect=False), history=True
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not done():
            left = deadline - time.monotonic()
            if left <= 0 or (stop is not None and stop.is_set()):
                raise TransportError(
                    f"none of {sorted(want)} alive after {timeout_s:g} s"
                    if any_of
                    else f"nodes not alive after {timeout_s:g} s: {sorted(want - alive)}"
                )
            try:
                key, up = q.get(timeout=min(left, 0.2))
            except queue.Empty:
                continue
            name = key.split("/")[-2]
            if up:
                alive.add(name)
            else:
                alive.discard(name)
        return want & alive
    finally:
        sub.undeclare()


def is_matching(entity: zenoh.Publisher | zenoh.Querier) -> bool:
    """Whether anyone matches this publisher/querier now.

    zenoh-python 1.10's stub says ``matching_status`` is a bool; at run time
    it is a ``MatchingStatus`` with a ``matching`` attribute. Accept both.
    """
    status: Any = entity.matching_status
    return bool(getattr(status, "matching", status))


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rewrite_endpoints(src: str | Path, dst: str | Path, host: str = "127.0.0.1") -> dict[str, int]:
    """Copy mission ``src`` to ``dst`` with every node on a fresh free port.

    Each node listens on ``tcp/{host}:{port}``; each non-CN node connects to
    the CN. The copy's ``pythonpath`` is made absolute
    (:func:`~zplatform.config.relocate_mission`), so it finds the mission's
    code wherever ``dst`` is. A vehicle world gets a free UDP port (``world``
    in the result), and each pty it serves (``serve_serial``) a path beside
    ``dst``, which the node's serial board follows. Returns ``{node: port}``.
    For running a shipped mission beside another one (tests, benchmarks)
    without clashes.
    """
    raw = yaml.safe_load(Path(src).read_text())
    relocate_mission(raw, src)
    nodes = raw.get("nodes") or {}
    world = raw.get("world")
    # Hold every socket until all are bound: ports picked one after the other
    # (each socket closed at once) may come back twice from the OS.
    with contextlib.ExitStack() as stack:
        ports = {}
        for name in nodes:
            s = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
            s.bind(("127.0.0.1", 0))
            ports[name] = int(s.getsockname()[1])
        if isinstance(world, dict):
            s = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            s.bind(("127.0.0.1", 0))
            ports["world"] = int(s.getsockname()[1])
            world["listen"] = f"127.0.0.1:{ports['world']}"
            for n in list(world.get("serve_serial") or {}):
                link = str(Path(dst).resolve().parent / f"{Path(dst).stem}-{n}.pty")
                world["serve_serial"][n] = link
                if isinstance(nodes.get(n), dict) and isinstance(nodes[n].get("board"), dict):
                    nodes[n]["board"]["port"] = link
    cn_ep = f"tcp/{host}:{ports['cn']}" if "cn" in ports else None
    # A standby control node is connected to by every node too, so the mesh
    # outlives cn (the device nodes, the ground and tools keep reaching it).
    sb_ep = f"tcp/{host}:{ports[STANDBY]}" if STANDBY in ports else None
    for name, node in nodes.items():
        node = node or {}
        node["listen"] = [f"tcp/{host}:{ports[name]}"]
        connect = [] if name == "cn" or cn_ep is None else [cn_ep]
        if sb_ep is not None and name not in ("cn", STANDBY):
            connect.append(sb_ep)
        node["connect"] = connect
        nodes[name] = node
    Path(dst).write_text(yaml.safe_dump(raw, sort_keys=False))
    return ports
