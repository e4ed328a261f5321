"""Safety smells that `zplatform check` reports (zplatform.mission.safety)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from zplatform import SafetyWarning, decode_mission, load_mission, safety_warnings
from zplatform.cli.main import main
from zplatform.control.devices import Actuator
from zplatform.core.datavector import DataVector

ROOT = Path(__file__).resolve().parents[2]
HERE = __name__


class NoSafe(Actuator):
    """An actuator that never says what a lost control node should leave."""

    def run(self, t_ns: int) -> None:
        pass


class Squib(Actuator):
    """A pyrotechnic by its class, with a safe value."""

    pyrotechnic = True

    def bind(self, dv: DataVector) -> None:
        self.board.set_digital(1, False)

    def run(self, t_ns: int) -> None:
        pass

    def safe(self, t_ns: int) -> None:
        self.board.set_digital(1, False)


def haz() -> dict[str, object]:
    """A hazardous LAUNCH, and how an operator clears a fault that refuses
    it (``fault_never_cleared`` otherwise)."""
    return {"hazardous": ["LAUNCH"], "writable": ["cn_fault"]}


def mission(**sections: object) -> dict[str, object]:
    doc: dict[str, object] = {
        "mission": "smells",
        "nodes": {"cn": {}, "dn0": {}, "gn": {}},
        "regions": {
            "cn": [{"name": "valve", "type": "bool"}],
            "cn_to_dn0": [{"name": "fire", "type": "bool"}],
        },
        "state_machine": {"initial": "SAFE", "states": {"SAFE": {}, "FLIGHT": {}}},
        "controllers": [
            {
                "name": "vent",
                "class": "tests.unit.test_controllers:Recorder",
                "node": "cn",
                "config": {"out": "valve"},
            },
        ],
        "devices": [
            {
                "name": "ign",
                "class": "zplatform.control.devices:DigitalOutput",
                "node": "dn0",
                "config": {"pin": 0, "command": "fire"},
            },
        ],
        "commands": {"writable": ["vent_mode"]},  # deny by default: the mode is listed
    }
    doc.update(sections)
    return doc


def warnings_of(doc: dict[str, object]) -> list[SafetyWarning]:
    return safety_warnings(decode_mission(yaml.safe_dump(doc)))


def test_a_plain_write_that_can_enable_a_controller_is_reported() -> None:
    """The issue's case: no `hazardous:` list, so controller modes are not
    protected and one unconfirmed WRITE enables the controller in SAFE."""
    (w,) = warnings_of(mission())
    assert (w.kind, w.path) == ("unprotected_mode", "$.controllers[0]")
    assert "vent_mode" in w.message and "commands.protected" in w.message
    assert str(w).endswith(" - at `$.controllers[0]`")


@pytest.mark.parametrize(
    "commands",
    [
        # modes are protected by default then
        {"hazardous": ["LAUNCH"], "writable": ["vent_mode", "cn_fault"]},
        {
            "protected": ["vent_mode"],
            "writable": ["vent_mode"],
            "whitelist": {"SAFE": ["ARM", "WRITE"]},
        },
        {"whitelist": {"SAFE": ["NOOP"], "FLIGHT": ["ABORT"]}},  # no WRITE anywhere
        {"writable": ["valve"]},  # the mode is not writable at all
        {},  # nothing is writable by default
    ],
)
def test_protected_or_unwritable_modes_are_fine(commands: dict[str, object]) -> None:
    assert warnings_of(mission(commands=commands)) == []


def test_without_a_ground_node_no_command_smell() -> None:
    doc = mission()
    doc["nodes"] = {"cn": {}, "dn0": {}}
    assert warnings_of(doc) == []


def test_an_actuator_without_a_safe_value() -> None:
    doc = mission(commands=haz())
    doc["devices"] = [
        {
            "name": "ign",
            "class": "zplatform.control.devices:DigitalOutput",
            "node": "dn0",
            "config": {"pin": 0, "command": "fire"},
        },
        {"name": "heater", "class": f"{HERE}:NoSafe", "node": "dn0"},
    ]
    (w,) = warnings_of(doc)
    assert (w.kind, w.path) == ("no_safe_value", "$.devices[1]")
    assert f"'heater' ({HERE}:NoSafe)" in w.message


def test_pyrotechnic_outputs_need_hazardous_commands() -> None:
    doc = mission(
        commands={
            "protected": ["vent_mode"],
            "writable": ["vent_mode"],
            "whitelist": {"SAFE": ["ARM", "WRITE"]},
        }
    )
    doc["devices"][0]["config"]["pyrotechnic"] = True  # type: ignore[index]
    doc["devices"].append({"name": "cutter", "class": f"{HERE}:Squib", "node": "dn0"})  # type: ignore[attr-defined]
    doc["recorder"] = {}  # a control node that resumes after a restart: not this test's smell
    (w,) = warnings_of(doc)
    assert (w.kind, w.path) == ("pyrotechnic_without_hazardous", "$.commands.hazardous")
    assert "(ign, cutter)" in w.message
    doc["commands"] = haz()
    assert warnings_of(doc) == []


def test_a_pyrotechnic_mission_whose_control_node_cannot_resume() -> None:
    """Pyrotechnic outputs, one control node and no flight recorder for it: a
    control node lost in flight ends the flight, and one restarted mid-run
    starts over. A recorder (it resumes from it) or a standby closes it."""
    doc = mission(commands=haz())
    doc["devices"][0]["config"]["pyrotechnic"] = True  # type: ignore[index]
    (w,) = warnings_of(doc)
    assert (w.kind, w.path) == ("control_node_cannot_resume", "$.nodes")
    assert "(ign)" in w.message and "cn_b" in w.message and "recorder" in w.message
    doc["recorder"] = {}
    assert warnings_of(doc) == []


def test_a_hazardous_mission_on_plain_links(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Plain links are the mission's choice (the flood tests need them), and
    `check` says what it costs; `--strict` refuses it."""
    doc = mission(commands=haz(), security={"transport": "plain"})
    (w,) = warnings_of(doc)
    assert (w.kind, w.path) == ("plain_transport_with_hazardous", "$.security.transport")
    assert "hazardous commands (LAUNCH)" in w.message and "auto" in w.message
    doc["security"] = {"transport": "auto"}  # mutual TLS: nothing to say
    assert warnings_of(doc) == []
    doc["security"] = {"transport": "plain"}
    # nothing hazardous: plain is the default
    doc["commands"] = {"protected": ["vent_mode"], "writable": ["vent_mode"]}
    assert warnings_of(doc) == []
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(mission(commands=haz())))
    assert main(["check", str(path), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert (rep["transport"], rep["deployment"]) == ("mtls", None)
    assert main(["check", str(path)]) == 0
    assert "links: mutual TLS with access control (security.transport is auto and the " in (
        capsys.readouterr().out
    )


def test_the_igniter_mission_is_clean_and_its_igniters_are_pyrotechnic() -> None:
    path = ROOT / "configs" / "recovery_igniter.yaml"
    assert safety_warnings(load_mission(path)) == []
    doc = yaml.safe_load(path.read_text())
    del doc["commands"]["hazardous"]
    doc["commands"].pop("protected", None)
    reduced = decode_mission(yaml.safe_dump(doc), base_dir=path.parent)
    kinds = {(w.kind, w.path) for w in safety_warnings(reduced)}
    assert ("pyrotechnic_without_hazardous", "$.commands.hazardous") in kinds
    assert ("unprotected_mode", "$.controllers[2]") in kinds  # safety0: the igniter's guard


def test_check_prints_warnings_lists_them_in_json_and_strict_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(mission()))
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert "mission smells: OK, 1 safety warning(s)" in out
    assert err.startswith("zplatform: warning: controller 'vent': a plain WRITE") and err.endswith(
        " - at `$.controllers[0]`\n"
    )
    assert main(["check", str(path), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["ok"] is True
    assert [(w["kind"], w["path"]) for w in rep["warnings"]] == [
        ("unprotected_mode", "$.controllers[0]")
    ]
    assert main(["check", str(path), "--strict"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("zplatform: error: controller 'vent'")
    assert main(["check", str(path), "--strict", "--json"]) == 2
    assert json.loads(capsys.readouterr().out)["ok"] is False
    clean = tmp_path / "clean.yaml"
    clean.write_text(yaml.safe_dump(mission(commands=haz())))
    assert main(["check", str(clean), "--strict"]) == 0
    out, err = capsys.readouterr()
    assert err == "" and "mission smells: OK  (" in out


def test_a_fault_no_write_can_clear_refuses_the_launch_until_a_restart() -> None:
    """LAUNCH is refused while a fault is latched (commands.refused_while_faulted):
    a mission where no WRITE may clear cn_fault in the states that accept it
    keeps a pad fault until the control node restarts."""
    doc = mission(commands={"hazardous": ["LAUNCH"], "whitelist": {"FLIGHT": ["NOOP"]}})
    (w,) = warnings_of(doc)
    assert (w.kind, w.path) == ("fault_never_cleared", "$.commands.writable")
    assert w.message.startswith("a fault latched in SAFE refuses LAUNCH until the control node")
    assert "write_states: {cn_fault: [SAFE]}" in w.message
    doc["commands"] = {
        **haz(),
        "write_states": {"cn_fault": ["SAFE"]},
        "whitelist": {"FLIGHT": ["NOOP"]},
    }
    assert warnings_of(doc) == []
    doc["commands"] = {"hazardous": ["LAUNCH"], "refused_while_faulted": []}
    assert warnings_of(doc) == []  # the mission's choice: LAUNCH is never refused for a fault
