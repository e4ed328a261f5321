"""Monitors and responses (zplatform.control.monitors): each kind, persistence, states,
each response in the loop it trips, the config's errors with their YAML paths."""

from __future__ import annotations

import sys
import textwrap
from typing import Any

import pytest
import yaml

from zplatform import EV, ConfigError, ControlLogic, DataVector, EventLog, Layout, decode_mission
from zplatform.config import Mission
from zplatform.control.statemachine import StateMachine

BASE = """
mission: montest
nodes: {cn: {}}
regions:
  cn:
    - {name: x, type: f32, limits: {yellow: [-1, 1], red: [-2, 2]}}
    - {name: stamp, type: i64}
    - {name: n, type: u16}
    - {name: flag, type: bool}
    - {name: vec, type: "f32[2]"}
controllers:
  - {name: ctl, class: "stub_components:Idle", node: cn, initial_mode: enabled}
state_machine:
  initial: A
  states:
    A:
      transitions:
        - {element: cn_cmd, op: "==", value: ABORT, to: C}
        - {element: n, op: ">", value: 100, to: C}
    B:
      transitions:
        - {element: cn_cmd, op: "==", value: ABORT, to: C}
    C: {}
"""


def mission(*monitors: dict[str, Any]) -> Mission:
    raw = yaml.safe_load(BASE)
    raw["monitors"] = list(monitors)
    return decode_mission(yaml.safe_dump(raw))


class Rig:
    """The CN's loop, with the mission's elements set directly before each loop."""

    def __init__(self, *monitors: dict[str, Any]) -> None:
        self.m = mission(*monitors)
        self.cn = ControlLogic(self.m, keys=None, epoch=1)
        self.dv = self.cn.dv
        self.loop = 0

    def step(self, **values: Any) -> list[tuple[str, str]]:
        """One loop with ``values`` written first; returns its events (id, text)."""
        self.loop += 1
        t = self.loop * self.m.period_ns
        self.cn.begin(self.loop, t)
        for k, v in values.items():
            self.dv.set(k, v)
        self.cn.finish()
        return [(e.id, e.text) for e in self.cn.events.drain()]

    def ids(self, **values: Any) -> list[str]:
        return [i for i, _ in self.step(**values)]


# -- kinds ------------------------------------------------------------------------


def test_limit_trips_after_its_persistence_once_and_clears() -> None:
    r = Rig({"name": "hot", "element": "x", "kind": "limit", "lo": -5, "hi": 5, "persistence": 3})
    assert r.ids(x=6.0) == [] and r.ids(x=6.0) == []
    ev = r.step(x=7.5)
    assert ev == [("monitor_warning", "monitor hot: x = 7.5 outside [-5, 5] for 3 loops")]
    assert r.ids(x=9.0) == []  # tripped once, not every loop
    ev = r.step(x=0.0)
    assert ev == [("monitor_cleared", "monitor hot: clear (x = 7.5 outside [-5, 5] for 3 loops)")]
    assert r.ids(x=-6.0) == [] and r.ids(x=0.0) == [] and r.ids(x=-6.0) == []  # count restarts
    assert r.cn.monitors.tripped("hot") is False
    assert r.ids(x=float("nan")) == []  # NaN is inside every limit


def test_limit_on_a_band_uses_the_elements_limits_open_bounds() -> None:
    r = Rig(
        {"name": "red", "element": "x", "kind": "limit", "band": "red"},
        {"name": "low", "element": "n", "kind": "limit", "lo": 10},
    )
    assert r.ids(x=1.5, n=10) == []  # yellow, not red; n at its bound
    assert r.step(x=-2.5, n=9) == [
        ("monitor_warning", "monitor red: x = -2.5 outside [-2, 2]"),
        ("monitor_warning", "monitor low: n = 9 outside [10, open]"),
    ]


def test_stale_unchanged_counts_loops_without_a_change() -> None:
    r = Rig({"name": "frozen", "element": "flag", "kind": "stale", "unchanged_loops": 3})
    assert r.ids(flag=True) == [] and r.ids() == [] and r.ids() == []
    assert r.step() == [("monitor_warning", "monitor frozen: flag unchanged for 3 loops")]
    assert r.ids(flag=False) == ["monitor_cleared"]


def test_stale_age_is_armed_by_the_first_stamp_and_measured_in_cn_time() -> None:
    period = 10_000_000
    r = Rig({"name": "old", "element": "stamp", "kind": "stale", "max_age_ms": 25})
    for _ in range(10):  # never stamped: not this monitor's business
        assert r.ids() == []
    assert r.ids(stamp=11 * period) == []  # fresh (loop 11)
    assert r.ids() == [] and r.ids() == []  # 10 ms, 20 ms old
    ev = r.step()  # 30 ms old
    assert ev == [("monitor_warning", "monitor old: stamp is 30.0 ms old (at most 25 ms)")]
    assert r.ids(stamp=15 * period) == ["monitor_cleared"]


def test_rate_of_change_over_a_window() -> None:
    # 100 Hz, a window of 2 loops (20 ms): a change of 1.0 is 50/s.
    r = Rig({"name": "jump", "element": "x", "kind": "rate", "hi": 40, "window_loops": 2})
    events = [r.step(x=v) for v in (0.0, 0.0, 0.5, 1.0, 1.0)]
    # the window fills; 25/s; 50/s trips; 25/s clears
    assert events[:3] == [[], [], []]
    assert events[3] == [("monitor_warning", "monitor jump: x changes 50/s, outside [open, 40]/s")]
    assert [i for i, _ in events[4]] == ["monitor_cleared"]


def test_rate_reports_falls_against_its_low_bound() -> None:
    r = Rig({"name": "fall", "element": "x", "kind": "rate", "lo": -10})
    events = [r.ids(x=v) for v in (5.0, 5.0, 4.95, 4.8, 4.8)]
    # the window fills; 0/s; -5/s; -15/s trips; 0/s clears
    assert events == [[], [], [], ["monitor_warning"], ["monitor_cleared"]]


def test_a_monitor_runs_only_in_its_states() -> None:
    r = Rig({"name": "b_only", "element": "x", "kind": "limit", "hi": 1, "states": ["B"]})
    assert r.ids(x=5.0) == [] and r.ids(x=5.0) == []  # in A: never trips
    r.cn.statemachine.request(1, "test")
    assert r.ids(x=5.0) == ["state_change"]  # monitors run before the state machine
    assert r.cn.statemachine.state == "B"
    assert r.ids(x=5.0) == ["monitor_warning"]


# -- responses ----------------------------------------------------------------------


def test_fault_response_latches_in_the_loop_it_trips() -> None:
    r = Rig(
        {"name": "hot", "element": "x", "kind": "limit", "hi": 1, "response": "fault"},
        {
            "name": "stuck",
            "element": "n",
            "kind": "limit",
            "hi": 0,
            "response": "fault",
            "fault": "THREAD_STALLED",
        },
    )
    ev = r.step(x=3.0, n=1)
    assert ev == [
        ("fault", "fault MONITOR: monitor hot: x = 3 outside [open, 1]"),
        ("monitor_tripped", "monitor hot: x = 3 outside [open, 1]; fault MONITOR latched"),
        (
            "monitor_tripped",
            "monitor stuck: n = 1 outside [open, 0]; fault THREAD_STALLED not latched "
            "(MONITOR already is)",
        ),
    ]
    assert r.dv.get_name("cn_fault") == "MONITOR"


def test_transition_response_moves_the_state_in_the_same_loop() -> None:
    r = Rig(
        {
            "name": "go_b",
            "element": "x",
            "kind": "limit",
            "hi": 1,
            "response": "transition",
            "to": "B",
            "states": ["A"],
        }
    )
    ev = r.step(x=2.0)
    assert ev == [
        ("monitor_tripped", "monitor go_b: x = 2 outside [open, 1]; transition to B requested"),
        ("state_change", "state A -> B (monitor go_b)"),
    ]
    assert r.dv.get_name("cn_state") == "B"


def test_a_requested_transition_comes_after_abort_and_before_the_states_others() -> None:
    m = mission()

    def machine() -> tuple[StateMachine, DataVector, EventLog]:
        dv = DataVector(Layout.for_node(m, "cn"))
        events = EventLog("cn")
        sm = StateMachine(m, dv, events)
        sm.step(0)
        return sm, dv, events

    # Before the state's data transition (n > 100 -> C): the request wins.
    sm, dv, events = machine()
    dv.set("n", 200)
    sm.request(1, "monitor m")
    sm.step(10)
    assert sm.state == "B" and not sm.consumed_cmd
    # A request for the current state is no transition.
    sm.request(1, "monitor m")
    events.drain()
    sm.step(20)
    assert sm.state == "B" and not sm.changed and not events.drain()
    # An ABORT-class command's transition wins; the request is dropped.
    sm, dv, events = machine()
    dv.set("cn_cmd", "ABORT")
    sm.request(1, "monitor m")
    sm.step(10)
    assert sm.state == "C" and sm.consumed_cmd
    sm.step(20)
    assert sm.state == "C"


def test_safe_response_safes_the_controller_before_it_runs() -> None:
    r = Rig(
        {
            "name": "cut",
            "element": "flag",
            "kind": "stale",
            "unchanged_loops": 2,
            "response": "safe",
            "controller": "ctl",
        }
    )
    ran: list[str] = []
    ctl = r.cn.controllers.controllers[0]
    ctl.run_enabled = lambda t: ran.append("enabled")  # type: ignore[method-assign]
    ctl.run_safed = lambda t: ran.append("safed")  # type: ignore[method-assign]
    r.step(flag=True)
    r.step()
    ev = r.step()
    assert ev == [
        ("monitor_tripped", "monitor cut: flag unchanged for 2 loops; controller ctl safed")
    ]
    assert ran == ["enabled", "enabled", "safed"]
    assert r.dv.get_name("ctl_mode") == "safed"


def test_a_loop_without_trips_allocates_nothing_that_stays() -> None:
    r = Rig(
        {"name": "a", "element": "x", "kind": "limit", "band": "red"},
        {"name": "b", "element": "flag", "kind": "stale", "unchanged_loops": 1000},
        {"name": "c", "element": "stamp", "kind": "stale", "max_age_ms": 1e9},
        {"name": "d", "element": "x", "kind": "rate", "hi": 1e9, "window_loops": 4},
    )
    mon = r.cn.monitors
    for n in range(50):
        mon.step(n)
    before = sys.getallocatedblocks()
    for n in range(50, 5050):
        mon.step(n)
    assert sys.getallocatedblocks() - before < 20


# -- the config ---------------------------------------------------------------------

GOOD = {"name": "m", "element": "x", "kind": "limit", "hi": 1}


@pytest.mark.parametrize(
    ("monitor", "path", "words"),
    [
        ({**GOOD, "element": "xx"}, "$.monitors[0].element", "no element named 'xx'"),
        ({**GOOD, "element": "vec"}, "$.monitors[0].element", "is an array"),
        ({**GOOD, "element": "flag"}, "$.monitors[0].element", "needs a number"),
        ({**GOOD, "name": "Bad"}, "$.monitors[0].name", "[a-z]"),
        ({**GOOD, "kind": "fast"}, "$.monitors[0].kind", "Invalid enum value 'fast'"),
        ({**GOOD, "unchanged_loops": 3}, "$.monitors[0].unchanged_loops", "does not apply"),
        ({**GOOD, "band": "red"}, "$.monitors[0].band", "not both"),
        (
            {"name": "m", "element": "n", "kind": "limit", "band": "red"},
            "$.monitors[0].band",
            "no red limits",
        ),
        ({"name": "m", "element": "x", "kind": "limit"}, "$.monitors[0]", "needs `lo`"),
        ({**GOOD, "lo": 2}, "$.monitors[0].lo", "above hi"),
        ({**GOOD, "hi": float("nan")}, "$.monitors[0].hi", "nan compares"),
        ({"name": "m", "element": "x", "kind": "stale"}, "$.monitors[0]", "exactly one"),
        (
            {"name": "m", "element": "x", "kind": "stale", "max_age_ms": 5},
            "$.monitors[0].element",
            "integer time stamp",
        ),
        ({"name": "m", "element": "x", "kind": "rate"}, "$.monitors[0]", "per second"),
        ({**GOOD, "window_loops": 3}, "$.monitors[0].window_loops", "rate monitors"),
        ({**GOOD, "persistence": 0}, "$.monitors[0].persistence", ">= 1"),
        ({**GOOD, "states": ["A", "Z"]}, "$.monitors[0].states[1]", "'Z' is not a state"),
        ({**GOOD, "response": "transition"}, "$.monitors[0]", "needs `to`"),
        ({**GOOD, "response": "transition", "to": "Q"}, "$.monitors[0].to", "not a state"),
        (
            {**GOOD, "response": "transition", "to": "B", "states": ["B"]},
            "$.monitors[0].states",
            "its own target",
        ),
        ({**GOOD, "response": "safe"}, "$.monitors[0]", "needs `controller`"),
        (
            {**GOOD, "response": "safe", "controller": "nope"},
            "$.monitors[0].controller",
            "no controller named",
        ),
        ({**GOOD, "response": "fault", "fault": "NONE"}, "$.monitors[0].fault", "not a fault"),
        ({**GOOD, "to": "B"}, "$.monitors[0].to", "does not apply to response 'event'"),
        (
            {**GOOD, "response": "fault", "controller": "ctl"},
            "$.monitors[0].controller",
            "does not apply",
        ),
    ],
)
def test_a_bad_monitor_names_its_path(monitor: dict[str, Any], path: str, words: str) -> None:
    with pytest.raises(ConfigError) as ei:
        mission(monitor)
    assert ei.value.path == path, ei.value
    assert words in str(ei.value)


def test_monitor_names_are_unique() -> None:
    with pytest.raises(ConfigError, match="duplicate monitor name 'm'") as ei:
        mission(GOOD, GOOD)
    assert ei.value.path == "$.monitors[1].name"


def test_a_mission_without_a_state_machine_monitors_in_idle() -> None:
    m = decode_mission(
        textwrap.dedent(
            """
            mission: nosm
            nodes: {cn: {}}
            regions: {cn: [{name: x, type: f32}]}
            monitors: [{name: m, element: x, kind: limit, hi: 1, states: [IDLE]}]
            """
        )
    )
    cn = ControlLogic(m, keys=None)
    cn.begin(1, 1)
    cn.dv.set("x", 2.0)
    cn.finish()
    assert [e.id for e in cn.events.drain()] == [EV.MONITOR_WARNING.name]


def test_a_state_reached_only_by_a_monitor_is_reachable() -> None:
    from zplatform.control.statemachine import unreachable_states

    assert unreachable_states(mission()) == ["B"]
    go_b = {"name": "m", "element": "x", "kind": "limit", "hi": 1, "response": "transition"}
    assert unreachable_states(mission({**go_b, "to": "B"})) == []
    assert unreachable_states(mission({**go_b, "to": "B", "states": ["C"]})) == []  # A -> C -> B
    assert unreachable_states(mission({**go_b, "to": "C", "states": ["B"]})) == ["B"]
