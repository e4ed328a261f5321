"""Retention as the mission configures it (``archive.max_bytes``,
``archive.max_age_days``), applied by the ground's writer: whole runs,
oldest first, never the run being written nor the newest, each removal
evented (``archive_removed``)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from tests.unit.test_archive import small
from zplatform.archive import Archive, ArchiveWriter, Query, store
from zplatform.config import Mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EventLog
from zplatform.mission.load import load_mission

ROOT = Path(__file__).resolve().parents[2]
MIB = 1024 * 1024
PERIOD = 10_000_000


@pytest.fixture(scope="module")
def flight() -> Mission:
    return load_mission(ROOT / "configs" / "flight.yaml", code=False)


def feed_random(
    w: ArchiveWriter, dv: DataVector, n: int, epoch: int, t0: int, seed: int = 0
) -> None:
    """``n`` snapshots of run ``epoch`` from ``t0``, their other bytes random
    (incompressible: a run's size is about ``n`` vectors, raw and Parquet)."""
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, (n, len(dv.buf)), np.uint8)
    for i in range(n):
        dv.buf[:] = noise[i].tobytes()
        dv.set("cn_loop", i + 1)
        dv.set("cn_epoch", epoch)
        dv.set("cn_time_ns", t0 + i * PERIOD)
        dv.set("cn_state", 0)
        w.snapshot(t0 + i * PERIOD, dv)
        if i % 500 == 499:
            assert w.flush()
    assert w.flush()


def removals(w: ArchiveWriter) -> list[tuple[int, str]]:
    events = EventLog("gn", 64)
    w.tick(0, events)
    return [
        (int(e.text.split()[e.text.split().index("run") + 1].rstrip(":,")), e.text)
        for e in events.drain()
        if e.id == "archive_removed"
    ]


def test_runs_past_max_bytes_are_removed_whole_oldest_first_never_the_running_one(
    flight: Mission, tmp_path: Path
) -> None:
    m = small(flight, max_bytes=6 * MIB, max_age_days=None, row_group_s=1.0, file_s=5.0)
    layout = Layout.for_node(m, "cn")
    dv = DataVector(layout)
    now = time.time_ns()
    w = ArchiveWriter(m, layout, tmp_path)
    try:
        # Four runs of about 2 x 1.5 MiB each (raw and Parquet), one writer:
        # each file closed applies retention, the run being written kept.
        for epoch in (1, 2, 3, 4):
            feed_random(w, dv, 2000, epoch, now + epoch * 10**9, seed=epoch)
            assert epoch in store.runs_on_disk(tmp_path)  # the running run, whatever its size
        told = removals(w)
    finally:
        w.close()
    told += removals(w)
    left = store.runs_on_disk(tmp_path)
    gone = [r for r, _ in told]
    assert gone == sorted(gone) and gone  # oldest first, each once
    assert gone + left == [1, 2, 3, 4]  # whole runs: those told gone, the rest whole
    assert 4 in left
    assert store.du(tmp_path) <= 6 * MIB
    assert all("more than 6291456 bytes" in text for _, text in told)
    with Archive(m, tmp_path) as a:
        for r in left:  # the runs kept are whole
            assert a.query(Query("cn_loop", run=r)).num_rows == 2000
        assert a.problems == []


def test_a_run_larger_than_max_bytes_survives_the_next_start(
    flight: Mission, tmp_path: Path
) -> None:
    m = small(flight, max_bytes=1 * MIB, max_age_days=None, row_group_s=1.0, file_s=5.0)
    layout = Layout.for_node(m, "cn")
    w = ArchiveWriter(m, layout, tmp_path)
    feed_random(w, DataVector(layout), 2000, 5, time.time_ns())
    w.close()
    assert store.du(tmp_path) > 1 * MIB
    # The ground node started again (its writer opens the archive, applies
    # retention): the last run, larger than the whole budget, is kept.
    w = ArchiveWriter(m, layout, tmp_path)
    w.close()
    assert removals(w) == []
    assert store.runs_on_disk(tmp_path) == [5]


def test_runs_older_than_max_age_are_removed_evented(flight: Mission, tmp_path: Path) -> None:
    m = small(flight, max_age_days=1.0, row_group_s=1.0, file_s=2.0)
    layout = Layout.for_node(m, "cn")
    dv = DataVector(layout)
    now = time.time_ns()
    w = ArchiveWriter(m, layout, tmp_path)
    try:
        feed_random(w, dv, 300, 1, now - 3 * 86_400 * 10**9)  # ended three days ago
        feed_random(w, dv, 300, 2, now - 3600 * 10**9)  # an hour ago
        feed_random(w, dv, 300, 3, now)  # being written: its first file closed
    finally:
        w.close()
    told = removals(w)
    assert [r for r, _ in told] == [1]
    assert "older than 1 day(s)" in told[0][1]
    assert store.runs_on_disk(tmp_path) == [2, 3]


def test_a_run_without_a_readable_end_is_aged_by_its_files_not_as_of_1970(
    flight: Mission, tmp_path: Path
) -> None:
    m = small(flight, row_group_s=1.0, file_s=2.0)
    layout = Layout.for_node(m, "cn")
    dv = DataVector(layout)
    w = ArchiveWriter(m, layout, tmp_path)
    feed_random(w, dv, 300, 7, time.time_ns())
    feed_random(w, dv, 300, 8, time.time_ns())
    w.close()
    (tmp_path / "runs" / "run-7.json").unlink()  # its record lost: no end to read
    removed: list[int] = []
    store.retain(
        tmp_path,
        max_bytes=1 << 40,
        max_age_days=365,
        keep=None,
        now_ns=time.time_ns(),
        removed=lambda r, _s, _why: removed.append(r),
    )
    assert removed == []
    assert store.runs_on_disk(tmp_path) == [7, 8]
