"""The generated fault suite: every tagged frame of every key a mission uses,
fed to the intake that guards it (in process, no network).

The plan is the key space (zplatform/security/keyspace.py): for each row of the
shipped flight and recovery_igniter missions, expanded per device node and
per node (:func:`zplatform.security.keyspace.expand_keys`), and each frame of it
that carries a tag, the row's intake gets

* junk of its longest accepted length, one byte over, of 0 and of 1 byte;
* a genuine frame with a bad tag;
* a same-run replay of a genuine frame it admitted;
* a genuine-format frame, tagged with the right key (an insider's), with the
  largest and then the smallest integer in every header field (u64/i64
  extremes; a field that only selects the channel, the node index, is kept);

and each must be refused and counted exactly once, never raise; after an
extreme frame the next genuine one must still be admitted (a frame stamped
at the end of time must not lock the receiver out).

A row whose frame has no recipe here fails (:data:`RECIPES`): a new channel
brings its recipe. What an intake cannot refuse yet is an
``xfail(strict=True)`` with the reason (:attr:`Harness.gaps`), so it turns
into a failure, to be unmarked, the day it is fixed.
"""

from __future__ import annotations

import os
import struct
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import blake3
import pytest

from tests.payload import Bytes, FakeSession, deliver
from zplatform.archive import Archive
from zplatform.archive import Query as ArchiveQuery
from zplatform.archive.server import ASK as ARCHIVE_ASK
from zplatform.archive.server import MAX_ASK, ArchiveAsk, ArchiveServer
from zplatform.archive.server import REPLY as ARCHIVE_REPLY
from zplatform.archive.server import SESSION_BODY as ARCHIVE_SESSION
from zplatform.archive.server import ask_payload as archive_ask
from zplatform.config import Mission
from zplatform.control.failover import Standby
from zplatform.control.fencing import ASK, NONCE_LEN, ask_frame, new_nonce
from zplatform.control.handoff import Waker
from zplatform.control.intake import (
    MirrorIntake,
    ProbeIntake,
    ReplyCheck,
    RequestIntake,
    TelemetryIntake,
    TriggerIntake,
    ahead_bound_ns,
)
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import Uplink
from zplatform.core.auth import KEY_ENV, TAG_LEN, KeySet, Run, channel
from zplatform.core.codec import BundleEncoder, decode_frame, encode_frame
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import Event, EventLog, encode_event
from zplatform.ground.gapfill import GapFill
from zplatform.ground.logic import EventGap, Gap, GroundLogic
from zplatform.mission.load import load_mission
from zplatform.recorder.format import (
    REPLY_BYTES,
    REPLY_EVENTS,
    REPLY_FRAMES,
    REPLY_LEN,
    REQUEST,
    REQUEST_MAGIC,
)
from zplatform.recorder.server import RecorderServer
from zplatform.runtime.bulk import HEADER as BULK_HEADER
from zplatform.runtime.bulk import SUMMARY_BYTES, BulkReader, body_digest, bulk_key, summary_of
from zplatform.runtime.clocksync import RUN_ANSWER, ClockLink, ClockResponder, RunAsker
from zplatform.security.keyspace import ExpandedKey, KeyFrames, expand_keys

ROOT = Path(__file__).resolve().parents[2]
# camera: the shipped mission with bulk channels (the bulk row's recipe).
MISSIONS = {
    n: load_mission(ROOT / "configs" / f"{n}.yaml")
    for n in ("flight", "recovery_igniter", "camera")
}
MASTER = bytes.fromhex(os.environ[KEY_ENV])
T0 = 1_700_000_000_000_000_000
EPOCH = 77

U64_MAX, I64_MAX, I64_MIN = (1 << 64) - 1, (1 << 63) - 1, -(1 << 63)
U32_MAX = (1 << 32) - 1
CASES = (
    "junk_max",
    "junk_over",
    "junk_empty",
    "junk_one",
    "bad_tag",
    "replay",
    "extreme_max",
    "extreme_min",
    "extreme_stamp",
    "replay_old_run",
)
DAY = 86_400 * 10**9


def _keys(m: Mission) -> KeySet:
    return KeySet.from_master(m, MASTER)


def _junk(n: int) -> bytes:
    """``n`` bytes of deterministic junk (no valid tag, no valid frame)."""
    return bytes((i * 131 + 7) & 0xFF for i in range(n))


def _reframe(tagged: bytes, hi: bool, key: Any) -> bytes:
    """A region frame with the data of ``tagged`` (a genuine frame) and every
    header integer at its largest (``hi``) or smallest, tagged with ``key``."""
    data = bytes(decode_frame(tagged[:-TAG_LEN]).data)
    frame = (
        encode_frame(U32_MAX, U64_MAX, I64_MAX, data) if hi else encode_frame(0, 0, I64_MIN, data)
    )
    return bytes(key.seal(frame))


def _restamp(tagged: bytes, key: Any, seq: int | None = None) -> bytes:
    """``tagged`` (a genuine region frame) stamped at i64 max (and loop
    ``seq``, by default u64 max), everything else as it was, tagged with ``key``."""
    f = decode_frame(tagged[:-TAG_LEN])
    s = U64_MAX if seq is None else seq
    return bytes(key.seal(encode_frame(f.layout_id, s, I64_MAX, bytes(f.data))))


class Harness(ABC):
    """One frame kind's intake, fed in process (module doc).

    ``kinds``: the counters the intake keeps (of ``size``, ``bad``,
    ``stale``); ``max_len``: the longest payload its size check takes;
    :meth:`genuine`: a new genuine frame, newer than every one before;
    :meth:`feed`: True when the intake admitted the payload; :meth:`counts`:
    its counters so far; :meth:`advance`: the receiver moves past the frame
    it just admitted (a new exchange, the next loop asked);
    :meth:`extreme`: a genuine-format frame, with the right tag, every
    header integer at an extreme. ``gaps(mission)``: the cases it cannot
    refuse yet, with why."""

    kinds: ClassVar[tuple[str, ...]] = ("size", "bad", "stale")
    max_len: int

    @classmethod
    def gaps(cls, m: Mission) -> dict[str, str]:
        return {}

    @classmethod
    def by_design(cls) -> dict[str, str]:
        """Cases this frame is answered in on purpose, with why: the test
        then asserts that answer is harmless (:meth:`harmless`), not a refusal."""
        return {}

    def harmless(self, old: Harness | None) -> None:
        """Assert the :meth:`by_design` cases' answers change nothing
        (``old``: the earlier run's harness, for ``replay_old_run``)."""
        raise NotImplementedError

    @abstractmethod
    def genuine(self) -> bytes: ...

    @abstractmethod
    def feed(self, payload: bytes) -> bool: ...

    @abstractmethod
    def counts(self) -> dict[str, int]: ...

    @abstractmethod
    def extreme(self, hi: bool) -> bytes: ...

    @abstractmethod
    def stamp_max(self) -> bytes:
        """A genuine frame whose freshness fields alone (its loop, stamp,
        number) are at their largest: what a key holder's bug or a stepped
        clock sends."""

    def advance(self) -> None:
        """By default the receiver needs no telling."""
        return None

    def close(self) -> None:
        """By default nothing to release."""
        return None


class _IntakeCounts:
    """Counts of a zplatform.control.intake.Intake, accumulated across take_counts()."""

    intake: Any

    def counts(self) -> dict[str, int]:
        s, b, t = self.intake.take_counts()
        c = self._c = getattr(self, "_c", {"size": 0, "bad": 0, "stale": 0})
        c["size"] += s
        c["bad"] += b
        c["stale"] += t
        return dict(c)


def _learn_run(m: Mission, node: str, keys: KeySet, t0: int, run: Run | None = None) -> Run:
    """The run of the control node that started at ``t0`` (its ``cn_epoch``),
    as ``node`` (a device node, or the standby ``cn_b``) learns it: one clock
    exchange, a hello, with that control node's clock server
    (zplatform.runtime.clocksync). Into ``run`` if given."""
    link = ClockLink(m, node, keys, run=run)
    responder = ClockResponder(m, keys, Run(t0))
    query, nonce = link.query(t0)
    reply = responder.answer(query, t0, t0 + 1)
    assert reply is not None and link.check(reply, nonce) is not None
    assert link.run.epoch == t0
    return link.run


def _ground_run(m: Mission, keys: KeySet, t0: int) -> Run:
    """The run of the control node that started at ``t0``, as the ground
    learns it: its run hello, answered by that control node's clock server
    (zplatform.runtime.clocksync.RunAsker)."""
    asker = RunAsker(keys)
    answer = ClockResponder(m, keys, Run(t0)).answer(asker.hello(), t0, t0 + 1)
    assert answer is not None and asker.check(answer) and asker.run.epoch == t0
    return asker.run


class TriggerH(_IntakeCounts, Harness):
    """A DN's triggers (TriggerIntake), alone or in a wildcard sync bundle."""

    def __init__(self, m: Mission, dn: str, bundle: bool = False, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys, self.bundle = m, _keys(m), bundle
        self.i = m.device_nodes.index(dn)
        self.ch = channel(self.keys, f"cn_to_{dn}", Run(t0))  # the CN's, for extremes
        # The DN's intake is bound to the run its clock exchange told.
        run = _learn_run(m, dn, self.keys, t0)
        self.intake: TriggerIntake[None] = TriggerIntake(
            m, dn, channel(self.keys, f"cn_to_{dn}", run)
        )
        self.max_len = self.intake.max_len
        self.cn = ControlLogic(m, keys=self.keys, epoch=self.t0)
        self.n = 0

    def _frames(self) -> list[bytes]:
        self.n += 1
        return [bytes(f) for f in self.cn.begin(self.n, self.t0 + self.n * self.m.period_ns)]

    def genuine(self) -> bytes:
        frames = self._frames()
        return bytes(BundleEncoder().pack(frames)) if self.bundle else frames[self.i]

    def feed(self, payload: bytes) -> bool:
        return self.intake.admit(Bytes(payload), None)

    def extreme(self, hi: bool) -> bytes:
        return _reframe(self._frames()[self.i], hi, self.ch)

    def stamp_max(self) -> bytes:
        return _restamp(self._frames()[self.i], self.ch)


class ReplyH(_IntakeCounts, Harness):
    """The CN's check of a sync reply from an unknown session (ReplyCheck)."""

    def __init__(self, m: Mission, dn: str, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.i = m.device_nodes.index(dn)
        self.ch = channel(self.keys, f"{dn}_to_cn", Run(t0))  # the DN's, for extremes
        self.intake = ReplyCheck(m, dn, channel(self.keys, f"{dn}_to_cn", Run(t0)))
        self.max_len = self.intake.max_len
        self.cn = ControlLogic(m, keys=self.keys, epoch=self.t0)
        self.dn = DeviceLogic(m, dn, keys=self.keys)
        self.n = 0

    def genuine(self) -> bytes:
        self.n += 1
        t = self.t0 + self.n * self.m.period_ns
        reply = self.dn.trigger(bytes(self.cn.begin(self.n, t)[self.i]), t)
        assert reply is not None
        self.intake.expect(self.n, t)
        return bytes(reply)

    def advance(self) -> None:
        self.intake.expect(self.n + 1, self.t0 + (self.n + 1) * self.m.period_ns)

    def _stamp_seq(self) -> int | None:
        return self.n  # the loop asked, stamped at the end of time

    def feed(self, payload: bytes) -> bool:
        return self.intake.check(Bytes(payload), None) is not None

    def extreme(self, hi: bool) -> bytes:
        return _reframe(self.genuine(), hi, self.ch)

    def stamp_max(self) -> bytes:
        return _restamp(self.genuine(), self.ch, self._stamp_seq())


class RequestH(_IntakeCounts, Harness):
    """The CN's command requests (RequestIntake)."""

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.ch = channel(self.keys, "gn_to_cn")
        self.last = 0
        self.epoch = EPOCH if t0 == T0 else EPOCH - 1  # an earlier run of the CN
        self.intake = RequestIntake(m, self.ch, self.epoch, lambda: self.last, 16)
        self.max_len = self.intake.max_len
        self.up = Uplink(m, self.keys)
        self.n = 0
        lay = Layout.for_node(m, "cn")
        self.up_layout = lay.region("gn_to_cn").layout_id
        base = lay.region("gn_to_cn").offset
        self._num = [
            (lay.element(e).offset - base, lay.element(e).scalar.struct)
            for e in ("gn_cmd_epoch", "gn_cmd_seq")
        ]

    def genuine(self) -> bytes:
        self.n += 1
        return bytes(self.up.frame("NOOP", self.n, 0, 0.0, self.t0 + self.n, self.epoch))

    def advance(self) -> None:
        self.last = self.n  # the loop took it

    def feed(self, payload: bytes) -> bool:
        return self.intake.admit(Bytes(payload), None)

    def extreme(self, hi: bool) -> bytes:
        # The request's own numbers (its run and number) are header fields too.
        data = bytearray(decode_frame(self.genuine()[:-TAG_LEN]).data)
        for off, fmt in self._num:
            size = struct.calcsize(fmt)
            signed = fmt.islower()
            v = ((1 << (8 * size - 1)) - 1 if signed else (1 << (8 * size)) - 1) if hi else 0
            v = v if hi or not signed else -(1 << (8 * size - 1))
            struct.pack_into("<" + fmt, data, off, v)
        frame = (
            encode_frame(U32_MAX, U64_MAX, I64_MAX, data)
            if hi
            else encode_frame(0, 0, I64_MIN, data)
        )
        assert self.ch is not None
        return bytes(self.ch.seal(frame))

    def stamp_max(self) -> bytes:
        # This run, the highest number a request may carry.
        off, fmt = self._num[1]
        data = bytearray(decode_frame(self.genuine()[:-TAG_LEN]).data)
        struct.pack_into("<" + fmt, data, off, (1 << (8 * struct.calcsize(fmt))) - 1)
        assert self.ch is not None
        return bytes(self.ch.seal(encode_frame(self.up_layout, self.n, I64_MAX, data)))


class TelemetryH(_IntakeCounts, Harness):
    """The ground's telemetry (TelemetryIntake)."""

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.ch = channel(self.keys, "telemetry", Run(t0))  # the CN's, for extremes
        run = _ground_run(m, self.keys, t0)  # a ground bound to the run it learned
        self.intake = TelemetryIntake(m, channel(self.keys, "telemetry", run), 8, 10**9)
        self.max_len = self.intake.max_len
        self.cn = ControlLogic(m, keys=self.keys, epoch=self.t0)
        self.n = 0

    # No gaps: an earlier run's snapshot is refused by the run the ground
    # learned (and, a day old, by its clock bound too), a far-ahead one by
    # the clock bound.

    def genuine(self) -> bytes:
        self.n += 1
        self.cn.begin(self.n, self.t0 + self.n * self.m.period_ns)
        return bytes(self.cn.telemetry())

    def feed(self, payload: bytes) -> bool:
        return self.intake.admit(Bytes(payload), self.t0 + self.n * self.m.period_ns)

    def extreme(self, hi: bool) -> bytes:
        return _reframe(self.genuine(), hi, self.ch)

    def stamp_max(self) -> bytes:
        return _restamp(self.genuine(), self.ch, self._stamp_seq())

    def _stamp_seq(self) -> int | None:
        return None


class EventH(Harness):
    """The ground's event records (EventReader, counted by GroundLogic)."""

    kinds = ("bad", "stale")

    def __init__(self, m: Mission, node: str, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys, self.node = m, _keys(m), node
        self.ch = channel(self.keys, f"events_{node}", Run(t0))  # the node's, in run t0
        self.logic = GroundLogic(m, keys=self.keys, run=_ground_run(m, self.keys, t0))
        self.key = f"{m.vehicle}/{node}/events"
        self.max_len = 4096
        self.n = 0

    def _record(self, seq: int, t_ns: int, severity: int) -> bytes:
        assert self.ch is not None
        body = encode_event(Event(self.node, seq, t_ns, severity, "bad_frame", "x"))
        return bytes(self.ch.seal(body))

    def genuine(self) -> bytes:
        self.n += 1
        return self._record(self.n, self.t0 + self.n, 2)

    def feed(self, payload: bytes) -> bool:
        return self.logic.on_event_bytes(self.key, payload, self.t0) is not None

    def counts(self) -> dict[str, int]:
        c = self.logic.counters
        return {"bad": c.bad_events, "stale": c.stale_events}

    def extreme(self, hi: bool) -> bytes:
        if hi:
            return self._record(U64_MAX, I64_MAX, U64_MAX)
        return self._record(0, I64_MIN, 0)

    def stamp_max(self) -> bytes:
        return self._record(U64_MAX, I64_MAX, 2)


class _NoSession:
    """A zenoh session as a BulkReader declares on it (nothing is delivered:
    the harness feeds the intake)."""

    def declare_subscriber(self, *a: Any, **k: Any) -> Any:
        return SimpleNamespace(undeclare=lambda: None)


class BulkH(Harness):
    """A bulk channel's samples at one of its readers (BulkReader's intake,
    the one both paths share: size, its tag's header, freshness, rate
    bound, then the pass over the array)."""

    kinds = ("bad", "stale")

    def __init__(self, m: Mission, owner: str, channel: str, reader: str, t0: int = T0) -> None:
        (self.bc,) = [c for c in m.bulk if c.name == channel]
        self.t0, self.m, self.keys = t0, m, _keys(m)
        # The owner's tags (one per reader), in run t0.
        self.tags = [self.keys.channel(f"bulk_{channel}/{r}", Run(t0)) for r in self.bc.readers]
        self.now = t0
        self.r = BulkReader(
            _NoSession(),  # type: ignore[arg-type]
            bulk_key(m.vehicle, self.bc),
            self.bc,
            auth=self.keys.for_node(reader).channel(f"bulk_{channel}/{reader}", Run(t0)),
            now_ns=lambda: self.now,
            ahead_ns=ahead_bound_ns(m),
        )
        self.max_len = self.bc.sample_bytes + TAG_LEN * len(self.bc.readers)
        self.n = 0

    def _sample(self, seq: int, loop: int, t_ns: int, flags: int = 0) -> bytes:
        n = self.bc.sample_bytes
        data = bytearray(n)
        BULK_HEADER.pack_into(data, 0, self.bc.layout_id, flags, seq, loop, t_ns)
        summary = bytearray(SUMMARY_BYTES + TAG_LEN)
        summary_of(summary, data, n)
        digest = body_digest(blake3.blake3(), memoryview(data)[BULK_HEADER.size :])
        summary[SUMMARY_BYTES - len(digest) : SUMMARY_BYTES] = digest
        for ch in self.tags:
            data += ch.seal_tail(summary)[SUMMARY_BYTES:]
        return bytes(data)

    def genuine(self) -> bytes:
        self.n += 1
        # One sample every rate_divisor loops, as its owner publishes them.
        self.now = self.t0 + self.n * self.bc.rate_divisor * self.m.period_ns
        return self._sample(self.n, self.n * self.bc.rate_divisor, self.now)

    def feed(self, payload: bytes) -> bool:
        self.r._polls += self.bc.rate_divisor  # the reader's loops since the last sample
        return self.r._take(payload, True)

    def counts(self) -> dict[str, int]:
        # A sample taken already (a replay in this run) is refused as a duplicate.
        return {"bad": self.r.bad, "stale": self.r.stale + self.r.duplicates}

    def extreme(self, hi: bool) -> bytes:
        if hi:
            return self._sample(U64_MAX, U64_MAX, I64_MAX, U32_MAX)
        return self._sample(0, 0, I64_MIN, 0)

    def stamp_max(self) -> bytes:
        return self._sample(U64_MAX, U64_MAX, I64_MAX)

    def close(self) -> None:
        self.r.undeclare()


def _asker_node(asker: str) -> str:
    return "cn_b" if asker == "peer" else asker


_QUERY = struct.Struct("<2sBB16sq")  # codecs/FORMAT.md §6.3
_CREPLY = struct.Struct("<2sBB16sqqq")


class ClockQueryH(Harness):
    """The CN's clock server (ClockResponder): a DN's (or the standby's) query."""

    kinds = ("bad",)

    def __init__(self, m: Mission, asker: str, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.responder = ClockResponder(m, self.keys, Run(t0))
        self.link = ClockLink(m, _asker_node(asker), self.keys)
        # The asker's first exchange (a hello) told it the run: its next
        # query names it (an earlier run's query names that run's).
        query, nonce = self.link.query(t0)
        reply = self.responder.answer(query, t0, t0 + 1)
        assert reply is not None and self.link.check(reply, nonce) is not None
        self.ch = channel(self.keys, f"clock_{asker}_to_cn", Run(t0))
        self.max_len = _QUERY.size + TAG_LEN
        self.n = 0

    def genuine(self) -> bytes:
        self.n += 1
        return self.link.query(self.t0 + self.n)[0]

    def feed(self, payload: bytes) -> bool:
        return self.responder.answer(payload, self.t0, self.t0 + 1) is not None

    def counts(self) -> dict[str, int]:
        return {"bad": self.responder.refused}

    def extreme(self, hi: bool) -> bytes:
        assert self.ch is not None
        v, t = (255, I64_MAX) if hi else (0, I64_MIN)
        body = _QUERY.pack(b"ZQ", v, self.link.index, new_nonce(), t)
        return bytes(self.ch.seal(body))

    def stamp_max(self) -> bytes:
        assert self.ch is not None
        return bytes(self.ch.seal(_QUERY.pack(b"ZQ", 1, self.link.index, new_nonce(), I64_MAX)))


class ClockReplyH(Harness):
    """A DN's (or the standby's) end of the clock exchange (ClockLink)."""

    kinds = ("bad", "stale")

    def __init__(self, m: Mission, asker: str, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.responder = ClockResponder(m, self.keys)
        self.link = ClockLink(m, _asker_node(asker), self.keys)
        self.ch = channel(self.keys, f"clock_cn_to_{asker}")
        self.max_len = _CREPLY.size + TAG_LEN
        self.n = 0
        self.nonce = b""

    def genuine(self) -> bytes:
        self.n += 1
        query, self.nonce = self.link.query(self.t0 + self.n)
        reply = self.responder.answer(query, self.t0 + self.n, self.t0 + self.n + 1)
        assert reply is not None
        return reply

    def advance(self) -> None:
        self.nonce = self.link.query(self.t0 + self.n + 1)[1]  # the next exchange

    def feed(self, payload: bytes) -> bool:
        return self.link.check(payload, self.nonce) is not None

    def counts(self) -> dict[str, int]:
        return {"bad": self.link.refused_bad, "stale": self.link.refused_other}

    def extreme(self, hi: bool) -> bytes:
        assert self.ch is not None
        self.genuine()  # a query in flight, whose nonce the frame echoes
        v, t = (255, I64_MAX) if hi else (0, I64_MIN)
        body = _CREPLY.pack(b"ZR", v, self.link.index, self.nonce, t, t, t)
        return bytes(self.ch.seal(body))

    def stamp_max(self) -> bytes:
        assert self.ch is not None
        self.genuine()
        t = I64_MAX
        return bytes(self.ch.seal(_CREPLY.pack(b"ZR", 1, self.link.index, self.nonce, t, t, t)))


class MirrorH(_IntakeCounts, Harness):
    """A standby's mirror frames, as the node takes them: its intake
    (zplatform.control.intake.MirrorIntake: size, tag, range, sender, newer), its
    mailbox, then Standby.mirror."""

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.ch = channel(self.keys, "mirror", Run(t0))  # the commander's
        self.cn = ControlLogic(m, keys=self.keys, epoch=self.t0)
        # A standby that just started (a run of its own), told the
        # commander's by its clock exchange with it.
        sb = ControlLogic(m, keys=self.keys, epoch=t0 + 12345, name="cn_b")
        _learn_run(m, "cn_b", self.keys, t0, sb.auth_run)
        self.sb = Standby(m, sb, self.keys)
        self.intake = MirrorIntake(m, "cn_b", channel(self.keys, "mirror", sb.auth_run))
        self.max_len = self.intake.max_len
        self.n = 0

    def genuine(self) -> bytes:
        self.n += 1
        self.cn.begin(self.n, self.t0 + self.n * self.m.period_ns)
        self.cn.finish()
        assert self.cn.mirror is not None
        return bytes(self.cn.mirror)

    def feed(self, payload: bytes) -> bool:
        if not self.intake.admit(Bytes(payload), None):
            return False
        assert self.intake.box is not None
        item = self.intake.box.pop()
        return item is not None and self.sb.mirror(item[1], self.t0 + self.n * self.m.period_ns)

    def extreme(self, hi: bool) -> bytes:
        return _reframe(self.genuine(), hi, self.ch)

    def stamp_max(self) -> bytes:
        return _restamp(self.genuine(), self.ch, self._stamp_seq())

    def _stamp_seq(self) -> int | None:
        return None


_ASK = struct.Struct(f"<2sBBBBI{NONCE_LEN}sq")  # codecs/FORMAT.md §6.5
_PREPLY = struct.Struct(f"<2sBB{NONCE_LEN}sIIBBqQq")


class ProbeAskH(_IntakeCounts, Harness):
    """A DN's probe questions (ProbeIntake)."""

    def __init__(self, m: Mission, dn: str, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.i = m.device_nodes.index(dn)
        self.ch = channel(self.keys, f"probe_cn_to_{dn}", Run(t0))  # a control node's
        # The rate bounds run on a clock a period on per question: these
        # recipes test the checks before them, never the bounds
        # (tests/unit/test_failover_wire.py tests those).
        self.clock_ns = t0
        self.intake: ProbeIntake[None] = ProbeIntake(
            dn,
            channel(self.keys, f"probe_cn_to_{dn}", _learn_run(m, dn, self.keys, t0)),
            Waker(),
            period_ns=m.period_ns,
            now_ns=lambda: self.clock_ns,
        )
        self.max_len = self.intake.max_len
        self.n = 0

    def genuine(self) -> bytes:
        self.n += 1
        return ask_frame(self.ch, ASK, self.i, 1, 1, new_nonce(), self.t0 + self.n)

    def feed(self, payload: bytes) -> bool:
        self.clock_ns += self.m.period_ns
        return self.intake.admit(Bytes(payload), None)

    def extreme(self, hi: bool) -> bytes:
        assert self.ch is not None
        if hi:
            body = _ASK.pack(b"ZP", 255, 255, self.i, 255, U32_MAX, new_nonce(), I64_MAX)
        else:
            body = _ASK.pack(b"ZP", 0, 0, self.i, 0, 0, new_nonce(), I64_MIN)
        return bytes(self.ch.seal(body))

    def stamp_max(self) -> bytes:
        return ask_frame(self.ch, ASK, self.i, 1, U32_MAX, new_nonce(), I64_MAX)


class ProbeReplyH(Harness):
    """A control node's probe replies (Standby.answer)."""

    kinds = ("bad",)

    @classmethod
    def gaps(cls, m: Mission) -> dict[str, str]:
        return {}  # read_reply range-checks term, promise and loop (zplatform.control.fencing)

    def __init__(self, m: Mission, dn: str, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.i = m.device_nodes.index(dn)
        self.ch = channel(self.keys, f"probe_{dn}_to_cn")
        self.sb = Standby(m, ControlLogic(m, keys=self.keys, epoch=self.t0, name="cn_b"), self.keys)
        self.dn = DeviceLogic(m, dn, keys=self.keys)
        self.max_len = _PREPLY.size + TAG_LEN
        self.n = 0
        self.asks = self.sb.ask(0, self.t0)

    def genuine(self) -> bytes:
        self.n += 1
        reply = self.dn.probe(self.asks[self.i], self.t0 + self.n)
        assert reply is not None
        return reply

    def advance(self) -> None:
        self.asks = self.sb.ask(self.n, self.t0 + self.n)  # the next round

    def feed(self, payload: bytes) -> bool:
        return self.sb.answer(self.i, payload)

    def counts(self) -> dict[str, int]:
        return {"bad": self.sb.bad_replies}

    def extreme(self, hi: bool) -> bytes:
        assert self.ch is not None
        nonce = _ask_nonce(self.asks[self.i])
        if hi:
            body = _PREPLY.pack(
                b"ZA", 255, self.i, nonce, U32_MAX, U32_MAX, 255, 255, I64_MAX, U64_MAX, I64_MAX
            )
        else:
            body = _PREPLY.pack(b"ZA", 0, self.i, nonce, 0, 0, 0, 0, I64_MIN, 0, I64_MIN)
        return bytes(self.ch.seal(body))

    def stamp_max(self) -> bytes:
        assert self.ch is not None
        nonce = _ask_nonce(self.asks[self.i])
        body = _PREPLY.pack(b"ZA", 1, self.i, nonce, U32_MAX, U32_MAX, 1, 0, 0, U64_MAX, I64_MAX)
        return bytes(self.ch.seal(body))


def _ask_nonce(ask: bytes) -> bytes:
    return _ASK.unpack(ask[: _ASK.size])[6]


class RecorderQueryH(Harness):
    """The CN's flight recorder server: a gap-fill request (RecorderServer);
    its thread is stopped, and each admitted request is served here."""

    kinds = ("size", "bad")

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.ch = channel(self.keys, "telemetry")
        rec: Any = SimpleNamespace(run=-1)  # never the run asked: no file is read
        self.server = RecorderServer(
            FakeSession(),  # type: ignore[arg-type]
            f"{m.vehicle}/cn/recorder",
            rec,
            channel(self.keys, "telemetry"),
            now_ns=lambda: t0,
            max_age_ns=10**9,
            serve_bps=10**9,
        )
        self.server.close()  # its thread: this harness serves what is admitted
        self.max_len = REQUEST.size + TAG_LEN
        self.n = 0

    def _request(self, run: int, first: int, last: int, t_ns: int) -> bytes:
        assert self.ch is not None
        return bytes(self.ch.seal(REQUEST.pack(REQUEST_MAGIC, run, first, last, t_ns)))

    def genuine(self) -> bytes:
        self.n += 1
        return self._request(7, self.n, self.n, self.t0 + self.n)

    def feed(self, payload: bytes) -> bool:
        served = self.server.served
        deliver(self.server, payload)
        return self.server.served > served

    def counts(self) -> dict[str, int]:
        s = self.server
        # Junk of the right size is refused by its header tag (or stamp) in
        # zenoh's callback, the rest of the checks on the serving thread: both bad.
        return {"size": s._refused_rx, "bad": s._refused_early + s._refused_checked}

    def extreme(self, hi: bool) -> bytes:
        if hi:
            return self._request(U64_MAX, U64_MAX, U64_MAX, I64_MAX)
        return self._request(0, 0, 0, I64_MIN)

    def stamp_max(self) -> bytes:
        return self._request(7, self.n + 1, self.n + 1, I64_MAX)


class GapFillH(Harness):
    """The ground's gap fill: frames in the recorder's replies (GapFill)."""

    kinds = ("bad",)

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.ch = channel(self.keys, "telemetry", Run(t0))  # the CN's, for extremes
        self.cn = ControlLogic(m, keys=self.keys, epoch=self.t0)
        run = _ground_run(m, self.keys, t0)
        self.gf = GapFill(m, self.keys, EventLog("gn"), lambda rx, dv: None, run=run)
        lay = Layout.for_node(m, "cn")
        logic: Any = SimpleNamespace(gaps=deque([Gap(self.t0, 1, 1000)]), dv=DataVector(lay))
        self.gf.snapshot(logic, self.t0)
        req = self.gf.take_request(self.t0)
        assert req is not None
        self.rid = req[0]
        self.max_len = 1 + REPLY_LEN.size + self.gf._frame_max
        self.n = 0

    def _reply(self, frame: bytes) -> bytes:
        return bytes([REPLY_FRAMES]) + REPLY_LEN.pack(len(frame)) + frame

    def _frame(self) -> bytes:
        self.n += 1
        self.cn.begin(self.n, self.t0 + self.n * self.m.period_ns)
        return bytes(self.cn.telemetry())

    def genuine(self) -> bytes:
        return self._reply(self._frame())

    def feed(self, payload: bytes) -> bool:
        ask = self.gf._ask
        assert ask is not None
        got = len(ask.got)
        self.gf.on_reply(self.rid, payload)
        return len(ask.got) > got

    def counts(self) -> dict[str, int]:
        return {"bad": self.gf.refused}

    def extreme(self, hi: bool) -> bytes:
        return self._reply(_reframe(self._frame(), hi, self.ch))

    def stamp_max(self) -> bytes:
        self._frame()
        return self._reply(_restamp(self._frame(), self.ch, self.n))


class EventFillH(Harness):
    """The ground's event gap fill: the CN's events in the recorder's
    replies to an events request (GapFill, GroundLogic.check_filled), for a
    gap of numbers 1..1000 of the CN's events."""

    kinds = ("bad",)

    @classmethod
    def by_design(cls) -> dict[str, str]:
        why = (
            "a genuine record (the CN's tag, this run) numbered outside the gap is one of "
            "the same loops that did arrive: skipped, neither taken nor counted"
        )
        return {"extreme_max": why, "extreme_min": why, "extreme_stamp": why}

    def harmless(self, old: Harness | None) -> None:
        f = self.gf._evf
        assert f is not None
        for bad in (self.extreme(True), self.extreme(False), self.stamp_max()):
            assert not self.feed(bad), "a record outside the gap was taken"
        assert self.gf.refused == 0 and not f.got, "a genuine record was counted or kept"
        assert self.feed(self.genuine()), "the gap's genuine record is refused after them"

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.seal = self.keys.channel("events_cn", Run(t0))  # as the CN tags its events
        run = _ground_run(m, self.keys, t0)
        self.logic = GroundLogic(m, keys=self.keys, run=run)
        self.gf = GapFill(m, self.keys, EventLog("gn"), lambda rx, dv: None, run=run)
        gap = EventGap("cn", t0, 1, 1000, 1, 100)
        # A gap the logic found (GroundLogic._number), for the fill to take.
        self.logic._ev_open[gap] = set()
        self.logic.event_gaps.append(gap)
        self.gf._logic = self.logic
        req = self.gf.take_request(self.t0)
        assert req is not None
        self.rid = req[0]
        self.max_len = 1 + REPLY_LEN.size + REPLY_BYTES
        self.n = 0

    def _reply(self, record: bytes) -> bytes:
        return bytes([REPLY_EVENTS]) + REPLY_LEN.pack(len(record)) + record

    def _event(self, seq: int, t_ns: int) -> bytes:
        e = Event("cn", seq, t_ns, 4, "error", f"event {seq}")
        return bytes(self.seal.seal(encode_event(e)))

    def genuine(self) -> bytes:
        self.n += 1
        return self._reply(self._event(self.n, self.t0 + self.n))

    def feed(self, payload: bytes) -> bool:
        f = self.gf._evf
        assert f is not None
        got = len(f.got)
        self.gf.on_reply(self.rid, payload)
        return len(f.got) > got

    def counts(self) -> dict[str, int]:
        return {"bad": self.gf.refused}

    def extreme(self, hi: bool) -> bytes:
        return self._reply(self._event(U64_MAX if hi else 0, I64_MAX if hi else I64_MIN))

    def stamp_max(self) -> bytes:
        return self._reply(self._event(U64_MAX, I64_MAX))


def _archive_session(t0: int) -> int:
    """The archive server's session word of the ground that started at ``t0``."""
    return (t0 & U64_MAX) or 1


class ArchiveQueryH(Harness):
    """The ground's archive server: an ask (ArchiveServer) in its session,
    with its cookie; its thread is stopped, and each admitted ask is served
    here (from no archive: the answer is an error reply, which counts as
    served). Another session's ask (an earlier ground's) is stale."""

    kinds = ("size", "bad", "stale")

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.t0 = t0
        self.m, self.keys = m, _keys(m)
        self.ch = channel(self.keys, "telemetry", Run(_archive_session(t0)))

        def no_archive() -> Archive:
            return Archive(m, Path("/nonexistent/archive"))

        self.server = ArchiveServer(
            FakeSession(),  # type: ignore[arg-type]
            f"{m.vehicle}/archive/query",
            no_archive,
            channel(self.keys, "telemetry"),
            now_ns=lambda: t0,
            max_age_ns=10**9,
            serve_bps=10**9,
            max_bytes=10**6,
            session_word=_archive_session(t0),
        )
        self.server.close()  # its thread: this harness serves what is admitted
        self.query = ArchiveQuery("cn_state")
        self.max_len = ARCHIVE_ASK.size + MAX_ASK + TAG_LEN
        self.n = 0

    def _ask(self, cookie: int, nonce: int, asker: int = 1) -> bytes:
        return archive_ask(self.ch, self.query, cookie, nonce, asker=asker)

    def genuine(self) -> bytes:
        self.n += 1
        return self._ask(self.t0, self.n)

    def feed(self, payload: bytes) -> bool:
        served = self.server.served
        deliver(self.server, payload)
        return self.server.served > served

    def counts(self) -> dict[str, int]:
        s = self.server
        # Junk of the right size is refused by its header tag on zenoh's
        # thread, the rest on the serving thread: both bad.
        return {
            "size": s._refused_rx,
            "bad": s._refused_early + s._refused_checked,
            "stale": s.stale,
        }

    def extreme(self, hi: bool) -> bytes:
        return self._ask(I64_MAX, U64_MAX, U64_MAX) if hi else self._ask(I64_MIN, 0, 0)

    def stamp_max(self) -> bytes:
        return self._ask(I64_MAX, self.n + 1)


class ArchiveReplyH(Harness):
    """A station asking the ground's archive: the answer's chunks
    (ArchiveAsk), once its hello taught it the ground's session."""

    kinds = ("bad",)

    def __init__(self, m: Mission, t0: int = T0) -> None:
        self.m, self.keys = m, _keys(m)
        session = _archive_session(t0)
        self.ch = channel(self.keys, "telemetry", Run(session))
        self.nonce = t0 & U64_MAX  # each run's asks have their own
        self.asker = ArchiveAsk(channel(self.keys, "telemetry"), self.nonce)
        hello = ARCHIVE_REPLY.pack(3, self.asker.hello_nonce, 0, 1) + ARCHIVE_SESSION.pack(
            session, t0
        )
        assert self.asker.on_reply(self._seal(hello)) and self.asker.session == session
        self.max_len = self.asker.max_len
        self.n = -1

    def _seal(self, frame: bytes) -> bytes:
        assert self.ch is not None
        return bytes(self.ch.seal(frame))

    def _reply(self, kind: int, nonce: int, i: int, count: int) -> bytes:
        return self._seal(ARCHIVE_REPLY.pack(kind, nonce, i, count) + b"chunk")

    def genuine(self) -> bytes:
        self.n += 1
        return self._reply(1, self.nonce, self.n, 1000)

    def feed(self, payload: bytes) -> bool:
        return self.asker.on_reply(payload)

    def counts(self) -> dict[str, int]:
        return {"bad": self.asker.refused}

    def extreme(self, hi: bool) -> bytes:
        if hi:
            return self._reply(255, U64_MAX, U32_MAX, U32_MAX)
        return self._reply(0, 0, 0, 0)

    def stamp_max(self) -> bytes:
        return self._reply(1, self.nonce, U32_MAX - 1, 1000)


_HELLO = struct.Struct("<2sB16s")  # codecs/FORMAT.md §6.3


class RunHelloH(Harness):
    """The commander's end of the run hello (ClockResponder): a ground's or
    a tool's hello, on the clock's queryable."""

    kinds = ("bad", "stale")

    @classmethod
    def by_design(cls) -> dict[str, str]:
        # A replay of this responder's hellos is refused by its nonce (stale);
        # a hello names no run, so one sent to an earlier run's commander is
        # a hello like any other here.
        return {
            "replay_old_run": (
                "a run hello names no run: one an earlier run's commander answered "
                "is answered again, and its answer echoes a nonce no asker awaits any more"
            )
        }

    def harmless(self, old: Harness | None) -> None:
        # The earlier run's hello is answered; the asker that sent it takes
        # one answer per hello, and an asker that did not send it takes
        # none: the answer teaches nobody a run (what a run word tells anyway).
        sender = old if isinstance(old, RunHelloH) else self
        hello = sender.asker.hello()
        if old is not None:
            first = old.responder.answer(hello, old.t0, old.t0 + 1)
            assert first is not None and sender.asker.check(first), "the genuine hello's answer"
        again = self.responder.answer(hello, self.t0, self.t0 + 2)
        assert again is not None, "another run's hello is answered (it names no run)"
        assert old is None or not sender.asker.check(again), "a second answer was taken"
        if old is not None:
            assert not self.asker.check(again), "an answer to another asker's hello was taken"

    def __init__(self, m: Mission, asker: str, t0: int = T0) -> None:
        self.m, self.keys, self.t0 = m, _keys(m), t0
        self.responder = ClockResponder(m, self.keys, Run(t0))
        self.asker = RunAsker(self.keys)
        self.ch = channel(self.keys, "run_hello")
        self.max_len = _HELLO.size + TAG_LEN

    def genuine(self) -> bytes:
        return self.asker.hello()

    def feed(self, payload: bytes) -> bool:
        return self.responder.answer(payload, self.t0, self.t0 + 1) is not None

    def counts(self) -> dict[str, int]:
        r = self.responder
        return {"bad": r.refused - r.stale, "stale": r.stale}

    def extreme(self, hi: bool) -> bytes:
        assert self.ch is not None
        v, nonce = (255, b"\xff" * 16) if hi else (0, bytes(16))
        return bytes(self.ch.seal(_HELLO.pack(b"ZH", v, nonce)))

    def stamp_max(self) -> bytes:
        # A hello has no stamp nor number (the nonce makes it fresh): the
        # one integer, its version, at its largest.
        return self.extreme(True)


class RunAnswerH(Harness):
    """A ground's or a tool's end of the run hello (RunAsker): the commander's answer."""

    kinds = ("bad", "stale")

    def __init__(self, m: Mission, asker: str, t0: int = T0) -> None:
        self.m, self.keys, self.t0 = m, _keys(m), t0
        self.responder = ClockResponder(m, self.keys, Run(t0))
        self.asker = RunAsker(self.keys)
        self.ch = channel(self.keys, "run_answer", Run(t0))  # the commander's
        self.max_len = RUN_ANSWER.size + TAG_LEN
        self._hello = b""

    def genuine(self) -> bytes:
        self._hello = self.asker.hello()
        answer = self.responder.answer(self._hello, self.t0, self.t0 + 1)
        assert answer is not None
        return answer

    def advance(self) -> None:
        self._hello = self.asker.hello()  # the next exchange

    def feed(self, payload: bytes) -> bool:
        return self.asker.check(payload)

    def counts(self) -> dict[str, int]:
        return {"bad": self.asker.refused_bad, "stale": self.asker.refused_other}

    def _answer(self, version: int, run: int) -> bytes:
        assert self.ch is not None
        nonce = _HELLO.unpack(self._hello[: _HELLO.size])[2]
        return bytes(self.ch.seal(RUN_ANSWER.pack(b"ZA", version, nonce, run)))

    def extreme(self, hi: bool) -> bytes:
        self.advance()  # a hello in flight, whose nonce the answer echoes
        return self._answer(255, U64_MAX) if hi else self._answer(0, 0)

    def stamp_max(self) -> bytes:
        # No stamp: the run it names at its largest (not the tag's run).
        self.advance()
        return self._answer(1, U64_MAX)


def _dn(k: ExpandedKey) -> dict[str, Any]:
    return {"dn": dict(k.params)["dn"]}


def _node(k: ExpandedKey) -> dict[str, Any]:
    return {"node": dict(k.params)["node"]}


def _asker(k: ExpandedKey) -> dict[str, Any]:
    return {"asker": dict(k.params)["asker"]}


def _none(k: ExpandedKey) -> dict[str, Any]:
    return {}


RECIPES: dict[tuple[str, str], tuple[type[Harness], Callable[[ExpandedKey], dict[str, Any]]]] = {
    ("dn_to_cn", "query"): (TriggerH, _dn),
    ("dn_to_cn", "reply"): (ReplyH, _dn),
    ("sync_all", "query"): (TriggerH, lambda k: {**_dn(k), "bundle": True}),
    ("telemetry", "sample"): (TelemetryH, _none),
    ("gn_to_cn", "sample"): (RequestH, _none),
    ("events", "sample"): (EventH, _node),
    ("all_events", "sample"): (EventH, _node),
    ("clock", "query"): (ClockQueryH, _asker),
    ("clock", "reply"): (ClockReplyH, _asker),
    ("clock", "query:run_hello"): (RunHelloH, _asker),
    ("clock", "reply:run_answer"): (RunAnswerH, _asker),
    ("recorder", "query"): (RecorderQueryH, _none),
    ("recorder", "reply"): (GapFillH, _none),
    ("recorder", "reply:events_cn"): (EventFillH, _none),
    ("archive", "query"): (ArchiveQueryH, _none),
    ("archive", "reply"): (ArchiveReplyH, _none),
    ("mirror", "sample"): (MirrorH, _none),
    ("probe", "query"): (ProbeAskH, _dn),
    ("probe", "reply"): (ProbeReplyH, _dn),
    ("bulk", "sample"): (BulkH, lambda k: dict(k.params)),
}
"""A fault recipe per (row, frame kind) whose frames are tagged and taken by
a node: the harness and its arguments from the expanded row."""


def _kind(f: KeyFrames) -> str:
    """The recipe's kind of frame ``f``: its kind, and its channel for the
    run hello, which shares the clock's row (``query:run_hello``)."""
    if f.channel.startswith("run_") or (f.kind == "reply" and f.channel.startswith("events_")):
        return f"{f.kind}:{f.channel}"  # a row's second kind of reply (the recorder's events)
    return f.kind


def _harness(m: Mission, k: ExpandedKey, kind: str, t0: int) -> Harness:
    recipe = RECIPES.get((k.row.name, kind))
    assert recipe is not None, (
        f"row {k.row.name!r} ({k.row.key}) carries tagged {kind} frames, and "
        "tests/faults/test_keyspace_faults.py has no fault recipe for them: add one to RECIPES"
    )
    cls, args = recipe
    return cls(m, **args(k), t0=t0)  # type: ignore[call-arg]


def _tagged() -> Iterator[tuple[str, Mission, ExpandedKey, int, KeyFrames]]:
    for name, m in MISSIONS.items():
        for k in expand_keys(m):
            for j, f in enumerate(k.row.frames):
                if f.tagged:
                    yield name, m, k, j, f


def _cases() -> Iterator[Any]:
    for name, m, k, j, f in _tagged():
        if f.intake == "none":
            continue
        recipe = RECIPES.get((k.row.name, _kind(f)))
        gaps = recipe[0].gaps(m) if recipe is not None else {}
        by_design = recipe[0].by_design() if recipe is not None else {}
        for case in CASES:
            marks = []
            if case in by_design:
                case = f"{case}:answered_by_design"
            elif case in gaps:
                marks.append(
                    pytest.mark.xfail(strict=True, reason=gaps[case], raises=AssertionError)
                )
            yield pytest.param(name, k, j, case, id=f"{name}-{k.id}-{_kind(f)}-{case}", marks=marks)


def _expected(h: Harness, case: str) -> str | None:
    """The counter a case must land in (None: any one, exactly once)."""
    want = {
        "junk_over": "size",
        "junk_empty": "size",
        "junk_one": "size",
        "junk_max": "bad",
        "bad_tag": "bad",
        "replay": "stale",
    }.get(case)
    if want == "size" and "size" not in h.kinds:
        want = "bad"
    return want if want in h.kinds else None


@pytest.mark.parametrize(("mission", "key", "frame", "case"), list(_cases()), indirect=False)
def test_every_tagged_frame_is_refused_and_counted_once(
    mission: str, key: ExpandedKey, frame: int, case: str
) -> None:
    m = MISSIONS[mission]
    f = key.row.frames[frame]
    h = _harness(m, key, _kind(f), T0)
    try:
        if case.endswith(":answered_by_design"):
            run_old = case.startswith("replay_old_run")
            old_h = _harness(m, key, _kind(f), T0 - DAY) if run_old else None
            try:
                h.harmless(old_h)
            finally:
                if old_h is not None:
                    old_h.close()
        elif case == "replay_old_run":
            old = _harness(m, key, _kind(f), T0 - DAY)
            try:
                _old_run(h, old.genuine())
            finally:
                old.close()
        else:
            _run_case(h, case)
    finally:
        h.close()


GROUND_RECEIVERS = frozenset(
    {
        ("telemetry", "sample"),
        ("events", "sample"),
        ("all_events", "sample"),
        ("recorder", "reply"),
        ("recorder", "reply:events_cn"),
        ("archive", "reply"),
    }
)
"""The ground's receivers of the vehicle's frames (and a station's of the archive's)."""


@pytest.mark.parametrize(
    ("mission", "key", "frame"),
    [
        pytest.param(n, k, j, id=f"{n}-{k.id}-{_kind(f)}")
        for n, _, k, j, f in _tagged()
        if (k.row.name, _kind(f)) in GROUND_RECEIVERS
    ],
)
def test_a_fresh_ground_refuses_a_run_that_just_ended(
    mission: str, key: ExpandedKey, frame: int
) -> None:
    """``replay_old_run`` at a ground that just started, the earlier run
    ended a moment ago (ten loops): its frames are stamped within the
    clock bound, so only the run the ground learned (its run hello) refuses
    them (the archive's answer: its ask's nonce), counted once."""
    m = MISSIONS[mission]
    kind = _kind(key.row.frames[frame])
    h = _harness(m, key, kind, T0)
    old = _harness(m, key, kind, T0 - 10 * m.period_ns)
    try:
        _old_run(h, old.genuine())
    finally:
        old.close()
        h.close()


def _old_run(h: Harness, old: bytes) -> None:
    """A receiver that just started takes, first, a genuine frame of its
    sender's earlier run (a day before, another epoch): refused as stale,
    and the sender's genuine frames of this run are taken after it."""
    before = h.counts()
    assert not h.feed(old), "replay_old_run: admitted"
    after = h.counts()
    delta = {k: after[k] - before[k] for k in after}
    assert sum(delta.values()) == 1, f"replay_old_run: counted {delta}, not once"
    if "stale" in h.kinds:
        assert delta["stale"] == 1, f"replay_old_run: counted {delta}, not as stale"
    assert h.feed(h.genuine()), "replay_old_run: this run's genuine frame is refused after it"


def _run_case(h: Harness, case: str) -> None:
    # The genuine frame is admitted: the recipe is sound.
    g = h.genuine()
    assert h.feed(g), "a genuine frame was refused"
    h.advance()
    if case == "junk_max":
        bad = _junk(h.max_len)
    elif case == "junk_over":
        bad = _junk(h.max_len + 1)
    elif case == "junk_empty":
        bad = b""
    elif case == "junk_one":
        bad = b"\x00"
    elif case == "bad_tag":
        g2 = h.genuine()
        bad = g2[:-1] + bytes([g2[-1] ^ 0x01])
    elif case == "replay":
        bad = g
    elif case == "extreme_stamp":
        bad = h.stamp_max()
    else:
        bad = h.extreme(case == "extreme_max")
    before = h.counts()
    assert not h.feed(bad), f"{case}: admitted"
    after = h.counts()
    delta = {k: after[k] - before[k] for k in after}
    assert sum(delta.values()) == 1, f"{case}: counted {delta}, not once"
    want = _expected(h, case)
    if want is not None:
        assert delta[want] == 1, f"{case}: counted {delta}, not in {want!r}"
    if case.startswith("extreme"):
        h.advance()
        assert h.feed(h.genuine()), f"{case}: the next genuine frame is refused after it"


@pytest.mark.parametrize(
    ("mission", "key", "frame"),
    [
        pytest.param(n, k, j, id=f"{n}-{k.id}-{f.kind}")
        for n, _, k, j, f in _tagged()
        if f.intake == "none"
    ],
)
def test_a_tagged_frame_no_intake_guards_is_taken_by_no_vehicle_node(
    mission: str, key: ExpandedKey, frame: int
) -> None:
    """A tap (``cn/to_dnX``): tagged, put for tools, taken by no node on the
    vehicle (only the ground and tools may declare on it)."""
    assert set(key.row.declares) <= {"gn", "tool"}, key.row.declares
