"""Tests of zplatform.control.statemachine: every config rule (message and YAML path),
every transition kind, action timing, ordering, hold and resume."""

from __future__ import annotations

import logging
import textwrap
from typing import Any

import pytest

from tests.drive import step_request
from zplatform import DataVector, Layout, decode_mission
from zplatform.config import Mission, StateConfig
from zplatform.control.commands import CommandHandler
from zplatform.control.statemachine import (
    StateMachine,
    check_config,
    logic_writable,
    unreachable_states,
)
from zplatform.control.uplink import fill_request
from zplatform.core.events import EventLog, Severity
from zplatform.errors import ConfigError

MS = 1_000_000
S = 1_000_000_000
PERIOD = 10 * MS

BASE = """
mission: smtest
nodes: {cn: {}, dn0: {}, gn: {}}
regions:
  cn:
    - {name: x, type: u8}
    - {name: z, type: i32}
    - {name: w, type: f64}
    - {name: y, type: f32}
    - {name: flag, type: bool}
    - {name: mode, enum: [P, Q, R]}
    - {name: vec, type: "f32[3]"}
    - {name: out, type: u16}
  cn_to_dn0:
    - {name: valve, type: bool}
  dn0_to_cn:
    - {name: pressure, type: f32}
controllers:
  - {name: ctl, class: "stub_components:Idle", node: cn}
"""


def mission(sm: str, extra: str = "") -> Mission:
    """A mission of BASE with ``sm`` (YAML under ``state_machine:``) and ``extra``."""
    text = BASE + "state_machine:\n" + textwrap.indent(textwrap.dedent(sm), "  ")
    return decode_mission(text + textwrap.dedent(extra))


def config_error(sm: str, extra: str = "") -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        mission(sm, extra)
    return ei.value


class Rig:
    """A CN Data Vector with a state machine and a command handler, stepped in
    virtual time: ``loop()`` is one CN loop (commands, then state machine)."""

    def __init__(self, m: Mission, t0: int = 5 * S) -> None:
        self.m = m
        self.dv = DataVector(Layout.for_node(m, "cn"))
        self.events = EventLog("cn")
        self.sm = StateMachine(m, self.dv, self.events)
        self.ch = CommandHandler(m, self.dv, self.events, self.sm)
        self.t = t0
        self.seq = 0

    def loop(self, n: int = 1, command: str | None = None) -> None:
        for i in range(n):
            new = command is not None and i == 0
            if new:
                assert command is not None
                self.seq += 1
                fill_request(self.dv, command, self.seq)
            step_request(self.ch, self.dv, new, self.t)
            self.sm.step(self.t)
            self.t += PERIOD

    def until(self, seconds: float) -> None:
        """Loop until ``seconds`` of virtual time have passed."""
        self.loop(round(seconds * S / PERIOD))

    @property
    def state(self) -> str:
        return self.dv.get_name("cn_state")

    def texts(self) -> list[str]:
        return [e.text for e in self.events.drain()]


# --------------------------------------------------------------------------- config rules


def test_rule_at_least_one_state() -> None:
    m = mission("initial: A\nstates: {A: {}}\n")
    assert m.state_machine is not None
    m.state_machine.states = {}
    with pytest.raises(ConfigError) as ei:
        check_config(m)
    assert ei.value.path == "$.state_machine.states"
    assert "at least one state" in ei.value.reason


def test_rule_state_names_are_identifiers() -> None:
    m = mission("initial: A\nstates: {A: {}}\n")
    assert m.state_machine is not None
    m.state_machine.states = {"A": StateConfig(), "bad-name": StateConfig()}
    with pytest.raises(ConfigError) as ei:
        check_config(m)
    assert ei.value.path == "$.state_machine.states.bad-name"
    assert "not an identifier" in ei.value.reason


def test_rule_initial_state_exists() -> None:
    m = mission("initial: A\nstates: {A: {}, B: {}}\n")
    assert m.state_machine is not None
    m.state_machine.initial = "Z"
    with pytest.raises(ConfigError) as ei:
        check_config(m)
    assert ei.value.path == "$.state_machine.initial"
    assert "'Z' is not a state" in ei.value.reason and "['A', 'B']" in ei.value.reason


def test_rule_target_state_exists() -> None:
    e = config_error(
        """
        initial: A
        states:
          A: {transitions: [{after_s: 1, to: B}, {after_s: 2, to: NOPE}]}
          B: {}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[1].to"
    assert "target state 'NOPE' is not a state" in e.reason


def test_rule_condition_and_after_s_are_exclusive() -> None:
    e = config_error(
        """
        initial: A
        states:
          A: {transitions: [{element: x, op: "==", value: 1, after_s: 1, to: A}]}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[0]"
    assert "not both" in e.reason


def test_rule_transition_needs_a_condition_or_after_s() -> None:
    e = config_error("initial: A\nstates:\n  A: {transitions: [{to: A}]}\n")
    assert e.path == "$.state_machine.states.A.transitions[0]"
    assert "needs a condition (element, op, value) or after_s" in e.reason


def test_rule_condition_needs_all_three_parts() -> None:
    e = config_error(
        """
        initial: A
        states:
          A: {transitions: [{element: x, value: 1, to: A}]}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[0].op"
    assert "`op` is missing" in e.reason


def test_rule_transition_element_exists() -> None:
    e = config_error(
        """
        initial: A
        states:
          A: {transitions: [{element: flg, op: "==", value: true, to: A}]}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[0].element"
    assert "no element named 'flg'" in e.reason and "did you mean flag" in e.reason


def test_rule_transition_element_is_scalar() -> None:
    e = config_error(
        """
        initial: A
        states:
          A: {transitions: [{element: vec, op: ">", value: 1.0, to: A}]}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[0].element"
    assert "is an array" in e.reason


@pytest.mark.parametrize(
    ("element", "value", "kind"), [("flag", True, "bool"), ("mode", "Q", "enum")]
)
def test_rule_bool_and_enum_compare_only_for_equality(element: str, value: Any, kind: str) -> None:
    e = config_error(
        f"""
        initial: A
        states:
          A: {{transitions: [{{after_s: 1, to: A}}, {{element: {element}, op: "<",
                               value: {str(value).lower()}, to: A}}]}}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[1].op"
    assert f"on {'an' if kind == 'enum' else 'a'} {kind} element" in e.reason
    assert "only with == and !=" in e.reason


@pytest.mark.parametrize(
    ("element", "value", "message"),
    [
        ("x", "300", "300 does not fit u8 element 'x' (range 0..255)"),
        ("x", "-1", "-1 does not fit u8"),
        ("z", "1.5", "1.5 does not fit i32"),
        ("w", "'1.5'", "expected a number for f64 element 'w'"),
        ("w", "nan", "nan compares unequal"),
        ("flag", "yes_please", "expected true or false for bool element 'flag'"),
        ("flag", "2", "expected true or false"),
        ("mode", "S", "'S' is not one of mode's names ['P', 'Q', 'R']"),
        ("mode", "3", "expected one of mode's names"),
        ("cn_cmd", "LANCH", "'LANCH' is not one of cn_cmd's names"),
    ],
)
def test_rule_condition_value_fits_the_element_type(element: str, value: str, message: str) -> None:
    e = config_error(
        f"""
        initial: A
        states:
          A: {{transitions: [{{element: {element}, op: "==", value: {value}, to: A}}]}}
        """
    )
    assert e.path == "$.state_machine.states.A.transitions[0].value"
    assert message in e.reason


def test_rule_action_element_exists() -> None:
    e = config_error(
        """
        initial: A
        states:
          A: {actions: [{element: x, value: 1}, {element: ouut, value: 1}]}
        """
    )
    assert e.path == "$.state_machine.states.A.actions[1].element"
    assert "no element named 'ouut'" in e.reason and "did you mean out" in e.reason


@pytest.mark.parametrize(
    ("element", "message"),
    [
        ("cn_state", "maintained by the platform"),
        ("cn_loop", "maintained by the platform"),
        ("cn_cmd", "maintained by the platform"),
        ("pressure", "received from dn0 every loop"),
        ("gn_cmd_value", "received from gn every loop"),
    ],
)
def test_rule_action_element_is_writable_by_logic(element: str, message: str) -> None:
    e = config_error(
        f"""
        initial: A
        states:
          A: {{actions: [{{element: {element}, value: 1}}]}}
        """
    )
    assert e.path == "$.state_machine.states.A.actions[0].element"
    assert message in e.reason


def test_controller_modes_and_fault_flag_are_writable_by_actions() -> None:
    m = mission(
        """
        initial: A
        states:
          A: {actions: [{element: ctl_mode, value: enabled}, {element: cn_fault, value: NONE}]}
        """
    )
    w = logic_writable(m)
    assert {"ctl_mode", "cn_fault", "x", "vec", "valve"} <= w
    assert not {"cn_state", "pressure", "gn_cmd", "cn_errors"} & w


@pytest.mark.parametrize(
    ("element", "value", "message"),
    [
        ("x", "256", "256 does not fit u8"),
        ("mode", "Z", "'Z' is not one of mode's names"),
        ("flag", "'true'", "expected true or false"),
        ("vec", "'x'", "expected a number for f32 element 'vec'"),
        ("y", "1.0e+39", "does not fit f32"),
    ],
)
def test_rule_action_value_fits_the_element_type(element: str, value: str, message: str) -> None:
    e = config_error(
        f"""
        initial: A
        states:
          A: {{actions: [{{element: {element}, value: {value}, at_s: 1}}]}}
        """
    )
    assert e.path == "$.state_machine.states.A.actions[0].value"
    assert message in e.reason


def test_rule_times_are_not_negative() -> None:
    e = config_error("initial: A\nstates:\n  A: {transitions: [{after_s: -1, to: A}]}\n")
    # msgspec writes a mapping key as [...]; parse_mission names it
    assert e.path.startswith("$.state_machine.states")
    assert e.path.endswith(".transitions[0].after_s")
    assert ">= 0" in e.reason


def test_unreachable_states_are_warnings_not_errors(caplog: pytest.LogCaptureFixture) -> None:
    sm = """
        initial: A
        states:
          A: {transitions: [{after_s: 1, to: B}]}
          B: {transitions: [{after_s: 1, to: A}]}
          C: {transitions: [{after_s: 1, to: D}]}
          D: {}
        """
    with caplog.at_level(logging.WARNING, logger="zplatform.statemachine"):
        m = mission(sm)
    assert unreachable_states(m) == ["C", "D"]
    warned = [r.getMessage() for r in caplog.records if r.name == "zplatform.statemachine"]
    assert len(warned) == 2
    assert "state 'C' cannot be reached" in warned[0]
    assert "$.state_machine.states.C" in warned[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="zplatform.statemachine"):
        StateMachine(m, DataVector(Layout.for_node(m, "cn")), EventLog("cn"))
    assert not caplog.records  # construction re-checks silently


def test_shipped_led_test_config_passes() -> None:
    from pathlib import Path

    from zplatform import load_mission

    root = Path(__file__).resolve().parents[2]
    m = load_mission(root / "configs" / "led_test.yaml")
    assert unreachable_states(m) == []


# --------------------------------------------------------------------------- transitions


def test_command_transition() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A: {transitions: [{element: cn_cmd, op: "==", value: LAUNCH, to: B}]}
              B: {}
            """
        )
    )
    r.loop(3)
    assert r.state == "A"
    r.loop(command="NOOP")
    assert r.state == "A"
    r.loop(command="LAUNCH")
    assert r.state == "B"
    assert r.sm.state == "B"
    assert "state A -> B (cn_cmd == LAUNCH)" in r.texts()


def test_time_transition_fires_when_after_s_has_elapsed() -> None:
    r = Rig(mission("initial: A\nstates:\n  A: {transitions: [{after_s: 0.5, to: B}]}\n  B: {}\n"))
    r.loop()  # entered at t0
    r.loop(48)  # t0 + 480 ms
    assert r.state == "A"
    r.loop()  # t0 + 490 ms
    assert r.state == "A"
    r.loop()  # t0 + 500 ms
    assert r.state == "B"
    assert r.dv.get("cn_time_in_state_ns") == 0
    r.loop()
    assert r.dv.get("cn_time_in_state_ns") == PERIOD


@pytest.mark.parametrize(
    ("op", "value", "holds_for"),
    [
        ("==", 5, [5]),
        ("!=", 5, [-7, 0, 6]),
        ("<", 5, [-7, 0]),
        ("<=", 5, [-7, 0, 5]),
        (">", 5, [6]),
        (">=", 5, [5, 6]),
    ],
)
@pytest.mark.parametrize("element", ["z", "w"])
def test_data_transition_every_op_on_int_and_float(
    element: str, op: str, value: int, holds_for: list[int]
) -> None:
    v = float(value) if element == "w" else value
    m = mission(
        f"""
        initial: A
        states:
          A: {{transitions: [{{element: {element}, op: "{op}", value: {v}, to: B}}]}}
          B: {{transitions: [{{after_s: 0, to: A}}]}}
        """
    )
    for probe in (-7, 0, 5, 6):
        r = Rig(m)
        r.dv.set(element, float(probe) if element == "w" else probe)
        r.loop()
        assert (r.state == "B") == (probe in holds_for), (element, op, probe)


def test_f32_equality_compares_with_the_stored_value() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A: {transitions: [{element: y, op: "==", value: 0.1, to: B}]}
              B: {}
            """
        )
    )
    r.loop()
    assert r.state == "A"
    r.dv.set("y", 0.1)  # stored as f32(0.1) != 0.1 as a double
    r.loop()
    assert r.state == "B"


def test_enum_compare_by_name_and_bool_compare() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A: {transitions: [{element: mode, op: "==", value: Q, to: B}]}
              B: {transitions: [{element: mode, op: "!=", value: Q, to: C}]}
              C: {transitions: [{element: flag, op: "==", value: true, to: D}]}
              D: {transitions: [{element: flag, op: "!=", value: true, to: A}]}
            """
        )
    )
    r.loop(2)
    assert r.state == "A"
    r.dv.set("mode", "Q")
    r.loop()
    assert r.state == "B"
    r.loop(2)
    assert r.state == "B"
    r.dv.set("mode", "R")
    r.loop()
    assert r.state == "C"
    r.dv.set("flag", True)
    r.loop()
    assert r.state == "D"
    r.dv.set("flag", False)
    r.loop()
    assert r.state == "A"


def test_transition_on_a_received_element_and_the_fault_flag() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A: {transitions: [{element: pressure, op: ">", value: 30.5, to: B}]}
              B: {transitions: [{element: cn_fault, op: "!=", value: NONE, to: C}]}
              C: {}
            """
        )
    )
    r.dv.set("pressure", 30.5)
    r.loop()
    assert r.state == "A"
    r.dv.set("pressure", 31.0)
    r.loop()
    assert r.state == "B"
    r.dv.set("cn_fault", "DN_LOST")
    r.loop()
    assert r.state == "C"


def test_first_matching_transition_wins() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A:
                transitions:
                  - {element: x, op: ">", value: 10, to: B}
                  - {element: x, op: ">", value: 5, to: C}
                  - {after_s: 0, to: D}
              B: {}
              C: {}
              D: {}
            """
        )
    )
    r.dv.set("x", 7)
    r.loop()
    assert r.state == "C"
    r2 = Rig(r.m)
    r2.dv.set("x", 11)
    r2.loop()
    assert r2.state == "B"
    r3 = Rig(r.m)
    r3.loop()
    assert r3.state == "D"


def test_at_most_one_transition_per_step() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A: {transitions: [{after_s: 0, to: B}]}
              B: {transitions: [{after_s: 0, to: C}]}
              C: {transitions: [{element: flag, op: "==", value: false, to: A}]}
            """
        )
    )
    seen = []
    for _ in range(4):
        r.loop()
        seen.append(r.state)
    assert seen == ["B", "C", "A", "B"]


def test_first_step_enters_the_initial_state_then_evaluates_its_transitions() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A:
                actions: [{element: x, value: 9}]
                transitions: [{element: cn_cmd, op: "==", value: LAUNCH, to: B}]
              B: {actions: [{element: out, value: 2}]}
            """
        )
    )
    assert r.sm.state == "A" and r.sm.time_in_state_ns == 0
    r.loop(command="LAUNCH")  # a command in the very first loop is not lost
    assert r.state == "B"
    assert r.dv.get("x") == 9  # and A's 0 s actions still ran
    assert r.dv.get("out") == 2


# --------------------------------------------------------------------------- actions


def test_actions_at_zero_run_on_entry_and_later_ones_once_when_due() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A: {transitions: [{element: cn_cmd, op: "==", value: LAUNCH, to: B}]}
              B:
                actions:
                  - {at_s: 0.05, element: out, value: 5}
                  - {at_s: 0, element: mode, value: Q}
                  - {at_s: 0.02, element: flag, value: true}
                  - {at_s: 0, element: ctl_mode, value: enabled}
                  - {at_s: 0.02, element: vec, value: 1.5}
            """
        )
    )
    r.loop(2)
    assert r.dv.get_name("mode") == "P" and r.dv.get_name("ctl_mode") == "safed"
    r.loop(command="LAUNCH")  # B entered at t; its 0 s actions run in this loop
    assert r.state == "B"
    assert r.dv.get_name("mode") == "Q" and r.dv.get_name("ctl_mode") == "enabled"
    assert r.dv.get("flag") is False
    r.loop()  # 10 ms
    assert r.dv.get("flag") is False
    r.loop()  # 20 ms
    assert r.dv.get("flag") is True and list(r.dv.get("vec")) == [1.5, 1.5, 1.5]
    assert r.dv.get("out") == 0
    r.loop(3)  # 30, 40, 50 ms
    assert r.dv.get("out") == 5
    # actions do not re-run: overwrite what they wrote and keep stepping
    r.dv.set("out", 0)
    r.dv.set("mode", "R")
    r.dv.set("flag", False)
    r.until(1.0)
    assert r.dv.get("out") == 0 and r.dv.get_name("mode") == "R" and r.dv.get("flag") is False


def test_actions_with_equal_times_run_in_config_order() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A:
                actions:
                  - {at_s: 0.01, element: out, value: 1}
                  - {at_s: 0.01, element: out, value: 2}
                  - {at_s: 0, element: out, value: 7}
            """
        )
    )
    r.loop()
    assert r.dv.get("out") == 7
    r.loop()
    assert r.dv.get("out") == 2


def test_actions_due_between_loops_all_run_at_the_next_loop() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A:
                actions:
                  - {at_s: 0.011, element: x, value: 1}
                  - {at_s: 0.013, element: z, value: -4}
                  - {at_s: 0.021, element: out, value: 3}
            """
        )
    )
    r.loop(2)  # 0 and 10 ms
    assert r.dv.get("x") == 0
    r.loop()  # 20 ms: both due actions run
    assert r.dv.get("x") == 1 and r.dv.get("z") == -4 and r.dv.get("out") == 0
    r.loop()
    assert r.dv.get("out") == 3


def test_re_entering_a_state_runs_its_actions_again() -> None:
    r = Rig(
        mission(
            """
            initial: A
            states:
              A:
                actions: [{at_s: 0, element: out, value: 1}]
                transitions: [{after_s: 0.02, to: B}]
              B:
                actions: [{at_s: 0, element: out, value: 2}]
                transitions: [{after_s: 0.02, to: A}]
            """
        )
    )
    values = []
    for _ in range(8):
        r.loop()
        values.append(r.dv.get("out"))
    assert values == [1, 1, 2, 2, 1, 1, 2, 2]


# --------------------------------------------------------------------------- state output


def test_writes_cn_state_and_time_in_state_every_step() -> None:
    r = Rig(mission("initial: B\nstates:\n  A: {}\n  B: {transitions: [{after_s: 1, to: A}]}\n"))
    assert r.dv.get_name("cn_state") == "B"
    r.loop()
    assert r.dv.get("cn_time_in_state_ns") == 0
    r.loop(5)
    assert r.dv.get("cn_time_in_state_ns") == 5 * PERIOD == r.sm.time_in_state_ns
    r.dv.set("cn_state", "A")  # a stray write is corrected by the next step
    r.loop()
    assert r.dv.get_name("cn_state") == "B"
    r.until(1.0)
    assert r.state == "A"


def test_state_change_event_is_info_and_names_the_cause() -> None:
    r = Rig(mission("initial: A\nstates:\n  A: {transitions: [{after_s: 0.01, to: B}]}\n  B: {}\n"))
    r.loop(2)
    (e,) = r.events.drain()
    assert e.severity == Severity.ACTIVITY_HI
    assert e.id == "state_change"
    assert e.text.startswith("state A -> B")
    assert e.text == "state A -> B (after 0.01 s)"
    assert e.t_ns == r.t - PERIOD


def test_mission_without_state_machine_is_idle() -> None:
    m = decode_mission(BASE)
    dv = DataVector(Layout.for_node(m, "cn"))
    sm = StateMachine(m, dv, EventLog("cn"))
    for i in range(3):
        sm.step(i * PERIOD)
    assert sm.state == "IDLE" and sm.states == ("IDLE",)
    assert dv.get("cn_time_in_state_ns") == 2 * PERIOD


# --------------------------------------------------------------------------- hold / resume

COUNTDOWN = """
initial: A
states:
  A:
    actions:
      - {at_s: 0, element: out, value: 1}
      - {at_s: 0.5, element: out, value: 2}
    transitions:
      - {element: cn_cmd, op: "==", value: ABORT, to: E}
      - {after_s: 1.0, to: B}
  B: {}
  E:
    actions:
      - {at_s: 0, element: flag, value: true}
      - {at_s: 0.1, element: x, value: 3}
"""


def test_hold_freezes_time_in_state_and_resume_continues() -> None:
    r = Rig(mission(COUNTDOWN))
    r.until(0.3)
    assert r.dv.get("cn_time_in_state_ns") == 290 * MS
    r.loop(command="HOLD")
    assert r.sm.holding
    frozen = r.dv.get("cn_time_in_state_ns")
    assert frozen == 300 * MS
    r.until(5.0)  # timed action (0.5 s) and after_s transition (1 s) wait
    assert r.state == "A" and r.dv.get("out") == 1
    assert r.dv.get("cn_time_in_state_ns") == frozen
    r.loop(command="RESUME")
    assert not r.sm.holding
    assert r.dv.get("cn_time_in_state_ns") == frozen
    r.loop()
    assert r.dv.get("cn_time_in_state_ns") == frozen + PERIOD
    r.until(0.2)
    assert r.dv.get("out") == 2 and r.state == "A"
    r.until(0.5)
    assert r.state == "B"
    texts = r.texts()
    assert any(t.startswith("hold in state A at 0.300 s") for t in texts)
    assert any(t.startswith("resume in state A at 0.300 s") for t in texts)


def test_abort_works_during_a_hold_and_ends_it() -> None:
    r = Rig(mission(COUNTDOWN))
    r.until(0.2)
    r.loop(command="HOLD")
    r.until(2.0)
    r.loop(command="ABORT")
    assert r.state == "E"
    assert not r.sm.holding
    assert r.dv.get("flag") is True  # the abort state's 0 s action ran
    r.until(0.1)
    assert r.dv.get("x") == 3  # and its clock runs
    assert "hold ended by a transition" in r.texts()


def test_hold_and_resume_are_idempotent() -> None:
    r = Rig(mission(COUNTDOWN))
    r.loop()
    assert r.sm.hold(r.t) is True
    assert r.sm.hold(r.t + PERIOD) is False
    assert r.sm.resume(r.t + 2 * PERIOD) is True
    assert r.sm.resume(r.t + 3 * PERIOD) is False


def test_hold_before_the_first_step() -> None:
    r = Rig(mission(COUNTDOWN))
    r.sm.hold(r.t - 5 * S)
    r.loop()
    assert r.dv.get("out") == 1 and r.dv.get("cn_time_in_state_ns") == 0
    r.until(3.0)
    assert r.state == "A" and r.dv.get("cn_time_in_state_ns") == 0
    r.sm.resume(r.t)  # the next loop runs at r.t: time in state 0 again
    r.until(1.0)
    assert r.state == "A"
    r.loop()
    assert r.state == "B"
