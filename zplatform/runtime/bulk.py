"""Bulk channels: large fixed arrays between nodes, outside the sync loop.

A bulk channel is a named, fixed-size array (``u8[4194304]``) that its *owner*
publishes every ``rate_divisor``-th loop on ``{vehicle}/{owner}/bulk/{name}``
for its *readers* (:class:`BulkWriter`, :class:`BulkReader`, :class:`NodeBulk`);
a same-host reader takes them over iceoryx2, zenoh only while one matches.

With ``security.auth`` on, a sample is ``header || array || tags``: one
32-byte tag per reader (link ``bulk-NAME-READER``, held by the owner and that
reader only) over a summary of the header, the length and the array's BLAKE3
digest (:func:`body_digest`), in the owner's run (codecs/FORMAT.md §6.1). A
reader checks header first (size, run, header tag, freshness, rate bound
:data:`RATE_BURST`, layout), then at most one body pass per loop; refusals
counted (``bad``, ``stale``), evented once a second (docs/architecture.md#intra-host).

Contract: :meth:`BulkWriter.publish` copies the array once per path and, with
no chunk free, counts a drop (never raises, never a heap copy). A reader's
zenoh callback keeps a sample whose header passed in a one-slot mailbox
(junk never displaces it); :meth:`BulkReader.poll` copies it into the array.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import blake3
import numpy as np
import zenoh

from ..control.intake import RefusalLog, ahead_bound_ns
from ..core.auth import TAG_LEN, AuthError, Channel, KeySet, Run, RunError, channel
from ..core.events import EV
from ..errors import IntraHostError, TransportError
from ..security.keyspace import key_of
from . import intrahost
from .transport import is_matching

__all__ = [
    "BULK_HEADER_BYTES",
    "DEFAULT_AHEAD_NS",
    "DIGEST_THREADS",
    "HEADER",
    "MAX_CHANNEL_BYTES",
    "RATE_BURST",
    "STALE_LOOPS",
    "SUMMARY_BYTES",
    "BulkChannelConfig",
    "BulkHeader",
    "BulkReader",
    "BulkStats",
    "BulkWriter",
    "NodeBulk",
    "body_digest",
    "bulk_channel",
    "bulk_key",
    "check_bulk_channels",
    "counter_elements",
    "counter_region",
    "decode_sample",
    "mission_shm_need",
    "parse_bulk_type",
    "pool_size",
    "summary_of",
    "tags_bytes",
]

from ..config import (
    BULK_HEADER_BYTES,
    MAX_CHANNEL_BYTES,
    BulkChannelConfig,
    check_bulk_channels,
    counter_elements,
    counter_region,
    parse_bulk_type,
)

#: Polls (loops) without an iceoryx2 sample after which a reader on that
#: path falls back to zenoh (or ``4 * rate_divisor``, if longer).
STALE_LOOPS = 100
RATE_BURST = 4
"""Samples a reader takes ahead of its channel's rate (one every
``rate_divisor`` polls, its loops): beyond, a sample, however authentic, is
refused (counted stale), so a key holder publishing faster than the channel
declares costs the reader at most this burst, then one copy a period."""
DEFAULT_AHEAD_NS = 1_000_000_000
"""How far ahead of a reader's clock a sample's stamp may be, when the
reader is given no bound of its own (a node's: the clock bound and a
period, :func:`zplatform.control.intake.ahead_bound_ns`)."""

# Sample header, little-endian: layout_id u32, flags u32 (0), seq u64 (the
# channel's own sample counter: gaps are missed samples), loop u64 (the
# owner's loop number), t_ns i64 (the owner's clock when it published).
# 32 bytes keeps the array 8-byte aligned inside the chunk.
HEADER = struct.Struct("<IIQQq")
assert HEADER.size == BULK_HEADER_BYTES

DIGEST_BYTES = 32
SUMMARY_BYTES = BULK_HEADER_BYTES + 8 + DIGEST_BYTES
"""Bytes of the summary each reader's tag covers (codecs/FORMAT.md §6.1):
the sample's header (32), its length (u32, header and array) and a u32 0,
then the array's BLAKE3 digest (32). Its first 40 bytes (the header tag's,
:data:`zplatform.core.auth.HEADER_LEN`) are the header and the length, so
the header tag is checked before any pass over the array."""
_DIGEST_AT = BULK_HEADER_BYTES + 8
DIGEST_THREADS = 1
"""Threads of the one BLAKE3 pass over an array (owner and reader alike):
one, the loop's own: on a 2-core host a second thread did not pay (4 MB,
p50 0.48 ms with one, 0.49 ms with two, on this box's shared cores) and
would take the core the other node's loop runs on."""


def body_digest(hasher: Any, array: bytes | bytearray | memoryview) -> bytes:
    """The one pass over a sample's array (module doc): BLAKE3-256 of
    ``array`` with ``hasher`` (a ``blake3.blake3()``, reset here, kept by
    the caller: no allocation but the 32-byte digest)."""
    hasher.reset()
    hasher.update(array)
    return hasher.digest(DIGEST_BYTES)


def summary_of(out: bytearray, header: bytes | bytearray | memoryview, length: int) -> None:
    """Write a sample's header and ``length`` into the first 40 bytes of
    summary ``out`` (:data:`SUMMARY_BYTES` or more); the digest is
    written after (:func:`body_digest`)."""
    out[:BULK_HEADER_BYTES] = header[:BULK_HEADER_BYTES]
    struct.pack_into("<II", out, BULK_HEADER_BYTES, length & 0xFFFF_FFFF, 0)


def tags_bytes(channel: BulkChannelConfig, auth: bool) -> int:
    """Bytes of the tags a sample of ``channel`` carries: one
    :data:`~zplatform.core.auth.TAG_LEN` per reader when authenticated."""
    return TAG_LEN * len(channel.readers) if auth else 0


def bulk_key(vehicle: str, channel: BulkChannelConfig) -> str:
    """``{vehicle}/{owner}/bulk/{name}`` (docs/architecture.md#key-space), from
    its row of :data:`zplatform.security.keyspace.KEYSPACE`."""
    return key_of("bulk", vehicle, owner=channel.node, channel=channel.name)


def bulk_channel(name: str, reader: str) -> str:
    """The auth channel of bulk channel ``name``'s tag for ``reader``:
    ``bulk_NAME/READER`` (tagged by link ``bulk-NAME-READER``,
    :func:`zplatform.core.auth.link_of`)."""
    return f"bulk_{name}/{reader}"


def pool_size(channels: Sequence[BulkChannelConfig], node: str) -> int:
    """Bytes of ``node``'s shared-memory pool: every channel it owns times its
    :attr:`~BulkChannelConfig.slot_count`, each sample (with room for its
    readers' tags) rounded up to 4 KiB pages (chunks are page-aligned in practice).
    0 when it owns none."""
    page = 4096
    total = 0
    for ch in channels:
        if ch.node == node:
            size = ch.sample_bytes + tags_bytes(ch, True)
            total += ch.slot_count * (-(-size // page) * page)
    return total


@dataclass(frozen=True, slots=True)
class BulkStats:
    """Counters of one channel end, a frozen snapshot."""

    published: int = 0
    dropped: int = 0
    received_iox: int = 0
    received_shm: int = 0
    received_copied: int = 0
    missed: int = 0
    bad: int = 0
    stale: int = 0


@dataclass(frozen=True, slots=True)
class BulkHeader:
    layout_id: int
    seq: int
    loop: int
    t_ns: int


def decode_sample(
    data: bytes | memoryview,
    channel: BulkChannelConfig,
    auth: Channel | None = None,
    *,
    tagged: bool | None = None,
) -> tuple[BulkHeader, np.ndarray[Any, Any]]:
    """Header and a read-only array view of one sample's bytes (no copy).

    ``auth``: one reader's auth channel of it (:func:`bulk_channel`), whose
    tag among the sample's is checked first (header first, then the body's
    digest), any run's (AuthError, a CodecError, when it does not check);
    ``tagged``: whether ``data`` carries its readers' tags (default: when
    ``auth`` is given), skipped unchecked without ``auth`` (a tool: it holds
    no bulk key). Raises TransportError if the length or layout does not
    match ``channel``. For ``zplatform tap`` and tests; the loop uses
    :class:`BulkReader`.
    """
    if tagged is None:
        tagged = auth is not None
    if tagged:
        tags = tags_bytes(channel, True)
        if len(data) != channel.sample_bytes + tags:
            raise TransportError(
                f"bulk {channel.name}: sample of {len(data)} bytes, expected "
                f"{channel.sample_bytes + tags} (with its {len(channel.readers)} tags)"
            )
        mv = memoryview(data)
        n = channel.sample_bytes
        if auth is not None:
            reader = auth.name.rpartition("/")[2]
            if reader not in channel.readers:
                raise TransportError(f"bulk {channel.name}: {reader!r} is none of its readers")
            at = n + TAG_LEN * channel.readers.index(reader)
            summary = bytearray(SUMMARY_BYTES + TAG_LEN)
            summary_of(summary, mv, n)
            summary[SUMMARY_BYTES:] = mv[at : at + TAG_LEN]
            auth.open_header(summary, any_run=True)
            digest = body_digest(blake3.blake3(), mv[HEADER.size : n])
            summary[_DIGEST_AT:SUMMARY_BYTES] = digest
            auth.check_body(summary)
        data = mv[:n]
    if len(data) != channel.sample_bytes:
        raise TransportError(
            f"bulk {channel.name}: sample of {len(data)} bytes, expected {channel.sample_bytes}"
        )
    layout, _flags, seq, loop, t_ns = HEADER.unpack_from(data, 0)
    if layout != channel.layout_id:
        raise TransportError(
            f"bulk {channel.name}: layout {layout:#x} is not {channel.layout_id:#x}"
        )
    arr = np.frombuffer(data, channel.dtype, math.prod(channel.shape), HEADER.size)
    return BulkHeader(layout, seq, loop, t_ns), arr.reshape(channel.shape)


class BulkWriter:
    """The owner's end of one channel.

    Write the frame into :attr:`array` (preallocated, the channel's dtype and
    shape), then call :meth:`publish` on the loops where :meth:`due` is true.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        channel: BulkChannelConfig,
        provider: Any | None,
        *,
        monotonic: Callable[[], int] = time.monotonic_ns,
        iox: Any | None = None,
        auths: Sequence[Channel] | None = None,
    ) -> None:
        self.channel = channel
        self.auths = tuple(auths) if auths is not None else None
        """The channel's auth channels, one per reader in ``readers`` order
        (:func:`bulk_channel`, bound to the owner's run), or None: the
        mission does not authenticate."""
        if self.auths is not None and len(self.auths) != len(channel.readers):
            raise ValueError(
                f"bulk {channel.name}: {len(self.auths)} auth channels for "
                f"{len(channel.readers)} readers"
            )
        self.iox = iox
        """The channel's iceoryx2 publisher (an IntraHostPublisher: same-host
        readers), or None."""
        self.key = key
        self._provider = provider
        self._mono = monotonic
        self._timeout_ns = round(channel.alloc_timeout_ms * 1e6)
        self._n = channel.sample_bytes
        self._size = self._n + tags_bytes(channel, self.auths is not None)
        self._layout = channel.layout_id
        # ZShmMut[:] accepts only bytes/bytearray (not a memoryview or an
        # ndarray), so the frame lives in a bytearray and the array views it;
        # its readers' tags, when authenticated, after it.
        self._buf = bytearray(self._size)
        self._mv = memoryview(self._buf)
        # The summary each reader's tag covers, and room for that tag
        # (Channel.seal_tail writes it there, then it is copied in place).
        self._summary = bytearray(SUMMARY_BYTES + TAG_LEN)
        self._hasher = blake3.blake3(max_threads=DIGEST_THREADS)
        self.array: np.ndarray[Any, Any] = np.frombuffer(
            self._buf, channel.dtype, math.prod(channel.shape), HEADER.size
        ).reshape(channel.shape)
        self._gc = zenoh.shm.GarbageCollect() if provider is not None else None
        # DROP: a slow link or reader loses samples, it never blocks the loop.
        # DATA_LOW: queued behind the sync frames when QoS is on.
        self._pub = session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_LOW,
            express=True,
        )
        # Zenoh carries a sample only when a subscriber matches (a reader on
        # another host, a reader whose iceoryx2 path fell back, a tool's tap):
        # kept current from zenoh's thread, asked exactly before a skip.
        self.remote = is_matching(self._pub)
        self._listener = self._pub.declare_matching_listener(
            zenoh.handlers.Callback(self._on_matching, indirect=False)
        )
        self._seq = 0
        self.published = 0
        self.dropped = 0
        self.published_iox = 0
        """Samples that went over iceoryx2 (counters never reset)."""
        self.published_zenoh = 0
        """Samples that went over zenoh."""

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self.remote = bool(status.matching)

    def due(self, loop: int) -> bool:
        """Whether ``loop`` is one of this channel's publishing loops."""
        return loop % self.channel.rate_divisor == self.channel.rate_phase

    def publish(self, loop: int, t_ns: int) -> bool:
        """Send :attr:`array` with ``loop`` and ``t_ns`` in its header, tagged
        when authenticated (module doc: one pass over the array, its digest,
        then a tag per reader over the 72-byte summary, written in place
        after the array: no copy of it); the same bytes go over both paths.

        Over iceoryx2 (:attr:`iox`, when a subscriber is attached): one copy
        into a loaned sample; none free counts a drop. Over zenoh, only when
        a zenoh subscriber matches (:attr:`remote`; nobody: no bytes sent):
        with a provider, one copy into a shared-memory chunk. If none is
        free, retry (garbage-collecting released chunks) for at most the
        channel's ``alloc_timeout_ms``, then give up on that path; never
        raises for an exhausted pool. Without a provider (shared memory
        off): one copy into a zenoh buffer. Each call counts once: in
        :attr:`published` (and takes the next sequence number) when a path
        carried it or nobody listens, and in :attr:`dropped` when a path
        could not (both when one did and another did not): so a reader's
        sequence gaps (its ``missed``) are samples some path carried, and
        one number never names two samples. Returns ``True`` when every
        path that listens carried it. Raises TransportError only if zenoh
        refuses the put itself.
        """
        HEADER.pack_into(self._buf, 0, self._layout, 0, self._seq, loop, t_ns)
        if self.auths is not None:
            self._seal()
        carried = lost = False
        iox = self.iox
        if iox is not None and iox.subscribers:
            loan = iox.loan()
            if loan is not None:
                loan[:] = self._buf  # the sample's one copy, into shared memory
                if iox.send():
                    self.published_iox += 1
                    carried = True
            lost = not carried
        if self.remote or is_matching(self._pub):
            if self._provider is None:
                payload: Any = self._buf
            else:
                payload = chunk = self._alloc()
                if chunk is not None:
                    chunk[:] = self._buf
            if payload is None:
                lost = True
            else:
                try:
                    self._pub.put(payload)
                except zenoh.ZError as exc:
                    raise TransportError(f"bulk put on {self.key} failed: {exc}") from exc
                self.published_zenoh += 1
                carried = True
        elif not lost:
            carried = True  # nobody listens: its number is spent all the same
        if carried:
            self._seq += 1
            self.published += 1
        if lost:
            self.dropped += 1
        return not lost

    def _seal(self) -> None:
        n, mv, s = self._n, self._mv, self._summary
        summary_of(s, mv, n)
        s[_DIGEST_AT:SUMMARY_BYTES] = body_digest(self._hasher, mv[HEADER.size : n])
        at = n
        for auth in self.auths:  # type: ignore[union-attr]
            auth.seal_tail(s)
            mv[at : at + TAG_LEN] = s[SUMMARY_BYTES:]
            at += TAG_LEN

    def _alloc(self) -> Any | None:
        deadline = self._mono() + self._timeout_ns
        while True:
            try:
                return self._provider.alloc(self._size, policy=self._gc)  # type: ignore[union-attr]
            except zenoh.ZError:
                pass  # "out of memory": every chunk is still held by a reader
            if self._mono() >= deadline:
                return None
            time.sleep(50e-6)

    def stats(self) -> BulkStats:
        return BulkStats(published=self.published, dropped=self.dropped)

    @property
    def matching(self) -> bool:
        """Whether any subscriber matches this channel's key now (zenoh's
        routing state, :func:`zplatform.runtime.transport.is_matching`; never blocks)."""
        return is_matching(self._pub)

    def undeclare(self) -> None:
        self._listener.undeclare()
        self._pub.undeclare()
        if self.iox is not None:
            self.iox.close()


class BulkReader:
    """A reader's end of one channel.

    :meth:`poll` (non-blocking) or :meth:`wait` (blocking, bounded) takes the
    newest sample, if any, into :attr:`array`. Older unread samples are
    superseded, never queued: a slow reader never stalls the session.

    ``auth``: this reader's auth channel of it (:func:`bulk_channel`: its
    own tag among the sample's), bound to the reader's run (None: the
    mission does not authenticate, samples carry no tag); ``now_ns``: the
    reader's clock (the control node's time) and ``ahead_ns`` how far ahead
    of it a stamp may be (module doc for the intake).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        channel: BulkChannelConfig,
        *,
        iox: Any | None = None,
        auth: Channel | None = None,
        now_ns: Callable[[], int] = time.time_ns,
        ahead_ns: int = DEFAULT_AHEAD_NS,
    ) -> None:
        self.channel = channel
        self.key = key
        self.auth = auth
        self._now = now_ns
        self._ahead = ahead_ns
        self.iox = iox
        """The channel's iceoryx2 subscriber (an IntraHostSubscriber: a
        same-host owner), or None."""
        self.on_iox = False
        """Whether iceoryx2 carries the samples (then no zenoh subscriber is
        declared, so the owner sends none over zenoh for this reader)."""
        self.fallbacks = 0
        """Times the iceoryx2 path fell back to zenoh."""
        self.changes: list[tuple[str, str]] = []
        """``(path, why)`` of each path change not yet evented (:class:`NodeBulk`)."""
        self._session = session
        self._quiet = 0  # polls without an iceoryx2 sample while on it
        self._quiet_max = max(STALE_LOOPS, 4 * channel.rate_divisor)
        self.array: np.ndarray[Any, Any] = np.zeros(channel.shape, channel.dtype)
        self.view: np.ndarray[Any, Any] | None = None
        self.header: BulkHeader | None = None
        self._n = channel.sample_bytes
        self._size = self._n + tags_bytes(channel, auth is not None)
        self._tag_at = self._n
        if auth is not None:
            reader = auth.name.rpartition("/")[2]
            if reader not in channel.readers:
                raise ValueError(f"bulk {channel.name}: {reader!r} is none of its readers")
            self._tag_at += TAG_LEN * channel.readers.index(reader)
        self._summary = bytearray(SUMMARY_BYTES + TAG_LEN)
        self._hasher = blake3.blake3(max_threads=DIGEST_THREADS)
        self.body_passes = 0
        """Passes over a sample's array (its digest) made by the intake: one
        per sample whose header passed (never for junk or a replay)."""
        self._layout = channel.layout_id
        self._count = math.prod(channel.shape)
        self._dtype = channel.dtype  # parsed once: poll must not re-parse the type
        self._shape = channel.shape
        # The zenoh path's one-slot mailbox (_on_sample): the newest sample
        # whose header passed, as (bytes, via shared memory, seq, t_ns).
        self._latest: tuple[bytes, bool, int, int] | None = None
        self._event = threading.Event()
        # zenoh's threads' own: a channel (a twin of auth), a summary, the
        # refusals counted there (folded into bad/stale/duplicates by poll,
        # the loop's thread, so each counter has one writer), one lock.
        self._rx_lock = threading.Lock()
        self._rx_auth = auth.twin() if auth is not None else None
        self._rx_summary = bytearray(SUMMARY_BYTES + TAG_LEN)
        self._rx_bad = self._rx_stale = self._rx_dup = 0
        self._rx_why = ""
        self._last_seq: int | None = None
        self._last_t_ns = 0
        self.duplicates = 0
        """Samples refused as taken already (numbered and stamped no later
        than the last one taken): the same sample over both paths around a
        switch."""
        self.received_iox = 0
        self.received_shm = 0
        self.received_copied = 0
        self.missed = 0
        self.bad = 0
        """Samples refused as malformed: the wrong size, a bad tag (forged,
        another key), a layout not this channel's."""
        self.stale = 0
        """Authentic samples refused: another run's (an earlier run's,
        replayed), stamped further ahead of the reader's clock than
        ``ahead_ns``, or beyond the channel's rate bound (:data:`RATE_BURST`)."""
        self.why = ""
        """Why the last sample was refused (for the refusal's event)."""
        # The rate bound (a GCRA in the reader's loops: the loop poll is
        # given, else its polls): the theoretical loop of the next sample,
        # one every rate_divisor.
        self._polls = 0
        self._tat = 0
        self._every = channel.rate_divisor
        self._burst = RATE_BURST * channel.rate_divisor
        self._sub: Any = None
        self._declare()

    def _declare(self) -> None:
        self._sub = self._session.declare_subscriber(
            self.key, zenoh.handlers.Callback(self._on_sample, indirect=False)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: the sample's header checks, then the hand-off
        (docs/architecture.md#intra-host). Its size (unread), one copy out
        of zenoh (zenoh-python has no read in place: the intake's one copy,
        made here instead of in :meth:`poll`; the chunk is released at
        once), then, with authentication, this reader's header tag over the
        header and the length (no pass over the array), and the header's
        stamp: not ahead of the reader's clock beyond ``ahead_ns``, and
        newer than the sample in the slot (a replay, or the same sample over
        the other path, is let go). Only a sample that passes replaces the
        slot: a keyless flood on the bulk key (plain TCP) costs a copy per
        sample, as zenoh's own reception of it does, and never displaces
        the genuine sample before :meth:`poll` takes it (issue 25). Never
        blocks beyond a short lock; never raises for what arrives."""
        payload = sample.payload
        n = len(payload)
        if n != self._size:
            with self._rx_lock:
                self._rx_bad += 1
                self._rx_why = f"a sample of {n} bytes, not {self._size}"
            return
        shm = payload.as_shm()
        # bytes(shm) is faster than payload.to_bytes() for shm (bench.shm)
        data = bytes(shm) if shm is not None else payload.to_bytes()
        via_shm = shm is not None
        del sample, payload, shm  # release the chunk now
        _, _, seq, _, t_ns = HEADER.unpack_from(data, 0)
        with self._rx_lock:
            auth = self._rx_auth
            if auth is not None:
                summary = self._rx_summary
                summary_of(summary, data, self._n)
                at = self._tag_at
                summary[SUMMARY_BYTES:] = data[at : at + TAG_LEN]
                try:
                    auth.open_header(summary)
                except RunError as exc:  # an earlier run's genuine sample: a replay
                    self._rx_stale += 1
                    self._rx_why = str(exc)
                    return
                except AuthError as exc:
                    self._rx_bad += 1
                    self._rx_why = str(exc)
                    return
                if t_ns > self._now() + self._ahead:
                    self._rx_stale += 1
                    self._rx_why = f"a sample stamped {t_ns}, ahead of this node's clock"
                    return
                held = self._latest
                last = self._last_seq  # the loop thread's: one read, a race costs a poll
                if (held is not None and seq <= held[2] and t_ns <= held[3]) or (
                    last is not None and seq <= last and t_ns <= self._last_t_ns
                ):
                    self._rx_dup += 1  # not newer than the one waiting, or one taken
                    return
            # Replacing the slot lets the superseded sample's bytes go.
            self._latest = (data, via_shm, seq, t_ns)
        self._event.set()

    def poll(self, *, copy: bool = True, loop: int | None = None) -> bool:
        """Take the newest sample if one arrived since the last call.

        ``loop``: the reader's loop number (:meth:`NodeBulk.receive`), the
        rate bound's clock, so loops the reader missed count; None: each
        poll counts as one loop (tools, tests).

        Returns ``True`` when :attr:`array` (``copy=True``) or :attr:`view`
        (``copy=False``: read-only, valid until the next poll) holds a new,
        checked sample; ``False`` when none arrived or it was refused
        (counted in ``bad`` or ``stale``, module doc; with what zenoh's
        callback refused, :meth:`_on_sample`). Never blocks; copies once
        out of zenoh (after the size check: the intake's one copy, made in
        zenoh's callback, checked in place after it) and, with
        ``copy=True``, once into :attr:`array`; a refused sample is never
        copied into it.
        """
        if loop is None:
            self._polls += 1
        else:
            if loop < self._polls:  # its loops start again (another run): so does the bound
                self._tat = min(self._tat, loop)
            self._polls = loop
        with self._rx_lock:
            self._fold_rx()
        iox = self.iox
        if iox is not None:
            got = self._poll_iox(iox, copy)
            if got is not None:
                return got
        with self._rx_lock:
            held = self._latest
            self._latest = None
            self._event.clear()
        if held is None:
            return False
        data, via_shm, _, _ = held
        # The whole intake again (the header's checks are microseconds): the
        # callback's screen decided only what waits in the slot.
        if not self._take(data, copy):
            return False
        if via_shm:
            self.received_shm += 1
        else:
            self.received_copied += 1
        return True

    def _fold_rx(self) -> None:
        """Fold what zenoh's callback refused into the counters (the loop's
        thread, with the callback's lock held)."""
        if self._rx_bad or self._rx_stale:
            self.why = self._rx_why
        self.bad += self._rx_bad
        self.stale += self._rx_stale
        self.duplicates += self._rx_dup
        self._rx_bad = self._rx_stale = self._rx_dup = 0

    def _poll_iox(self, iox: Any, copy: bool) -> bool | None:
        """The iceoryx2 path's part of :meth:`poll`: whether a sample from it
        was taken (True) or refused (False); None when none came (then
        zenoh's is looked at). Switches the path (module doc of
        :mod:`zplatform.runtime.intrahost`; docs/architecture.md#intra-host):
        onto iceoryx2 at its first sample that passes the intake (the zenoh
        subscriber goes, so zenoh sends nothing more for this reader), back
        to zenoh when the owner's publisher is gone or silent for
        ``max(STALE_LOOPS, 4 * rate_divisor)`` polls."""
        view = iox.receive()
        if view is None:
            if self.on_iox:
                self._quiet += 1
                if iox.publishers == 0:
                    self._fall("the owner's iceoryx2 publisher is gone")
                elif self._quiet > self._quiet_max:
                    self._fall(f"no sample over iceoryx2 for {self._quiet} loops")
            return None
        # The same intake as zenoh's samples, over the sample in place; the
        # array's copy is its one copy (copy=False: a view on it, held until
        # the next poll).
        ok = self._take(view, copy)
        if copy:
            iox.release()
        if not ok:
            return False
        self.received_iox += 1
        self._quiet = 0
        if not self.on_iox:
            self.on_iox = True
            if self._sub is not None:
                self._sub.undeclare()
                self._sub = None
            self._latest = None
            self.changes.append(("iox", "a sample over it passed the intake"))
        return True

    def _fall(self, why: str) -> None:
        self.on_iox = False
        self.fallbacks += 1
        self._quiet = 0
        if self._sub is None:
            self._declare()  # rare (once per fallback): the loop thread may declare
        self.changes.append(("zenoh", why))

    def _take(self, data: bytes | memoryview, copy: bool) -> bool:
        """The intake of one sample (module doc: size, tag, freshness, rate
        bound, layout; sequence gaps counted as missed), then into
        :attr:`array` (or :attr:`view`). Reads ``data`` in place."""
        if len(data) != self._size:
            self.bad += 1
            self.why = f"a sample of {len(data)} bytes, not {self._size}"
            return False
        auth = self.auth
        summary = self._summary
        if auth is not None:
            # Header first: this reader's tag over the header and the length
            # (the summary's first 40 bytes), before any pass over the array.
            summary_of(summary, data, self._n)
            at = self._tag_at
            summary[SUMMARY_BYTES:] = data[at : at + TAG_LEN]
            try:
                auth.open_header(summary)
            except RunError as exc:  # an earlier run's genuine sample: a replay
                self.stale += 1
                self.why = str(exc)
                return False
            except AuthError as exc:
                self.bad += 1
                self.why = str(exc)
                return False
        layout, _flags, seq, loop, t_ns = HEADER.unpack_from(data, 0)
        if self._last_seq is not None and seq <= self._last_seq and t_ns <= self._last_t_ns:
            # A sample taken already (or older): the same one over the other
            # path around a switch. Not taken twice; a restarted owner's
            # sequence starts again at 0 but its stamps go on.
            self.duplicates += 1
            return False
        if t_ns > self._now() + self._ahead:
            # Authentic but stamped beyond any owner's clock (a key holder's
            # bug, a stepped clock): taken, it would refuse every genuine
            # sample after it as older.
            self.stale += 1
            self.why = f"a sample stamped {t_ns}, ahead of this node's clock"
            return False
        polls = self._polls
        if polls < self._tat - self._burst:
            self.stale += 1
            self.why = f"samples beyond the rate bound (one every {self._every} loops)"
            return False
        if layout != self._layout:
            self.bad += 1
            self.why = f"layout {layout:#x}, not this channel's {self._layout:#x}"
            return False
        if auth is not None:
            # The body pass: one per poll at most (a poll takes one sample),
            # and only for a genuine header that is new and within the rate.
            self.body_passes += 1
            mv = memoryview(data)
            summary[_DIGEST_AT:SUMMARY_BYTES] = body_digest(self._hasher, mv[HEADER.size : self._n])
            try:
                auth.check_body(summary)
            except AuthError as exc:  # a genuine header spliced onto another array
                self.bad += 1
                self.why = str(exc)
                return False
        self._tat = max(self._tat, polls) + self._every
        if self._last_seq is not None and seq > self._last_seq + 1:
            self.missed += seq - self._last_seq - 1
        self._last_seq, self._last_t_ns = seq, t_ns
        self.header = BulkHeader(layout, seq, loop, t_ns)
        src = np.frombuffer(data, self._dtype, self._count, HEADER.size)
        if copy:
            np.copyto(self.array.reshape(-1), src)
            self.view = None
        else:
            self.view = src.reshape(self._shape)
        return True

    def wait(self, timeout_s: float, *, copy: bool = True) -> bool:
        """Block up to ``timeout_s`` for a sample, then :meth:`poll`. On the
        iceoryx2 path (no wake-up of its own) it looks every millisecond:
        for tools and tests, never the loop (which polls)."""
        if self.iox is None:
            if self._latest is None:
                self._event.wait(timeout_s)
            return self.poll(copy=copy)
        t_end = time.monotonic() + timeout_s
        while True:
            if self.poll(copy=copy):
                return True
            if time.monotonic() >= t_end:
                return False
            self._event.wait(min(0.001, max(0.0, t_end - time.monotonic())))

    def stats(self) -> BulkStats:
        return BulkStats(
            received_iox=self.received_iox,
            received_shm=self.received_shm,
            received_copied=self.received_copied,
            missed=self.missed,
            bad=self.bad,
            stale=self.stale,
        )

    def undeclare(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        self._latest = None
        if self.iox is not None:
            self.iox.close()


class NodeBulk:
    """Every bulk channel end of one node, declared from the mission.

    ``NodeBulk(session, vehicle, channels, node, shared_memory=...)`` creates
    one shared-memory pool (:func:`pool_size`; pre-touched, so the first
    frames pay no page faults) when the node owns a channel and shared memory
    is on, a :class:`BulkWriter` per owned channel (:attr:`writers`) and a
    :class:`BulkReader` per channel it reads (:attr:`readers`).

    It is the node loop's :class:`~zplatform.control.loop.BulkPort`: the loop
    (:class:`~zplatform.control.loop.ControlLogic`, :class:`~zplatform.control.loop.DeviceLogic`)
    calls :meth:`receive` before its logic, :meth:`write_counters`, and
    :meth:`publish` after its logic; the components fill and read
    :attr:`arrays`. By hand, per loop::

        bulk.receive(loop)             # readers: the newest samples into their arrays
        ...the logic reads bulk.arrays[name] and fills the owned ones...
        bulk.publish(loop, t_ns)       # writers due on this loop
        bulk.write_counters(dv)        # or bulk.counters() into telemetry

    ``keys``: the node's keys (None: the mission does not authenticate);
    each channel's samples are then tagged (one tag per reader) and
    checked (a reader its own tag) with the auth channels of
    :func:`bulk_channel`, bound to ``run`` (the node's run: the
    loop's ``auth_run``; None: bound to none). ``now_ns``: the node's clock
    (its corrected one on a device node), which stamps events and bounds a
    sample's stamp ``ahead_ns`` ahead of it. Refusals (a reader's ``bad``
    and ``stale``) are evented (``bulk_refused``) at most once a second.

    Blocks at construction for the pool's first touch (one write of every
    chunk: proportional to the pool). Raises TransportError if the pool
    cannot be created, KeyError_ when ``keys`` lacks a channel's link.
    """

    def __init__(
        self,
        session: zenoh.Session,
        vehicle: str,
        channels: Sequence[BulkChannelConfig],
        node: str,
        *,
        shared_memory: bool = True,
        prefault: bool = True,
        intra_host: Any | None = None,
        events: Any | None = None,
        now_ns: Callable[[], int] = time.time_ns,
        keys: KeySet | None = None,
        run: Run | None = None,
        ahead_ns: int = DEFAULT_AHEAD_NS,
    ) -> None:
        self.node = node
        self.events = events
        """Where path changes are evented (an EventLog; None: kept in
        :attr:`changes` only)."""
        self._now = now_ns
        self.changes: list[tuple[str, str, str]] = []
        """``(channel, path, why)`` of the path changes :meth:`receive` saw
        (the last ones; cleared when evented)."""
        self._refusals = RefusalLog(2)
        self._refused = (0, 0)  # the readers' (bad, stale) when last counted
        self._owed = False  # refusals counted in _refusals and not evented yet
        self._auth = keys is not None
        self.pool_bytes = pool_size(channels, node) if shared_memory else 0
        self.provider: Any | None = None
        if self.pool_bytes:
            try:
                self.provider = zenoh.shm.ShmProvider.default_backend(self.pool_bytes)
            except Exception as exc:  # ZError: /dev/shm too small, no permission
                raise TransportError(
                    f"cannot create a {self.pool_bytes}-byte shared-memory pool for {node}: {exc}"
                ) from exc
            if prefault:
                self._prefault(channels)
        self.writers: dict[str, BulkWriter] = {}
        self.readers: dict[str, BulkReader] = {}
        for ch in channels:
            key = bulk_key(vehicle, ch)
            if ch.node != node and node not in ch.readers:
                continue
            if ch.node == node:
                # One tag per reader, on its own link (the channel's name
                # spelled out: tests/unit/test_keyspace.py traces it).
                auths = (
                    [keys.channel(f"bulk_{ch.name}/{r}", run) for r in ch.readers]
                    if keys is not None
                    else None
                )
                pub = self._iox(intra_host, ch, publisher=True) if ch.readers else None
                self.writers[ch.name] = BulkWriter(
                    session, key, ch, self.provider, iox=pub, auths=auths
                )
            else:
                auth = channel(keys, f"bulk_{ch.name}/{node}", run)
                sub = self._iox(intra_host, ch, publisher=False)
                self.readers[ch.name] = BulkReader(
                    session, key, ch, iox=sub, auth=auth, now_ns=now_ns, ahead_ns=ahead_ns
                )
        self._handles: list[tuple[Any, Callable[[], int]]] = []
        self.arrays: dict[str, Any] = {n: w.array for n, w in self.writers.items()}
        """Every channel's array by name: the owned ones (filled by the node's
        components, published from) and the read ones (the newest sample)."""
        self.arrays.update({n: r.array for n, r in self.readers.items()})
        self._writers = tuple(self.writers.values())
        self._readers = tuple(self.readers.values())

    def _iox(self, mission: Any | None, ch: BulkChannelConfig, *, publisher: bool) -> Any | None:
        """This node's iceoryx2 end of ``ch`` (its publisher, or a
        subscriber), or None: the mission's ``transport.intra_host`` is
        ``zenoh`` (or no mission was given), or the end cannot open
        (under ``shm`` that raises TransportError: the operator asked for
        it; under ``auto`` it is noted in :attr:`changes` and zenoh carries
        the channel)."""
        if mission is None or mission.transport.intra_host == "zenoh":
            return None
        end = intrahost.IntraHostPublisher if publisher else intrahost.IntraHostSubscriber
        try:
            name = intrahost.bulk_service_name(mission, ch.node, ch.name)
            return end(name, ch.sample_bytes + tags_bytes(ch, self._auth), len(ch.readers))
        except IntraHostError as exc:
            if mission.transport.intra_host == "shm":
                raise TransportError(f"bulk {ch.name}: {exc}") from exc
            self.changes.append((ch.name, "zenoh", f"no iceoryx2 end ({exc})"))
            return None

    def receive(self, loop: int) -> None:
        """Take the newest sample of every read channel into its array
        (:meth:`BulkReader.poll`), then event each reader's path change and
        the refusals (at most once a second, :attr:`events`); never blocks
        (a fallback declares a zenoh subscriber, rarely)."""
        for r in self._readers:
            r.poll(loop=loop)
            if r.changes:
                for path, why in r.changes:
                    self.changes.append((r.channel.name, path, why))
                r.changes.clear()
        if self.events is not None:
            if self.changes:
                self._event_changes()
            if self._readers:
                self._event_refusals()

    def _event_refusals(self) -> None:
        bad = stale = 0
        for r in self._readers:
            bad += r.bad
            stale += r.stale
        b0, s0 = self._refused
        if bad == b0 and stale == s0:
            if not self._owed:  # nothing new, nothing left to event: the usual loop
                return
            n = self._refusals.add(self._now(), 0, 0)  # what is left, a period on
        else:
            self._refused = (bad, stale)
            n = self._refusals.add(self._now(), bad - b0, stale - s0)
        self._owed = n is None  # counted, not evented yet
        if n is None:
            return
        why = next((f"{r.channel.name}: {r.why}" for r in self._readers if r.why), "")
        self.events.emit(  # type: ignore[union-attr]
            EV.BULK_REFUSED, self._now(), node=self.node, bad=n[0], stale=n[1], why=why
        )

    def _event_changes(self) -> None:
        t_ns = self._now()
        for name, path, why in self.changes:
            r = self.readers.get(name)
            fallbacks = r.fallbacks if r is not None else 0
            ev = EV.BULK_ON_SHM if path == "iox" else EV.BULK_FALLBACK
            self.events.emit(  # type: ignore[union-attr]
                ev, t_ns, node=self.node, channel=name, why=why, fallbacks=fallbacks
            )
        self.changes.clear()

    def paths(self) -> dict[str, str]:
        """Each read channel's path now: ``iox`` or ``zenoh``."""
        return {n: "iox" if r.on_iox else "zenoh" for n, r in self.readers.items()}

    def publish(self, loop: int, t_ns: int) -> None:
        """Publish every owned channel due on ``loop`` (:meth:`BulkWriter.publish`:
        a full pool counts a drop after ``alloc_timeout_ms``)."""
        for w in self._writers:
            if w.due(loop):
                w.publish(loop, t_ns)

    def _prefault(self, channels: Sequence[BulkChannelConfig]) -> None:
        # Allocate every chunk once and write it whole, so the kernel maps the
        # pool's pages now; then give them back to the pool.
        assert self.provider is not None
        held = []
        for ch in channels:
            if ch.node != self.node:
                continue
            zeros = bytes(ch.sample_bytes)
            for _ in range(ch.slot_count):
                try:
                    chunk = self.provider.alloc(ch.sample_bytes)
                except zenoh.ZError:
                    break
                chunk[:] = zeros
                held.append(chunk)
        del held
        self.provider.garbage_collect()

    def counters(self) -> dict[str, int]:
        """Current counters under the names of :func:`counter_elements`."""
        out: dict[str, int] = {}
        for name, w in self.writers.items():
            out[f"bulk_{name}_published"] = w.published
            out[f"bulk_{name}_dropped"] = w.dropped
        for name, r in self.readers.items():
            out[f"bulk_{name}_iox"] = r.received_iox
            out[f"bulk_{name}_shm"] = r.received_shm
            out[f"bulk_{name}_copied"] = r.received_copied
            out[f"bulk_{name}_missed"] = r.missed
            out[f"bulk_{name}_bad"] = r.bad
            out[f"bulk_{name}_stale"] = r.stale
        return out

    def write_counters(self, dv: Any) -> None:
        """Write :meth:`counters` into Data Vector ``dv`` (u32, wrapping);
        elements the layout lacks are skipped. Handles are built once."""
        if not self._handles:
            for name in self.counters():
                try:
                    self._handles.append((dv.handle(name), _getter(self, name)))
                except Exception:  # the runtime has not added this element
                    continue
        for h, get in self._handles:
            h.set(get() & 0xFFFF_FFFF)

    def close(self) -> None:
        for w in self.writers.values():
            w.undeclare()
        for r in self.readers.values():
            r.undeclare()


def mission_shm_need(mission: Any) -> int:
    """Shared memory the mission's intra-host links and bulk pools take, in
    bytes: the sync's links, zenoh's bulk pools and the bulk channels'
    iceoryx2 segments and the telemetry's to a ground node on the CN's host
    (when ``transport.intra_host`` is not ``zenoh``)."""
    need = sum(
        intrahost.segment_bytes(*intrahost.mission_link_sizes(mission, dn))
        for dn in mission.device_nodes
    )
    nodes = {ch.node for ch in mission.bulk}
    auth = bool(mission.security.auth)
    if mission.transport.intra_host != "zenoh":
        need += sum(
            intrahost.bulk_segment_bytes(ch.sample_bytes + tags_bytes(ch, auth), len(ch.readers))
            for ch in mission.bulk
        )
        if mission.has_ground:
            n = intrahost.telemetry_sample_bytes(mission, auth)
            need += intrahost.telemetry_segment_bytes(n, 2 * len(mission.control_nodes))
    return need + sum(pool_size(mission.bulk, n) for n in nodes)


def _getter(bulk: NodeBulk, element: str) -> Callable[[], int]:
    _, rest = element.split("_", 1)
    name, field = rest.rsplit("_", 1)
    attr = {"iox": "received_iox", "shm": "received_shm", "copied": "received_copied"}.get(
        field, field
    )
    end: Any = bulk.writers[name] if name in bulk.writers else bulk.readers[name]
    return lambda: int(getattr(end, attr))


def open_bulk(
    session: zenoh.Session,
    mission: Any,
    node: str,
    logic: Any,
    keys: KeySet | None,
    now_ns: Callable[[], int] = time.time_ns,
) -> NodeBulk | None:
    """The node's bulk channel ends (None when it has none), attached to the
    node's loop (``logic.attach_bulk``), which receives, publishes and counts
    them in its protocol order and hands :attr:`NodeBulk.arrays` to its
    components. ``keys``: the node's (None only when the mission does not
    authenticate); the channels are bound to the loop's run
    (``logic.auth_run``), stamps bounded ahead of ``now_ns`` (the node's
    clock) by the clock bound and a period. Raises TransportError as
    :class:`NodeBulk`."""

    mine = [ch for ch in mission.bulk if ch.node == node or node in ch.readers]
    if not mine:
        return None
    bulk = NodeBulk(
        session,
        mission.vehicle,
        mission.bulk,
        node,
        shared_memory=mission.transport.shared_memory,
        intra_host=mission,
        events=logic.events,
        now_ns=now_ns,
        keys=keys,
        run=logic.auth_run,
        ahead_ns=ahead_bound_ns(mission),
    )
    logic.attach_bulk(bulk)
    return bulk
