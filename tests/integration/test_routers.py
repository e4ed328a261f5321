"""Stations through zenoh routers (zplatform.runtime.router), in this process,
on loopback, over mutual TLS with the deployment's access control: a ``cn``
peer session (its node's config), a pad router connected to it, a
control-room router connected to the pad router, and a station tool that
reaches the vehicle as a zenoh client of the room router
(``ground.stations[].connect``; the tool's certificate).

* The station gets the CN's telemetry through both routers, its run hello
  on ``{vehicle}/cn/clock`` is answered by the CN, and its request on
  ``{vehicle}/gn/to_cn`` reaches the CN's subscriber.
* A router forwards, nothing more: a peer presenting the pad router's
  certificate, connected to the CN, declares a queryable on dn0's sync key
  and a subscriber on the CN's mirror (what a standby follows); the CN's
  sync query never reaches it, and no mirror sample is routed to it.
* Each router presents its own certificate: with the room router removed
  from the mission the CN runs, a peer presenting the room's certificate
  gets no telemetry and its requests never reach the CN, while the pad
  router, its certificate unchanged, forwards both (and, the room router
  still listed, the same peer gets both through: the control).
* A router presenting a node's certificate has that node's rights, not a
  router's: the station behind it gets no telemetry and its requests,
  which reach the router, never reach the CN (with its own certificate the
  same router carries both: the control).
"""

from __future__ import annotations

import json
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
from zplatform.security.deploy import router_identity

pytestmark = pytest.mark.timeout(120)

V = "rocket"
NODES = ["cn", "dn0", "gn"]
ROUTERS = [router_identity("pad"), router_identity("room")]


def _mission(cn: int, pad: int, room: int, *, with_room: bool = True) -> Any:
    room_router = (
        f"    - {{name: room, listen: ['tcp/127.0.0.1:{room}'], connect: ['tcp/127.0.0.1:{pad}']}}"
        if with_room
        else ""
    )
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
{room_router}
""")


@pytest.fixture
def net(tmp_path: Path) -> Iterator[tuple[Any, dict[str, zenoh.Session]]]:
    m = _mission(free_port(), free_port(), free_port())
    dep = make_test_pki(tmp_path / "pki", [*NODES, *ROUTERS], may_command=True)
    opened: dict[str, zenoh.Session] = {}
    try:
        opened["cn"] = open_session(zenoh_config(m, "cn", deployment=dep))
        for name in ("pad", "room"):
            r = find_router(m, name)
            opened[name] = open_session(
                router_config(m, r.listen, r.connect, deployment=dep, name=name)
            )
        room = m.ground.stations[1].connect
        opened["station"] = open_session(zenoh_config(m, None, deployment=dep, via=room))
        # A peer with the pad router's certificate, straight on the CN.
        cn_ep = m.nodes["cn"].listen
        opened["rogue"] = open_session(router_config(m, [], cn_ep, deployment=dep, name="pad"))
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


@pytest.mark.parametrize("listed", [True, False], ids=["room listed", "room removed"])
def test_a_router_removed_from_the_mission_is_cut_off_the_others_keep_their_certificates(
    tmp_path: Path, listed: bool
) -> None:
    ports = free_port(), free_port(), free_port()
    full = _mission(*ports)
    # The vehicle runs the mission as it now is; the PKI is the one made
    # with both routers, nobody's certificate remade.
    at_cn = full if listed else _mission(*ports, with_room=False)
    dep = make_test_pki(tmp_path / "pki", [*NODES, *ROUTERS], may_command=True)
    cn_ep = full.nodes["cn"].listen
    opened: dict[str, zenoh.Session] = {}
    try:
        cn = opened["cn"] = open_session(zenoh_config(at_cn, "cn", deployment=dep))
        # The room router's certificate, connected straight to the CN.
        room = opened["room"] = open_session(
            router_config(full, [], cn_ep, deployment=dep, name="room")
        )
        pad = opened["pad"] = open_session(
            router_config(full, [], cn_ep, deployment=dep, name="pad")
        )
        tm: dict[str, queue.SimpleQueue[bytes]] = {"pad": queue.SimpleQueue()}
        tm["room"] = queue.SimpleQueue()
        for name, s in (("room", room), ("pad", pad)):
            s.declare_subscriber(
                f"{V}/cn/telemetry",
                zenoh.handlers.Callback(
                    lambda x, q=tm[name]: q.put(x.payload.to_bytes()), indirect=False
                ),
            )
        req: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        cn.declare_subscriber(
            f"{V}/gn/to_cn",
            zenoh.handlers.Callback(lambda x: req.put(x.payload.to_bytes()), indirect=False),
        )
        # The pad router, its certificate as it was, forwards both ways.
        _until(lambda t: cn.put(f"{V}/cn/telemetry", t), tm["pad"], b"loop 1")
        _until(lambda t: pad.put(f"{V}/gn/to_cn", t), req, b"from pad")
        if listed:  # the control: the same peer, listed, gets both through
            _until(lambda t: cn.put(f"{V}/cn/telemetry", t), tm["room"], b"loop 2")
            _until(lambda t: room.put(f"{V}/gn/to_cn", t), req, b"from room")
            return
        for i in range(50):
            room.put(f"{V}/gn/to_cn", b"from room")
            cn.put(f"{V}/cn/telemetry", b"loop %d" % (i + 2))
        # The pad's last sample routed: the CN has routed (or dropped) all before it.
        _until(lambda t: pad.put(f"{V}/gn/to_cn", t), req, b"pad again")
        _until(lambda t: cn.put(f"{V}/cn/telemetry", t), tm["pad"], b"last")
        got = []
        while not req.empty():
            got.append(req.get())
        assert b"from room" not in got
        assert tm["room"].empty()
    finally:
        for s in reversed(opened.values()):
            s.close()


@pytest.mark.parametrize("cert", ["router-pad", "dn0"], ids=["its own", "a node's"])
def test_a_station_behind_a_router_presenting_a_nodes_certificate_is_cut_off(
    tmp_path: Path, cert: str
) -> None:
    """A router that presents a node's certificate (its start refuses it:
    tests/unit/test_router_config.py; here a hostile one, made by hand) has
    that node's rights at the vehicle, not a router's: the station behind it
    gets no telemetry and its requests never reach the CN, though they reach
    the router. With its own certificate the same router carries both (the
    control)."""
    from zplatform.security.deploy import zenoh_settings

    m = _mission(free_port(), free_port(), free_port())
    dep = make_test_pki(tmp_path / "pki", [*NODES, *ROUTERS], may_command=True)
    r = find_router(m, "pad")
    opened: dict[str, zenoh.Session] = {}
    try:
        cn = opened["cn"] = open_session(zenoh_config(m, "cn", deployment=dep))
        cfg = router_config(m, r.listen, r.connect)  # no identity yet
        for key, value in zenoh_settings(m, dep, cert).items():
            cfg.insert_json5(key, json.dumps(value))
        router = opened["router"] = open_session(cfg)
        station = opened["station"] = open_session(
            zenoh_config(m, None, deployment=dep, via=list(r.listen))
        )
        at_router: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        router.declare_subscriber(
            f"{V}/gn/to_cn",
            zenoh.handlers.Callback(lambda x: at_router.put(x.payload.to_bytes()), indirect=False),
        )
        req: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        cn.declare_subscriber(
            f"{V}/gn/to_cn",
            zenoh.handlers.Callback(lambda x: req.put(x.payload.to_bytes()), indirect=False),
        )
        tm: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        station.declare_subscriber(
            f"{V}/cn/telemetry",
            zenoh.handlers.Callback(lambda x: tm.put(x.payload.to_bytes()), indirect=False),
        )
        # The station's requests reach the router either way.
        _until(lambda t: station.put(f"{V}/gn/to_cn", t), at_router, b"request")
        if cert == "router-pad":
            _until(lambda t: station.put(f"{V}/gn/to_cn", t), req, b"request 2")
            _until(lambda t: cn.put(f"{V}/cn/telemetry", t), tm, b"loop 1")
            return
        for i in range(50):
            station.put(f"{V}/gn/to_cn", b"request %d" % i)
            cn.put(f"{V}/cn/telemetry", b"loop %d" % i)
        _until(lambda t: station.put(f"{V}/gn/to_cn", t), at_router, b"last")
        assert req.empty() and tm.empty()
    finally:
        for s in reversed(opened.values()):
            s.close()
