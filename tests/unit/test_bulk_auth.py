"""Bulk samples are authenticated (zplatform.runtime.bulk, codecs/FORMAT.md §6.1):
every sample carries a tag per reader, each under that reader's own link
``bulk-NAME-READER`` (the owner and that reader hold it), bound to the
owner's run; a reader's intake (size, its tag's header, freshness, rate
bound, then the one pass over the array) refuses and counts what fails,
before any copy into its array. No reader's key forges another's samples,
the tool holds no bulk key and a tap shows samples unverified. In process,
on one local zenoh session."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from tests.zsession import lone_session
from zplatform.config import Mission
from zplatform.core import auth
from zplatform.core.auth import (
    TAG_LEN,
    KeySet,
    Run,
    link_of,
    read_key_file,
    role_links,
    write_key_set,
)
from zplatform.core.events import EventLog
from zplatform.ground.tap import TapDecoder
from zplatform.mission.load import decode_mission
from zplatform.runtime import bulk
from zplatform.runtime.bulk import HEADER, NodeBulk, bulk_key, decode_sample

MASTER = secrets.token_bytes(32)
RUN = 1_700_000_000_000_000_000
T0 = 1_000


def _refused(r: Any) -> None:
    """The sample just put on ``r``'s key was refused, and counted once.
    Zenoh runs a local subscriber's callback inside the put (one session
    here), so the refusal is counted when the put returns: nothing to wait
    for (a late delivery would fail the count, never pass unseen)."""
    before = r.bad + r.stale + r.duplicates
    assert not r.wait(0.0)
    assert r.bad + r.stale + r.duplicates == before + 1, (r.bad, r.stale, r.duplicates)


def _mission(rate_divisor: int = 1, size: int = 64) -> Mission:
    return decode_mission(
        "mission: bulk_auth\n"
        "nodes:\n  cn: {}\n  dn0: {}\n  dn1: {}\n  gn: {}\n"
        "regions:\n  cn_to_dn0:\n    - {name: x, type: u8}\n"
        "bulk:\n"
        f"  - {{name: frame, node: dn0, type: 'u8[{size}]', readers: [cn, gn], "
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
    data = bytearray(ch.sample_bytes + (TAG_LEN * len(ch.readers) if tag else 0))
    HEADER.pack_into(data, 0, ch.layout_id, 0, seq, seq, T0 + seq)
    data[HEADER.size : ch.sample_bytes] = bytes([fill]) * ch.nbytes
    return bytes(data)


def test_every_reader_of_a_bulk_channel_has_a_link_only_it_and_the_owner_hold() -> None:
    m = _mission()
    from zplatform.runtime.bulk import bulk_channel

    assert bulk_channel("frame", "cn") == "bulk_frame/cn"
    assert link_of("bulk_frame/cn") == "bulk-frame-cn"
    roles = ("cn", "dn0", "dn1", "gn", "tool")
    for reader in ("cn", "gn"):
        link = f"bulk-frame-{reader}"
        # The owner and that reader; not the other reader, not dn1, not the tools.
        assert {r for r in roles if link in role_links(m, r)} == {"dn0", reader}
    assert [ln for ln in role_links(m, "tool") if ln.startswith("bulk")] == []


def test_the_tool_key_file_holds_no_bulk_key(tmp_path: Any) -> None:
    """A stolen tool key file (a read-only role's) holds no key that tags a
    bulk sample: ``zplatform keygen`` writes none into it."""
    m = _mission()
    files = write_key_set(m, tmp_path / "keys")
    tool = read_key_file(files["tool"], m)
    assert tool.links and not [ln for ln in tool.links if ln.startswith("bulk")]
    lines = [ln for ln in files["tool"].read_text().splitlines() if not ln.startswith("#")]
    assert not [ln for ln in lines if ln.startswith("bulk")]
    # The owner's file holds each reader's link, a reader's only its own.
    assert [ln for ln in read_key_file(files["dn0"], m).links if ln.startswith("bulk")] == [
        "bulk-frame-cn",
        "bulk-frame-gn",
    ]
    assert [ln for ln in read_key_file(files["gn"], m).links if ln.startswith("bulk")] == [
        "bulk-frame-gn"
    ]


def test_a_readers_key_cannot_forge_a_sample_another_reader_takes(
    session: zenoh.Session,
) -> None:
    """gn reads the channel too: with its keys it plays the owner, its own
    bulk key standing in for every bulk link it does not hold (the best an
    insider with gn's key file can do). cn refuses every such sample as bad
    and keeps the genuine owner's; gn's own reader takes it (its own key)."""
    m = _mission()
    keys = KeySet.from_master(m, MASTER)
    gn = keys.for_node("gn")
    (mine,) = [ln for ln in gn.links if ln.startswith("bulk")]
    forged_keys = KeySet(
        m,
        {ln: gn.link_key(ln if gn.has(ln) else mine) for ln in role_links(m, "dn0")},
        source="gn's key file",
    )
    owner, reader, _ = _ends(session, m)
    forger = NodeBulk(
        session, m.vehicle, m.bulk, "dn0", shared_memory=False,
        keys=forged_keys, run=Run(RUN),
    )  # fmt: skip
    gn_reader = NodeBulk(
        session, m.vehicle, m.bulk, "gn", shared_memory=False,
        keys=gn, run=Run(RUN), now_ns=lambda: T0 + 10**9,
    )  # fmt: skip
    r, g = reader.readers["frame"], gn_reader.readers["frame"]
    try:
        owner.writers["frame"].array[:] = 7
        owner.publish(1, T0 + 1)
        assert r.wait(5.0) and int(r.array[0]) == 7
        assert g.wait(5.0) and int(g.array[0]) == 7
        forger.writers["frame"].array[:] = 0xEE
        for i in range(3):
            forger.writers["frame"]._seq = 100 + i  # newer than the genuine ones
            forger.publish(2 + i, T0 + 2 + i)
            _refused(r)
            assert g.wait(5.0) and int(g.array[0]) == 0xEE  # gn's own tag: it fools only gn
        assert (r.bad, r.stale, int(r.array[0])) == (3, 0, 7)
        assert reader.counters()["bulk_frame_bad"] == 3
    finally:
        forger.close()
        gn_reader.close()
        owner.close()
        reader.close()


def test_a_forged_untagged_sample_over_zenoh_is_refused_counted_and_evented(
    session: zenoh.Session,
) -> None:
    m = _mission()
    owner, reader, events = _ends(session, m)
    r, key = reader.readers["frame"], bulk_key(m.vehicle, m.bulk[0])
    try:
        assert len(m.bulk[0].readers) == 2  # a sample carries two tags, cn's and gn's
        # A genuine sample is taken.
        owner.writers["frame"].array[:] = 7
        owner.publish(1, T0 + 1)
        assert r.wait(5.0) and int(r.array[0]) == 7
        # A keyless peer's well-formed samples: untagged (the old format),
        # and with a tag that is not the key's. Neither reaches the array.
        for n, payload in enumerate((_untagged(m, 5, 0xEE), _untagged(m, 6, 0xEE, tag=True))):
            session.put(key, payload)
            _refused(r)
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
        _refused(r)
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
        _refused(r)
        assert r.stale == 1
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


def test_a_tap_shows_bulk_samples_unverified(
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
        assert len(got) == 1 and len(got[0]) == m.bulk[0].sample_bytes + 2 * TAG_LEN
        tap = TapDecoder(m)
        out = tap.decode(key, got[0])
        assert out["verified"] is False and out["seq"] == 0 and out["bulk"]["max"] == 5.0
        assert out["bulk"]["bytes"] == m.bulk[0].sample_bytes
        # The tool holds no bulk key: a forged sample is shown, unverified too.
        forged = tap.decode(key, _untagged(m, 9, 1, tag=True))
        assert forged["verified"] is False and forged["seq"] == 9
        # Checked by hand, with a reader's key: the same bytes, its tag checked.
        keys = KeySet.from_master(m, MASTER)
        for rd in ("cn", "gn"):
            ch = keys.for_node(rd).channel(f"bulk_frame/{rd}")
            hdr, arr = decode_sample(got[0], m.bulk[0], ch)
            assert hdr.loop == 1 and np.all(arr == 5)
        with pytest.raises(auth.AuthError):
            decode_sample(forged_bytes := _untagged(m, 9, 1, tag=True), m.bulk[0], ch)
        assert len(forged_bytes) == len(got[0])
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


class _Passes:
    n = 0


@pytest.fixture
def passes(monkeypatch: pytest.MonkeyPatch) -> Iterator[_Passes]:
    """Counts passes over a sample's array, wherever they are made: a MAC
    over a frame of at least a MiB, or the bulk digest (its one pass)."""
    counter = _Passes()
    mac, digest = auth._RunKey.mac, getattr(bulk, "body_digest", None)

    def counted_mac(self: Any, frame: Any) -> bytes:
        counter.n += len(frame) >= 1 << 20
        return mac(self, frame)  # type: ignore[no-any-return]

    def counted_digest(hasher: Any, array: Any) -> bytes:
        counter.n += 1
        return digest(hasher, array)  # type: ignore[misc,no-any-return]

    monkeypatch.setattr(auth._RunKey, "mac", counted_mac)
    if digest is not None:
        monkeypatch.setattr(bulk, "body_digest", counted_digest)
    yield counter


def test_a_replayed_or_junk_full_size_sample_is_refused_without_a_pass_over_its_body(
    session: zenoh.Session, passes: _Passes
) -> None:
    """A 4 MiB channel: a genuine sample replayed (taken already) and junk
    of the full size are refused on their header, before any pass over the
    4 MiB; the owner's next sample costs one pass to make and one to check."""
    m = _mission(size=4 * 1024 * 1024)
    owner, reader, _ = _ends(session, m)
    r, key = reader.readers["frame"], bulk_key(m.vehicle, m.bulk[0])
    got: list[bytes] = []
    sub = session.declare_subscriber(
        key,
        zenoh.handlers.Callback(lambda s: got.append(s.payload.to_bytes()), indirect=False),
    )
    try:
        owner.writers["frame"].array[:] = 3
        owner.publish(1, T0 + 1)
        assert r.wait(5.0) and int(r.array[-1]) == 3 and len(got) == 1
        passes.n = 0
        for i in range(5):
            session.put(key, got[0])  # the genuine sample, again
            _refused(r)
            reader.receive(2 + i)
        junk = bytes([0x5A]) * len(got[0])
        for i in range(5):
            session.put(key, junk)
            _refused(r)
            reader.receive(10 + i)
        assert (passes.n, r.duplicates, r.bad, int(r.array[-1])) == (0, 5, 5, 3)
        owner.writers["frame"].array[:] = 4
        owner.publish(20, T0 + 20)
        assert r.wait(5.0) and int(r.array[-1]) == 4
        assert passes.n == 2  # the owner's one, the reader's one
    finally:
        sub.undeclare()
        owner.close()
        reader.close()


def test_a_genuine_header_spliced_onto_another_array_costs_one_pass_and_is_refused(
    session: zenoh.Session, passes: _Passes
) -> None:
    """cn's genuine tag and a new header, on an array the owner never
    hashed: the header passes, the one pass over the array finds another
    digest, the summary's MAC fails: bad, never taken."""
    import blake3

    from zplatform.runtime.bulk import SUMMARY_BYTES, body_digest, summary_of

    m = _mission(size=4 * 1024 * 1024)
    ch = m.bulk[0]
    owner, reader, _ = _ends(session, m)
    r, key = reader.readers["frame"], bulk_key(m.vehicle, ch)
    keys = KeySet.from_master(m, MASTER).for_node("dn0")
    tags = [keys.channel(f"bulk_frame/{rd}", Run(RUN)) for rd in ch.readers]
    try:
        data = bytearray(ch.sample_bytes)
        HEADER.pack_into(data, 0, ch.layout_id, 0, 1, 1, T0 + 1)
        summary = bytearray(SUMMARY_BYTES + TAG_LEN)
        summary_of(summary, data, ch.sample_bytes)
        summary[SUMMARY_BYTES - 32 : SUMMARY_BYTES] = body_digest(
            blake3.blake3(), memoryview(data)[HEADER.size :]
        )
        for t in tags:
            data += t.seal_tail(summary)[SUMMARY_BYTES:]
        data[HEADER.size + 5] ^= 0xFF  # the splice: one byte of the array
        passes.n = 0
        session.put(key, bytes(data))
        _refused(r)
        assert (passes.n, r.bad, r.stale, int(r.array[5])) == (1, 1, 0, 0)
        data[HEADER.size + 5] ^= 0xFF  # the very sample the owner tagged is taken
        session.put(key, bytes(data))
        assert r.wait(5.0) and r.header is not None and r.header.seq == 1
    finally:
        owner.close()
        reader.close()


class _Sample:
    """A zenoh sample as the reader's callback gets one (not in shared memory)."""

    def __init__(self, data: bytes) -> None:
        self.payload = self
        self._data = data

    def __len__(self) -> int:
        return len(self._data)

    def as_shm(self) -> None:
        return None

    def to_bytes(self) -> bytes:
        return self._data


def _genuine(m: Mission, seq: int, fill: int) -> bytes:
    """A sample as the owner tags it (both readers' tags, the owner's run)."""
    import blake3

    from zplatform.runtime.bulk import SUMMARY_BYTES, body_digest, summary_of

    ch = m.bulk[0]
    keys = KeySet.from_master(m, MASTER).for_node("dn0")
    data = bytearray(ch.sample_bytes)
    HEADER.pack_into(data, 0, ch.layout_id, 0, seq, seq, T0 + seq)
    data[HEADER.size :] = bytes([fill]) * ch.nbytes
    summary = bytearray(SUMMARY_BYTES + TAG_LEN)
    summary_of(summary, data, ch.sample_bytes)
    summary[SUMMARY_BYTES - 32 : SUMMARY_BYTES] = body_digest(
        blake3.blake3(), memoryview(data)[HEADER.size :]
    )
    for rd in ch.readers:
        data += keys.channel(f"bulk_frame/{rd}", Run(RUN)).seal_tail(summary)[SUMMARY_BYTES:]
    return bytes(data)


def test_junk_after_a_genuine_sample_never_displaces_it_before_the_poll(
    session: zenoh.Session,
) -> None:
    """Issue 25: the reader's zenoh callback kept the newest sample of any
    kind in its one slot, so a keyless flood on the bulk key (plain TCP)
    replaced the genuine sample before any check, and the reader never got
    one. Now the callback checks the size, this reader's header tag and the
    header's stamp first: a genuine sample followed by junk (full size,
    well-formed headers with a tag of zeros or the genuine header's, and a
    replay of an older genuine sample) before the poll is still taken, and
    each is counted."""
    m = _mission()
    _, reader, _ = _ends(session, m)
    r = reader.readers["frame"]
    try:
        older, genuine = _genuine(m, 1, 1), _genuine(m, 2, 2)
        spliced = bytearray(_untagged(m, 9, 0xEE, tag=True))
        spliced[-2 * TAG_LEN :] = genuine[-2 * TAG_LEN :]  # the genuine tags, another header
        junk = [
            _untagged(m, 9, 0xEE, tag=True),  # well-formed, newer, a tag of zeros
            bytes(spliced),
            bytes([0x5A]) * len(genuine),
            older,  # a genuine sample, older: replayed
        ] * 8
        r._on_sample(_Sample(genuine))  # type: ignore[arg-type]
        for data in junk:
            r._on_sample(_Sample(data))  # type: ignore[arg-type]
        assert r.poll() and r.header is not None and r.header.seq == 2
        assert int(r.array[0]) == 2
        assert (r.bad, r.stale, r.duplicates) == (24, 0, 8)
    finally:
        reader.close()
