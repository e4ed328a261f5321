"""The CN's telemetry over iceoryx2 to a ground node on its host (issue 27;
zplatform.runtime.tmiox, docs/architecture.md#intra-host).

In process, on real iceoryx2 services: the control node's loop logic
(:class:`~zplatform.control.loop.ControlLogic`) makes each telemetry frame,
its :class:`~zplatform.runtime.tmiox.TelemetryPublisher` sends it over
iceoryx2 (encoded into the loan, or copied into one), and the very bytes
it would put on zenoh are handed to the ground node's zenoh callback
(``GroundLink._on_telemetry``), as zenoh's thread would. Verified:

* a local ground takes every frame over iceoryx2 (its vector is the CN's,
  byte for byte), and zenoh's copy of each is a duplicate, never a refusal;
* a forged sample written into the service (a same-user process that
  opened a publisher) is refused and counted exactly as the same bytes over
  zenoh, and never makes iceoryx2 the path;
* a frame on both paths, zenoh's first, is taken once; a third copy (a
  replay) is refused as stale;
* the publisher gone (or silent) falls back to zenoh with one event, and
  the ground keeps every frame zenoh carries;
* a ground on another host (another host tag) or a mission pinned to zenoh
  never uses iceoryx2;
* the CN's real loop (``ControlNode.step``) encodes each frame into its
  loan when zenoh takes no copy, and copies it into one when a zenoh
  subscriber matches: the same bytes on both paths;
* between processes: a CN publisher killed with SIGKILL (its port left in
  iceoryx2's state) falls back once, and the ground misses no frame zenoh
  carried; an end that cannot open stops a node pinned to ``shm`` and
  leaves ``auto`` on zenoh.

Waits are on the receiver's counts (``poll_until``), never on a guess.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.waits import poll_until
from zplatform.config import Mission
from zplatform.control.loop import ControlLogic
from zplatform.core.auth import KEY_ENV, TAG_LEN, KeySet, channel, new_run_epoch
from zplatform.core.codec import frame_stamp
from zplatform.errors import IntraHostError, TransportError
from zplatform.ground import link as link_module
from zplatform.ground.link import GroundLink
from zplatform.mission.load import decode_mission, load_mission
from zplatform.node.control import ControlNode
from zplatform.runtime import intrahost, tmiox
from zplatform.runtime.intrahost import IntraHostPublisher, IntraHostSubscriber
from zplatform.runtime.tmiox import (
    STALE_FRAMES,
    TelemetryPublisher,
    open_telemetry_publisher,
    telemetry_path_wanted,
)
from zplatform.runtime.transport import free_port, rewrite_endpoints

pytest.importorskip("iceoryx2")
pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"


class _Payload:
    def __init__(self, b: bytes) -> None:
        self._b = b

    def __len__(self) -> int:
        return len(self._b)

    def to_bytes(self) -> bytes:
        return self._b


class _Sample:
    """What the ground's zenoh callback reads of a sample."""

    def __init__(self, b: bytes) -> None:
        self.key_expr = "rocket/cn/telemetry"
        self.payload = _Payload(b)


def _mission(tmp: Path, intra_host: str = "auto") -> Mission:
    path = tmp / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)  # free ports: a service of this test alone
    raw = yaml.safe_load(path.read_text())
    raw.setdefault("transport", {})["intra_host"] = intra_host
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return load_mission(path)


class _Rig:
    """A CN's loop logic and iceoryx2 publisher, and a ground node's link."""

    def __init__(self, m: Mission) -> None:
        self.m = m
        self.keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
        run = new_run_epoch(time.time_ns())
        self.logic = ControlLogic(m, keys=self.keys, epoch=run)
        self.emitted: list[str] = []
        self.link = GroundLink(
            m, node="gn", keys=self.keys, on_event=lambda r: self.emitted.append(r.id)
        )
        # The ground node's own events handed to on_event as a tool's are,
        # not published (no peer here).
        assert self.link._ev_pub is not None
        self.link._ev_pub.undeclare()
        self.link._ev_pub = None
        assert self.link.run is not None
        self.link.run.set(run)  # as if learned by its run hello
        self.tmx = open_telemetry_publisher(m, self.logic.telemetry_length)
        self.loop = 0

    @property
    def rx(self) -> tmiox.TelemetryReceiver:
        rx = self.link.telemetry_iox
        assert rx is not None
        return rx

    def frame(self, *, lend: bool = False) -> tuple[bytes, bool]:
        """The next loop's telemetry: its bytes (what zenoh carries) and
        whether iceoryx2 sent it (encoded into the loan with ``lend``)."""
        self.loop += 1
        self.logic.begin(self.loop, time.time_ns())
        into = self.tmx.lend(copied=False) if lend and self.tmx is not None else None
        tm = self.logic.finish(tm_into=into)
        assert tm is not None  # telemetry_divisor 1
        data = bytes(tm)  # before the send: a lent sample is the subscriber's after
        sent = self.tmx.publish(tm) if self.tmx is not None else False
        return data, sent

    def zenoh(self, data: bytes) -> None:
        self.link._on_telemetry(_Sample(data))  # type: ignore[arg-type]

    def take(self) -> None:
        """Take everything queued (the ground node's thread)."""
        while self.link.next(0.0) is not None:
            pass

    def ids(self) -> list[str]:
        """The telemetry path's events emitted since the last call."""
        out = [n for n in self.emitted if n in ("tm_on_shm", "tm_fallback")]
        self.emitted.clear()
        return out

    def close(self) -> None:
        if self.tmx is not None:
            self.tmx.close()
        self.link.close()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[_Rig]:
    r = _Rig(_mission(tmp_path))
    yield r
    r.close()


def test_a_local_ground_takes_every_frame_over_iceoryx2_each_once(rig: _Rig) -> None:
    assert rig.tmx is not None and rig.link.telemetry_iox is not None
    assert poll_until(lambda: rig.tmx is not None and rig.tmx.subscribed, 10)
    n = 40
    for i in range(n):
        data, sent = rig.frame(lend=i % 2 == 0)  # into the loan, and copied into one
        assert sent
        assert poll_until(lambda i=i: rig.rx.taken == i + 1, 10), "not taken over iceoryx2"
        rig.zenoh(data)  # zenoh's copy, after: a duplicate
        rig.take()
        # The ground's vector is the CN's snapshot, byte for byte.
        assert bytes(rig.link.dv.view()) == bytes(rig.logic.dv.view())
    c = rig.link.logic.counters
    assert (c.received, c.iox, c.duplicates, c.gaps) == (n, n, n, 0)
    assert c.bad == 0 and sum(c.refused.values()) == 0
    assert rig.tmx.sent == n and rig.tmx.lent == n // 2 and rig.tmx.dropped == 0
    assert rig.link.tm_paths.path == "iox"
    assert rig.ids() == ["tm_on_shm"]


def test_the_iceoryx2_sample_is_the_zenoh_frame(rig: _Rig) -> None:
    # A subscriber of the test's own (the service's second slot) reads what
    # the ground reads: the very bytes zenoh carries, lent or copied.
    sub = IntraHostSubscriber(
        intrahost.telemetry_service_name(rig.m),
        rig.logic.telemetry_length,
        1,
        buffer=intrahost.TELEMETRY_BUFFER,
        publishers=2,
        wake=True,
    )
    try:
        assert poll_until(lambda: rig.tmx is not None and rig.tmx.pub.subscribers == 2, 10)
        for lend in (True, False):
            data, sent = rig.frame(lend=lend)
            assert sent
            view = None
            for _ in range(100):
                sub.wait(0.1)
                view = sub.receive_next()
                if view is not None:
                    break
            assert view is not None and bytes(view) == data
            assert len(data) == intrahost.telemetry_sample_bytes(rig.m, True)
            sub.release()
    finally:
        sub.close()


def test_a_forged_iceoryx2_sample_is_refused_as_a_forged_zenoh_frame(rig: _Rig) -> None:
    assert rig.tmx is not None
    genuine, _ = rig.frame()
    assert poll_until(lambda: rig.rx.taken == 1, 10)
    rig.take()
    before = rig.link.logic.counters
    # A same-user process opens a publisher of its own on the service.
    forger = IntraHostPublisher(
        intrahost.telemetry_service_name(rig.m),
        rig.logic.telemetry_length,
        1,
        buffer=intrahost.TELEMETRY_BUFFER,
        publishers=2,
        wake=True,
        check=False,
    )
    try:
        rig.logic.begin(rig.loop + 1, time.time_ns())
        real = bytearray(rig.logic.telemetry())
        real[-1] ^= 1  # a well-formed frame of the next loop, its tag one bit off
        junk = bytes(len(real))
        for forged in (bytes(real), junk):
            loan = forger.loan()
            assert loan is not None
            loan[:] = forged
            assert forger.send()
        assert poll_until(lambda: rig.rx.samples == 3, 10)
        rig.take()
        mid = rig.link.logic.counters
        assert mid.bad - before.bad == 2 and mid.received == before.received == 1
        # The same bytes over zenoh: counted alike.
        rig.zenoh(bytes(real))
        rig.zenoh(junk)
        rig.take()
        after = rig.link.logic.counters
        assert after.bad - mid.bad == 2 and after.received == 1
        assert after.iox == 1 and after.duplicates == 0
        assert rig.ids() == ["tm_on_shm"]  # from the genuine frame only
    finally:
        forger.close()
    assert genuine  # (the genuine frame's zenoh copy was never sent)


def test_zenoh_first_then_iceoryx2_is_taken_once_and_a_third_copy_is_stale(rig: _Rig) -> None:
    assert rig.tmx is not None
    # zenoh's copy first (the ground's iceoryx2 thread was late): taken from
    # zenoh; iceoryx2's is then the duplicate.
    rig.logic.begin(1, time.time_ns())
    rig.loop = 1
    tm = rig.logic.finish()
    assert tm is not None
    data = bytes(tm)
    rig.zenoh(data)
    rig.take()
    assert rig.link.logic.counters.received == 1
    assert rig.tmx.publish(tm)
    assert poll_until(lambda: rig.rx.samples == 1, 10)
    rig.take()
    c = rig.link.logic.counters
    assert (c.received, c.iox, c.duplicates, c.bad, sum(c.refused.values())) == (1, 0, 1, 0, 0)
    # A third copy (a replay on zenoh) is refused as not fresh, as before.
    rig.zenoh(data)
    rig.take()
    c = rig.link.logic.counters
    assert (c.received, c.duplicates, c.refused["not_newer"]) == (1, 1, 1)
    assert rig.link.tm_paths.path == "zenoh" and rig.ids() == []


def test_the_publisher_gone_falls_back_once_and_zenoh_carries_on(rig: _Rig) -> None:
    assert rig.tmx is not None
    for i in range(5):
        data, _ = rig.frame()
        assert poll_until(lambda i=i: rig.rx.taken == i + 1, 10)
        rig.zenoh(data)
        rig.take()
    assert rig.link.tm_paths.path == "iox" and rig.ids() == ["tm_on_shm"]
    rig.tmx.close()  # the CN's publisher is gone
    assert poll_until(lambda: rig.rx.publishers == 0, 10)
    rig.tmx = None
    for _ in range(20):
        data, sent = rig.frame()
        assert not sent
        rig.zenoh(data)
        rig.take()
    c = rig.link.logic.counters
    assert (c.received, c.gaps, c.iox, c.path_fallbacks) == (25, 0, 5, 1)
    assert rig.link.tm_paths.path == "zenoh"
    assert rig.ids() == ["tm_fallback"]


def test_a_silent_publisher_falls_back_after_stale_frames(rig: _Rig) -> None:
    assert rig.tmx is not None
    data, _ = rig.frame()
    assert poll_until(lambda: rig.rx.taken == 1, 10)
    rig.zenoh(data)
    rig.take()
    assert rig.ids() == ["tm_on_shm"]
    held = rig.tmx
    rig.tmx = None  # still attached, sending nothing (a stalled path)
    for i in range(STALE_FRAMES):
        data, _ = rig.frame()
        rig.zenoh(data)
        rig.take()
        assert rig.link.tm_paths.path == ("zenoh" if i == STALE_FRAMES - 1 else "iox")
    assert rig.ids() == ["tm_fallback"]
    # Back on iceoryx2 at its next frame.
    rig.tmx = held
    data, _ = rig.frame()
    assert poll_until(lambda: rig.rx.taken == 2, 10)
    rig.zenoh(data)
    rig.take()
    c = rig.link.logic.counters
    assert (c.received, c.gaps, c.path_fallbacks) == (STALE_FRAMES + 2, 0, 1)
    assert rig.ids() == ["tm_on_shm"]


def test_a_ground_on_another_host_takes_zenoh_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = _mission(tmp_path)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    logic = ControlLogic(m, keys=keys, epoch=new_run_epoch(time.time_ns()))
    tmx = open_telemetry_publisher(m, logic.telemetry_length)
    assert tmx is not None
    # Another host: another kernel boot or network namespace, another name.
    monkeypatch.setattr(intrahost, "host_tag", lambda: "elsewhere.0")
    link = GroundLink(m, node="gn", keys=keys)
    try:
        assert link.telemetry_iox is not None  # its own service, which nobody publishes on
        assert not tmx.subscribed
        logic.begin(1, time.time_ns())
        tm = logic.finish()
        assert tm is not None and not tmx.publish(tm)  # nobody attached: nothing sent
        assert tmx.sent == tmx.dropped == 0
    finally:
        link.close()
        tmx.close()


def test_a_mission_pinned_to_zenoh_opens_no_iceoryx2_end(tmp_path: Path) -> None:
    m = _mission(tmp_path, "zenoh")
    assert not telemetry_path_wanted(m)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    logic = ControlLogic(m, keys=keys)
    assert open_telemetry_publisher(m, logic.telemetry_length) is None
    link = GroundLink(m, node="gn", keys=keys)
    try:
        assert link.telemetry_iox is None and link._tm.dedupe is None
    finally:
        link.close()


def test_a_tool_never_takes_the_iceoryx2_path(tmp_path: Path) -> None:
    # Tools (tap, cmd, up's watcher, stations) see what they saw: zenoh.
    m = _mission(tmp_path)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    link = GroundLink(m, keys=keys)
    try:
        assert link.telemetry_iox is None and link._tm.dedupe is None
    finally:
        link.close()


def test_publish_without_a_subscriber_sends_nothing(tmp_path: Path) -> None:
    m = _mission(tmp_path)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    logic = ControlLogic(m, keys=keys)
    tmx = open_telemetry_publisher(m, logic.telemetry_length)
    assert isinstance(tmx, TelemetryPublisher)
    try:
        assert tmx.lend(copied=False) is None  # nobody attached: the logic's own buffer
        logic.begin(1, time.time_ns())
        tm: Any = logic.finish()
        assert len(tm) == tmx.length == logic.telemetry_length
        assert len(tm) - TAG_LEN > 0 and not tmx.publish(tm)
    finally:
        tmx.close()


def test_the_control_nodes_loop_lends_when_zenoh_takes_no_copy_and_copies_when_it_does() -> None:
    # The CN's real loop (ControlNode.step; a mission without device nodes,
    # so nothing waits) and a ground's iceoryx2 subscriber alone: every
    # frame is encoded and tagged straight into its loan. With a zenoh
    # subscriber too, each is copied into a loan, the same bytes both ways.
    cn, gn = free_port(), free_port()
    m = decode_mission(
        "mission: tm_step\nnodes:\n"
        f"  cn: {{listen: ['tcp/127.0.0.1:{cn}']}}\n"
        f"  gn: {{listen: ['tcp/127.0.0.1:{gn}'], connect: ['tcp/127.0.0.1:{cn}']}}\n"
        "regions:\n  cn:\n    - {name: x, type: u32}\n"
    )
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    node = ControlNode(m, keys=keys)
    sub = tmiox.open_telemetry_subscriber(m, True)
    zenoh_got: list[bytes] = []
    try:
        tmx = node._tm_iox
        assert tmx is not None and tmx.subscribed
        seal = channel(keys, "telemetry", node.logic.auth_run)
        assert seal is not None
        t0 = time.monotonic_ns()

        def take() -> bytes:
            view = sub.receive_next()
            assert view is not None
            data = bytes(view)
            sub.release()
            return data

        for k in range(3):
            node.step(k, t0 + k * m.period_ns)
            frame = take()
            assert frame_stamp(seal.open(frame))[0] == k + 1  # genuine, of loop k + 1
        assert (tmx.sent, tmx.lent, tmx.dropped) == (3, 3, 0)
        tap = node.ns.session.declare_subscriber(
            node.ns.keys.telemetry, lambda s: zenoh_got.append(s.payload.to_bytes())
        )
        try:
            assert poll_until(node._tm_pub.wanted, 10)
            node.step(3, t0 + 3 * m.period_ns)
            frame = take()
            assert poll_until(lambda: zenoh_got, 10)
            assert zenoh_got == [frame]
            assert (tmx.sent, tmx.lent) == (4, 3)
        finally:
            tap.undeclare()
    finally:
        sub.close()
        node.close()


def test_an_end_that_cannot_open_stops_a_pinned_node_and_leaves_auto_on_zenoh(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    usage = type("U", (), {"free": 4096})  # /dev/shm too small for the service
    monkeypatch.setattr(intrahost.shutil, "disk_usage", lambda _p: usage)

    def refused(*_a: Any, **_k: Any) -> None:
        raise IntraHostError("iceoryx2 refused")

    monkeypatch.setattr(link_module, "open_telemetry_subscriber", refused)
    for mode in ("auto", "shm"):
        (tmp_path / mode).mkdir()
        m = _mission(tmp_path / mode, mode)
        keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
        length = ControlLogic(m, keys=keys).telemetry_length
        if mode == "shm":
            with pytest.raises(TransportError, match=r"telemetry over iceoryx2: .*4096 free"):
                open_telemetry_publisher(m, length)
            with pytest.raises(TransportError, match="telemetry over iceoryx2: iceoryx2 refused"):
                GroundLink(m, node="gn", keys=keys)
            continue
        assert open_telemetry_publisher(m, length) is None
        link = GroundLink(m, node="gn", keys=keys)
        try:
            assert link.telemetry_iox is None and link._tm.dedupe is None
            (ev,) = [e for e in link.logic.events.drain() if e.id == "tm_fallback"]
            assert "no iceoryx2 end (iceoryx2 refused)" in ev.text
        finally:
            link.close()


def _spawn_cn(path: Path, run: int) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "tests.integration.test_telemetry_iox", str(path), str(run)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


def _cn_main(path: str, run: str) -> None:
    """Child: a CN's telemetry (its loop logic in run ``run`` and its
    iceoryx2 publisher); says ``ready`` once a subscriber is attached, then
    each 10 ms prints a frame (hex, what zenoh would carry) and sends it
    over iceoryx2, until killed."""
    m = load_mission(path)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    logic = ControlLogic(m, keys=keys, epoch=int(run))
    tmx = open_telemetry_publisher(m, logic.telemetry_length)
    if tmx is None or not poll_until(lambda: tmx.subscribed, 20):
        print("error no subscriber", flush=True)
        return
    print("ready", flush=True)
    loop = 0
    while True:
        loop += 1
        logic.begin(loop, time.time_ns())
        tm = logic.finish()
        assert tm is not None
        print(bytes(tm).hex(), flush=True)  # before the send: every frame sent is told
        tmx.publish(tm)
        time.sleep(0.01)  # stimulus: the CN's period


def test_a_kill_9d_publisher_falls_back_once_and_the_ground_misses_nothing(
    tmp_path: Path,
) -> None:
    m = _mission(tmp_path)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    run = new_run_epoch(time.time_ns())
    got: list[str] = []
    link = GroundLink(m, node="gn", keys=keys, on_event=lambda r: got.append(r.id))
    assert link._ev_pub is not None and link.run is not None
    link._ev_pub.undeclare()  # its events to on_event (no peer here)
    link._ev_pub = None
    link.run.set(run)
    rx = link.telemetry_iox
    assert rx is not None
    child = _spawn_cn(tmp_path / "m.yaml", run)
    try:
        assert child.stdout is not None
        said = child.stdout.readline().decode().strip()
        assert said == "ready", said
        frames = []
        while rx.taken < 5:  # frames the ground took over iceoryx2
            line = child.stdout.readline().decode().strip()
            assert line, f"the CN child ended (rc {child.poll()})"
            frames.append(bytes.fromhex(line))
            link._on_telemetry(_Sample(frames[-1]))  # type: ignore[arg-type]
            while link.next(0.0) is not None:
                pass
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        for line in child.stdout.read().decode().split():  # what it told before it died
            frames.append(bytes.fromhex(line))
            link._on_telemetry(_Sample(frames[-1]))  # type: ignore[arg-type]
        # Its publisher stays in iceoryx2's state (dead, not removed): the
        # CN's next frames come by zenoh alone (a restarted CN's, same run).
        logic = ControlLogic(m, keys=keys, epoch=run)
        for loop in range(len(frames) + 1, len(frames) + STALE_FRAMES + 6):
            logic.begin(loop, time.time_ns())
            tm = logic.finish()
            assert tm is not None
            link._on_telemetry(_Sample(bytes(tm)))  # type: ignore[arg-type]
            while link.next(0.0) is not None:
                pass
        total = len(frames) + STALE_FRAMES + 5
        c = link.logic.counters
        assert (c.received, c.gaps, c.bad, sum(c.refused.values())) == (total, 0, 0, 0)
        # On zenoh at the end, by one fallback after the kill; a ground
        # thread starved beside a CPU hog may also have fallen back (and come
        # back) while the CN ran: each fallback told once, after an iox spell.
        paths = [i for i in got if i in ("tm_on_shm", "tm_fallback")]
        assert link.tm_paths.path == "zenoh" and paths[-1] == "tm_fallback", paths
        assert paths == ["tm_on_shm", "tm_fallback"] * (len(paths) // 2), paths
        assert c.path_fallbacks == len(paths) // 2 >= 1
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        link.close()


if __name__ == "__main__":
    _cn_main(sys.argv[1], sys.argv[2])
