"""Tests of zplatform.control.commands: every outcome of a request, the Active -> Idle
clear, ARM double confirmation, WRITE checks, config rules, ground helpers."""

from __future__ import annotations

import logging
import math
import textwrap

import pytest

from tests.drive import step_request
from zplatform import DataVector, Layout, decode_mission
from zplatform.config import Mission
from zplatform.control.commands import (
    ARM_WINDOW_NS,
    Command,
    CommandHandler,
    CommandStatus,
    writable_elements,
    write_states,
)
from zplatform.control.statemachine import StateMachine
from zplatform.control.uplink import element_index, fill_request
from zplatform.core.events import EventLog, Severity
from zplatform.errors import CommandError, ConfigError

MS = 1_000_000
S = 1_000_000_000
PERIOD = 10 * MS

BASE = """
mission: cmdtest
nodes: {cn: {}, dn0: {}, gn: {}}
health: null  # the tests compare whole vectors; health is its own test
regions:
  cn:
    - {name: x, type: u8}
    - {name: z, type: i32}
    - {name: big, type: u64}
    - {name: w, type: f64}
    - {name: y, type: f32}
    - {name: flag, type: bool}
    - {name: mode, enum: [P, Q, R]}
    - {name: vec, type: "f32[3]"}
  cn_to_dn0:
    - {name: valve, type: bool}
  dn0_to_cn:
    - {name: pressure, type: f32}
controllers:
  - {name: ctl, class: "stub_components:Idle", node: cn}
state_machine:
  initial: A
  states:
    A:
      transitions:
        - {element: cn_cmd, op: "==", value: LAUNCH, to: B}
        - {element: cn_cmd, op: "==", value: ABORT, to: E}
    B:
      transitions:
        - {element: cn_cmd, op: "==", value: ABORT, to: E}
    E: {}
"""

WHITELIST = """
commands:
  writable: [x, z, big, w, y, flag, mode, valve, ctl_mode, cn_fault]
  whitelist:
    A: [NOOP, LAUNCH, ABORT, WRITE, HOLD, RESUME, ARM]
    B: [ABORT]
"""


def mission(extra: str = WHITELIST, base: str = BASE) -> Mission:
    return decode_mission(base + textwrap.dedent(extra))


class Rig:
    """CN Data Vector, command handler and state machine, with a ground side
    that fills the ``gn_to_cn`` elements directly (as the runtime would after
    applying a frame)."""

    def __init__(self, m: Mission, with_sm: bool = True) -> None:
        self.m = m
        self.dv = DataVector(Layout.for_node(m, "cn"))
        self.events = EventLog("cn")
        self.sm = StateMachine(m, self.dv, self.events) if with_sm else None
        self.ch = CommandHandler(m, self.dv, self.events, self.sm)
        self.t = 100 * S

    def send(self, command: str, seq: int, element: str | int = 0, value: float = 0.0) -> str:
        """One loop with a request; returns its verdict: ``cn_cmd_status``, or
        ``cn_cmd_reject_status`` for a request refused without consuming a
        number (a replay, another run's epoch)."""
        idx = element_index(self.m, element) if isinstance(element, str) else element
        fill_request(self.dv, command, seq, idx, value)
        return self.loop(new=True)

    def loop(self, new: bool = False) -> str:
        rejects = self.dv.get("cn_cmd_rejects")
        step_request(self.ch, self.dv, new, self.t)
        if self.sm is not None:
            self.sm.step(self.t)
        self.t += PERIOD
        if self.dv.get("cn_cmd_rejects") != rejects:
            return self.dv.get_name("cn_cmd_reject_status")
        return self.dv.get_name("cn_cmd_status")

    @property
    def cmd(self) -> str:
        return self.dv.get_name("cn_cmd")


# --------------------------------------------------------------------------- outcomes


def test_accepted_command_is_active_for_one_loop_then_cleared() -> None:
    r = Rig(mission())
    assert r.send("NOOP", 1) == "ACCEPTED"
    assert r.cmd == "NOOP" and r.ch.active
    assert r.dv.get("cn_cmd_seq") == 1
    r.loop()
    assert r.cmd == "NONE" and not r.ch.active
    assert r.dv.get_name("cn_cmd_status") == "ACCEPTED"  # the status stays
    assert r.dv.get("cn_cmd_seq") == 1


def test_launch_reaches_the_state_machine_in_the_same_loop() -> None:
    r = Rig(mission())
    r.loop()
    assert r.send("LAUNCH", 1) == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "B"
    r.loop()
    assert r.cmd == "NONE" and r.dv.get_name("cn_state") == "B"


def test_a_new_request_right_after_an_active_one() -> None:
    r = Rig(mission())
    r.send("NOOP", 1)
    assert r.send("ABORT", 2) == "ACCEPTED"
    assert r.cmd == "ABORT" and r.dv.get_name("cn_state") == "E"


@pytest.mark.parametrize("code", [0, len(Command), 200, 255])
def test_rejected_unknown(code: int) -> None:
    r = Rig(mission())
    fill_request(r.dv, "NOOP", 5)
    r.dv.handle("gn_cmd").set(code)  # raw code, as a frame may carry
    assert r.loop(new=True) == "REJECTED_UNKNOWN"
    assert r.cmd == "NONE" and r.dv.get("cn_cmd_seq") == 5
    assert r.send("NOOP", 5) == "REJECTED_REPLAY"  # the number was used
    assert r.send("NOOP", 6) == "ACCEPTED"


def test_rejected_replay() -> None:
    r = Rig(mission())
    fill_request(r.dv, "NOOP", 1)
    r.dv.handle("gn_cmd_seq").set(0)  # fill_request refuses 0; a frame may carry it
    assert r.loop(new=True) == "REJECTED_REPLAY"  # numbers start at 1
    assert r.send("NOOP", 7) == "ACCEPTED"  # any first number >= 1
    assert r.send("NOOP", 7) == "REJECTED_REPLAY"
    assert r.cmd == "NONE"
    assert r.send("NOOP", 3) == "REJECTED_REPLAY"
    # A replay never moves cn_cmd_seq (issue 9, defect 5): the operator's
    # tools keep numbering from the last real verdict. It is counted instead.
    assert r.dv.get("cn_cmd_seq") == 7
    assert r.dv.get("cn_cmd_rejects") == 3
    assert r.send("NOOP", 8) == "ACCEPTED"
    assert r.ch.last_seq == 8


def test_rejected_requests_use_up_their_number() -> None:
    r = Rig(mission())
    r.loop()
    r.send("LAUNCH", 1)
    assert r.send("NOOP", 2) == "REJECTED_NOT_ALLOWED"
    assert r.send("NOOP", 2) == "REJECTED_REPLAY"


def test_rejected_not_allowed_by_the_state_whitelist() -> None:
    r = Rig(mission())
    r.loop()
    assert r.send("LAUNCH", 1) == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "B"
    for seq, c in enumerate(["NOOP", "ARM", "LAUNCH", "WRITE", "HOLD"], start=2):
        assert r.send(c, seq, "x", 1) == "REJECTED_NOT_ALLOWED", c
        assert r.cmd == "NONE"
    assert r.dv.get("x") == 0
    assert r.send("ABORT", 10) == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "E"


def test_a_state_absent_from_the_whitelist_allows_every_command() -> None:
    r = Rig(mission())
    r.send("ABORT", 1)
    assert r.dv.get_name("cn_state") == "E"  # E is not in the whitelist
    for seq, c in enumerate(["NOOP", "ARM", "LAUNCH", "HOLD", "RESUME", "ABORT"], start=2):
        assert r.send(c, seq) == "ACCEPTED", c
    assert r.send("WRITE", 20, "x", 3) == "ACCEPTED"


def test_no_whitelist_allows_everything() -> None:
    r = Rig(mission(extra=""))
    r.send("LAUNCH", 1)
    assert r.send("LAUNCH", 2) == "ACCEPTED"
    assert r.send("NOOP", 3) == "ACCEPTED"


# --------------------------------------------------------------------------- ARM

HAZARD = """
commands:
  hazardous: [LAUNCH, WRITE]
  writable: [x]
  whitelist:
    A: [NOOP, LAUNCH, ABORT, WRITE, ARM]
"""


def test_arm_then_hazardous_command_with_the_next_number_is_accepted() -> None:
    r = Rig(mission(HAZARD))
    assert r.send("ARM", 4) == "ACCEPTED"
    assert r.cmd == "ARM"
    assert r.send("LAUNCH", 5) == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "B"


def test_hazardous_command_without_arm_is_rejected() -> None:
    r = Rig(mission(HAZARD))
    assert r.send("LAUNCH", 1) == "REJECTED_NOT_ARMED"
    assert r.cmd == "NONE" and r.dv.get_name("cn_state") == "A"
    assert r.send("NOOP", 2) == "ACCEPTED"  # not hazardous: no ARM needed


def test_arm_then_hazardous_command_two_numbers_later_is_rejected() -> None:
    r = Rig(mission(HAZARD))
    assert r.send("ARM", 1) == "ACCEPTED"
    assert r.send("LAUNCH", 3) == "REJECTED_NOT_ARMED"


def test_arm_then_another_command_then_hazardous_is_rejected() -> None:
    r = Rig(mission(HAZARD))
    r.send("ARM", 1)
    r.send("NOOP", 2)
    assert r.send("LAUNCH", 3) == "REJECTED_NOT_ARMED"


def test_arm_expires_after_ten_seconds() -> None:
    r = Rig(mission(HAZARD))
    r.send("ARM", 1)
    r.t += ARM_WINDOW_NS  # the request comes 10 s + one period after the ARM
    assert r.send("LAUNCH", 2) == "REJECTED_NOT_ARMED"
    r2 = Rig(mission(HAZARD))
    r2.send("ARM", 1)
    r2.t += ARM_WINDOW_NS - PERIOD  # exactly 10 s later: still armed
    assert r2.send("LAUNCH", 2) == "ACCEPTED"


def test_an_arm_confirms_one_command_only() -> None:
    r = Rig(mission(HAZARD))
    r.send("ARM", 1)
    assert r.send("WRITE", 2, "x", 4) == "ACCEPTED"
    assert r.send("WRITE", 3, "x", 5) == "REJECTED_NOT_ARMED"
    assert r.dv.get("x") == 4


def test_a_rejected_arm_does_not_arm() -> None:
    r = Rig(mission(HAZARD))
    r.send("NOOP", 5)
    assert r.send("ARM", 5) == "REJECTED_REPLAY"
    assert r.send("LAUNCH", 6) == "REJECTED_NOT_ARMED"


# --------------------------------------------------------------------------- WRITE


@pytest.mark.parametrize(
    ("element", "value", "expected"),
    [
        ("x", 255.0, 255),
        ("x", 0.0, 0),
        ("z", -2147483648.0, -2147483648),
        ("big", 2.0**53, 2**53),
        ("w", -1.25e300, -1.25e300),
        ("y", 0.5, 0.5),
        ("flag", 1.0, True),
        ("mode", 2.0, 2),
        ("valve", 1.0, True),
        ("ctl_mode", 0.0, 0),
        ("cn_fault", 0.0, 0),
    ],
)
def test_write_accepted(element: str, value: float, expected: object) -> None:
    r = Rig(mission())
    assert r.send("WRITE", 1, element, value) == "ACCEPTED"
    assert r.cmd == "WRITE"
    assert r.dv.get(element) == expected
    (e,) = r.events.drain()
    assert e.severity == Severity.COMMAND and e.id == "cmd_accepted"
    assert e.text.startswith(f"command WRITE #1 accepted ({element} = ")


@pytest.mark.parametrize(
    ("element", "value", "reason"),
    [
        ("x", 256.0, "not an integer in 0..255"),
        ("x", -1.0, "not an integer in 0..255"),
        ("x", 1.5, "not an integer"),
        ("z", 2147483648.0, "not an integer in -2147483648..2147483647"),
        ("flag", 2.0, "not 0 or 1"),
        ("flag", 0.5, "not 0 or 1"),
        ("mode", 3.0, "not an index of mode's names 0..2"),
        ("mode", -1.0, "not an index"),
        ("y", 1e39, "does not fit f32"),
        ("w", math.nan, "not finite"),
        ("w", math.inf, "not finite"),
        ("cn_state", 1.0, "element cn_state is not writable"),
        ("cn_loop", 1.0, "element cn_loop is not writable"),
        ("cn_cmd_status", 1.0, "not writable"),
        ("pressure", 1.0, "element pressure is not writable"),
        ("gn_cmd", 1.0, "not writable"),
        ("vec", 1.0, "element vec is not writable"),
        (60000, 1.0, "no element with index 60000"),
    ],
)
def test_write_rejected_bad_argument(element: str | int, value: float, reason: str) -> None:
    r = Rig(mission())
    before = r.dv.values()
    assert r.send("WRITE", 1, element, value) == "REJECTED_BAD_ARGUMENT"
    assert r.cmd == "NONE"
    after = r.dv.values()
    for k in before:
        if not k.startswith(("cn_cmd", "gn_", "cn_time_in", "cn_state")):
            assert after[k] == before[k], k
    (e,) = r.events.drain()
    assert e.severity == Severity.WARNING_LO and e.id == "cmd_rejected"
    assert "(REJECTED_BAD_ARGUMENT)" in e.text and reason in e.text


def test_explicit_writable_list_restricts_writes() -> None:
    m = mission("commands:\n  writable: [flag, ctl_mode]\n")
    assert writable_elements(m) == ["ctl_mode", "flag"]
    r = Rig(m)
    assert r.send("WRITE", 1, "flag", 1.0) == "ACCEPTED"
    assert r.send("WRITE", 2, "x", 1.0) == "REJECTED_BAD_ARGUMENT"


def test_writable_elements_are_those_listed_in_data_vector_order() -> None:
    w = writable_elements(mission())
    assert w == ["cn_fault", "ctl_mode", "x", "z", "big", "w", "y", "flag", "mode", "valve"]


def test_nothing_is_writable_by_default_and_the_refusal_names_the_list() -> None:
    """Deny by default: without ``commands.writable`` a WRITE sets nothing,
    and the CN's reason names the element and where to list it."""
    m = mission("commands:\n  whitelist:\n    A: [NOOP, LAUNCH, ABORT, WRITE]\n")
    assert writable_elements(m) == [] and write_states(m) == {}
    r = Rig(m)
    assert r.send("WRITE", 1, "flag", 1.0) == "REJECTED_BAD_ARGUMENT"
    assert r.dv.get("flag") is False
    e = r.events.drain()[-1]
    assert (
        "element flag is not writable: commands.writable does not list it (a WRITE sets only "
        "those)" in e.text
    )


def test_a_write_of_a_parameter_points_to_prm_set() -> None:
    m = mission(
        "params:\n  - {name: gain, type: f32, default: 1, min: 0, max: 2}\n"
        "commands:\n  writable: [flag]\n"
    )
    r = Rig(m)
    assert r.send("WRITE", 1, "gain", 1.5) == "REJECTED_BAD_ARGUMENT"
    assert "element gain is not writable: it is a parameter: set it with PRM_SET" in (
        r.events.drain()[-1].text
    )


WRITE_STATES = """
commands:
  writable: [flag, x]
  write_states:
    flag: [E]
  whitelist:
    A: [NOOP, LAUNCH, ABORT, WRITE]
    B: [ABORT]
"""


def test_write_states_limit_where_an_element_may_be_written() -> None:
    """``flag`` only in E (absent from the whitelist: every command), ``x``
    wherever WRITE is allowed (A and E)."""
    m = mission(WRITE_STATES)
    assert write_states(m) == {"x": ["A", "E"], "flag": ["E"]}
    r = Rig(m)
    assert r.send("WRITE", 1, "x", 3) == "ACCEPTED"
    assert r.send("WRITE", 2, "flag", 1.0) == "REJECTED_NOT_ALLOWED"
    assert r.dv.get("flag") is False
    assert "a WRITE of flag is not allowed in state A (only in E" in r.events.drain()[-1].text
    assert r.send("ABORT", 3) == "ACCEPTED" and r.dv.get_name("cn_state") == "E"
    assert r.send("WRITE", 4, "flag", 1.0) == "ACCEPTED" and r.dv.get("flag") is True


def test_a_hazardous_output_is_written_only_in_its_states() -> None:
    """``valve`` (cn_to_dn0) may be driven only in E: a WRITE in A is refused
    even though A allows WRITE and ``writable`` lists it."""
    m = mission(
        "hazardous_outputs:\n  - {element: valve, states: [E]}\n"
        "commands:\n  writable: [valve]\n  whitelist:\n    A: [NOOP, ABORT, WRITE]\n"
    )
    assert write_states(m) == {"valve": ["E"]}
    r = Rig(m)
    assert r.send("WRITE", 1, "valve", 1.0) == "REJECTED_NOT_ALLOWED"
    assert r.dv.get("valve") is False
    assert r.send("ABORT", 2) == "ACCEPTED"
    assert r.send("WRITE", 3, "valve", 1.0) == "ACCEPTED" and r.dv.get("valve") is True


@pytest.mark.parametrize(
    ("extra", "path", "message"),
    [
        (
            "commands:\n  writable: [x]\n  write_states: {flag: [A]}\n",
            "$.commands.write_states.flag",
            "'flag' is not in commands.writable",
        ),
        (
            "commands:\n  writable: [x]\n  write_states: {x: A}\n",
            "$.commands.write_states.x",
            "Expected `array`, got `str`",
        ),
        (
            "commands:\n  writable: [x]\n  write_states: {x: [A, Z]}\n",
            "$.commands.write_states.x[1]",
            "'Z' is not a state",
        ),
        (
            "commands:\n  writable: [x]\n  write_states: {x: [B]}\n  whitelist: {B: [ABORT]}\n",
            "$.commands.write_states.x[0]",
            "state B's whitelist does not allow WRITE",
        ),
        (
            "commands:\n  writable: [x, x]\n",
            "$.commands.writable[1]",
            "listed twice",
        ),
        (
            "commands:\n  writable: [x]\n  whitelist: {A: [NOOP], B: [NOOP], E: [NOOP]}\n",
            "$.commands.writable[0]",
            "'x' may be written in no state",
        ),
        (
            "hazardous_outputs:\n  - {element: valve, states: [B]}\n"
            "commands:\n  writable: [valve]\n  write_states: {valve: [A]}\n",
            "$.commands.write_states.valve[0]",
            "hazardous output that may be driven only in B (hazardous_outputs), not in A",
        ),
    ],
)
def test_rule_write_states(extra: str, path: str, message: str) -> None:
    e = _config_error(extra)
    assert e.path == path
    assert message in e.reason


TRANSITION_READS = """
state_machine:
  initial: A
  states:
    A:
      transitions:
        - {element: cn_cmd, op: "==", value: ABORT, to: E}
    E:
      transitions:
        - {element: flag, op: "==", value: true, to: A}
"""


def test_rule_no_write_may_fire_a_transition() -> None:
    """The issue's attack on configs/flight.yaml: a flight-event flag a
    state's transition reads, WRITE-able in that state. Refused at load,
    naming the element's entry and the transition; allowed once the
    element's states leave that state out."""
    base = BASE.split("state_machine:")[0] + TRANSITION_READS
    with pytest.raises(ConfigError) as ei:
        mission("commands:\n  writable: [x, flag]\n", base=base)
    e = ei.value
    assert e.path == "$.commands.writable[1]"
    assert "'flag' is read by a transition of state E" in e.reason
    assert "$.state_machine.states.E.transitions[0]" in e.reason
    with pytest.raises(ConfigError) as ei:
        mission("commands:\n  writable: [flag]\n  write_states: {flag: [A, E]}\n", base=base)
    assert ei.value.path == "$.commands.write_states.flag"
    m = mission("commands:\n  writable: [flag]\n  write_states: {flag: [A]}\n", base=base)
    assert write_states(m) == {"flag": ["A"]}
    # Nor by a whitelist that refuses WRITE where the flag is read.
    m = mission("commands:\n  writable: [flag]\n  whitelist: {E: [NOOP]}\n", base=base)
    assert write_states(m) == {"flag": ["A"]}


# --------------------------------------------------------------------------- HOLD / RESUME


def test_hold_and_resume_reach_the_state_machine() -> None:
    r = Rig(mission())
    r.loop()
    assert r.send("HOLD", 1) == "ACCEPTED"
    assert r.sm is not None and r.sm.holding and r.cmd == "HOLD"
    assert r.send("HOLD", 2) == "ACCEPTED"  # idempotent
    assert "no change" in r.events.drain()[-1].text
    assert r.send("RESUME", 3) == "ACCEPTED"
    assert not r.sm.holding


def test_hold_without_a_state_machine_is_not_allowed() -> None:
    r = Rig(mission(), with_sm=False)
    assert r.send("HOLD", 1) == "REJECTED_NOT_ALLOWED"
    assert r.send("RESUME", 2) == "REJECTED_NOT_ALLOWED"
    assert r.send("LAUNCH", 3) == "ACCEPTED"


# --------------------------------------------------------------------------- events, no ground


def test_events_name_the_outcome_and_the_reason() -> None:
    r = Rig(mission())
    r.loop()
    r.send("LAUNCH", 1)
    r.send("NOOP", 2)
    texts = [(e.severity, e.id, e.text) for e in r.events.drain()]
    assert (Severity.COMMAND, "cmd_accepted", "command LAUNCH #1 accepted") in texts
    assert (
        Severity.WARNING_LO,
        "cmd_rejected",
        "command NOOP #2 rejected (REJECTED_NOT_ALLOWED): not allowed in state B",
    ) in texts


def test_no_request_no_event_and_no_ground_is_fine() -> None:
    r = Rig(mission())
    for _ in range(5):
        r.loop()
    assert r.events.drain() == []
    m = decode_mission(BASE.replace(", gn: {}", ""))
    dv = DataVector(Layout.for_node(m, "cn"))
    ch = CommandHandler(m, dv, EventLog("cn"))
    ch.step(True, 0)  # no gn_to_cn region: nothing to handle
    assert dv.get_name("cn_cmd_status") == "NONE"


# --------------------------------------------------------------------------- ground helpers


def test_fill_request_and_element_index() -> None:
    m = mission()
    dv = DataVector(Layout.for_node(m, "gn"))
    fill_request(dv, "write", 9, element_index(m, "mode"), 2.0)
    assert dv.get_name("gn_cmd") == "WRITE"
    assert dv.get("gn_cmd_seq") == 9
    assert dv.get("gn_cmd_value") == 2.0
    cn = DataVector(Layout.for_node(m, "cn"))
    assert cn.layout.element("mode").index == dv.get("gn_cmd_element")


@pytest.mark.parametrize(
    ("command", "seq", "idx", "message"),
    [
        ("LAUNCHH", 1, 0, "unknown command 'LAUNCHH'"),
        ("NONE", 1, 0, "unknown command 'NONE'"),
        ("NOOP", 0, 0, r"outside 1..2\*\*64-1"),
        ("NOOP", 2**64, 0, r"outside 1..2\*\*64-1"),
        ("NOOP", 1, 70000, "element index 70000 is outside 0..65535"),
    ],
)
def test_fill_request_refuses(command: str, seq: int, idx: int, message: str) -> None:
    m = mission()
    dv = DataVector(Layout.for_node(m, "gn"))
    with pytest.raises(CommandError, match=message):
        fill_request(dv, command, seq, idx)


def test_fill_request_needs_the_gn_region_and_element_index_a_name() -> None:
    m = mission()
    with pytest.raises(CommandError, match="cannot fill"):
        fill_request(DataVector(Layout.for_node(m, "dn0")), "NOOP", 1)
    with pytest.raises(CommandError, match="did you mean mode"):
        element_index(m, "mod")


def test_command_enums_mirror_the_config_names() -> None:
    assert Command.LAUNCH == 2 and CommandStatus.REJECTED_NOT_ARMED == 6


# --------------------------------------------------------------------------- config rules


def _config_error(extra: str) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        mission(extra)
    return ei.value


def test_rule_whitelist_keys_are_states() -> None:
    e = _config_error("commands:\n  whitelist:\n    A: [NOOP]\n    Z: [NOOP]\n")
    assert e.path == "$.commands.whitelist.Z"
    assert "names state 'Z'" in e.reason and "['A', 'B', 'E']" in e.reason


def test_rule_whitelist_values_are_commands() -> None:
    e = _config_error("commands:\n  whitelist:\n    A: [NOOP, LANCH]\n")
    assert e.path == "$.commands.whitelist.A[1]"
    assert "'LANCH' is not a command" in e.reason


def test_rule_none_is_not_a_command() -> None:
    e = _config_error("commands:\n  whitelist:\n    A: [NONE]\n")
    assert e.path == "$.commands.whitelist.A[0]"


def test_rule_hazardous_are_commands() -> None:
    e = _config_error("commands:\n  hazardous: [LAUNCH, FIRE]\n")
    assert e.path == "$.commands.hazardous[1]"
    assert "'FIRE' is not a command" in e.reason


def test_rule_arm_is_not_hazardous() -> None:
    e = _config_error("commands:\n  hazardous: [ARM]\n")
    assert e.path == "$.commands.hazardous[0]"
    assert "ARM cannot be hazardous" in e.reason


def test_rule_hazardous_command_needs_arm_in_the_same_whitelist() -> None:
    e = _config_error("commands:\n  hazardous: [LAUNCH]\n  whitelist:\n    A: [LAUNCH, NOOP]\n")
    assert e.path == "$.commands.whitelist.A"
    assert "LAUNCH is hazardous and needs an ARM first" in e.reason


def test_rule_writable_elements_exist() -> None:
    e = _config_error("commands:\n  writable: [x, flg]\n")
    assert e.path == "$.commands.writable[1]"
    assert "no element named 'flg'" in e.reason and "did you mean flag" in e.reason


def test_rule_writable_elements_are_scalars() -> None:
    e = _config_error("commands:\n  writable: [vec]\n")
    assert e.path == "$.commands.writable[0]"
    assert "is an array" in e.reason


@pytest.mark.parametrize(
    ("element", "message"),
    [("cn_state", "maintained by the platform"), ("pressure", "received from dn0")],
)
def test_rule_writable_elements_may_be_written(element: str, message: str) -> None:
    e = _config_error(f"commands:\n  writable: [{element}]\n")
    assert e.path == "$.commands.writable[0]"
    assert message in e.reason


def test_warns_about_a_command_transition_the_whitelist_blocks(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING, logger="zplatform.commands"):
        mission("commands:\n  whitelist:\n    A: [NOOP, ABORT]\n")
    (rec,) = [r for r in caplog.records if r.name == "zplatform.commands"]
    assert "refuses command LAUNCH" in rec.getMessage()
    assert "$.state_machine.states.A.transitions[0]" in rec.getMessage()


# --------------------------------------------------------------------------- latched faults

FAULTED = """
commands:
  hazardous: [LAUNCH, WRITE]
  writable: [x, cn_fault]
  whitelist:
    A: [NOOP, LAUNCH, ABORT, WRITE, ARM]
"""


def _latch(r: Rig, seq: int, fault: str = "SYNC_OVERRUNS") -> int:
    """ARM n, WRITE cn_fault (WRITE is hazardous here); returns the next number."""
    assert r.send("ARM", seq) == "ACCEPTED"
    code = r.dv.layout.element("cn_fault").enum.index(fault)  # type: ignore[union-attr]
    assert r.send("WRITE", seq + 1, "cn_fault", float(code)) == "ACCEPTED"
    assert r.dv.get_name("cn_fault") == fault
    return seq + 2


def test_a_hazardous_command_is_refused_while_a_fault_is_latched_naming_it() -> None:
    r = Rig(mission(FAULTED))
    n = _latch(r, 1)
    assert r.send("ARM", n) == "ACCEPTED"
    assert r.send("LAUNCH", n + 1) == "REJECTED_NOT_ALLOWED"
    assert r.dv.get_name("cn_state") == "A" and r.cmd == "NONE"
    why = [e for e in r.events.drain() if e.id == "cmd_rejected"][-1].text
    assert "a fault is latched (SYNC_OVERRUNS): clear cn_fault first (WRITE cn_fault NONE)" in why
    # ABORT and NOOP are never refused for a fault; a hazardous WRITE clears it.
    assert r.send("NOOP", n + 2) == "ACCEPTED"
    assert r.send("ARM", n + 3) == "ACCEPTED"
    assert r.send("WRITE", n + 4, "cn_fault", 0.0) == "ACCEPTED"
    assert r.send("ARM", n + 5) == "ACCEPTED"
    assert r.send("LAUNCH", n + 6) == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "B"


def test_abort_is_accepted_with_a_fault_latched() -> None:
    r = Rig(mission(FAULTED))
    n = _latch(r, 1)
    assert r.send("ABORT", n) == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "E"


def test_refused_while_faulted_is_the_missions_to_widen_or_empty() -> None:
    r = Rig(mission(FAULTED + "  refused_while_faulted: []\n"))
    n = _latch(r, 1)
    assert r.send("ARM", n) == "ACCEPTED"
    assert r.send("LAUNCH", n + 1) == "ACCEPTED"  # the mission said so
    r = Rig(mission(FAULTED + "  refused_while_faulted: [LAUNCH, HOLD]\n"))
    n = _latch(r, 1)
    assert r.send("ARM", n) == "ACCEPTED"
    assert r.send("LAUNCH", n + 1) == "REJECTED_NOT_ALLOWED"


@pytest.mark.parametrize(
    ("entry", "why"),
    [
        ("ABORT", "ABORT is never refused for a fault: it is the response to one"),
        ("WRITE", "WRITE is never refused for a fault: WRITE cn_fault NONE is how"),
        ("ARM", "ARM is never refused for a fault"),
        ("FLY", "'FLY' is not a command"),
    ],
)
def test_refused_while_faulted_names_its_bad_entry(entry: str, why: str) -> None:
    with pytest.raises(ConfigError) as ei:
        Rig(mission(FAULTED + f"  refused_while_faulted: [LAUNCH, {entry}]\n"))
    assert ei.value.path == "$.commands.refused_while_faulted[1]"
    assert why in ei.value.reason


def test_a_fault_no_write_may_clear_is_told_so() -> None:
    """cn_fault not writable where LAUNCH is refused: the reason names the
    way out (a restart), not a WRITE the CN would refuse."""
    r = Rig(mission(FAULTED + "  write_states: {cn_fault: [B]}\n"))
    r.dv.set("cn_fault", r.dv.layout.element("cn_fault").enum.index("DN_LOST"))  # type: ignore[union-attr]
    assert r.send("ARM", 1) == "ACCEPTED"
    assert r.send("LAUNCH", 2) == "REJECTED_NOT_ALLOWED"
    why = [e for e in r.events.drain() if e.id == "cmd_rejected"][-1].text
    assert "a fault is latched (DN_LOST): no WRITE may clear cn_fault in A: restart" in why
