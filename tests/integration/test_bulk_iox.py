"""Bulk channels over iceoryx2 between nodes of one host (zplatform.runtime.bulk,
zplatform.runtime.intrahost; docs/architecture.md#intra-host).

Verified here, on real iceoryx2 services:

* a same-host reader takes the owner's samples over iceoryx2 (``bulk_<ch>_iox``
  counts them), drops its zenoh subscriber, so the owner sends nothing over
  zenoh, until a tool's tap subscribes: then the tap gets the samples over
  zenoh and the reader still over iceoryx2;
* a forged sample written into the channel's iceoryx2 service (a process
  that took the publisher slot first) meets the same intake as over zenoh:
  refused and counted (``bulk_<ch>_bad``), the path never taken;
* between processes: an owner killed with SIGKILL leaves its publisher in
  iceoryx2's state; the reader falls back to zenoh (``bulk_fallback``), and
  a restarted owner's start removes the dead one's resources, so its
  publisher opens (the service admits one) and the reader is back on
  iceoryx2.

Waits are on samples and counters (``poll_until``), never on a guess.
"""

from __future__ import annotations

import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.waits import poll_until
from tests.zsession import lone_session
from zplatform.config import Mission
from zplatform.core.auth import TAG_LEN, KeySet, Run
from zplatform.core.events import EventLog
from zplatform.errors import TransportError
from zplatform.mission.load import decode_mission
from zplatform.runtime.bulk import HEADER, STALE_LOOPS, NodeBulk, bulk_key, decode_sample
from zplatform.runtime.intrahost import IntraHostPublisher, bulk_service_name
from zplatform.runtime.transport import free_port, is_matching

ROOT = Path(__file__).resolve().parents[2]
N = 4096
RUN = 1_700_000_000_000_000_000


def _mission_text(n: int = N) -> str:
    cn, dn = free_port(), free_port()  # ports in the digest: a service of this test alone
    return (
        "mission: bulk_iox\n"
        "nodes:\n"
        f"  cn: {{listen: ['tcp/127.0.0.1:{cn}']}}\n"
        f"  dn0: {{listen: ['tcp/127.0.0.1:{dn}'], connect: ['tcp/127.0.0.1:{cn}']}}\n"
        "regions:\n  cn_to_dn0:\n    - {name: x, type: u8}\n"
        "bulk:\n"
        f"  - {{name: frame, node: dn0, type: 'u8[{n}]', readers: [cn]}}\n"
    )


@pytest.fixture
def mission() -> Mission:
    return decode_mission(_mission_text())


@pytest.fixture
def session() -> Iterator[Any]:
    s = lone_session()
    yield s
    s.close()


def _ids(log: EventLog) -> list[str]:
    return [e.id for e in log.drain()]


def test_same_host_bulk_takes_iceoryx2_and_a_tap_still_gets_samples(
    mission: Mission, session: Any
) -> None:
    events = EventLog("cn")
    reader = NodeBulk(
        session, mission.vehicle, mission.bulk, "cn", intra_host=mission, events=events
    )
    owner = NodeBulk(session, mission.vehicle, mission.bulk, "dn0", intra_host=mission)
    try:
        w, r = owner.writers["frame"], reader.readers["frame"]
        assert w.iox is not None and r.iox is not None
        w.array[:] = 7
        owner.publish(0, 1)  # the reader's zenoh subscriber is still there: both paths
        reader.receive(0)
        assert r.on_iox and int(r.array[0]) == 7 and r.array.sum() == 7 * N
        assert _ids(events) == ["bulk_on_shm"]
        assert reader.paths() == {"frame": "iox"}
        # The reader dropped its zenoh subscriber: nobody matches, no bytes go.
        assert not is_matching(w._pub)
        assert poll_until(lambda: not w.remote, 10), "the matching listener never said so"
        for loop in (1, 2):
            w.array[:] = loop
            owner.publish(loop, loop + 1)
            reader.receive(loop)
            assert int(r.array[-1]) == loop
        assert w.published_zenoh == 1 and w.published_iox == 3
        # A tool's tap: zenoh carries the samples again, for it alone.
        taps: list[bytes] = []
        tap = session.declare_subscriber(
            bulk_key(mission.vehicle, mission.bulk[0]), lambda s: taps.append(s.payload.to_bytes())
        )
        try:
            w.array[:] = 3
            owner.publish(3, 4)
            reader.receive(3)
            assert poll_until(lambda: taps, 10), "the tap got no sample"
        finally:
            tap.undeclare()
        header, arr = decode_sample(taps[0], mission.bulk[0])
        assert header.loop == 3 and int(arr[0]) == 3
        c = reader.counters()
        assert (c["bulk_frame_iox"], c["bulk_frame_bad"], c["bulk_frame_missed"]) == (4, 0, 0)
        # The one sample zenoh brought before the switch was superseded, not taken.
        assert c["bulk_frame_shm"] + c["bulk_frame_copied"] == 0
        assert w.published_zenoh == 2 and w.published_iox == 4
    finally:
        owner.close()
        reader.close()


def test_a_forged_sample_in_the_iceoryx2_service_is_refused_and_counted(
    mission: Mission, session: Any
) -> None:
    ch = mission.bulk[0]
    name = bulk_service_name(mission, ch.node, ch.name)
    events = EventLog("cn")
    reader = NodeBulk(
        session, mission.vehicle, mission.bulk, "cn", intra_host=mission, events=events
    )
    r = reader.readers["frame"]
    try:
        # A local process took the publisher slot before the owner came up.
        for size, fill in ((ch.sample_bytes + 8, 0), (ch.sample_bytes, 0xAB)):
            forger = IntraHostPublisher(name, size, 1, check=False)
            buf = forger.loan()
            assert buf is not None
            buf[:] = bytes([fill]) * size  # junk: a wrong size, then a wrong layout
            assert forger.send()
            reader.receive(0)
            forger.close()
        c = reader.counters()
        assert (c["bulk_frame_bad"], c["bulk_frame_iox"]) == (2, 0)
        # Refused and evented (bulk_refused, once), never a path change.
        assert not r.on_iox and [e.id for e in events.drain()] == ["bulk_refused"]
        # The genuine owner (the slot free again) is taken at its first sample.
        owner = NodeBulk(session, mission.vehicle, mission.bulk, "dn0", intra_host=mission)
        try:
            owner.writers["frame"].array[:] = 9
            owner.publish(1, 2)
            reader.receive(1)
            assert r.on_iox and int(r.array[0]) == 9 and reader.counters()["bulk_frame_iox"] == 1
        finally:
            owner.close()
    finally:
        reader.close()


def test_a_forged_well_formed_sample_over_iceoryx2_fails_the_tag_and_is_counted(
    mission: Mission, session: Any
) -> None:
    """With the mission's keys: a local process that took the publisher
    slot first feeds the reader a well-formed sample (the channel's layout,
    newer numbers), untagged or with a tag not the key's; each is refused
    at the tag, counted in ``bulk_<ch>_bad`` and never copied into the
    array; the genuine owner's tagged sample is then taken over iceoryx2."""
    ch = mission.bulk[0]
    name = bulk_service_name(mission, ch.node, ch.name)
    keys = KeySet.from_master(mission, secrets.token_bytes(32))
    events = EventLog("cn")
    reader = NodeBulk(
        session, mission.vehicle, mission.bulk, "cn", intra_host=mission, events=events,
        keys=keys.for_node("cn"), run=Run(RUN),
    )  # fmt: skip
    r = reader.readers["frame"]
    try:
        for size in (ch.sample_bytes, ch.sample_bytes + TAG_LEN):
            forger = IntraHostPublisher(name, size, 1, check=False)
            buf = forger.loan()
            assert buf is not None
            sample = bytearray(size)
            HEADER.pack_into(sample, 0, ch.layout_id, 0, 5, 5, 5)
            sample[HEADER.size : ch.sample_bytes] = b"\xee" * ch.nbytes
            buf[:] = sample
            assert forger.send()
            reader.receive(0)
            forger.close()
        c = reader.counters()
        assert (c["bulk_frame_bad"], c["bulk_frame_iox"], int(r.array.max())) == (2, 0, 0)
        assert not r.on_iox and [e.id for e in events.drain()] == ["bulk_refused"]
        owner = NodeBulk(
            session, mission.vehicle, mission.bulk, "dn0", intra_host=mission,
            keys=keys.for_node("dn0"), run=Run(RUN),
        )  # fmt: skip
        try:
            owner.writers["frame"].array[:] = 9
            owner.publish(1, 2)
            reader.receive(1)
            assert r.on_iox and int(r.array[0]) == 9 and reader.counters()["bulk_frame_iox"] == 1
        finally:
            owner.close()
    finally:
        reader.close()


@pytest.mark.parametrize("mode", ["auto", "shm"])
def test_an_owner_whose_publisher_cannot_open_stays_on_zenoh_or_refuses_under_shm(
    session: Any, mode: str
) -> None:
    """A live process holds the channel's one publisher slot: under ``auto``
    the owner's channel goes over zenoh alone (noted in ``changes``); under
    ``shm`` (the operator asked for it) the node refuses to start."""
    m = decode_mission(_mission_text() + f"transport: {{intra_host: {mode}}}\n")
    ch = m.bulk[0]
    squatter = IntraHostPublisher(
        bulk_service_name(m, ch.node, ch.name), ch.sample_bytes, 1, check=False
    )
    try:
        if mode == "shm":
            with pytest.raises(TransportError, match="bulk frame"):
                NodeBulk(session, m.vehicle, m.bulk, "dn0", intra_host=m)
            return
        owner = NodeBulk(session, m.vehicle, m.bulk, "dn0", intra_host=m)
        try:
            assert owner.writers["frame"].iox is None
            assert [(c, p) for c, p, _ in owner.changes] == [("frame", "zenoh")]
        finally:
            owner.close()
    finally:
        squatter.close()


def _spawn_owner(text: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "tests.integration.test_bulk_iox", text],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


def _owner_main(text: str) -> None:
    """Child: the channel's owner; says ``ready`` (or the error) once its
    iceoryx2 publisher is open, then publishes every 10 ms until killed."""
    m = decode_mission(text)
    s = lone_session()  # alone: only iceoryx2 can carry its samples to the test
    try:
        bulk = NodeBulk(s, m.vehicle, m.bulk, "dn0", intra_host=m)
    except Exception as exc:
        print(f"error {exc}", flush=True)
        return
    w = bulk.writers["frame"]
    print("ready" if w.iox is not None else f"error {bulk.changes}", flush=True)
    loop = 0
    while True:
        w.array[:] = loop % 256
        w.publish(loop, time.monotonic_ns())
        loop += 1
        time.sleep(0.01)  # stimulus: the owner's period


def test_a_kill_9d_owner_leaves_nothing_its_restart_trips_over(session: Any) -> None:
    text = _mission_text()
    m = decode_mission(text)
    events = EventLog("cn")
    reader = NodeBulk(session, m.vehicle, m.bulk, "cn", intra_host=m, events=events)
    r = reader.readers["frame"]
    loops = iter(range(10**9))
    children: list[subprocess.Popen[bytes]] = []

    def on_iox() -> bool:
        reader.receive(next(loops))
        return r.on_iox

    try:
        for run in (1, 2):
            child = _spawn_owner(text)
            children.append(child)
            assert child.stdout is not None
            said = child.stdout.readline().decode().strip()
            assert said == "ready", f"run {run}'s owner: {said}"
            assert poll_until(on_iox, 20), f"run {run}: no sample over iceoryx2"
            taken = reader.counters()["bulk_frame_iox"]
            assert taken >= 1
            os.kill(child.pid, signal.SIGKILL)
            child.wait()
            # Its publisher stays in iceoryx2's state (dead, not removed):
            # the reader falls back once the channel stays quiet.
            for _ in range(STALE_LOOPS + 2):
                reader.receive(next(loops))
            assert not r.on_iox and r.fallbacks == run
            assert _ids(events) == ["bulk_on_shm", "bulk_fallback"]
        assert np.all(r.array == r.array[0])  # one sample's pattern, whole
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
        reader.close()


if __name__ == "__main__":
    _owner_main(sys.argv[1])
