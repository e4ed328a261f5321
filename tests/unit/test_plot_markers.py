"""Telemetry plots: markers for state changes and commands; bools and enums as steps."""

from __future__ import annotations

from pathlib import Path

import pytest

from zplatform.telemetry import Marker, events_path, plot_markers, plot_telemetry


def _rows() -> list[dict[str, str]]:
    base = 1_000_000_000
    states = ["A"] * 3 + ["B"] * 4 + ["C"] * 3
    cmd = ["NONE"] * 2 + ["LAUNCH"] * 8
    seq = ["0"] * 2 + ["1"] * 8
    status = ["NONE"] * 2 + ["ACCEPTED"] * 8
    led = ["1", "1", "0", "0", "1", "1", "0", "0", "0", "1"]
    return [
        {
            "rx_time_ns": str(base + i * 100_000_000),
            "cn_state": states[i],
            "cn_cmd": cmd[i],
            "cn_cmd_seq": seq[i],
            "cn_cmd_status": status[i],
            "led": led[i],
            "alt": str(i * 1.5),
        }
        for i in range(10)
    ]


def test_markers_are_state_changes_and_command_verdicts() -> None:
    m = plot_markers(_rows())
    assert m == [
        Marker(0.2, "LAUNCH ACCEPTED", "command"),
        Marker(0.3, "B", "state"),
        Marker(0.7, "C", "state"),
    ]


def test_markers_without_the_columns_are_none() -> None:
    assert plot_markers([{"rx_time_ns": "1", "x": "2"}, {"rx_time_ns": "2", "x": "3"}]) == []
    assert plot_markers([]) == []


def test_plot_of_a_bool_an_enum_and_a_number_renders(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "p.png"
    markers = plot_telemetry(_rows(), ["cn_state", "led", "alt"], out, title="t")
    assert len(markers) == 3
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.stat().st_size > 5000


def test_events_path_is_beside_the_csv() -> None:
    assert events_path("tm.csv") == Path("tm.events.jsonl")
    assert events_path("/a/b/run.CSV") == Path("/a/b/run.events.jsonl")
    assert events_path("log") == Path("log.events.jsonl")
