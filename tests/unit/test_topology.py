"""One dialer per pair of nodes (issue 25): the zenoh session configs the
mission makes never have two nodes dial each other, the case of a split
session after a stall (eclipse-zenoh/zenoh#2806, docs/architecture.md#failover)."""

from __future__ import annotations

import json
import queue
from pathlib import Path

import pytest
import yaml
import zenoh

from zplatform.config import Mission
from zplatform.errors import ConfigError, TransportError
from zplatform.mission.load import decode_mission, load_mission
from zplatform.runtime.transport import (
    dial_ranks,
    dials,
    free_port,
    open_session,
    rewrite_endpoints,
    zenoh_config,
    zid_for,
)

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted((ROOT / "configs").glob("*.yaml"))


def _zenoh_order(zid: str) -> bytes:
    """What zenoh's ``greater-zid`` compares: the id's little-endian bytes
    (``uhlc::ID`` derives ``Ord`` over its ``to_le_bytes`` array)."""
    return int(zid, 16).to_bytes(16, "little")


def _missions(tmp_path: Path) -> list[Mission]:
    out = []
    for path in SHIPPED:
        if "nodes:" not in path.read_text():
            continue
        out.append(load_mission(path))
        dst = tmp_path / path.name
        rewrite_endpoints(path, dst)  # what `up --free-ports` and the tests run
        out.append(load_mission(dst))
    return out


def test_no_pair_of_nodes_dials_each_other_in_any_shipped_mission(tmp_path: Path) -> None:
    missions = _missions(tmp_path)
    assert len(missions) >= 10
    for m in missions:
        d = dials(m)
        both = sorted((a, b) for a, b in d if (b, a) in d)
        assert both == [], (m.mission, both)


def test_the_session_configs_order_zenoh_ids_as_the_connect_lists_dial(tmp_path: Path) -> None:
    """Every node's config: gossip autoconnects ``greater-zid`` only, and
    its id is above (in zenoh's order) every node it connects to; an id is
    fresh per config (a restarted node is a new peer)."""
    for m in _missions(tmp_path):
        cfgs = {n: zenoh_config(m, n) for n in m.nodes}
        ids = {n: json.loads(c.get_json("id")) for n, c in cfgs.items()}
        ranks = dial_ranks(m)
        for a, b in dials(m):
            assert _zenoh_order(ids[a]) > _zenoh_order(ids[b]), (a, b, ids)
        owner = {ep: n for n, node in m.nodes.items() for ep in node.listen}
        for n, c in cfgs.items():  # every endpoint a node dials is a node's below it
            for ep in json.loads(c.get_json("connect/endpoints")):
                assert ep not in owner or ranks[owner[ep]] < ranks[n], (n, ep)
            if m.transport.gossip_scouting:  # and it dials every node below it
                below = {o for o in m.nodes if ranks[o] < ranks[n] and m.nodes[o].listen}
                dialed = {owner[ep] for ep in json.loads(c.get_json("connect/endpoints"))}
                assert dialed == below, (n, dialed, below)
        for n, c in cfgs.items():
            for how in ("gossip", "multicast"):
                strategy = json.loads(c.get_json(f"scouting/{how}/autoconnect_strategy"))
                assert strategy == {"peer": {"to_peer": "greater-zid"}}, (n, how)
            assert int(ids[n], 16) & 0xFF == ranks[n]
        again = json.loads(zenoh_config(m, "cn").get_json("id"))
        assert again != ids["cn"]


def test_flight_ranks_the_standby_above_the_commander_and_the_ground_above_both() -> None:
    m = load_mission(ROOT / "configs" / "flight.yaml")
    assert dial_ranks(m) == {"cn": 1, "dn0": 2, "dn1": 3, "cn_b": 4, "gn": 5}
    assert ("cn_b", "cn") in dials(m) and ("cn", "cn_b") not in dials(m)


def test_a_pair_connecting_both_ways_is_refused_at_load_naming_the_field() -> None:
    doc = yaml.safe_load((ROOT / "configs" / "minimal.yaml").read_text())
    doc["nodes"]["cn"]["connect"] = list(doc["nodes"]["dn0"]["listen"])
    with pytest.raises(ConfigError, match="cn and dn0 connect to each other") as ei:
        decode_mission(yaml.safe_dump(doc))
    assert ei.value.path == "$.nodes.cn.connect[0]"


def test_connect_lists_in_a_circle_are_refused_naming_the_nodes() -> None:
    doc = yaml.safe_load((ROOT / "configs" / "minimal.yaml").read_text())
    doc["nodes"]["cn"]["connect"] = list(doc["nodes"]["gn"]["listen"])
    doc["nodes"]["gn"]["connect"] = list(doc["nodes"]["dn0"]["listen"])  # cn -> gn -> dn0 -> cn
    m = decode_mission(yaml.safe_dump(doc))
    with pytest.raises(TransportError, match=r"\['cn', 'dn0', 'gn'\] \(in a circle\)"):
        zenoh_config(m, "cn")


def test_a_zid_out_of_rank_range_is_refused() -> None:
    with pytest.raises(TransportError):
        zid_for(0)
    with pytest.raises(TransportError):
        zid_for(256)


def test_zenoh_dials_only_from_the_greater_rank() -> None:
    """zenoh itself, three peers: X and Y each connect to Z (X first) and learn
    of each other by gossip; Y listens nowhere, so only Y can dial X. Their ids are
    made so zenoh's order (the rank byte, little-endian first) and the hex
    string's order disagree: X ``ff..ff01``, Y ``102``. The link forms (Y's
    token reaches X: peers do not forward for each other): Y dialed, so
    zenoh ranked Y above X by the lowest byte as :func:`zid_for` assumes."""
    pz, px = free_port(), free_port()
    base = load_mission(ROOT / "configs" / "minimal.yaml")  # its transport settings

    def cfg(zid: str, listen: list[str], connect: list[str]) -> zenoh.Config:
        c = zenoh_config(base, None)
        c.insert_json5("id", json.dumps(zid))
        c.insert_json5("listen/endpoints", json.dumps(listen))
        c.insert_json5("connect/endpoints", json.dumps(connect))
        return c

    x_id, y_id = zid_for(1, high=(1 << 120) - 1), zid_for(2, high=1)
    assert x_id > y_id and _zenoh_order(y_id) > _zenoh_order(x_id)

    def arrived(key: str, session: zenoh.Session, timeout_s: float) -> bool:
        """Whether ``session`` sees a liveliness token on ``key`` in time."""
        q: queue.Queue[bool] = queue.Queue()

        def on_token(s: zenoh.Sample) -> None:  # hand off only
            q.put(s.kind == zenoh.SampleKind.PUT)

        sub = session.liveliness().declare_subscriber(
            key, zenoh.handlers.Callback(on_token, indirect=False), history=True
        )
        try:
            return q.get(timeout=timeout_s)
        except queue.Empty:
            return False
        finally:
            sub.undeclare()

    z = open_session(cfg(zid_for(3), [f"tcp/127.0.0.1:{pz}"], []))
    x = open_session(cfg(x_id, [f"tcp/127.0.0.1:{px}"], [f"tcp/127.0.0.1:{pz}"]))
    try:
        x_token = x.liveliness().declare_token("t/x/alive")
        assert arrived("t/x/alive", z, 20)  # X joined Z before Y does
        x_token.undeclare()
        # zenoh's gossip tells a newcomer the peers its introducer knows then,
        # and on a busy host may not have X's locators yet: Y joins again
        # (a new session, the same id) until it learns of X. With the order
        # the other way round (X above Y), no attempt would ever link them.
        for _attempt in range(3):
            y = open_session(cfg(y_id, [], [f"tcp/127.0.0.1:{pz}"]))
            try:
                assert str(y.info.zid()) == y_id
                y_token = y.liveliness().declare_token("t/y/alive")
                linked = arrived("t/y/alive", x, 10)
                y_token.undeclare()
            finally:
                y.close()
            if linked:
                break
        assert linked, "Y never dialed X"
    finally:
        x.close()
        z.close()


def test_a_node_opens_its_session_at_once_and_finds_the_node_it_dials_when_it_comes(
    tmp_path: Path,
) -> None:
    """A node's session does not wait in ``zenoh.open`` for the nodes it
    dials (zenoh's ``open/return_conditions/connect_scouted``, whose wait
    cost every start-up half a second, ``scouting/delay``, when a peer it
    dials was not up yet): each node waits for the peers it needs by
    liveliness instead. Opened before the node it dials exists, dn0 still
    finds it when it comes, and a query reaches it. A tool keeps zenoh's
    default (it sends at once, to nodes already running)."""
    path = tmp_path / "minimal.yaml"
    rewrite_endpoints(ROOT / "configs" / "minimal.yaml", path)
    m = load_mission(path)
    for n in m.nodes:
        assert (
            json.loads(zenoh_config(m, n).get_json("open/return_conditions/connect_scouted"))
            is False
        )
    assert json.loads(zenoh_config(m, None).get_json("open/return_conditions/connect_scouted")) in (
        None,
        True,
    )

    dn0 = open_session(zenoh_config(m, "dn0"))  # cn, which dn0 dials, is not up
    try:
        tokens: queue.Queue[bool] = queue.Queue()
        sub = dn0.liveliness().declare_subscriber(
            "t/cn/alive",
            zenoh.handlers.Callback(
                lambda s: tokens.put(s.kind == zenoh.SampleKind.PUT), indirect=False
            ),
            history=True,
        )
        cn = open_session(zenoh_config(m, "cn"))
        try:
            q = cn.declare_queryable("t/cn/q", lambda query: query.reply("t/cn/q", b"here"))
            token = cn.liveliness().declare_token("t/cn/alive")
            assert tokens.get(timeout=30) is True  # dn0 dialed cn once it listened
            replies = [r.ok.payload.to_bytes() for r in dn0.get("t/cn/q", timeout=10) if r.ok]
            assert replies == [b"here"]
            token.undeclare()
            q.undeclare()
        finally:
            cn.close()
        sub.undeclare()
    finally:
        dn0.close()
