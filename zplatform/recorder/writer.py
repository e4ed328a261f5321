"""The recording side: a node's loop copies, a writer thread writes.

:class:`FlightRecorder` keeps one node's records in a ring of segment files
(:mod:`~.format`): a preallocated RAM ring (``buffer_bytes``) that the loop
fills and a writer thread that checksums, writes (unbuffered), fsyncs as
``fsync_ms`` says, and only then frees the space.

Contract: the loop thread's calls (:meth:`~FlightRecorder.frame`,
:meth:`~FlightRecorder.event`, :meth:`~FlightRecorder.tick`) never block,
never raise and allocate nothing per call. Bounded everywhere: a loop the
buffer cannot take is dropped whole and counted (:attr:`FlightRecorder.dropped`,
a ``DROPPED`` record, ``recorder_dropping``/``recorder_resumed`` events); the
directory's segments stay within ``max_bytes``, the oldest removed first
(:attr:`evicted`, ``recorder_evicted``); a failed write, fsync or open is
counted (:attr:`errors`) and told once per kind (``recorder_failed``). One
recorder per directory: it is locked for the recorder's life, and a second
one is refused with :class:`~zplatform.errors.RecordingError`.

The design and what survives a kill: docs/architecture.md#flight-recorder.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

from ..core.datavector import DataVector
from ..core.events import EV, EventLog
from ..core.health import Heartbeat
from ..errors import RecordingError
from .format import (
    COUNTS,
    DROPPED,
    END,
    EVENT,
    FORMAT_VERSION,
    FRAME,
    HEAD,
    HEADER,
    HEADER_LEN,
    SEGMENT_RE,
    SYNC,
    WRAP,
    record_crc,
    segment_name,
)

__all__ = ["FlightRecorder", "SegmentInfo", "default_opener"]

LOCK_FILE = ".lock"
_U32_MAX = 0xFFFF_FFFF


def default_opener(path: Path) -> BinaryIO:
    """A new segment file, unbuffered (every write goes to the OS at once);
    FileExistsError if ``path`` exists."""
    return open(path, "xb", buffering=0)


class SegmentInfo:
    """One segment of the ring, as the writer knows it: ``index``, ``path``,
    ``size`` (bytes written), and for segments of this run, ``run`` and the
    ``first``/``last`` loop of its frames (0 before the first). Read by the
    gap-fill server under :attr:`FlightRecorder.lock`."""

    __slots__ = ("first", "index", "last", "path", "run", "size")

    def __init__(self, index: int, path: Path, size: int, run: int | None) -> None:
        self.index, self.path, self.size, self.run = index, path, size, run
        self.first = self.last = 0


class FlightRecorder:
    """A node's flight recorder (module doc).

    ``head``: the fields of every segment's ``HEAD`` record (``mission``,
    ``vehicle``, ``node``, ``run``, ``kind``, ``layout_id``, ``channel``,
    ``period_ns``, ``telemetry_divisor``); ``max_record``: the longest
    payload the node will hand over (its frame with the tag; events are
    shorter). ``opener`` makes each segment file (default
    :func:`default_opener`; tests pass slow or failing fakes). The writer
    thread checks in through :attr:`heartbeat` (``recorder``,
    :mod:`zplatform.core.health`) each time it wakes, at least every
    ``interval_s``: one stuck in a write to a hung storage is named stalled.

    Construction creates and locks the directory and opens the first
    segment (removing the oldest ones if the ring is full), then starts the
    writer; RecordingError (naming the directory) if any of that fails.
    The loop-thread methods never raise; :meth:`close` ends the run
    (idempotent).
    """

    def __init__(
        self,
        directory: str | Path,
        head: dict[str, Any],
        *,
        max_bytes: int,
        file_bytes: int,
        fsync_ms: float | None,
        buffer_bytes: int,
        max_record: int,
        interval_s: float = 0.01,
        opener: Callable[[Path], BinaryIO] = default_opener,
    ) -> None:
        self.directory = Path(directory)
        self._head_meta = dict(head)
        self.run = int(head["run"])
        self.node = str(head["node"])
        self.max_bytes = max_bytes
        self.file_bytes = file_bytes
        self._fsync_ns = None if fsync_ms is None else int(fsync_ms * 1e6)
        self._opener = opener
        self.heartbeat = Heartbeat("recorder")
        """The writer thread's check-in, for the node's :class:`~zplatform.core.health.Liveness`."""
        self._interval = interval_s
        rec = HEADER_LEN + max_record
        if file_bytes < HEADER_LEN * 2 + 4096 + 4 * rec:
            raise RecordingError(
                f"recorder file_bytes {file_bytes} is too small for {self.node}'s records "
                f"({rec} bytes each): a file must hold a header and several loops"
            )
        cap = max(buffer_bytes, 4 * rec)
        self._buf = bytearray(cap)
        self._mv = memoryview(self._buf)
        self._cap = cap
        self._half = cap // 2
        self._max_payload = min(cap // 2, file_bytes // 4) - HEADER_LEN
        # The ring's indices: absolute byte counts, head moved only by the
        # loop thread, tail only by the writer (space is free once written).
        self._head = 0
        self._tail = 0
        self.loop = 0
        """The loop of the last frame handed over (events are filed under it)."""
        # loop-thread counters
        self.loops = 0
        """Frames (loops) copied into the buffer."""
        self.events_kept = 0
        self.events_dropped = 0
        self._dropped_ring = 0
        self._drop_first = self._drop_last = self._drop_n = 0
        # writer-thread counters (ints: read by the loop thread, written here)
        self.lost = 0
        """Loops whose records a failed write lost."""
        self.evicted = 0
        """Segment files removed by the ring to stay within ``max_bytes``."""
        self.errors = 0
        """Failed opens, writes, fsyncs, removals."""
        self.bytes_written = 0
        self.written_loop = 0
        """The last loop whose frame is in a file (written, maybe not fsynced)."""
        self.last_error = ""
        self.last_evicted = ("", 0)
        # reporting (attach)
        self._events: EventLog | None = None
        self._h: tuple[Any, Any, Any] | None = None
        self._seen = [0, 0, 0]  # dropped, evicted, errors as last reported
        self._error_kinds: set[str] = set()
        self._new_errors: deque[tuple[str, str]] = deque(maxlen=16)
        self.lock = threading.Lock()
        """Guards :attr:`segments` (the writer changes it, the gap-fill server reads it)."""
        self.segments: list[SegmentInfo] = []
        self._file: BinaryIO | None = None
        self._cur: SegmentInfo | None = None
        self._dirty = False
        self._last_sync = time.monotonic_ns()
        self._stop = False
        self._closed = False
        self._lock_fd = -1
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            self._lock_fd = os.open(self.directory / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise RecordingError(
                    f"the recorder directory {str(self.directory)!r} is in use by another "
                    "recorder (another run of this node?)"
                ) from None
            self._scan()
            self._open_segment()
        except OSError as exc:
            self._release_lock()
            raise RecordingError(
                f"cannot record into {str(self.directory)!r}: {exc.strerror or exc}"
            ) from exc
        except RecordingError:
            self._release_lock()
            raise
        self._wake = threading.Event()
        self._thread = threading.Thread(
            target=self._write_loop, name=f"recorder-{self.node}", daemon=True
        )
        self._thread.start()

    # -- reporting into the node's Data Vector and events --------------------
    def attach(self, dv: DataVector, events: EventLog, *, prefix: str | None = None) -> None:
        """Report from now on: the counters into ``dv``'s ``<node>_rec_dropped``,
        ``_rec_evicted`` and ``_rec_errors`` (at :meth:`tick`), and the
        recorder's events into ``events``. Call before the first loop.
        ``prefix``: the elements' owner when not the node (a standby control
        node reports into the commander's ``cn_rec_*``)."""
        n = prefix or self.node
        self._h = (
            dv.handle(f"{n}_rec_dropped"),
            dv.handle(f"{n}_rec_evicted"),
            dv.handle(f"{n}_rec_errors"),
        )
        self._events = events

    @property
    def backlog(self) -> int:
        """Bytes copied in and not yet written out (0: the files hold everything)."""
        return self._head - self._tail

    @property
    def dropped(self) -> int:
        """Loops not kept: the buffer was full, or a failed write lost them."""
        return self._dropped_ring + self.lost

    def tick(self, t_ns: int) -> None:
        """Loop thread, once per loop: bring the Data Vector counters up to
        date and tell what the writer met (evictions, failures) as events.
        Costs three int compares when nothing changed."""
        h = self._h
        if h is None:
            return
        seen = self._seen
        d, ev, er = self.dropped, self.evicted, self.errors
        if d != seen[0]:
            h[0].set(min(d, _U32_MAX))
            seen[0] = d
        if ev != seen[1]:
            h[1].set(min(ev, _U32_MAX))
            seen[1] = ev
            name, size = self.last_evicted
            self._emit(EV.RECORDER_EVICTED, t_ns, file=name, size=size, n=ev)
        if er != seen[2]:
            h[2].set(min(er, _U32_MAX))
            seen[2] = er
            while self._new_errors:
                what, error = self._new_errors.popleft()
                self._emit(EV.RECORDER_FAILED, t_ns, what=what, error=error)

    def _emit(self, ev: Any, t_ns: int, **args: Any) -> None:
        if self._events is not None:
            self._events.emit(ev, t_ns, node=self.node, **args)

    # -- the loop's side -----------------------------------------------------
    def frame(self, loop: int, frame: bytes | bytearray | memoryview, t_ns: int = 0) -> bool:
        """Keep the frame of loop ``loop`` (a copy); False when the loop is
        dropped (counted; events at the start and the end of a streak,
        stamped ``t_ns``)."""
        self.loop = loop
        if self._drop_n:
            # Say which loops were lost before the first one kept again, and
            # only when that record and this loop's both fit.
            need = 2 * (2 * HEADER_LEN + COUNTS.size + len(frame))
            if self._cap - (self._head - self._tail) < need or not self._put(
                DROPPED, loop, COUNTS.size, None, self._drop_first
            ):
                return self._dropping(loop, t_ns)
            first, last, n = self._drop_first, self._drop_last, self._drop_n
            self._drop_n = 0
            self._emit(EV.RECORDER_RESUMED, t_ns, loop=loop, n=n, first=first, last=last)
        if self._put(FRAME, loop, len(frame), frame, 0):
            self.loops += 1
            return True
        return self._dropping(loop, t_ns)

    def _dropping(self, loop: int, t_ns: int) -> bool:
        self._dropped_ring += 1
        if not self._drop_n:
            self._drop_first = loop
            self._emit(
                EV.RECORDER_DROPPING,
                t_ns,
                loop=loop,
                why=f"its {self._cap}-byte buffer is full (the storage is slower than the loop "
                "or stalled)",
            )
        self._drop_last = loop
        self._drop_n += 1
        return False

    def event(self, payload: bytes | bytearray | memoryview) -> bool:
        """Keep one encoded event record, filed under the current loop;
        False (counted in :attr:`events_dropped`) when it does not fit."""
        if self._put(EVENT, self.loop, len(payload), payload, 0):
            self.events_kept += 1
            return True
        self.events_dropped += 1
        return False

    def _put(
        self,
        typ: int,
        loop: int,
        n: int,
        payload: bytes | bytearray | memoryview | None,
        first: int,
    ) -> bool:
        """Copy one record into the ring (``payload`` None: the DROPPED counts
        of the streak, ``first`` its first loop); False when it does not fit."""
        if n > self._max_payload:
            return False
        size = HEADER_LEN + n
        cap = self._cap
        head = self._head
        pos = head % cap
        pad = cap - pos if cap - pos < size else 0
        if head + pad + size - self._tail > cap:
            if head - self._tail > self._half:
                self._wake.set()
            return False
        buf = self._buf
        if pad:
            if pad >= HEADER_LEN:  # tell the writer the rest of the ring is unused
                HEADER.pack_into(buf, pos, SYNC, 0, pad - HEADER_LEN, WRAP, 0, 0, 0)
            pos = 0
        HEADER.pack_into(buf, pos, SYNC, 0, n, typ, 0, 0, loop)
        if payload is None:
            COUNTS.pack_into(buf, pos + HEADER_LEN, first, self._drop_last, self._drop_n)
        elif n:
            self._mv[pos + HEADER_LEN : pos + size] = payload
        head += pad + size
        self._head = head  # published: the writer may take it from now on
        if head - self._tail > self._half:
            self._wake.set()
        return True

    # -- the writer thread ---------------------------------------------------
    def _write_loop(self) -> None:
        while True:
            stop = self._stop
            self._wake.wait(self._interval)
            self._wake.clear()
            self.heartbeat.beat()
            self._drain()
            self._sync_due(time.monotonic_ns())
            if stop:
                self.heartbeat.idle()  # ended: not stalled
                return

    def _drain(self) -> None:
        """Write every published record (checksummed here), in batches of
        records contiguous in the ring and within one segment; free their
        space once written."""
        head = self._head
        tail = self._tail
        cap = self._cap
        buf, mv = self._buf, self._mv
        start = tail % cap  # the batch: ring bytes [start, start + length)
        length = frames = 0
        roll_failed = False
        while tail + length < head:
            pos = (tail + length) % cap
            if length and pos != start + length:  # wrapped to the ring's start
                tail = self._flush(start, length, frames, tail)
                start, length, frames = pos, 0, 0
            left = cap - pos
            typ = WRAP
            n = loop = 0
            if left >= HEADER_LEN:
                _, _, n, typ, _, _, loop = HEADER.unpack_from(buf, pos)
            if typ == WRAP:  # the rest of the ring is unused (marked, or too short)
                tail = self._flush(start, length, frames, tail) + left
                self._tail = tail
                start, length, frames = 0, 0, 0
                continue
            size = HEADER_LEN + n
            cur = self._cur
            if (cur is None and not roll_failed) or (
                cur is not None and cur.size + length + size > self.file_bytes
            ):
                tail = self._flush(start, length, frames, tail)
                start, length, frames = pos, 0, 0
                self._roll()
                cur = self._cur
                roll_failed = cur is None  # once per drain: a dead storage is not hammered
            HEADER.pack_into(buf, pos, SYNC, record_crc(mv, pos, pos + size), n, typ, 0, 0, loop)
            if typ == FRAME:
                frames += 1
                if cur is not None:
                    if not cur.first:
                        cur.first = loop
                    cur.last = loop
            length += size
        self._flush(start, length, frames, tail)

    def _flush(self, start: int, length: int, frames: int, tail: int) -> int:
        """Write ``length`` bytes from ring position ``start`` to the current
        segment (``frames`` of its records are loops); free them; return the
        new tail. A failed write loses them (counted)."""
        if not length:
            return tail
        f, cur = self._file, self._cur
        try:
            if f is None or cur is None:
                raise OSError("no file is open (starting one failed)")
            view = self._mv[start : start + length]
            done = 0
            while done < length:
                w = f.write(view[done:])
                if not w:
                    raise OSError("the write wrote nothing")
                done += w
            with self.lock:
                cur.size += length
            if cur.last:
                self.written_loop = cur.last
            self.bytes_written += length
            self._dirty = True
        except OSError as exc:
            self.lost += frames
            self._failed("write its file", exc)
            self._close_segment()  # it may be torn: the next write starts another
        tail += length
        self._tail = tail
        return tail

    def _sync_due(self, now_ns: int) -> None:
        every = self._fsync_ns
        if every is None or not self._dirty or now_ns - self._last_sync < every:
            return
        self._fsync()
        self._last_sync = now_ns

    def _fsync(self) -> None:
        f = self._file
        if f is None:
            return
        try:
            os.fsync(f.fileno())
            self._dirty = False
        except OSError as exc:
            self._failed("flush its file to the storage", exc)
        except (AttributeError, ValueError):  # a file object with no descriptor
            self._dirty = False

    def _failed(self, what: str, exc: BaseException) -> None:
        text = f"{exc.strerror or exc}" if isinstance(exc, OSError) else str(exc)
        self.last_error = f"{what}: {text}"
        if what not in self._error_kinds:  # told once per kind; every one is counted
            self._error_kinds.add(what)
            self._new_errors.append((what, text))
        self.errors += 1

    # -- segments --------------------------------------------------------------
    def _scan(self) -> None:
        """The segments already in the directory (earlier runs), oldest first."""
        found: list[SegmentInfo] = []
        for name in os.listdir(self.directory):
            m = SEGMENT_RE.fullmatch(name)
            if m is None:
                continue
            p = self.directory / name
            st = os.lstat(p)
            if stat.S_ISREG(st.st_mode):
                found.append(SegmentInfo(int(m.group(1)), p, st.st_size, None))
        found.sort(key=lambda s: s.index)
        self.segments = found
        self._next_index = found[-1].index + 1 if found else 1

    def _roll(self) -> None:
        """Close the current segment and start the next one (writer thread)."""
        self._close_segment()
        try:
            self._open_segment()
        except OSError as exc:
            self._failed("start a new file", exc)

    def _close_segment(self) -> None:
        f, self._file = self._file, None
        self._cur = None
        if f is None:
            return
        if self._fsync_ns is not None and self._dirty:
            with contextlib.suppress(OSError, AttributeError, ValueError):
                os.fsync(f.fileno())
        self._dirty = False
        try:
            f.close()
        except OSError as exc:
            self._failed("close its file", exc)

    def _open_segment(self) -> None:
        """Make room (oldest segments first), then create the next segment and
        write its header. Raises OSError when it cannot."""
        with self.lock:
            total = sum(s.size for s in self.segments)
            while self.segments and total + self.file_bytes > self.max_bytes:
                old = self.segments.pop(0)
                total -= old.size
                try:
                    os.unlink(old.path)
                except FileNotFoundError:
                    pass
                except OSError as exc:
                    self._failed("remove its oldest file", exc)
                    continue
                self.last_evicted = (old.path.name, old.size)
                self.evicted += 1
        index = self._next_index
        self._next_index += 1
        path = self.directory / segment_name(index)
        meta = dict(self._head_meta)
        meta.update(format=FORMAT_VERSION, segment=index, created_unix_ns=time.time_ns())
        body = json.dumps(meta, sort_keys=True).encode()
        rec = bytearray(HEADER_LEN + len(body))
        HEADER.pack_into(rec, 0, SYNC, 0, len(body), HEAD, 0, 0, 0)
        rec[HEADER_LEN:] = body
        HEADER.pack_into(rec, 0, SYNC, record_crc(rec, 0, len(rec)), len(body), HEAD, 0, 0, 0)
        f = self._opener(path)
        try:
            f.write(rec)
        except OSError:
            f.close()
            raise
        info = SegmentInfo(index, path, len(rec), self.run)
        with self.lock:
            self.segments.append(info)
        self._file, self._cur = f, info
        self._dirty = True
        if self._fsync_ns is not None:  # the new file's name, durable too
            self._fsync_dir()

    def _fsync_dir(self) -> None:
        try:
            fd = os.open(self.directory, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(fd)
        except OSError as exc:
            self._failed("flush its directory", exc)
        finally:
            os.close(fd)

    # -- the end ---------------------------------------------------------------
    def close(self, timeout_s: float = 5.0) -> None:
        """End the run: a DROPPED record for a streak still open, an END
        record, then everything written, fsynced (unless the policy is
        never) and closed. Waits up to ``timeout_s`` for the writer; a
        storage stalled beyond that is left to it (the thread is a daemon)
        and counted as an error. Idempotent; call from the loop's thread
        after the last loop."""
        if self._closed:
            return
        self._closed = True
        if self._drop_n and self._put(DROPPED, self.loop, COUNTS.size, None, self._drop_first):
            self._drop_n = 0
        end = COUNTS.pack(self.loops, self.dropped, self.events_kept)
        self._put(END, self.loop, len(end), end, 0)
        self._stop = True
        self._wake.set()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            stalled = TimeoutError(f"the storage did not take its data in {timeout_s:g} s")
            self._failed("finish writing", stalled)
            return  # the writer still holds the file: leave it and the lock to it
        self._close_segment()
        self._release_lock()

    def _release_lock(self) -> None:
        if self._lock_fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self._lock_fd)
            self._lock_fd = -1

    def stats(self) -> dict[str, int | str]:
        """What the recorder did (for summaries): loops and events kept and
        dropped, bytes written, files removed, errors and the last one."""
        return {
            "loops": self.loops,
            "dropped_loops": self.dropped,
            "events": self.events_kept,
            "dropped_events": self.events_dropped,
            "bytes": self.bytes_written,
            "evicted_files": self.evicted,
            "errors": self.errors,
            "last_error": self.last_error,
        }
