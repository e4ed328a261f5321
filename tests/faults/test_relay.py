"""The fault relay's drop, delay, reorder and partition each take effect on a
zenoh get/reply stream, and its counts are exactly those its seeded plan
gives (README.md, "zenoh link facts").

Readiness is always a reply (or a liveliness sample), never a sleep.
"""

from __future__ import annotations

import queue
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.faults.conftest import ZenohPair
from tests.faults.peers import ECHO_KEY, echo, get_once, peer_config
from tests.faults.relay import DirStats, FaultPlan, FaultRelay, RelayProcess
from zplatform.runtime.transport import free_port

# The relay and zenoh sessions only: no node, no mission (tests/conftest.py).
pytestmark = pytest.mark.no_mission

ROOT = Path(__file__).resolve().parents[2]

LOSSY_TIMEOUT_S = 0.05  # a lost get costs little while faults are on
SURE_TIMEOUT_S = 1.0  # gets that must be answered: room for a loaded box


def wait_ready(s: zenoh.Session, timeout_s: float = 10.0) -> float:
    """Poll with gets until one is answered; the time it took."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if get_once(s, 0.1, b"ready") is not None:
            return time.monotonic() - t0
    raise AssertionError(f"no reply within {timeout_s} s")


def burst(
    s: zenoh.Session, n: int, in_flight: int = 4, timeout_s: float = LOSSY_TIMEOUT_S
) -> list[float | None]:
    """``n`` gets, ``in_flight`` at a time; each one's round trip (s) or None."""
    out: list[float | None] = []
    while len(out) < n:
        k = min(in_flight, n - len(out))
        pending = []
        for i in range(k):
            t0 = time.monotonic()
            h = s.get(
                ECHO_KEY,
                payload=str(len(out) + i).encode(),
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            pending.append((t0, h))
        for t0, h in pending:
            rtt: float | None = None
            for r in h:
                if r.ok is not None and rtt is None:
                    rtt = time.monotonic() - t0
            out.append(rtt)
    return out


def assert_exact(relay: FaultRelay) -> dict[str, DirStats]:
    """The relay's counts equal a fresh replay of its seeded plan."""
    c = relay.counts()
    for d, st in c.items():
        assert st.seen > 0, d
        assert st.decisions() == relay.plan.expected(st.seen, d).decisions(), d
    return c


def test_plan_replays_identically_for_a_seed() -> None:
    a = FaultPlan(seed=42, drop=0.1, delay_s=0.001, jitter_s=0.0005, reorder=0.1)
    b = FaultPlan(seed=42, drop=0.1, delay_s=0.001, jitter_s=0.0005, reorder=0.1)
    sa = [a.decide("up") for _ in range(1000)]
    assert sa == [b.decide("up") for _ in range(1000)]
    assert sa != [FaultPlan(seed=43, drop=0.1, reorder=0.1).decide("up") for _ in range(1000)]
    e = a.expected(1000, "up")
    assert e.seen == e.forwarded + e.dropped == 1000
    assert 60 < e.dropped < 140 and 60 < e.reordered < 140  # ~10 % each
    assert all(0.0005 <= d <= 0.0015 for w, d in sa if w != "drop")


@pytest.mark.timeout(60)
@pytest.mark.parametrize("proto", ["tcp", "udp", "tcp+lowlatency"])
def test_drop_loses_gets_session_survives_counts_exact(
    zenoh_pair: Callable[..., ZenohPair], proto: str
) -> None:
    p = zenoh_pair(proto, seed=7)
    wait_ready(p.b)
    assert all(r is not None for r in burst(p.b, 20, timeout_s=SURE_TIMEOUT_S))
    p.relay.arm(drop=0.1)
    res = burst(p.b, 200)
    c = assert_exact(p.relay)
    lost = sum(r is None for r in res)
    dropped = c["up"].dropped + c["down"].dropped
    assert dropped > 0 and lost > 0, (lost, c)
    # A dropped batch costs at most the gets it carried (a batch may hold
    # several queries or replies when in flight together).
    assert lost <= 4 * dropped, (lost, c)
    p.relay.disarm()
    # The transport survived: no reconnect, every get answered again.
    assert all(r is not None for r in burst(p.b, 50, timeout_s=SURE_TIMEOUT_S))
    assert p.relay.connections == 1


@pytest.mark.timeout(60)
@pytest.mark.parametrize("proto", ["tcp", "udp"])
def test_delay_adds_at_least_its_minimum_each_way(
    zenoh_pair: Callable[..., ZenohPair], proto: str
) -> None:
    p = zenoh_pair(proto, seed=11)
    wait_ready(p.b)
    p.relay.arm(delay_s=0.001, jitter_s=0.0005)
    res = burst(p.b, 60, in_flight=1, timeout_s=SURE_TIMEOUT_S)
    c = assert_exact(p.relay)
    assert all(r is not None for r in res), res
    # Each way waits 1 ms +- 0.5 ms: no round trip can beat 2 x 0.5 ms.
    assert min(r for r in res if r is not None) >= 0.001
    assert c["up"].delayed == c["up"].forwarded == c["up"].seen
    assert c["down"].delayed == c["down"].seen


@pytest.mark.timeout(60)
@pytest.mark.parametrize("proto", ["tcp", "udp"])
def test_reorder_swaps_batches_zenoh_discards_the_late_one(
    zenoh_pair: Callable[..., ZenohPair], proto: str
) -> None:
    p = zenoh_pair(proto, seed=5)
    wait_ready(p.b)
    p.relay.arm(reorder=0.2)
    res = burst(p.b, 200)
    c = assert_exact(p.relay)
    assert c["up"].dropped == c["down"].dropped == 0
    assert c["up"].reordered + c["down"].reordered > 0
    # Nothing was dropped, yet gets were lost: zenoh drops a batch whose
    # sequence number is older than one it has already taken.
    assert any(r is None for r in res), c
    p.relay.disarm()
    assert all(r is not None for r in burst(p.b, 50, timeout_s=SURE_TIMEOUT_S))
    assert p.relay.connections == 1


@pytest.mark.timeout(60)
def test_puts_are_never_delivered_out_of_order(
    zenoh_pair: Callable[..., ZenohPair],
) -> None:
    p = zenoh_pair("tcp", seed=3)
    got: queue.SimpleQueue[int] = queue.SimpleQueue()
    sub = p.a.declare_subscriber("faults/seq", lambda s: got.put(int(s.payload.to_bytes())))
    wait_ready(p.b)
    pub = p.b.declare_publisher("faults/seq")
    p.relay.arm(reorder=0.2)
    for i in range(300):
        pub.put(str(i))
        time.sleep(0.0005)  # stimulus: the stream's pace
    p.relay.disarm()
    # End marker: a get answered after the burst means every earlier batch
    # has been delivered or discarded (one TCP stream, one order).
    wait_ready(p.b)
    seq = []
    while not got.empty():
        seq.append(got.get())
    sub.undeclare()
    assert p.relay.counts()["up"].reordered > 0
    assert seq == sorted(seq), "zenoh delivered a put out of order"
    assert len(seq) < 300, "no reordered batch was discarded"


@pytest.mark.timeout(60)
def test_partition_shorter_than_lease_keeps_the_session(
    zenoh_pair: Callable[..., ZenohPair],
) -> None:
    p = zenoh_pair("tcp", seed=1)
    wait_ready(p.b)
    p.relay.reset_counts()
    p.relay.partition()
    res = burst(p.b, 6, in_flight=2)  # ~0.15 s, well under the 1 s lease
    c = p.relay.counts()
    assert all(r is None for r in res)
    assert c["up"].blocked > 0 and c["up"].forwarded == 0
    p.relay.heal()
    assert get_once(p.b, SURE_TIMEOUT_S) is not None  # at once, same transport
    assert p.relay.connections == 1


@pytest.mark.timeout(60)
def test_partition_longer_than_lease_closes_then_heal_reconnects(
    zenoh_pair: Callable[..., ZenohPair],
) -> None:
    p = zenoh_pair("tcp", seed=1)
    tok = p.a.liveliness().declare_token("faults/alive/a")
    alive: queue.SimpleQueue[bool] = queue.SimpleQueue()

    def on_alive(s: Any) -> None:
        alive.put(s.kind == zenoh.SampleKind.PUT)

    sub = p.b.liveliness().declare_subscriber("faults/alive/a", on_alive, history=True)
    try:
        assert alive.get(timeout=10) is True
        p.relay.partition()
        t0 = time.monotonic()
        assert alive.get(timeout=10) is False  # the lease (1 s) expired
        lost_after = time.monotonic() - t0
        assert 0.5 < lost_after < 5, lost_after
        assert get_once(p.b, 0.1) is None
        p.relay.heal()
        t1 = time.monotonic()
        assert alive.get(timeout=10) is True  # zenoh reconnected by itself
        assert time.monotonic() - t1 < 5
        assert p.relay.connections >= 2  # a new transport, not the old one
        wait_ready(p.b, 5)
    finally:
        sub.undeclare()
        tok.undeclare()


@pytest.mark.timeout(60)
def test_relay_subprocess_driven_over_stdio() -> None:
    """The same relay as a process (for use inside a namespace)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = zenoh.open(peer_config([ep]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.faults.relay", ep, "--seed", "9"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        bufsize=1,
        cwd=ROOT,
    )
    rp = RelayProcess(proc)
    b = None
    try:
        q = a.declare_queryable(ECHO_KEY, echo)
        b = zenoh.open(peer_config(connect=[rp.endpoint]))
        wait_ready(b)
        rp.arm(drop=0.5)
        res = burst(b, 40)
        c = rp.counts()
        plan = FaultPlan(seed=9, drop=0.5)
        for d in ("up", "down"):
            assert c[d].decisions() == plan.expected(c[d].seen, d).decisions(), d
        assert any(r is None for r in res)
        rp.partition()
        assert get_once(b, LOSSY_TIMEOUT_S) is None
        rp.heal()
        rp.disarm()
        assert all(r is not None for r in burst(b, 20, timeout_s=SURE_TIMEOUT_S))
        assert rp.counts()["connections"] == 1
        q.undeclare()
    finally:
        if b is not None:
            b.close()
        rp.close()
        a.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
