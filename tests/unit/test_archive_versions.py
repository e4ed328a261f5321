"""The run record's format version (issue 28, compatibility): a record an
older zplatform wrote is read with defaults; one a newer zplatform wrote is
refused with a clear error naming the file, and never overwritten."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import pytest

from tests.unit.test_archive import feed
from zplatform.archive import Archive, ArchiveWriter, Query, store
from zplatform.config import Mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EventLog
from zplatform.errors import ArchiveError
from zplatform.mission.load import load_mission

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def mission() -> Mission:
    return load_mission(ROOT / "configs" / "flight.yaml", code=False)


def _one_run(mission: Mission, root: Path, loops: range, epoch: int = 7) -> None:
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, root)
    feed(w, DataVector(layout), loops, epoch=epoch)
    w.close()


def _record(root: Path, run: int) -> Path:
    return root / "runs" / f"run-{run}.json"


def test_a_record_of_97fbbe2_and_of_before_group_columns_reads_with_defaults(
    mission: Mission, tmp_path: Path
) -> None:
    _one_run(mission, tmp_path, range(1, 301))
    path = _record(tmp_path, 7)
    new = json.loads(path.read_bytes())
    # The record as 97fbbe2 wrote it: every field but `version`.
    old = {k: v for k, v in new.items() if k != "version"}
    path.write_text(json.dumps(old))
    with Archive(mission, tmp_path) as a:
        (info,) = a.runs()
        assert (info.run, info.loops, info.outcome) == (7, 300, "ended")
        assert info.group_columns == store.GROUP_COLUMNS
        assert a.query(Query("cn_loop")).column("loop").to_pylist() == list(range(1, 301))
        assert a.problems == []
    # Older still: before `group_columns` (every element in part-N.parquet).
    older = {k: v for k, v in old.items() if k != "group_columns"}
    path.write_text(json.dumps(older))
    info2 = store.read_run(tmp_path, 7)
    assert info2 is not None and info2.group_columns == 0 and info2.loops == 300
    # A writer taking the run on writes it back in this format.
    path.write_text(json.dumps(old))
    _one_run(mission, tmp_path, range(301, 401))
    again = json.loads(path.read_bytes())
    assert again["loops"] == 400 and again["version"] == store.RUN_VERSION


def test_a_record_of_a_newer_zplatform_is_refused_named_and_never_overwritten(
    mission: Mission, tmp_path: Path
) -> None:
    _one_run(mission, tmp_path, range(1, 201), epoch=5)
    _one_run(mission, tmp_path, range(1, 301), epoch=7)
    path = _record(tmp_path, 7)
    future = json.loads(path.read_bytes())
    future.update(version=1000, outcome="open", a_future_field=[1, 2])
    body = json.dumps(future).encode()
    path.write_bytes(body)

    with pytest.raises(ArchiveError, match="written by a newer zplatform") as err:
        store.read_run(tmp_path, 7)
    assert str(path) in str(err.value)

    # Opening the archive recovers "open" runs: not this one (left as it is).
    with Archive(mission, tmp_path) as a:
        assert [r.run for r in a.runs()] == [5]
        assert len(a.problems) == 1 and "written by a newer zplatform" in a.problems[0]
        assert str(path) in a.problems[0]
        with pytest.raises(ArchiveError, match=r"run-7\.json: written by a newer zplatform"):
            a.run(7)
        assert a.run(None).run == 5
    assert path.read_bytes() == body

    # A writer handed that run's loops: refused, counted, told once; the record kept.
    layout = Layout.for_node(mission, "cn")
    w = ArchiveWriter(mission, layout, tmp_path)
    feed(w, DataVector(layout), range(301, 401), epoch=7)
    events = EventLog("gn", 16)
    w.tick(0, events)
    w.close()
    assert (w.stats()["lost"], w.stats()["rows"]) == (100, 0), w.stats()
    told = [e for e in events.drain() if e.id == "archive_failed"]
    assert len(told) == 1 and "written by a newer zplatform" in told[0].text
    assert path.read_bytes() == body

    # Retention and merge leave it alone too.
    other = tmp_path / "other"
    _one_run(mission, other, range(1, 101), epoch=7)
    notes: list[str] = []
    got = store.merge(tmp_path, other, layout, mission.mission, mission.vehicle, notes.append)
    assert [c.run for c in got] == []
    assert any("written by a newer zplatform" in n for n in notes)
    assert path.read_bytes() == body


def test_the_version_is_part_of_every_record_written() -> None:
    info = store.RunInfo(1, "m", "v", 0)
    raw = msgspec.json.decode(msgspec.json.encode(info))
    assert raw["version"] == store.RUN_VERSION


def test_the_cli_says_which_record_a_newer_zplatform_wrote(
    mission: Mission, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tests.unit.test_archive import _cli

    _one_run(mission, tmp_path, range(1, 201), epoch=5)
    _one_run(mission, tmp_path, range(1, 201), epoch=7)
    path = _record(tmp_path, 7)
    future = json.loads(path.read_bytes())
    future.update(version=1000, a_future_field=True)
    path.write_text(json.dumps(future))
    capsys.readouterr()
    assert _cli(tmp_path, "runs", "--json") == 0
    out, err = capsys.readouterr()
    assert [r["run"] for r in json.loads(out)] == [5]
    assert f"{path}: written by a newer zplatform" in err
    assert _cli(tmp_path, "query", "--run", "7", "--elements", "cn_state") == 2
    err = capsys.readouterr().err
    assert f"{path}: written by a newer zplatform" in err and "Traceback" not in err
