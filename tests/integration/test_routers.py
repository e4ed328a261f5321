"""Stations through zenoh routers (zplatform.runtime.router), in this process,
on loopback, over mutual TLS with the deployment's access control: a ``cn``
peer session (its node's config), a pad router connected to it, a
control-room router connected to the pad router, and a station tool that
reaches the vehicle as a zenoh client of the room router
(``ground.stations[].connect``; the tool's certificate).

* The station gets the CN's telemetry through both routers, its run hello
  on ``{vehicle}/cn/clock`` is answered by the CN, and its request on
  ``{vehicle}/gn/to_cn`` reaches the CN's subscriber.
* A router forwards, nothing more: a peer presenting the router's
  certificate, connected to the CN, declares a queryable on dn0's sync key
  and a subscriber on the CN's mirror (what a standby follows); the CN's
  sync query never reaches it, and no mirror sample is routed to it.
"""

from __future__ import annotations

import queue
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.pki import make_test_pki
from zplatform.mission.load import decode_mission
from zplatform.runtime.router import find_router, router_config
from zplatform.runtime.transport import free_port, open_session, zenoh_config
from zplatform.security.deploy import ROUTER

pytestmark = pytest.mark.timeout(120)

V = "rocket"


def _mission(cn: int, pad: int, room: int) -> Any:
    return decode_mission(f"""
mission: routed
security: {{transport: mtls}}
nodes:
  cn:  {{listen: ['tls/127.0.0.1:{cn}']}}
  dn0: {{connect: ['tls/127.0.0.1:{cn}']}}
  gn:  {{connect: ['tls/127.0.0.1:{cn}']}}
transport: {{gossip_scouting: false, multicast_scouting: false}}
regions:
  dn0_to_cn:
    - {{name: v, type: f64}}
ground:
  stations:
    - {{name: pad}}
    - {{name: room, connect: ['tcp/127.0.0.1:{room}']}}
  operators:
    - {{name: fd, roles: [flight_director]}}
  routers:
    - {{name: pad, listen: ['tcp/127.0.0.1:{pad}'], connect: ['tcp/127.0.0.1:{cn}']}}
    - {{name: room, listen: ['tcp/127.0.0.1:{room}'], connect: ['tcp/127.0.0.1:{pad}']}}
""")


@pytest.fixture
def net(tmp_path: Path) -> Iterator[tuple[Any, dict[str, zenoh.Session]]]:
    m = _mission(free_port(), free_port(), free_port())
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", ROUTER], may_command=True)
    opened: dict[str, zenoh.Session] = {}
    try:
        opened["cn"] = open_session(zenoh_config(m, "cn", deployment=dep))
        for name in ("pad", "room"):
            r = find_router(m, name)
            opened[name] = open_session(router_config(m, r.listen, r.connect, deployment=dep))
        room = m.ground.stations[1].connect
        opened["station"] = open_session(zenoh_config(m, None, deployment=dep, via=room))
        # A peer with the router's certificate, straight on the CN.
        cn_ep = m.nodes["cn"].listen
        opened["rogue"] = open_session(router_config(m, [], cn_ep, deployment=dep))
        yield m, opened
    finally:
        for s in reversed(opened.values()):
            s.close()


def _until(put: Any, got: queue.SimpleQueue[bytes], tag: bytes) -> None:
    """Put ``tag`` until it arrives (the route is up): no sleeps."""
    for _ in range(400):
        put(tag)
        try:
            while got.get(timeout=0.05) != tag:
                pass
            return
        except queue.Empty:
            continue
    pytest.fail(f"{tag!r} never arrived")


def test_a_station_two_routers_away_gets_telemetry_asks_the_run_and_commands(
    net: tuple[Any, dict[str, zenoh.Session]],
) -> None:
    _, s = net
    cn, station = s["cn"], s["station"]
    tm: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    station.declare_subscriber(
        f"{V}/cn/telemetry",
        zenoh.handlers.Callback(lambda x: tm.put(x.payload.to_bytes()), indirect=False),
    )
    _until(lambda t: cn.put(f"{V}/cn/telemetry", t), tm, b"loop 1")
    cn.declare_queryable(
        f"{V}/cn/clock",
        zenoh.handlers.Callback(lambda q: q.reply(q.key_expr, b"run 7"), indirect=False),
    )
    answers: list[bytes] = []
    for _ in range(400):
        answers = [
            r.ok.payload.to_bytes() for r in station.get(f"{V}/cn/clock", timeout=1.0) if r.ok
        ]
        if answers:
            break
    assert answers == [b"run 7"]
    req: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    cn.declare_subscriber(
        f"{V}/gn/to_cn",
        zenoh.handlers.Callback(lambda x: req.put(x.payload.to_bytes()), indirect=False),
    )
    _until(lambda t: station.put(f"{V}/gn/to_cn", t), req, b"request 1")


def test_a_router_certificate_forwards_only_it_drives_no_sync(
    net: tuple[Any, dict[str, zenoh.Session]],
) -> None:
    _, s = net
    cn, rogue = s["cn"], s["rogue"]
    seen: queue.SimpleQueue[str] = queue.SimpleQueue()
    rogue.declare_queryable(
        f"{V}/dn0/to_cn",
        zenoh.handlers.Callback(lambda q: seen.put(str(q.key_expr)), indirect=False),
    )
    rogue.declare_subscriber(
        f"{V}/cn/mirror",
        zenoh.handlers.Callback(lambda x: seen.put(str(x.key_expr)), indirect=False),
    )
    marks: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    rogue.declare_subscriber(
        f"{V}/cn/telemetry",
        zenoh.handlers.Callback(lambda x: marks.put(x.payload.to_bytes()), indirect=False),
    )
    # One link, in order: once the marker is routed, the CN has taken in
    # (or dropped) every declaration before it.
    _until(lambda t: cn.put(f"{V}/cn/telemetry", t), marks, b"ready")
    for _ in range(20):
        cn.put(f"{V}/cn/mirror", b"the commander's vector")
    replies = list(cn.get(f"{V}/dn0/to_cn", timeout=0.5, target=zenoh.QueryTarget.ALL))
    _until(lambda t: cn.put(f"{V}/cn/telemetry", t), marks, b"after")
    assert [r for r in replies if r.ok is not None] == []
    got = []
    while not seen.empty():
        got.append(seen.get())
    assert got == []
