"""Tests of zplatform.telemetry.logs: the CSV log format of docs/architecture.md#files."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from zplatform import DataVector, DataVectorError, Layout, decode_mission
from zplatform.telemetry.logs import (
    MAX_ARRAY_COLUMNS,
    CsvLogger,
    EventWriter,
    csv_columns,
    read_csv,
)
from zplatform.telemetry.records import EventRecord

MISSION = """
mission: tmtest
nodes: {cn: {}, dn0: {}}
state_machine:
  initial: IDLE
  states: {IDLE: {}, RUN: {}}
regions:
  cn:
    - {name: flag, type: bool}
    - {name: count, type: i32, initial: -7}
    - {name: big, type: u64}
    - {name: x64, type: f64}
    - {name: x32, type: f32}
    - {name: vec, type: "f32[3]"}
    - {name: sixteen, type: "u8[16]"}
    - {name: blob, type: "u8[17]"}
    - {name: mode, enum: ["OFF", LOW, HIGH], initial: LOW}
  cn_to_dn0:
    - {name: cmd, type: bool}
  dn0_to_cn:
    - {name: fb, type: bool}
"""


@pytest.fixture
def dv() -> DataVector:
    return DataVector(Layout.for_node(decode_mission(MISSION), "cn"))


def one_row(dv: DataVector, t: int = 5) -> dict[str, str]:
    buf = io.StringIO()
    CsvLogger(buf, dv.layout).write(t, dv)
    buf.seek(0)
    rows = read_csv(buf)
    assert len(rows) == 1
    return rows[0]


def test_header_lists_elements_in_order_expands_small_arrays_omits_large(dv: DataVector) -> None:
    cols = csv_columns(dv.layout)
    assert cols[0] == "rx_time_ns"
    assert cols[1:4] == ["cn_loop", "cn_time_ns", "cn_state"]
    i = cols.index("x32")
    assert cols[i + 1 : i + 4] == ["vec[0]", "vec[1]", "vec[2]"]
    assert [c for c in cols if c.startswith("sixteen")] == [f"sixteen[{k}]" for k in range(16)]
    assert MAX_ARRAY_COLUMNS == 16
    assert not any(c.startswith("blob") for c in cols)
    # region order: cn, cn_to_dn0, dn0_to_cn
    assert cols.index("mode") < cols.index("cmd") < cols.index("dn0_loop") < cols.index("fb")
    buf = io.StringIO()
    log = CsvLogger(buf, dv.layout)
    assert log.columns == cols
    assert buf.getvalue() == ",".join(cols) + "\n"


def test_values_are_formatted_per_type(dv: DataVector) -> None:
    dv.set("flag", True)
    dv.set("big", 2**64 - 1)
    dv.set("x64", 0.1)
    dv.set("x32", 0.1)
    dv.set("vec", [1.5, -2.0, 3.25])
    dv.handle("sixteen").get()[:] = np.arange(16)
    dv.handle("blob").get()[:] = 9
    dv.set("cn_state", "RUN")
    row = one_row(dv, t=123)
    assert row["rx_time_ns"] == "123"
    assert row["flag"] == "1" and row["cmd"] == "0"
    assert row["count"] == "-7"
    assert row["big"] == "18446744073709551615"
    assert row["x64"] == "0.1"
    assert row["x32"] == "0.1"  # shortest text that reads back as the same f32
    assert [row[f"vec[{k}]"] for k in range(3)] == ["1.5", "-2.0", "3.25"]
    assert [row[f"sixteen[{k}]"] for k in range(16)] == [str(k) for k in range(16)]
    assert row["mode"] == "LOW"  # enums by name
    assert row["cn_state"] == "RUN"
    assert row["cn_cmd_status"] == "NONE"
    assert "9" not in [row.get("blob"), row.get("blob[0]")]


def test_enum_value_without_a_name_is_written_as_its_number(dv: DataVector) -> None:
    dv.handle("mode").set(9)
    assert one_row(dv)["mode"] == "9"


F64 = [0.1, 1 / 3, -1e-300, 1e300, 5e-324, 2.0**53 + 1, -0.0, 123456789.123456789]


@pytest.mark.parametrize("v", F64)
def test_f64_round_trips_exactly(dv: DataVector, v: float) -> None:
    dv.set("x64", v)
    text = one_row(dv)["x64"]
    assert float(text) == v and math.copysign(1, float(text)) == math.copysign(1, v)


F32 = [0.1, 1 / 3, 3.4028234663852886e38, 1.17549435e-38, 1e-45, 16777217.0, -2.5e-7, 1e20]


@pytest.mark.parametrize("v", F32)
def test_f32_round_trips_exactly(dv: DataVector, v: float) -> None:
    dv.set("x32", v)
    stored = dv.get("x32")
    text = one_row(dv)["x32"]
    assert np.float32(float(text)) == np.float32(stored)
    assert len(text) <= 16


@pytest.mark.parametrize(("v", "text"), [(math.nan, "nan"), (math.inf, "inf"), (-math.inf, "-inf")])
def test_non_finite_floats(dv: DataVector, v: float, text: str) -> None:
    dv.set("x64", v)
    dv.set("x32", v)
    row = one_row(dv)
    assert row["x64"] == text and row["x32"] == text


def test_file_target_context_manager_and_rows(dv: DataVector, tmp_path: Path) -> None:
    p = tmp_path / "tm.csv"
    with CsvLogger(p, dv.layout) as log:
        for k in range(3):
            dv.set("cn_loop", k)
            log.write(1000 + k, dv)
        assert log.rows == 3
    rows = read_csv(p)
    assert [r["cn_loop"] for r in rows] == ["0", "1", "2"]
    assert [r["rx_time_ns"] for r in rows] == ["1000", "1001", "1002"]
    data = p.read_bytes()
    assert b"\r" not in data and data.endswith(b"\n")
    log.close()  # idempotent


def test_stream_target_is_not_closed(dv: DataVector) -> None:
    buf = io.StringIO()
    with CsvLogger(buf, dv.layout) as log:
        log.write(0, dv)
    assert not buf.closed


def test_other_layout_is_refused(dv: DataVector) -> None:
    other = DataVector(Layout.for_node(decode_mission(MISSION.replace("flag", "flog")), "cn"))
    log = CsvLogger(io.StringIO(), dv.layout)
    with pytest.raises(DataVectorError, match="not the logger's"):
        log.write(0, other)


def test_same_layout_from_another_build_is_accepted(dv: DataVector) -> None:
    twin = DataVector(Layout.for_node(decode_mission(MISSION), "cn"))
    log = CsvLogger(io.StringIO(), dv.layout)
    log.write(0, twin)


def test_rows_are_identical_for_identical_vectors(dv: DataVector) -> None:
    twin = DataVector(Layout.for_node(decode_mission(MISSION), "cn"))
    for v in (dv, twin):
        v.set("x32", 0.3)
        v.set("mode", "HIGH")
    assert one_row(dv) == one_row(twin)


def test_one_unpack_covers_every_column(dv: DataVector) -> None:
    log = CsvLogger(io.StringIO(), dv.layout)
    n_values = len(log._struct.unpack_from(dv.buf, 0))
    assert n_values == len(log.columns) - 1
    assert log._struct.size <= dv.layout.size


# ------------------------------------------------- a log reopened (station restart)


def _log_rows(dv: DataVector, p: Path, loops: range, **kw: Any) -> CsvLogger:
    with CsvLogger(p, dv.layout, **kw) as log:
        for k in loops:
            dv.set("cn_loop", k)
            log.write(1000 + k, dv)
    return log


def test_an_appending_log_keeps_the_rows_before_it_under_one_header(
    dv: DataVector, tmp_path: Path
) -> None:
    """A restarted station's CSV: the earlier process's rows stay, the new
    ones follow under the one header (``plot`` reads the whole), and the
    torn row a killed process left is cut off, not glued to the next."""
    p = tmp_path / "telemetry.csv"
    _log_rows(dv, p, range(3), append=True)  # no file yet: written with its header
    with p.open("a") as f:
        f.write("1003,3,17")  # killed mid-row: no newline
    log = _log_rows(dv, p, range(4, 6), append=True)
    assert log.path == p
    assert [r["cn_loop"] for r in read_csv(p)] == ["0", "1", "2", "4", "5"]
    assert p.read_text().count("rx_time_ns") == 1
    _log_rows(dv, p, range(6, 7))  # without append: written anew, as every --log file is
    assert [r["cn_loop"] for r in read_csv(p)] == ["6"]


def test_an_appending_log_of_another_layout_goes_to_a_numbered_file(
    dv: DataVector, tmp_path: Path
) -> None:
    """The mission changed between two runs of a station: the old CSV is
    left as it was; the new layout's rows go to ``telemetry.1.csv``, and
    on to it again on the next restart."""
    p = tmp_path / "telemetry.csv"
    other = DataVector(Layout.for_node(decode_mission(MISSION.replace("flag", "flog")), "cn"))
    _log_rows(other, p, range(2), append=True)
    before = p.read_bytes()
    assert _log_rows(dv, p, range(2, 4), append=True).path == tmp_path / "telemetry.1.csv"
    assert _log_rows(dv, p, range(4, 5), append=True).path == tmp_path / "telemetry.1.csv"
    assert p.read_bytes() == before
    assert [r["cn_loop"] for r in read_csv(tmp_path / "telemetry.1.csv")] == ["2", "3", "4"]
    # A header cut short (killed before its first row was written): rewritten.
    (tmp_path / "t2.csv").write_text("rx_time_ns,cn_lo")
    _log_rows(dv, tmp_path / "t2.csv", range(1), append=True)
    assert [r["cn_loop"] for r in read_csv(tmp_path / "t2.csv")] == ["0"]


def test_an_appending_event_log_keeps_the_events_before_it(tmp_path: Path) -> None:
    p = tmp_path / "events.jsonl"

    def rec(seq: int) -> EventRecord:
        return EventRecord(seq, "cn", seq, seq, "INFO", "loop_started", f"event {seq}")

    with EventWriter(p, append=True) as w:
        w.write(rec(1))
    with p.open("a") as f:
        f.write('{"rx_time_ns": 2, "node"')  # killed mid-line
    with EventWriter(p, append=True) as w:
        w.write(rec(3))
        assert w.count == 1
    assert [json.loads(line)["seq"] for line in p.read_text().splitlines()] == [1, 3]
    with EventWriter(p) as w:  # without append: written anew
        w.write(rec(4))
    assert [json.loads(line)["seq"] for line in p.read_text().splitlines()] == [4]


def test_a_grounds_log_has_each_row_on_disk_as_it_is_taken(dv: DataVector, tmp_path: Path) -> None:
    """A ground or station killed with SIGKILL loses no row it took: the
    ground's log flushes each one (read here before the log is closed)."""
    from zplatform.ground.logger import TelemetryLog

    p = tmp_path / "tm.csv"
    log = TelemetryLog.beside(dv.layout, p)
    for k in range(3):
        dv.set("cn_loop", k)
        log.snapshot(1000 + k, dv)
        assert [r["cn_loop"] for r in read_csv(p)] == [str(i) for i in range(k + 1)]
    log.close()


def test_a_grounds_log_on_a_full_disk_counts_what_it_loses_and_goes_on(
    dv: DataVector, caplog: pytest.LogCaptureFixture
) -> None:
    """/dev/full refuses every write (ENOSPC): the ground's receive path
    never sees the error; each row lost is counted, the spell logged once."""
    from zplatform.core.events import EventLog
    from zplatform.ground.logger import TelemetryLog

    events = EventLog("gn")
    log = TelemetryLog(dv.layout, "/dev/full", "/dev/full")
    for k in range(3):
        dv.set("cn_loop", k)
        log.snapshot(1000 + k, dv)
        log.tick(1000 + k, events)
    log.close()
    assert log.errors >= 3
    told = [r for r in caplog.records if "cannot be written" in r.getMessage()]
    assert len(told) == 1
    # Evented once for the spell, for the operator's console.
    (e,) = events.drain()
    assert e.id == "ground_log_failed" and "/dev/full" in e.text and "No space" in e.text


def test_a_grounds_log_that_recovers_says_so_once_with_what_it_lost(
    dv: DataVector, tmp_path: Path
) -> None:
    """A spell of failed writes, then a disk that takes them again: one
    ground_log_failed, then one ground_log_resumed with the count lost."""
    from zplatform.core.events import EventLog
    from zplatform.ground.logger import TelemetryLog

    events = EventLog("gn")
    log = TelemetryLog(dv.layout, tmp_path / "tm.csv", None)
    csv = log._csv
    assert csv is not None
    real = csv.write

    def full(*args: object) -> None:
        raise OSError(28, "No space left on device")

    csv.write = full  # type: ignore[method-assign]
    for k in range(4):
        log.snapshot(1000 + k, dv)
        log.tick(1000 + k, events)
    csv.write = real  # type: ignore[method-assign]
    log.snapshot(2000, dv)
    log.tick(2000, events)
    log.snapshot(2001, dv)
    log.tick(2001, events)
    log.close()
    got = [(e.id, e.text) for e in events.drain()]
    assert [i for i, _ in got] == ["ground_log_failed", "ground_log_resumed"], got
    assert "4 row(s) or event(s) lost from it so far" in got[1][1]


def test_a_full_csv_beside_an_events_file_that_takes_writes_is_one_spell(
    dv: DataVector, tmp_path: Path
) -> None:
    """Each file has its own spell: the events file taking its writes does
    not end the CSV's (before, one flag for both ended and started a spell
    at every row: an event pair per snapshot on the console)."""
    from zplatform.core.events import EventLog
    from zplatform.ground.logger import TelemetryLog

    events = EventLog("gn")
    log = TelemetryLog(dv.layout, tmp_path / "tm.csv", tmp_path / "tm.events.jsonl")
    csv = log._csv
    assert csv is not None

    def full(*args: object) -> None:
        raise OSError(28, "No space left on device")

    csv.write = full  # type: ignore[method-assign]
    for k in range(5):
        log.snapshot(1000 + k, dv)
        log.event(EventRecord(1000 + k, "cn", k, k, "INFO", "cmd_accepted", f"ev {k}"))
        log.tick(1000 + k, events)
    log.close()
    assert [e.id for e in events.drain()] == ["ground_log_failed"]
    assert log.errors == 5 and log.event_count == 5
