"""A run recorded by several stations is one run, each loop once (issue 28):
``zplatform archive MISSION merge SRC...`` takes another station's archive
in, deduplicated by (run, loop) and events by (node, seq, stamp)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.unit.test_archive import T0, feed
from zplatform.archive import Archive, ArchiveWriter, Query, store
from zplatform.cli.main import main
from zplatform.core.datavector import DataVector, Layout
from zplatform.mission.load import load_mission
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
MISSION_FILE = str(ROOT / "configs" / "flight.yaml")
MISSION = load_mission(MISSION_FILE, code=False)
LAYOUT = Layout.for_node(MISSION, "cn")


def ev(seq: int, text: str = "x") -> EventRecord:
    return EventRecord(T0 + seq, "gn", seq, T0 + seq, "COMMAND", "cmd_sent", text)


def station(d: Path, runs: list[tuple[int, range, list[EventRecord]]]) -> Path:
    """An archive at ``d`` holding, per (run, loops, events), those."""
    for run, loops, events in runs:
        w = ArchiveWriter(MISSION, LAYOUT, d)  # a ground started for each run
        feed(w, DataVector(LAYOUT), loops, epoch=run)
        for e in events:
            w.event(e)
        w.close()
    return d


def _merge(dest: Path, *srcs: Path) -> int:
    return main(["archive", MISSION_FILE, "--dir", str(dest), "merge", *map(str, srcs)])


@pytest.fixture
def two(tmp_path: Path) -> tuple[Path, Path, Path]:
    """Station A saw run 7's loops 1..200; station B 150..300 and run 8;
    both the event 2; and a reference that saw everything."""
    a = station(tmp_path / "a", [(7, range(1, 201), [ev(1, "ARM"), ev(2, "LAUNCH")])])
    b = station(
        tmp_path / "b",
        [(7, range(150, 301), [ev(2, "LAUNCH"), ev(3, "ABORT")]), (8, range(1, 51), [])],
    )
    ref = station(
        tmp_path / "ref", [(7, range(1, 301), [ev(1), ev(2), ev(3)]), (8, range(1, 51), [])]
    )
    return a, b, ref


def test_merge_takes_each_loop_and_event_once(
    two: tuple[Path, Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    a, b, ref = two
    assert _merge(a, b) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [
        f"{b}: run 7: 100 row(s) and 1 event(s) taken, 51 row(s) and 1 event(s) held already",
        f"{b}: run 8: 50 row(s) and 0 event(s) taken, 0 row(s) and 0 event(s) held already",
    ]
    q = Query("cn_state,apogee_target_m", run=7)
    with Archive(MISSION, a) as merged, Archive(MISSION, ref) as whole:
        t = merged.query(q)
        assert t.column("loop").to_pylist() == list(range(1, 301))
        assert t.equals(whole.query(q))
        assert merged.query(Query("cn_state", run=8)).num_rows == 50
        info = merged.run(7)
        assert (info.loops, info.first_loop, info.last_loop) == (300, 1, 300)
        assert info.events == 3 and not info.in_order
        assert info.commands == ["gn: ARM", "gn: LAUNCH", "gn: ABORT"]
        assert merged.events(7).column("seq").to_pylist() == [1, 2, 3]
        assert merged.problems == []
    # Again: nothing is taken twice.
    assert _merge(a, b) == 0
    assert capsys.readouterr().out.splitlines()[0] == (
        f"{b}: run 7: 0 row(s) and 0 event(s) taken, 151 row(s) and 2 event(s) held already"
    )
    with Archive(MISSION, a) as merged:
        assert merged.query(q).num_rows == 300 and merged.run(7).loops == 300


def test_merge_into_an_empty_archive_and_the_raw_segments_hold_each_loop_once(
    two: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    a, b, _ = two
    c = tmp_path / "c"
    assert _merge(c, a, b) == 0
    with Archive(MISSION, c) as merged:
        assert merged.run(7).loops == 300 and merged.run(7).outcome == "ended"
        assert merged.query(Query("cn_state", run=7)).column("loop").to_pylist() == list(
            range(1, 301)
        )
    # The raw segments are the source of truth: decoded again from them
    # alone (the Parquet files gone, the run left open), each loop once.
    shutil.rmtree(c / "tm")
    shutil.rmtree(c / "ev")
    info = store.read_run(c, 7)
    assert info is not None
    info.outcome, info.loops, info.events = "open", 0, 0
    store.write_run(c, info)
    with Archive(MISSION, c) as again:
        assert again.query(Query("cn_state", run=7)).column("loop").to_pylist() == list(
            range(1, 301)
        )
        assert again.run(7).loops == 300 and again.run(7).events == 3


def test_merge_refuses_what_it_cannot_take(
    two: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a, b, _ = two
    assert _merge(a, tmp_path / "nothing") == 2
    assert "not an archive directory" in capsys.readouterr().err
    assert _merge(a, a) == 2
    w = ArchiveWriter(MISSION, LAYOUT, a)  # a ground node writes it
    try:
        assert _merge(a, b) == 2
        assert "a ground node writes the archive" in capsys.readouterr().err
    finally:
        w.close()
    with Archive(MISSION, a) as merged:
        assert merged.run(7).loops == 200  # nothing taken
