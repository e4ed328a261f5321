"""A wide layout stored as file groups (issue 28): past ``GROUP_COLUMNS``
elements, a run's telemetry files are split into groups of at most that
many element columns (``part-N.parquet`` with the loop and times, then
``part-N.gK.parquet``), so a query of one element parses and reads one
group's file beside group 0's, never the others'. Here the flight mission's
elements with ``GROUP_COLUMNS`` a third of them: three groups; every answer
equals that of the same rows stored in one file."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from tests.unit.test_archive import feed
from zplatform.archive import Archive, ArchiveWriter, Query, store
from zplatform.core.datavector import DataVector, Layout
from zplatform.mission.load import load_mission

ROOT = Path(__file__).resolve().parents[2]
MISSION = load_mission(ROOT / "configs" / "flight.yaml", code=False)
LAYOUT = Layout.for_node(MISSION, "cn")
NAMES = list(LAYOUT.elements)
G = -(-len(NAMES) // 3)
"""Element columns per group: three groups, whatever the layout's size (the
indexes below name elements of groups 1 and 2 by it: 70, 100; 150, 170, 180)."""


def _same(a: pa.Table, b: pa.Table) -> bool:
    """Equal tables, a NaN equal to a NaN (an element never set: a float's
    default), which ``Table.equals`` does not grant."""
    if a.schema != b.schema or a.num_rows != b.num_rows:
        return False
    for x, y in zip(a.columns, b.columns, strict=True):
        for u, v in zip(x.to_pylist(), y.to_pylist(), strict=True):
            if u != v and not (isinstance(u, float) and isinstance(v, float) and u != u and v != v):
                return False
    return True


def _write(d: Path, loops: range) -> Path:
    w = ArchiveWriter(MISSION, LAYOUT, d)
    feed(w, DataVector(LAYOUT), loops)
    w.close()
    return d


@pytest.fixture
def pair(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path]:
    """Run 7, loops 1..300: stored whole (``ref``) and in groups of G."""
    ref = _write(tmp_path / "ref", range(1, 301))
    monkeypatch.setattr(store, "GROUP_COLUMNS", G)
    return _write(tmp_path / "wide", range(1, 301)), ref


def test_a_wide_run_is_stored_in_groups_of_at_most_group_columns(pair: tuple[Path, Path]) -> None:
    wide, ref = pair
    assert store.read_run(wide, 7).group_columns == G  # type: ignore[union-attr]
    assert store.read_run(ref, 7).group_columns == 1024  # type: ignore[union-attr]
    (part,) = store.parquet_files(wide, "tm", 7)
    groups = store.column_groups(LAYOUT, G)
    assert [len(g) for g in groups] == [G, G, len(NAMES) - 2 * G]
    for k, g in enumerate(groups):
        schema = pq.read_schema(store.group_path(part, k))
        head = ["loop", "t_ns", "rx_ns"] if k == 0 else []
        assert schema.names == head + g
    assert sorted(p.name for p in part.parent.iterdir()) == [
        "part-000000.g1.parquet",
        "part-000000.g2.parquet",
        "part-000000.parquet",
    ]
    (one,) = store.parquet_files(ref, "tm", 7)
    assert len(pq.read_schema(one).names) == 3 + len(NAMES)  # stored whole (1024 then)


@pytest.mark.parametrize(
    "q",
    [
        Query(NAMES[150]),  # one element of group 2: group 0 and 2 read
        Query(f"{NAMES[3]},{NAMES[70]},{NAMES[180]}", run=7, start="loop:20", end="loop:250"),
        Query("apogee_target_m,cn_state", run=7, start="1", end="2.5"),
        Query(f"{NAMES[130]},cn_state", run=7, every="1s", agg=["min", "max", "mean"]),
    ],
)
def test_every_answer_equals_the_whole_files(pair: tuple[Path, Path], q: Query) -> None:
    wide, ref = pair
    with Archive(MISSION, wide) as a, Archive(MISSION, ref) as b:
        got, want = a.query(q), b.query(q)
        assert got.num_rows > 0 and _same(got, want)
        assert a.problems == []


def test_a_crash_between_the_renames_is_recovered_from_the_raw_segments(
    pair: tuple[Path, Path],
) -> None:
    """Group 0's file lost (the crash came after its groups' renames): the
    group files left alone are removed, and the rows decoded again from the
    raw segments, in groups, each loop once."""
    wide, ref = pair
    (part,) = store.parquet_files(wide, "tm", 7)
    part.unlink()
    info = store.read_run(wide, 7)
    assert info is not None
    info.outcome, info.loops = "open", 0
    store.write_run(wide, info)
    q = Query(f"cn_state,{NAMES[100]},{NAMES[170]}", run=7)
    with Archive(MISSION, wide) as a, Archive(MISSION, ref) as b:
        assert _same(a.query(q), b.query(q)) and a.run(7).loops == 300
    names = sorted(p.name for p in part.parent.iterdir())
    assert names == ["part-000000.g1.parquet", "part-000000.g2.parquet", "part-000000.parquet"]


def test_a_missing_group_file_skips_its_part_with_a_note(pair: tuple[Path, Path]) -> None:
    wide, _ = pair
    (part,) = store.parquet_files(wide, "tm", 7)
    store.group_path(part, 2).unlink()
    with Archive(MISSION, wide, recover=False) as a:
        assert a.query(Query(NAMES[150], run=7)).num_rows == 0
        assert len(a.problems) == 1 and "skipped" in a.problems[0]
        # Group 0 and 1 are whole: their elements are still there.
        assert a.query(Query(f"cn_state,{NAMES[70]}", run=7)).num_rows == 300


def test_merge_writes_groups_too(pair: tuple[Path, Path], tmp_path: Path) -> None:
    wide, ref = pair
    c = tmp_path / "c"
    got = store.merge(c, ref, LAYOUT, MISSION.mission, MISSION.vehicle, print)
    assert [(m.run, m.rows) for m in got] == [(7, 300)]
    assert store.read_run(c, 7).group_columns == G  # type: ignore[union-attr]
    q = Query(f"{NAMES[0]},{NAMES[180]}", run=7)
    with Archive(MISSION, c) as a, Archive(MISSION, wide) as b:
        assert _same(a.query(q), b.query(q))
