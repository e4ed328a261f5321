"""The archive's writing side: the receive path copies, the archive's thread writes.

:class:`ArchiveWriter` takes every snapshot the ground accepted (copied into
a slot of a ring) and every event (a bounded queue); the ring and the row
group's block are sized from the mission (``archive_sizing`` in
:mod:`zplatform.config.checks`) and mapped whole at start. Its thread wakes
every :data:`WAKE_S`, drops loops it already holds, appends the raw records
(:mod:`.store`; a closed segment is sealed on the encoder threads) and
copies the rows into the block; a full block is one closed Parquet file per
file group, encoded on :data:`ENCODERS` threads: a running run is queryable
up to its last row group. Every ``file_s`` and at the run's end a run of
one file group has them compacted per hour (:func:`.store.compact`).

Contract: :meth:`~ArchiveWriter.snapshot`, :meth:`~ArchiveWriter.event` and
:meth:`~ArchiveWriter.tick` never block, never raise, and allocate nothing
per snapshot; a full queue drops, counted and evented once a second. An I/O
error (a full disk) is counted and evented once per kind; what the raw
segment could not take is lost (counted), the rest refilled from it at the
run's end (:func:`.store.refill`); writing resumes once space is freed. One
writer per archive directory (a lock)."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import fcntl
import logging
import mmap
import os
import threading
import time
import zlib
from bisect import bisect_right
from collections import deque
from collections.abc import Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..config import Mission
from ..config.checks import archive_sizing
from ..config.schema import ARCHIVE_QUEUE_BYTES, ARCHIVE_ROW_GROUP_BYTES
from ..core.datavector import DataVector, Layout
from ..core.events import EV, EventLog, EventType
from ..errors import ArchiveError
from ..recorder.format import EVENT, FRAME, HEADER, SYNC, segment_name
from ..telemetry.records import EventRecord
from . import store

__all__ = [
    "ENCODERS",
    "EVENT_BACKLOG",
    "QUEUE_BYTES",
    "ROW_GROUP_BYTES",
    "WAKE_S",
    "ArchiveWriter",
    "LoopSet",
    "release_memory",
]

log = logging.getLogger("zplatform.archive")
_FILE_KINDS = frozenset({"write", "compact its files", "close its files", "compress a raw segment"})


def _libc_trim() -> Any:
    """glibc's ``malloc_trim`` (None elsewhere: musl, macOS)."""
    with contextlib.suppress(OSError, AttributeError):
        name = ctypes.util.find_library("c")
        if name:
            trim = ctypes.CDLL(name).malloc_trim
            trim.argtypes = [ctypes.c_size_t]
            trim.restype = ctypes.c_int
            return trim
    return None


_trim = _libc_trim()


def release_memory() -> None:
    """Give back to the system the memory a Parquet write left free in the
    allocators: Arrow's pool (``release_unused``: mimalloc or jemalloc keep
    freed pages) and glibc's heaps (``malloc_trim``). Issue 25: encoding a
    row group (a minute of the flight mission's 190 columns, decoded, then
    dictionary- and zstd-encoded) left the ground node 26-40 MB larger for
    good, about a minute into every flight; the soak saw it "during a
    flood", whichever flood ran then (``python -m bench.ground_memory
    --variant archive``). Costs the calling thread (the archive's) under a
    millisecond here; other threads' allocations wait meanwhile. Never
    raises."""
    pa.default_memory_pool().release_unused()
    if _trim is not None:
        _trim(0)


class LoopSet:
    """A set of loop numbers kept as sorted, disjoint, inclusive ranges: a
    run's loops, nearly all consecutive, cost one range, not an entry each.
    (Issue 25: the archive's set of a run's loops grew by about 80 bytes a
    loop, 28 MB an hour of a 100 Hz run.) Adding at the end is O(1), anywhere
    O(log n) to find and O(n) in ranges to insert; not thread-safe."""

    __slots__ = ("_hi", "_lo")

    def __init__(self, loops: Iterable[int] = ()) -> None:
        self._lo: list[int] = []
        self._hi: list[int] = []
        for lp in sorted(loops):
            self.add(lp)

    def __contains__(self, lp: int) -> bool:
        i = bisect_right(self._lo, lp) - 1
        return i >= 0 and lp <= self._hi[i]

    def add(self, lp: int) -> None:
        lo, hi = self._lo, self._hi
        i = bisect_right(lo, lp) - 1  # the range starting at or before lp
        if i >= 0 and lp <= hi[i]:
            return
        j = i + 1  # the range after lp
        joins_next = j < len(lo) and lo[j] == lp + 1
        if i >= 0 and hi[i] == lp - 1:
            if joins_next:  # lp fills the hole between two ranges
                hi[i] = hi[j]
                del lo[j], hi[j]
            else:
                hi[i] = lp
        elif joins_next:
            lo[j] = lp
        else:
            lo.insert(j, lp)
            hi.insert(j, lp)

    @property
    def ranges(self) -> int:
        """How many ranges it holds (its size in memory)."""
        return len(self._lo)

    def __len__(self) -> int:
        return sum(h - lo + 1 for lo, h in zip(self._lo, self._hi, strict=True))

    def max(self, default: int) -> int:
        """The highest loop held (``default`` when none)."""
        return self._hi[-1] if self._hi else default


WAKE_S = 0.1
"""How often the archive's thread takes what was queued."""
QUEUE_BYTES = ARCHIVE_QUEUE_BYTES
"""Most bytes of snapshots the hand-off ring holds (``archive.queue_s``:
:func:`zplatform.config.checks.archive_sizing`)."""
ROW_GROUP_BYTES = ARCHIVE_ROW_GROUP_BYTES
"""Most bytes of snapshots in one row group (``archive.row_group_s``: a
large vector gets fewer rows, or its mission is refused): the writer's
preallocated block, mapped once at start (:func:`prefaulted`: the flight
mission's 757-byte vector takes 4.5 MB for its 60 s). Large, because a
Parquet column chunk costs 15 to 30 us of CPU to write whatever its rows: a
100,000-element vector at 100 Hz in row groups of 167 rows (64 MiB) is
60,000 column chunks a second, more than a core can write; in 1,340 rows
(this), 7,500."""
ENCODERS = 2
"""Threads that encode a row group's file groups at once (Parquet's encoder
releases the GIL) and seal the closed raw segments (made at the first use:
a layout of one file group uses them for its seals only)."""
TAKE_BYTES = 16 * 2**20
"""Bytes of snapshots the archive's thread takes from the ring at a time, at
most (and at most an eighth of the ring): their slots are freed once they
are in the raw segment and the block, so a row group written meanwhile
holds no more of the ring than that."""
EVENT_BACKLOG = 4096
"""Events queued for the archive's thread, at most."""
SEGMENT_BYTES = 64 * 2**20
"""A new raw segment is started past this size."""
MAX_COMMANDS = 1000
"""Command events a run's record lists, at most (the events file keeps every one)."""
LOCK_FILE = ".lock"


def lock_archive(root: Path) -> int | None:
    """An exclusive lock on the archive ``root`` (a file descriptor), or None
    when another process holds it. Raises OSError when it cannot be made."""
    root.mkdir(parents=True, exist_ok=True)
    fd = os.open(root / LOCK_FILE, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def prefaulted(nbytes: int) -> mmap.mmap:
    """``nbytes`` of zeroed anonymous memory, its pages mapped now (Linux's
    ``MAP_POPULATE``; elsewhere as first touched). Why: a page first touched
    costs a fault, and the writer's block and ring are touched row by row
    as snapshots come: 0.5 ms per 400 KB row of a 100,000-element vector in
    its first row group, on the archive's thread (the ring's, on the
    receive path), against 0.15 ms for the whole 512 MiB mapped at once at
    start. Raises OSError when the memory cannot be had."""
    flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_POPULATE", 0)
    return mmap.mmap(-1, max(nbytes, 1), flags=flags)


def _write_all(f: BinaryIO, data: bytes | memoryview) -> None:
    """Write all of ``data`` to the unbuffered ``f`` (a short write, a disk
    filling up, is written on or raises)."""
    view = memoryview(data)
    while view:
        n = f.write(view)
        if not n:
            raise OSError(errno.ENOSPC, "No space left on device (a write took nothing)")
        view = view[n:]


class ArchiveWriter:
    """Archives one ground's snapshots and events into ``root`` (module doc).

    ``layout``: the CN layout of the vectors handed in. Recovers what a crash
    left (:func:`.store.recover`) and applies retention before its thread
    starts. Raises ArchiveError when another writer holds ``root`` or it
    cannot be created."""

    def __init__(
        self,
        mission: Mission,
        layout: Layout,
        root: str | Path,
        *,
        group_columns: int | None = None,
    ) -> None:
        self.mission, self.layout, self.root = mission, layout, Path(root)
        # Elements per Parquet file group of a new run (0: one file whatever
        # the width; None: store.GROUP_COLUMNS); a run keeps its grouping.
        self._group_columns = group_columns
        cfg = mission.archive
        self.cfg = cfg
        self.sizing = archive_sizing(mission, layout.size)
        """Its row group's and queue's rows (the block and the ring it holds)."""
        try:
            fd = lock_archive(self.root)
        except OSError as exc:
            raise ArchiveError(f"cannot open the archive {self.root}: {exc.strerror}") from None
        if fd is None:
            raise ArchiveError(f"another ground node writes the archive {self.root}")
        self._lock_fd = fd
        size = self.sizing.vector_bytes
        per_s = mission.loop_hz / mission.telemetry_divisor
        cap = self.sizing.queue_rows
        self._size, self._cap = size, cap
        self._rg_rows = self.sizing.row_group_rows
        try:  # both mapped now, whole: never a page fault on the receive path
            self._ring = prefaulted(cap * size)
            self._block = np.frombuffer(prefaulted(self._rg_rows * size), np.uint8)
        except OSError as exc:
            os.close(fd)
            raise ArchiveError(
                f"cannot map the archive's queue and row group "
                f"({(self.sizing.queue_bytes + self.sizing.block_bytes) / 2**20:.0f} MiB): "
                f"{exc.strerror}"
            ) from None
        self._block = self._block.reshape(self._rg_rows, size)
        self._ring_mv = memoryview(self._ring)
        self._rx = np.zeros(cap, np.int64)
        self._head = 0  # written by the receive path only
        self._tail = 0  # written by the archive's thread only
        self._events: deque[EventRecord] = deque()
        self.dropped = 0
        """Snapshots the full queue did not take."""
        self.events_dropped = 0
        self._dropped_told = (0, 0)
        self._told_ns = -(10**18)
        self.errors = 0
        self.lost = 0
        """Snapshots taken from the queue that the raw segment could not
        take (a full disk): not archived."""
        self._failed: set[str] = set()
        self._notes: deque[tuple[EventType, dict[str, Any]]] = deque(maxlen=256)
        self.rows = 0
        """Snapshots archived (each loop once)."""
        self.duplicates = 0
        """Snapshots of loops already archived (not written again)."""
        self.loop_ranges = 0
        """Ranges of consecutive loops the run's record of its archived loops
        holds (:class:`LoopSet`: 1 for a run without a hole, whatever its
        length), as of the archive thread's last batch."""
        self.releases = 0
        """Times the archive's thread gave its Parquet writes' memory back
        (:func:`release_memory`): once after its warm-up at start, once per
        row group written (its rows freed), once per file closed."""
        self._schema = store.file_schema(layout)
        self._ring2d = np.frombuffer(self._ring, np.uint8).reshape(cap, size)
        self._retain_rows = max(self._rg_rows, int(cfg.file_s * per_s))
        self._since_retain = 0
        # The open row group (self._block, mapped above): filled by the archive's thread.
        self._block_rx = np.empty(self._rg_rows, np.int64)
        self._pend_n = 0
        # The raw records of the snapshots taken at a time, built in place.
        self._take = max(1, min(cap // 8, TAKE_BYTES // size))
        self._rec_len = HEADER.size + 8 + layout.size
        self._raw_buf = bytearray(self._take * self._rec_len)
        self._raw_np = np.frombuffer(self._raw_buf, np.uint8).reshape(self._take, self._rec_len)
        self._pool: ThreadPoolExecutor | None = None
        self._sealing: deque[Future[None]] = deque()  # raw segments being sealed, in order
        self._decoders: list[store.GroupDecoder] = []
        self._decoders_for = -1
        self._parts: dict[str, int] = {}  # per run/hour: the next part number
        self._part_dirs: dict[str, Path] = {}
        self._compacted: dict[str, int] = {}  # per run/hour: the first part not compacted
        self._covered: list[Path] = []  # parts compacted, removed at the next pass
        self._loop_at = layout.element("cn_loop").offset
        self._epoch_at = layout.element("cn_epoch").offset
        # The archive's thread's own state.
        self._run: int | None = None
        self._info: store.RunInfo | None = None
        self._seen = LoopSet()  # the run's loops archived (their ranges: bounded)
        self._max_loop = -1
        self._seg: BinaryIO | None = None
        self._seg_bytes = 0
        self._seg_index = 0
        self._synced = 0.0
        self._groups: list[list[str]] = store.column_groups(layout, 0)
        self._ev_pend: list[EventRecord] = []
        self._early_events: list[EventRecord] = []
        self._refill = False
        """A write of this run failed: its end re-decodes its raw segments."""
        self._batch_raw = 0
        try:
            store.recover(self.root, layout, mission.mission, mission.vehicle, self._damage)
            self._retain()
        except (OSError, pa.ArrowException) as exc:
            self._fail("recover what a crash left", exc)
        self._stop = threading.Event()
        self._drained = threading.Condition()
        self._thread = threading.Thread(target=self._main, name="archive", daemon=True)
        self._thread.start()

    # -- the receive path ---------------------------------------------------
    def snapshot(self, rx_ns: int, dv: DataVector) -> None:
        """Queue a copy of ``dv`` (the CN vector of an accepted snapshot)
        received at ``rx_ns``; a full queue drops it, counted."""
        head = self._head
        if head - self._tail >= self._cap or len(dv.buf) != self._size:
            self.dropped += 1  # full, or not a CN vector of this layout
            return
        i = head % self._cap
        at = i * self._size
        self._ring_mv[at : at + self._size] = dv.buf
        self._rx[i] = rx_ns
        self._head = head + 1

    def event(self, rec: EventRecord) -> None:
        """Queue an event; beyond :data:`EVENT_BACKLOG` waiting it is dropped, counted."""
        if len(self._events) >= EVENT_BACKLOG:
            self.events_dropped += 1
            return
        self._events.append(rec)

    def tick(self, now_ns: int, events: EventLog) -> None:
        """Tell ``events`` (the ground's) what the archive has to say: its
        thread's notes, and drops at most once a second. Call from the
        thread that owns ``events``."""
        while self._notes:
            ev, args = self._notes.popleft()
            events.emit(ev, now_ns, **args)
        dropped = (self.dropped, self.events_dropped)
        if dropped != self._dropped_told and now_ns - self._told_ns >= 1_000_000_000:
            self._dropped_told, self._told_ns = dropped, now_ns
            events.emit(EV.ARCHIVE_DROPPING, now_ns, n=dropped[0], events=dropped[1])

    # -- the archive's thread -----------------------------------------------
    def _note(self, ev: EventType, **args: Any) -> None:
        self._notes.append((ev, args))

    def _fail(self, what: str, exc: BaseException) -> None:
        self.errors += 1
        # Told once per kind; the file operations one full disk fails all at
        # once (write, compact, close, compress) are one kind: one message.
        kind = "files" if what in _FILE_KINDS else what
        if kind not in self._failed:
            self._failed.add(kind)
            log.warning("the ground archive cannot %s: %s", what, exc)
            self._note(EV.ARCHIVE_FAILED, what=what, error=str(exc)[:200])

    def _damage(self, what: str) -> None:
        log.warning("the ground archive skipped damage: %s", what)
        self._note(EV.ARCHIVE_DAMAGED, what=what[:300])

    def _main(self) -> None:
        self._warm_up()
        while not self._stop.wait(WAKE_S):
            self._drain_safely()
            with self._drained:
                self._drained.notify_all()
        self._drain_safely()

    def _warm_up(self) -> None:
        """Encode one snapshot's row as the files are written, into memory,
        and give the memory back: the Parquet code is paged in and the
        encoder's allocations made once, at start, not in the middle of a
        flight (issue 25: the ground's first row group, a minute in, was
        its biggest step, +14 MB after the release, 8 now). The file groups'
        decoders of a new run are made here too, and the row is group 0's
        file only: a 100,000-element layout's whole row took 3.2 s of CPU
        (its 100,000 columns in one file), group 0's 1,024 a few ms. Never
        raises."""
        try:
            gc = store.GROUP_COLUMNS if self._group_columns is None else self._group_columns
            coder = self._coders(gc)[0]
            table = coder.table(np.zeros((1, self._size), np.uint8), np.zeros(1, np.int64))
            with pq.ParquetWriter(pa.BufferOutputStream(), table.schema, **coder.options) as pw:
                pw.write_table(table)
            del table, pw
        except Exception as exc:  # a layout the decoder cannot take shows at the first row group
            log.debug("archive warm-up: %s", exc)
        self._release()

    def _drain_safely(self) -> None:
        try:
            self._drain()
        except Exception as exc:  # a bug must not end the thread silently: told, and on
            self._fail("archive (an unexpected error)", exc)

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Block until the archive's thread took everything queued before
        this call (written to the raw segment; rows wait for their row
        group), at most ``timeout_s``; True when it did. Not for the
        receive path."""
        target = self._head
        with self._drained:
            return self._drained.wait_for(
                lambda: self._tail >= target or not self._thread.is_alive(), timeout_s
            )

    def _drain(self) -> None:
        self._reap_seals(wait=False)
        evs = []
        while self._events:
            evs.append(self._events.popleft())
        cap = self._cap
        # A few at a time (TAKE_BYTES), read in place in the ring; their
        # slots freed once they are in the raw segment and the block (a row
        # group written meanwhile keeps no more of the ring taken).
        failed: BaseException | None = None
        while self._tail < self._head:
            tail = self._tail
            i = tail % cap
            n = min(self._head - tail, cap - i, self._take)
            rows, rx = self._ring2d[i : i + n], self._rx[i : i + n]
            self._batch_raw = 0
            try:
                epochs = rows[:, self._epoch_at : self._epoch_at + 8].copy().view("<u8")[:, 0]
                cuts = np.flatnonzero(np.diff(epochs)) + 1
                for part in np.split(np.arange(n), cuts):
                    a, b = int(part[0]), int(part[-1]) + 1
                    self._ingest(int(epochs[a]), rows[a:b], rx[a:b])
            except (OSError, pa.ArrowException, ArchiveError) as exc:
                self.lost += n - self._batch_raw  # those in the raw segment are kept
                failed = failed or exc
            self._tail = tail + n
        if failed is not None:
            self._failure("write", failed)  # counted once a wake-up, as one write
        try:
            for e in evs:
                self._event(e)
            self._sync()
        except (OSError, pa.ArrowException, ArchiveError) as exc:
            self._failure("write", exc)

    def _failure(self, what: str, exc: BaseException) -> None:
        """A write failed (a full disk): counted, told once per kind; the
        rows and events pending for the Parquet files are dropped (a row
        group's files half written are removed where they failed: the
        space comes back). They are in the raw segment: the run's end
        re-decodes them (:func:`.store.refill`), so after space is freed
        the archive goes on and the run ends whole but for what the raw
        segment could not take (counted in :attr:`lost`)."""
        self._fail(what, exc)
        self._pend_n = 0
        self._ev_pend = []
        if self._run is not None:
            self._refill = True

    def _frames(self, rows: np.ndarray, rx: np.ndarray, loops: np.ndarray) -> memoryview:
        """The raw ``FRAME`` records of ``rows`` (at most ``self._take``), built
        in the preallocated buffer: a view of it, valid until the next call."""
        n, rec = len(rows), self._rec_len
        out = self._raw_np[:n]
        out[:, HEADER.size : HEADER.size + 8] = rx.view(np.uint8).reshape(n, 8)
        out[:, HEADER.size + 8 :] = rows
        buf, mv = self._raw_buf, memoryview(self._raw_buf)
        for i, lp in enumerate(loops.tolist()):
            at = i * rec
            HEADER.pack_into(buf, at, SYNC, 0, rec - HEADER.size, FRAME, 0, 0, lp)
            crc = zlib.crc32(mv[at + 8 : at + rec])  # recorder.format.record_crc
            HEADER.pack_into(buf, at, SYNC, crc, rec - HEADER.size, FRAME, 0, 0, lp)
        return mv[: n * rec]

    def _ingest(self, run: int, rows: np.ndarray, rx: np.ndarray) -> None:
        if run != self._run:
            self._end_run("ended")
            self._start_run(run)
        n_in = len(rows)
        loops = rows[:, self._loop_at : self._loop_at + 8].copy().view("<u8")[:, 0]
        keep = []
        new: set[int] = set()
        dups = 0
        for i, lp in enumerate(loops.tolist()):
            if lp in self._seen or lp in new:
                dups += 1
            else:
                new.add(lp)
                keep.append(i)
        if not keep:
            self.duplicates += dups
            self._batch_raw += n_in
            return
        if len(keep) != len(rows):
            rows, rx, loops = rows[keep], rx[keep], loops[keep]
        info = self._info
        assert info is not None
        if info.in_order and (int(loops[0]) <= self._max_loop or bool(np.any(np.diff(loops) <= 0))):
            info.in_order = False  # a late loop (a gap filled out of order): queries sort
        self._raw(self._frames(rows, rx, loops))
        # Taken only once in the raw segment: a loop whose write failed is
        # not seen, so a later copy of it (a gap fill) is archived.
        for lp in sorted(new):
            self._seen.add(lp)
        self.duplicates += dups
        self._batch_raw += n_in
        self.loop_ranges = self._seen.ranges
        self._max_loop = max(self._max_loop, int(loops.max()))
        self.rows += len(rows)
        at = 0
        while at < len(rows):
            k = min(len(rows) - at, self._rg_rows - self._pend_n)
            self._block[self._pend_n : self._pend_n + k] = rows[at : at + k]
            self._block_rx[self._pend_n : self._pend_n + k] = rx[at : at + k]
            self._pend_n += k
            at += k
            if self._pend_n >= self._rg_rows:
                self._flush_groups()

    def _event(self, e: EventRecord) -> None:
        if self._run is None:
            self._early_events.append(e)  # before the first snapshot: the first run's
            del self._early_events[:-EVENT_BACKLOG]
            return
        self._raw(store.raw_record(EVENT, 0, store.encode_event(e)))
        self._ev_pend.append(e)
        info = self._info
        assert info is not None
        info.events += 1
        if (e.severity == "COMMAND" or e.id.startswith("cmd_")) and len(
            info.commands
        ) < MAX_COMMANDS:
            info.commands.append(f"{e.node}: {e.text}")

    def _start_run(self, run: int) -> None:
        # A record a newer zplatform wrote raises ArchiveError here, before
        # this run is taken: its rows are lost, counted and told (_drain).
        info = store.read_run(self.root, run)
        self._run = run
        if info is None:
            info = store.RunInfo(
                run, self.mission.mission, self.mission.vehicle, self.layout.layout_id
            )
            gc = self._group_columns
            info.group_columns = store.GROUP_COLUMNS if gc is None else gc
        self._info = info
        self._groups = store.column_groups(self.layout, info.group_columns)
        self._info.outcome = "open"
        self._seen = LoopSet(
            store.loops_in(store.parquet_files(self.root, "tm", run), self._damage)
        )
        self._max_loop = self._seen.max(-1)
        raw = store.run_dirs(self.root, "raw", run)
        raw.mkdir(parents=True, exist_ok=True)
        used = [store.segment_index(p) for p in raw.iterdir()]
        self._seg_index = max((i for i in used if i is not None), default=-1) + 1
        self._open_segment()
        store.write_run(self.root, self._info)
        early, self._early_events = self._early_events, []
        for e in early:
            self._event(e)

    def _executor(self) -> ThreadPoolExecutor:
        """The encoder threads (made at the first use)."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(ENCODERS, thread_name_prefix="archive-enc")
        return self._pool

    def _seal_segment(self) -> None:
        """Close the open raw segment and hand its compression
        (:func:`.store.seal_segment`) to the encoder threads: the archive's
        thread goes on taking snapshots meanwhile (a 64 MiB segment of a
        100,000-element vector fills every 1.6 s at 100 Hz). The plain
        segment stays until its sealed file is whole (renamed), so a crash
        meanwhile loses nothing; a failure (a full disk) leaves it as it is,
        readable unsealed, and is told by :meth:`_reap_seals`."""
        seg, self._seg = self._seg, None
        if seg is None:
            return
        try:
            with contextlib.suppress(OSError):
                os.fsync(seg.fileno())
        finally:
            seg.close()
        self._sealing.append(self._executor().submit(store.seal_segment, Path(str(seg.name))))

    def _reap_seals(self, *, wait: bool) -> None:
        """Tell the failures of the seals done (``wait``: of every seal handed
        off, waited for first: a run's end, before its raw segments are read
        again)."""
        while self._sealing and (wait or self._sealing[0].done()):
            exc = self._sealing.popleft().exception()
            if isinstance(exc, (OSError, pa.ArrowException)):
                self._fail("compress a raw segment", exc)
            elif exc is not None:
                self._fail("archive (an unexpected error)", exc)

    def _open_segment(self) -> None:
        """Seal the open raw segment, start the next one with its ``HEAD``
        (on an error, a full disk, none is open and the error raised: the
        next write tries again)."""
        self._seal_segment()
        assert self._run is not None
        path = store.run_dirs(self.root, "raw", self._run) / segment_name(self._seg_index)
        head = store.head_record(
            self.mission.mission, self.mission.vehicle, self._run, self.layout, self._seg_index
        )
        # Appending: after a cut back (_raw) the next write goes at the new end.
        seg = open(path, "ab", buffering=0)  # noqa: SIM115
        try:
            _write_all(seg, head)
        except OSError:
            seg.close()
            with contextlib.suppress(OSError):
                path.unlink()
            raise
        self._seg_index += 1
        self._seg, self._seg_bytes = seg, len(head)

    def _raw(self, data: bytes | memoryview) -> None:
        """Append ``data`` (whole records) to the run's raw segment. On an
        error (a full disk) the segment is cut back to its last whole record
        and the error raised: no torn record between good ones."""
        if self._run is None:
            return
        if self._seg is None or self._seg_bytes + len(data) > SEGMENT_BYTES:
            self._open_segment()
        assert self._seg is not None
        try:
            _write_all(self._seg, data)
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(self._seg.fileno(), self._seg_bytes)
            raise
        self._seg_bytes += len(data)

    def _sync(self) -> None:
        now = time.monotonic()
        if self._seg is not None and now - self._synced >= 1.0:
            self._synced = now
            os.fsync(self._seg.fileno())

    def _flush_groups(self) -> None:
        """The block's rows (if any) as one row group: one closed file per
        file group (:meth:`_write_group`)."""
        n, self._pend_n = self._pend_n, 0
        if n:
            self._write_group(self._block[:n], self._block_rx[:n])

    def _coders(self, gc: int | None = None) -> list[store.GroupDecoder]:
        """The file groups' decoders of the run (or of ``gc`` elements per
        group), made once per grouping."""
        if gc is None:
            assert self._info is not None
            gc = self._info.group_columns
        if self._decoders_for != gc:
            groups = store.column_groups(self.layout, gc)
            n = len(groups)
            self._decoders = [store.GroupDecoder(self.layout, groups, k) for k in range(n)]
            self._decoders_for = gc
        return self._decoders

    def _write_group(self, rows: np.ndarray, rx: np.ndarray) -> None:
        """``rows`` as one row group: a closed file per file group in the
        hour of its first row, written as ``*.tmp``, the groups renamed
        first and group 0 last (a reader that sees a group-0 file sees its
        groups); then the events held and the run's record, and every
        ``file_s`` retention. On an error the ``*.tmp`` files are removed
        and it is raised."""
        assert self._info is not None and self._run is not None
        coders = self._coders()
        t_at = self.layout.element("cn_time_ns").offset
        hour = store.hour_dir(int(rows[0, t_at : t_at + 8].view("<i8")[0]))
        d = store.run_dirs(self.root, "tm", self._run) / hour
        d.mkdir(parents=True, exist_ok=True)
        key = f"{self._run}/{hour}"
        if key not in self._parts:
            self._parts[key] = self._compacted[key] = store.next_part(d)
            self._part_dirs[key] = d
        part = d / f"part-{self._parts[key]:06d}.parquet"
        self._parts[key] += 1
        tmps = [Path(str(store.group_path(part, k)) + ".tmp") for k in range(len(coders))]

        def write(k: int) -> None:
            c = coders[k]
            pq.write_table(c.table(rows, rx), tmps[k], **c.options)

        try:
            if len(coders) == 1:
                write(0)
            else:
                # every group's file done (or failed) before any is renamed
                pool = self._executor()
                futures = [pool.submit(write, k) for k in range(len(coders))]
                errors = [f.exception() for f in futures]
                for exc in errors:
                    if exc is not None:
                        raise exc
            for k in range(len(coders) - 1, -1, -1):
                os.replace(tmps[k], store.group_path(part, k))
        except BaseException:
            for t in tmps:
                with contextlib.suppress(OSError):
                    t.unlink()
            # Its number is a hole: compaction starts after it (the parts
            # before it in this hour stay as they are).
            self._compacted[key] = self._parts[key]
            raise
        store._account(self._info, self.layout, rows)
        self._close_file()
        self._since_retain += len(rows)
        if self._since_retain >= self._retain_rows:
            self._since_retain = 0
            self._compact(final=False)
            self._retain()

    def _compact(self, *, final: bool) -> None:
        """Every ``file_s`` and at the run's end: the row-group files of a
        run of one file group written since the last pass, per hour, as one
        file (:func:`.store.compact`; a query of an hour opens a few files,
        not sixty). The parts compacted at the last pass are removed now
        (``final``: these too), so a reader that listed them before finds
        them. A failure is counted and told; the parts stay, whole."""
        for f in self._covered:
            with contextlib.suppress(OSError):
                f.unlink()
        self._covered = []
        if self._info is None or len(self._coders()) != 1:
            return  # a wide layout's row groups are large: files of one each
        for key, nxt in self._parts.items():
            first, d = self._compacted[key], self._part_dirs[key]
            if nxt - first < 2:
                continue
            try:
                store.compact(d, first, nxt - 1)
            except (OSError, pa.ArrowException) as exc:
                self._fail("compact its files", exc)
                continue
            self._compacted[key] = nxt
            self._covered += [d / f"part-{n:06d}.parquet" for n in range(first, nxt)]
        if final:
            for f in self._covered:
                with contextlib.suppress(OSError):
                    f.unlink()
            self._covered = []

    def _release(self) -> None:
        release_memory()
        self.releases += 1

    def _close_file(self) -> None:
        """Write the events held and the run's record."""
        if self._ev_pend and self._run is not None:
            d = store.run_dirs(self.root, "ev", self._run)
            d.mkdir(parents=True, exist_ok=True)
            store._write_parquet(
                d / f"part-{store.next_part(d):06d}.parquet", store.event_table(self._ev_pend)
            )
            self._ev_pend = []
        if self._info is not None:
            store.write_run(self.root, self._info)
        # Each row group closes its files here: their encoders' memory goes
        # back to the system (the ground's step in the flood soak).
        self._release()

    def _retain(self) -> None:
        def removed(run: int, size: int, why: str) -> None:
            self._note(EV.ARCHIVE_REMOVED, run=run, size=size, why=why)

        store.retain(
            self.root,
            max_bytes=self.cfg.max_bytes,
            max_age_days=self.cfg.max_age_days,
            keep=self._run,
            now_ns=time.time_ns(),
            removed=removed,
        )

    def _end_run(self, outcome: str) -> None:
        """Close the run's files; after a failed write re-decode what its
        Parquet files lack from its raw segments first. On an error the
        record stays ``open``: the next opening recovers it."""
        if self._run is None:
            return
        info = self._info
        assert info is not None
        try:
            self._flush_groups()
            info.outcome = "open" if self._refill else outcome
            self._close_file()
            self._compact(final=True)
            self._retain()
            if self._refill:
                if self._seg is not None:
                    with contextlib.suppress(OSError):
                        os.fsync(self._seg.fileno())
                self._reap_seals(wait=True)  # no segment renamed under refill's reading
                store.refill(self.root, self.layout, info, self._damage, self._schema)
                store.recount(self.root, self.layout, info, self._damage)
                info.outcome = outcome
                store.write_run(self.root, info)
        finally:
            self._run = None
            self._refill = False
            self._pend_n = 0
            self._parts.clear()
            self._part_dirs.clear()
            self._compacted.clear()
            self._seal_segment()
            self._reap_seals(wait=True)  # the run's segments all sealed when it ends

    # -- the end ------------------------------------------------------------
    def close(self, timeout_s: float = 30.0) -> None:
        """Take what is queued, close the run's files (outcome ``ended``),
        release the lock; idempotent. Blocks up to ``timeout_s`` for the
        thread."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout_s)
        try:
            self._end_run("ended")
        except (OSError, pa.ArrowException) as exc:
            self._fail("close its files", exc)
        finally:
            if self._pool is not None:
                self._pool.shutdown()
            os.close(self._lock_fd)

    def stats(self) -> dict[str, int]:
        """What it kept: rows, duplicates, dropped snapshots and events,
        errors and the snapshots they lost."""
        return {
            "rows": self.rows,
            "duplicates": self.duplicates,
            "dropped": self.dropped,
            "events_dropped": self.events_dropped,
            "errors": self.errors,
            "lost": self.lost,
        }
