"""Bulk channels without a second process: config checks, pool sizing, the
sample header, pool exhaustion (a fake provider and a fake clock) and a
writer/reader pair on one local zenoh session."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
import zenoh

from tests.zsession import lone_session
from zplatform.errors import ConfigError, TransportError
from zplatform.runtime.bulk import (
    HEADER,
    BulkChannelConfig,
    BulkWriter,
    NodeBulk,
    bulk_key,
    check_bulk_channels,
    counter_elements,
    counter_region,
    decode_sample,
    parse_bulk_type,
    pool_size,
)

NODES = ("cn", "dn0", "dn1", "gn")


def _ch(**kw: Any) -> BulkChannelConfig:
    base: dict[str, Any] = {"name": "cam", "node": "dn0", "type": "u8[4194304]", "readers": ["cn"]}
    base.update(kw)
    return msgspec.convert(base, type=BulkChannelConfig)


# -- config ------------------------------------------------------------------


def test_parse_bulk_type() -> None:
    s, shape = parse_bulk_type("f32[1024, 1024]") or (None, None)
    assert s is not None and s.name == "f32" and shape == (1024, 1024)
    assert parse_bulk_type("u8[4194304]") is not None
    for bad in ("u8", "u8[]", "u8[0]", "q8[3]", "f32[2,0]", "f32[1024x1024]"):
        assert parse_bulk_type(bad) is None, bad


def test_derived_sizes() -> None:
    ch = _ch(type="f32[1024,1024]")
    assert ch.shape == (1024, 1024) and ch.dtype == np.dtype("<f4")
    assert ch.nbytes == 4 << 20 and ch.sample_bytes == HEADER.size + (4 << 20)
    assert ch.layout_id != _ch(type="f32[1024,1023]").layout_id


def test_unknown_field_is_refused_at_decode() -> None:
    with pytest.raises(msgspec.ValidationError, match="rate"):
        msgspec.convert({"name": "a", "node": "dn0", "type": "u8[4]", "rate": 2}, BulkChannelConfig)


@pytest.mark.parametrize(
    ("channels", "path", "text"),
    [
        ([_ch(type="u8")], "$.bulk[0].type", "shape"),
        ([_ch(type="f32[1024,0]")], "$.bulk[0].type", "shape"),
        ([_ch(type="u8[2000000000]")], "$.bulk[0].type", "at most"),
        ([_ch(name="Cam")], "$.bulk[0].name", "must match"),
        # A trailing newline passed re.match's `$` (the bulk check used match,
        # the others fullmatch): one name rule for every name now.
        ([_ch(name="cam\n")], "$.bulk[0].name", "must match"),
        ([_ch(), _ch()], "$.bulk[1].name", "duplicate"),
        ([_ch(node="dn7")], "$.bulk[0].node", "no node"),
        ([_ch(readers=["cn", "dn9"])], "$.bulk[0].readers[1]", "no node"),
        ([_ch(readers=["dn0"])], "$.bulk[0].readers[0]", "owns"),
        ([_ch(readers=["cn", "cn"])], "$.bulk[0].readers[1]", "twice"),
        ([_ch(rate_divisor=4, rate_phase=4)], "$.bulk[0].rate_phase", "below"),
    ],
)
def test_check_names_the_yaml_path(channels: list[BulkChannelConfig], path: str, text: str) -> None:
    with pytest.raises(ConfigError, match=text) as ei:
        check_bulk_channels(channels, NODES)
    assert ei.value.path == path


def test_valid_channels_pass() -> None:
    check_bulk_channels(
        [_ch(), _ch(name="depth", node="cn", type="f32[1024,1024]", readers=["dn0", "dn1"])],
        NODES,
    )


def test_pool_size_counts_owned_channels_and_slots() -> None:
    chans = [
        _ch(type="u8[4096]", readers=["cn"]),  # 3 slots of 4096+32 -> 2 pages each
        _ch(name="b", type="u8[100]", readers=["cn", "dn1", "gn"]),  # 7 slots, 1 page
        _ch(name="c", node="cn", type="u8[100]", readers=["dn0"]),  # not dn0's
        _ch(name="d", type="u8[100]", slots=2),
    ]
    assert pool_size(chans, "dn0") == 3 * 8192 + 7 * 4096 + 2 * 4096
    assert pool_size(chans, "gn") == 0


def test_counter_elements_by_role() -> None:
    chans = [_ch()]
    assert [e["name"] for e in counter_elements(chans, "dn0")] == [
        "bulk_cam_published",
        "bulk_cam_dropped",
    ]
    assert [e["name"] for e in counter_elements(chans, "cn")] == [
        "bulk_cam_iox",
        "bulk_cam_shm",
        "bulk_cam_copied",
        "bulk_cam_missed",
        "bulk_cam_bad",
        "bulk_cam_stale",
    ]
    assert counter_elements(chans, "dn1") == []
    assert all(e["type"] == "u32" for e in counter_elements(chans, "cn"))


def test_key() -> None:
    assert bulk_key("rocket", _ch()) == "rocket/dn0/bulk/cam"


def test_decode_sample_checks_length_and_layout() -> None:
    ch = _ch(type="u16[2,3]")
    data = bytearray(ch.sample_bytes)
    HEADER.pack_into(data, 0, ch.layout_id, 0, 7, 70, 123)
    np.frombuffer(data, "<u2", 6, HEADER.size)[:] = np.arange(6)
    hdr, arr = decode_sample(bytes(data), ch)
    assert (hdr.seq, hdr.loop, hdr.t_ns) == (7, 70, 123)
    assert arr.shape == (2, 3) and arr[1, 2] == 5
    with pytest.raises(TransportError, match="bytes"):
        decode_sample(bytes(data[:-1]), ch)
    HEADER.pack_into(data, 0, ch.layout_id ^ 1, 0, 7, 70, 123)
    with pytest.raises(TransportError, match="layout"):
        decode_sample(bytes(data), ch)


# -- zenoh, one local session ---------------------------------------------------


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = lone_session()
    yield s
    s.close()


class _FullProvider:
    """Always out of memory, like a pool whose chunks readers still hold."""

    def __init__(self) -> None:
        self.calls = 0

    def alloc(self, size: int, policy: Any = None) -> Any:
        self.calls += 1
        raise zenoh.ZError("out of memory")


def test_exhausted_pool_waits_until_deadline_then_counts_a_drop(session: zenoh.Session) -> None:
    now = [0]

    def clock() -> int:
        now[0] += 200_000  # each reading advances 0.2 ms
        return now[0]

    prov = _FullProvider()
    sub = session.declare_subscriber("t/dn0/bulk/cam", lambda s: None)  # someone listens
    w = BulkWriter(session, "t/dn0/bulk/cam", _ch(alloc_timeout_ms=1.0), prov, monotonic=clock)
    assert w.publish(0, 0) is False
    assert (w.published, w.dropped) == (0, 1)
    assert 3 <= prov.calls <= 6  # retried until the 1 ms deadline, then gave up
    assert w.publish(1, 0) is False and w.dropped == 2
    w.undeclare()
    sub.undeclare()


def test_zero_timeout_drops_after_one_try(session: zenoh.Session) -> None:
    prov = _FullProvider()
    sub = session.declare_subscriber("t/dn0/bulk/cam", lambda s: None)  # someone listens
    w = BulkWriter(session, "t/dn0/bulk/cam", _ch(alloc_timeout_ms=0), prov)
    assert w.publish(0, 0) is False and prov.calls == 1 and w.dropped == 1
    w.undeclare()
    sub.undeclare()


def test_nobody_subscribed_sends_no_bytes_over_zenoh(session: zenoh.Session) -> None:
    """Zenoh carries a sample only when a subscriber matches (a remote
    reader, a tool's tap): with none, no chunk is even taken from the pool."""
    prov = _FullProvider()
    w = BulkWriter(session, "t/dn0/bulk/nobody", _ch(alloc_timeout_ms=0), prov)
    assert w.publish(0, 0) is True and w.publish(1, 0) is True
    assert prov.calls == 0 and (w.published, w.dropped, w.published_zenoh) == (2, 0, 0)
    sub = session.declare_subscriber("t/dn0/bulk/nobody", lambda s: None)
    assert w.publish(2, 0) is False and prov.calls == 1 and w.dropped == 1
    sub.undeclare()
    w.undeclare()


def test_due_follows_divisor_and_phase(session: zenoh.Session) -> None:
    w = BulkWriter(session, "t/dn0/bulk/cam", _ch(type="u8[8]", rate_divisor=4, rate_phase=1), None)
    assert [i for i in range(10) if w.due(i)] == [1, 5, 9]
    w.undeclare()


@pytest.mark.parametrize("shm", [True, False])
def test_local_roundtrip_into_preallocated_array(session: zenoh.Session, shm: bool) -> None:
    ch = _ch(type="f32[64,32]", node="dn0", readers=["cn"])
    owner = NodeBulk(session, "t", [ch], "dn0", shared_memory=shm)
    reader = NodeBulk(session, "t", [ch], "cn", shared_memory=shm)
    w, r = owner.writers["cam"], reader.readers["cam"]
    assert (owner.provider is not None) == shm and owner.pool_bytes == (
        pool_size([ch], "dn0") if shm else 0
    )
    target = r.array
    for i in range(3):
        w.array[:] = np.float32(i) + np.arange(64 * 32, dtype=np.float32).reshape(64, 32)
        assert w.publish(10 + i, 1000 + i)
        assert r.wait(5.0)
        assert r.array is target  # preallocated, filled in place
        np.testing.assert_array_equal(r.array, w.array)
        assert r.header is not None and (r.header.seq, r.header.loop) == (i, 10 + i)
    assert not r.poll()  # nothing new
    c = owner.counters() | reader.counters()
    assert c["bulk_cam_published"] == 3 and c["bulk_cam_dropped"] == 0
    assert c["bulk_cam_shm"] + c["bulk_cam_copied"] == 3 and c["bulk_cam_missed"] == 0
    # view mode: no second copy, read-only
    w.publish(20, 0)
    assert r.wait(5.0, copy=False) and r.view is not None
    assert not r.view.flags.writeable and r.view.shape == (64, 32)
    owner.close()
    reader.close()


def test_reader_keeps_the_latest_and_counts_missed(session: zenoh.Session) -> None:
    ch = _ch(type="u8[16]")
    owner = NodeBulk(session, "t", [ch], "dn0", shared_memory=False)
    reader = NodeBulk(session, "t", [ch], "cn", shared_memory=False)
    w, r = owner.writers["cam"], reader.readers["cam"]
    for i in range(5):
        w.array[0] = i
        w.publish(i, 0)
    # Local delivery is synchronous: all five arrived, only the last is kept.
    assert r.wait(5.0) and r.array[0] == 4
    assert r.header is not None and r.header.seq == 4
    w.publish(5, 0)
    assert r.wait(5.0)
    w.publish(6, 0)
    w.publish(7, 0)
    assert r.wait(5.0) and r.missed == 1
    owner.close()
    reader.close()


def test_wrong_layout_is_counted_bad(session: zenoh.Session) -> None:
    ch = _ch(type="u8[16]")
    reader = NodeBulk(session, "t", [ch], "cn", shared_memory=False)
    r = reader.readers["cam"]
    session.put(bulk_key("t", ch), bytes(ch.sample_bytes))  # layout 0
    assert not r.wait(0.0) and r.bad == 1  # local delivery runs in the put
    session.put(bulk_key("t", ch), b"short")
    assert not r.wait(0.0) and r.bad == 2
    assert r.array.sum() == 0
    reader.close()


class _FakeHandle:
    def __init__(self) -> None:
        self.value = -1

    def set(self, v: int) -> None:
        self.value = v


class _FakeDV:
    def __init__(self, names: list[str]) -> None:
        self.h = {n: _FakeHandle() for n in names}

    def handle(self, name: str) -> _FakeHandle:
        return self.h[name]


def test_write_counters_into_data_vector(session: zenoh.Session) -> None:
    ch = _ch(type="u8[16]")
    owner = NodeBulk(session, "t", [ch], "dn0", shared_memory=False)
    dv = _FakeDV(["bulk_cam_published"])  # dropped not in this layout: skipped
    owner.writers["cam"].publish(0, 0)
    owner.write_counters(dv)
    assert dv.h["bulk_cam_published"].value == 1
    owner.close()


def test_camera_mission_declares_valid_channels() -> None:
    """configs/camera.yaml: the mission part loads, the bulk part checks.

    Until ``Mission`` has ``bulk: list[BulkChannelConfig]`` the two are
    decoded separately here."""
    import yaml

    from zplatform.mission.load import decode_mission

    path = Path(__file__).resolve().parents[2] / "configs" / "camera.yaml"
    raw = yaml.safe_load(path.read_text())
    bulk = msgspec.convert(raw.pop("bulk"), type=list[BulkChannelConfig])
    mission = decode_mission(yaml.safe_dump(raw))
    check_bulk_channels(bulk, mission.nodes)
    assert [c.name for c in bulk] == ["frame", "flat_field"]
    assert pool_size(bulk, "dn0") == 3 * (4 << 20) + 3 * 4096  # header pushes into a 4 KiB page
    assert bulk[1].shape == (1024, 1024)


def test_counter_region() -> None:
    assert [counter_region(n) for n in ("cn", "dn3", "gn")] == ["cn", "dn3_to_cn", None]


def test_real_pool_exhausted_drops_then_recovers_and_a_reader_never_holds_it(
    session: zenoh.Session,
) -> None:
    # One chunk in the pool. The reader's callback copies a sample out and
    # lets its chunk go at once (the slot holds bytes): an unread sample
    # never holds the owner's pool.
    ch = _ch(type="u8[65536]", slots=1, alloc_timeout_ms=2.0)
    owner = NodeBulk(session, "t", [ch], "dn0", shared_memory=True)
    reader = NodeBulk(session, "t", [ch], "cn", shared_memory=True)
    w, r = owner.writers["cam"], reader.readers["cam"]
    assert w.publish(0, 0)
    assert r._latest is not None and r._latest[1]  # carried in shared memory, copied out
    assert w.publish(1, 0)  # the chunk is free again though the reader has not polled
    assert r.poll() and r.header is not None and r.header.loop == 1
    held = w._alloc()  # someone else holds the one chunk (garbage-collected for it)
    assert held is not None
    assert w.publish(2, 0) is False  # waited ~2 ms, then dropped: no raise, no heap copy
    assert (w.published, w.dropped) == (2, 1)
    del held
    assert w.publish(3, 0)
    assert r.poll() and r.header is not None and r.header.loop == 3
    owner.close()
    reader.close()


# -- the loop's order (zplatform.control.loop owns it; drivers only supply the port) --


class _Port:
    """A BulkPort that notes each call with the loop counter the node's Data
    Vector shows at that moment (set by the logic, so it tells before from after)."""

    def __init__(self, element: str, calls: list[tuple[str, int]]) -> None:
        self.arrays: dict[str, Any] = {}
        self._element = element
        self._calls = calls
        self.dv: Any = None

    def _note(self, what: str) -> None:
        self._calls.append((what, int(self.dv.get(self._element))))

    def receive(self, loop: int) -> None:
        self._note(f"receive {loop}")

    def publish(self, loop: int, t_ns: int) -> None:
        self._note(f"publish {loop}")

    def write_counters(self, dv: Any) -> None:
        self._note("counters")


def test_the_loop_receives_before_its_logic_and_publishes_after() -> None:
    from tests.drive import run_dn_loop
    from zplatform.control.loop import ControlLogic, DeviceLogic
    from zplatform.mission.load import load_mission
    from zplatform.sim.lockstep import sim_keys

    m = load_mission(Path(__file__).resolve().parents[2] / "configs" / "minimal.yaml")
    calls: list[tuple[str, int]] = []
    cn = ControlLogic(m, keys=sim_keys(m))
    port = _Port("cn_loop", calls)
    port.dv = cn.dv
    cn.attach_bulk(port)
    cn.begin(1, 10**9)
    cn.finish()
    # cn_loop is 0 until the logic of loop 1 ran: receive and counters before it.
    assert calls == [("receive 1", 0), ("counters", 0), ("publish 1", 1)]
    calls.clear()
    dn = DeviceLogic(m, "dn0")
    port = _Port("dn0_loop", calls)
    port.dv = dn.dv
    dn.attach_bulk(port)
    run_dn_loop(dn, 1, 10**9)
    assert calls == [("receive 1", 0), ("publish 1", 1), ("counters", 1)]
    calls.clear()
    dn.safe(2 * 10**9, "test")  # a safed DN runs no actuators, but its channels go on
    run_dn_loop(dn, 2, 2 * 10**9)
    assert calls == [("receive 2", 1), ("publish 2", 2), ("counters", 2)]


def test_a_sample_over_both_paths_is_taken_once_and_a_restarted_owner_again(
    session: zenoh.Session,
) -> None:
    """Around a switch between iceoryx2 and zenoh the same sample can come
    over both paths (found by test_camera: published 590, taken 592): it is
    taken once, counted in ``duplicates``; a restarted owner's sequence
    starts again at 0 with later stamps, and is taken."""
    ch = _ch(type="u8[16]")
    reader = NodeBulk(session, "t", [ch], "cn", shared_memory=False)
    r = reader.readers["cam"]

    def sample(seq: int, t_ns: int) -> bytes:
        data = bytearray(ch.sample_bytes)
        HEADER.pack_into(data, 0, ch.layout_id, 0, seq, seq, t_ns)
        return bytes(data)

    assert r._take(sample(4, 400), True)
    assert not r._take(sample(4, 400), True)  # the same, over the other path
    assert not r._take(sample(3, 300), True)  # an older one
    assert r._take(sample(5, 500), True)
    assert r._take(sample(0, 900), True)  # the owner restarted
    assert (r.duplicates, r.missed, r.bad) == (2, 0, 0)
    reader.close()


class _Iox:
    """An iceoryx2 publisher port with one subscriber: it sends every sample
    it loans, and has no sample to loan when ``full``."""

    def __init__(self, *, full: bool = False) -> None:
        self.subscribers = 1
        self.full = full

    def loan(self) -> bytearray | None:
        return None if self.full else bytearray(1)

    def send(self) -> bool:
        return True

    def close(self) -> None:
        pass


def test_a_sample_one_path_carried_and_another_dropped_is_counted_once_each(
    session: zenoh.Session,
) -> None:
    """The defect (test_camera beside the hog: the CN's reader had taken 3
    samples more than dn0 said it published): with a tap subscribed over
    zenoh and its pool full, a sample sent over iceoryx2 was counted neither
    published nor given a new number, so the next one went out under the
    same number. Now a sample a path carried is published and takes the
    next number, and one a path could not carry is dropped, both when both
    happen; a sample no path carried spends no number (the readers' gaps
    are samples some path carried)."""
    sub = session.declare_subscriber("t/dn0/bulk/cam", lambda s: None)  # a tap listens
    w = BulkWriter(session, "t/dn0/bulk/cam", _ch(alloc_timeout_ms=0), _FullProvider())
    iox = _Iox()
    w.iox = iox  # type: ignore[assignment]
    assert w.publish(0, 0) is False  # iceoryx2 carried it, zenoh's pool was full
    assert (w.published, w.dropped, w.published_iox, w._seq) == (1, 1, 1, 1)
    iox.full = True
    assert w.publish(1, 0) is False  # no path carried it: no number spent
    assert (w.published, w.dropped, w._seq) == (1, 2, 1)
    w.iox = None
    w.undeclare()
    sub.undeclare()
