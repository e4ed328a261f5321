"""The sync over the intra-host link (zplatform.runtime.sync: ShmLink,
DeviceSync.attach_shm; docs/architecture.md#intra-host), both ends in this process on
one zenoh session and real iceoryx2 services: the trigger and reply take
shared memory once a reply passed the intake, fall back to zenoh in the
same loop when the DN's end is gone, come back after RETRY_LOOPS, and a
forged or replayed frame over shared memory is refused and counted by the
same intake as over zenoh."""

from __future__ import annotations

import queue
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.waits import wait_until
from tests.zsession import lone_session
from zplatform.config import Mission
from zplatform.control.intake import CnRefusals, ReplyCheck, TriggerIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import TAG_LEN, channel
from zplatform.mission.load import load_mission
from zplatform.runtime import sync as sync_mod
from zplatform.runtime.intrahost import (
    IntraHostClient,
    IntraHostServer,
    LinkNames,
    link_names,
    mission_link_sizes,
)
from zplatform.runtime.sync import ControlSync, DeviceSync, ShmLink
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import sim_keys

MINIMAL = Path(__file__).resolve().parents[2] / "configs" / "minimal.yaml"
T0 = 10**9
PERIOD = 10**7


@dataclass
class Pair:
    m: Mission
    cn: ControlLogic
    dn: DeviceLogic
    cs: ControlSync
    ds: DeviceSync
    link: ShmLink
    intake: TriggerIntake[Any]
    names: LinkNames
    sizes: tuple[int, int]

    def loop(self, loop: int) -> bool:
        """One loop: the DN serves on a thread, the CN syncs; whether the
        CN got every reply."""
        served = threading.Thread(target=self.ds.wait, args=(self.dn, 10.0))
        served.start()
        self.cs.sync(self.cs.begin(self.cn, loop, T0 + loop * PERIOD), self.cn)
        served.join()
        ok = self.cn.pending == 0
        self.cn.finish()
        return ok


@pytest.fixture
def pair() -> Iterator[Pair]:
    m = load_mission(MINIMAL)
    sim = sim_keys(m)
    cn = ControlLogic(m, keys=sim)
    dn = DeviceLogic(m, "dn0", keys=sim)
    names = link_names(f"t{uuid.uuid4().hex[:12]}", m.vehicle, "1", "cn", "dn0")
    sizes = mission_link_sizes(m, "dn0")
    session = lone_session()
    keys = KeySpace(m.vehicle)
    # The DN's clock: a period per read, from the CN's first loop on (the
    # intake's bound ahead and the logic's staleness both hold).
    now = iter(range(T0, 100 * T0, PERIOD // 4)).__next__
    intake: TriggerIntake[Any] = TriggerIntake(m, "dn0", channel(sim, "cn_to_dn0"), now)
    ds = DeviceSync(
        session,
        keys,
        "dn0",
        now,
        intake=intake,
        shm=IntraHostServer(names, *sizes),
        path=dn.dv.handle("dn0_sync_path"),
    )
    # Generous deadlines: these check what happens, not how fast.
    link = ShmLink("dn0", IntraHostClient(names, *sizes, deadline_s=2.0))
    cs = ControlSync(
        session,
        keys,
        ["dn0"],
        2_000_000_000,
        2.0,
        checks=[ReplyCheck(m, "dn0", channel(sim, "dn0_to_cn"))],
        shm=[link],
    )
    try:
        yield Pair(m, cn, dn, cs, ds, link, intake, names, sizes)
    finally:
        cs.close()
        ds.close()
        session.close()


def changes(cs: ControlSync) -> list[tuple[str, str]]:
    out: list[tuple[str, str, str]] = []
    cs.take_path_changes(out)
    return [(dn, path) for dn, path, _ in out]


def test_the_sync_takes_shared_memory_once_a_reply_passed_the_intake(pair: Pair) -> None:
    hops: list[str] = []
    pair.cs._trace = lambda h, n: hops.append(h)
    for loop in (1, 2, 3):
        assert pair.loop(loop)
    assert pair.link.on_shm and pair.link.tries == 1
    assert pair.link.client.replies == 3
    # Nothing came back over zenoh ("back" is zenoh's thread handing a reply over).
    assert hops == ["issued", "taken"] * 3
    # The path is in the DN's reply, so in the CN's vector (telemetry).
    assert pair.dn.dv.get_name("dn0_sync_path") == "shm"
    assert pair.cn.dv.get_name("dn0_sync_path") == "shm"
    assert int(pair.cn.dv.get("cn_missed_dn0")) == 0
    assert changes(pair.cs) == [("dn0", "shm")]
    assert pair.cs.paths() == ["shm"]


def test_the_shared_memory_path_marks_the_trace_points_with_its_frames(pair: Pair) -> None:
    """bench.bandwidth sizes its raw floors, and bench.frame_trace splits a
    loop, from these points: unmarked over shared memory, the floors moved
    0-byte frames beside a 100,000-element point."""
    from zplatform import trace

    assert pair.loop(1)  # zenoh's first reply puts the link on shared memory
    ring = trace.Ring(256)
    trace.install(ring)
    served = threading.Thread(target=pair.ds.wait, args=(pair.dn, 10.0))
    served.start()
    try:
        frames = pair.cs.begin(pair.cn, 2, T0 + 2 * PERIOD)
        trigger = len(frames[0])
        pair.cs.sync(frames, pair.cn)
    finally:
        trace.uninstall()
        served.join()
    assert pair.cn.pending == 0 and pair.link.client.replies == 2
    marks = [(name, n, v) for name, n, v, _t in ring.records() if name.startswith("sync.")]
    reply = pair.dn.reply_length  # the DN's reply frame, every loop the same length
    assert marks == [
        ("sync.issued", 0, trigger),
        ("sync.sent", 0, 0),
        ("sync.back", 0, reply),
        ("sync.shm", 0, 0),
        ("sync.taken", 0, 0),
    ]


def test_a_dead_shm_server_falls_back_to_zenoh_in_the_same_loop_and_returns(
    pair: Pair, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sync_mod, "RETRY_LOOPS", 3)
    assert pair.loop(1) and pair.link.on_shm
    server = pair.ds.detach_shm()  # the DN's end goes; its node and zenoh stay
    assert server is not None
    server.close()
    # The next trigger finds no server and goes over zenoh at once: no loop lost.
    for loop in (2, 3, 4):
        assert pair.loop(loop)
        assert pair.dn.dv.get_name("dn0_sync_path") == "zenoh"
    assert not pair.link.on_shm and pair.link.fallbacks == 1
    assert changes(pair.cs) == [("dn0", "shm"), ("dn0", "zenoh")]
    # The DN's end comes back (a restarted DN): after RETRY_LOOPS loops the
    # CN tries shared memory again, and the reply passes: back on it.
    pair.ds.attach_shm(IntraHostServer(pair.names, *pair.sizes))
    for loop in range(5, 9):
        assert pair.loop(loop)
    assert pair.link.on_shm and pair.dn.dv.get_name("dn0_sync_path") == "shm"
    assert changes(pair.cs) == [("dn0", "shm")]
    assert int(pair.cn.dv.get("cn_missed_dn0")) == 0


def test_a_forged_reply_over_shared_memory_is_refused_and_counted(pair: Pair) -> None:
    """Someone else's server on the link (the DN's closed): its reply of the
    right size fails the tag check, is counted like a bad reply over zenoh,
    and the link is never used: zenoh carries the loops."""
    server = pair.ds.detach_shm()
    assert server is not None
    server.close()
    forger = IntraHostServer(pair.names, *pair.sizes)
    stop = threading.Event()

    def forge() -> None:
        while not stop.is_set():
            if forger.wait(0.05) is not None:
                forger.respond(bytes(pair.sizes[1] - 4))

    t = threading.Thread(target=forge)
    t.start()
    try:
        # The CN's first try goes to the forger: no valid reply, the loop is lost.
        served = threading.Thread(target=pair.ds.wait, args=(pair.dn, 0.2))
        served.start()
        pair.cs.sync(pair.cn.begin(1, T0 + PERIOD), pair.cn)
        served.join()
        assert pair.cn.pending == 1
        refused = CnRefusals()
        pair.cs.take_refusals(refused)
        assert (refused.reply_size, refused.reply_bad, refused.reply_stale) == (0, 1, 0)
        assert pair.link.refused == 1 and not pair.link.on_shm
        pair.cn.finish()
        # The next loops go over zenoh (the try waits RETRY_LOOPS).
        for loop in (2, 3):
            assert pair.loop(loop)
        assert pair.dn.dv.get_name("dn0_sync_path") == "zenoh"
        assert changes(pair.cs) == []  # never verified: no path change to tell
    finally:
        stop.set()
        t.join()
        forger.close()


def test_junk_and_replayed_triggers_over_shared_memory_meet_the_same_intake(pair: Pair) -> None:
    """A local process writing into the DN's service: junk is refused (bad
    tag), a genuine trigger replayed is refused (stale), neither answered;
    each counted in the DN's ``dn0_bad_frames`` as over zenoh, and the next
    genuine loop runs."""
    frame = bytes(pair.cn.begin(1, T0 + PERIOD)[0])
    pair.cn.finish()  # loop 1 was begun only for its frame: one miss
    assert pair.loop(2)  # over shared memory, verified
    attacker = IntraHostClient(pair.names, *pair.sizes, deadline_s=0.05)
    try:
        for k, sent in enumerate((bytes(len(frame)), frame), start=1):  # junk; loop 1's, stale
            buf = attacker.trigger(len(sent))
            assert buf is not None
            buf[:] = sent
            assert attacker.send()  # queued in the DN's service before the DN waits
            # The DN's wait takes it, refuses it, waits out its timeout unanswered.
            assert not pair.ds.wait(pair.dn, 0.05)
            assert attacker.collect() is None
            assert int(pair.dn.dv.get("dn0_bad_frames")) == k
    finally:
        attacker.close()
    assert pair.loop(3)
    assert pair.link.on_shm and pair.dn.dv.get_name("dn0_sync_path") == "shm"
    assert int(pair.cn.dv.get("cn_missed_dn0")) == 1


def test_a_dn_waiting_on_its_link_is_woken_by_zenoh_triggers(pair: Pair) -> None:
    """A CN that syncs over zenoh (its link off) with a DN whose loop
    thread blocks in the link's listener: zenoh's admitted triggers wake it
    (the mailbox's waker notifies the listener from zenoh's thread), each
    loop runs, and the path says zenoh."""
    cs = ControlSync(
        pair.cs.session,
        KeySpace(pair.m.vehicle),
        ["dn0"],
        2_000_000_000,
        2.0,
        checks=[ReplyCheck(pair.m, "dn0", channel(sim_keys(pair.m), "dn0_to_cn"))],
    )
    own, pair.cs = pair.cs, cs  # the fixture's (never used here) closes last
    try:
        for loop in (1, 2, 3):
            assert pair.loop(loop)
    finally:
        cs.close()
        pair.cs = own
    assert pair.ds.shm is not None
    assert pair.dn.dv.get_name("dn0_sync_path") == "zenoh"
    assert int(pair.cn.dv.get("cn_rx_dn0")) == 3


def test_taps_see_the_frames_whichever_path_the_sync_takes(pair: Pair) -> None:
    """A tool subscribed to ``dn0/to_dn``'s and ``dn0/to_cn``'s taps gets
    each loop's trigger and reply over zenoh while the sync itself takes
    shared memory: what ``tap`` sees does not change."""
    keys = KeySpace(pair.m.vehicle)
    session = pair.cs.session
    down: queue.Queue[bytes] = queue.Queue()
    up: queue.Queue[bytes] = queue.Queue()
    subs = [
        session.declare_subscriber(keys.cn_to_dn("dn0"), lambda s: down.put(s.payload.to_bytes())),
        session.declare_subscriber(keys.dn_to_cn("dn0"), lambda s: up.put(s.payload.to_bytes())),
    ]
    try:
        # The taps learn of the subscribers from zenoh's matching listeners.
        taps = [pair.cs._taps[0], pair.ds._tap]
        wait_until(lambda: all(t.matching for t in taps), 10, "both taps' subscribers")
        frames = []
        for loop in (1, 2, 3):
            served = threading.Thread(target=pair.ds.wait, args=(pair.dn, 10.0))
            served.start()
            # A tap subscribes: the trigger is framed in the logic's buffer
            # (not lent), so the tap can read it after the send.
            frame = pair.cs.begin(pair.cn, loop, T0 + loop * PERIOD)
            assert isinstance(frame[0], bytearray)
            frames.append(bytes(frame[0]))
            pair.cs.sync(frame, pair.cn)
            served.join()
            assert pair.cn.pending == 0
            pair.cn.finish()
        assert pair.link.on_shm
        # zenoh hands the samples over on its own thread: each is waited for.
        assert [down.get(timeout=10) for _ in frames] == frames
        assert len([up.get(timeout=10) for _ in frames]) == 3
        assert down.empty() and up.empty()
    finally:
        for s in subs:
            s.undeclare()


def test_frames_over_shared_memory_are_checked_and_decoded_in_place(
    pair: Pair, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Copies to the fewest (docs/architecture.md#intra-host): each end's
    intake checks the frame where it arrived and its logic decodes it from
    there (a view on the loaned sample, not a copy in bytes), and the DN's
    trigger stays readable until its loop ran: the setpoint lands."""
    kinds: list[tuple[str, type]] = []
    dn_trigger, cn_reply = pair.dn.trigger, pair.cn.reply

    def on_trigger(payload: Any, *a: Any, **k: Any) -> Any:
        kinds.append(("trigger", type(payload)))
        return dn_trigger(payload, *a, **k)

    def on_reply(i: int, payload: Any) -> bool:
        kinds.append(("reply", type(payload)))
        return cn_reply(i, payload)

    monkeypatch.setattr(pair.dn, "trigger", on_trigger)
    monkeypatch.setattr(pair.cn, "reply", on_reply)
    for loop in (1, 2, 3):
        pair.cn.dv.set("dn0_setpoint", 1.5 * loop)
        assert pair.loop(loop)
        pair.dn.run(T0 + loop * PERIOD)
        assert pair.dn.dv.get("dn0_setpoint") == 1.5 * loop
    assert pair.link.on_shm and pair.link.client.replies == 3
    assert kinds == [("trigger", memoryview), ("reply", memoryview)] * 3


def test_triggers_and_replies_are_framed_straight_in_their_loans(
    pair: Pair, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No copy of a frame into shared memory (docs/architecture.md#intra-host):
    the CN's trigger is encoded and tagged in its loaned sample (what
    ``ControlSync.begin`` returns is that sample), the DN's reply in its
    loaned reply (sent as it is, never copied in by ``respond``), and the
    bytes are those of the copy path, bit for bit: a twin logic framing the
    same loop in its own buffer writes the same trigger, and the CN takes
    the DN's reply (tag checked) into the same region bytes."""
    loaned: list[memoryview] = []
    copied: list[int] = []
    client, server = pair.link.client, pair.ds.shm
    assert server is not None
    lend, respond = client.trigger, server.respond

    def spy_trigger(n: int) -> Any:
        view = lend(n)
        loaned.append(view)
        return view

    def spy_respond(frame: Any) -> bool:
        copied.append(len(frame))
        return respond(frame)

    monkeypatch.setattr(client, "trigger", spy_trigger)
    monkeypatch.setattr(server, "respond", spy_respond)
    twin = ControlLogic(pair.m, keys=sim_keys(pair.m))
    for loop in (1, 2, 3):
        t = T0 + loop * PERIOD
        pair.cn.dv.set("dn0_setpoint", 0.25 * loop)
        twin.dv.set("dn0_setpoint", 0.25 * loop)
        served = threading.Thread(target=pair.ds.wait, args=(pair.dn, 10.0))
        served.start()
        frames = pair.cs.begin(pair.cn, loop, t)
        sent = bytes(frames[0])
        own = frames[0] is loaned[-1] if loaned else False
        pair.cs.sync(frames, pair.cn)
        served.join()
        assert own, "the trigger is the loaned sample itself"
        assert sent == bytes(twin.begin(loop, t)[0])
        assert pair.cn.pending == 0
        assert bytes(pair.cn.dv.region_view("dn0_to_cn")) == bytes(
            pair.dn.dv.region_view("dn0_to_cn")
        )
        pair.dn.run(t)
        assert pair.dn.dv.get("dn0_setpoint") == 0.25 * loop
        pair.cn.finish()
        twin.finish()
    assert pair.link.on_shm and client.replies == 3 and server.replied == 3
    assert len(loaned) == 3 and copied == []  # every reply went in its own loan
    assert pair.ds.reply is None  # gone with its sample: nobody keeps it


def test_a_dn_that_keeps_its_replies_copies_them_into_the_loan(pair: Pair) -> None:
    """A DN whose flight recorder keeps every reply (``keep_reply``) frames it
    in the logic's buffer, which stays readable after the send, and copies it
    into the loaned reply: the recorder gets the bytes the CN took."""
    pair.ds.keep_reply = True
    for loop in (1, 2):
        assert pair.loop(loop)
        assert isinstance(pair.ds.reply, bytearray)
        kept = bytes(pair.ds.reply)
        assert bytes(pair.cn.dv.region_view("dn0_to_cn")) == bytes(
            pair.dn.dv.region_view("dn0_to_cn")
        )
        assert kept[: len(kept) - TAG_LEN].endswith(bytes(pair.dn.dv.region_view("dn0_to_cn")))
    assert pair.link.on_shm
