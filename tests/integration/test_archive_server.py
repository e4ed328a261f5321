"""The ground archive served over zenoh (issue 28): two in-process sessions on
loopback, a ground's archive of run 7 (loops 1..300) answering a second
station's queries with the same rows as a local query."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.faults.peers import peer_config
from tests.unit.test_archive import feed
from tests.waits import wait_matching
from zplatform.archive import Archive, ArchiveWriter, Query
from zplatform.archive.server import ArchiveServer, remote_query
from zplatform.core.auth import KeySet
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import ArchiveError
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import free_port

ROOT = Path(__file__).resolve().parents[2]
MISSION = load_mission(ROOT / "configs" / "flight.yaml", code=False)
KEYS = KeySet.from_master(MISSION, bytes(range(32)))
KEYEXPR = "rocket/archive/query"


@pytest.fixture
def station(tmp_path: Path) -> Iterator[Any]:
    layout = Layout.for_node(MISSION, "cn")
    w = ArchiveWriter(MISSION, layout, tmp_path)
    feed(w, DataVector(layout), range(1, 301))
    w.close()
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = zenoh.open(peer_config([ep]))
    b = zenoh.open(peer_config(connect=[ep]))
    server = ArchiveServer(
        a,
        KEYEXPR,
        lambda: Archive(MISSION, tmp_path, recover=False),
        KEYS.channel("telemetry"),
        max_age_ns=60 * 10**9,
        serve_bps=50_000_000,
        max_bytes=200_000,
    )
    querier = b.declare_querier(KEYEXPR)
    wait_matching(querier, 10, "the archive's queryable, declared to b")
    querier.undeclare()
    tool = KEYS.for_node("tool").channel("telemetry")  # a read-only station asks
    nonce = iter(range(1, 1000))

    def ask(q: Query, **kw: Any) -> Any:
        return remote_query(
            b,
            KEYEXPR,
            kw.pop("channel", tool),
            q,
            nonce=next(nonce),
            timeout_s=kw.pop("timeout", 10.0),
        )

    try:
        yield ask, server, tmp_path
    finally:
        server.close()
        b.close()
        a.close()


def test_a_second_station_gets_the_same_rows(station: Any) -> None:
    ask, server, root = station
    q = Query("apogee_target_m,cn_state", run=7, start="loop:10", end="loop:250")
    with Archive(MISSION, root) as a:
        local = a.query(q)
    remote = ask(q)
    assert remote.equals(local) and remote.num_rows == 241
    agg = Query("cn_state", run=7, every="1s", agg=["min", "max"])
    with Archive(MISSION, root) as a:
        assert ask(agg).equals(a.query(agg))
    assert server.served == 2 and server.refused == 0


def test_a_bad_query_and_an_oversized_answer_are_refused_with_the_reason(station: Any) -> None:
    ask, server, _ = station
    assert server.served == 0
    with pytest.raises(ArchiveError, match="no element matches 'cn_stat'; did you mean"):
        ask(Query("cn_stat"))
    # Every element of 300 loops: more than the 200,000 bytes this station serves.
    with pytest.raises(ArchiveError, match="more than this station serves"):
        ask(Query("*", run=7))
    assert server.served == 2 and server.refused == 0  # answered, with the reasons


def test_an_ask_without_the_key_or_out_of_time_gets_no_answer(station: Any) -> None:
    ask, server, _ = station
    stranger = KeySet.generate(MISSION).channel("telemetry")  # another mission's key
    with pytest.raises(ArchiveError, match="no station answered"):
        ask(Query("cn_state"), channel=stranger, timeout=1.0)
    # One thread serves in order: once a good ask is answered, the hello was refused.
    assert ask(Query("cn_state", run=7)).num_rows == 300
    assert server.refused == 1 and server.served == 1 and server.hellos == 1
    # The unit tests (tests/unit/test_archive_server.py) replay asks of
    # another session, of run 0 and of this one: refused, counted stale.
