"""Property tests of the state machine and the command handler."""

from __future__ import annotations

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.drive import step_request
from tests.property.strategies import LoopInput, loop_inputs, state_machine_missions
from zplatform import DataVector, Layout, decode_mission
from zplatform.control.commands import CommandHandler, CommandStatus
from zplatform.control.statemachine import StateMachine
from zplatform.core.events import EventLog

PERIOD = 10_000_000
_SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_SETTINGS
@given(state_machine_missions(), st.lists(loop_inputs(), max_size=60))
def test_random_state_machines_stay_in_their_states_and_never_raise(
    text: str, inputs: list[LoopInput]
) -> None:
    """Stepped with any commands and element writes, a valid state machine is
    always in one of its configured states."""
    m = decode_mission(text)
    assert m.state_machine is not None
    states = list(m.state_machine.states)
    dv = DataVector(Layout.for_node(m, "cn"))
    events = EventLog("cn", capacity=64)
    sm = StateMachine(m, dv, events)
    ch = CommandHandler(m, dv, events, sm)
    seq = 0
    t = 1_000_000_000
    for cmd, seq_step, idx, value, write in inputs:
        if write is not None:
            dv.set(*write)
        if cmd is not None:
            seq = max(seq + seq_step, 0)
            dv.set("gn_cmd", cmd)
            dv.set("gn_cmd_seq", min(seq, 0xFFFF_FFFF))
            dv.set("gn_cmd_element", idx)
            dv.set("gn_cmd_value", value)
        step_request(ch, dv, cmd is not None, t)
        sm.step(t)
        assert sm.state in states
        assert dv.get_name("cn_state") == sm.state
        assert dv.get("cn_time_in_state_ns") >= 0
        t += PERIOD
        events.drain()


_CH_MISSION = """
mission: chprop
nodes: {cn: {}, dn0: {}, gn: {}}
regions:
  cn:
    - {name: x, type: u8}
    - {name: f, type: f32}
    - {name: b, type: bool}
    - {name: e, enum: [P, Q, R]}
    - {name: big, type: i64}
state_machine:
  initial: A
  states:
    A: {transitions: [{element: cn_cmd, op: "==", value: LAUNCH, to: B}]}
    B: {transitions: [{element: cn_cmd, op: "==", value: ABORT, to: A}]}
commands:
  hazardous: [WRITE]
  whitelist: {A: [NOOP, LAUNCH, WRITE, ARM, HOLD, RESUME]}
"""
_ch_mission = decode_mission(_CH_MISSION)
_GN_SIZE = Layout.for_node(_ch_mission, "cn").region("gn_to_cn").size


@_SETTINGS
@given(st.lists(st.binary(min_size=_GN_SIZE, max_size=_GN_SIZE), min_size=1, max_size=30))
def test_command_handler_never_raises_on_any_request_bytes(frames: list[bytes]) -> None:
    """Whatever bytes land in gn_to_cn, a step never raises and gives every
    request a verdict: a status, or a refusal counted without consuming a
    number (a replay or another run's epoch)."""
    dv = DataVector(Layout.for_node(_ch_mission, "cn"))
    events = EventLog("cn")
    sm = StateMachine(_ch_mission, dv, events)
    ch = CommandHandler(_ch_mission, dv, events, sm)
    t = 0
    for frame in frames:
        dv.write_region("gn_to_cn", frame)
        rejects = dv.get("cn_cmd_rejects")
        step_request(ch, dv, True, t)
        sm.step(t)
        assert 0 <= dv.get("cn_cmd_status") < len(CommandStatus)
        if dv.get("cn_cmd_rejects") == rejects:
            assert dv.get("cn_cmd_status") != CommandStatus.NONE
        else:
            assert dv.get("cn_cmd_rejects") == rejects + 1
            assert dv.get("cn_cmd_reject_status") != CommandStatus.NONE
        assert sm.state in ("A", "B")
        t += PERIOD
    assert events.emitted >= len(frames)
