"""What the ground archive costs and gives (``zplatform.archive``, issue 28).

An hour of the flight mission's telemetry at 100 Hz, synthesized in process:
the CN's Data Vector of a lockstep flight (``configs/flight.commands``: ARM,
LAUNCH, the flight to landing), captured once for :data:`CAPTURE` loops and
replayed loop after loop with the loop number and time advanced, fed to an
:class:`~zplatform.archive.ArchiveWriter` as fast as its thread takes it
(``flush`` every 1,000 snapshots, so none is dropped). Reported:

* ``ingest``: snapshots archived per second of wall time, and that as a
  multiple of real time (100 Hz); the receive path's cost, ``snapshot()``'s
  p50/p99 per call; snapshots dropped (must be 0);
* ``size``: bytes per hour of the Parquet files, of the raw segments and of
  the ground's CSV log for the same rows (the CSV of the first
  :data:`CSV_ROWS` rows, scaled);
* ``query_one``: one element over the whole hour (every row), and
  ``query_ten_1s``: ten elements aggregated to 1 s buckets (min, max, mean)
  over the hour, each timed :data:`QUERY_ROUNDS` times after one warm-up.

With ``--wide N`` also a layout of N more f32 scalars (:func:`wide`), each
snapshot new random values: ``wide_grouped``, stored in file groups of
:data:`zplatform.archive.store.GROUP_COLUMNS` elements and offered at
:data:`WIDE_HZ` (paced, as a ground receives them: the snapshots archived
and dropped, counted; the writer's CPU per snapshot), ``wide_grouped_max``
the same as fast as the writer takes them (``flush`` every 100), and
``wide_whole``, every column in one file (:data:`WIDE_WHOLE_ROWS`, as fast
as taken): ingest rate, and one element queried over the rows from a new
:class:`Archive` and from one kept.

Run ``python -m bench.archive [--quick] [--wide N] [--json PATH]``
(``--quick``: six minutes of telemetry); results go to
``bench/results/archive.json``.
"""

from __future__ import annotations

import io
import tempfile
import time
from pathlib import Path

from bench.common import bench_argparser, summarize, write_result
from zplatform import LockstepRunner, load_mission
from zplatform.archive import Archive, ArchiveWriter, Query
from zplatform.archive.store import du
from zplatform.config.checks import archive_sizing
from zplatform.control.uplink import load_commands
from zplatform.core.datavector import DataVector, Layout
from zplatform.telemetry.logs import CsvLogger

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "configs" / "flight.yaml"
CAPTURE = 6000
"""Loops of the lockstep flight captured (60 s: the whole flight, landed)."""
QUICK_S = 360
"""Seconds of telemetry ``--quick`` synthesizes."""
CSV_ROWS = 30_000
QUERY_ROUNDS = 5
WIDE_ROWS = 3000
"""Snapshots of ``--wide``'s grouped layout (30 s at 100 Hz: 1.2 GB of vectors
at 100,000 elements, two row groups of 1,340 and the rest)."""
WIDE_WHOLE_ROWS = 300
WIDE_HZ = 100.0
TEN = (
    "apogee_pred_m,nav_h_m,nav_v_mps,cn_state,dn0_state,dn1_state,cn_cpu_pct,"
    "apogee_target_m,main_deploy_m,airbrake_rate_ps"
)


def capture(loops: int) -> list[bytes]:
    """The CN's vector after each of ``loops`` loops of a lockstep flight."""
    m = load_mission(MISSION)
    r = LockstepRunner(m, commands=load_commands(ROOT / "configs" / "flight.commands"))
    out = []
    for _ in range(loops):
        r.step()
        out.append(bytes(r.control.dv.buf))
    return out


def wide(n_elements: int, rows: int, group_columns: int, hz: float) -> dict[str, float | int]:
    """A mission of ``n_elements`` more f32 scalars (a wide region): ``rows``
    snapshots of new random values archived with ``group_columns`` elements
    per file group (0: one file of every column), offered at ``hz`` (paced;
    0: as fast as the writer takes them, ``flush`` every 100), then one
    element (the last) queried over them all :data:`QUERY_ROUNDS` times
    after one warm-up, in a new :class:`Archive` each (the footers parsed
    each time: a first ask) and in one kept (:data:`QUERY_ROUNDS` more)."""
    import numpy as np

    from bench.cluster import make_mission

    extra = {"cn": [{"name": f"w{i}", "type": "f32"} for i in range(n_elements)]}
    with tempfile.TemporaryDirectory() as tmp:
        m = load_mission(make_mission(Path(tmp) / "wide.yaml", n_dn=1, extra=extra), code=False)
        layout = Layout.for_node(m, "cn")
        dv = DataVector(layout)
        rng = np.random.default_rng(1)
        buf = np.frombuffer(dv.buf, np.uint8)
        root = Path(tmp) / "wide"
        w = ArchiveWriter(m, layout, root, group_columns=group_columns)
        t0 = 1_800_000_000_000_000_000
        start = time.perf_counter()
        cpu0 = time.process_time()
        for i in range(1, rows + 1):
            buf[:] = np.frombuffer(rng.bytes(layout.size), np.uint8)
            for n, v in (("cn_loop", i), ("cn_time_ns", t0 + i * 10**7), ("cn_epoch", 1)):
                dv.set(n, v)
            dv.set("cn_state", 0)
            if hz:
                ahead = start + i / hz - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)  # the next snapshot's arrival
            w.snapshot(t0 + i * 10**7 + 1000, dv)
            if not hz and i % 100 == 0:
                w.flush(600.0)
        w.close(600.0)
        ingest = time.perf_counter() - start
        cpu = time.process_time() - cpu0
        stats = w.stats()
        q = Query(f"w{n_elements - 1}", run=1)
        cold: list[int] = []
        warm: list[int] = []
        for k in range(QUERY_ROUNDS + 1):
            c0 = time.perf_counter_ns()
            with Archive(m, root) as a:
                assert a.query(q).num_rows == stats["rows"]
            if k:
                cold.append(time.perf_counter_ns() - c0)
        with Archive(m, root) as a:
            for k in range(QUERY_ROUNDS + 1):
                c0 = time.perf_counter_ns()
                assert a.query(q).num_rows == stats["rows"]
                if k:
                    warm.append(time.perf_counter_ns() - c0)
        return {
            "elements": len(layout.elements),
            "vector_bytes": layout.size,
            "offered_hz": hz,
            "snapshots": rows,
            "archived": stats["rows"],
            "dropped": stats["dropped"],
            "lost": stats["lost"],
            "group_columns": group_columns,
            "ingest_rows_per_s": round(stats["rows"] / ingest, 1),
            "cpu_ms_per_snapshot": round(cpu / rows * 1e3, 2),
            "tm_bytes": du(root / "tm"),
            "raw_bytes": du(root / "raw"),
            "query_one_new_archive_p50_ms": round(sorted(cold)[len(cold) // 2] / 1e6, 1),
            "query_one_kept_archive_p50_ms": round(sorted(warm)[len(warm) // 2] / 1e6, 1),
        }


def main() -> None:
    ap = bench_argparser(__doc__.splitlines()[0])
    ap.add_argument(
        "--wide",
        type=int,
        default=0,
        metavar="N",
        help="also a wide layout: N more f32 scalars, WIDE_ROWS snapshots stored in file "
        "groups, offered at WIDE_HZ and as fast as taken (wide_grouped, wide_grouped_max), "
        "and WIDE_WHOLE_ROWS stored whole (wide_whole)",
    )
    args = ap.parse_args()
    seconds = QUICK_S if args.quick else 3600
    m = load_mission(MISSION, code=False)
    layout = Layout.for_node(m, "cn")
    hz = m.loop_hz / m.telemetry_divisor
    rows = int(seconds * hz)
    frames = capture(CAPTURE)
    dv = DataVector(layout)
    loop_h, time_h, epoch_h = (dv.handle(n) for n in ("cn_loop", "cn_time_ns", "cn_epoch"))
    t0 = 1_800_000_000_000_000_000
    period = int(1e9 / hz)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "flight"
        w = ArchiveWriter(m, layout, root)
        calls: list[int] = []
        clock = time.perf_counter_ns
        start = time.perf_counter()
        for i in range(1, rows + 1):
            dv.write_all(frames[(i - 1) % CAPTURE])
            loop_h.set(i)
            time_h.set(t0 + i * period)
            epoch_h.set(1)
            c0 = clock()
            w.snapshot(t0 + i * period + 1000, dv)
            calls.append(clock() - c0)
            if i % 1000 == 0:
                w.flush(60.0)
        w.close(600.0)
        wall = time.perf_counter() - start
        stats = w.stats()
        tm, raw = du(root / "tm"), du(root / "raw")
        csv = io.StringIO()
        logger = CsvLogger(csv, layout)
        n_csv = min(CSV_ROWS, rows)
        for i in range(1, n_csv + 1):
            dv.write_all(frames[(i - 1) % CAPTURE])
            loop_h.set(i)
            time_h.set(t0 + i * period)
            epoch_h.set(1)
            logger.write(t0 + i * period + 1000, dv)
        csv_per_hour = len(csv.getvalue()) / n_csv * hz * 3600
        per_hour = 3600 / seconds
        one: list[int] = []
        ten: list[int] = []
        with Archive(m, root) as a:
            for k in range(QUERY_ROUNDS + 1):
                c0 = clock()
                t = a.query(Query("nav_h_m", run=1))
                c1 = clock()
                g = a.query(Query(TEN, run=1, every="1s", agg=["min", "max", "mean"]))
                c2 = clock()
                assert t.num_rows == rows and g.num_rows == seconds
                if k:  # the first is the warm-up (files into the page cache)
                    one.append(c1 - c0)
                    ten.append(c2 - c1)
    recv = summarize(calls)
    recv.update(
        {
            "snapshots": rows,
            "archived": stats["rows"],
            "dropped": stats["dropped"],
            "errors": stats["errors"],
            "ingest_rows_per_s": round(rows / wall),
            "x_real_time": round(rows / wall / hz, 1),
        }
    )
    size = {
        "parquet_bytes_per_hour": round(tm * per_hour),
        "raw_bytes_per_hour": round(raw * per_hour),
        "csv_bytes_per_hour": round(csv_per_hour),
        "parquet_vs_csv": round(tm * per_hour / csv_per_hour, 4),
        "archive_vs_csv": round((tm + raw) * per_hour / csv_per_hour, 4),
    }
    extra = {}
    if args.wide:
        from zplatform.archive.store import GROUP_COLUMNS

        extra["wide_grouped"] = wide(args.wide, WIDE_ROWS, GROUP_COLUMNS, WIDE_HZ)
        extra["wide_grouped_max"] = wide(args.wide, WIDE_ROWS, GROUP_COLUMNS, 0)
        extra["wide_whole"] = wide(args.wide, WIDE_WHOLE_ROWS, 0, 0)
    write_result(
        "archive",
        {
            "mission": "flight",
            "seconds": seconds,
            "hz": hz,
            "vector_bytes": layout.size,
            "elements": len(layout.elements),
            "row_group_s": archive_sizing(m, layout.size).row_group_rows / hz,
            "file_s": m.archive.file_s,
        },
        {
            "ingest_snapshot_call": recv,
            "size": size,
            "query_one_element_hour": summarize(one),
            "query_ten_elements_1s_hour": summarize(ten),
            **extra,
        },
        args.json,
    )


if __name__ == "__main__":
    main()
