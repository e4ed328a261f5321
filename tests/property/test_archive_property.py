"""Property: the archive's queries and aggregations equal a reference
computed from the raw frames that went in (gaps, repeats and all)."""

from __future__ import annotations

import random
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from zplatform.archive import Archive, ArchiveWriter, Query
from zplatform.config import Mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import ArchiveError
from zplatform.mission.load import load_mission

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_800_000_000_000_000_000
PERIOD = 10_000_000
N = 3000


@pytest.fixture(scope="module")
def archived() -> Iterator[tuple[Archive, dict[int, tuple[int, float, int]]]]:
    """An archive of run 7 (loops 1..N less some, a few sent twice, in
    batches of any order within a batch's neighbourhood) and the reference
    ``{loop: (t_ns, apogee_target_m as f32, cn_cmd_rejects)}``."""
    mission: Mission = load_mission(ROOT / "configs" / "flight.yaml", code=False)
    layout = Layout.for_node(mission, "cn")
    rnd = random.Random(28)
    ref: dict[int, tuple[int, float, int]] = {}
    with tempfile.TemporaryDirectory() as d:
        w = ArchiveWriter(mission, layout, d)
        dv = DataVector(layout)
        loops = [i for i in range(1, N + 1) if rnd.random() > 0.1]  # a tenth never came
        loops += rnd.sample(loops, 200)  # and some came twice (a gap fill, a second copy)
        for k, i in enumerate(loops):
            t = T0 + i * PERIOD
            if i not in ref:
                v = float(np.float32(rnd.uniform(-1e4, 1e4)))
                ref[i] = (t, v, rnd.randrange(0, 2**32))
            t, v, c = ref[i]
            dv.set("cn_loop", i)
            dv.set("cn_epoch", 7)
            dv.set("cn_time_ns", t)
            dv.set("apogee_target_m", v)
            dv.set("cn_cmd_rejects", c)
            w.snapshot(t + 1, dv)
            if k % 500 == 0:
                assert w.flush()
        w.close()
        with Archive(mission, d) as a:
            yield a, ref


def _time(text: str, start_ns: int) -> int:
    return start_ns + round(float(text) * 1e9)


@given(
    lo=st.integers(0, N + 10),
    span=st.integers(-5, N),
    as_seconds=st.booleans(),
)
def test_a_range_query_returns_exactly_the_loops_in_range(
    archived: tuple[Archive, dict[int, tuple[int, float, int]]],
    lo: int,
    span: int,
    as_seconds: bool,
) -> None:
    a, ref = archived
    start_ns = ref[min(ref)][0]
    hi = lo + span
    if as_seconds:
        s, e = f"{(lo - 1) * PERIOD / 1e9:.2f}", f"{(hi - 1) * PERIOD / 1e9:.2f}"
        t_lo, t_hi = _time(s, start_ns), _time(e, start_ns)
        want = [i for i in sorted(ref) if t_lo <= ref[i][0] <= t_hi]
    else:
        s, e = f"loop:{lo}", f"loop:{max(hi, 0)}"
        want = [i for i in sorted(ref) if lo <= i <= max(hi, 0)]
    try:
        t = a.query(Query("apogee_target_m,cn_cmd_rejects", run=7, start=s, end=e))
    except ArchiveError as exc:  # only a reversed range may be refused
        assert "reversed" in str(exc) and span < 0
        return
    assert t.column("loop").to_pylist() == want
    assert t.column("apogee_target_m").to_pylist() == [ref[i][1] for i in want]
    assert t.column("cn_cmd_rejects").to_pylist() == [ref[i][2] for i in want]


@given(
    every_ms=st.sampled_from([10, 100, 250, 1000, 7000, 60_000]),
    lo=st.integers(1, N),
    span=st.integers(0, N),
    aggs=st.lists(
        st.sampled_from(["min", "max", "mean", "first", "last", "count"]),
        min_size=1,
        max_size=6,
        unique=True,
    ),
)
def test_aggregates_equal_the_reference(
    archived: tuple[Archive, dict[int, tuple[int, float, int]]],
    every_ms: int,
    lo: int,
    span: int,
    aggs: list[str],
) -> None:
    a, ref = archived
    start_ns = ref[min(ref)][0]
    every = every_ms * 1_000_000
    q = Query(
        "apogee_target_m,cn_cmd_rejects",
        run=7,
        start=f"loop:{lo}",
        end=f"loop:{lo + span}",
        every=f"{every_ms}ms",
        agg=aggs,
    )
    t = a.query(q).to_pylist()
    buckets: dict[int, list[int]] = {}
    for i in sorted(ref):
        if lo <= i <= lo + span:
            b = start_ns + (ref[i][0] - start_ns) // every * every
            buckets.setdefault(b, []).append(i)
    assert [r["bucket_ns"] for r in t] == sorted(buckets)
    for row in t:
        loops = buckets[row["bucket_ns"]]
        for col, k in (("apogee_target_m", 1), ("cn_cmd_rejects", 2)):
            vals = [ref[i][k] for i in loops]
            want = {
                "min": min(vals),
                "max": max(vals),
                "mean": pytest.approx(sum(vals) / len(vals), rel=1e-9, abs=1e-9),
                "first": vals[0],
                "last": vals[-1],
                "count": len(vals),
            }
            for agg in aggs:
                assert row[f"{col}_{agg}"] == want[agg], (col, agg)
