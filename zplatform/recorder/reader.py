"""Reading a flight recorder directory back: every record that checks, and a
clear word about every one that does not.

:class:`RecorderReader` lists a node's segment files (regular files named
``seg-NNNNNNNN.zfr``, oldest first) and yields their records in order
(:meth:`RecorderReader.records`). Nothing it meets raises: a damaged or torn
record, a file without a readable header, a file that is not a regular file
or is larger than any segment can be, each adds one line to
:attr:`RecorderReader.problems` (naming the file and the offset) and the
reading goes on with the next record that checks. Reads are bounded: each
segment is mapped read-only (never read whole into memory), every length is
checked against the file before it is used, and a record's payload is copied
out only once its checksum holds.

:func:`scan_segment` is the one parser, shared with the CN's gap-fill server
(:mod:`zplatform.recorder.server`), which reads the segments of the running
recorder the same way.
"""

from __future__ import annotations

import contextlib
import json
import mmap
import os
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from ..errors import RecordingError
from .format import (
    COUNTS,
    END,
    FORMAT_VERSION,
    FRAME,
    HEAD,
    HEADER,
    HEADER_LEN,
    MAX_HEAD_LEN,
    SEGMENT_RE,
    SYNC,
    TYPE_NAMES,
    UNTAGGED_FORMATS,
    record_crc,
)

__all__ = ["MAX_SEGMENT_BYTES", "Record", "RecorderReader", "SegmentHead", "scan_segment"]

MAX_SEGMENT_BYTES = (1 << 30) + (1 << 20)
"""Larger than any segment the recorder writes (``file_bytes`` is at most 1 GiB)."""


class Record(NamedTuple):
    """One record that checked: its ``type`` (:mod:`~.format` constants),
    ``loop``, ``payload`` (a copy) and where it was (``offset`` in its file)."""

    type: int
    loop: int
    payload: bytes
    offset: int


class SegmentHead(NamedTuple):
    """A segment's header record, read back (:mod:`~.format`, ``HEAD``)."""

    path: Path
    segment: int
    mission: str
    vehicle: str
    node: str
    run: int
    kind: str
    layout_id: int
    channel: str | None
    period_ns: int
    telemetry_divisor: int
    created_unix_ns: int

    @classmethod
    def parse(cls, path: Path, segment: int, payload: bytes) -> SegmentHead:
        """RecordingError (saying what is wrong) for a header that is not ours."""
        try:
            meta: Any = json.loads(payload.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise RecordingError(f"its header is not JSON ({exc})") from None
        if not isinstance(meta, dict):
            raise RecordingError("its header is not a JSON object")
        fmt = meta.get("format")
        if fmt in UNTAGGED_FORMATS and meta.get("channel") is not None:
            raise RecordingError(
                f"recorder format {fmt}: its frames carry an earlier zplatform's authentication "
                f"tag, which this one (format {FORMAT_VERSION}: the tag with a header tag, "
                "codecs/FORMAT.md §6.1) does not check; read it with the zplatform that wrote it"
            )
        if fmt != FORMAT_VERSION and fmt not in UNTAGGED_FORMATS:
            raise RecordingError(f"recorder format {fmt!r}, this zplatform reads {FORMAT_VERSION}")

        def field(name: str, typ: type, optional: bool = False) -> Any:
            v = meta.get(name)
            if (v is None and optional) or (isinstance(v, typ) and not isinstance(v, bool)):
                return v
            raise RecordingError(f"its header has no valid {name!r} ({v!r})")

        return cls(
            path,
            segment,
            field("mission", str),
            field("vehicle", str),
            field("node", str),
            field("run", int),
            field("kind", str),
            field("layout_id", int),
            field("channel", str, optional=True),
            field("period_ns", int),
            field("telemetry_divisor", int),
            field("created_unix_ns", int),
        )


def _next_record(mm: mmap.mmap, start: int, end: int) -> int:
    """The offset of the next record at or after ``start`` whose length and
    checksum hold, or ``end`` when there is none."""
    off = start
    while True:
        off = mm.find(SYNC, off, end)
        if off < 0:
            return end
        if off + HEADER_LEN <= end:
            _, crc, length, *_ = HEADER.unpack_from(mm, off)
            stop = off + HEADER_LEN + length
            if stop <= end and record_crc(mm[off:stop], 0, stop - off) == crc:
                return off
        off += 1


def scan_segment(
    path: Path,
    problem: Callable[[str], None],
    *,
    limit: int | None = None,
    start: int = 0,
    want: Callable[[int, int], bool] | None = None,
) -> Iterator[Record]:
    """Every record of segment ``path`` that checks, in order, from byte
    ``start`` up to ``limit`` bytes (None: the file's size when opened).
    ``want(type, loop)``: yield only the records it accepts; the others are
    stepped over by their length without being checksummed (cheaper, for the
    gap-fill server: a damaged length among them is met at the next record,
    which then fails its marker and is resynchronised).

    ``problem(text)`` is called once per damage met (text names the file
    and offset): a torn tail, bytes skipped to the next good record, a file
    that cannot be opened, is not a regular file or is too large. Never
    raises for the file's contents."""
    name = path.name
    try:
        # Not through a symlink; a FIFO named like a segment must not block the open.
        flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
        fd = os.open(path, flags)
    except OSError as exc:
        problem(f"{name}: cannot open it: {exc.strerror}")
        return
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            problem(f"{name}: not a regular file: skipped")
            return
        size = st.st_size if limit is None else min(limit, st.st_size)
        if size > MAX_SEGMENT_BYTES:
            problem(f"{name}: {size} bytes, larger than any recorder segment: skipped")
            return
        if size <= start:
            return
        try:
            mm = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError) as exc:
            problem(f"{name}: cannot map it: {exc}")
            return
    finally:
        os.close(fd)
    with contextlib.closing(mm):
        end = min(size, len(mm))
        off = start
        while off < end:
            bad = ""
            if end - off < HEADER_LEN:
                bad = "an incomplete record header"
            elif mm[off : off + 4] != SYNC:
                bad = "no record marker"
            else:
                _, crc, length, typ, _flags, _res, loop = HEADER.unpack_from(mm, off)
                stop = off + HEADER_LEN + length
                if stop > end:
                    bad = f"a record of {length} bytes that runs past the end of the file"
                elif want is not None and not want(typ, loop):
                    off = stop
                    continue
                else:
                    body = mm[off:stop]
                    if record_crc(body, 0, len(body)) != crc:
                        bad = "a record whose checksum does not match"
                    else:
                        yield Record(typ, loop, body[HEADER_LEN:], off)
                        off = stop
                        continue
            nxt = _next_record(mm, off + 1, end)
            if nxt >= end:
                problem(
                    f"{name}: offset {off}: torn tail ({bad}; the last {end - off} bytes hold "
                    "no complete record): skipped"
                )
            else:
                problem(
                    f"{name}: offset {off}: damaged ({bad}): {nxt - off} bytes skipped to the "
                    "next good record"
                )
            off = nxt


class RecorderReader:
    """One node's recorder directory, read back (module doc).

    Construction lists the segments; RecordingError when ``directory`` is
    not a directory or holds no segment (naming the node directories inside
    when it is the recorder's base directory). :meth:`records` may be
    called once; afterwards :attr:`problems` lists every damage met (one
    line each) and the counters say what was read."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        d = self.directory
        try:
            entries = sorted(os.listdir(d))
        except NotADirectoryError:
            raise RecordingError(f"{str(d)!r} is not a directory") from None
        except FileNotFoundError:
            raise RecordingError(f"no recorder directory {str(d)!r}") from None
        except OSError as exc:
            raise RecordingError(
                f"cannot read the recorder directory {str(d)!r}: {exc.strerror}"
            ) from None
        self.problems: list[str] = []
        self.segments: list[tuple[int, Path]] = []
        for e in entries:
            m = SEGMENT_RE.fullmatch(e)
            if m is not None:
                self.segments.append((int(m.group(1)), d / e))
        if not self.segments:
            inner = sorted(
                e
                for e in entries
                if (d / e).is_dir() and any(SEGMENT_RE.fullmatch(f) for f in _ls(d / e))
            )
            hint = (
                f": it holds the recorder directories of {', '.join(inner)}; pass one of them"
                if inner
                else ""
            )
            raise RecordingError(f"{str(d)!r} holds no recorder segment (seg-*.zfr){hint}")
        self.heads: list[SegmentHead] = []
        """The header of every segment read, in order."""
        self.records_read = 0
        self.damaged = 0
        """Damages met (torn tails, bytes skipped, files skipped): one per line of problems."""
        self.ended_runs = 0
        """Runs whose END record was read (they ended cleanly)."""

    def first_head(self) -> SegmentHead | None:
        """The header of the oldest segment that has a readable one (what
        node and layout the directory holds), without reading further and
        without adding to :attr:`problems`; None when no segment has one."""
        for index, path in self.segments:
            head = self.head_of(index, path)
            if head is not None:
                return head
        return None

    @staticmethod
    def head_of(index: int, path: Path) -> SegmentHead | None:
        """The header of one segment (reading its first record only), None
        when it has no readable one; adds nothing to :attr:`problems`."""
        for rec in scan_segment(path, lambda _text: None):
            if rec.type == HEAD and rec.offset == 0 and len(rec.payload) <= MAX_HEAD_LEN:
                try:
                    return SegmentHead.parse(path, index, rec.payload)
                except RecordingError:
                    pass
            break
        return None

    def _problem(self, text: str) -> None:
        self.damaged += 1
        self.problems.append(text)

    def last_frame(self) -> tuple[SegmentHead, Record] | None:
        """The newest FRAME record (and its segment's header), reading the
        segments newest first and stopping at the first that holds one: what
        a restarted control node resumes from. None when none holds one."""
        for index, path in reversed(self.segments):
            head: SegmentHead | None = None
            last: Record | None = None
            for rec in scan_segment(path, self._problem):
                if head is None:
                    if rec.type != HEAD or rec.offset != 0 or len(rec.payload) > MAX_HEAD_LEN:
                        break
                    try:
                        head = SegmentHead.parse(path, index, rec.payload)
                    except RecordingError:
                        break
                    continue
                if rec.type == FRAME:
                    last = rec
            if head is not None and last is not None:
                return head, last
        return None

    def records(self) -> Iterator[tuple[SegmentHead, Record]]:
        """Every record after a readable header, oldest segment first, with
        that segment's header (HEAD records themselves are not yielded)."""
        for index, path in self.segments:
            head: SegmentHead | None = None
            for rec in scan_segment(path, self._problem):
                if head is None:
                    if rec.type != HEAD or rec.offset != 0 or len(rec.payload) > MAX_HEAD_LEN:
                        self._problem(
                            f"{path.name}: does not start with a readable header "
                            f"(first good record: {TYPE_NAMES.get(rec.type, rec.type)} at offset "
                            f"{rec.offset}): file skipped"
                        )
                        break
                    try:
                        head = SegmentHead.parse(path, index, rec.payload)
                    except RecordingError as exc:
                        self._problem(f"{path.name}: {exc}: file skipped")
                        break
                    self.heads.append(head)
                    continue
                if rec.type == HEAD:
                    self._problem(f"{path.name}: offset {rec.offset}: a second header: skipped")
                    continue
                if rec.type == END:
                    self.ended_runs += 1
                self.records_read += 1
                yield head, rec


def _ls(d: Path) -> list[str]:
    try:
        return os.listdir(d)
    except OSError:
        return []


def counts(payload: bytes) -> tuple[int, int, int] | None:
    """The three u64 of a DROPPED or END record, or None when it is malformed."""
    if len(payload) != COUNTS.size:
        return None
    a, b, c = COUNTS.unpack(payload)
    return int(a), int(b), int(c)
