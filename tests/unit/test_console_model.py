"""The console's model without zenoh or a screen: fed snapshots, events, times."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("textual")

from zplatform import load_mission
from zplatform.console.model import (
    ConsoleModel,
    Limits,
    severity_rank,
    severity_style,
)
from zplatform.core.datavector import DataVector
from zplatform.core.events import Severity
from zplatform.errors import CommandError, DataVectorError
from zplatform.telemetry.records import CommandOutcome, EventRecord

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
MISSION = load_mission(CONFIGS / "recovery_igniter.yaml")
MS = 1_000_000


def _feed(model: ConsoleModel, loop: int, rx_ns: int) -> DataVector:
    dv = DataVector(model.layout)
    dv.set("cn_loop", loop)
    dv.set("cn_time_ns", loop * 10 * MS)
    model.on_snapshot(dv, rx_ns)
    return dv


def test_snapshot_is_copied_and_rate_is_measured() -> None:
    m = ConsoleModel(MISSION)
    for i in range(1, 101):
        dv = _feed(m, i, i * 10 * MS)
    dv.set("cn_loop", 999)  # the caller's vector; the model kept its own copy
    s = m.status()
    assert s.loop == 100 and s.received == 100
    assert s.loop_hz == pytest.approx(100.0)
    assert s.state == "SAFE"
    assert m.region_rows()[0][0] == "cn"


def test_loss_of_signal_after_silence_and_back() -> None:
    m = ConsoleModel(MISSION, los_s=0.3)
    assert m.tick(0)  # nothing received yet: no signal
    _feed(m, 1, 1_000 * MS)
    assert not m.tick(1_200 * MS)
    assert m.tick(1_301 * MS)
    assert m.status().los
    assert [x.text for x in m.log][-1] == "LOSS OF SIGNAL"
    _feed(m, 2, 1_400 * MS)
    assert not m.tick(1_400 * MS)
    assert [x.text for x in m.log][-1] == "signal acquired"


def test_limits_from_caller_and_from_mission_field() -> None:
    m = ConsoleModel(MISSION, limits={"cn_loop": {"yellow": [None, 10], "red": [None, 20]}})
    _feed(m, 5, 0)
    assert dict((n, lv) for n, _, lv in m.region_rows()[0][1])["cn_loop"] == ""
    _feed(m, 15, 0)
    assert dict((n, lv) for n, _, lv in m.region_rows()[0][1])["cn_loop"] == "yellow"
    _feed(m, 25, 0)
    assert dict((n, lv) for n, _, lv in m.region_rows()[0][1])["cn_loop"] == "red"
    assert Limits.parse({"red": [-1, 1]}, "x").level(-2) == "red"
    with pytest.raises(DataVectorError, match=r"limits\.red"):
        Limits.parse({"red": 3}, "x")
    with pytest.raises(DataVectorError, match="no element"):
        ConsoleModel(MISSION, limits={"nope": {"red": [0, 1]}})


def test_events_by_severity_name_and_filter() -> None:
    m = ConsoleModel(MISSION)
    for i, sev in enumerate(Severity):
        m.on_event(EventRecord(0, "cn", i, 0, sev.name, "id", sev.name))
    assert [x.severity for x in m.events()] == [s.name for s in Severity]
    worst = max(Severity, key=lambda s: severity_rank(s.name))
    m.set_filter([worst.name])
    assert [x.severity for x in m.events()] == [worst.name]
    m.set_filter(["all"])
    assert len(m.events()) == len(Severity)
    with pytest.raises(CommandError, match="unknown severity"):
        m.set_filter(["LOUD"])
    # Old and new names both rank and colour.
    assert severity_rank("FATAL") == severity_rank("CRITICAL") > severity_rank("WARNING_LO")
    assert severity_rank("DIAGNOSTIC") == severity_rank("DEBUG") == 0
    assert severity_style("WARNING_HI") and severity_style("FATAL")


def test_completion_of_commands_and_elements() -> None:
    m = ConsoleModel(MISSION)
    assert m.complete("lau") == "launch"
    assert m.complete("fil") == "filter"
    some = m.writable[-1]
    assert m.complete(f"write {some[:-1]}") is not None
    assert (m.complete(f"write {some[:-1]}") or "").startswith("write ")
    assert m.complete("launch x") is None
    assert m.complete("") is None


@pytest.mark.parametrize("name", ["recovery_igniter.yaml", "led_test.yaml", "minimal.yaml"])
def test_write_completes_the_platforms_writable_elements_only(name: str) -> None:
    """The console's writable-element rule is the platform's one
    (zplatform.control.commands.writable_elements), whatever the mission."""
    from zplatform.control.commands import writable_elements

    m = load_mission(CONFIGS / name)
    model = ConsoleModel(m)
    assert model.writable == writable_elements(m)
    params = {p.name for p in m.params}
    for element in model.layout.elements:
        completed = model.complete(f"write {element}"[:-1])
        if completed == f"write {element}":
            assert element in model.writable and element not in params


def test_plot_series_keeps_a_window() -> None:
    m = ConsoleModel(MISSION, plot_window_s=1.0)
    m.set_plot(["cn_loop"])
    for i in range(1, 200):
        _feed(m, i, i * 10 * MS)
    xs, ys = m.plot_series()["cn_loop"]
    assert len(xs) == 20  # one point per 50 ms, one second kept
    assert ys[-1] >= 190
    with pytest.raises(DataVectorError):
        m.set_plot(["nope"])


def test_command_outcomes_show_with_their_reason() -> None:
    m = ConsoleModel(MISSION)
    why = "not allowed in state X"
    m.on_result(0, CommandOutcome("NOOP", 3, "REJECTED_NOT_ALLOWED", reason=why, reason_from="cn"))
    assert m.status().last_command == "NOOP #3: REJECTED_NOT_ALLOWED: not allowed in state X"
    assert [(x.severity, x.source) for x in m.log] == [("WARNING_HI", "cmd")]
    m.on_refusal(1, "LAUNCH", "not sent (ARM not accepted)")
    assert m.status().last_command == "LAUNCH: not sent (ARM not accepted)"


def test_one_value_formatter_serves_the_console_and_the_parameter_table(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """zplatform.telemetry.records.value_text spells values for both, each keeping its own
    spelling."""
    from zplatform.console import model as console_model
    from zplatform.telemetry.records import value_text

    # the parameter table's spelling (mission-file words, 7 digits)...
    assert [value_text(v) for v in (True, False, 1 / 3, 2.5, 7, "x")] == [
        "true",
        "false",
        "0.3333333",
        "2.5",
        "7",
        "x",
    ]
    # ...and the console's (telemetry CSV bits, 6 digits), from the same function
    assert [value_text(v, bools=("0", "1"), digits=6) for v in (True, False, 1 / 3)] == [
        "1",
        "0",
        "0.333333",
    ]
    m = ConsoleModel(MISSION)
    spec = m.layout.elements
    m.dv.set("cn_prm_unsaved", True)
    m.dv.set("cn_cpu_pct", 12.345678)
    called: list[object] = []

    def spy(v: object, **kw: object) -> str:
        called.append(v)
        return value_text(v, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(console_model, "value_text", spy)
    assert m.format_value(spec["cn_prm_unsaved"]) == "1"
    assert m.format_value(spec["cn_cpu_pct"]) == "12.3457"
    assert m.format_value(spec["cn_loop"]) == "0"
    assert len(called) == 3  # the console's values went through the shared formatter


def test_a_redundant_missions_header_says_who_commands_in_which_term() -> None:
    """The flight mission has a standby: the console's header and ``up``'s
    status line show the commander, its term and whether the standby is
    ready; a mission without one shows none of it."""
    from zplatform.ground.status import status_line

    flight = load_mission(CONFIGS / "flight.yaml")
    m = ConsoleModel(flight)
    dv = DataVector(m.layout)
    dv.set("cn_loop", 5)
    dv.set("cn_term", 2)
    dv.set("cn_commander", flight.control_nodes.index("cn_b"))
    dv.set("cn_standby_ready", False)
    m.on_snapshot(dv, 50 * MS)
    s = m.status()
    assert (s.commander, s.term, s.standby_ready) == ("cn_b", 2, False)
    line = status_line(flight, m.dv, None)
    assert "cn_b commands (term 2, NO STANDBY)" in line
    plain = ConsoleModel(MISSION)
    _feed(plain, 1, 10 * MS)
    assert plain.status().commander == ""
    assert "commands (term" not in status_line(MISSION, plain.dv, None)


def test_times_show_as_times_of_day_and_durations_never_raw_ns() -> None:
    from zplatform.telemetry.records import ns_text

    m = ConsoleModel(MISSION)
    spec = m.layout.elements
    t = (12 * 3600 + 3 * 60 + 10) * 10**9 + 123_456_789 + 20_000 * 86_400 * 10**9
    m.dv.set("cn_time_ns", t)
    m.dv.set("cn_time_in_state_ns", 2_500_000_000)
    assert m.format_value(spec["cn_time_ns"]) == "12:03:10.123"
    assert m.format_value(spec["cn_time_in_state_ns"]) == "2.500 s"
    assert [ns_text(v) for v in (0, 18_742, -5_706, 3_200_000)] == [
        "0",
        "18.7 us",
        "-5.7 us",
        "3.200 ms",
    ]


def test_before_the_run_is_learned_the_header_says_so() -> None:
    """A console whose link has not learned the vehicle's run shows nothing
    but that (zplatform.ground.link: nothing unverified is taken meanwhile)."""
    from zplatform.console.app import _status_text

    m = ConsoleModel(MISSION)
    m.waiting_for_run = True
    s = m.status()
    assert not s.connected and s.waiting_for_run
    assert "waiting for the vehicle's run" in _status_text(s).plain
    m.waiting_for_run = False
    assert "waiting for telemetry" in _status_text(m.status()).plain
