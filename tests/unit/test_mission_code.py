"""Where a mission's code comes from: ``pythonpath`` and ``load_mission(code=False)``.

A team's mission is a YAML file with its Python package beside it. The verbs
that run flight code import that package through the mission's
``pythonpath`` (default: the mission file's directory), without PYTHONPATH;
the ground verbs load the mission with ``code=False`` and import nothing of
it, so they work on a ground station that has only the mission file.
"""

from __future__ import annotations

import os
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from zplatform import DataVector, Layout, LockstepRunner
from zplatform.config import relocate_mission, resolve_pythonpath
from zplatform.errors import ConfigError
from zplatform.mission.load import decode_mission, load_mission
from zplatform.runtime.transport import rewrite_endpoints
from zplatform.sim.replay_recording import MISSION_FILE, Recorder

CODE = '''
"""A team's mission code (test fixture)."""

from zplatform import Controller, Sensor


class Valve(Controller):
    def bind(self, dv):
        self._out = self.output("valve_cmd", "", kinds=("bool",))

    def run_enabled(self, t_ns):
        self._out.set(True)

    def run_safed(self, t_ns):
        self._out.set(False)


class Gauge(Sensor):
    def bind(self, dv):
        self._out = self.output("pressure", "", kinds=("float",))

    def run(self, t_ns):
        self._out.set(self.board.get_analog(0))


def physics(board, t_ns):
    board.inject_analog(0, 1.5)
'''


def team_mission(directory: Path, pkg: str, *, pythonpath: list[str] | None = None) -> Path:
    """A mission ``hotfire`` in ``directory`` whose controller, device and
    physics live in package ``pkg`` (not written here: see :func:`write_code`)."""
    doc = {
        "mission": "hotfire",
        "nodes": {
            "cn": {"listen": ["tcp/127.0.0.1:7600"]},
            "dn0": {
                "listen": ["tcp/127.0.0.1:7601"],
                "connect": ["tcp/127.0.0.1:7600"],
                "board": {"physics": f"{pkg}:physics"},
            },
            "gn": {"listen": ["tcp/127.0.0.1:7602"], "connect": ["tcp/127.0.0.1:7600"]},
        },
        "regions": {
            "cn": [{"name": "valve_cmd", "type": "bool"}],
            "dn0_to_cn": [{"name": "pressure", "type": "f32"}],
        },
        "state_machine": {
            "initial": "SAFE",
            "states": {
                "SAFE": {
                    "actions": [{"element": "valve_mode", "value": "safed"}],
                    "transitions": [
                        {"element": "cn_cmd", "op": "==", "value": "LAUNCH", "to": "FIRE"}
                    ],
                },
                "FIRE": {"actions": [{"element": "valve_mode", "value": "enabled"}]},
            },
        },
        "commands": {"hazardous": ["LAUNCH"]},
        "controllers": [{"name": "valve", "class": f"{pkg}:Valve", "node": "cn"}],
        "devices": [{"name": "gauge", "class": f"{pkg}:Gauge", "node": "dn0"}],
    }
    if pythonpath is not None:
        doc["pythonpath"] = pythonpath
    path = directory / "hotfire.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def write_code(directory: Path, pkg: str) -> None:
    (directory / pkg).mkdir(parents=True)
    (directory / pkg / "__init__.py").write_text(textwrap.dedent(CODE))


def pkg_name(tmp_path: Path) -> str:
    """A package name no other test imports (sys.modules caches by name)."""
    return "hotfire_" + "".join(c for c in tmp_path.name if c.isalnum())


def team_dir(tmp_path: Path) -> tuple[str, Path]:
    """``(package, directory)``: tmp_path/team holding the team's package."""
    pkg = pkg_name(tmp_path)
    team = tmp_path / "team"
    team.mkdir()
    write_code(team, pkg)
    return pkg, team


def test_a_mission_finds_its_package_next_to_it_from_any_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pkg, mission_dir = team_dir(tmp_path)
    path = team_mission(mission_dir, pkg)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    before = list(sys.path)
    m = load_mission(path)
    assert m.pythonpath == [str(mission_dir)]
    assert sys.path == before  # on sys.path while importing, not after
    r = LockstepRunner(m)  # builds every node: the controller, the device, the physics
    r.run(0.05)
    assert r.devices[0].dv.get("pressure") == pytest.approx(1.5)
    assert sys.modules[pkg].__file__ == str(mission_dir / pkg / "__init__.py")


def test_pythonpath_entries_are_relative_to_the_mission_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pkg = pkg_name(tmp_path)
    write_code(tmp_path / "lib", pkg)
    (tmp_path / "missions").mkdir()
    path = team_mission(tmp_path / "missions", pkg, pythonpath=["../lib"])
    monkeypatch.chdir("/")
    m = load_mission(path)
    assert m.pythonpath == [str(tmp_path / "lib")]
    assert pkg in sys.modules


def test_a_missing_pythonpath_directory_is_refused_with_its_path(tmp_path: Path) -> None:
    path = team_mission(tmp_path, pkg_name(tmp_path), pythonpath=[".", "nope"])
    with pytest.raises(ConfigError, match=r"'.*nope' does not exist.* - at `\$\.pythonpath\[1\]`"):
        load_mission(path)


def test_without_the_code_the_error_names_the_class_path_and_where_it_looked(
    tmp_path: Path,
) -> None:
    pkg = pkg_name(tmp_path)
    path = team_mission(tmp_path, pkg)
    with pytest.raises(ConfigError) as ei:
        load_mission(path)
    assert ei.value.path == "$.controllers[0].class"
    assert f"cannot import module '{pkg}'" in str(ei.value)
    assert str(tmp_path) in str(ei.value)  # the directories it searched


def test_code_false_imports_nothing_and_keeps_the_layout(tmp_path: Path) -> None:
    """A ground station with only the mission file: every check that needs
    no code runs, no class is imported, and the layout is the one the flight
    nodes have (controller modes come from the YAML, not the class)."""
    pkg = pkg_name(tmp_path)
    with_code = tmp_path / "with"
    with_code.mkdir()
    write_code(with_code, pkg)
    flight = load_mission(team_mission(with_code, pkg))
    ground_only = tmp_path / "ground"
    ground_only.mkdir()
    path = team_mission(ground_only, pkg + "_absent")
    m = load_mission(path, code=False)
    assert pkg + "_absent" not in sys.modules
    a, b = Layout.for_node(flight, "cn"), Layout.for_node(m, "cn")
    assert (a.layout_id, a.size, list(a.elements)) == (b.layout_id, b.size, list(b.elements))
    assert "valve_mode" in b.elements
    for dn in m.device_nodes:
        assert Layout.for_node(flight, dn).layout_id == Layout.for_node(m, dn).layout_id
    # A missing pythonpath directory matters only to code: not checked here.
    team = yaml.safe_load(path.read_text())
    team["pythonpath"] = ["nope"]
    path.write_text(yaml.safe_dump(team))
    load_mission(path, code=False)


def test_code_false_still_checks_everything_else(tmp_path: Path) -> None:
    path = team_mission(tmp_path, pkg_name(tmp_path) + "_absent")
    doc = yaml.safe_load(path.read_text())
    doc["state_machine"]["states"]["SAFE"]["transitions"][0]["to"] = "NOWHERE"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="NOWHERE"):
        load_mission(path, code=False)
    doc = yaml.safe_load(team_mission(tmp_path, "x").read_text())
    doc["commands"]["hazardous"] = ["FLY"]
    with pytest.raises(ConfigError, match=r"\$\.commands\.hazardous"):
        decode_mission(yaml.safe_dump(doc), code=False)


def test_resolve_pythonpath() -> None:
    assert resolve_pythonpath(None, "/a/b") == ["/a/b"]
    assert resolve_pythonpath(None, None) == []
    assert resolve_pythonpath(["..", "lib", "/abs"], "/a/b") == ["/a", "/a/b/lib", "/abs"]
    assert resolve_pythonpath(["lib"], None) == [os.path.join(os.getcwd(), "lib")]


def test_copies_of_a_mission_keep_finding_its_code(tmp_path: Path) -> None:
    """`up --free-ports` (rewrite_endpoints) and a recording copy the mission
    elsewhere: the copy's pythonpath is absolute, against the source's directory."""
    pkg, team = team_dir(tmp_path)
    src = team_mission(team, pkg)
    out = tmp_path / "runtime"
    out.mkdir()
    rewrite_endpoints(src, out / "m.yaml")
    assert load_mission(out / "m.yaml").pythonpath == [str(team)]

    rel = team_mission(team, pkg, pythonpath=["."])
    rec = tmp_path / "rec"
    m = load_mission(rel)
    Recorder(rec, m, rel, DataVector(Layout.for_node(m, "cn"))).close()
    assert yaml.safe_load((rec / MISSION_FILE).read_text())["pythonpath"] == [str(team)]
    assert load_mission(rec / MISSION_FILE).pythonpath == [str(team)]

    raw: dict[str, object] = {"pythonpath": 3}  # malformed: left for the loader
    relocate_mission(raw, src)
    assert raw["pythonpath"] == 3
