"""The messages a mission sends, as the transport must carry them: the
largest one, the form of the sync query, and whether zenoh's lowlatency
transport can carry them all.

Zenoh-free (the lockstep simulator asks the same questions as the live
nodes); :mod:`zplatform.runtime.transport` applies the answers to zenoh's config.
"""

from __future__ import annotations

from ..config import Mission
from ..errors import ConfigError
from .auth import TAG_LEN
from .codec import bundle_size, frame_overhead
from .datavector import Layout
from .events import MAX_TEXT

__all__ = [
    "LOWLATENCY_MAX_MESSAGE",
    "WILDCARD_MAX_BUNDLE",
    "check_intra_host",
    "check_lowlatency",
    "intra_host_mode",
    "largest_message",
    "lowlatency_for",
    "sync_bundle_size",
    "wildcard_sync_for",
]

#: The largest message a lowlatency mission may send. zenoh's lowlatency
#: transport cannot fragment: on zenoh 1.10 a put above about 48 KiB is
#: dropped without an error (tests/integration/test_lowlatency.py measures
#: the edge); a third of that leaves room for protocol overhead and a
#: future zenoh with a smaller buffer.
LOWLATENCY_MAX_MESSAGE = 16 * 1024


def largest_message(mission: Mission) -> int:
    """Bytes of the largest message the mission's nodes send (an upper bound).

    Telemetry (the CN's whole Data Vector in one frame) and every region
    frame, with frame overhead and authentication tag; a CCSDS downlink
    packet; an event record (text capped at :data:`zplatform.core.events.MAX_TEXT`).
    Bulk channels are unbounded here (their samples can be megabytes).
    """

    if mission.bulk:
        return max(ch.nbytes for ch in mission.bulk)
    sizes = [Layout.for_node(mission, "cn").size]
    sizes += [Layout.for_regions(mission, [r]).size for r in mission.region_names()]
    largest = max(n + frame_overhead(n) + TAG_LEN for n in sizes)
    if wildcard_sync_for(mission):
        largest = max(largest, sync_bundle_size(mission))
    if mission.downlink.ccsds:
        largest = max(largest, mission.downlink.max_data + 16)  # + primary and secondary headers
    return max(largest, 4 * MAX_TEXT + 512)  # an event: UTF-8 text, node, name, numbers


#: The largest sync bundle ``sync_query: auto`` sends as one wildcard query:
#: every DN receives the whole bundle, so it stays small.
WILDCARD_MAX_BUNDLE = 4 * 1024


#: Zenoh 1.x moves a message through shared memory only above this size
#: (``transport/shared_memory/transport_optimization/message_size_threshold``,
#: its default): a node whose messages are all smaller gains nothing from it.
SHM_MESSAGE_THRESHOLD = 3 * 1024


def shared_memory_for(mission: Mission, node: str | None) -> bool:
    """Whether ``node`` needs zenoh shared memory: it owns or reads a bulk
    channel, or one of its region frames is over
    :data:`SHM_MESSAGE_THRESHOLD`; the ground node never does. A node with it
    on maps the whole pool (16 MiB) of every same-host peer that sends it a
    large payload and keeps it mapped after the peer has gone
    (bench.ground_memory), so a long-running node has it only where it helps;
    ``None`` (a tool: short-lived, and ``tap`` shows a bulk sample's path) has.
    """
    if node is None:
        return True
    if node == "gn" or node not in mission.nodes:
        return False
    if any(node == ch.node or node in ch.readers for ch in mission.bulk):
        return True
    regions = mission.node_regions(node)
    sizes = [Layout.for_regions(mission, [r]).size for r in regions]
    return any(n + frame_overhead(n) + TAG_LEN > SHM_MESSAGE_THRESHOLD for n in sizes)


def sync_bundle_size(mission: Mission) -> int:
    """Bytes of the mission's sync bundle (every ``cn_to_dnX`` frame, authenticated)."""

    tag = TAG_LEN if mission.security.auth else 0
    sizes = []
    for dn in mission.device_nodes:
        n = Layout.for_regions(mission, [f"cn_to_{dn}"]).size
        sizes.append(n + frame_overhead(n) + tag)
    return bundle_size(sizes)


def wildcard_sync_for(mission: Mission) -> bool:
    """Whether the CN sends one wildcard sync query per loop (else one per DN).

    ``transport.sync_query`` is ``per_node`` by default (it measured faster:
    :class:`zplatform.config.TransportConfig`). ``auto``: wildcard for two or
    more DNs while :func:`sync_bundle_size` is within
    :data:`WILDCARD_MAX_BUNDLE`. ``wildcard``/``per_node`` as given (a DN
    accepts either form always).
    """
    mode = mission.transport.sync_query
    if mode == "auto":
        return len(mission.device_nodes) >= 2 and sync_bundle_size(mission) <= WILDCARD_MAX_BUNDLE
    return mode == "wildcard" and bool(mission.device_nodes)


def lowlatency_for(mission: Mission) -> bool:
    """Whether the mission's sessions use zenoh's lowlatency transport.

    ``transport.lowlatency`` is off by default (a stalled link blocks the
    sending thread: :class:`zplatform.config.TransportConfig`). ``auto``: on
    when no bulk channel is configured and :func:`largest_message` is
    within :data:`LOWLATENCY_MAX_MESSAGE`; off otherwise. ``true``/``false``
    as given (:func:`check_lowlatency` refuses ``true`` where a message may
    not fit).
    """
    ll = mission.transport.lowlatency
    if ll == "auto":
        return not mission.bulk and largest_message(mission) <= LOWLATENCY_MAX_MESSAGE
    return bool(ll)


def check_lowlatency(mission: Mission) -> None:
    """Raise ConfigError at ``transport.lowlatency`` for ``true`` on a mission
    with a message the lowlatency transport would drop."""
    if mission.transport.lowlatency is not True:
        return
    if mission.bulk:
        raise ConfigError(
            "lowlatency cannot carry bulk channels (zenoh's lowlatency transport does not"
            " fragment): use auto or false",
            "$.transport.lowlatency",
        )
    n = largest_message(mission)
    if n > LOWLATENCY_MAX_MESSAGE:
        raise ConfigError(
            f"lowlatency cannot carry this mission: its largest message is {n} B, over"
            f" {LOWLATENCY_MAX_MESSAGE} B (zenoh's lowlatency transport does not fragment"
            " and drops bigger ones): use auto or false",
            "$.transport.lowlatency",
        )


def intra_host_mode(mission: Mission, dn: str | None = None) -> str:
    """``transport.intra_host`` as the sync takes it for ``dn``'s link
    (``intra_host_links``' entry, else the mission's), or with ``dn`` None
    for the mission (``zenoh`` only when every link's is): ``zenoh`` for a
    redundant mission (failover syncs over zenoh) or one without device
    nodes, else ``auto``, ``zenoh`` or ``shm``."""
    t = mission.transport
    if mission.standby is not None or not mission.device_nodes:
        return "zenoh"
    if dn is not None:
        return t.intra_host_links.get(dn, t.intra_host)
    modes = {t.intra_host_links.get(d, t.intra_host) for d in mission.device_nodes}
    return "zenoh" if modes == {"zenoh"} else ("shm" if "shm" in modes else "auto")


def check_intra_host(mission: Mission) -> None:
    """Raise ConfigError at ``transport.intra_host`` (or the link's entry)
    for ``shm`` on a redundant mission (its standby and takeovers sync over
    zenoh), and for a link entry that names no device node."""
    t = mission.transport
    for dn, mode in t.intra_host_links.items():
        if dn not in mission.device_nodes:
            raise ConfigError(
                f"intra_host_links: {dn!r} is not a device node ({mission.device_nodes})",
                f"$.transport.intra_host_links.{dn}",
            )
        if mode == "shm" and mission.standby is not None:
            raise ConfigError(
                "a redundant mission (failover) syncs over zenoh: intra_host shm cannot be "
                "pinned, use auto or zenoh",
                f"$.transport.intra_host_links.{dn}",
            )
    if t.intra_host == "shm" and mission.standby is not None:
        raise ConfigError(
            "a redundant mission (failover) syncs over zenoh: intra_host shm cannot be "
            "pinned, use auto or zenoh",
            "$.transport.intra_host",
        )
