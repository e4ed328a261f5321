"""Tests of zplatform.archive: the writer, recovery, dedupe, retention, queries."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from zplatform.archive import Archive, ArchiveWriter, Query, archive_dir, store
from zplatform.archive import writer as writer_mod
from zplatform.config import Mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EventLog
from zplatform.errors import ArchiveError, ConfigError
from zplatform.mission.load import decode_mission, load_mission
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_800_000_000_000_000_000
PERIOD = 10_000_000


@pytest.fixture(scope="module")
def mission() -> Mission:
    return load_mission(ROOT / "configs" / "flight.yaml", code=False)


def small(mission: Mission, **archive: object) -> Mission:
    """``mission`` with its archive section replaced."""
    raw = msgspec.to_builtins(mission)
    raw["archive"] = {**raw["archive"], **archive}
    return msgspec.convert(raw, type=Mission)


def feed(w: ArchiveWriter, dv: DataVector, loops: range | list[int], epoch: int = 7) -> None:
    """Snapshots of ``loops`` of run ``epoch`` (state = loop // 100 % 4), then flush."""
    for i in loops:
        dv.set("cn_loop", i)
        dv.set("cn_epoch", epoch)
        dv.set("cn_time_ns", T0 + i * PERIOD)
        dv.set("cn_state", i // 100 % 4)
        dv.set("apogee_target_m", float(i) / 4)
        w.snapshot(T0 + i * PERIOD + 3, dv)
        if i % 500 == 0:
            assert w.flush()
    assert w.flush()


def lose_parquet(root: Path, run: int) -> None:
    """Run ``run``'s Parquet files lost and the run left open (a writer
    killed before it closed them): opening the archive must re-decode it
    from the raw segments."""
    for f in [*root.glob(f"tm/run-{run}/*/*.parquet"), *root.glob(f"ev/run-{run}/*.parquet")]:
        f.unlink()
    info = store.read_run(root, run)
    assert info is not None
    info.outcome = "open"
    store.write_run(root, info)


def test_rows_written_once_each_and_read_back(mission: Mission, tmp_path: Path) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    dv = DataVector(layout)
    feed(w, dv, range(1, 1201))
    feed(w, dv, range(1001, 1301))  # a gap fill / a second copy: 200 loops again
    w.event(EventRecord(T0, "gn", 1, T0, "COMMAND", "cmd_sent", "command ARM sent"))
    w.close()
    assert w.stats() == {
        "rows": 1300,
        "duplicates": 200,
        "dropped": 0,
        "events_dropped": 0,
        "errors": 0,
        "lost": 0,
    }
    with Archive(mission, tmp_path) as a:
        (info,) = a.runs()
        assert (info.run, info.first_loop, info.last_loop, info.loops) == (7, 1, 1300, 1300)
        assert info.states == ["SAFE", "ARMED", "BOOST", "COAST"][: len(info.states)]
        assert info.outcome == "ended" and info.events == 1
        assert info.commands == ["gn: command ARM sent"]
        t = a.query(Query("apogee_target_m,cn_state"))
        assert t.column("loop").to_pylist() == list(range(1, 1301))
        assert t.column("apogee_target_m").to_pylist() == [i / 4 for i in range(1, 1301)]
        assert t.column("rx_ns").to_pylist()[0] == T0 + PERIOD + 3
        assert t.column_names == ["loop", "t_ns", "rx_ns", "cn_state", "apogee_target_m"]
        assert a.problems == []


def test_a_closed_segment_is_sealed_and_a_lost_run_is_redecoded_from_it(
    mission: Mission, tmp_path: Path
) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    feed(w, DataVector(layout), range(1, 301))
    w.event(EventRecord(T0, "cn", 1, T0, "WARNING_HI", "fault", "a fault"))
    w.close()
    raw = sorted(p.name for p in (tmp_path / "raw" / "run-7").iterdir())
    assert raw == ["seg-00000000.zfr.zsb"]
    # The Parquet files lost, the run left open: all of it comes back from the raw.
    lose_parquet(tmp_path, 7)
    with Archive(mission, tmp_path) as a:
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 301))
        assert a.events(7).column("text").to_pylist() == ["a fault"]
        assert a.runs()[0].outcome == "interrupted" and a.problems == []


def test_an_event_filled_from_the_recorder_is_archived_marked_filled(
    mission: Mission, tmp_path: Path
) -> None:
    """The events table says which events were filled from the control node's
    recorder (the console and the events JSONL say it too); a run's events file
    written before the column existed reads back beside a newer one, not filled."""
    import pyarrow.parquet as pq

    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    feed(w, DataVector(layout), range(1, 301))
    w.event(EventRecord(T0, "cn", 1, T0, "WARNING_HI", "fault", "live"))
    w.event(EventRecord(T0 + 5, "cn", 2, T0 + 1, "WARNING_HI", "fault", "filled", True, True))
    w.close()
    (part,) = store.parquet_files(tmp_path, "ev", 7)
    new = pq.read_table(part)
    assert new.column("filled").to_pylist() == [False, True]
    # An older writer's part, before it: the same events without the column.
    older = part
    part.rename(part.with_name("part-000001.parquet"))
    pq.write_table(new.drop_columns(["filled"]), older)
    with Archive(mission, tmp_path) as a:
        t = a.events(7)
        assert t.schema == store.EVENT_SCHEMA
        got = list(zip(t.column("text").to_pylist(), t.column("filled").to_pylist(), strict=True))
        assert sorted(got) == [
            ("filled", False),
            ("filled", True),
            ("live", False),
            ("live", False),
        ]


def test_a_late_loop_is_in_its_place_in_a_query(mission: Mission, tmp_path: Path) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(small(mission, row_group_s=1.0), layout, tmp_path)
    dv = DataVector(layout)
    feed(w, dv, [*range(1, 101), *range(150, 201)])
    feed(w, dv, range(101, 150))  # a gap filled after later loops came
    w.close()
    with Archive(mission, tmp_path) as a:
        assert a.runs()[0].in_order is False
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 201))
    w = ArchiveWriter(mission, layout, tmp_path)
    feed(w, dv, range(1, 101), epoch=8)
    w.close()
    with Archive(mission, tmp_path) as a:
        assert a.run(8).in_order is True


def test_every_parquet_write_gives_its_memory_back(
    mission: Mission, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 25: the ground node grew 26-40 MB "during a flood" of the
    flight soak, about a minute into the flight whichever flood ran then:
    the archive's first row group (60 s of the flight's 190 columns,
    decoded and encoded) left that memory free in Arrow's pool and glibc's
    heaps, kept for good (``python -m bench.ground_memory --variant
    archive``: +33 MB at the first row group before; now +8, +4 at the
    second, then under 0.2 MB a group). Now the archive's thread
    encodes one row at start (the Parquet code paged in then, not in
    flight) and gives the memory back after that and each time it closes
    its files (every row group is its own closed files, and once more at
    the run's end): 650 loops in row groups of 100 are the warm-up, 7 row
    groups (the last of 50, at the run's end) and the run's end, exactly
    9 releases."""
    layout = Layout.for_node(mission, "cn")
    calls: list[int] = []
    monkeypatch.setattr(writer_mod, "release_memory", lambda: calls.append(1))
    w = ArchiveWriter(small(mission, row_group_s=1.0, file_s=3.0), layout, tmp_path)
    feed(w, DataVector(layout), range(1, 651))
    w.close()
    assert (w.rows, len(calls), w.releases) == (650, 9, 9)
    monkeypatch.undo()
    writer_mod.release_memory()  # the real one: never raises


def test_the_loops_a_run_archived_are_kept_as_ranges(mission: Mission, tmp_path: Path) -> None:
    """Issue 25: the archive kept every loop of a run in a set (about 80
    bytes a loop: 28 MB an hour at 100 Hz, seen as the ground's slow growth
    in ``bench.ground_memory --variant archive``). Now as ranges of
    consecutive loops: 600 loops with a hole of 99 are 2 ranges; the hole
    filled late (a gap fill), 1; a repeat changes nothing."""
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(small(mission, row_group_s=1.0), layout, tmp_path)
    dv = DataVector(layout)
    feed(w, dv, [*range(1, 301), *range(400, 601)])
    assert w.loop_ranges == 2
    feed(w, dv, range(301, 400))
    assert w.loop_ranges == 1
    feed(w, dv, range(250, 350))  # every one archived already
    assert (w.loop_ranges, w.rows, w.duplicates) == (1, 600, 100)
    w.close()


@settings(max_examples=200)
@given(st.lists(st.integers(min_value=0, max_value=60), max_size=80))
def test_a_loop_set_holds_what_a_set_holds(loops: list[int]) -> None:
    got, want = writer_mod.LoopSet(), set()
    for lp in loops:
        got.add(lp)
        want.add(lp)
        assert lp in got
    assert [lp for lp in range(-1, 62) if lp in got] == sorted(want)
    assert len(got) == len(want) and got.max(-1) == max(want, default=-1)
    # As few ranges as the loops have runs of consecutive numbers.
    assert got.ranges == sum(1 for lp in want if lp - 1 not in want)
    assert writer_mod.LoopSet(loops).ranges == got.ranges


def test_runs_are_kept_apart(mission: Mission, tmp_path: Path) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    dv = DataVector(layout)
    feed(w, dv, range(1, 101), epoch=5)
    feed(w, dv, range(1, 51), epoch=9)  # the CN restarted: a new run, its loops anew
    w.close()
    with Archive(mission, tmp_path) as a:
        assert [(r.run, r.loops, r.outcome) for r in a.runs()] == [
            (5, 100, "ended"),
            (9, 50, "ended"),
        ]
        assert a.query(Query("cn_loop", run=5)).num_rows == 100
        assert a.query(Query("cn_loop")).num_rows == 50  # the last run by default


def test_a_full_queue_drops_counted_and_evented_once_a_second(
    mission: Mission, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(writer_mod, "WAKE_S", 3600.0)  # the thread takes nothing until close
    layout = Layout.for_node(mission, "cn")
    m = small(mission, queue_s=0.1)  # 16 slots (the least)
    w = ArchiveWriter(m, layout, tmp_path)
    dv = DataVector(layout)
    for i in range(1, 22):
        dv.set("cn_loop", i)
        w.snapshot(T0 + i, dv)
    assert w.dropped == 5
    events = EventLog("gn", 16)
    w.tick(T0, events)
    w.tick(T0 + 500_000_000, events)  # within the second: not told again
    w.close()
    told = [e for e in events.drain() if e.id == "archive_dropping"]
    assert len(told) == 1 and "5 snapshot(s)" in told[0].text


def test_a_vector_of_another_layout_is_dropped_counted_never_raised(
    mission: Mission, tmp_path: Path
) -> None:
    other = load_mission(ROOT / "configs" / "led_test.yaml", code=False)
    w = ArchiveWriter(mission, Layout.for_node(mission, "cn"), tmp_path)
    w.snapshot(T0, DataVector(Layout.for_node(other, "cn")))
    w.close()
    assert (w.dropped, w.rows) == (1, 0)


def _child(tmp_path: Path, n: int) -> subprocess.Popen[str]:
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(ROOT / "tests")!r})
        from unit.test_archive import feed, _mission_for_child
        from zplatform.archive import ArchiveWriter
        from zplatform.core.datavector import DataVector, Layout
        m = _mission_for_child()
        layout = Layout.for_node(m, "cn")
        w = ArchiveWriter(m, layout, {str(tmp_path)!r})
        feed(w, DataVector(layout), range(1, {n + 1}))
        print("fed", flush=True)
        sys.stdin.read()
        """
    )
    return subprocess.Popen(
        [sys.executable, "-c", code],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def _mission_for_child() -> Mission:
    return small(load_mission(ROOT / "configs" / "flight.yaml", code=False), row_group_s=1.0)


def test_kill_9_of_the_writer_then_the_archive_opens_clean(
    mission: Mission, tmp_path: Path
) -> None:
    # 1 s row groups of 100 loops: 250 loops leave 2 row groups written (a
    # closed file each) and 50 loops held in memory; the raw segment holds all 250.
    p = _child(tmp_path, 250)
    try:
        assert p.stdout is not None and p.stdout.readline() == "fed\n"
        assert len(list(tmp_path.glob("tm/run-7/*/part-*.parquet"))) == 2
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    with Archive(mission, tmp_path) as a:
        (info,) = a.runs()
        assert info.outcome == "interrupted"
        t = a.query(Query("cn_loop"))
        assert t.column("cn_loop").to_pylist() == list(range(1, 251))
        assert a.problems == []
    assert not list(tmp_path.glob("**/*.tmp"))


def test_a_damaged_segment_is_skipped_with_a_note_and_the_rest_stays(
    mission: Mission, tmp_path: Path
) -> None:
    p = _child(tmp_path, 250)
    try:
        assert p.stdout is not None and p.stdout.readline() == "fed\n"
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    (seg,) = tmp_path.glob("raw/run-7/seg-*.zfr")
    data = bytearray(seg.read_bytes())
    data[-100] ^= 0xFF  # inside the last loop's record (it is not in any Parquet file yet)
    seg.write_bytes(bytes(data))
    with Archive(mission, tmp_path) as a:
        t = a.query(Query("cn_loop"))
        assert t.column("cn_loop").to_pylist() == list(range(1, 250))
        assert len(a.problems) == 1 and "seg-00000000.zfr" in a.problems[0]


def test_an_unreadable_parquet_file_is_skipped_with_a_note(
    mission: Mission, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ArchiveWriter, "_compact", lambda self, final: None)  # 3 files kept
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(small(mission, row_group_s=1.0, file_s=1.0), layout, tmp_path)
    feed(w, DataVector(layout), range(1, 301))
    w.close()
    files = sorted(tmp_path.glob("tm/run-7/*/part-*.parquet"))
    assert len(files) == 3
    files[1].write_bytes(b"not parquet")
    with Archive(mission, tmp_path) as a:
        t = a.query(Query("cn_loop"))
        assert t.column("cn_loop").to_pylist() == [*range(1, 101), *range(201, 301)]
        assert len(a.problems) == 1 and files[1].name in a.problems[0]


def test_a_damaged_footer_is_found_when_duckdb_fails_and_skipped(
    mission: Mission, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ArchiveWriter, "_compact", lambda self, final: None)  # 3 files kept
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(small(mission, row_group_s=1.0, file_s=1.0), layout, tmp_path)
    feed(w, DataVector(layout), range(1, 301))
    w.close()
    files = sorted(tmp_path.glob("tm/run-7/*/part-*.parquet"))
    data = bytearray(files[2].read_bytes())
    data[-8:-4] = (len(data) * 2).to_bytes(4, "little")  # the footer's length; magic kept
    files[2].write_bytes(bytes(data))
    with Archive(mission, tmp_path) as a:
        t = a.query(Query("cn_loop"))
        assert t.column("cn_loop").to_pylist() == list(range(1, 201))
        assert len(a.problems) == 1 and files[2].name in a.problems[0]


def test_a_full_disk_is_counted_told_once_and_the_archive_goes_on(
    mission: Mission, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    dv = DataVector(layout)
    feed(w, dv, range(1, 101))
    raw = ArchiveWriter._raw

    def full(self: ArchiveWriter, data: bytes) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ArchiveWriter, "_raw", full)
    feed(w, dv, range(101, 201))
    feed(w, dv, range(201, 301))
    monkeypatch.setattr(ArchiveWriter, "_raw", raw)  # the disk has room again
    feed(w, dv, range(301, 401))
    events = EventLog("gn", 16)
    w.tick(T0, events)
    w.close()
    s = w.stats()
    assert s["errors"] == 2 and s["lost"] == 200 and s["dropped"] == 0
    told = [e for e in events.drain() if e.id == "archive_failed"]
    assert len(told) == 1 and "No space left" in told[0].text
    with Archive(mission, tmp_path) as a:
        loops = a.query(Query("cn_loop")).column("loop").to_pylist()
    assert loops == [*range(1, 101), *range(301, 401)]


def test_a_full_disk_failing_writes_and_compaction_is_told_once(
    mission: Mission, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The defect (a live full-disk test saw two archive_failed events): a
    full disk fails the raw writes and then the compaction of the Parquet
    files, each told as its own kind. One full disk is one message; both
    failures are counted."""
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    dv = DataVector(layout)
    feed(w, dv, range(1, 101))

    def full(*a: object, **kw: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ArchiveWriter, "_raw", full)
    feed(w, dv, range(101, 201))  # the raw write fails (the archive's thread)
    # ... and the compaction's, as the archive's thread tells it
    w._fail("compact its files", OSError(28, "No space left on device"))
    events = EventLog("gn", 16)
    w.tick(T0, events)
    told = [e for e in events.drain() if e.id == "archive_failed"]
    assert w.errors == 2 and len(told) == 1
    monkeypatch.undo()
    w.close()


def test_retention_removes_the_oldest_runs_whole(mission: Mission, tmp_path: Path) -> None:
    layout = Layout.for_node(mission, "cn")
    dv = DataVector(layout)
    for epoch in (1, 2, 3):
        w = ArchiveWriter(mission, layout, tmp_path)
        feed(w, dv, range(1, 301), epoch=epoch)
        w.close()
    one_run = sum(store.du(store.run_dirs(tmp_path, k, 3)) for k in ("raw", "tm", "ev"))
    removed: list[tuple[int, str]] = []
    store.retain(
        tmp_path,
        max_bytes=int(store.du(tmp_path) - one_run / 2),
        max_age_days=None,
        keep=None,
        now_ns=T0,
        removed=lambda r, _s, why: removed.append((r, why)),
    )
    assert [r for r, _ in removed] == [1]
    assert store.runs_on_disk(tmp_path) == [2, 3]
    store.retain(
        tmp_path,
        max_bytes=1 << 40,
        max_age_days=1,
        keep=3,  # the run being written is never removed
        now_ns=T0 + 2 * 86_400 * 10**9,
        removed=lambda r, _s, why: removed.append((r, why)),
    )
    assert [r for r, _ in removed] == [1, 2]
    assert "older than 1 day(s)" in removed[1][1]
    assert store.runs_on_disk(tmp_path) == [3]


def test_one_writer_per_archive(mission: Mission, tmp_path: Path) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    try:
        with pytest.raises(ArchiveError, match="another ground node writes"):
            ArchiveWriter(mission, layout, tmp_path)
    finally:
        w.close()


def test_archive_dir_follows_the_environment_then_the_mission(
    mission: Mission, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("ZPLATFORM_ARCHIVE_DIR", str(tmp_path))
    assert archive_dir(mission) == tmp_path / "flight"
    monkeypatch.delenv("ZPLATFORM_ARCHIVE_DIR")
    assert archive_dir(small(mission, dir="/srv/arch")) == Path("/srv/arch/flight")


def test_archive_config_errors_name_the_yaml_path() -> None:
    base = (ROOT / "configs" / "minimal.yaml").read_text()
    with pytest.raises(ConfigError, match=r"\$\.archive"):
        decode_mission(base + "\narchive: {rows: 3}\n", code=False)
    with pytest.raises(ConfigError, match=r"\$\.archive\.row_group_s"):
        decode_mission(base + "\narchive: {row_group_s: 60, file_s: 10}\n", code=False)
    m = decode_mission(base + "\narchive: {enabled: false}\n", code=False)
    assert not m.archive.enabled
    assert os.environ.get("ZPLATFORM_ARCHIVE_DIR")  # the tests never write the user's


@pytest.fixture
def cli_archive(mission: Mission, tmp_path: Path) -> Path:
    """An archive of run 7, loops 1..300, and a WARNING_HI event."""
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    feed(w, DataVector(layout), range(1, 301))
    w.event(EventRecord(T0 + 5, "cn", 3, T0 + 4, "WARNING_HI", "fault", "a fault"))
    w.event(EventRecord(T0 + 6, "gn", 4, T0 + 6, "COMMAND", "cmd_sent", "ARM sent"))
    w.close()
    return tmp_path


def _cli(d: Path, *args: str) -> int:
    from zplatform.cli.main import main

    return main(["archive", str(ROOT / "configs" / "flight.yaml"), "--dir", str(d), *args])


def test_cli_query_prints_the_telemetry_logs_csv(
    cli_archive: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = _cli(
        cli_archive, "query", "--elements", "apogee_t*,cn_state", "--from", "1", "--to", "loop:102"
    )
    assert rc == 0
    assert capsys.readouterr().out.splitlines() == [
        "rx_time_ns,cn_state,apogee_target_m",
        f"{T0 + 101 * PERIOD + 3},ARMED,25.25",
        f"{T0 + 102 * PERIOD + 3},ARMED,25.5",
    ]
    rc = _cli(cli_archive, "query", "--elements", "cn_state,ev_liftoff", "--every", "1s")
    assert rc == 0
    assert capsys.readouterr().out.splitlines() == [
        "bucket_ns,cn_state_min,cn_state_max,cn_state_mean,ev_liftoff_min,ev_liftoff_max,"
        "ev_liftoff_mean",
        f"{T0 + PERIOD},0,1,0.01,0,0,0.0",
        f"{T0 + 101 * PERIOD},1,2,1.01,0,0,0.0",
        f"{T0 + 201 * PERIOD},2,3,2.01,0,0,0.0",
    ]


def test_cli_runs_events_and_export(
    cli_archive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    import pyarrow.parquet as pq

    assert _cli(cli_archive, "runs", "--json") == 0
    (run,) = json.loads(capsys.readouterr().out)
    assert (run["run"], run["loops"], run["states"], run["outcome"]) == (
        7,
        300,
        ["SAFE", "ARMED", "BOOST", "COAST"],
        "ended",
    )
    assert run["commands"] == ["gn: ARM sent"]
    assert _cli(cli_archive, "events", "--severity", "warning_hi") == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert json.loads(line)["text"] == "a fault"
    out = tmp_path / "x.parquet"
    assert _cli(cli_archive, "export", "--format", "parquet", "--out", str(out)) == 0
    t = pq.read_table(out)
    assert t.num_rows == 300 and "dn0_state" in t.column_names


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["query", "--elements", "cn_stat"], "no element matches 'cn_stat'; did you mean"),
        (["query", "--elements", "cn_state", "--from", "5", "--to", "2"], "reversed"),
        (["query", "--elements", "cn_state", "--from", "noon"], "expected ISO UTC"),
        (["query", "--elements", "cn_state", "--from", "2026-12-07T03:20:00"], "time zone"),
        (["query", "--elements", "cn_state", "--run", "3"], "no run 3"),
        (["query", "--elements", "cn_state", "--every", "1s", "--agg", "median"], "median"),
        (["query", "--elements", "cn_state", "--every", "0s"], "longer than 0"),
        (["query", "--elements", "nav_*", "--every", "1s"], "nav_cov is an array"),
        (["query", "--elements", ","], "--elements is empty"),
        (["events", "--severity", "LOUD"], "no severity 'LOUD'"),
    ],
)
def test_cli_refuses_a_bad_query_with_its_reason(
    cli_archive: Path, capsys: pytest.CaptureFixture[str], args: list[str], reason: str
) -> None:
    assert _cli(cli_archive, *args) == 2
    err = capsys.readouterr().err
    assert reason in err and "Traceback" not in err


def test_cli_refuses_a_missing_archive(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _cli(tmp_path / "none", "runs") == 2
    assert "no archive of mission 'flight'" in capsys.readouterr().err
