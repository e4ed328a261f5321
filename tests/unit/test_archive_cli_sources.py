"""``log``, ``plot`` and ``replay --log`` read the ground archive as well as
files (issue 28): a run of the archive written as the ground's log equals
``archive query``'s rows and events, and plots like the CSV it would be."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.unit.test_archive import PERIOD, T0, feed
from zplatform.archive import Archive, ArchiveWriter, Query
from zplatform.cli.main import main
from zplatform.core.datavector import DataVector, Layout
from zplatform.mission.load import load_mission
from zplatform.telemetry.logs import read_csv
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
MISSION_FILE = str(ROOT / "configs" / "flight.yaml")
MISSION = load_mission(MISSION_FILE, code=False)


@pytest.fixture
def archive(tmp_path: Path) -> Path:
    """Runs 7 (loops 1..300, two events) and 9 (loops 1..50) in an archive."""
    d = tmp_path / "archive"
    layout = Layout.for_node(MISSION, "cn")
    w = ArchiveWriter(MISSION, layout, d)
    feed(w, DataVector(layout), range(1, 301))
    w.event(EventRecord(T0 + 5, "cn", 3, T0 + 4, "WARNING_HI", "fault", "a fault"))
    w.event(EventRecord(T0 + 6, "gn", 4, T0 + 6, "COMMAND", "cmd_sent", "ARM sent"))
    w.close()
    w = ArchiveWriter(MISSION, layout, d)  # the ground started again: run 9
    feed(w, DataVector(layout), range(1, 51), epoch=9)
    w.close()
    return d


def _expected(d: Path, run: int) -> tuple[list[int], list[str]]:
    with Archive(MISSION, d) as a:
        t = a.query(Query("cn_state", run=run))
        ev = a.events(run)
    return t.column("rx_ns").to_pylist(), ev.column("id").to_pylist()


def test_log_from_archive_writes_the_runs_rows_and_events(
    archive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "tm.csv"
    rc = main(
        ["log", MISSION_FILE, "--out", str(out), "--from-archive", str(archive), "--run", "7"]
    )
    assert rc == 0
    rows = read_csv(out)
    rx, ids = _expected(archive, 7)
    assert [int(r["rx_time_ns"]) for r in rows] == rx and len(rows) == 300
    assert rows[100]["cn_state"] == "ARMED" and rows[100]["apogee_target_m"] == "25.25"
    evs = [json.loads(x) for x in (tmp_path / "tm.events.jsonl").read_text().splitlines()]
    assert [e["id"] for e in evs] == ids == ["fault", "cmd_sent"]
    assert "run 7 of the archive" in capsys.readouterr().out
    # Without --run: the last run (9).
    assert main(["log", MISSION_FILE, "--out", str(out), "--from-archive", str(archive)]) == 0
    assert len(read_csv(out)) == 50
    # The mission's own archive, found as `archive` finds it (ZPLATFORM_ARCHIVE_DIR).
    assert main(["log", MISSION_FILE, "--out", str(out), "--from-archive"]) == 2  # none there


def test_log_from_archive_refuses_what_does_not_fit(
    archive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = str(tmp_path / "tm.csv")
    base = ["log", MISSION_FILE, "--out", out, "--from-archive", str(archive)]
    assert main([*base, "--run", "8"]) == 2
    assert "no run 8 in the archive" in capsys.readouterr().err
    assert main([*base, "--duration", "1"]) == 2
    assert main([*base, "--from-recorder", str(tmp_path)]) == 2
    assert not Path(out).exists()


def test_replay_log_reads_a_ground_archive(
    archive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r.csv"
    rc = main(["replay", str(archive), "--mission", MISSION_FILE, "--log", str(out), "--run", "7"])
    assert rc == 0
    assert [int(r["rx_time_ns"]) for r in read_csv(out)] == _expected(archive, 7)[0]
    assert len((tmp_path / "r.events.jsonl").read_text().splitlines()) == 2
    text = capsys.readouterr().out
    assert "run 7: loops 1..300 (300 rows" in text and "not replayed" in text
    # An archive cannot be replayed (no device node replies): said, not tried.
    assert main(["replay", str(archive), "--mission", MISSION_FILE]) == 2
    assert "ground archive" in capsys.readouterr().err


def test_plot_reads_a_run_of_the_archive(
    archive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("matplotlib")
    png = tmp_path / "p.png"
    rc = main(
        [
            "plot",
            MISSION_FILE,
            "apogee_target_m",
            "cn_state",
            "--out",
            str(png),
            "--run",
            "7",
            "--archive",
            str(archive),
        ]
    )
    assert rc == 0 and png.stat().st_size > 0
    # The states change at loops 100, 200 and 300: three markers (no command).
    assert "run 7: 300 rows, 3 state/command markers" in capsys.readouterr().out
    # The same as the CSV `log --from-archive` writes, plotted.
    csv = tmp_path / "tm.csv"
    argv = ["log", MISSION_FILE, "--out", str(csv), "--from-archive", str(archive)]
    assert main([*argv, "--run", "7"]) == 0
    capsys.readouterr()
    assert main(["plot", str(csv), "apogee_target_m", "cn_state", "--out", str(png)]) == 0
    assert "(300 rows, 3 state/command markers)" in capsys.readouterr().out
    rc = main(
        [
            "plot",
            MISSION_FILE,
            "apogee_targt_m",
            "--out",
            str(png),
            "--run",
            "7",
            "--archive",
            str(archive),
        ]
    )
    assert rc == 2 and "did you mean" in capsys.readouterr().err


def test_the_archive_csv_equals_a_query_row_for_row(archive: Path, tmp_path: Path) -> None:
    """Every row of run 7: loop i received at T0 + i periods + 3."""
    out = tmp_path / "tm.csv"
    assert (
        main(["log", MISSION_FILE, "--out", str(out), "--from-archive", str(archive), "--run", "7"])
        == 0
    )
    rows = read_csv(out)
    assert [int(r["rx_time_ns"]) for r in rows] == [T0 + i * PERIOD + 3 for i in range(1, 301)]
