"""Hazardous outputs (zplatform.control.interlocks): the config rules, the device
node's interlock on the state its trigger carries, and `zplatform check`'s
list of every writable element and hazardous output."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

from zplatform import DataVector, Layout, RegionCodec, decode_mission, load_mission
from zplatform.boards import SimBoard
from zplatform.cli.main import main
from zplatform.config import Mission
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.errors import ConfigError
from zplatform.mission.safety import doors

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = ROOT / "configs" / "flight.yaml"
S = 1_000_000_000
PERIOD = 10_000_000

BASE = """
mission: interlock
nodes: {cn: {}, dn0: {}, gn: {}}
regions:
  cn:
    - {name: go, type: bool}
  cn_to_dn0:
    - {name: valve_cmd, type: bool}
    - {name: level, type: u8}
  dn0_to_cn:
    - {name: valve_fb, type: bool}
state_machine:
  initial: SAFE
  states:
    SAFE:
      transitions:
        - {element: cn_cmd, op: "==", value: LAUNCH, to: OPEN}
    OPEN:
      transitions:
        - {element: cn_cmd, op: "==", value: ABORT, to: SAFE}
devices:
  - {name: valve, class: "zplatform.control.devices:DigitalOutput", node: dn0,
     config: {pin: 0, command: valve_cmd, feedback: valve_fb}}
"""


def mission(extra: str) -> Mission:
    return decode_mission(BASE + textwrap.dedent(extra))


def config_error(extra: str) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        mission(extra)
    return ei.value


# --------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    ("extra", "path", "message"),
    [
        (
            "hazardous_outputs: [{element: valve_cmdd, states: [OPEN]}]\n",
            "$.hazardous_outputs[0].element",
            "no element named 'valve_cmdd' in the Data Vector; did you mean valve_cmd",
        ),
        (
            "hazardous_outputs: [{element: go, states: [OPEN]}]\n",
            "$.hazardous_outputs[0].element",
            "not an output a device node drives",
        ),
        (
            "hazardous_outputs: [{element: dn0_final, states: [OPEN]}]\n",
            "$.hazardous_outputs[0].element",
            "not an output a device node drives",
        ),
        (
            "hazardous_outputs:\n  - {element: valve_cmd, states: [OPEN]}\n"
            "  - {element: valve_cmd, states: [SAFE]}\n",
            "$.hazardous_outputs[1].element",
            "named twice",
        ),
        (
            "hazardous_outputs: [{element: valve_cmd, states: [OPEN, SHUT]}]\n",
            "$.hazardous_outputs[0].states[1]",
            "'SHUT' is not a state",
        ),
        (
            "hazardous_outputs: [{element: level, states: [OPEN], safe: 300}]\n",
            "$.hazardous_outputs[0].safe",
            "300 does not fit u8",
        ),
        (
            "hazardous_outputs: [{element: valve_cmd, states: [OPEN], bogus: 1}]\n",
            "$.hazardous_outputs[0]",
            "bogus",
        ),
    ],
)
def test_rule_hazardous_outputs(extra: str, path: str, message: str) -> None:
    e = config_error(extra)
    assert e.path == path
    assert message in e.reason


def test_rule_no_action_drives_a_hazardous_output_outside_its_states() -> None:
    text = BASE.replace(
        "    SAFE:\n      transitions:",
        "    SAFE:\n      actions:\n        - {element: valve_cmd, value: false}\n"
        "        - {element: valve_cmd, value: true}\n      transitions:",
    )
    with pytest.raises(ConfigError) as ei:
        decode_mission(text + "hazardous_outputs: [{element: valve_cmd, states: [OPEN]}]\n")
    assert ei.value.path == "$.state_machine.states.SAFE.actions[1]"
    assert "drives hazardous output 'valve_cmd' to True" in ei.value.reason
    # Its safe value there is fine, and the action is fine in a state of its own.
    decode_mission(text + "hazardous_outputs: [{element: valve_cmd, states: [OPEN, SAFE]}]\n")


def test_the_state_travels_only_to_a_device_node_holding_a_hazardous_output() -> None:
    plain = mission("")
    assert "dn0_state" not in Layout.for_node(plain, "dn0").elements
    m = mission("hazardous_outputs: [{element: valve_cmd, states: [OPEN]}]\n")
    layout = Layout.for_node(m, "dn0")
    assert tuple(layout.element("dn0_state").enum or ()) == ("SAFE", "OPEN")
    assert "dn0_interlocked" in layout.elements


# --------------------------------------------------------------------------- the interlock


class Pair:
    """The real CN and DN logics of a mission, one loop at a time; the CN's
    frame can be changed before the DN takes it (what a CN told to command
    the output, or a forged-yet-authentic trigger, would carry)."""

    def __init__(self, m: Mission) -> None:
        self.cn = ControlLogic(m)
        self.board = SimBoard({"digital_pins": 2, "analog_pins": 1})
        self.dn = DeviceLogic(m, "dn0", board=self.board)
        self.loop = 0

    def step(self, **force: object) -> None:
        self.loop += 1
        t = S + self.loop * PERIOD
        self.cn.begin(self.loop, t)
        dv = DataVector(self.cn.layout)  # the trigger the DN runs: the CN's, changed
        dv.buf[:] = self.cn.dv.buf
        for name, v in force.items():
            dv.set(name, v)
        reply = self.dn.step(RegionCodec(dv, "cn_to_dn0").encode(self.loop, t), t)
        assert reply is not None and self.dn.triggered == self.loop
        self.cn.reply(0, reply)
        self.cn.finish()


def test_a_device_node_drives_a_hazardous_output_only_in_its_states() -> None:
    m = mission("hazardous_outputs: [{element: valve_cmd, states: [OPEN], doc: valve}]\n")
    p = Pair(m)
    p.step()
    assert p.cn.dv.get_name("dn0_state") == "SAFE"  # the CN writes its state in each trigger
    p.step(valve_cmd=True)  # commanded in SAFE: the node writes the safe value instead
    assert p.board.get_digital(0) is False and p.dn.dv.get("valve_cmd") is False
    assert p.dn.dv.get("dn0_interlocked") == 1
    (ev,) = [e for e in p.dn.events.drain() if e.id == "dn_interlocked"]
    assert ev.text == (
        "dn0 drove 1 hazardous output(s) to their safe value in state SAFE, where they may not "
        "be driven: valve_cmd (hazardous_outputs)"
    )
    for _ in range(50):  # half a second more of it: counted, evented once a second at most
        p.step(valve_cmd=True)
    assert p.dn.dv.get("dn0_interlocked") == 51 and p.board.get_digital(0) is False
    assert not [e for e in p.dn.events.drain() if e.id == "dn_interlocked"]
    p.step()
    assert p.cn.dv.get("dn0_interlocked") == 51  # the CN sees the count in the reply
    p.step(valve_cmd=True, dn0_state="OPEN")  # its state: driven
    assert p.board.get_digital(0) is True and p.dn.dv.get("dn0_interlocked") == 51


def test_the_shipped_flight_keeps_the_motor_safe_on_a_trigger_stamped_safe() -> None:
    """The issue's second attack, on the device node: a trigger whose state
    is SAFE with the motor command set leaves the motor igniter off (the
    interlock writes its safe value and counts it); the same trigger
    stamped ARMED lights it (the rule, not a dead pin)."""
    m = load_mission(FLIGHT)
    board = SimBoard({"digital_pins": 4, "analog_pins": 6})
    dn = DeviceLogic(m, "dn0", board=board)
    cn = DataVector(Layout.for_node(m, "cn"))
    cn.set("dn0_motor_cmd", True)
    assert cn.get_name("dn0_state") == "SAFE"
    dn.step(RegionCodec(cn, "cn_to_dn0").encode(1, S), S)
    assert board.get_digital(0) is False and dn.dv.get("dn0_motor_fb") is False
    assert dn.dv.get("dn0_interlocked") == 1
    cn.set("dn0_state", "ARMED")
    dn.step(RegionCodec(cn, "cn_to_dn0").encode(2, S + PERIOD), S + PERIOD)
    assert board.get_digital(0) is True and dn.dv.get("dn0_interlocked") == 1


# --------------------------------------------------------------------------- check


def test_check_lists_every_writable_element_and_hazardous_output(
    capsys: pytest.CaptureFixture[str],
) -> None:
    m = load_mission(FLIGHT)
    writable, outputs = doors(m)
    assert [(w.element, w.states, w.protected) for w in writable] == [
        ("cn_fault", ["SAFE"], False),  # a fault latched on the pad is cleared there
        ("ekf_mode", ["SAFE"], True),
        ("airbrakes_mode", ["SAFE", "LANDED"], True),
        ("dn1_airbrake_cmd", ["SAFE", "LANDED"], False),
    ]
    assert [(h.element, h.node, h.states, h.safe) for h in outputs] == [
        ("dn0_motor_cmd", "dn0", ["ARMED"], False),
        ("dn0_drogue_out", "dn0", ["DROGUE", "MAIN"], False),
        ("dn1_drogue_out", "dn1", ["DROGUE", "MAIN"], False),
        ("dn0_main_out", "dn0", ["MAIN"], False),
        ("dn1_main_out", "dn1", ["MAIN"], False),
    ]
    assert main(["check", str(FLIGHT)]) == 0
    out = capsys.readouterr().out
    assert "WRITE may set 4 element(s) (commands.writable; deny by default):" in out
    assert "  airbrakes_mode           in SAFE, LANDED  (ARM n, then WRITE n+1)\n" in out
    assert "  dn0_motor_cmd            dn0: driven only in ARMED; else false\n" in out
    assert main(["check", str(FLIGHT), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["writable"][3] == {
        "element": "dn1_airbrake_cmd",
        "states": ["SAFE", "LANDED"],
        "protected": False,
        "path": "$.commands.writable[2]",
    }
    assert rep["hazardous_outputs"][0]["path"] == "$.hazardous_outputs[0]"


def test_check_refuses_a_flight_event_writable_where_a_transition_reads_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The issue's first attack as a mission: the shipped flight with its
    apogee flag writable (ABORTED allows WRITE and leaves on ev_apogee)."""
    text = FLIGHT.read_text().replace(
        "  writable: [ekf_mode, airbrakes_mode, dn1_airbrake_cmd, cn_fault]",
        "  writable: [ekf_mode, airbrakes_mode, dn1_airbrake_cmd, cn_fault, ev_apogee]",
    )
    path = tmp_path / "flight.yaml"
    path.write_text(text.replace('pythonpath: [".."]', f"pythonpath: [{str(ROOT)!r}]"))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "element 'ev_apogee' is read by a transition of state ABORTED" in err
    assert err.rstrip().endswith("- at `$.commands.writable[4]`")
