"""The ground archive on disk: where each file goes, how rows become Parquet.

A mission's archive (``DIR/<mission>/``) holds, per run (CN epoch ``R``):
``raw/run-R/seg-N.zfr`` (the flight recorder's checksummed records: a
``HEAD``, then one ``FRAME`` per snapshot, the CN vector's bytes, and one
``EVENT`` per event, its JSON; once closed, compressed into
``seg-N.zfr.zsb``: :func:`seal_segment`; zplatform before it wrote
``seg-N.zfr.zst``, a zstd stream, still read), ``tm/run-R/hYYYYMMDDHH/part-N.parquet``
(decoded snapshots, a row group each, ``part-A-B.parquet`` parts A to B
compacted: :func:`compact`; one column per element; an array is one fixed-size-list
column, so a query of another element never reads it; a layout of more than
:data:`GROUP_COLUMNS` elements in file groups, ``part-N.gK.parquet`` beside
it: :func:`column_groups`), ``ev/run-R/part-N.parquet``
(events) and ``runs/run-R.json`` (:class:`RunInfo`). A Parquet file is
written as ``*.tmp`` and renamed when closed: a reader never sees half a file.

Contract: pure file layout and decoding; :func:`recover` and :func:`retain`
do I/O, never raise for damaged contents (they report it through ``note``).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import struct
import tempfile
import time
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, BinaryIO

import msgspec
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from ..core.datavector import Layout
from ..errors import ArchiveError
from ..recorder.format import EVENT, FORMAT_VERSION, FRAME, HEAD, HEADER, SYNC, record_crc
from ..recorder.reader import scan_segment
from ..telemetry.records import EventRecord

__all__ = [
    "GROUP_COLUMNS",
    "RUN_VERSION",
    "GroupDecoder",
    "MergeCount",
    "RunInfo",
    "column_groups",
    "compact",
    "covered_parts",
    "decode_rows",
    "event_table",
    "file_schema",
    "group_path",
    "group_schema",
    "merge",
    "parquet_options",
    "raw_record",
    "raw_segments",
    "read_run",
    "recount",
    "recover",
    "refill",
    "retain",
    "run_dirs",
    "seal_segment",
    "segment_index",
    "unseal",
    "write_run",
    "write_tm",
]

_RUN_RE = re.compile(r"run-([0-9]{1,20})")
_PART_RE = re.compile(r"part-([0-9]{6,})(?:-([0-9]{6,}))?\.parquet")
META_KEY = b"zplatform.layout"
_EVENT_DECODER = msgspec.json.Decoder(EventRecord)
_EVENT_ENCODER = msgspec.json.Encoder()
_U64 = struct.Struct("<Q")


RUN_VERSION = 1
"""The run record's format (:attr:`RunInfo.version`). A record without a
``version`` is of version 0 (zplatform before versions: without
``group_columns`` or with it), read with the defaults for what it lacks.
Every field added to :class:`RunInfo` bumps it: a zplatform refuses a
record of a version above its own (:func:`read_run`) instead of misreading
it, and never overwrites one."""


class _Version(msgspec.Struct):
    """A run record's ``version`` alone (whatever else it holds)."""

    version: int = 0


_VERSION_DECODER = msgspec.json.Decoder(_Version)


class RunInfo(msgspec.Struct, forbid_unknown_fields=True):
    """One run (CN epoch) as the archive knows it: ``runs/run-R.json``.

    ``start_ns``/``end_ns``: the first and last snapshot's ``cn_time_ns``;
    ``states``: every state reached, in the order first reached;
    ``outcome``: ``open`` while a writer holds it, ``ended`` when closed,
    ``interrupted`` when recovered after a crash; ``commands``: the text of
    every command event (requests, verdicts)."""

    run: int
    mission: str
    vehicle: str
    layout_id: int
    start_ns: int = 0
    end_ns: int = 0
    first_loop: int = -1
    last_loop: int = -1
    loops: int = 0
    states: list[str] = msgspec.field(default_factory=list)
    final_state: str = ""
    outcome: str = "open"
    events: int = 0
    commands: list[str] = msgspec.field(default_factory=list)
    in_order: bool = True
    """Every row was written after every lower loop (the files, in order,
    hold the loops in order): a query need not sort."""
    group_columns: int = 0
    """Elements per file group (:func:`column_groups`): 0, every element in
    ``part-N.parquet``; else the elements past the first ``group_columns``
    in ``part-N.gK.parquet`` beside it, ``group_columns`` each."""
    version: int = RUN_VERSION
    """The record's format (:data:`RUN_VERSION`); a record read from an
    older one is written back as this one's."""


def run_dirs(root: Path, kind: str, run: int) -> Path:
    """``root/kind/run-R``: the directory of run ``run``'s ``kind`` files."""
    return root / kind / f"run-{run}"


def read_run(root: Path, run: int) -> RunInfo | None:
    """Run ``run``'s record, or None when missing or unreadable. A record
    of an older format (:data:`RUN_VERSION`) is read with the defaults for
    the fields it lacks; one of a newer format raises ArchiveError (naming
    the file): the caller must neither misread nor overwrite it."""
    path = root / "runs" / f"run-{run}.json"
    try:
        data = path.read_bytes()
        version = _VERSION_DECODER.decode(data).version
    except (OSError, msgspec.ValidationError, msgspec.DecodeError):
        return None
    if version > RUN_VERSION:
        raise ArchiveError(
            f"{path}: written by a newer zplatform (run record version {version}; this one "
            f"reads up to {RUN_VERSION}): upgrade zplatform to read run {run}"
        )
    try:
        info = msgspec.json.decode(data, type=RunInfo)
    except (msgspec.ValidationError, msgspec.DecodeError):
        return None
    info.version = RUN_VERSION  # what it lacked has its default: this format's meaning
    return info


def write_run(root: Path, info: RunInfo) -> None:
    """Write run ``info.run``'s record atomically (a temporary file renamed)."""
    d = root / "runs"
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f"run-{info.run}.json.tmp"
    try:
        tmp.write_bytes(msgspec.json.encode(info))
    except BaseException:  # a full disk: no temporary file left behind
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    os.replace(tmp, d / f"run-{info.run}.json")


def runs_on_disk(root: Path) -> list[int]:
    """Every run with a record, a raw segment or a Parquet file, sorted."""
    found: set[int] = set()
    for kind in ("raw", "tm", "ev"):
        with contextlib.suppress(OSError):
            for name in os.listdir(root / kind):
                m = _RUN_RE.fullmatch(name)
                if m:
                    found.add(int(m.group(1)))
    with contextlib.suppress(OSError):
        for name in os.listdir(root / "runs"):
            m = re.fullmatch(r"run-([0-9]{1,20})\.json", name)
            if m:
                found.add(int(m.group(1)))
    return sorted(found)


def _parts_in(d: Path) -> list[Path]:
    """The telemetry or event files of directory ``d`` in order: each
    ``part-N.parquet`` and each compacted ``part-A-B.parquet`` (the rows of
    parts A to B, :func:`compact`), a part it covers left out (removed a
    little later: a reader that listed it first still finds it)."""
    found = [(m, n) for n in _listdir(d) if (m := _PART_RE.fullmatch(n))]
    ranges = [(int(m.group(1)), int(m.group(2))) for m, _ in found if m.group(2)]
    keep = [
        (int(m.group(1)), n)
        for m, n in found
        if m.group(2) or not any(lo <= int(m.group(1)) <= hi for lo, hi in ranges)
    ]
    return [d / n for _, n in sorted(keep)]


def parquet_files(root: Path, kind: str, run: int) -> list[Path]:
    """Run ``run``'s closed Parquet files of ``kind`` (``tm``/``ev``), in order."""
    base = run_dirs(root, kind, run)
    if kind != "tm":
        return _parts_in(base)
    out: list[Path] = []
    with contextlib.suppress(OSError):
        for hour in sorted(os.listdir(base)):
            out.extend(_parts_in(base / hour))
    return out


def covered_parts(d: Path) -> list[Path]:
    """The parts of directory ``d`` a compacted file covers (to remove)."""
    found = [(m, n) for n in _listdir(d) if (m := _PART_RE.fullmatch(n))]
    ranges = [(int(m.group(1)), int(m.group(2))) for m, _ in found if m.group(2)]
    return [
        d / n
        for m, n in found
        if not m.group(2) and any(lo <= int(m.group(1)) <= hi for lo, hi in ranges)
    ]


def _listdir(d: Path) -> list[str]:
    try:
        return os.listdir(d)
    except OSError:
        return []


def compact(d: Path, first: int, last: int) -> Path:
    """Parts ``first`` to ``last`` of directory ``d`` (one file group each,
    closed) as one file ``part-first-last.parquet``, their row groups kept;
    written as ``*.tmp`` and renamed. The parts stay (the caller removes
    them later: :func:`covered_parts`); readers skip them once it is there.
    Raises OSError or ArrowException (the temporary file removed)."""
    out = d / f"part-{first:06d}-{last:06d}.parquet"
    tmp = out.with_name(out.name + ".tmp")
    files = [d / f"part-{n:06d}.parquet" for n in range(first, last + 1)]
    try:
        schema = pq.read_schema(files[0])
        with pq.ParquetWriter(tmp, schema, **parquet_options(schema)) as w:
            for f in files:
                pf = pq.ParquetFile(f)
                for i in range(pf.num_row_groups):
                    t = pf.read_row_group(i).replace_schema_metadata(schema.metadata)
                    w.write_table(t, row_group_size=max(1, t.num_rows))
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    os.replace(tmp, out)
    return out


def next_part(directory: Path) -> int:
    """The next free part number in ``directory`` (temporary files count)."""
    top = -1
    with contextlib.suppress(OSError):
        for n in os.listdir(directory):
            m = re.fullmatch(r"part-([0-9]{6,})(?:-([0-9]{6,}))?(\.g[0-9]+)?\.parquet(\.tmp)?", n)
            if m:
                top = max(top, int(m.group(2) or m.group(1)))
    return top + 1


def hour_dir(t_ns: int) -> str:
    """``hYYYYMMDDHH`` (UTC) of vehicle time ``t_ns``: the time partition."""
    return "h" + time.strftime("%Y%m%d%H", time.gmtime(t_ns // 1_000_000_000))


def _arrow_type(layout: Layout, name: str) -> pa.DataType:
    e = layout.element(name)
    t = pa.from_numpy_dtype(np.dtype(e.scalar.numpy))
    return pa.list_(t, e.count) if e.count else t


GROUP_COLUMNS = 1024
"""Elements per file group in a run the writer starts: a layout of more
elements (a wide scalar region) is stored as files of at most this many
element columns each (:func:`column_groups`), so a query of one element
parses one group's footer and reads its column, never the others'."""


WIDE_COMPRESSION = "lz4"
"""The compression of the files of a run of several file groups (a wide
layout; Parquet's ``LZ4_RAW``), zstd for the rest. Each column chunk is
compressed on its own, and zstd costs about 10 us a chunk whatever its size
(a context made per chunk): a 100,000-element row group has 100,000 chunks.
Measured on 1,024 f32 columns of 1,340 rows (byte-stream-split): lz4 17 ms
of CPU a file, zstd 34; the values slowly drifting, 0.84 of their size
against zstd's 0.83 (random, 1.03 both)."""


def column_groups(layout: Layout, group_columns: int) -> list[list[str]]:
    """The layout's elements per file group, in layout order: one group of
    them all when ``group_columns`` is 0 or they fit, else groups of
    ``group_columns``. Group 0 (``part-N.parquet``) also holds ``loop``,
    ``t_ns`` and ``rx_ns``; group K (``part-N.gK.parquet``) only its
    elements, its rows those of the group-0 file beside it, in order."""
    names = list(layout.elements)
    if group_columns <= 0 or len(names) <= group_columns:
        return [names]
    return [names[i : i + group_columns] for i in range(0, len(names), group_columns)]


def group_path(part: Path, k: int) -> Path:
    """Group ``k``'s file beside the group-0 file ``part`` (``part-N.parquet``)."""
    return part if k == 0 else part.with_name(part.name[: -len(".parquet")] + f".g{k}.parquet")


def group_schema(layout: Layout, groups: list[list[str]], k: int) -> pa.Schema:
    """Group ``k``'s file schema: its columns, and the layout of its
    elements only in the metadata (a 100,000-element layout's description
    in every file's footer would outweigh its data)."""
    head = [pa.field("loop", pa.uint64()), pa.field("t_ns", pa.int64())]
    head.append(pa.field("rx_ns", pa.int64()))
    names = groups[k]
    meta = {
        "layout_id": layout.layout_id,
        "group": k,
        "elements": {
            e.name: {"type": e.type_text, "enum": list(e.enum) if e.enum else None}
            for e in (layout.element(n) for n in names)
        },
    }
    fields = (head if k == 0 else []) + [pa.field(n, _arrow_type(layout, n)) for n in names]
    return pa.schema(fields, metadata={META_KEY: json.dumps(meta).encode()})


def write_tm(path: Path, table: pa.Table, layout: Layout, group_columns: int) -> None:
    """``table`` (of :func:`file_schema`) as the telemetry file ``path``
    (``part-N.parquet``) and its group files: those first, group 0 last,
    each written as ``*.tmp`` and renamed, so a reader that sees a group-0
    file sees its groups (:func:`recover` removes a group file left alone)."""
    groups = column_groups(layout, group_columns)
    for k in range(len(groups) - 1, -1, -1):
        schema = group_schema(layout, groups, k)
        part = table.select(schema.names).replace_schema_metadata(schema.metadata)
        _write_parquet(group_path(path, k), part)


def _orphan_groups(root: Path, run: int) -> None:
    """Remove group files whose group-0 file is not there (a crash between renames)."""
    base = run_dirs(root, "tm", run)
    with contextlib.suppress(OSError):
        for hour in os.listdir(base):
            d = base / hour
            for n in os.listdir(d):
                m = _GROUP_RE.fullmatch(n)
                if m and not (d / f"part-{m.group(1)}.parquet").exists():
                    with contextlib.suppress(OSError):
                        (d / n).unlink()


_GROUP_RE = re.compile(r"part-([0-9]{6,})\.g[0-9]+\.parquet")


def file_schema(layout: Layout) -> pa.Schema:
    """The telemetry files' schema: ``loop``, ``t_ns`` (``cn_time_ns``),
    ``rx_ns`` (the ground's receive time) and one column per element; the
    layout (types, enum names) in the schema's metadata, for any reader."""
    fields = [pa.field("loop", pa.uint64()), pa.field("t_ns", pa.int64())]
    fields.append(pa.field("rx_ns", pa.int64()))
    meta = {
        "layout_id": layout.layout_id,
        "elements": {
            e.name: {"type": e.type_text, "enum": list(e.enum) if e.enum else None}
            for e in layout.elements.values()
        },
    }
    fields.extend(pa.field(n, _arrow_type(layout, n)) for n in layout.elements)
    return pa.schema(fields, metadata={META_KEY: json.dumps(meta).encode()})


def parquet_options(schema: pa.Schema) -> dict[str, Any]:
    """How every archive file is written: zstd; statistics only for the
    columns queries filter on (``loop``, the times, an event's severity), so
    a wide vector's footer (read by every query) stays small. Encodings by
    type: 64-bit integers (loops, times, counters: each row's a step from
    the last) delta-packed, floats byte-stream-split, the rest (enums,
    flags, small integers, strings) dictionary-encoded. Measured on the
    bench's hour (bench/archive.py): the files half the size of zstd over
    dictionary alone; with the footers cached (:class:`.query.Archive`), a
    one-element query over the hour 67 -> 12 ms (p50, on a loaded two-core
    machine)."""
    stats = [n for n in ("loop", "t_ns", "rx_ns", "severity") if n in schema.names]
    wide = (pa.int64(), pa.uint64())  # made once: a type made per field costs 10 us
    encoding: dict[str, str] = {}
    other = []
    for f in schema:
        if f.type in wide:
            encoding[f.name] = "DELTA_BINARY_PACKED"
        elif pa.types.is_floating(f.type):
            encoding[f.name] = "BYTE_STREAM_SPLIT"
        else:
            other.append(f.name)
    return {
        "compression": "zstd",
        "write_statistics": stats,
        "use_dictionary": other,
        "column_encoding": encoding,
    }


def decode_rows(layout: Layout, schema: pa.Schema, rows: np.ndarray, rx: np.ndarray) -> pa.Table:
    """Snapshots ``rows`` (an ``(n, layout.size)`` uint8 array of CN vectors)
    received at ``rx`` into a table of :func:`file_schema`. Copies."""
    rec = rows.view(layout.dtype).reshape(-1)
    cols: list[pa.Array] = [
        pa.array(np.ascontiguousarray(rec["cn_loop"]), pa.uint64()),
        pa.array(np.ascontiguousarray(rec["cn_time_ns"]), pa.int64()),
        pa.array(np.ascontiguousarray(rx), pa.int64()),
    ]
    for e in layout.elements.values():
        v = np.ascontiguousarray(rec[e.name])
        if e.count:
            flat = pa.array(v.reshape(-1))
            cols.append(pa.FixedSizeListArray.from_arrays(flat, e.count))
        else:
            cols.append(pa.array(v))
    return pa.Table.from_arrays(cols, schema=schema)


class GroupDecoder:
    """Decodes blocks of snapshots into one file group's table (group ``k``
    of ``groups``: :func:`column_groups`), for the writer's hot flush.

    Each run of consecutive elements of one type is transposed at once (one
    copy of its bytes, rows x elements into elements x rows), and each
    element's column is a zero-copy view of its row of that: per element
    one Arrow array, never a strided gather. The schema and the Parquet
    options are made once (:attr:`schema`, :attr:`options`). Immutable:
    safe to use from several threads at once."""

    def __init__(self, layout: Layout, groups: list[list[str]], k: int) -> None:
        self.schema = group_schema(layout, groups, k)
        self.options = parquet_options(self.schema)
        if len(groups) > 1:
            self.options["compression"] = WIDE_COMPRESSION
        self.head = k == 0
        self._loop = layout.element("cn_loop")
        self._time = layout.element("cn_time_ns")
        # (start byte, elements, bytes each, numpy type, array length)
        runs: list[list[Any]] = []
        for name in groups[k]:
            e = layout.element(name)
            dt = np.dtype(e.scalar.numpy)
            last = runs[-1] if runs else None
            if (
                last is not None
                and last[3] == dt
                and last[4] == e.count
                and last[0] + last[1] * last[2] == e.offset
            ):
                last[1] += 1
            else:
                runs.append([e.offset, 1, e.size, dt, e.count])
        # ... and an element's bytes as one opaque item (table: moved whole)
        self._runs = [(*r, np.dtype(f"V{r[2]}")) for r in runs]

    @staticmethod
    def _column(rows: np.ndarray, offset: int, dtype: np.dtype[Any]) -> np.ndarray:
        """One scalar element of every row (a copy: contiguous)."""
        return np.ascontiguousarray(rows[:, offset : offset + dtype.itemsize]).view(dtype)[:, 0]

    def table(self, rows: np.ndarray, rx: np.ndarray) -> pa.Table:
        """Snapshots ``rows`` (an ``(n, layout.size)`` uint8 array of CN
        vectors) received at ``rx`` as this group's table. Copies each
        element's bytes once; does not keep ``rows``."""
        cols: list[pa.Array] = []
        if self.head:
            lp, tt = self._loop, self._time
            lt, tt_ = np.dtype(lp.scalar.numpy), np.dtype(tt.scalar.numpy)
            cols.append(pa.array(self._column(rows, lp.offset, lt), pa.uint64()))
            cols.append(pa.array(self._column(rows, tt.offset, tt_), pa.int64()))
            cols.append(pa.array(np.ascontiguousarray(rx), pa.int64()))
        for start, count, size, dt, length, void in self._runs:
            # elements x rows: each element's bytes contiguous (the one copy),
            # each element's bytes one opaque item: moved whole, 9 times
            # faster than as `size` separate bytes (1 against 9 ms for 1,340
            # rows of 1,024 f32)
            flat = np.ascontiguousarray(rows[:, start : start + count * size].view(void).T)
            values = flat.view(dt)
            for j in range(count):
                v = pa.array(values[j])
                cols.append(pa.FixedSizeListArray.from_arrays(v, length) if length else v)
        return pa.Table.from_arrays(cols, schema=self.schema)


EVENT_SCHEMA = pa.schema(
    [
        ("rx_ns", pa.int64()),
        ("t_ns", pa.int64()),
        ("node", pa.string()),
        ("seq", pa.int64()),
        ("severity", pa.string()),
        ("id", pa.string()),
        ("text", pa.string()),
        ("verified", pa.bool_()),
        ("filled", pa.bool_()),
    ]
)
"""An archived event; ``filled``: it came from the control node's flight
recorder, filling a gap, not live (:class:`~zplatform.telemetry.records.EventRecord`)."""


def events_in_schema(t: pa.Table) -> pa.Table:
    """``t`` (events read back) in :data:`EVENT_SCHEMA`: ``filled`` False
    where files written before the column have none."""
    if "filled" not in t.column_names:
        t = t.append_column("filled", pa.nulls(t.num_rows, pa.bool_()))
    filled = pc.fill_null(t.column("filled"), False)
    t = t.set_column(t.column_names.index("filled"), "filled", filled)
    return t.select(EVENT_SCHEMA.names).cast(EVENT_SCHEMA)


def event_table(events: Iterable[EventRecord]) -> pa.Table:
    """Events as a table of :data:`EVENT_SCHEMA`."""
    evs = list(events)
    return pa.Table.from_pydict(
        {
            "rx_ns": [e.rx_time_ns for e in evs],
            "t_ns": [e.t_ns for e in evs],
            "node": [e.node for e in evs],
            "seq": [e.seq for e in evs],
            "severity": [e.severity for e in evs],
            "id": [e.id for e in evs],
            "text": [e.text for e in evs],
            "verified": [e.verified for e in evs],
            "filled": [e.filled for e in evs],
        },
        schema=EVENT_SCHEMA,
    )


def raw_record(typ: int, loop: int, payload: bytes | bytearray | memoryview) -> bytes:
    """One checksummed record of the flight recorder's format."""
    rec = bytearray(HEADER.size + len(payload))
    rec[HEADER.size :] = payload
    HEADER.pack_into(rec, 0, SYNC, 0, len(payload), typ, 0, 0, loop)
    HEADER.pack_into(rec, 0, SYNC, record_crc(rec, 0, len(rec)), len(payload), typ, 0, 0, loop)
    return bytes(rec)


def head_record(mission: str, vehicle: str, run: int, layout: Layout, segment: int) -> bytes:
    """The ``HEAD`` record of a raw segment (what the recorder's reader parses)."""
    body = {
        "format": FORMAT_VERSION,
        "mission": mission,
        "vehicle": vehicle,
        "node": "gn",
        "run": run,
        "kind": "archive",
        "layout_id": layout.layout_id,
        "channel": None,
        "period_ns": 0,
        "telemetry_divisor": 1,
        "created_unix_ns": time.time_ns(),
        "segment": segment,
    }
    return raw_record(HEAD, 0, json.dumps(body).encode())


def loops_in(files: Iterable[Path], note: Callable[[str], None]) -> set[int]:
    """Every loop the telemetry ``files`` hold (only their ``loop`` column is read)."""
    seen: set[int] = set()
    for f in files:
        try:
            seen.update(pq.read_table(f, columns=["loop"]).column(0).to_pylist())
        except (OSError, pa.ArrowException) as exc:
            note(f"{f.name}: unreadable Parquet file skipped ({exc})")
    return seen


def _events_in(files: Iterable[Path], note: Callable[[str], None]) -> set[tuple[str, int, int]]:
    """Every event (node, seq, t_ns) the event ``files`` hold."""
    seen: set[tuple[str, int, int]] = set()
    for f in files:
        try:
            t = pq.read_table(f, columns=["node", "seq", "t_ns"])
        except (OSError, pa.ArrowException) as exc:
            note(f"{f.name}: unreadable Parquet file skipped ({exc})")
            continue
        seen.update(zip(*(t.column(i).to_pylist() for i in range(3)), strict=True))
    return seen


def recover(
    root: Path, layout: Layout, mission: str, vehicle: str, note: Callable[[str], None]
) -> list[int]:
    """After a crash: remove half-written ``*.tmp`` files and re-decode every
    loop and event the raw segments hold that no Parquet file does, into new
    files; runs left ``open`` become ``interrupted``. Returns the runs
    touched. A damaged record or segment is skipped (``note`` says where)."""
    touched: list[int] = []
    for kind in ("tm", "ev", "raw"):
        for tmp in (root / kind).glob("run-*/**/*.tmp"):
            with contextlib.suppress(OSError):
                tmp.unlink()
    schema: pa.Schema | None = None  # made for a run to refill only (1 s at 100,000 elements)
    for run in runs_on_disk(root):
        try:
            info = read_run(root, run)
        except ArchiveError as exc:
            note(str(exc))  # a newer zplatform's run: not ours to rewrite, left as it is
            continue
        if info is not None and info.outcome != "open":
            continue
        if info is None:
            info = RunInfo(run, mission, vehicle, layout.layout_id)
            info.group_columns = GROUP_COLUMNS
        for hour in _listdir(run_dirs(root, "tm", run)):
            for f in covered_parts(run_dirs(root, "tm", run) / hour):
                with contextlib.suppress(OSError):
                    f.unlink()  # a compaction's parts, its file whole
        if schema is None:
            schema = file_schema(layout)
        refill(root, layout, info, note, schema)
        # The record's counts as the files hold them (a writer that failed
        # before the crash may have counted rows it had not written).
        recount(root, layout, info, note)
        info.outcome = "interrupted"
        write_run(root, info)
        touched.append(run)
    return touched


def refill(
    root: Path,
    layout: Layout,
    info: RunInfo,
    note: Callable[[str], None],
    schema: pa.Schema | None = None,
) -> None:
    """Re-decode into new Parquet files every loop and event run
    ``info.run``'s raw segments hold that no closed Parquet file does (a
    crash, or a write that failed: :meth:`.writer.ArchiveWriter` after a
    full disk), and fold them into ``info`` (not written). Removes group
    files left without their group-0 file first. A damaged record or
    segment is skipped (``note`` says where). Raises OSError or
    ArrowException when a file cannot be written."""
    run = info.run
    if schema is None:
        schema = file_schema(layout)
    _orphan_groups(root, run)
    seen = loops_in(parquet_files(root, "tm", run), note)
    known = _events_in(parquet_files(root, "ev", run), note)
    rows: list[bytes] = []
    rx: list[int] = []
    events: list[EventRecord] = []
    for seg in raw_segments(run_dirs(root, "raw", run)):
        for r in _scan(seg, note):
            if r.type == FRAME and len(r.payload) == 8 + layout.size:
                if r.loop not in seen:  # the record's loop is the vector's cn_loop
                    seen.add(r.loop)
                    rx.append(_U64.unpack_from(r.payload, 0)[0])
                    rows.append(r.payload[8:])
            elif r.type == EVENT:
                with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
                    e = _EVENT_DECODER.decode(r.payload)
                    if (e.node, e.seq, e.t_ns) not in known:
                        known.add((e.node, e.seq, e.t_ns))
                        events.append(e)
    if rows:
        info.in_order = False  # recovered rows go after rows of later loops, maybe
        arr = np.frombuffer(b"".join(rows), np.uint8).reshape(len(rows), layout.size)
        table = decode_rows(layout, schema, arr, np.array(rx, np.int64))
        t0 = int(table.column("t_ns")[0].as_py())
        d = run_dirs(root, "tm", run) / hour_dir(t0)
        d.mkdir(parents=True, exist_ok=True)
        write_tm(d / f"part-{next_part(d):06d}.parquet", table, layout, info.group_columns)
        _account(info, layout, arr)
    if events:
        d = run_dirs(root, "ev", run)
        d.mkdir(parents=True, exist_ok=True)
        _write_parquet(d / f"part-{next_part(d):06d}.parquet", event_table(events))
        info.events += len(events)


def recount(root: Path, layout: Layout, info: RunInfo, note: Callable[[str], None]) -> None:
    """Set ``info``'s loops, first and last loop and times, states reached,
    final state, events and commands from what run ``info.run``'s closed
    Parquet files hold (only the ``loop``, ``t_ns`` and ``cn_state``
    columns, and the events' ``severity``, ``id``, ``node``, ``text``): for
    a writer whose counts in memory went past the files (a write that
    failed), after :func:`refill`. An unreadable file is skipped (``note``)."""
    groups = column_groups(layout, info.group_columns)
    k = next(i for i, g in enumerate(groups) if "cn_state" in g)
    loops: list[np.ndarray] = []
    times: list[np.ndarray] = []
    states: list[np.ndarray] = []
    for part in parquet_files(root, "tm", info.run):
        try:
            head = pq.read_table(part, columns=["loop", "t_ns"])
            st = pq.read_table(group_path(part, k), columns=["cn_state"])
        except (OSError, pa.ArrowException) as exc:
            note(f"{part.name}: unreadable Parquet file skipped ({exc})")
            continue
        loops.append(head.column(0).to_numpy())
        times.append(head.column(1).to_numpy())
        states.append(st.column(0).to_numpy())
    spec = layout.element("cn_state")
    info.loops, info.states, info.final_state = 0, [], ""
    info.first_loop = info.last_loop = -1
    info.start_ns = info.end_ns = 0
    if loops:
        lp, tt, ss = np.concatenate(loops), np.concatenate(times), np.concatenate(states)
        order = np.argsort(lp, kind="stable")
        lp, tt, ss = lp[order], tt[order], ss[order]
        info.loops = len(lp)
        info.first_loop, info.last_loop = int(lp[0]), int(lp[-1])
        info.start_ns, info.end_ns = int(tt[0]), int(tt[-1])
        info.final_state = spec.name_of(int(ss[-1]))
        _, first = np.unique(ss, return_index=True)
        info.states = [spec.name_of(int(ss[i])) for i in sorted(first.tolist())]
    info.events, info.commands = 0, []
    for f in parquet_files(root, "ev", info.run):
        try:
            t = pq.read_table(f, columns=["node", "severity", "id", "text"]).to_pylist()
        except (OSError, pa.ArrowException) as exc:
            note(f"{f.name}: unreadable Parquet file skipped ({exc})")
            continue
        info.events += len(t)
        for e in t:
            if (e["severity"] == "COMMAND" or e["id"].startswith("cmd_")) and len(
                info.commands
            ) < 1000:
                info.commands.append(f"{e['node']}: {e['text']}")


_SEG_RE = re.compile(r"seg-([0-9]{8})\.zfr(\.zst|\.zsb)?")
ZSB_SYNC = b"\x89ZSB"
ZSB_HEADER = struct.Struct("<4sIIIII")  # sync, crc, stored, plain, width, reserved
ZSB_RECORDS = 4096
"""Records of one length a sealed block holds, at most (41 s of the flight
mission's snapshots: shorter than the bench's 60 s replay, so the bench's
sizes owe nothing to it)."""
ZSB_BYTES = 8 * 2**20
"""Bytes of segment a sealed block holds, at most."""
ZSB_LEVEL = 3
ZSB_TRANSPOSE_BYTES = 64 * 1024
"""Records longer than this are sealed one per block, as they are (not
transposed): a block holds few of them (8 MiB: 20 of a 100,000-element
vector), too few for the transposition to find runs, and it costs. Measured
on 20 snapshots of 100,000 f32 (a two-core machine): transposed, 0.2 ms of
CPU per snapshot when the values are random (no gain: incompressible),
2.4 ms when they drift slowly (zstd takes 2.2 of it), for 0.87 of their
size; as they are, 0.07 and 0.5 ms, for 0.93."""


def segment_index(path: Path) -> int | None:
    """The index of raw segment ``path`` (``seg-N.zfr``, or sealed ``.zfr.zsb``/``.zfr.zst``)."""
    m = _SEG_RE.fullmatch(path.name)
    return int(m.group(1)) if m else None


def raw_segments(directory: Path) -> list[Path]:
    """A run's raw segments in order, sealed or open (a sealed one first when
    a crash left both: the same records, each loop then taken once)."""
    try:
        names = [p for p in directory.iterdir() if _SEG_RE.fullmatch(p.name)]
    except OSError:
        return []
    return sorted(names, key=lambda p: (segment_index(p), p.name.endswith(".zfr")))


def _blocks(data: bytes | memoryview) -> Iterable[tuple[int, int, int]]:
    """``data`` (a segment) cut into sealed blocks: ``(start, end, width)``,
    ``width`` the length of each of the block's records (a run of records of
    one length: the frames), or 0 for bytes that are not whole records (a
    torn tail), kept as they are."""
    n = len(data)
    start, width, count, off = 0, 0, 0, 0
    while off < n:
        length, whole = n - off, False  # not a record: the rest, as it is
        if off + HEADER.size <= n and data[off : off + 4] == SYNC:
            rec = HEADER.size + struct.unpack_from("<I", data, off + 8)[0]
            if off + rec <= n:
                length, whole = rec, True
        if (
            whole
            and length == width
            and length <= ZSB_TRANSPOSE_BYTES
            and count < ZSB_RECORDS
            and off + length - start <= ZSB_BYTES
        ):
            count += 1
        else:
            if off > start:
                yield start, off, width
            start, count, width = off, 1, length if whole else 0
        off += length
    if off > start:
        yield start, off, width


def seal_segment(path: Path) -> None:
    """Compress a closed raw segment into ``seg-N.zfr.zsb``, then remove it:
    blocks (codecs/FORMAT.md §12) of at most :data:`ZSB_RECORDS` records of
    one length, each stored as its bytes transposed (byte 0 of every record,
    then byte 1...: a snapshot's slowly changing values side by side; a
    record longer than :data:`ZSB_TRANSPOSE_BYTES` alone, as it is) and
    zstd-compressed, checksummed; decoding gives the segment back byte for
    byte (:func:`unseal`). Written as a temporary file renamed, so a crash
    leaves one whole file or both. On an error (a full disk) the temporary
    file is removed, the segment left as it is (readable unsealed), and the
    error raised."""
    tmp = path.with_name(path.name + ".zsb.tmp")
    codec = pa.Codec("zstd", compression_level=ZSB_LEVEL)
    try:
        data = path.read_bytes()
        with open(tmp, "wb") as dst:
            for start, end, width in _blocks(data):
                chunk: bytes | memoryview = memoryview(data)[start:end]
                if width > 1 and end - start > width:
                    rows = np.frombuffer(data, np.uint8, end - start, start).reshape(-1, width)
                    chunk = np.ascontiguousarray(rows.T).data
                stored = codec.compress(chunk, asbytes=True)
                head = bytearray(ZSB_HEADER.pack(ZSB_SYNC, 0, len(stored), end - start, width, 0))
                crc = zlib.crc32(stored, zlib.crc32(memoryview(head)[8:]))
                struct.pack_into("<I", head, 4, crc)
                dst.write(head)
                dst.write(stored)
            dst.flush()
            os.fsync(dst.fileno())
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    os.replace(tmp, path.with_name(path.name + ".zsb"))
    path.unlink()


def unseal(seg: Path, out: BinaryIO, note: Callable[[str], None]) -> None:
    """Write sealed segment ``seg`` (``.zfr.zsb``) back as the segment it was
    into ``out``. A block that does not check is skipped (``note`` says where:
    the records around it stay readable); a torn or damaged block header
    ends it there."""
    data = seg.read_bytes()
    off, n = 0, len(data)
    codec = pa.Codec("zstd")
    while off < n:
        if off + ZSB_HEADER.size > n or data[off : off + 4] != ZSB_SYNC:
            note(f"{seg.name}: not a sealed block at byte {off}: the rest skipped")
            return
        _, crc, stored, plain, width, _ = ZSB_HEADER.unpack_from(data, off)
        end = off + ZSB_HEADER.size + stored
        if end > n:
            note(f"{seg.name}: a torn block at byte {off}: the rest skipped")
            return
        body = memoryview(data)[off + ZSB_HEADER.size : end]
        if zlib.crc32(body, zlib.crc32(memoryview(data)[off + 8 : off + ZSB_HEADER.size])) != crc:
            note(f"{seg.name}: a damaged block at byte {off} skipped")
            off = end
            continue
        try:
            raw = codec.decompress(body, decompressed_size=plain, asbytes=True)
        except (pa.ArrowException, ValueError) as exc:
            note(f"{seg.name}: a block at byte {off} does not decompress ({exc}): skipped")
            off = end
            continue
        if width > 1 and plain > width and plain % width == 0:
            rows = np.frombuffer(raw, np.uint8).reshape(width, plain // width)
            raw = np.ascontiguousarray(rows.T).tobytes()
        out.write(raw)
        off = end


def _scan(seg: Path, note: Callable[[str], None]) -> Iterable[Any]:
    """The records of raw segment ``seg`` that check (a sealed one unpacked
    to a temporary file first)."""
    if seg.name.endswith(".zfr"):
        yield from scan_segment(seg, note)
        return
    with tempfile.TemporaryDirectory() as d:
        plain = Path(d) / seg.name[: -len(".zst")]
        try:
            if seg.name.endswith(".zsb"):
                with open(plain, "wb") as dst:
                    unseal(seg, dst, note)
            else:
                with pa.CompressedInputStream(str(seg), "zstd") as src, open(plain, "wb") as dst:
                    while chunk := src.read(1 << 20):
                        dst.write(chunk)
        except (OSError, pa.ArrowException) as exc:
            note(f"{seg.name}: cannot unpack it ({exc}); what it held up to there is read")
        yield from scan_segment(plain, note)


def _write_parquet(path: Path, table: pa.Table) -> None:
    """``table`` as ``path``, written as ``*.tmp`` and renamed; on an error
    (a full disk) the temporary file removed, the error raised."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        pq.write_table(table, tmp, **parquet_options(table.schema))
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    os.replace(tmp, path)


def _account(info: RunInfo, layout: Layout, rows: np.ndarray) -> None:
    """Fold snapshots ``rows`` into ``info`` (loops, times, states reached)."""
    rec = rows.view(layout.dtype).reshape(-1)
    loops, times, states = rec["cn_loop"], rec["cn_time_ns"], rec["cn_state"]
    n = len(rec)
    if not n:
        return
    lo, hi = int(loops.min()), int(loops.max())
    if info.loops == 0 or lo < info.first_loop:
        info.first_loop = lo
        info.start_ns = int(times[int(loops.argmin())])
    if info.loops == 0 or hi > info.last_loop:
        info.last_loop = hi
        info.end_ns = int(times[int(loops.argmax())])
        info.final_state = layout.element("cn_state").name_of(int(states[int(loops.argmax())]))
    info.loops += n
    spec = layout.element("cn_state")
    _, first = np.unique(states, return_index=True)
    for i in sorted(first.tolist()):
        name = spec.name_of(int(states[i]))
        if name not in info.states:
            info.states.append(name)


def du(path: Path) -> int:
    """Bytes of every file under ``path``."""
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, f)).st_size
    return total


def _written_ns(root: Path, run: int) -> int:
    """When run ``run``'s files (its record, its directories) last changed, ns."""
    paths = [root / "runs" / f"run-{run}.json"]
    paths += [run_dirs(root, k, run) for k in ("raw", "tm", "ev")]
    t = 0
    for p in paths:
        with contextlib.suppress(OSError):
            t = max(t, p.stat().st_mtime_ns)
    return t


def remove_run(root: Path, run: int) -> None:
    """Remove every file of run ``run``."""
    for kind in ("raw", "tm", "ev"):
        shutil.rmtree(run_dirs(root, kind, run), ignore_errors=True)
    with contextlib.suppress(OSError):
        (root / "runs" / f"run-{run}.json").unlink()


def retain(
    root: Path,
    *,
    max_bytes: int,
    max_age_days: float | None,
    keep: int | None,
    now_ns: int,
    removed: Callable[[int, int, str], None],
) -> None:
    """Remove whole runs, oldest first: those that ended more than
    ``max_age_days`` before ``now_ns`` (vehicle time), then as many as it takes
    for the archive to hold at most ``max_bytes``. Never run ``keep`` (the one
    being written), nor the newest run (the last one ended: a ground node
    started again after a run larger than ``max_bytes`` keeps it).
    ``removed(run, bytes, why)`` is told each."""
    on_disk = runs_on_disk(root)
    runs = [r for r in on_disk[:-1] if r != keep]
    sizes = {r: sum(du(run_dirs(root, k, r)) for k in ("raw", "tm", "ev")) for r in runs}
    ends = {}
    for r in runs:
        try:
            info = read_run(root, r)
        except ArchiveError:
            info = None  # a newer zplatform's run: its end unknown here
        # A run without a readable end (no record, a newer one's, no row):
        # aged by when its files were last written, not as if it ended in 1970.
        ends[r] = info.end_ns if info is not None and info.end_ns else _written_ns(root, r)
    runs.sort(key=lambda r: ends[r])
    total = du(root)
    left = []
    for r in runs:
        if max_age_days is not None and now_ns - ends[r] > max_age_days * 86_400e9:
            remove_run(root, r)
            total -= sizes[r]
            removed(r, sizes[r], f"older than {max_age_days:g} day(s)")
        else:
            left.append(r)
    for r in left:
        if total <= max_bytes:
            break
        remove_run(root, r)
        total -= sizes[r]
        removed(r, sizes[r], f"the archive holds more than {max_bytes} bytes")


def events_of(records: Iterable[Any]) -> list[EventRecord]:
    """Decode raw ``EVENT`` records' payloads (the undecodable skipped)."""
    out = []
    for p in records:
        with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
            out.append(_EVENT_DECODER.decode(p))
    return out


def encode_event(rec: EventRecord) -> bytes:
    """An event's raw ``EVENT`` payload (its JSON, as the events JSONL writes it)."""
    return _EVENT_ENCODER.encode(rec)


class MergeCount(msgspec.Struct):
    """What :func:`merge` took of one run: rows (loops) and events new to
    the archive, and the ones it already held (skipped)."""

    run: int
    rows: int = 0
    events: int = 0
    duplicate_rows: int = 0
    duplicate_events: int = 0


def merge(
    root: Path,
    src: Path,
    layout: Layout,
    mission: str,
    vehicle: str,
    note: Callable[[str], None],
    *,
    runs: Iterable[int] | None = None,
) -> list[MergeCount]:
    """Take into the archive ``root`` what another station's archive ``src``
    holds of the same runs (or new ones): each run is one run, each loop
    once (by run and loop), each event once (by node, seq and stamp). Read
    from ``src``'s raw segments (the source of truth); what is new is written
    as a raw segment of its own (sealed), then as Parquet files per hour,
    then the run's record (a crash between leaves at most a raw segment
    whose loops a later merge writes again: taken once, by loop). A run of
    another layout is skipped (``note`` says so), as is a damaged record.
    The caller holds ``root``'s lock (no writer writes it). Returns per run
    what was taken."""
    out: list[MergeCount] = []
    schema = file_schema(layout)
    want = set(runs) if runs is not None else None
    for run in runs_on_disk(src):
        if want is not None and run not in want:
            continue
        try:
            theirs = read_run(src, run)
            read_run(root, run)  # ours: refused alike when a newer zplatform wrote it
        except ArchiveError as exc:
            note(f"{exc}: run {run} skipped")
            continue
        if theirs is not None and theirs.layout_id != layout.layout_id:
            note(
                f"run {run} of {src}: layout {theirs.layout_id:#x}, not this mission's "
                f"{layout.layout_id:#x}: skipped"
            )
            continue
        count = MergeCount(run)
        seen = loops_in(parquet_files(root, "tm", run), note)
        had_rows = bool(seen)
        known = _events_in(parquet_files(root, "ev", run), note)
        frames: dict[int, bytes] = {}
        events: list[EventRecord] = []
        records: list[bytes] = []
        for seg in raw_segments(run_dirs(src, "raw", run)):
            for r in _scan(seg, note):
                if r.type == FRAME and len(r.payload) == 8 + layout.size:
                    if r.loop in seen or r.loop in frames:
                        count.duplicate_rows += 1
                    else:
                        frames[r.loop] = bytes(r.payload)
                elif r.type == EVENT:
                    try:
                        e = _EVENT_DECODER.decode(r.payload)
                    except (msgspec.DecodeError, msgspec.ValidationError):
                        continue
                    if (e.node, e.seq, e.t_ns) in known:
                        count.duplicate_events += 1
                    else:
                        known.add((e.node, e.seq, e.t_ns))
                        events.append(e)
                        records.append(raw_record(EVENT, 0, r.payload))
        if not frames and not events:
            out.append(count)
            continue
        loops = sorted(frames)
        records[:0] = [raw_record(FRAME, n, frames[n]) for n in loops]
        raw = run_dirs(root, "raw", run)
        raw.mkdir(parents=True, exist_ok=True)
        used = [segment_index(p) for p in raw.iterdir()]
        index = max((i for i in used if i is not None), default=-1) + 1
        seg_path = raw / f"seg-{index:08d}.zfr"
        with open(seg_path, "wb") as f:
            f.write(head_record(mission, vehicle, run, layout, index))
            for rec in records:
                f.write(rec)
            f.flush()
            os.fsync(f.fileno())
        seal_segment(seg_path)
        info = read_run(root, run)
        if info is None:
            info = RunInfo(run, mission, vehicle, layout.layout_id)
            info.group_columns = GROUP_COLUMNS
            if theirs is not None:
                info.outcome = "interrupted" if theirs.outcome == "open" else theirs.outcome
            else:
                info.outcome = "interrupted"
        if loops:
            arr = np.frombuffer(b"".join(frames[n][8:] for n in loops), np.uint8)
            arr = arr.reshape(len(loops), layout.size)
            rx = np.array([_U64.unpack_from(frames[n], 0)[0] for n in loops], np.int64)
            table = decode_rows(layout, schema, arr, rx)
            t = table.column("t_ns").to_numpy()
            hours = [hour_dir(int(x)) for x in t]
            start = 0
            for i in range(1, len(hours) + 1):
                if i == len(hours) or hours[i] != hours[start]:
                    d = run_dirs(root, "tm", run) / hours[start]
                    d.mkdir(parents=True, exist_ok=True)
                    part = d / f"part-{next_part(d):06d}.parquet"
                    write_tm(part, table.slice(start, i - start), layout, info.group_columns)
                    start = i
            if had_rows:
                info.in_order = False  # merged rows go between the loops already there
            _account(info, layout, arr)
            count.rows = len(loops)
        if events:
            d = run_dirs(root, "ev", run)
            d.mkdir(parents=True, exist_ok=True)
            _write_parquet(d / f"part-{next_part(d):06d}.parquet", event_table(events))
            info.events += len(events)
            for e in events:
                if (e.severity == "COMMAND" or e.id.startswith("cmd_")) and len(
                    info.commands
                ) < 1000:
                    info.commands.append(f"{e.node}: {e.text}")
            count.events = len(events)
        write_run(root, info)
        out.append(count)
    return out
