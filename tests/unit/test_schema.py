"""`zplatform schema`: the mission file's JSON Schema and the reference generated from it."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from zplatform.boards import BUILTIN_DRIVERS
from zplatform.cli.main import main
from zplatform.mission.load import decode_mission
from zplatform.mission.schema import (
    BOARD_CONFIGS,
    REFERENCE_PATH,
    builtin_devices,
    mission_schema,
    reference_markdown,
)

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted((ROOT / "configs").glob("*.yaml"))


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    schema = mission_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _errors(validator: jsonschema.Draft202012Validator, doc: dict[str, Any]) -> list[str]:
    return [e.message for e in validator.iter_errors(doc)]


def _minimal() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "configs" / "minimal.yaml").read_text())


def test_the_shipped_missions_exist() -> None:
    assert len(SHIPPED) >= 4, SHIPPED


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_mission_validates(
    validator: jsonschema.Draft202012Validator, path: Path
) -> None:
    """A file `zplatform check` accepts is never refused by the schema."""
    decode_mission(path.read_text(), str(path))  # the platform accepts it...
    assert _errors(validator, yaml.safe_load(path.read_text())) == []  # ...and so does the schema


@pytest.mark.parametrize(
    "where",
    [
        ("lisen",),
        ("nodes", "cn", "lisen"),
        ("regions", "cn", 0, "initail"),
        ("state_machine", "states", "RUN", "transitions", 0, "after"),
        ("commands", "hazzardous"),
        ("faults", "dn_lost"),
    ],
    ids=lambda w: ".".join(map(str, w)),
)
def test_an_unknown_key_is_refused(
    validator: jsonschema.Draft202012Validator, where: tuple[Any, ...]
) -> None:
    doc = _minimal()
    node: Any = doc
    for key in where[:-1]:
        node = node.setdefault(key, {}) if isinstance(key, str) else node[key]
    node[where[-1]] = 1
    errors = _errors(validator, doc)
    assert errors, where
    assert any(repr(where[-1]) in e for e in errors), errors


@pytest.mark.parametrize(
    ("where", "value"),
    [
        (("loop_hz",), 0),
        (("loop_hz",), 20_000),
        (("faults", "dn_watchdog_loops"), 0),
        (("nodes", "cn", "priority"), 100),
        (("transport", "sync_query"), "sometimes"),
        (("regions", "cn", 0, "limits"), {"red": [1, 2, 3]}),
    ],
    ids=lambda v: ".".join(map(str, v)) if isinstance(v, tuple) else repr(v),
)
def test_types_and_bounds_are_checked(
    validator: jsonschema.Draft202012Validator, where: tuple[Any, ...], value: object
) -> None:
    doc = _minimal()
    node: Any = doc
    for key in where[:-1]:
        node = node.setdefault(key, {}) if isinstance(key, str) else node[key]
    node[where[-1]] = value
    assert _errors(validator, doc), (where, value)


def test_a_board_follows_its_driver(validator: jsonschema.Draft202012Validator) -> None:
    doc = _minimal()

    def with_board(board: dict[str, Any]) -> list[str]:
        d = copy.deepcopy(doc)
        d["nodes"]["dn0"]["board"] = board
        return _errors(validator, d)

    assert with_board({}) == []
    assert with_board({"digital_pins": 4, "physics": "m:f", "params": {"x": 1}}) == []
    assert with_board({"driver": "serial", "port": "/dev/ttyACM0", "safe_digital": {0: True}}) == []
    assert with_board({"driver": "gpiod", "outputs": {0: 17}, "bias": "pull-up"}) == []
    assert with_board({"driver": "team.boards:Hat", "spi_bus": 0}) == []
    assert with_board({"driver": "serial"})  # no port
    assert with_board({"driver": "serial", "port": "p", "physics": "m:f"})  # a sim key
    assert with_board({"driver": "gpiod", "bias": "up"})
    assert with_board({"driver": "nonsense"})


def test_a_builtin_device_config_follows_its_class(
    validator: jsonschema.Draft202012Validator,
) -> None:
    doc = _minimal()
    device = {"name": "led", "class": "zplatform.control.devices:DigitalOutput", "node": "dn0"}
    doc["devices"] = [{**device, "config": {"pin": 0, "command": "dn0_setpoint"}}]
    assert _errors(validator, doc) == []
    doc["devices"] = [{**device, "config": {"pin": 0, "comand": "dn0_setpoint"}}]
    assert _errors(validator, doc)
    # A team's own class: its config is checked by `zplatform check`, not here.
    doc["devices"] = [{**device, "class": "team.devs:Valve", "config": {"anything": 1}}]
    assert _errors(validator, doc) == []


def test_every_key_has_a_description() -> None:
    """One source: a key added to a struct without `Meta(description=...)`
    (or a struct without a docstring) fails here, naming it."""
    schema = mission_schema()
    missing = []
    for name, d in schema["$defs"].items():
        if not d.get("description"):
            missing.append(name)
        for key, prop in d.get("properties", {}).items():
            described = prop.get("description") or (
                "$ref" in prop and schema["$defs"][prop["$ref"].split("/")[-1]].get("description")
            )
            if not described:
                missing.append(f"{name}.{key}")
    assert missing == []


def test_every_builtin_board_and_device_is_covered() -> None:
    # `world` takes no config of its own (its pins are under $.world): the
    # schema has a branch for it beside the configs of the others.
    assert set(BOARD_CONFIGS) | {"world"} == set(BUILTIN_DRIVERS)
    assert set(builtin_devices()) >= {
        "zplatform.control.devices:AnalogInput",
        "zplatform.control.devices:AnalogOutput",
        "zplatform.control.devices:DigitalInput",
        "zplatform.control.devices:DigitalOutput",
    }


def test_the_verb_prints_the_schema_as_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == mission_schema()
    assert printed["$schema"] == "https://json-schema.org/draft/2020-12/schema"


def test_the_verb_writes_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mission.schema.json"
    assert main(["schema", "--out", str(out)]) == 0
    assert json.loads(out.read_text()) == mission_schema()
    md = tmp_path / "ref.md"
    assert main(["schema", "--markdown", "--out", str(md)]) == 0
    assert md.read_text() == reference_markdown()
    capsys.readouterr()
    assert main(["schema", "--out", str(tmp_path / "no" / "such.json")]) == 2
    assert "zplatform: error: cannot write the mission schema" in capsys.readouterr().err


def test_the_reference_names_every_key_by_its_yaml_path() -> None:
    text = reference_markdown()
    for path in (
        "`$.nodes.<node>.listen`",
        "`$.regions.<region>[i].initial`",
        "`$.state_machine.states.<state>.actions[i].at_s`",
        "`$.state_machine.states.<state>.transitions[i].after_s`",
        "`$.state_machine.states.<state>.transitions[i].op`",
        "`$.controllers[i].config`",
        "`$.commands.protected`",
        "`$.nodes.<dnX>.board.physics`",
        "`$.nodes.<dnX>.board.params`",
        "`$.nodes.<dnX>.board.port`",
        "`$.devices[i].config.feedback`",
        "`cn_fault`",
        "`dnX_safed`",
    ):
        assert path in text, path


def test_the_committed_reference_is_up_to_date() -> None:
    """docs/mission-reference.md is generated: it never drifts from the structs."""
    committed = (ROOT / REFERENCE_PATH).read_text(encoding="utf-8")
    assert committed == reference_markdown(), (
        f"{REFERENCE_PATH} is out of date; regenerate it from the repository root with\n"
        f"    zplatform schema --markdown --out {REFERENCE_PATH}"
    )
