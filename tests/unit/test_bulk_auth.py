"""Bulk samples are authenticated (zplatform.runtime.bulk, codecs/FORMAT.md §6.1):
every sample carries a tag under link ``bulk-NAME``, bound to the owner's
run, and a reader's intake (size, tag, freshness, rate bound) refuses and
counts what fails, before any copy into its array; a tap with the tool's
keys checks and shows them. In process, on one local zenoh session."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from tests.zsession import lone_session
from zplatform.config import Mission
from zplatform.core.auth import TAG_LEN, KeySet, Run, link_of, role_links
from zplatform.core.events import EventLog
from zplatform.ground.tap import TapDecoder
from zplatform.mission.load import decode_mission
from zplatform.runtime.bulk import HEADER, NodeBulk, bulk_key, decode_sample

MASTER = secrets.token_bytes(32)
RUN = 1_700_000_000_000_000_000
T0 = 1_000


def _mission(rate_divisor: int = 1) -> Mission:
    return decode_mission(
        "mission: bulk_auth\n"
        "nodes:\n  cn: {}\n  dn0: {}\n  dn1: {}\n  gn: {}\n"
        "regions:\n  cn_to_dn0:\n    - {name: x, type: u8}\n"
        "bulk:\n"
        f"  - {{name: frame, node: dn0, type: 'u8[64]', readers: [cn], "
        f"rate_divisor: {rate_divisor}}}\n"
    )


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = lone_session()
    yield s
    s.close()


def _ends(
    session: zenoh.Session,
    m: Mission,
    *,
    owner_run: int = RUN,
    reader_run: int = RUN,
    now_ns: Any = lambda: T0 + 10**9,
) -> tuple[NodeBulk, NodeBulk, EventLog]:
    keys = KeySet.from_master(m, MASTER)
    events = EventLog("cn")
    owner = NodeBulk(
        session, m.vehicle, m.bulk, "dn0", shared_memory=False,
        keys=keys.for_node("dn0"), run=Run(owner_run),
    )  # fmt: skip
    reader = NodeBulk(
        session, m.vehicle, m.bulk, "cn", shared_memory=False,
        keys=keys.for_node("cn"), run=Run(reader_run), events=events, now_ns=now_ns,
    )  # fmt: skip
    return owner, reader, events


def _untagged(m: Mission, seq: int, fill: int, *, tag: bool = False) -> bytes:
    """A well-formed sample (the channel's layout, a newer number and
    stamp) as a keyless peer makes it: no tag, or a tag of zeros."""
    ch = m.bulk[0]
    data = bytearray(ch.sample_bytes + (TAG_LEN if tag else 0))
    HEADER.pack_into(data, 0, ch.layout_id, 0, seq, seq, T0 + seq)
    data[HEADER.size : ch.sample_bytes] = bytes([fill]) * ch.nbytes
    return bytes(data)


def test_every_bulk_channel_has_a_link_its_owner_readers_and_tools_hold() -> None:
    m = _mission()
    from zplatform.runtime.bulk import bulk_channel

    assert bulk_channel("frame") == "bulk_frame" and link_of("bulk_frame") == "bulk-frame"
    holders = {r for r in ("cn", "dn0", "dn1", "gn", "tool") if "bulk-frame" in role_links(m, r)}
    # The owner, its reader and the read-only tools (tap); not dn1, not the ground.
    assert holders == {"dn0", "cn", "tool"}


def test_a_forged_untagged_sample_over_zenoh_is_refused_counted_and_evented(
    session: zenoh.Session,
) -> None:
    m = _mission()
    owner, reader, events = _ends(session, m)
    r, key = reader.readers["frame"], bulk_key(m.vehicle, m.bulk[0])
    try:
        # A genuine sample is taken.
        owner.writers["frame"].array[:] = 7
        owner.publish(1, T0 + 1)
        assert r.wait(5.0) and int(r.array[0]) == 7
        # A keyless peer's well-formed samples: untagged (the old format),
        # and with a tag that is not the key's. Neither reaches the array.
        for n, payload in enumerate((_untagged(m, 5, 0xEE), _untagged(m, 6, 0xEE, tag=True))):
            session.put(key, payload)
            assert not r.wait(5.0)
            reader.receive(2 + n)
        assert int(r.array[0]) == 7 and (r.bad, r.stale) == (2, 0)
        assert reader.counters()["bulk_frame_bad"] == 2
        # Evented once for both (at most once a second), naming why.
        got = events.drain()
        assert [e.id for e in got] == ["bulk_refused"]
        assert "bad authentication tag" in got[0].text or "bytes" in got[0].text
        # The genuine owner's next sample is still taken.
        owner.writers["frame"].array[:] = 8
        owner.publish(2, T0 + 2)
        assert r.wait(5.0) and int(r.array[0]) == 8
    finally:
        owner.close()
        reader.close()


def test_a_genuine_sample_of_an_earlier_run_is_refused_as_stale(session: zenoh.Session) -> None:
    m = _mission()
    # The owner of an earlier run (its samples recorded, replayed now).
    old, reader, _ = _ends(session, m, owner_run=RUN - 10**12)
    r = reader.readers["frame"]
    try:
        old.writers["frame"].array[:] = 3
        old.publish(100, T0 + 100)
        assert not r.wait(5.0)
        assert (r.stale, r.bad, int(r.array[0])) == (1, 0, 0)
        assert reader.counters()["bulk_frame_stale"] == 1
    finally:
        old.close()
        reader.close()


def test_an_authentic_sample_stamped_ahead_or_beyond_the_rate_is_refused(
    session: zenoh.Session,
) -> None:
    from zplatform.runtime.bulk import RATE_BURST

    m = _mission(rate_divisor=10)
    owner, reader, _ = _ends(session, m)
    w, r = owner.writers["frame"], reader.readers["frame"]
    try:
        # Stamped at the end of time: refused, and it locks nobody out.
        w.publish(1, (1 << 63) - 1)
        assert not r.wait(5.0) and r.stale == 1
        # One every 10 polls is the channel's rate: a burst of RATE_BURST
        # more is taken, then the excess is refused until the polls catch up.
        taken = 0
        for i in range(RATE_BURST + 3):
            w.publish(2 + i, T0 + 2 + i)
            taken += r.wait(5.0)
        assert taken == RATE_BURST + 1 and r.stale == 1 + 2
        for _ in range(10):
            r.poll()
        w.publish(50, T0 + 50)
        assert r.wait(5.0) and r.header is not None and r.header.loop == 50
    finally:
        owner.close()
        reader.close()


def test_a_tap_with_the_tools_keys_checks_and_shows_bulk_samples(
    session: zenoh.Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = _mission()
    monkeypatch.setenv("ZPLATFORM_KEY", MASTER.hex())
    monkeypatch.delenv("ZPLATFORM_KEY_FILE", raising=False)
    owner, reader, _ = _ends(session, m)
    key = bulk_key(m.vehicle, m.bulk[0])
    got: list[bytes] = []
    sub = session.declare_subscriber(
        key,
        zenoh.handlers.Callback(lambda s: got.append(s.payload.to_bytes()), indirect=False),
    )
    try:
        owner.writers["frame"].array[:] = 5
        owner.publish(1, T0 + 1)
        assert len(got) == 1 and len(got[0]) == m.bulk[0].sample_bytes + TAG_LEN
        tap = TapDecoder(m)
        out = tap.decode(key, got[0])
        assert out["verified"] is True and out["seq"] == 0 and out["bulk"]["max"] == 5.0
        forged = tap.decode(key, _untagged(m, 9, 1, tag=True))
        assert "bad authentication tag" in forged["error"]
        # Checked by hand: the same bytes, the tag checked with the key.
        keys = KeySet.from_master(m, MASTER).for_node("tool")
        hdr, arr = decode_sample(got[0], m.bulk[0], keys.channel("bulk_frame"))
        assert hdr.loop == 1 and np.all(arr == 5)
    finally:
        sub.undeclare()
        owner.close()
        reader.close()


def test_a_flood_of_refusals_is_evented_at_most_once_a_second(session: zenoh.Session) -> None:
    """The first refusal is evented at once; the ones within the next
    second are counted and evented together once it has passed."""
    m = _mission()
    now = [T0 + 10**9]
    owner, reader, events = _ends(session, m, now_ns=lambda: now[0])
    r, key = reader.readers["frame"], bulk_key(m.vehicle, m.bulk[0])
    try:
        for i in range(3):
            session.put(key, _untagged(m, 10 + i, 1, tag=True))
            reader.receive(i)
            now[0] += 10**8
        first = events.drain()
        assert [e.id for e in first] == ["bulk_refused"] and "1 bad" in first[0].text
        reader.receive(3)  # still within the second: nothing more
        assert events.drain() == []
        now[0] += 10**9
        reader.receive(4)  # the two counted since, at most a period later
        (later,) = events.drain()
        assert "2 bad" in later.text and r.bad == 3
        reader.receive(5)
        assert events.drain() == []
    finally:
        owner.close()
        reader.close()


def test_the_rate_bound_counts_the_readers_loops_not_its_polls(session: zenoh.Session) -> None:
    """A reader that runs only some loops (a device node whose triggers were
    missed) polls less often than the channel publishes per poll: its loop
    numbers, not its polls, are the bound's clock, so none is refused; a
    run that starts its loops again starts the bound again."""
    m = _mission(rate_divisor=10)
    owner, reader, _ = _ends(session, m)
    w, r = owner.writers["frame"], reader.readers["frame"]
    try:
        for i in range(1, 21):  # one poll per sample, each 10 loops after the last
            w.publish(10 * i, T0 + i)
            reader.receive(10 * i)
        assert (r.received_copied + r.received_shm, r.stale) == (20, 0)
        for i in range(1, 4):  # a new run: its loops from 0 again
            w.publish(10 * i, T0 + 100 + i)
            reader.receive(10 * i)
        assert (r.received_copied + r.received_shm, r.stale) == (23, 0)
    finally:
        owner.close()
        reader.close()
