"""Fixtures of the fault-injection suite (README.md).

* ``fault_relay``: a factory ``fault_relay(upstream_endpoint, **plan) ->
  FaultRelay``; every relay it made is closed after the test.
* ``netns_hosts``: a factory ``netns_hosts(n, topology="bridge") ->
  list[NetnsHost]``; skips the test (with the reason) when not root or
  without ``ip``; every namespace and process is removed after the test, even
  on failure.
* ``zenoh_pair``: two in-process peers, ``a`` listening on a free loopback
  port and ``b`` connected to it through a fresh relay.

Every test in this directory gets the ``faults`` marker.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh

from tests.faults.netns import NetnsHost, NetnsLab, netns_unavailable
from tests.faults.peers import ECHO_KEY, echo, peer_config
from tests.faults.relay import FaultRelay
from zplatform.runtime.transport import free_port


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if "tests/faults/" in item.nodeid.replace("\\", "/"):
            item.add_marker(pytest.mark.faults)


@pytest.fixture
def fault_relay() -> Iterator[Callable[..., FaultRelay]]:
    made: list[FaultRelay] = []

    def make(upstream: str, **kw: Any) -> FaultRelay:
        r = FaultRelay(upstream, **kw)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()


@pytest.fixture
def netns_hosts() -> Iterator[Callable[..., list[NetnsHost]]]:
    why = netns_unavailable()
    if why is not None:
        pytest.skip(why)
    labs: list[NetnsLab] = []

    def make(n: int, topology: str = "bridge") -> list[NetnsHost]:
        lab = NetnsLab(n, topology)
        labs.append(lab)
        return lab.hosts

    try:
        yield make
    finally:
        for lab in labs:
            lab.close()


@dataclass
class ZenohPair:
    """``a`` serves :data:`ECHO_KEY`; ``b`` reaches ``a`` only through ``relay``."""

    a: zenoh.Session
    b: zenoh.Session
    relay: FaultRelay
    queryable: Any


def open_pair(relay_factory: Callable[..., FaultRelay], proto: str, **plan: Any) -> ZenohPair:
    """``proto``: ``tcp``, ``udp``, or ``tcp+lowlatency`` (zenoh's lowlatency transport)."""
    proto, _, variant = proto.partition("+")
    ll = variant == "lowlatency"
    if ll:
        plan["lowlatency"] = True
    ep = f"{proto}/127.0.0.1:{free_port()}"
    a = zenoh.open(peer_config([ep], lowlatency=ll))
    try:
        q = a.declare_queryable(ECHO_KEY, echo)
        relay = relay_factory(ep, **plan)
        b = zenoh.open(peer_config(connect=[relay.endpoint], lowlatency=ll))
    except BaseException:
        a.close()
        raise
    return ZenohPair(a, b, relay, q)


@pytest.fixture
def zenoh_pair(fault_relay: Callable[..., FaultRelay]) -> Iterator[Callable[..., ZenohPair]]:
    pairs: list[ZenohPair] = []

    def make(proto: str = "tcp", **plan: Any) -> ZenohPair:
        p = open_pair(fault_relay, proto, **plan)
        pairs.append(p)
        return p

    yield make
    for p in pairs:
        p.b.close()
        p.a.close()
