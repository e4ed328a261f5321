"""The intra-host carrier in one process (zplatform/runtime/intrahost.py): names,
sizing, the shared-memory check, and an exchange's outcomes with a peer that
is absent, silent, or there. Cross-process round trips and a kill -9 are in
tests/integration/test_intrahost.py.

Each test runs under an iceoryx2 prefix of its own and asserts that closing
its ends leaves no data segment behind.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from tests.intrahost_peer import leftovers, wipe
from zplatform.errors import IntraHostError, ZPlatformError
from zplatform.mission.load import decode_mission
from zplatform.runtime import intrahost
from zplatform.runtime.bulk import mission_shm_need
from zplatform.runtime.intrahost import (
    IntraHostClient,
    IntraHostServer,
    LinkState,
    check_shm,
    link_names,
    mission_link_sizes,
    segment_bytes,
)

MISSION = """\
mission: {name}
nodes:
  cn: {{}}
  dn0: {{}}
regions:
  cn_to_dn0:
    - {{name: cmd, type: "u8[{trigger}]"}}
  dn0_to_cn:
    - {{name: obs, type: "u8[{reply}]"}}
"""

_count = 0


@pytest.fixture
def prefix() -> Iterator[str]:
    global _count
    _count += 1
    p = f"zpt{os.getpid()}u{_count}_"
    yield p
    left = leftovers(p)
    wipe(p)
    assert left == [], "a data segment outlived its link"


def _echo(server: IntraHostServer, stop: threading.Event) -> threading.Thread:
    def run() -> None:
        while not stop.is_set():
            view = server.wait(0.05)
            if view is not None:
                server.respond(bytes(view).translate(bytes(255 - i for i in range(256))))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_names_part_by_mission_vehicle_run_and_nodes() -> None:
    a = link_names("m1", "rocket", 7, "cn", "dn0")
    assert a.sync == "zplatform/m1/rocket/7/cn/dn0/sync"
    others = [
        link_names("m2", "rocket", 7, "cn", "dn0"),
        link_names("m1", "rover", 7, "cn", "dn0"),
        link_names("m1", "rocket", 8, "cn", "dn0"),
        link_names("m1", "rocket", 7, "cn_b", "dn0"),
        link_names("m1", "rocket", 7, "cn", "dn1"),
    ]
    services = {a.sync, a.request_event, a.reply_event}
    for o in others:
        assert not services & {o.sync, o.request_event, o.reply_event}


@pytest.mark.parametrize("bad", ["", "a/b", "x" * 65, "sp ace", "ü"])
def test_a_name_that_would_shift_levels_is_refused(bad: str) -> None:
    with pytest.raises(IntraHostError, match="not"):
        link_names("m", "rocket", 1, bad, "dn0")


def test_sizes_come_from_the_mission() -> None:
    m = decode_mission(MISSION.format(name="sz", trigger=1000, reply=325_000))
    trigger, reply = mission_link_sizes(m, "dn0")
    # A region frame at its widest plus the tag: over the region, under 1 KB more.
    assert 1000 < trigger < 2000
    assert 325_000 < reply < 326_000
    assert mission_shm_need(m) == segment_bytes(trigger, reply)


def test_too_small_shm_is_refused_with_the_figures(
    prefix: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    need = segment_bytes(1000, 325_000)
    with pytest.raises(IntraHostError, match=f"need {need} bytes of shared memory, /x has 4096"):
        usage = type("U", (), {"free": 4096})
        monkeypatch.setattr(intrahost.shutil, "disk_usage", lambda _p: usage)
        check_shm(need, "/x")
    names = link_names("small", "rocket", 1, "cn", "dn0")
    # The link refuses before it creates anything.
    with pytest.raises(IntraHostError, match="/dev/shm has 4096 free") as err:
        IntraHostServer(names, 1000, 325_000, prefix=prefix)
    assert isinstance(err.value, ZPlatformError)
    assert leftovers(prefix) == []


def test_missing_shm_dir_is_refused(tmp_path: object) -> None:
    with pytest.raises(IntraHostError, match="unusable"):
        check_shm(1, "/nonexistent/shm")


def test_segments_stay_within_the_computed_bound(prefix: str) -> None:
    names = link_names("bound", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 1000, 325_000, prefix=prefix)
    client = IntraHostClient(names, 1000, 325_000, prefix=prefix)
    try:
        used = sum(os.path.getsize(p) for p in leftovers(prefix))
        assert 325_000 < used <= segment_bytes(1000, 325_000)
    finally:
        client.close()
        server.close()


def test_no_server_is_no_peer(prefix: str) -> None:
    client = IntraHostClient(link_names("np", "rocket", 1, "cn", "dn0"), 64, 64, prefix=prefix)
    try:
        assert client.call(b"x", bytearray(64)) is None
        assert (client.state, client.no_peer, client.timeouts) == (LinkState.NO_PEER, 1, 1)
    finally:
        client.close()


def test_a_silent_peer_times_out_then_stalls_and_a_reply_recovers(prefix: str) -> None:
    names = link_names("silent", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix)
    client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=0.002, stall_after=3)
    out = bytearray(64)
    try:
        states = []
        for _ in range(3):
            assert client.call(b"trigger", out) is None
            states.append(client.state)
        assert states == [LinkState.UP, LinkState.UP, LinkState.STALLED]
        assert (client.sent, client.replies, client.timeouts) == (3, 0, 3)
        # The timed-out triggers were withdrawn: the server has none to serve late.
        assert server.wait(0) is None
        stop = threading.Event()
        t = _echo(server, stop)
        client.set_deadline(30.0)  # behaviour, not the box's speed: wait for the reply
        assert client.call(b"\x00\x01", out) == 2
        assert bytes(out[:2]) == b"\xff\xfe"
        assert (client.state, client.consecutive_timeouts, client.replies) == (LinkState.UP, 0, 1)
        stop.set()
        t.join()
    finally:
        client.close()
        server.close()


def test_a_dn_holding_its_answered_trigger_then_stalling_costs_no_loans(prefix: str) -> None:
    """The DN's end keeps the trigger it answered until its next wait (its
    loop copies the data from it); if it then stalls, the CN's next tries
    still find a sample to send (each times out, as before the hold), and
    the next trigger after the DN's return is served."""
    names = link_names("held", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix)
    client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=0.002)
    try:
        buf = client.trigger(4)
        assert buf is not None
        buf[:] = b"loop"
        assert client.send()
        view = server.wait(30.0)
        assert view is not None and bytes(view) == b"loop"
        assert server.respond(b"ok")
        client.set_deadline(30.0)
        assert client.collect() is not None
        assert bytes(view) == b"loop"  # held: still the trigger after the reply
        client.release()
        client.set_deadline(0.002)
        for _ in range(5):  # the DN stalls: no wait
            buf = client.trigger(4)
            assert buf is not None, "a held trigger starved the CN's loans"
            buf[:] = b"late"
            assert client.send()
            assert client.collect() is None
        buf = client.trigger(4)
        assert buf is not None
        buf[:] = b"back"
        assert client.send()
        view = server.wait(30.0)
        assert view is not None and bytes(view) == b"back"
    finally:
        client.close()
        server.close()


def test_oversized_frames_are_refused(prefix: str) -> None:
    names = link_names("big", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 16, 16, prefix=prefix)
    # A client whose bound exceeds the server's (a peer built for another
    # mission, or a hostile one on the host).
    client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=0.002)
    try:
        with pytest.raises(IntraHostError, match="bound 64"):
            client.trigger(65)
        # Send without waiting (as a hostile client would), so the request
        # is still there when the server looks.
        assert client.trigger(17) is not None
        pending = client._loan.assume_init().send()
        assert server.wait(0) is None
        assert (server.refused, server.received) == (1, 0)
        del pending
        with pytest.raises(IntraHostError, match="bound 16"):
            server.reply(17)
    finally:
        client.close()
        server.close()


def test_round_trip_in_process_byte_exact(prefix: str) -> None:
    bound = 325_000 + 64
    names = link_names("rt", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, bound, bound, prefix=prefix)
    client = IntraHostClient(names, bound, bound, prefix=prefix, deadline_s=30.0)
    stop = threading.Event()
    t = _echo(server, stop)
    out = bytearray(bound)
    sizes = [1, 2, 255, 256, 4096, 65_536, 325_000, bound]
    try:
        for n in sizes:
            frame = os.urandom(n)
            assert client.call(frame, out) == n
            assert bytes(out[:n]) == bytes(frame).translate(bytes(255 - i for i in range(256)))
        assert (client.sent, client.replies, client.timeouts) == (len(sizes), len(sizes), 0)
    finally:
        stop.set()
        t.join()
        client.close()
        server.close()
    assert (server.received, server.replied) == (len(sizes), len(sizes))


def test_two_missions_side_by_side_do_not_collide(prefix: str) -> None:
    ends = []
    stop = threading.Event()
    threads = []
    for mission in ("alpha", "bravo"):
        names = link_names(mission, "rocket", 1, "cn", "dn0")
        server = IntraHostServer(names, 64, 64, prefix=prefix)
        client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=30.0)
        ends.append((server, client))
        threads.append(_echo(server, stop))
    out = bytearray(64)
    try:
        for k in range(5):
            for i, (_server, client) in enumerate(ends):
                assert client.call(bytes([i, k]), out) == 2
                assert bytes(out[:2]) == bytes([255 - i, 255 - k])
        assert [(s.received, c.replies) for s, c in ends] == [(5, 5), (5, 5)]
    finally:
        stop.set()
        for t in threads:
            t.join()
        for server, client in ends:
            client.close()
            server.close()


def test_a_view_over_the_reply_reads_in_place(prefix: str) -> None:
    names = link_names("view", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix)
    client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=30.0)
    stop = threading.Event()
    t = _echo(server, stop)
    try:
        buf = client.trigger(3)
        assert buf is not None and not buf.readonly
        buf[:] = b"abc"
        reply = client.exchange()
        assert (
            reply is not None
            and reply.readonly
            and bytes(reply) == b"abc".translate(bytes(255 - i for i in range(256)))
        )
        client.release()
    finally:
        stop.set()
        t.join()
        client.close()
        server.close()


def test_send_to_every_dn_then_collect_against_one_deadline(prefix: str) -> None:
    import time

    stop = threading.Event()
    servers, clients, threads = [], [], []
    for dn in ("dn0", "dn1", "dn2", "dn3"):
        names = link_names("multi", "rocket", 1, "cn", dn)
        servers.append(IntraHostServer(names, 64, 64, prefix=prefix))
        clients.append(IntraHostClient(names, 64, 64, prefix=prefix))
    for server in servers[:3]:  # dn3 stays silent
        threads.append(_echo(server, stop))
    try:
        for i, c in enumerate(clients):
            buf = c.trigger(1)
            assert buf is not None
            buf[0] = i
            assert c.send()
        t_end = time.monotonic() + 30.0
        got = []
        for c in clients[:3]:
            reply = c.collect(t_end)
            got.append(None if reply is None else bytes(reply))
            c.release()
        assert got == [b"\xff", b"\xfe", b"\xfd"]
        # The silent one: nothing by a deadline already passed, one miss.
        assert clients[3].collect(time.monotonic()) is None
        assert [c.timeouts for c in clients] == [0, 0, 0, 1]
    finally:
        stop.set()
        for t in threads:
            t.join()
        for c in clients:
            c.close()
        for s in servers:
            s.close()


def test_exchanges_leave_no_memory_behind(prefix: str) -> None:
    import gc
    import sys

    names = link_names("leak", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 4096, 4096, prefix=prefix)
    client = IntraHostClient(names, 4096, 4096, prefix=prefix, deadline_s=30.0)
    stop = threading.Event()
    t = _echo(server, stop)
    frame, out = bytes(4096), bytearray(4096)
    try:
        for _ in range(50):  # warm-up: caches, ctypes' array types
            assert client.call(frame, out) == 4096
        gc.collect()
        before = sys.getallocatedblocks()
        for _ in range(500):
            assert client.call(frame, out) == 4096
        gc.collect()
        # Python objects per exchange are freed: nothing accumulates.
        assert sys.getallocatedblocks() - before < 200
    finally:
        stop.set()
        t.join()
        client.close()
        server.close()


def test_a_second_server_on_a_link_is_refused(prefix: str) -> None:
    # A process that took the link's one server place (a squatter, a DN
    # started twice) makes the next fail to open, with an error, not a hang.
    names = link_names("twice", "rocket", 1, "cn", "dn0")
    first = IntraHostServer(names, 64, 64, prefix=prefix)
    try:
        with pytest.raises(IntraHostError, match="no server"):
            IntraHostServer(names, 64, 64, prefix=prefix)
    finally:
        first.close()


def test_a_signal_during_a_wait_ends_it_without_raising(prefix: str) -> None:
    """A node's SIGTERM handler runs while its loop thread waits in the
    listener: iceoryx2 raises ListenerWaitError(InterruptSignal); the wait
    ends (as a spurious wake-up) instead, so the node stops cleanly."""
    import signal

    names = link_names("sig", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix, check=False)
    fired: list[int] = []
    old = signal.signal(signal.SIGALRM, lambda signum, _frame: fired.append(signum))
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        server.block(30.0)  # ends with the signal
        assert fired == [signal.SIGALRM]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        server.close()


def _ends(wait: Callable[[], object]) -> bool:
    """Whether ``wait()`` returns on its own, within 20 s (it takes at most
    a few ms when it honours its timeout). A wait that does not is ended by
    a signal to its thread, so the test fails instead of hanging."""
    import signal

    old = signal.signal(signal.SIGALRM, lambda *_: None)
    t = threading.Thread(target=wait, daemon=True)
    try:
        t.start()
        t.join(20.0)
        ended = not t.is_alive()
        while t.is_alive():
            signal.pthread_kill(t.ident or 0, signal.SIGALRM)  # EINTR ends the wait
            t.join(0.1)
        return ended
    finally:
        signal.signal(signal.SIGALRM, old)


@pytest.mark.parametrize("timeout_s", [5e-7, 0.0, -1.0])
def test_a_wait_of_under_a_microsecond_ends(prefix: str, timeout_s: float) -> None:
    """A deadline's last sliver: iceoryx2's listener timed_wait read one
    under a microsecond as 0, which the kernel takes for forever: a device
    node blocked until its next trigger, and for good once its control node
    had gone (it then outlived its SIGTERM; CI saw it)."""
    names = link_names("sliver", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix, check=False)
    name = "zplatform/sliver/rocket/x/cn/gn/telemetry"
    sub = intrahost.IntraHostSubscriber(name, 64, 1, prefix=prefix, wake=True)
    try:
        assert _ends(lambda: server.block(timeout_s))
        assert _ends(lambda: server.wait(timeout_s))
        assert _ends(lambda: sub.wait(timeout_s))
    finally:
        sub.close()
        server.close()


def test_a_reply_deadline_that_ends_in_a_sliver_is_kept(
    prefix: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The control node's collect, its deadline's last sliver under a
    microsecond and no reply coming (a dead device node): a miss, counted,
    never a loop blocked for good. Its clock is stepped by 0.1 µs a reading,
    so the sliver comes every time."""
    import time as real_time
    from types import SimpleNamespace

    names = link_names("sliverc", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix, check=False)
    client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=1e-6)
    now = [1000.0]

    def monotonic() -> float:
        now[0] += 1e-7
        return now[0]

    monkeypatch.setattr(
        intrahost, "time", SimpleNamespace(monotonic=monotonic, sleep=real_time.sleep)
    )
    got: list[object] = []
    try:
        view = client.trigger(7)
        assert view is not None
        view[:] = b"trigger"
        assert client.send()
        assert _ends(lambda: got.append(client.collect()))
        assert got == [None]
        assert (client.sent, client.replies, client.timeouts) == (1, 0, 1)
    finally:
        client.close()
        server.close()


@pytest.mark.parametrize(
    ("seconds", "ms"),
    [(1e-9, 1), (0.001, 1), (0.0010001, 2), (0.0025, 3), (0.01, 10), (1.0, 1000)],
)
def test_a_wait_takes_whole_milliseconds_rounded_up_from_a_table_built_at_start(
    prefix: str, seconds: float, ms: int
) -> None:
    """The WaitSet counts whole milliseconds, rounded up: a loop's wait takes
    that Duration from a table built once per process, the same object
    every time and for every end (none built per wait); a wait over a
    second builds its own."""
    names = link_names("table", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix, check=False)
    try:
        waiter = server._waiter
        assert waiter.duration(seconds).as_millis() == ms
        assert waiter.duration(seconds) is waiter.duration(seconds)
        other = IntraHostServer(link_names("table2", "rocket", 1, "cn", "dn0"), 64, 64,
                                prefix=prefix, check=False)  # fmt: skip
        try:
            assert other._waiter.duration(seconds) is waiter.duration(seconds)
        finally:
            other.close()
        assert waiter.duration(2.5).as_secs_f64() == 2.5
        assert waiter.duration(2.5) is not waiter.duration(2.5)
    finally:
        server.close()


def test_collect_against_a_given_deadline_builds_no_duration(prefix: str) -> None:
    """The sync collects each device node's reply against one deadline for
    all: a silent peer's miss, counted, with iceoryx2's Duration out of
    reach (so none is built per loop)."""
    from types import SimpleNamespace

    names = link_names("nodur", "rocket", 1, "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=prefix, check=False)
    client = IntraHostClient(names, 64, 64, prefix=prefix, deadline_s=0.002)
    iox = client._iox
    try:
        client._iox = SimpleNamespace()
        view = client.trigger(7)
        assert view is not None
        view[:] = b"trigger"
        assert client.send()
        assert client.collect(time.monotonic() + 0.003) is None
        assert (client.sent, client.replies, client.timeouts) == (1, 0, 1)
    finally:
        client._iox = iox
        client.close()
        server.close()


def test_the_telemetry_service_stays_within_its_computed_bound(prefix: str) -> None:
    # Both control nodes' publishers (and their restarts) and the ground's
    # subscriber, every frame queued TELEMETRY_BUFFER deep, its wake-up event.
    n = 325_000
    pubs = 2
    name = "zplatform/bound/rocket/x/cn/gn/telemetry"
    sub = intrahost.IntraHostSubscriber(
        name, n, 1, prefix=prefix, buffer=intrahost.TELEMETRY_BUFFER, publishers=pubs, wake=True
    )
    pub = intrahost.IntraHostPublisher(
        name,
        n,
        1,
        prefix=prefix,
        buffer=intrahost.TELEMETRY_BUFFER,
        publishers=pubs,
        wake=True,
        need=intrahost.telemetry_segment_bytes(n, pubs),
    )
    try:
        for i in range(intrahost.TELEMETRY_BUFFER + 2):  # more than it queues
            loan = pub.loan()
            assert loan is not None
            loan[:1] = bytes([i])
            assert pub.send()
        used = sum(os.path.getsize(p) for p in leftovers(prefix))
        assert n < used <= intrahost.telemetry_segment_bytes(n, pubs)
        # Queued in order, the oldest overwritten past the buffer.
        got = []
        while (view := sub.receive_next()) is not None:
            got.append(view[0])
            sub.release()
        assert got == list(range(2, intrahost.TELEMETRY_BUFFER + 2))
    finally:
        pub.close()
        sub.close()
