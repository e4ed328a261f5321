"""The access-control list bounds what a peer may *declare*, not only what
it may send (zplatform.security.deploy.access_control), measured on the wire.

In this process, on loopback, over mutual TLS with the deployment's access
control: a ``cn`` and a ``dn0`` session with their own certificates and
configs (:func:`zplatform.runtime.transport.zenoh_config`, what their nodes run),
and a peer presenting the mission's read-only ``tool`` certificate,
connected to both, that declares :data:`N` subscribers on the whole key
space ``{vehicle}/**`` and :data:`N` queryables on dn0's sync key, then one
subscriber the ACL allows (``{vehicle}/cn/telemetry``) as a marker. One
link carries the tool's declarations to the CN in order, and the CN's puts
back in order: once the marker has a sample, the CN has taken in every
declaration before it, and every sample it routed to the tool before the
marker's has arrived.

* The CN puts on its trigger tap ``{vehicle}/cn/to_dn0`` (which only a
  ``{vehicle}/**`` subscriber would get) and then telemetry: the marker gets
  telemetry, the wildcard subscribers get nothing: the CN never entered them
  in its routing tables. (On 9cf8fea, where every identity might subscribe
  to ``{vehicle}/**``, they got every sample.)
* The CN's sync query on ``{vehicle}/dn0/to_cn`` is answered by dn0 alone:
  none of the tool's queryables sees it.

What the flood costs a node in CPU is a benchmark (``python -m
bench.faults --case declaration_flood``), not a test.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.pki import make_test_pki
from zplatform.mission.load import decode_mission
from zplatform.runtime.transport import free_port, open_session, zenoh_config

pytestmark = pytest.mark.timeout(120)

N = 2000
"""Declarations of each kind the tool peer makes (the defect's "thousands")."""


def _mission(cn: int, dn: int) -> Any:
    return decode_mission(f"""
mission: acldecl
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


class _Counter:
    """Thread-safe counts of callback calls by key expression (zenoh's
    threads call it with a sample or a query)."""

    def __init__(self) -> None:
        self.by_key: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, x: Any) -> None:
        key = str(x.key_expr)
        with self._lock:
            self.by_key[key] = self.by_key.get(key, 0) + 1


@pytest.fixture
def sessions(tmp_path: Path) -> Iterator[dict[str, zenoh.Session]]:
    m = _mission(free_port(), free_port())
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn"])
    opened: dict[str, zenoh.Session] = {}
    try:
        for who in ("cn", "dn0", None):
            opened[who or "tool"] = open_session(zenoh_config(m, who, deployment=dep))
        yield opened
    finally:
        for s in reversed(opened.values()):
            s.close()


def test_a_tool_cert_cannot_declare_a_wildcard_subscriber_or_a_queryable(
    sessions: dict[str, zenoh.Session],
) -> None:
    cn, dn0, tool = sessions["cn"], sessions["dn0"], sessions["tool"]
    v = "rocket"
    dn0_q = dn0.declare_queryable(
        f"{v}/dn0/to_cn", zenoh.handlers.Callback(lambda q: q.reply(q.key_expr, b"dn0"))
    )
    # dn0's queryable is known to the CN: its querier's matching listener says
    # so (a get before the declaration arrives returns at once with no reply,
    # so a poll of gets raced it).
    matched: queue.SimpleQueue[bool] = queue.SimpleQueue()
    probe = cn.declare_querier(f"{v}/dn0/to_cn", target=zenoh.QueryTarget.ALL)
    listener = probe.declare_matching_listener(
        zenoh.handlers.Callback(lambda st: matched.put(st.matching), indirect=False)
    )
    try:
        if not probe.matching_status.matching:
            while not matched.get(timeout=10):
                pass
    except queue.Empty:
        pytest.fail("dn0's queryable never reached the CN")
    finally:
        listener.undeclare()
        probe.undeclare()
    assert any(r.ok is not None for r in cn.get(f"{v}/dn0/to_cn", timeout=2))

    wildcard, queries = _Counter(), _Counter()
    flood = [
        tool.declare_subscriber(f"{v}/**", zenoh.handlers.Callback(wildcard, indirect=False))
        for _ in range(N)
    ]
    flood += [
        tool.declare_queryable(f"{v}/dn0/to_cn", zenoh.handlers.Callback(queries, indirect=False))
        for _ in range(N)
    ]
    marks: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    marker = tool.declare_subscriber(
        f"{v}/cn/telemetry",
        zenoh.handlers.Callback(lambda s: marks.put(s.payload.to_bytes()), indirect=False),
    )
    flood.append(marker)

    def until_marked(tag: bytes) -> None:
        """Put ``tag`` on telemetry until the marker has it: everything the
        CN sent the tool before it has arrived."""
        for _ in range(200):
            cn.put(f"{v}/cn/telemetry", tag)
            try:
                while marks.get(timeout=0.05) != tag:
                    pass
                return
            except queue.Empty:
                continue
        pytest.fail("the tool's allowed subscriber never got telemetry")

    until_marked(b"ready")  # the CN has taken in every declaration above
    for _ in range(20):
        cn.put(f"{v}/cn/to_dn0", b"trigger tap")
    until_marked(b"after taps")
    # The wildcard subscribers got the marker's telemetry (inside the tool's
    # own session, which matches them locally), but no tap: the CN routed
    # none to the tool.
    assert set(wildcard.by_key) == {f"{v}/cn/telemetry"}, wildcard.by_key

    # The CN's sync query reaches dn0 alone.
    replies = [
        r.ok.payload.to_bytes()
        for r in cn.get(
            f"{v}/dn0/to_cn",
            timeout=1.0,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
        )
        if r.ok is not None
    ]
    assert replies == [b"dn0"]
    assert queries.by_key == {}
    for d in flood:
        d.undeclare()
    dn0_q.undeclare()
