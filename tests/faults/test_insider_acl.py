"""The access-control list shields the vehicle from an insider's
declarations outside its role (issue 25): what a device node's, the ground's
or a tool's certificate may declare, put or ask, by the generated ACL
(zplatform.security.deploy.access_control), is what the key-space table gives
that role, and nothing that reaches another node.

* In process, generated from the table: for each insider role of each
  shipped mission and each key the mission uses, every message kind the ACL
  lets that role's certificate send is one the table lists for the role on
  that key, or a put under the role's own prefix that no role's certificate
  may subscribe to (so no node takes it), or a tap subscription of the
  ground and the tools (:func:`zplatform.security.deploy.tool_watch_keys`).
* Live, over mutual TLS on loopback (the harness of
  tests/faults/test_acl_declarations.py): a device node's certificate
  declares subscribers on the command key ``{vehicle}/gn/to_cn``; what is
  put there never reaches the device node.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import zenoh

from tests.faults.insider import _resolve, shipped
from tests.pki import make_test_pki
from zplatform.config import Mission
from zplatform.core.auth import host_roles
from zplatform.mission.load import decode_mission
from zplatform.runtime.transport import free_port, open_session, zenoh_config
from zplatform.security.deploy import access_control, tool_watch_keys
from zplatform.security.keyspace import ExpandedKey, expand_keys

MISSIONS = shipped()
MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
)


def _acl_allows(acl: dict[str, Any], who: str, message: str, key: str) -> bool:
    (pol,) = [p for p in acl["policies"] if p["subjects"] == [f"s-{who}"]]
    by_id = {r["id"]: r for r in acl["rules"]}
    want = zenoh.KeyExpr(key)
    return any(
        r["flows"] == ["ingress"]
        and message in r["messages"]
        and any(zenoh.KeyExpr(ke).includes(want) for ke in r["key_exprs"])
        for r in (by_id[i] for i in pol["rules"])
    )


def _table_allows(m: Mission, ks: list[ExpandedKey], role: str, message: str) -> bool:
    """Whether any row expanded to this key gives ``role`` ``message``."""

    def has(k: ExpandedKey, col: tuple[str, ...]) -> bool:
        return any(role in _resolve(m, k, w) for w in col)

    for k in ks:
        kinds = {f.kind for f in k.row.frames}
        if message == "put" and has(k, k.row.puts):
            return True
        if message == "declare_subscriber" and "sample" in kinds and has(k, k.row.declares):
            return True
        if message == "query" and "query" in kinds and has(k, k.row.queries):
            return True
        if (
            message in ("declare_queryable", "reply")
            and "query" in kinds
            and has(k, k.row.declares)
        ):
            return True
        if message == "liveliness_token" and kinds == {"token"} and has(k, k.row.declares):
            return True
    return False


def _insiders(m: Mission) -> list[str]:
    return [r for r in host_roles(m) if r not in m.control_nodes]


def _acl(m: Mission) -> dict[str, Any]:
    return access_control(m, SimpleNamespace(tool=SimpleNamespace(may_command=False)))


@pytest.mark.parametrize("name", list(MISSIONS))
def test_an_insider_certificate_may_send_only_what_the_table_gives_its_role(name: str) -> None:
    m = MISSIONS[name]
    acl = _acl(m)
    by_key: dict[str, list[ExpandedKey]] = {}
    for k in expand_keys(m):
        by_key.setdefault(k.key, []).append(k)
    roles = host_roles(m)
    taps = set(tool_watch_keys(m))
    extra: list[str] = []
    checked = 0
    for key, ks in by_key.items():
        for role in _insiders(m):
            for message in MESSAGES:
                if not _acl_allows(acl, role, message, key):
                    continue
                checked += 1
                if _table_allows(m, ks, role, message):
                    continue
                if message == "declare_subscriber" and role in ("gn", "tool") and key in taps:
                    continue  # a region's tap, by its exact key
                if message == "put" and key.startswith(f"{m.vehicle}/{role}/"):
                    # Its own prefix: harmless only when no certificate may
                    # subscribe to the key (no node takes the put).
                    listeners = [r for r in roles if _acl_allows(acl, r, "declare_subscriber", key)]
                    if not listeners:
                        continue
                extra.append(f"{role} {message} {key}")
    assert not extra, f"the ACL lets an insider past the table: {extra}"
    assert checked >= 20


@pytest.mark.parametrize(
    ("who", "message", "key"),
    [
        ("tool", "declare_queryable", "rocket/dn0/to_cn"),  # answer the CN's trigger
        ("tool", "put", "rocket/gn/to_cn"),  # a command, a tool that may not command
        ("tool", "put", "rocket/cn/mirror"),
        ("dn0", "declare_subscriber", "rocket/gn/to_cn"),  # hear the commands
        ("dn0", "declare_queryable", "rocket/dn1/to_cn"),  # answer for another DN
        ("dn0", "reply", "rocket/dn1/to_cn"),
        ("dn0", "declare_queryable", "rocket/dn1/probe"),
        ("dn0", "put", "rocket/cn/mirror"),
        ("dn0", "declare_queryable", "rocket/cn/clock"),  # answer the other DN's clock
        ("dn0", "query", "rocket/dn1/probe"),  # ask another DN for a term
        ("gn", "declare_queryable", "rocket/dn0/to_cn"),
        ("gn", "put", "rocket/cn/mirror"),
        ("gn", "query", "rocket/dn0/probe"),
        ("gn", "declare_subscriber", "rocket/cn/mirror"),
    ],
)
def test_named_insider_declarations_are_denied(who: str, message: str, key: str) -> None:
    """The cases issue 25 names, on the flight mission (a standby, two DNs)."""
    assert not _acl_allows(_acl(MISSIONS["flight"]), who, message, key)


# -- live, over mutual TLS ----------------------------------------------------------


def _mission(cn: int, dn: int) -> Any:
    return decode_mission(f"""
mission: insideracl
security: {{transport: mtls}}
nodes:
  cn:  {{listen: ['tls/127.0.0.1:{cn}']}}
  dn0: {{listen: ['tls/127.0.0.1:{dn}'], connect: ['tls/127.0.0.1:{cn}']}}
  gn:  {{connect: ['tls/127.0.0.1:{cn}']}}
transport: {{gossip_scouting: false, multicast_scouting: false}}
regions:
  dn0_to_cn:
    - {{name: v, type: f64}}
""")


@pytest.fixture
def sessions(tmp_path: Path) -> Iterator[dict[str, zenoh.Session]]:
    m = _mission(free_port(), free_port())
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn"])
    opened: dict[str, zenoh.Session] = {}
    try:
        for who in ("cn", "dn0"):
            opened[who] = open_session(zenoh_config(m, who, deployment=dep))
        yield opened
    finally:
        for s in reversed(opened.values()):
            s.close()


def _wait_matching(querier: Any, what: str) -> None:
    """Until ``querier`` has a matching queryable (its listener says so)."""
    matched: queue.SimpleQueue[bool] = queue.SimpleQueue()
    listener = querier.declare_matching_listener(
        zenoh.handlers.Callback(lambda st: matched.put(st.matching), indirect=False)
    )
    try:
        if not querier.matching_status.matching:
            while not matched.get(timeout=10):
                pass
    except queue.Empty:
        pytest.fail(f"{what} never matched")
    finally:
        listener.undeclare()


@pytest.mark.timeout(120)
def test_a_device_node_cert_cannot_hear_the_commands(sessions: dict[str, zenoh.Session]) -> None:
    """dn0's certificate declares subscribers on the command key, then its
    own sync queryable (allowed): once the CN's querier matches that
    queryable, the CN has taken in (and dropped) the subscribers declared
    before them on the same link. The CN then puts on the command key
    (what a routing node would forward of the ground's commands) and asks
    dn0's sync queryable over the same link: dn0 answers, and its
    subscribers got nothing. (With access control off they get every put.)"""
    cn, dn0 = sessions["cn"], sessions["dn0"]
    v, n = "rocket", 20
    lock = threading.Lock()
    heard: list[bytes] = []

    def hear(s: Any) -> None:
        with lock:
            heard.append(s.payload.to_bytes())

    spies = [
        dn0.declare_subscriber(f"{v}/gn/to_cn", zenoh.handlers.Callback(hear, indirect=False))
        for _ in range(10)
    ]
    spies.append(
        dn0.declare_subscriber(f"{v}/gn/**", zenoh.handlers.Callback(hear, indirect=False))
    )
    dn0_q = dn0.declare_queryable(
        f"{v}/dn0/to_cn", zenoh.handlers.Callback(lambda q: q.reply(q.key_expr, b"dn0"))
    )
    querier = cn.declare_querier(f"{v}/dn0/to_cn", target=zenoh.QueryTarget.ALL)
    _wait_matching(querier, "dn0's sync queryable at the CN")
    querier.undeclare()
    for i in range(n):
        cn.put(f"{v}/gn/to_cn", f"command {i}".encode())
    replies = [
        r.ok.payload.to_bytes()
        for r in cn.get(f"{v}/dn0/to_cn", timeout=2.0, target=zenoh.QueryTarget.ALL)
        if r.ok is not None
    ]
    assert replies == [b"dn0"]
    with lock:
        assert heard == [], f"dn0 heard {len(heard)} commands"
    for d in [*spies, dn0_q]:
        d.undeclare()
