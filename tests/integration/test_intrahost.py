"""The intra-host carrier between real processes (zplatform/runtime/intrahost.py).

The device node's end runs in a child process (tests/intrahost_peer.py) that
says ``ready`` once its server exists; the control node's end is this test.
Verified here:

* frames of 1 B up to the largest bound cross and come back byte-exact;
* a peer killed with SIGKILL mid-link leaves stale iceoryx2 resources that
  the next run's ends remove (``stale_removed``), and that run's round
  trips work; the dead peer's link reads STALLED, then NO_PEER;
* a control node's end killed with SIGKILL while its trigger waits: the
  server's reply finds no one, the dead end is removed, and a new client
  (two, as many as the service admits) is served;
* two missions' links on one host, with the same node names, stay apart.

No sleeps: the test waits for the peer's ``ready`` line and its exit.
Each test runs under an iceoryx2 prefix of its own and wipes it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.intrahost_peer import leftovers, wipe
from zplatform.runtime.intrahost import (
    IntraHostClient,
    IntraHostServer,
    LinkState,
    link_names,
    remove_stale,
)

ROOT = Path(__file__).resolve().parents[2]
BOUND = 325_000 + 64
INVERT = bytes(255 - i for i in range(256))
_count = 0


@pytest.fixture
def prefix() -> Iterator[str]:
    global _count
    _count += 1
    p = f"zpt{os.getpid()}i{_count}_"
    yield p
    wipe(p)


class Peer:
    def __init__(self, mode: str, prefix: str, mission: str, run: str = "1") -> None:
        self.p = subprocess.Popen(
            [sys.executable, "-m", "tests.intrahost_peer", mode, prefix, mission, run, str(BOUND)],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.p.stdout is not None
        line = self.p.stdout.readline()
        assert line == "ready\n", f"peer did not start: {line!r} (exit {self.p.poll()})"

    def stop(self) -> None:
        if self.p.poll() is None:
            assert self.p.stdin is not None
            self.p.stdin.close()
            try:
                self.p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()

    def kill9(self) -> None:
        self.p.send_signal(signal.SIGKILL)
        assert self.p.wait(timeout=30) == -signal.SIGKILL


def _client(prefix: str, mission: str, run: str = "1", deadline_s: float = 30.0) -> IntraHostClient:
    return IntraHostClient(
        link_names(mission, "rocket", run, "cn", "dn0"),
        BOUND,
        BOUND,
        prefix=prefix,
        deadline_s=deadline_s,
    )


def test_round_trip_across_processes_byte_exact(prefix: str) -> None:
    peer = Peer("echo", prefix, "xproc")
    client = _client(prefix, "xproc")
    out = bytearray(BOUND)
    sizes = [1, 2, 255, 256, 1024, 4096, 65_536, 100_000, 325_000, BOUND]
    try:
        for n in sizes:
            frame = os.urandom(n)
            assert client.call(frame, out) == n, n
            assert bytes(out[:n]) == frame.translate(INVERT), n
        assert (client.sent, client.replies, client.timeouts) == (len(sizes), len(sizes), 0)
    finally:
        client.close()
        peer.stop()
    assert peer.p.returncode == 0
    assert leftovers(prefix) == []


def test_a_killed_run_leaves_nothing_the_next_trips_over(prefix: str) -> None:
    # Run 1: the peer holds its server (and its share of the segments), the
    # client's trigger is in its queue, then SIGKILL.
    peer = Peer("hold", prefix, "crash")
    client = _client(prefix, "crash", deadline_s=0.002, run="1")
    out = bytearray(BOUND)
    try:
        for _ in range(3):
            assert client.call(b"x" * 100, out) is None
        assert client.state is LinkState.STALLED
        peer.kill9()
        # The dead server's port is removed with its node: the link has no peer.
        assert remove_stale(prefix) == 1
        assert client.call(b"x", out) is None
        assert client.state is LinkState.NO_PEER
    finally:
        client.close()
    # Run 2, same names as run 1 would be after a restart in place: a new
    # server (max_servers is 1: a dead one still registered would refuse it).
    peer2 = Peer("hold", prefix, "crash")
    peer2.kill9()
    server = IntraHostServer(
        link_names("crash", "rocket", "1", "cn", "dn0"), BOUND, BOUND, prefix=prefix
    )
    assert server.stale_removed == 1
    server.close()
    peer3 = Peer("echo", prefix, "crash")
    client = _client(prefix, "crash")
    try:
        frame = os.urandom(BOUND)
        assert client.call(frame, out) == BOUND
        assert bytes(out) == frame.translate(INVERT)
    finally:
        client.close()
        peer3.stop()
    assert leftovers(prefix) == []


def test_two_missions_on_one_host_do_not_collide(prefix: str) -> None:
    peers = [Peer("echo", prefix, m) for m in ("left", "right")]
    clients = [_client(prefix, m) for m in ("left", "right")]
    out = bytearray(BOUND)
    try:
        for k in range(3):
            for i, c in enumerate(clients):
                frame = bytes([i, k]) * 100
                assert c.call(frame, out) == 200
                assert bytes(out[:200]) == frame.translate(INVERT)
        assert [c.replies for c in clients] == [3, 3]
    finally:
        for c in clients:
            c.close()
        for p in peers:
            p.stop()
    assert leftovers(prefix) == []


def test_a_killed_control_node_end_leaves_nothing_the_next_trips_over(prefix: str) -> None:
    import threading

    names = link_names("cnkill", "rocket", "1", "cn", "dn0")
    server = IntraHostServer(names, BOUND, BOUND, prefix=prefix)
    peer = Peer("ask", prefix, "cnkill")
    try:
        trigger = server.wait(30.0)
        assert trigger is not None and bytes(trigger) == b"ask"
        peer.kill9()
        assert remove_stale(prefix) == 1
        # Its request is still in hand; once the dead end is removed the
        # reply has nobody to go to.
        assert server.reply(3) is None
        assert not server.send()
        stop = threading.Event()

        def serve() -> None:
            while not stop.is_set():
                view = server.wait(0.05)
                if view is not None:
                    server.respond(bytes(view).translate(INVERT))

        t = threading.Thread(target=serve, daemon=True)
        t.start()
        clients = [_client(prefix, "cnkill") for _ in range(2)]
        out = bytearray(BOUND)
        try:
            for c in clients:
                assert c.call(b"again", out) == 5
                assert bytes(out[:5]) == b"again".translate(INVERT)
        finally:
            stop.set()
            t.join()
            for c in clients:
                c.close()
    finally:
        server.close()
        peer.stop()
    assert leftovers(prefix) == []
