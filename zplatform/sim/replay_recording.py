"""Recording a live CN's loop inputs, and reading them back for a replay.

:class:`Recorder` (attached to a :class:`~zplatform.control.loop.ControlLogic` by
``up --record DIR``) writes every input the CN's loop consumed, per loop in
call order, and the telemetry it produced, to ``DIR/cn.zrec`` beside the
effective ``DIR/mission.yaml``; :class:`RecordReader` and
:func:`read_recording` read them back for ``zplatform replay``.

Contract: the recorder runs on the loop thread, copies each item into a
preallocated chunk and never blocks or allocates per loop; a writer thread
writes full chunks, and loops that find no free chunk are dropped and
counted (a ``DROPPED`` item), never silently. The reader trusts nothing: it
never imports code the recording names, reads with bounds (regular files
only, sizes capped, one item at a time), checks the recording is of the
mission it is given (:func:`mission_digest`, naming the first difference),
and raises one :class:`~zplatform.errors.RecordingError` naming the file,
offset and what was expected (a tail cut off mid-item is only incomplete).

The file, byte by byte, and the reader's bounds: codecs/FORMAT.md (section 11).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import queue
import stat
import struct
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, TextIO

import msgspec
import yaml

from ..config import Mission, relocate_mission
from ..config.codes import CommandStatus
from ..control.intake import CnRefusals
from ..control.params import SaveResult
from ..core.auth import TAG_LEN
from ..core.codec import RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.health import BLOCK_SIZE, Heartbeat
from ..errors import CodecError, ConfigError, RecordingError

if TYPE_CHECKING:
    from ..telemetry.logs import CsvLogger

__all__ = [
    "MAX_META_BYTES",
    "MAX_MISSION_BYTES",
    "LoopRecord",
    "RecordMeta",
    "RecordReader",
    "Recorder",
    "RecordingSummary",
    "mission_digest",
    "read_recording",
]

MAGIC = b"ZPREC\x00"
# 2: BEGIN's final flag; 3: PRM_SAVED; 4: HEALTH; 5: FINISH the refusals;
# 6: the mission's digest in the header; 7: FINISH the querier recoveries;
# 8: the header-tagged frames; 9: FINISH the frames dropped unchecked;
# 10: FINISH the mirrors refused
VERSION = 10
RECORD_FILE = "cn.zrec"
MISSION_FILE = "mission.yaml"
MAX_META_BYTES = 64 * 1024
"""The longest JSON metadata a recording may have."""
MAX_MISSION_BYTES = 64 * 1024 * 1024
"""The longest recorded ``mission.yaml`` a reader takes (a 100,000-element
mission is about 4 MB)."""
_MAX_SAVE_DETAIL = 512  # bytes of a PRM_SAVED item's detail (the recorder truncates to it)
# Items a loop may hold: the live CN takes one reply per DN and query (a
# few more from late repliers) and the frames of its command inbox. A
# recording over these is not one a CN made, and reading it must not grow
# without bound.
_MAX_REPLIES_PER_DN = 64
_MAX_GROUNDS_PER_LOOP = 1024

BEGIN, REPLY, REPLY_ERR, OVERSIZE, GROUND, GROUND_OVERSIZE, TELEMETRY, FINISH, DROPPED = range(
    1, 10
)
PRM_SAVED, HEALTH = 11, 12  # 10 was FOREIGN (version 4 and before)

_ITEM = struct.Struct("<BBI")  # type, dn, length
_BEGIN = struct.Struct("<QqB")
_FINISH = struct.Struct("<BII" + "I" * 7 + "BQIIII")
_CMD_STATUS = 7  # the refusals' cmd_status, after their seven counts
_STATUSES = frozenset(int(s) for s in CommandStatus)
_U32 = struct.Struct("<I")
_NONE_REFUSED = CnRefusals().fields()
_U64 = struct.Struct("<Q")
_SAVED = struct.Struct("<QB")
_HEAD = struct.Struct("<6sHI")


class _NoAliasDumper(yaml.SafeDumper):
    """A safe dumper that writes a repeated object out again instead of an alias."""

    def ignore_aliases(self, data: Any) -> bool:
        return True


class RecordMeta(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A recording's metadata (its header's JSON): what the CN recorded."""

    mission: str
    layout_id: int
    size: int
    period_ns: int
    device_nodes: list[str]
    telemetry_divisor: int
    mission_digest: str
    created_unix_s: float


def _loop_content(mission: Mission) -> dict[str, Any]:
    """The parts of a mission that decide what its CN's loop does: all of
    it but where it runs (node endpoints, CPUs, priorities and boards,
    the world's address and ptys, ``pythonpath``, the zenoh session
    settings and the link security), which a copy of the mission run on
    other ports or hosts (``up --free-ports``, a recording) changes."""
    raw: dict[str, Any] = msgspec.to_builtins(mission)
    raw["nodes"] = sorted(raw["nodes"])
    raw.pop("pythonpath", None)
    raw.pop("transport", None)
    if isinstance(raw.get("security"), dict):
        raw["security"].pop("transport", None)
    if isinstance(raw.get("world"), dict):
        raw["world"].pop("listen", None)
        raw["world"]["serve_serial"] = sorted(raw["world"].get("serve_serial", {}))
    return raw


def mission_digest(mission: Mission) -> str:
    """SHA-256 (hex) of the mission's loop content (:func:`_loop_content`,
    keys sorted): two missions with the same digest run the same CN loop."""
    return hashlib.sha256(msgspec.json.encode(_loop_content(mission), order="sorted")).hexdigest()


_ABSENT = "<absent>"


def _first_mission_difference(a: Any, b: Any, path: str = "$") -> tuple[str, Any, Any] | None:
    """The YAML path and the two values where ``a`` and ``b`` first differ
    (``<absent>`` for a key or item only one side has)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            d = _first_mission_difference(a.get(k, _ABSENT), b.get(k, _ABSENT), f"{path}.{k}")
            if d is not None:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            d = _first_mission_difference(x, y, f"{path}[{i}]")
            if d is not None:
                return d
        n = min(len(a), len(b))
        if len(a) == len(b):
            return None
        return f"{path}[{n}]", a[n] if n < len(a) else _ABSENT, b[n] if n < len(b) else _ABSENT
    return None if a == b else (path, a, b)


def _frame_bounds(mission: Mission, dv: DataVector) -> tuple[tuple[int, ...], int, int]:
    """The longest reply of each DN, command request and telemetry frame
    ``mission``'s CN takes or makes, as they come off the wire (with an
    authentication tag): what the recorder sizes its chunks for and what a
    reader allows."""
    reply_max = tuple(
        RegionCodec(dv, f"{dn}_to_cn").max_frame_len + TAG_LEN for dn in mission.device_nodes
    )
    ground_max = RegionCodec(dv, "gn_to_cn").max_frame_len + TAG_LEN if mission.has_ground else 0
    return reply_max, ground_max, RegionCodec(dv).max_frame_len + TAG_LEN


class Recorder:
    """Records a CN's loop inputs into ``directory`` (module doc).

    Construction creates the directory, copies ``mission_source`` (the
    mission file the CN loaded; its ``pythonpath`` made absolute, so the copy
    finds the mission's code from anywhere) into it, writes the header with ``dv``'s
    bytes as they are now (call it after the warm-up, before loop 1) and
    starts the writer thread; RecordingError if any of that fails. The
    ``begin``/``reply``/``finish`` methods implement
    :class:`~zplatform.control.loop.LoopRecorder`: they never block, allocate no
    buffers and never raise. :meth:`close` flushes and joins the writer
    (idempotent). ``seconds`` sizes the ring: that many seconds of loops can
    wait for the disk before loops are dropped.
    """

    def __init__(
        self,
        directory: str | Path,
        mission: Mission,
        mission_source: str | Path,
        dv: DataVector,
        *,
        seconds: float = 2.0,
        start: bool = True,
    ) -> None:
        self.directory = Path(directory)
        dns = mission.device_nodes
        # The longest loop record with one reply per DN and the telemetry;
        # a loop with late replies on top simply spans chunks.
        reply_max, ground_max, tm_max = _frame_bounds(mission, dv)
        item = _ITEM.size
        loop_max = (
            item * (5 + 2 * len(dns))
            + BLOCK_SIZE
            + _BEGIN.size
            + _FINISH.size
            + 2 * sum(reply_max)
            + ground_max
            + tm_max
        )
        self._max_reply = reply_max
        self._max_ground = ground_max
        self.chunk_size = max(256 * 1024, 4 * loop_max)
        n_chunks = max(8, int(seconds * mission.loop_hz * loop_max / self.chunk_size) + 2)
        self._chunks = [bytearray(self.chunk_size) for _ in range(n_chunks)]
        self._views = [memoryview(c) for c in self._chunks]
        self._used = [0] * n_chunks
        self._free: queue.SimpleQueue[int] = queue.SimpleQueue()
        self._full: queue.SimpleQueue[int] = queue.SimpleQueue()
        for i in range(1, n_chunks):
            self._free.put(i)
        self._cur = 0
        self._mv = self._views[0]
        self._off = 0
        self._dropping = False
        self._open_loop = False  # a BEGIN is written and its FINISH is not yet
        self.loops = 0
        self.dropped_loops = 0
        self._pending_drops = 0
        self._closed = False
        self.error: str | None = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            # The recorded mission must find its code from the recording's
            # directory too: its pythonpath is made absolute.
            raw = yaml.safe_load(Path(mission_source).read_text())
            relocate_mission(raw, mission_source)
            # Without aliases: a reader refuses them (module doc).
            text = yaml.dump(raw, Dumper=_NoAliasDumper, sort_keys=False)
            (self.directory / MISSION_FILE).write_text(text)
            self._file: BinaryIO = open(self.directory / RECORD_FILE, "wb")  # noqa: SIM115
            meta = msgspec.json.encode(
                RecordMeta(
                    mission=mission.mission,
                    layout_id=dv.layout.layout_id,
                    size=dv.layout.size,
                    period_ns=mission.period_ns,
                    device_nodes=dns,
                    telemetry_divisor=mission.telemetry_divisor,
                    mission_digest=mission_digest(mission),
                    created_unix_s=time.time(),
                )
            )
            self._file.write(_HEAD.pack(MAGIC, VERSION, len(meta)) + meta)
        except (OSError, yaml.YAMLError) as exc:
            raise RecordingError(f"cannot record into {str(self.directory)!r}: {exc}") from exc
        self.started = False
        if start:
            self.start(dv)
        self.heartbeat = Heartbeat("record")
        """The writer thread's check-in (zplatform.core.health), for the node's liveness."""
        self._writer = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._writer.start()

    def start(self, dv: DataVector) -> None:
        """Write ``dv`` as the recording's first vector (what the replay starts
        from); loops may be recorded from now on. Construction does it unless
        ``start=False``: a standby control node makes its recorder ahead (the
        allocations, the mission's copy) and starts it when it takes command,
        with the vector it took over (one small file write). RecordingError
        if the write fails."""
        if self.started:
            return
        init = bytearray(dv.size)
        dv.read_all(init)
        try:
            self._file.write(_U32.pack(len(init)) + init)
        except OSError as exc:
            raise RecordingError(f"cannot record into {str(self.directory)!r}: {exc}") from exc
        self.started = True

    # -- the writer thread -------------------------------------------------
    def _write_loop(self) -> None:
        # Idle while it waits for a chunk; a write that hangs (a stuck disk)
        # is a stall (zplatform.core.health).
        f = self._file
        hb = self.heartbeat
        while True:
            hb.idle()
            i = self._full.get()
            if i < 0:
                return
            hb.beat()
            try:
                f.write(self._views[i][: self._used[i]])
            except OSError as exc:  # disk full: keep draining, report once
                if self.error is None:
                    self.error = str(exc)
            self._free.put(i)

    # -- the loop's side ---------------------------------------------------
    def _submit(self) -> bool:
        """Hand the current chunk to the writer and take a free one; False
        (and drop mode) when none is free."""
        self._used[self._cur] = self._off
        self._full.put(self._cur)
        if self._free.empty():
            self._cur = -1
            self._dropping = True
            return False
        self._cur = self._free.get_nowait()
        self._mv = self._views[self._cur]
        self._off = 0
        return True

    def _put(self, typ: int, dn: int, payload: bytes | bytearray | memoryview, n: int) -> None:
        if self._dropping:
            return
        if self._off + _ITEM.size + n > self.chunk_size and not self._submit():
            return
        off = self._off
        _ITEM.pack_into(self._mv, off, typ, dn, n)
        off += _ITEM.size
        if n:
            self._mv[off : off + n] = payload
        self._off = off + n

    def begin(self, loop: int, t_ns: int, final: bool = False, standby: bool = False) -> None:
        if self._dropping:
            # Resume only at a loop boundary, with a chunk free.
            if self._free.empty():
                self.dropped_loops += 1
                self._pending_drops += 1
                return
            self._cur = self._free.get_nowait()
            self._mv = self._views[self._cur]
            self._off = 0
            self._dropping = False
            self._put_u64(DROPPED, self._pending_drops)
            self._pending_drops = 0
        if self._off + 64 > self.chunk_size:
            self._submit()
            if self._dropping:
                self.dropped_loops += 1
                self._pending_drops += 1
                return
        off = self._off
        _ITEM.pack_into(self._mv, off, BEGIN, 0, _BEGIN.size)
        _BEGIN.pack_into(self._mv, off + _ITEM.size, loop, t_ns, final | (standby << 1))
        self._off = off + _ITEM.size + _BEGIN.size
        self._open_loop = True

    def _put_u64(self, typ: int, v: int) -> None:
        off = self._off
        _ITEM.pack_into(self._mv, off, typ, 0, _U64.size)
        _U64.pack_into(self._mv, off + _ITEM.size, v)
        self._off = off + _ITEM.size + _U64.size

    def reply(self, i: int, payload: bytes | bytearray | memoryview | None) -> None:
        if payload is None:
            self._put(REPLY_ERR, i, b"", 0)
        elif len(payload) > self._max_reply[i]:
            self._put(OVERSIZE, i, _U32.pack(min(len(payload), 0xFFFF_FFFF)), _U32.size)
        else:
            self._put(REPLY, i, payload, len(payload))

    def health(self, block: bytes | bytearray | memoryview) -> None:
        self._put(HEALTH, 0, block, len(block))

    def finish(
        self,
        grounds: Sequence[bytes | bytearray | memoryview],
        sync_overrun: bool,
        loop_overruns: int,
        inbox_dropped: int,
        refused: CnRefusals | None,
        saves: Sequence[SaveResult],
        telemetry: bytearray | memoryview | None,
    ) -> None:
        if not self._dropping:
            for save in saves:  # rare: a PRM_SAVE finished
                detail = save.detail.encode(errors="replace")[:_MAX_SAVE_DETAIL]
                body = _SAVED.pack(save.seq, save.ok) + detail
                self._put(PRM_SAVED, 0, body, len(body))
            for ground in grounds:
                if len(ground) > self._max_ground:
                    self._put(GROUND_OVERSIZE, 0, _U32.pack(min(len(ground), 0xFFFF_FFFF)), 4)
                else:
                    self._put(GROUND, 0, ground, len(ground))
            if telemetry is not None:
                self._put(TELEMETRY, 0, telemetry, len(telemetry))
            self._put(
                FINISH,
                0,
                _FINISH.pack(
                    bool(sync_overrun),
                    loop_overruns,
                    inbox_dropped,
                    *(refused.fields() if refused is not None else _NONE_REFUSED),
                ),
                _FINISH.size,
            )
        if self._open_loop:
            self._open_loop = False
            if self._dropping:  # begun, then the ring filled: the loop is lost
                self.dropped_loops += 1
                self._pending_drops += 1
            else:
                self.loops += 1

    def close(self) -> None:
        """Flush every chunk to the file and stop the writer (idempotent). A
        recorder never started (a standby that never took command) removes
        the files it made: there is no recording."""
        if self._closed:
            return
        self._closed = True
        if not self.started:
            self._full.put(-1)
            self._writer.join()
            self._file.close()
            for name in (RECORD_FILE, MISSION_FILE):
                (self.directory / name).unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                self.directory.rmdir()  # only if it is empty: nothing of anyone's is lost
            return
        if not self._dropping and self._off:
            self._used[self._cur] = self._off
            self._full.put(self._cur)
        self._full.put(-1)
        self._writer.join()
        try:
            if self._pending_drops:
                # The run ended inside a drop: say so at the end of the file.
                self._file.write(_ITEM.pack(DROPPED, 0, _U64.size) + _U64.pack(self._pending_drops))
            self._file.close()
        except OSError as exc:
            self.error = self.error or str(exc)


class LoopRecord(msgspec.Struct, frozen=True):
    """One recorded loop: the CN's inputs and the telemetry it produced."""

    loop: int
    t_ns: int
    final: bool
    replies: list[tuple[int, bytes | None]]
    grounds: list[bytes]
    sync_overrun: bool
    loop_overruns: int
    inbox_dropped: int
    refused: tuple[int, ...]
    """:meth:`zplatform.control.intake.CnRefusals.fields` of the loop."""
    telemetry: bytes | None
    saves: list[SaveResult] = []
    health: bytes | None = None
    """The health block the loop copied in (None: not a health loop)."""
    standby: bool = False
    """A redundant mission's: whether the driver saw the standby ready
    (``cn_standby_ready``, an input of the loop)."""


class RecordReader:
    """Reads a recording directory with bounds, trusting nothing in it
    (module doc). Context manager; :meth:`close` closes the record file.

    ``mission``: the mission the operator vouches for (loaded from the file
    they passed, with its code); the recording must be of it (the recorded
    layout and :func:`mission_digest`), else RecordingError naming the first
    difference. None: the recorded ``mission.yaml``, loaded without its
    code (:attr:`recorded_mission`), for what needs no mission code (the
    recorded loops and telemetry). Either way :attr:`mission` is the one
    that bounds every item.

    Construction reads the header and the initial Data Vector
    (:attr:`initial`); :meth:`loops` then reads one loop at a time and
    stops at the first gap (the recorder dropped loops) or at a tail cut
    off mid-item, setting :attr:`complete` False. Raises RecordingError for
    a missing, unreadable, oversized or malformed recording; never
    anything else. Blocks on file I/O.
    """

    def __init__(self, directory: str | Path, mission: Mission | None = None) -> None:
        self.directory = Path(directory)
        self.mission_path = self.directory / MISSION_FILE
        self._path = self.directory / RECORD_FILE
        where = str(self.directory)
        try:
            dfd = os.open(self.directory, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        except OSError as exc:
            raise RecordingError(f"no recording at {where!r}: {exc.strerror}") from exc
        try:
            mission_text, _ = _read_regular(dfd, MISSION_FILE, where, MAX_MISSION_BYTES)
            fd, self._size = _open_regular(dfd, RECORD_FILE, where)
        finally:
            os.close(dfd)
        self._f: BinaryIO = os.fdopen(fd, "rb")
        try:
            self._read_header(mission_text, mission)
        except BaseException:
            self._f.close()
            raise
        self.complete = True
        self.dropped_loops = 0
        self._read_loops = False

    # -- the header --------------------------------------------------------
    def _fail(self, what: str) -> RecordingError:
        return RecordingError(f"{self._path}: {what}")

    def _read(self, n: int, what: str) -> bytes:
        """Exactly ``n`` bytes (``n`` already bounded) or RecordingError."""
        b = self._f.read(n)
        if len(b) != n:
            raise self._fail(f"truncated {what} ({len(b)} of {n} bytes)")
        return b

    def _read_header(self, mission_text: bytes, mission: Mission | None) -> None:
        magic, version, n = _HEAD.unpack(self._read(_HEAD.size, "header"))
        if magic != MAGIC:
            raise self._fail("not a zplatform recording")
        if version == 7:
            raise self._fail(
                f"recording version {version}, made by an earlier zplatform: its frames carry "
                f"that zplatform's authentication tag (24 bytes; this one reads version "
                f"{VERSION}, whose frames carry the 32-byte tag with a header tag, "
                "codecs/FORMAT.md §6.1): replay it with the zplatform that recorded it, or "
                "record again"
            )
        if version < VERSION:
            raise self._fail(
                f"recording version {version}, made by an earlier zplatform (this one reads "
                f"version {VERSION}: the header-tagged frames, the mission digest, the intake's "
                "refusals with the frames dropped unchecked and the mirrors refused, and the "
                "querier recoveries): record again"
            )
        if version != VERSION:
            raise self._fail(f"recording version {version}, expected {VERSION}")
        if n > MAX_META_BYTES:
            raise self._fail(f"metadata of {n} bytes (at most {MAX_META_BYTES})")
        try:
            self.meta = msgspec.json.decode(self._read(n, "metadata"), type=RecordMeta)
        except (msgspec.DecodeError, UnicodeDecodeError) as exc:
            raise self._fail(f"malformed metadata: {exc}") from None
        self.recorded_mission = _decode_recorded_mission(mission_text, self.mission_path)
        if mission_digest(self.recorded_mission) != self.meta.mission_digest:
            raise self._fail(
                f"the header is not of the {MISSION_FILE} beside it (their mission digests differ)"
            )
        if mission is not None:
            _check_same_mission(self.recorded_mission, mission, self.directory)
        self.mission = mission or self.recorded_mission
        layout = Layout.for_node(self.mission, "cn")
        if self.meta.layout_id != layout.layout_id or self.meta.size != layout.size:
            raise self._fail(
                f"the recorded Data Vector layout does not match {MISSION_FILE} (recorded "
                f"{self.meta.layout_id:#x}, {self.meta.size} B; mission {layout.layout_id:#x}, "
                f"{layout.size} B)"
            )
        (m,) = _U32.unpack(self._read(_U32.size, "header"))
        if m != layout.size:
            raise self._fail(f"initial Data Vector of {m} bytes, the layout's is {layout.size}")
        self.initial = self._read(m, "initial Data Vector")
        self.layout = layout
        self._reply_max, self._ground_max, self._tm_max = _frame_bounds(
            self.mission, DataVector(layout)
        )

    # -- the loops -----------------------------------------------------------
    def _bound(self, typ: int, dn: int, n: int, off: int) -> None:
        """RecordingError unless an item of type ``typ`` for DN ``dn`` may be
        ``n`` bytes long in this mission."""
        dns = len(self._reply_max)
        if typ in (REPLY, REPLY_ERR, OVERSIZE):
            if dn >= dns:
                raise self._fail(f"item at byte {off}: a reply of DN {dn}; the mission has {dns}")
            limit = {REPLY: self._reply_max[dn], REPLY_ERR: 0, OVERSIZE: _U32.size}[typ]
            exact = typ != REPLY
        elif typ in (GROUND, GROUND_OVERSIZE):
            if not self._ground_max:
                raise self._fail(f"item at byte {off}: a command frame; the mission has no gn")
            limit, exact = (self._ground_max, False) if typ == GROUND else (_U32.size, True)
        elif typ == TELEMETRY:
            limit, exact = self._tm_max, False
        elif typ == HEALTH:
            if self.mission.health is None:
                raise self._fail(f"item at byte {off}: a health block; the mission has no health")
            limit, exact = BLOCK_SIZE, True
        elif typ == PRM_SAVED:
            if n < _SAVED.size:
                raise self._fail(
                    f"item at byte {off}: PRM_SAVED of {n} bytes (at least {_SAVED.size})"
                )
            limit, exact = _SAVED.size + _MAX_SAVE_DETAIL, False
        elif typ in _EXACT:
            limit, exact = _EXACT[typ], True
        else:
            raise self._fail(f"item at byte {off}: unknown type {typ}")
        if n > limit or (exact and n != limit):
            raise self._fail(
                f"item at byte {off}: {_NAMES[typ]} of {n} bytes "
                f"({'exactly' if exact else 'at most'} {limit} in this mission)"
            )

    def loops(self) -> Iterator[LoopRecord]:
        """The recorded loops in order (once: the file is read as it goes).
        RecordingError for a malformed item or loop; stops, with
        :attr:`complete` False, at a gap or a tail cut off mid-item."""
        if self._read_loops:
            raise RecordingError(f"{self._path}: its loops were read already")
        self._read_loops = True
        f = self._f
        off = f.tell()
        in_loop = False
        loop = t = 0
        final = standby = False
        grounds: list[bytes] = []
        telemetry: bytes | None = None
        health: bytes | None = None
        replies: list[tuple[int, bytes | None]] = []
        saves: list[SaveResult] = []
        n_replies = 0
        max_replies = _MAX_REPLIES_PER_DN * len(self._reply_max)
        while True:
            head = f.read(_ITEM.size)
            if len(head) < _ITEM.size:  # the end, or a tail cut off mid-item
                self.complete = self.complete and not head and not in_loop
                return
            typ, dn, n = _ITEM.unpack(head)
            self._bound(typ, dn, n, off)
            body = f.read(n)
            if len(body) < n:
                self.complete = False
                return
            off += _ITEM.size + n
            if typ == BEGIN:
                if in_loop:
                    raise self._fail(f"item at byte {off - n - _ITEM.size}: loop {loop} never ends")
                loop, t, flags = _BEGIN.unpack(body)
                final, standby = bool(flags & 1), bool(flags & 2)
                in_loop = True
                telemetry = None
                health = None
                grounds = []
                replies = []
                saves = []
                n_replies = 0
                continue
            if typ == DROPPED:
                self.dropped_loops += _U64.unpack(body)[0]
                self.complete = False
                return
            if not in_loop:
                raise self._fail(
                    f"item at byte {off - n - _ITEM.size}: {_NAMES[typ]} outside a loop"
                )
            if typ == FINISH:
                so, lo, dr, *refused = _FINISH.unpack(body)
                if refused[_CMD_STATUS] not in _STATUSES:  # the loop names it: a known one
                    raise self._fail(
                        f"loop {loop}: FINISH with command status {refused[_CMD_STATUS]} "
                        f"(at most {max(_STATUSES)})"
                    )
                yield LoopRecord(
                    loop,
                    t,
                    final,
                    replies,
                    grounds,
                    bool(so),
                    lo,
                    dr,
                    tuple(refused),
                    telemetry,
                    saves,
                    health,
                    standby,
                )
                in_loop = False
            elif typ == TELEMETRY:
                if telemetry is not None:
                    raise self._fail(f"loop {loop}: two telemetry frames")
                telemetry = body
            elif typ in (GROUND, GROUND_OVERSIZE):
                if len(grounds) >= _MAX_GROUNDS_PER_LOOP:
                    raise self._fail(f"loop {loop}: over {_MAX_GROUNDS_PER_LOOP} command frames")
                grounds.append(body if typ == GROUND else b"")
            elif typ == PRM_SAVED:
                if len(saves) >= _MAX_GROUNDS_PER_LOOP:  # a save answers a command frame
                    raise self._fail(f"loop {loop}: over {_MAX_GROUNDS_PER_LOOP} parameter saves")
                seq, ok = _SAVED.unpack_from(body)
                detail = body[_SAVED.size :].decode(errors="replace")
                saves.append(SaveResult(seq, bool(ok), detail))
            elif typ == HEALTH:
                if health is not None:
                    raise self._fail(f"loop {loop}: two health blocks")
                health = body
            else:  # REPLY, REPLY_ERR, OVERSIZE
                n_replies += 1
                if n_replies > max_replies:
                    raise self._fail(f"loop {loop}: over {max_replies} DN replies")
                replies.append((dn, body if typ == REPLY else None if typ == REPLY_ERR else b""))

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> RecordReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_EXACT = {BEGIN: _BEGIN.size, FINISH: _FINISH.size, DROPPED: _U64.size}
_NAMES = {
    BEGIN: "BEGIN",
    REPLY: "REPLY",
    REPLY_ERR: "REPLY_ERR",
    OVERSIZE: "OVERSIZE",
    GROUND: "GROUND",
    GROUND_OVERSIZE: "GROUND_OVERSIZE",
    TELEMETRY: "TELEMETRY",
    FINISH: "FINISH",
    DROPPED: "DROPPED",
    PRM_SAVED: "PRM_SAVED",
    HEALTH: "HEALTH",
}


def _open_regular(dfd: int, name: str, where: str) -> tuple[int, int]:
    """Open ``name`` inside the directory ``dfd`` for reading: a regular
    file of the directory itself, never a symlink, FIFO or device (opened
    non-blocking, so a FIFO cannot hang the open). Returns (fd, size)."""
    try:
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=dfd)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise RecordingError(
                f"{where}/{name} is a symbolic link; a recording holds its files itself"
            ) from None
        raise RecordingError(f"no recording at {where!r}: {name}: {exc.strerror}") from exc
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise RecordingError(f"{where}/{name} is not a regular file")
    os.set_blocking(fd, True)
    return fd, st.st_size


def _read_regular(dfd: int, name: str, where: str, limit: int) -> tuple[bytes, int]:
    """The whole of regular file ``name`` (:func:`_open_regular`), at most
    ``limit`` bytes: its size is checked before anything is read."""
    fd, size = _open_regular(dfd, name, where)
    with os.fdopen(fd, "rb") as f:
        if size > limit:
            raise RecordingError(f"{where}/{name} is {size} bytes; at most {limit} are read")
        data = f.read(limit + 1)
    if len(data) > limit:  # it grew while we read
        raise RecordingError(f"{where}/{name} is over {limit} bytes")
    return data, size


def _decode_recorded_mission(text: bytes, path: Path) -> Mission:
    """The recorded mission, loaded without importing any of its code;
    RecordingError if it does not load or uses YAML aliases (a recorder
    never writes them, and an alias bomb would expand beyond any bound)."""
    from ..mission.load import decode_mission

    try:
        for event in yaml.parse(text, Loader=_YAML_LOADER):
            if isinstance(event, yaml.AliasEvent):
                raise RecordingError(f"{path}: YAML aliases; a recorded mission has none")
        return decode_mission(text, source=str(path), code=False)
    except ConfigError as exc:
        raise RecordingError(f"{path} does not load: {exc}") from exc
    except yaml.YAMLError as exc:
        raise RecordingError(f"{path} is not valid YAML: {exc}") from exc


def _short(value: Any, limit: int = 120) -> str:
    """``repr(value)``, cut to ``limit`` characters (a recorded value is anyone's)."""
    text = value if value is _ABSENT else repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _check_same_mission(recorded: Mission, mission: Mission, directory: Path) -> None:
    """RecordingError unless ``mission`` (the operator's) is the recorded
    one: the same Data Vector layout and loop content, else the first
    difference by its YAML path."""
    a, b = Layout.for_node(recorded, "cn"), Layout.for_node(mission, "cn")
    if mission_digest(recorded) == mission_digest(mission) and a.layout_id == b.layout_id:
        return
    diff = _first_mission_difference(_loop_content(recorded), _loop_content(mission))
    what = (
        f"first at `{diff[0]}`: recorded {_short(diff[1])}, the mission file {_short(diff[2])}"
        if diff is not None
        else f"Data Vector layout {a.layout_id:#x} recorded, {b.layout_id:#x} in the mission file"
    )
    raise RecordingError(
        f"{directory} is a recording of another mission than the one given ({what}); a replay "
        "runs only the mission that was recorded"
    )


class RecordingSummary(msgspec.Struct, frozen=True):
    """What a recording holds (:func:`read_recording`): its mission's name,
    the loops (``first_loop``..``last_loop``), the telemetry frames among
    them, whether it is complete (``dropped_loops`` otherwise), and the
    state of its last telemetry frame (``""`` without one)."""

    mission: str
    loops: int
    first_loop: int
    last_loop: int
    telemetry_frames: int
    complete: bool
    dropped_loops: int
    final_state: str


def read_recording(
    directory: str | Path, *, log: CsvLogger | None = None, listing: TextIO | None = None
) -> RecordingSummary:
    """Read a recording without its mission's code (none is imported: the
    recorded ``mission.yaml`` gives the layout only) and summarise it.

    ``log``: write each recorded telemetry frame, decoded, as a CSV row at
    its loop's time (the frames are the recording's word: their tags are not
    checked, a replay does that). ``listing``: one line per loop (number,
    time, DN replies, command frames, telemetry, flags). Raises
    RecordingError for a malformed recording or telemetry that does not
    decode in its layout.
    """
    with RecordReader(directory) as reader:
        mission = reader.mission
        dv = DataVector(reader.layout)
        dv.write_all(reader.initial)
        codec = RegionCodec(dv)
        tag = TAG_LEN if mission.security.auth else 0
        names = mission.device_nodes
        loops = frames = first = last = 0
        for rec in reader.loops():
            loops += 1
            first = first or rec.loop
            last = rec.loop
            if rec.telemetry is not None:
                frames += 1
                try:
                    codec.apply(rec.telemetry[: len(rec.telemetry) - tag])
                except CodecError as exc:
                    raise RecordingError(
                        f"{reader.directory}: loop {rec.loop}'s recorded telemetry does not "
                        f"decode: {exc}"
                    ) from None
                if log is not None:
                    log.write(rec.t_ns, dv)
            if listing is not None:
                replies = " ".join(
                    f"{names[i]}={'err' if p is None else len(p)}" for i, p in rec.replies
                )
                flags = [
                    f
                    for f, on in (
                        ("final", rec.final),
                        ("overrun", rec.sync_overrun),
                        ("health", rec.health is not None),
                    )
                    if on
                ]
                print(
                    f"loop {rec.loop:>8}  t {rec.t_ns}  replies [{replies}]  "
                    f"commands {len(rec.grounds)}  telemetry "
                    f"{'-' if rec.telemetry is None else len(rec.telemetry)}"
                    + (f"  {' '.join(flags)}" if flags else ""),
                    file=listing,
                )
        if log is not None:
            log.flush()
        return RecordingSummary(
            mission=mission.mission,
            loops=loops,
            first_loop=first,
            last_loop=last,
            telemetry_frames=frames,
            complete=reader.complete,
            dropped_loops=reader.dropped_loops,
            final_state=dv.get_name("cn_state") if frames else "",
        )
