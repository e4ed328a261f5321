"""Mission files rewired for fault tests.

* :func:`relay_links`: put a :class:`~tests.faults.relay.FaultRelay` on the
  link from each chosen node to the CN of an (already port-rewritten)
  mission file. Gossip scouting is switched off in the file, so no node can
  learn the CN's real endpoint and bypass the relay (docs/architecture.md#zenoh: with
  gossip on, peers connect to each other by themselves), and the sync is
  pinned to zenoh (``transport.intra_host``), so it does not bypass the
  relay through shared memory either.
* :func:`plain_tcp_mission`: a copy of a mission on plain TCP, which the
  flood cases need (``floods.py``): the transport every flood test states,
  in this one place.
* :func:`netns_mission`: node number ``k`` (in the file's order) listens on
  ``tcp/<its host's address>:PORT+k`` of a bridged
  :class:`~tests.faults.netns.NetnsLab` (hosts may be shared); each non-CN
  node connects to the CN. Run the nodes with ``host.popen(["python", "-m",
  "zplatform", "node", path, name])``.
* :func:`mesh_mission`: the same on a mesh lab (one host per node): every
  node listens on each of its host's links and reaches each peer over the
  link the two share, so one pair can be cut apart.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from tests.faults.netns import NetnsHost
from tests.faults.relay import FaultRelay
from zplatform.config import relocate_mission
from zplatform.core.messages import lowlatency_for
from zplatform.mission.load import load_mission

PORT = 7447


def relay_links(
    path: str | Path,
    relay_factory: Callable[..., FaultRelay],
    nodes: Iterable[str],
    **plan: Any,
) -> dict[str, FaultRelay]:
    """Rewrite ``path`` in place: each node of ``nodes`` connects to the CN
    through a relay of its own (made by ``relay_factory(cn_endpoint, **plan)``).
    Returns ``{node: relay}``."""
    p = Path(path)
    raw = yaml.safe_load(p.read_text())
    cn_ep = raw["nodes"]["cn"]["listen"][0]
    relays: dict[str, FaultRelay] = {}
    # The relay frames messages as the mission's transport does.
    plan.setdefault("lowlatency", lowlatency_for(load_mission(p)))
    for name in nodes:
        relays[name] = relay_factory(cn_ep, **plan)
        raw["nodes"][name]["connect"] = [relays[name].endpoint]
    raw.setdefault("transport", {})["gossip_scouting"] = False
    # The sync too goes through the relays (over zenoh): on one host it
    # would take shared memory past them (transport.intra_host).
    raw["transport"]["intra_host"] = "zenoh"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return relays


def netns_mission(
    src: str | Path, dst: str | Path, hosts: Mapping[str, NetnsHost], port: int = PORT
) -> Path:
    """Copy mission ``src`` to ``dst`` with node ``n`` on ``hosts[n]``."""
    raw = yaml.safe_load(Path(src).read_text())
    relocate_mission(raw, src)  # the copy finds the mission's code from its own directory
    missing = set(raw["nodes"]) - set(hosts)
    if missing:
        raise ValueError(f"no host for nodes {sorted(missing)}")
    ports = {name: port + k for k, name in enumerate(raw["nodes"])}
    cn_ep = hosts["cn"].endpoint(ports["cn"])
    for name, node in raw["nodes"].items():
        node = node or {}
        node["listen"] = [hosts[name].endpoint(ports[name])]
        node["connect"] = [] if name == "cn" else [cn_ep]
        raw["nodes"][name] = node
    Path(dst).write_text(yaml.safe_dump(raw, sort_keys=False))
    return Path(dst)


def mesh_mission(
    src: str | Path, dst: str | Path, hosts: Mapping[str, NetnsHost], port: int = PORT
) -> Path:
    """Copy mission ``src`` to ``dst`` with node ``n`` on ``hosts[n]`` of a
    mesh :class:`~tests.faults.netns.NetnsLab` (one host per node): node
    number ``k`` listens on port ``PORT+k`` of each of its host's links, and
    connects to the nodes it connects to in ``src``, each at the address of
    the link between the two hosts. Cutting one link (``NetnsLab.set_pair``)
    then parts exactly those two nodes: no other route joins them."""
    raw = yaml.safe_load(Path(src).read_text())
    relocate_mission(raw, src)
    missing = set(raw["nodes"]) - set(hosts)
    if missing:
        raise ValueError(f"no host for nodes {sorted(missing)}")
    lab = next(iter(hosts.values())).lab
    if lab.topology != "mesh" or len({h.index for h in hosts.values()}) != len(hosts):
        raise ValueError("mesh_mission needs a mesh lab and a host of its own per node")
    ports = {name: port + k for k, name in enumerate(raw["nodes"])}
    owner = {
        ep: name for name, node in raw["nodes"].items() for ep in (node or {}).get("listen", [])
    }
    for name, node in raw["nodes"].items():
        node = node or {}
        i = hosts[name].index
        links = [h.index for h in lab.hosts if h.index != i]
        node["listen"] = [f"tcp/{lab.addr_of(i, seen_from=j)}:{ports[name]}" for j in links]
        node["connect"] = [
            f"tcp/{lab.addr_of(hosts[owner[ep]].index, seen_from=i)}:{ports[owner[ep]]}"
            for ep in node.get("connect", [])
        ]
        raw["nodes"][name] = node
    Path(dst).write_text(yaml.safe_dump(raw, sort_keys=False))
    return Path(dst)


def plain_tcp_mission(src: str | Path, dst: str | Path) -> Path:
    """Copy mission ``src`` to ``dst`` on plain TCP (endpoints as in ``src``;
    ``Cluster`` moves them to free ports), its ``pythonpath`` made absolute.

    The flood cases attack from a peer without any key, so they need a
    transport that lets such a peer in: with mutual TLS and the generated
    access control it gets no session at all, which hides what a flood
    does to the nodes. A mission with hazardous commands runs mutual TLS by
    default (``security.transport: auto``), so the copy opts out here
    (``plain``): every flood test states its transport in this one place.
    Raises ValueError for a mission whose endpoints are not ``tcp/``.
    """
    raw = yaml.safe_load(Path(src).read_text())
    relocate_mission(raw, src)
    raw.setdefault("security", {})["transport"] = "plain"
    for name, node in raw["nodes"].items():
        for ep in [*node.get("listen", []), *node.get("connect", [])]:
            if not ep.startswith("tcp/"):
                raise ValueError(f"{src}: node {name} uses {ep}; the flood cases need plain TCP")
    Path(dst).write_text(yaml.safe_dump(raw, sort_keys=False))
    return Path(dst)
