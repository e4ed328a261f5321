"""What the ground archive holds for a mission, and how it writes a wide
vector cheaply (issue 28: the 100,000-element vector at 100 Hz): the row
group and the queue sized from the mission (a value set that needs more
than the archive holds is refused at load, naming its field), the file_s
check saying what the writer does, raw segments sealed on the encoder
threads (a wide record alone, as it is), a wide run's files LZ4."""

from __future__ import annotations

import errno
import io
import re
import threading
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from tests.unit.test_archive import feed, lose_parquet, small
from zplatform.archive import Archive, ArchiveWriter, Query, store
from zplatform.archive import writer as writer_mod
from zplatform.config import Mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EventLog
from zplatform.errors import ConfigError
from zplatform.mission.load import decode_mission, load_mission
from zplatform.recorder.format import FRAME, HEADER

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml", code=False)
BASE = (ROOT / "configs" / "minimal.yaml").read_text()
# The bench's 100,000 f32 as one array element: a 400 KB vector, quick to load.
WIDE = BASE.replace(
    "    - {name: heartbeat, type: u32, initial: 0}\n",
    "    - {name: heartbeat, type: u32, initial: 0}\n    - {name: wide, type: 'f32[100000]'}\n",
)


def _wide(archive: str = "") -> Mission:
    return decode_mission(WIDE + (f"\narchive: {archive}\n" if archive else ""), code=False)


def test_the_row_group_and_queue_are_sized_from_the_mission(tmp_path: Path) -> None:
    # The flight mission: 60 s and 10 s of its 757-byte vector at 100 Hz.
    layout = Layout.for_node(FLIGHT, "cn")
    w = ArchiveWriter(FLIGHT, layout, tmp_path / "flight")
    try:
        assert w.sizing == (6000, 1000, layout.size)
        assert w._block.nbytes == 6000 * layout.size
        assert len(w._ring) == 1000 * layout.size
    finally:
        w.close()
    # A wide vector, unset: the defaults cut to what the archive holds.
    m = _wide()
    size = Layout.for_node(m, "cn").size
    assert size > 400_000
    sizing = writer_mod.archive_sizing(m, size)
    assert sizing.row_group_rows == writer_mod.ROW_GROUP_BYTES // size  # 1,341: 13.41 s
    assert sizing.queue_rows == writer_mod.QUEUE_BYTES // size
    # Set: exactly what the mission says, and the writer holds just that.
    m = _wide("{row_group_s: 1, queue_s: 0.5, file_s: 10}")
    w = ArchiveWriter(m, Layout.for_node(m, "cn"), tmp_path / "wide")
    try:
        assert w.sizing == (100, 50, size)
        assert w._block.nbytes == 100 * size and len(w._ring) == 50 * size
    finally:
        w.close()


def test_a_row_group_or_queue_the_archive_cannot_hold_is_refused_naming_its_field() -> None:
    with pytest.raises(ConfigError) as err:
        _wide("{row_group_s: 60}")
    assert err.value.path == "$.archive.row_group_s"
    assert "6000 snapshots" in err.value.reason and "more than the 512 MiB" in err.value.reason
    size = Layout.for_node(_wide(), "cn").size
    rows = writer_mod.ROW_GROUP_BYTES // size  # 1,341
    assert f"at most {rows / 100:g} s ({rows} snapshots)" in err.value.reason
    with pytest.raises(ConfigError) as err:
        _wide("{queue_s: 10}")
    assert err.value.path == "$.archive.queue_s"
    rows = writer_mod.QUEUE_BYTES // size
    assert "more than the 256 MiB" in err.value.reason
    assert f"at most {rows / 100:g} s ({rows} snapshots)" in err.value.reason
    # What fits loads; an archive turned off holds nothing.
    assert _wide("{row_group_s: 13.4, queue_s: 6.7}").archive.row_group_s == 13.4
    assert not _wide("{enabled: false, row_group_s: 60, queue_s: 10}").archive.enabled


def test_file_s_shorter_than_a_row_group_is_refused_saying_what_the_writer_does() -> None:
    with pytest.raises(ConfigError) as err:
        decode_mission(BASE + "\narchive: {row_group_s: 60, file_s: 10}\n", code=False)
    assert err.value.path == "$.archive.row_group_s"
    assert "each row group (60 s) is written as closed files" in err.value.reason
    assert "compacted" in err.value.reason and "must fit in a file" not in err.value.reason
    # Unset, the row group is 60 s: the field to change is file_s.
    with pytest.raises(ConfigError) as err:
        decode_mission(BASE + "\narchive: {file_s: 30}\n", code=False)
    assert err.value.path == "$.archive.file_s"
    # A wide vector's row group is what fits (13.4 s): file_s 20 holds it.
    assert _wide("{file_s: 20}").archive.file_s == 20


def _blocks(sealed: bytes) -> list[tuple[int, int]]:
    """``(plain, width)`` of each block of a sealed segment."""
    out, off = [], 0
    while off < len(sealed):
        _, _, stored, plain, width, _ = store.ZSB_HEADER.unpack_from(sealed, off)
        out.append((plain, width))
        off += store.ZSB_HEADER.size + stored
    return out


def test_a_wide_record_is_sealed_alone_as_it_is_and_read_back_whole(tmp_path: Path) -> None:
    wide = [store.raw_record(FRAME, i, bytes([i]) * 70_000) for i in range(5)]
    narrow = [store.raw_record(FRAME, i, bytes([i]) * 700) for i in range(5, 10)]
    seg = tmp_path / "seg-00000000.zfr"
    data = b"".join(wide + narrow)
    seg.write_bytes(data)
    store.seal_segment(seg)
    sealed = tmp_path / "seg-00000000.zfr.zsb"
    w, n = len(wide[0]), len(narrow[0])
    assert w > 64 * 1024 >= n  # store.ZSB_TRANSPOSE_BYTES
    # Each wide record a block of its own; the narrow ones one block, transposed.
    assert _blocks(sealed.read_bytes()) == [(w, w)] * 5 + [(5 * n, n)]
    out = io.BytesIO()
    notes: list[str] = []
    store.unseal(sealed, out, notes.append)
    assert out.getvalue() == data and notes == []
    assert HEADER.size + 70_000 == w


def test_raw_segments_are_sealed_on_the_encoder_threads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(writer_mod, "SEGMENT_BYTES", 64 * 1024)  # a segment every ~85 loops
    sealed_by: list[str] = []
    seal = store.seal_segment

    def spy(path: Path) -> None:
        sealed_by.append(threading.current_thread().name)
        seal(path)

    monkeypatch.setattr(store, "seal_segment", spy)
    layout = Layout.for_node(FLIGHT, "cn")
    w = ArchiveWriter(FLIGHT, layout, tmp_path)
    feed(w, DataVector(layout), range(1, 601))
    w.close()
    raw = sorted(p.name for p in (tmp_path / "raw" / "run-7").iterdir())
    assert len(raw) == len(sealed_by) >= 6
    assert all(n.endswith(".zfr.zsb") for n in raw)  # every one sealed when the run ends
    assert all(n.startswith("archive-enc") for n in sealed_by)  # never the archive's thread
    with Archive(FLIGHT, tmp_path) as a:
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 601))


def test_a_seal_that_fails_is_told_once_and_its_segment_stays_readable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(writer_mod, "SEGMENT_BYTES", 64 * 1024)

    def full(path: Path) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store, "seal_segment", full)
    layout = Layout.for_node(FLIGHT, "cn")
    w = ArchiveWriter(FLIGHT, layout, tmp_path)
    feed(w, DataVector(layout), range(1, 601))
    events = EventLog("gn", 64)
    w.tick(0, events)
    w.close()
    w.tick(0, events)
    raw = sorted(p.name for p in (tmp_path / "raw" / "run-7").iterdir())
    assert len(raw) >= 6 and all(n.endswith(".zfr") for n in raw)  # left plain
    assert w.errors == len(raw) and w.stats()["lost"] == 0
    told = [e for e in events.drain() if e.id == "archive_failed"]
    assert len(told) == 1 and "compress a raw segment" in told[0].text
    # The Parquet files lost, the run re-decoded from the plain segments.
    lose_parquet(tmp_path, 7)
    with Archive(FLIGHT, tmp_path) as a:
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 601))


def test_a_wide_run_is_written_lz4_and_a_narrow_one_zstd(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = small(FLIGHT, row_group_s=1.0)
    layout = Layout.for_node(m, "cn")
    w = ArchiveWriter(m, layout, tmp_path / "narrow")
    feed(w, DataVector(layout), range(1, 201))
    w.close()
    monkeypatch.setattr(store, "GROUP_COLUMNS", 64)  # three file groups
    w = ArchiveWriter(m, layout, tmp_path / "wide")
    feed(w, DataVector(layout), range(1, 201))
    w.close()

    def codecs(root: Path) -> set[str]:
        out = set()
        for f in root.glob("tm/run-7/*/part-*.parquet"):
            md = pq.ParquetFile(f).metadata
            for g in range(md.num_row_groups):
                rg = md.row_group(g)
                out |= {rg.column(c).compression for c in range(rg.num_columns)}
        return out

    assert codecs(tmp_path / "narrow") == {"ZSTD"}
    assert codecs(tmp_path / "wide") == {"LZ4"}  # Parquet's LZ4_RAW
    with Archive(m, tmp_path / "wide") as a, Archive(m, tmp_path / "narrow") as b:
        q = Query("cn_loop,apogee_target_m,dn1_state")
        assert a.query(q).equals(b.query(q))


def _resident_kb(address: int) -> tuple[int, int]:
    """``(Size, Rss)`` in kB of this process's mapping that holds ``address``."""
    found = False
    size = 0
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()[0] if line.split() else ""
        if re.fullmatch(r"[0-9a-f]+-[0-9a-f]+", head):
            if found:
                break
            lo, hi = (int(x, 16) for x in head.split("-"))
            found = lo <= address < hi
        elif found and head == "Size:":
            size = int(line.split()[1])
        elif found and head == "Rss:":
            return size, int(line.split()[1])
    raise LookupError(hex(address))


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="Linux's /proc")
def test_the_ring_and_the_block_are_mapped_whole_at_start(tmp_path: Path) -> None:
    """Never a first-touch page fault on the receive path (the ring) nor in
    the archive's thread's copy (the block): both resident before any
    snapshot came."""
    layout = Layout.for_node(FLIGHT, "cn")
    w = ArchiveWriter(FLIGHT, layout, tmp_path)
    try:
        for arr in (w._block, w._ring2d):
            size_kb, rss_kb = _resident_kb(arr.__array_interface__["data"][0])
            assert size_kb * 1024 >= arr.nbytes
            assert rss_kb * 1024 >= arr.nbytes  # (a mapping may hold more than it)
    finally:
        w.close()
