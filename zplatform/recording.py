"""Recording a live CN's loop inputs, and reading them back for a replay.

``zplatform up --record DIR`` (and ``node MISSION cn --record DIR``) attaches
a :class:`Recorder` to the CN's :class:`~zplatform.loop.ControlLogic`: every
input its loop consumed is written, per loop, in call order: the loop number,
timestamp and whether it was the run's last (``final``), each DN reply as it
arrived (its bytes, or that the DN answered with an error), the ground
frame, the sync-overrun flag and the skipped periods, the parameter saves
that finished (:mod:`zplatform.params`), the node's health block on health
loops (:mod:`zplatform.health`), and the telemetry frame the loop
produced (what a replay must reproduce). ``DIR`` holds
``mission.yaml`` (the effective mission) and ``cn.zrec``; ``zplatform replay
DIR`` needs nothing else.

``cn.zrec``, all integers little-endian::

    header:  b"ZPREC\\0"  u16 version (5)  u32 n  n bytes of JSON metadata
             u32 m  m bytes: the CN's Data Vector when recording started
    items:   u8 type  u8 dn  u32 length  length bytes
               1 BEGIN      u64 loop, i64 t_ns, u8 final (1: the run's last loop)
               2 REPLY      the reply frame of DN ``dn``
               3 REPLY_ERR  DN ``dn`` answered with an error (length 0)
               4 OVERSIZE   a reply longer than any valid frame: u32 its length
               5 GROUND     a command request frame the loop took (any number)
               6 GROUND_OVERSIZE  u32 its length
               7 TELEMETRY  the telemetry frame the loop produced
               8 FINISH     u8 sync_overrun, u32 loop_overruns, u32 inbox_dropped,
                            then what the intake refused (zplatform.intake.CnRefusals,
                            in its field order): u32 reply_size, reply_bad,
                            reply_stale, reply_foreign, cmd_size, cmd_bad, cmd_stale,
                            u8 cmd_status, u64 cmd_seq (ends a loop)
               9 DROPPED    u64 loops the recorder could not keep (ring full)
              11 PRM_SAVED  a parameter save finished: u64 its PRM_SAVE number,
                            u8 ok, then its detail (UTF-8, at most 512 bytes)
              12 HEALTH     the CN's health block the loop copied in
                            (health loops of a mission with ``health:``)

Version 5: the intake's refusals in FINISH (counts: a flood is not
recorded frame by frame). Versions 2 to 4 had an ``inbox_oversize`` count
there and an item (10, FOREIGN) per reply from no DN, which this loop no
longer takes: such a recording is refused by name (replay it with the
zplatform that made it).

An oversize frame cannot decode (it is longer than the widest valid
encoding), so a replay feeds an empty payload in its place: the same bad
frame to the loop, without storing an attacker's megabytes.

Hot path: :class:`Recorder` copies each item into one of a set of
preallocated chunks (no buffer is allocated per loop, nothing blocks); a
writer thread writes full chunks to the file and returns them. If the
writer falls behind and no chunk is free, the loops that do not fit are
dropped and counted, never silently: the record says so (``DROPPED``) and a
replay stops there.
"""

from __future__ import annotations

import json
import queue
import struct
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

import msgspec
import yaml

from .auth import TAG_LEN
from .codec import RegionCodec
from .config import Mission, relocate_mission
from .datavector import DataVector, Layout
from .errors import RecordingError
from .health import BLOCK_SIZE, Heartbeat
from .intake import CnRefusals
from .params import SaveResult

__all__ = ["LoopRecord", "RecordReader", "Recorder"]

MAGIC = b"ZPREC\x00"
VERSION = 5  # 2: BEGIN's final flag; 3: PRM_SAVED; 4: HEALTH; 5: FINISH the refusals
_EARLIER = (2, 3, 4)  # FINISH without the intake's refusals, FOREIGN items: not replayable
RECORD_FILE = "cn.zrec"
MISSION_FILE = "mission.yaml"

BEGIN, REPLY, REPLY_ERR, OVERSIZE, GROUND, GROUND_OVERSIZE, TELEMETRY, FINISH, DROPPED = (
    range(1, 10)
)
PRM_SAVED, HEALTH = 11, 12  # 10 was FOREIGN (version 4 and before)

_ITEM = struct.Struct("<BBI")  # type, dn, length
_BEGIN = struct.Struct("<QqB")
_FINISH = struct.Struct("<BII" + "I" * 7 + "BQ")
_U32 = struct.Struct("<I")
_NONE_REFUSED = CnRefusals().fields()
_U64 = struct.Struct("<Q")
_SAVED = struct.Struct("<QB")
_HEAD = struct.Struct("<6sHI")


class Recorder:
    """Records a CN's loop inputs into ``directory`` (module doc).

    Construction creates the directory, copies ``mission_source`` (the
    mission file the CN loaded; its ``pythonpath`` made absolute, so the copy
    finds the mission's code from anywhere) into it, writes the header with ``dv``'s
    bytes as they are now (call it after the warm-up, before loop 1) and
    starts the writer thread; RecordingError if any of that fails. The
    ``begin``/``reply``/``finish`` methods implement
    :class:`~zplatform.loop.LoopRecorder`: they never block, allocate no
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
    ) -> None:
        self.directory = Path(directory)
        dns = mission.device_nodes
        # The longest loop record with one reply per DN and the telemetry;
        # a loop with late replies on top simply spans chunks.
        reply_max = [RegionCodec(dv, f"{dn}_to_cn").max_frame_len + TAG_LEN for dn in dns]
        # Frames as they came off the wire: with an authentication tag.
        ground_max = (
            RegionCodec(dv, "gn_to_cn").max_frame_len + TAG_LEN if mission.has_ground else 0
        )
        tm_max = RegionCodec(dv).max_frame_len + TAG_LEN
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
        self._max_reply = tuple(reply_max)
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
            (self.directory / MISSION_FILE).write_text(yaml.safe_dump(raw, sort_keys=False))
            self._file: BinaryIO = open(self.directory / RECORD_FILE, "wb")  # noqa: SIM115
            meta = json.dumps(
                {
                    "mission": mission.mission,
                    "layout_id": dv.layout.layout_id,
                    "size": dv.layout.size,
                    "period_ns": mission.period_ns,
                    "device_nodes": dns,
                    "telemetry_divisor": mission.telemetry_divisor,
                    "created_unix_s": time.time(),
                }
            ).encode()
            self._file.write(_HEAD.pack(MAGIC, VERSION, len(meta)) + meta)
            init = bytearray(dv.size)
            dv.read_all(init)
            self._file.write(_U32.pack(len(init)) + init)
        except (OSError, yaml.YAMLError) as exc:
            raise RecordingError(f"cannot record into {str(self.directory)!r}: {exc}") from exc
        self.heartbeat = Heartbeat("record")
        """The writer thread's check-in (zplatform.health), for the node's liveness."""
        self._writer = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._writer.start()

    # -- the writer thread -------------------------------------------------
    def _write_loop(self) -> None:
        # Idle while it waits for a chunk; a write that hangs (a stuck disk)
        # is a stall (zplatform.health).
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

    def begin(self, loop: int, t_ns: int, final: bool = False) -> None:
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
        _BEGIN.pack_into(self._mv, off + _ITEM.size, loop, t_ns, final)
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
        telemetry: bytearray | None,
    ) -> None:
        if not self._dropping:
            self._finish(
                grounds, sync_overrun, loop_overruns, inbox_dropped, refused, saves, telemetry
            )
        if self._open_loop:
            self._open_loop = False
            if self._dropping:  # begun, then the ring filled: the loop is lost
                self.dropped_loops += 1
                self._pending_drops += 1
            else:
                self.loops += 1

    def _finish(
        self,
        grounds: Sequence[bytes | bytearray | memoryview],
        sync_overrun: bool,
        loop_overruns: int,
        inbox_dropped: int,
        refused: CnRefusals | None,
        saves: Sequence[SaveResult],
        telemetry: bytearray | None,
    ) -> None:
        for save in saves:  # rare: a PRM_SAVE finished
            detail = save.detail.encode(errors="replace")[:512]
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

    def close(self) -> None:
        """Flush every chunk to the file and stop the writer (idempotent)."""
        if self._closed:
            return
        self._closed = True
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
    """:meth:`zplatform.intake.CnRefusals.fields` of the loop."""
    telemetry: bytes | None
    saves: list[SaveResult] = []
    health: bytes | None = None
    """The health block the loop copied in (None: not a health loop)."""


class RecordReader:
    """Reads a recording directory (module doc). RecordingError when it is
    missing or its header is malformed; :meth:`loops` stops at the first gap
    or damage and sets :attr:`complete` False."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.mission_path = self.directory / MISSION_FILE
        path = self.directory / RECORD_FILE
        try:
            self._data = path.read_bytes()
        except OSError as exc:
            raise RecordingError(
                f"no recording at {str(self.directory)!r}: {exc.strerror} ({path.name})"
            ) from exc
        if not self.mission_path.is_file():
            raise RecordingError(f"{str(self.directory)!r} has no {MISSION_FILE}")
        d = self._data
        try:
            magic, version, n = _HEAD.unpack_from(d, 0)
            if magic != MAGIC:
                raise RecordingError(f"{path} is not a zplatform recording")
            if version in _EARLIER:
                raise RecordingError(
                    f"{path}: recording version {version}, made by an earlier zplatform "
                    f"(before the intake's refusals in version {VERSION}): replay it with "
                    "the zplatform that recorded it"
                )
            if version != VERSION:
                raise RecordingError(f"{path}: recording version {version}, expected {VERSION}")
            off = _HEAD.size
            self.meta = json.loads(d[off : off + n])
            off += n
            (m,) = _U32.unpack_from(d, off)
            off += 4
            self.initial = d[off : off + m]
            if len(self.initial) != m:
                raise RecordingError(f"{path}: truncated header")
            self._start = off + m
        except (struct.error, ValueError) as exc:
            raise RecordingError(f"{path}: malformed header: {exc}") from exc
        self.complete = True
        self.dropped_loops = 0

    def check_layout(self, layout: Layout) -> None:
        """RecordingError unless the recorded CN vector has ``layout``."""
        if self.meta.get("layout_id") != layout.layout_id or len(self.initial) != layout.size:
            raise RecordingError(
                f"{self.directory}: the recorded Data Vector layout does not match "
                f"{MISSION_FILE} (recorded {self.meta.get('layout_id')}, mission "
                f"{layout.layout_id})"
            )

    def loops(self) -> Iterator[LoopRecord]:
        d = self._data
        off = self._start
        end = len(d)
        in_loop = False
        loop = t = 0
        final = False
        grounds: list[bytes] = []
        telemetry: bytes | None = None
        health: bytes | None = None
        replies: list[tuple[int, bytes | None]] = []
        saves: list[SaveResult] = []
        while off < end:
            if off + _ITEM.size > end:
                self.complete = False
                return
            typ, dn, n = _ITEM.unpack_from(d, off)
            off += _ITEM.size
            if off + n > end:
                self.complete = False
                return
            body = d[off : off + n]
            off += n
            if typ == BEGIN:
                loop, t, final_byte = _BEGIN.unpack(body)
                final = bool(final_byte)
                in_loop = True
                telemetry = None
                health = None
                grounds = []
                replies = []
                saves = []
            elif typ == DROPPED:
                self.dropped_loops += _U64.unpack(body)[0]
                self.complete = False
                return
            elif not in_loop:
                self.complete = False
                return
            elif typ == REPLY:
                replies.append((dn, body))
            elif typ == REPLY_ERR:
                replies.append((dn, None))
            elif typ == OVERSIZE:
                replies.append((dn, b""))
            elif typ == GROUND:
                grounds.append(body)
            elif typ == GROUND_OVERSIZE:
                grounds.append(b"")
            elif typ == TELEMETRY:
                telemetry = body
            elif typ == PRM_SAVED and n >= _SAVED.size:
                seq, ok = _SAVED.unpack_from(body)
                detail = body[_SAVED.size :].decode(errors="replace")
                saves.append(SaveResult(seq, bool(ok), detail))
            elif typ == HEALTH:
                health = body
            elif typ == FINISH:
                so, lo, dr, *refused = _FINISH.unpack(body)
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
                )
                in_loop = False
            else:
                self.complete = False
                return
        if in_loop:
            self.complete = False
