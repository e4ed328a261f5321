"""The CN's flight recorder answering gap-fill requests over zenoh (issue 20):
two in-process sessions on loopback, a recorder with loops 1..100 written."""

from __future__ import annotations

import queue
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.faults.peers import peer_config
from tests.waits import wait_matching, wait_until
from zplatform.control.loop import ControlLogic
from zplatform.core.auth import KeySet
from zplatform.mission.load import decode_mission
from zplatform.recorder import RECORDER_DIR_ENV, open_recorder
from zplatform.recorder.format import (
    MAX_REQUEST_LOOPS,
    REPLY_END,
    REPLY_FRAMES,
    REPLY_LEN,
    REPLY_TOTALS,
    REQUEST,
    REQUEST_MAGIC,
)
from zplatform.recorder.server import RecorderServer
from zplatform.runtime.transport import free_port

ROOT = Path(__file__).resolve().parents[2]
MISSION = decode_mission(
    (ROOT / "configs" / "minimal.yaml").read_text() + "\nrecorder: {}\n", code=False
)
KEYS = KeySet.from_master(MISSION, bytes(range(32)))  # every link, from one master key
EPOCH = 1_700_000_000_000_000_000
KEYEXPR = "rocket/cn/recorder"
NOT_RUN = (50, 51, 52)  # periods the CN "skipped": never recorded, never dropped


class Rig:
    def __init__(self, server: RecorderServer, client: zenoh.Session, frames: dict[int, bytes]):
        self.server, self.client, self.frames = server, client, frames
        self.now = EPOCH + 10**9
        self.channel = KEYS.for_node("tool").channel("telemetry")  # a read-only tool asks

    def request(self, first: int, last: int, *, run: int = EPOCH, t_ns: int | None = None) -> bytes:
        body = REQUEST.pack(REQUEST_MAGIC, run, first, last, self.now if t_ns is None else t_ns)
        return bytes(self.channel.seal(body))

    def ask(self, payload: bytes, timeout_s: float = 10.0) -> list[bytes]:
        replies = self.client.get(
            KEYEXPR,
            payload=payload,
            timeout=timeout_s,
            consolidation=zenoh.ConsolidationMode.NONE,
        )
        return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]


def unpack(replies: list[bytes]) -> tuple[dict[int, bytes], tuple[int, int] | None]:
    """The frames by loop, and the END totals."""
    frames: dict[int, bytes] = {}
    totals = None
    for p in replies:
        if p[0] == REPLY_END:
            totals = REPLY_TOTALS.unpack_from(p, 1)
            continue
        assert p[0] == REPLY_FRAMES
        off = 1
        while off < len(p):
            (n,) = REPLY_LEN.unpack_from(p, off)
            frame = p[off + 4 : off + 4 + n]
            frames[int.from_bytes(frame[7:15], "big")] = frame  # the seq (msgpack 0xcf, u64)
            off += 4 + n
    return frames, totals


@pytest.fixture
def rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp_path))

    def make(serve_bps: int = 10_000_000) -> Rig:
        cn = ControlLogic(MISSION, keys=KEYS, epoch=EPOCH)
        rec = open_recorder(MISSION, "cn", cn.dv, run=EPOCH, authenticated=True)
        frames = {}
        for n in range(1, 101):
            if n in NOT_RUN:
                continue
            cn.begin(n, EPOCH + n * 10_000_000)
            tm = cn.finish()
            assert tm is not None
            frames[n] = bytes(tm)
            rec.frame(n, tm)
        wait_until(lambda: not rec.backlog, 10, "the recorder's writer thread")
        ep = f"tcp/127.0.0.1:{free_port()}"
        a = zenoh.open(peer_config([ep]))
        b = zenoh.open(peer_config(connect=[ep]))
        server = RecorderServer(
            a,
            KEYEXPR,
            rec,
            KEYS.channel("telemetry"),
            now_ns=lambda: EPOCH + 10**9,
            max_age_ns=2 * 10**9,
            serve_bps=serve_bps,
        )
        querier = b.declare_querier(KEYEXPR)
        wait_matching(querier, 10, "the recorder's queryable, declared to b")
        querier.undeclare()
        made.append((server, rec, a, b))
        return Rig(server, b, frames)

    made: list[Any] = []
    yield make
    for server, rec, a, b in made:
        server.close()
        rec.close()
        b.close()
        a.close()


def test_a_range_comes_back_as_the_recorded_frames(rig: Any) -> None:
    r = rig()
    frames, totals = unpack(r.ask(r.request(5, 15)))
    assert frames == {n: r.frames[n] for n in range(5, 16)}
    assert totals == (11, 0, 0)
    # Past what was recorded: what there is, and how much is not held.
    frames, totals = unpack(r.ask(r.request(95, 105)))
    assert sorted(frames) == list(range(95, 101)) and totals == (6, 5, 0)
    # Loops that never ran (skipped periods) are told apart from lost ones.
    frames, totals = unpack(r.ask(r.request(45, 55)))
    assert sorted(frames) == [45, 46, 47, 48, 49, 53, 54, 55] and totals == (8, 0, 3)
    # Another run of the CN: nothing of it here.
    frames, totals = unpack(r.ask(r.request(5, 15, run=EPOCH + 1)))
    assert frames == {} and totals == (0, 11, 0)
    assert r.server.served == 4 and r.server.refused == 0


@pytest.mark.parametrize(
    ("what", "why"),
    [
        ("tag", "bad authentication tag"),
        ("stale", "stamped -3.000 s"),
        ("range", "a range of loops"),
        ("size", "a request of"),
    ],
)
def test_a_request_that_does_not_check_gets_nothing(rig: Any, what: str, why: str) -> None:
    r = rig()
    payload = {
        "tag": r.request(5, 15)[:-1] + b"\x00",
        "stale": r.request(5, 15, t_ns=EPOCH + 4 * 10**9),
        "range": r.request(1, MAX_REQUEST_LOOPS + 1),
        "size": r.request(5, 15) + b"junk",
    }[what]
    assert r.ask(payload, timeout_s=2.0) == []
    assert r.server.refused == 1 and why in r.server.last_refusal


def test_askers_beyond_the_bound_are_dropped_and_replies_are_paced(rig: Any) -> None:
    bps = 40_000  # ~270 bytes per frame: 97 frames take about 0.65 s
    r = rig(serve_bps=bps)
    done: queue.SimpleQueue[int] = queue.SimpleQueue()
    start = time.monotonic()

    def asker(k: int) -> None:
        replies: list[bytes] = []

        def on_reply(rep: zenoh.Reply) -> None:
            if rep.ok is not None:
                replies.append(rep.ok.payload.to_bytes())

        r.client.get(
            KEYEXPR,
            zenoh.handlers.Callback(on_reply, lambda: done.put(len(replies)), indirect=False),
            payload=r.request(1, 100 - k),  # four requests, not one replayed
            timeout=30,
            consolidation=zenoh.ConsolidationMode.NONE,
        )

    for k in range(4):  # at once: two are taken, two are turned away
        asker(k)
    answered = sorted(done.get(timeout=40) for _ in range(4))
    elapsed = time.monotonic() - start
    assert answered[:2] == [0, 0] and answered[2] > 0 and answered[3] > 0
    assert r.server.busy == 2 and r.server.served == 2
    # Two answers of ~26 kB each at 40 kB/s: no faster than the rate allows.
    assert elapsed >= 2 * 97 * 270 / bps * 0.9
