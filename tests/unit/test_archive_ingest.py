"""The archive's ingest at scale (issue 28): the writer's transposed row
groups decode exactly as the reference decoder does, a writer that falls
behind drops (counted, told) and never blocks the receive path, a running
run's query sees every row group written, and sealed raw segments are
smaller than zstd alone and give the segment back byte for byte."""

from __future__ import annotations

import io
import threading
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from tests.unit.test_archive import PERIOD, T0, feed, small
from zplatform import LockstepRunner
from zplatform.archive import Archive, ArchiveWriter, Query, store
from zplatform.control.uplink import load_commands
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EventLog
from zplatform.mission.load import load_mission
from zplatform.recorder.format import FRAME

ROOT = Path(__file__).resolve().parents[2]
MISSION = load_mission(ROOT / "configs" / "flight.yaml", code=False)
LAYOUT = Layout.for_node(MISSION, "cn")


def _random_rows(n: int, seed: int = 3) -> np.ndarray:
    """``n`` CN vectors of random values (floats finite, bools 0/1)."""
    rng = np.random.default_rng(seed)
    rows = np.frombuffer(rng.bytes(n * LAYOUT.size), np.uint8).reshape(n, LAYOUT.size).copy()
    rec = rows.view(LAYOUT.dtype).reshape(-1)
    for e in LAYOUT.elements.values():
        kind = np.dtype(e.scalar.numpy).kind
        if kind == "f":
            rec[e.name] = np.nan_to_num(rec[e.name])
        elif kind == "b":
            rec[e.name] = rng.random(rec[e.name].shape) < 0.5
    return rows


@pytest.mark.parametrize("group_columns", [0, 64, 7])
def test_the_transposed_groups_equal_the_reference_decoding(group_columns: int) -> None:
    rows = _random_rows(37)
    rx = np.arange(37, dtype=np.int64) * 11
    ref = store.decode_rows(LAYOUT, store.file_schema(LAYOUT), rows, rx)
    groups = store.column_groups(LAYOUT, group_columns)
    seen: list[str] = []
    for k in range(len(groups)):
        t = store.GroupDecoder(LAYOUT, groups, k).table(rows, rx)
        assert t.schema == store.group_schema(LAYOUT, groups, k)
        for name in t.column_names:
            assert t.column(name).equals(ref.column(name)), name
        seen += t.column_names
    assert seen == ref.column_names  # every column once, in order


def test_a_writer_that_falls_behind_drops_counted_and_never_blocks(tmp_path: Path) -> None:
    m = small(MISSION, row_group_s=1.0, queue_s=2.0)  # row groups of 100, a ring of 200
    w = ArchiveWriter(m, LAYOUT, tmp_path)
    entered, release = threading.Event(), threading.Event()
    write = ArchiveWriter._write_group

    def stuck(self: ArchiveWriter, rows: np.ndarray, rx: np.ndarray) -> None:
        entered.set()
        assert release.wait(60)  # a disk that hangs: the thread is stuck here
        write(self, rows, rx)

    w._write_group = stuck.__get__(w)  # type: ignore[method-assign]
    dv = DataVector(LAYOUT)
    offered = 0

    def offer(loops: range) -> None:
        nonlocal offered
        for i in loops:
            dv.set("cn_loop", i)
            dv.set("cn_epoch", 7)
            dv.set("cn_time_ns", T0 + i * PERIOD)
            w.snapshot(T0 + i * PERIOD, dv)  # returns at once, stuck thread or not
            offered += 1

    try:
        offer(range(1, 101))  # a row group's worth: its write hangs
        assert entered.wait(60)
        offer(range(101, 501))  # the ring fills behind the stuck thread
        assert w.dropped > 0
        events = EventLog("gn", 16)
        w.tick(T0, events)
        w.tick(T0 + 1, events)  # within the second: told once
        told = [e for e in events.drain() if e.id == "archive_dropping"]
        assert len(told) == 1 and f"{w.dropped} snapshot(s)" in told[0].text
    finally:
        release.set()
    assert w.flush()
    w.close()
    s = w.stats()
    # Every snapshot offered is archived or counted dropped: none silently lost.
    assert s["rows"] + s["dropped"] == offered == 500
    assert s["lost"] == 0 and s["errors"] == 0 and s["duplicates"] == 0
    with Archive(MISSION, tmp_path) as a:
        assert a.query(Query("cn_loop")).num_rows == s["rows"]


def test_a_running_runs_query_sees_every_row_group_written(tmp_path: Path) -> None:
    # Row groups of 100 loops, files of 600 s: 250 loops are two row groups
    # written and 50 loops in the block, the run open.
    w = ArchiveWriter(small(MISSION, row_group_s=1.0), LAYOUT, tmp_path)
    try:
        feed(w, DataVector(LAYOUT), range(1, 251))
        with Archive(MISSION, tmp_path) as a:
            (info,) = a.runs()
            assert (info.outcome, info.loops, info.last_loop) == ("open", 200, 200)
            t = a.query(Query("cn_state", run=7))
            assert t.column("loop").to_pylist() == list(range(1, 201))
            assert t.column("cn_state").to_pylist() == [i // 100 % 4 for i in range(1, 201)]
            assert a.problems == []
            feed(w, DataVector(LAYOUT), range(251, 301))  # the third row group
            assert a.query(Query("cn_loop", run=7)).num_rows == 300
    finally:
        w.close()
    with Archive(MISSION, tmp_path) as a:
        assert a.runs()[0].outcome == "ended"
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 301))


@pytest.fixture(scope="module")
def flight_segment(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A raw segment of 2,000 loops of a lockstep flight (ARM, LAUNCH, the
    flight), as the writer writes it, before sealing."""
    r = LockstepRunner(MISSION, commands=load_commands(ROOT / "configs" / "flight.commands"))
    d = tmp_path_factory.mktemp("seg")
    w = ArchiveWriter(MISSION, LAYOUT, d)
    for i in range(2000):
        r.step()
        w.snapshot(T0 + i * PERIOD, r.control.dv)
        if i % 500 == 0:
            assert w.flush()
    assert w.flush()
    assert w._seg is not None
    data = Path(w._seg.name).read_bytes()
    w.close()
    return data


def test_a_sealed_segment_gives_the_segment_back_byte_for_byte(
    flight_segment: bytes, tmp_path: Path
) -> None:
    seg = tmp_path / "seg-00000000.zfr"
    torn = flight_segment + flight_segment[:100]  # and a torn record at the end
    seg.write_bytes(torn)
    store.seal_segment(seg)
    sealed = tmp_path / "seg-00000000.zfr.zsb"
    assert not seg.exists() and sealed.exists()
    out = io.BytesIO()
    notes: list[str] = []
    store.unseal(sealed, out, notes.append)
    assert out.getvalue() == torn and notes == []
    # Smaller than the zstd stream zplatform sealed with before (0.17 of the
    # segment for this flight): its snapshots transposed, a field beside itself.
    assert sealed.stat().st_size < 0.11 * len(torn)
    stream = pa.BufferOutputStream()
    with pa.CompressedOutputStream(stream, "zstd") as z:
        z.write(torn)
    assert sealed.stat().st_size < 0.6 * len(stream.getvalue())


def test_a_damaged_or_torn_sealed_block_is_skipped_and_the_rest_read(
    flight_segment: bytes, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(store, "ZSB_RECORDS", 500)  # four blocks of frames
    seg = tmp_path / "seg-00000000.zfr"
    seg.write_bytes(flight_segment)
    store.seal_segment(seg)
    sealed = tmp_path / "seg-00000000.zfr.zsb"
    blocks = list(store._blocks(flight_segment))
    assert [w for _, _, w in blocks] == [blocks[0][2]] + [blocks[1][2]] * 4  # HEAD, frames
    whole = [r.loop for r in store._scan(sealed, lambda _t: None) if r.type == FRAME]
    assert whole == list(range(1, 2001))
    data = bytearray(sealed.read_bytes())
    data[-50] ^= 0xFF  # inside the last block
    sealed.write_bytes(bytes(data))
    notes: list[str] = []
    loops = [r.loop for r in store._scan(sealed, notes.append) if r.type == FRAME]
    assert loops == list(range(1, 1501))  # the last block's 500 lost, the rest read
    assert len(notes) == 1 and "damaged block" in notes[0]
    sealed.write_bytes(bytes(data[:-50]))  # torn inside the last block
    notes = []
    assert [r.loop for r in store._scan(sealed, notes.append) if r.type == FRAME] == loops
    assert len(notes) == 1 and "torn block" in notes[0]


def test_a_segment_sealed_as_a_zstd_stream_before_is_still_read(
    flight_segment: bytes, tmp_path: Path
) -> None:
    old = tmp_path / "seg-00000000.zfr.zst"
    with pa.CompressedOutputStream(str(old), "zstd") as z:
        z.write(flight_segment)
    assert store.raw_segments(tmp_path) == [old]
    loops = [r.loop for r in store._scan(old, lambda _t: None) if r.type == FRAME]
    assert loops == list(range(1, 2001))


def test_row_group_files_are_compacted_every_file_s_and_at_the_end(tmp_path: Path) -> None:
    # Row groups of 100 loops, retention and compaction every 300.
    w = ArchiveWriter(small(MISSION, row_group_s=1.0, file_s=3.0), LAYOUT, tmp_path)
    try:
        feed(w, DataVector(LAYOUT), range(1, 451))
        # 4 row groups written: parts 0-2 compacted at the third, part 3 alone
        (hour,) = (tmp_path / "tm" / "run-7").iterdir()
        assert [p.name for p in store.parquet_files(tmp_path, "tm", 7)] == [
            "part-000000-000002.parquet",
            "part-000003.parquet",
        ]
        with Archive(MISSION, tmp_path) as a:  # the parts compacted are skipped
            assert a.query(Query("cn_loop", run=7)).column("loop").to_pylist() == list(
                range(1, 401)
            )
    finally:
        w.close()
    # At the end: parts 3 and 4 (loops 401-450) compacted too, every part removed.
    assert sorted(p.name for p in hour.iterdir()) == [
        "part-000000-000002.parquet",
        "part-000003-000004.parquet",
    ]
    with Archive(MISSION, tmp_path) as a:
        t = a.query(Query("cn_state", run=7))
        assert t.column("loop").to_pylist() == list(range(1, 451))
        assert t.column("cn_state").to_pylist() == [i // 100 % 4 for i in range(1, 451)]
        assert a.runs()[0].loops == 450 and a.problems == []
    assert [
        pq.ParquetFile(p).metadata.num_row_groups for p in store.parquet_files(tmp_path, "tm", 7)
    ] == [3, 2]


def test_recovery_removes_the_parts_a_compacted_file_covers(tmp_path: Path) -> None:
    w = ArchiveWriter(small(MISSION, row_group_s=1.0), LAYOUT, tmp_path)
    feed(w, DataVector(LAYOUT), range(1, 301))
    w.close()
    (hour,) = (tmp_path / "tm" / "run-7").iterdir()
    (merged,) = hour.iterdir()
    assert merged.name == "part-000000-000002.parquet"
    # A crash after the compacted file's rename, before its parts' removal:
    # the parts again beside it, the run open.
    for i in range(3):
        t = pq.ParquetFile(merged).read_row_group(i)
        pq.write_table(t, hour / f"part-{i:06d}.parquet")
    info = store.read_run(tmp_path, 7)
    assert info is not None
    info.outcome = "open"
    store.write_run(tmp_path, info)
    with Archive(MISSION, tmp_path) as a:
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 301))
        assert a.runs()[0].outcome == "interrupted"
    assert [p.name for p in hour.iterdir()] == ["part-000000-000002.parquet"]


def test_a_row_group_that_failed_leaves_no_hole_for_compaction(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    w = ArchiveWriter(small(MISSION, row_group_s=1.0, file_s=3.0), LAYOUT, tmp_path)
    write = pq.write_table
    calls = 0

    def full_once(*args: object, **kwargs: object) -> None:
        nonlocal calls
        calls += 1
        if calls == 2:  # the second row group's file: a full disk
            raise OSError(28, "No space left on device")
        write(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(pq, "write_table", full_once)
    feed(w, DataVector(LAYOUT), range(1, 601))
    w.close()
    s = w.stats()
    # One write failed, counted once; no compaction tripped over its number.
    assert (s["errors"], s["lost"], s["rows"]) == (1, 0, 600)
    with Archive(MISSION, tmp_path) as a:  # its rows re-decoded from the raw segment
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 601))
        assert a.runs()[0].outcome == "ended" and a.problems == []
