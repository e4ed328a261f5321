"""Mission parameters (zplatform.control.params): config checks, PRM_SET and PRM_SAVE
through the CN's loop with real (authenticated) request frames, the
parameter file, loading at start, and the ground's side."""

from __future__ import annotations

import logging
import textwrap
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.waits import wait_until
from zplatform import ControlLogic, decode_mission
from zplatform.config import Mission, parse_mission
from zplatform.config.codes import ParamLoad
from zplatform.console.model import ConsoleModel
from zplatform.control.commands import writable_elements
from zplatform.control.params import (
    ParamFileError,
    ParamSaver,
    SaveResult,
    decode_params,
    encode_params,
    params_layout_id,
    params_path,
    read_params_file,
)
from zplatform.control.uplink import Uplink, element_index, parse_commands, validate_command
from zplatform.core.auth import KeySet
from zplatform.errors import CommandError, ConfigError
from zplatform.ground.logic import needs_arm
from zplatform.telemetry.records import param_rows

S = 1_000_000_000
PERIOD = 10_000_000
KEY = b"k" * 32
EPOCH = 77

BASE = """
mission: prmtest
nodes: {cn: {}, gn: {}}
params:
  - {name: gain, type: f32, default: 1.5, min: 0.0, max: 10.0, units: 1/s,
     doc: "a controller gain"}
  - {name: deploy_m, type: u16, default: 150, min: 60, max: 350, units: m,
     states: [PAD], hazardous: true}
  - {name: use_gps, type: bool, default: true, states: [PAD, FLY]}
regions:
  cn:
    - {name: x, type: f32}
state_machine:
  initial: PAD
  states:
    PAD:
      transitions:
        - {element: cn_cmd, op: "==", value: LAUNCH, to: FLY}
    FLY:
      transitions:
        - {element: cn_cmd, op: "==", value: ABORT, to: PAD}
commands:
  whitelist:
    PAD: [NOOP, ARM, LAUNCH, WRITE, PRM_SET, PRM_SAVE]
    FLY: [NOOP, ABORT, ARM, PRM_SET]
"""


def mission(text: str = BASE) -> Mission:
    return decode_mission(textwrap.dedent(text))


def variant(old: str, new: str) -> str:
    assert old in BASE, old
    return BASE.replace(old, new)


def config_error(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        mission(text)
    return info.value


# --------------------------------------------------------------------------- config


def test_each_parameter_is_an_element_of_cn_named_after_it() -> None:
    m = mission()
    cn = [e.name for e in m.regions["cn"]]
    for name in ("gain", "deploy_m", "use_gps", "cn_prm_load_status", "cn_prm_save_status"):
        assert name in cn
    assert m.element("gain")[1].initial == 1.5
    assert m.element("deploy_m")[1].type == "u16"


def test_a_mission_without_parameters_has_no_parameter_elements() -> None:
    m = mission(BASE.split("params:")[0] + "regions:" + BASE.split("regions:")[1])
    assert not any(e.name.startswith("cn_prm_") for e in m.regions["cn"])


@pytest.mark.parametrize(
    ("old", "new", "path", "text"),
    [
        ("default: 1.5", "default: 11", "$.params[0].default", "outside [0.0, 10.0]"),
        ("min: 0.0, max: 10.0", "min: 10.0, max: 0.0", "$.params[0].min", "above max"),
        ("type: f32", "type: 'f32[3]'", "$.params[0].type", "not a scalar type"),
        ("type: f32", "type: enum", "$.params[0].type", "not a scalar type"),
        ("min: 0.0, max: 10.0, ", "", "$.params[0].min", "needs `min`"),
        ("max: 350", "max: 70000", "$.params[1].max", "not a finite u16"),
        ("default: 150", "default: 150.5", "$.params[1].default", "not a finite u16"),
        ("default: 1.5", "default: .nan", "$.params[0].default", "not a finite f32"),
        ("default: true", "default: true, min: 0", "$.params[2].min", "no bounds"),
        ("states: [PAD], ", "states: [PADD], ", "$.params[1].states[0]", "not a state"),
        ("name: deploy_m", "name: gain", "$.params[1].name", "duplicate parameter"),
        ("name: deploy_m", "name: Deploy", "$.params[1].name", "must match"),
        ("{name: x, type: f32}", "{name: gain, type: f32}", "$.params[0].name", "rename one"),
    ],
)
def test_a_bad_parameter_is_refused_at_load_with_its_path(
    old: str, new: str, path: str, text: str
) -> None:
    err = config_error(variant(old, new))
    assert err.path == path and text in err.reason, err


def test_a_parameter_clashing_with_a_platform_element_is_refused() -> None:
    err = config_error(variant("name: gain", "name: cn_loop"))
    assert err.path == "$.params[0].name" and "rename one" in err.reason


def test_write_cannot_set_a_parameter() -> None:
    err = config_error(BASE + "  writable: [x, gain]\n")
    assert err.path == "$.commands.writable[1]" and "is a parameter" in err.reason
    err = config_error(BASE + "  hazardous: [LAUNCH]\n  protected: [gain]\n")
    assert err.path == "$.commands.protected[0]" and "is a parameter" in err.reason
    # writable_elements skips parameters, whatever a mission lists (parsed unchecked here).
    m = parse_mission(textwrap.dedent(BASE + "  writable: [x, gain]\n"))
    assert writable_elements(m) == ["x"]
    assert "gain" not in writable_elements(mission())


def test_a_state_machine_action_cannot_set_a_parameter() -> None:
    err = config_error(
        variant("    PAD:\n", "    PAD:\n      actions:\n        - {element: gain, value: 2}\n")
    )
    assert err.path == "$.state_machine.states.PAD.actions[0].element"
    assert "is a parameter" in err.reason


def test_a_hazardous_parameter_needs_arm_wherever_it_may_change() -> None:
    text = variant("FLY: [NOOP, ABORT, ARM, PRM_SET]", "FLY: [NOOP, ABORT, PRM_SET]")
    err = config_error(text.replace("states: [PAD], hazardous", "hazardous"))
    assert err.path == "$.params[1].hazardous" and "state FLY" in err.reason


def test_a_parameter_no_state_may_change_is_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, "zplatform.params"):
        text = variant("states: [PAD, FLY]", "states: [FLY]")
        mission(text.replace("FLY: [NOOP, ABORT, ARM, PRM_SET]", "FLY: [NOOP, ABORT, ARM]"))
    assert "parameter use_gps can change in no state" in caplog.text


# --------------------------------------------------------------------------- the CN


class Cn:
    """A ControlLogic and the ground's uplink: real, authenticated request frames."""

    def __init__(self, m: Mission | None = None, key: bytes | None = KEY) -> None:
        self.m = m or mission()
        keys = KeySet.from_master(self.m, key) if key is not None else None
        self.cn = ControlLogic(self.m, keys=keys and keys.for_node("cn"), epoch=EPOCH)
        self.up = Uplink(self.m, keys and keys.for_node("gn"))
        self.dv = self.cn.dv
        self.loop = 0
        self.seq = 0
        self.events: list[str] = []

    def step(self, *frames: bytes, saves: tuple[SaveResult, ...] = ()) -> None:
        self.loop += 1
        self.cn.begin(self.loop, self.loop * PERIOD)
        self.cn.finish(list(frames), saves=saves)
        self.events += [f"{e.id}: {e.text}" for e in self.cn.events.drain()]

    def frame(self, command: str, *args: str, seq: int | None = None) -> bytes:
        cmd, index, value = validate_command(self.m, command, *args)
        return bytes(self.up.frame(cmd, seq or self.seq + 1, index, value, 0, EPOCH))

    def send(self, command: str, *args: str) -> str:
        """One request as a frame; returns its verdict (either status)."""
        self.seq += 1
        rejects = self.dv.get("cn_cmd_rejects")
        self.step(self.frame(command, *args, seq=self.seq))
        if self.dv.get("cn_cmd_rejects") != rejects:
            return self.dv.get_name("cn_cmd_reject_status")
        return self.dv.get_name("cn_cmd_status")

    def raw(self, command: str, index: int, value: float) -> str:
        self.seq += 1
        self.step(bytes(self.up.frame(command, self.seq, index, value, 0, EPOCH)))
        return self.dv.get_name("cn_cmd_status")

    def last(self, prefix: str) -> str:
        return next(e for e in reversed(self.events) if e.startswith(prefix))


def test_prm_set_changes_the_parameter_and_says_from_what() -> None:
    c = Cn()
    assert c.send("prm_set", "gain", "2.25") == "ACCEPTED"
    assert c.dv.get("gain") == 2.25 and c.dv.get("cn_prm_unsaved") is True
    assert c.last("cmd_accepted").endswith("accepted (gain = 2.25, was 1.5)")
    assert c.send("prm_set", "use_gps", "off") == "ACCEPTED" and c.dv.get("use_gps") is False
    assert c.send("prm_set", "gain", "2.2") == "ACCEPTED"  # an f32: said as it is stored
    assert c.last("cmd_accepted").endswith("accepted (gain = 2.2, was 2.25)")


def test_prm_set_outside_its_bounds_is_rejected_with_its_own_status() -> None:
    c = Cn()
    assert c.raw("PRM_SET", element_index(c.m, "gain"), 10.5) == "REJECTED_OUT_OF_BOUNDS"
    assert c.dv.get("gain") == 1.5 and c.dv.get("cn_prm_unsaved") is False
    assert "10.5 is outside gain's bounds [0.0, 10.0] 1/s" in c.last("cmd_rejected")
    assert c.raw("PRM_SET", element_index(c.m, "gain"), -0.001) == "REJECTED_OUT_OF_BOUNDS"
    assert c.raw("PRM_SET", element_index(c.m, "gain"), 10.0) == "ACCEPTED"  # bounds included


def test_prm_set_of_a_value_the_type_cannot_hold_is_a_bad_argument() -> None:
    c = Cn()
    gain, deploy = element_index(c.m, "gain"), element_index(c.m, "deploy_m")
    assert c.raw("PRM_SET", gain, float("nan")) == "REJECTED_BAD_ARGUMENT"
    assert c.send("arm") == "ACCEPTED"
    assert c.raw("PRM_SET", deploy, 200.5) == "REJECTED_BAD_ARGUMENT"  # u16
    assert c.raw("PRM_SET", element_index(c.m, "x"), 1.0) == "REJECTED_BAD_ARGUMENT"
    assert "element x is not a parameter" in c.last("cmd_rejected")
    assert c.raw("PRM_SET", 9999, 1.0) == "REJECTED_BAD_ARGUMENT"
    assert c.dv.get("gain") == 1.5 and c.dv.get("deploy_m") == 150


def test_prm_set_in_a_state_the_parameter_forbids_is_rejected_with_its_own_status() -> None:
    c = Cn()
    assert c.send("launch") == "ACCEPTED" and c.dv.get_name("cn_state") == "FLY"
    assert c.send("arm") == "ACCEPTED"
    assert c.send("prm_set", "deploy_m", "200") == "REJECTED_PARAM_STATE"
    assert "parameter deploy_m may not change in state FLY (only in PAD)" in c.last("cmd_rejected")
    assert c.dv.get("deploy_m") == 150
    assert c.send("prm_set", "use_gps", "false") == "ACCEPTED"  # FLY is one of its states
    assert c.send("prm_save") == "REJECTED_NOT_ALLOWED"  # FLY's whitelist: no PRM_SAVE


def test_a_hazardous_parameter_needs_arm_just_before() -> None:
    c = Cn()
    assert c.send("prm_set", "deploy_m", "200") == "REJECTED_NOT_ARMED"
    assert c.send("arm") == "ACCEPTED"
    assert c.send("prm_set", "deploy_m", "200") == "ACCEPTED" and c.dv.get("deploy_m") == 200
    assert c.send("prm_set", "deploy_m", "210") == "REJECTED_NOT_ARMED"  # one ARM, one set
    assert c.dv.get("deploy_m") == 200


def test_unauthenticated_replayed_or_foreign_prm_set_changes_nothing() -> None:
    c = Cn()
    gain = element_index(c.m, "gain")
    other = KeySet.from_master(c.m, b"x" * 32).for_node("gn")
    forged = bytes(Uplink(c.m, other).frame("PRM_SET", 1, gain, 9.0, 0, EPOCH))
    c.step(forged)
    assert c.dv.get_name("cn_cmd_reject_status") == "REJECTED_AUTH" and c.dv.get("gain") == 1.5
    ok = c.frame("prm_set", "gain", "3", seq=1)
    c.step(ok)
    assert c.dv.get_name("cn_cmd_status") == "ACCEPTED" and c.dv.get("gain") == 3.0
    c.step(c.frame("prm_set", "gain", "4", seq=2))
    c.step(ok)  # the first frame again, captured and replayed
    assert c.dv.get_name("cn_cmd_reject_status") == "REJECTED_REPLAY"
    assert c.dv.get("gain") == 4.0 and c.dv.get("cn_cmd_seq") == 2
    c.step(bytes(c.up.frame("PRM_SET", 3, gain, 5.0, 0, EPOCH - 1)))  # another run's
    assert c.dv.get_name("cn_cmd_reject_status") == "REJECTED_EPOCH" and c.dv.get("gain") == 4.0
    assert c.dv.get("cn_cmd_rejects") == 3


def test_prm_save_queues_a_snapshot_and_its_result_is_an_input() -> None:
    c = Cn()
    c.send("prm_set", "gain", "2.5")
    assert c.send("prm_save") == "ACCEPTED"
    seq = c.seq
    assert c.dv.get("cn_prm_save_seq") == seq and c.dv.get_name("cn_prm_save_status") == "PENDING"
    assert c.dv.get("cn_prm_unsaved") is False
    got = c.cn.params.take_save()
    assert got is not None and got[0] == seq and c.cn.params.take_save() is None
    f = decode_params(c.m, got[1])
    assert f.values == {"gain": 2.5, "deploy_m": 150, "use_gps": True} and f.seq == seq
    assert c.send("prm_save") == "REJECTED_BUSY"  # still being written
    assert f"PRM_SAVE #{seq} is still being written" in c.last("cmd_rejected")
    c.send("prm_set", "gain", "3")  # a change while it is written: unsaved again
    c.step(saves=(SaveResult(seq - 1, True, "stale"),))  # not the pending save: ignored
    assert c.dv.get_name("cn_prm_save_status") == "PENDING"
    c.step(saves=(SaveResult(seq, True, "/x/prmtest.params"),))
    assert c.dv.get_name("cn_prm_save_status") == "SAVED"
    assert c.dv.get("cn_prm_unsaved") is True  # gain = 3 is not in that file
    saved = f"prm_saved: parameters saved (PRM_SAVE #{seq}) to /x/prmtest.params"
    assert c.last("prm_saved") == saved
    assert c.send("prm_save") == "ACCEPTED"
    c.step(saves=(SaveResult(c.seq, False, "/x: No space left on device"),))
    assert c.dv.get_name("cn_prm_save_status") == "FAILED" and c.dv.get("cn_prm_unsaved")
    failed = c.last("prm_save_failed")
    assert "failed: /x: No space left on device; the parameter file keeps" in failed


def test_prm_commands_in_a_mission_without_parameters_are_refused() -> None:
    m = decode_mission("mission: np\nnodes: {cn: {}, gn: {}}\nregions: {cn: [{name: x, type: u8}]}")
    c = Cn(m)
    assert c.raw("PRM_SAVE", 0, 0.0) == "REJECTED_NOT_ALLOWED"
    assert c.raw("PRM_SET", element_index(m, "x"), 1.0) == "REJECTED_NOT_ALLOWED"
    with pytest.raises(CommandError, match="has no parameters"):
        validate_command(m, "prm_save")
    with pytest.raises(CommandError, match="has no parameters"):
        validate_command(m, "prm_set", "x", "1")


# --------------------------------------------------------------------------- the file


def test_the_file_round_trips_and_names_its_mission_and_list() -> None:
    m = mission()
    data = encode_params(m, {"gain": 2.0, "deploy_m": 120, "use_gps": False}, seq=9, saved_ns=5)
    f = decode_params(m, data)
    assert (f.mission, f.seq, f.saved_ns) == ("prmtest", 9, 5)
    assert f.values == {"gain": 2.0, "deploy_m": 120, "use_gps": False}
    assert f.layout_id == params_layout_id(m)
    assert data[:6] == b"ZPPRM\x00"


def test_every_truncation_and_every_flipped_byte_is_refused() -> None:
    m = mission()
    data = encode_params(m, {"gain": 2.0, "deploy_m": 120, "use_gps": False})
    for n in range(len(data)):
        with pytest.raises(ParamFileError) as info:
            decode_params(m, data[:n])
        assert info.value.status == ParamLoad.CORRUPT, n
    for i in range(len(data)):
        bad = bytearray(data)
        bad[i] ^= 0x40
        with pytest.raises(ParamFileError) as info:
            decode_params(m, bytes(bad))
        assert info.value.status == ParamLoad.CORRUPT, i
    with pytest.raises(ParamFileError, match="bytes, the header says"):
        decode_params(m, data + b"\x00")


def test_another_mission_s_or_another_list_s_file_is_foreign() -> None:
    m = mission()
    other = mission(BASE.replace("mission: prmtest", "mission: other"))
    with pytest.raises(ParamFileError, match="saved by mission 'other'") as info:
        decode_params(m, encode_params(other, {"gain": 2.0, "deploy_m": 120, "use_gps": False}))
    assert info.value.status == ParamLoad.FOREIGN
    renamed = mission(variant("name: deploy_m", "name: main_m"))
    with pytest.raises(ParamFileError, match="another parameter list") as info:
        decode_params(m, encode_params(renamed, {"gain": 2.0, "main_m": 120, "use_gps": False}))
    assert info.value.status == ParamLoad.FOREIGN
    retyped = mission(variant("type: u16", "type: u32"))
    assert params_layout_id(retyped) != params_layout_id(m)
    rebounded = mission(variant("max: 350", "max: 300"))  # bounds are not the list
    assert params_layout_id(rebounded) == params_layout_id(m)


def test_the_start_loads_the_file_or_falls_back_to_defaults_with_an_event(
    tmp_path: Path,
) -> None:
    m = mission()
    good = encode_params(m, {"gain": 2.0, "deploy_m": 120, "use_gps": False}, seq=4)
    foreign = encode_params(
        mission(BASE.replace("prmtest", "zz")), {"gain": 2.0, "deploy_m": 1, "use_gps": True}
    )
    cases: list[tuple[bytes | OSError | None, str, dict[str, object], str]] = [
        (good, "LOADED", {"gain": 2.0, "deploy_m": 120}, "prm_loaded: parameters loaded"),
        (None, "MISSING", {"gain": 1.5, "deploy_m": 150}, "prm_file_missing: no parameter"),
        (good[:-3], "CORRUPT", {"gain": 1.5}, "refused (CORRUPT): body of"),
        (foreign, "FOREIGN", {"gain": 1.5}, "refused (FOREIGN): saved by mission 'zz'"),
        (
            PermissionError(13, "Permission denied"),
            "UNREADABLE",
            {"gain": 1.5},
            "refused (UNREADABLE): Permission denied",
        ),
        (
            encode_params(m, {"gain": 2.0, "deploy_m": 400, "use_gps": False}),
            "PARTIAL",
            {"gain": 2.0, "deploy_m": 150, "use_gps": False},
            "prm_defaulted: parameter deploy_m: the saved value 400 is outside [60, 350] m; "
            "its default 150 is used",
        ),
        (
            encode_params(m, {"gain": 2.0, "deploy_m": 7.5, "use_gps": 3}),
            "PARTIAL",
            {"gain": 2.0, "deploy_m": 150, "use_gps": True},
            "prm_defaulted: parameter use_gps: the saved value 3 is not true or false",
        ),
    ]
    for data, status, values, event in cases:
        c = Cn(m)
        c.cn.params.load(data, 0, source="/p/prmtest.params")
        c.step()
        assert c.dv.get_name("cn_prm_load_status") == status, status
        for k, v in values.items():
            assert c.dv.get(k) == v, (status, k)
        assert any(event in e for e in c.events), (status, c.events)
        assert c.dv.get("cn_prm_unsaved") is False


def test_read_params_file_says_missing_and_unreadable_apart(tmp_path: Path) -> None:
    assert read_params_file(tmp_path / "none.params") is None
    assert isinstance(read_params_file(tmp_path), OSError)  # a directory
    (tmp_path / "a.params").write_bytes(b"abc")
    assert read_params_file(tmp_path / "a.params") == b"abc"


def _finished(saver: ParamSaver) -> SaveResult:
    """Poll as a loop would (the save is on the saver's thread), for up to 10 s."""
    return wait_until(saver.poll, 10, "the saver to finish")


def test_the_saver_writes_off_the_loop_thread_and_reports(tmp_path: Path) -> None:
    m = mission()
    path = tmp_path / "sub" / "prmtest.params"
    steps: list[str] = []
    saver = ParamSaver(path, step=steps.append)
    try:
        assert saver.poll() is None
        saver.submit(3, encode_params(m, {"gain": 2.0, "deploy_m": 120, "use_gps": False}))
        assert _finished(saver) == SaveResult(3, True, str(path))
        assert decode_params(m, path.read_bytes()).values["gain"] == 2.0
        assert steps == ["opened", "partial", "written", "synced", "renamed", "dir_synced"]
        names = sorted(p.name for p in path.parent.iterdir())
        assert names == [".prmtest.params.lock", "prmtest.params"]  # no temporary file left
    finally:
        saver.close()
    (tmp_path / "file").write_text("not a directory")
    bad = ParamSaver(tmp_path / "file" / "prmtest.params")
    try:
        bad.submit(4, b"data")
        result = _finished(bad)
        assert not result.ok and result.seq == 4 and "File exists" in result.detail
    finally:
        bad.close()


def test_the_parameter_file_lives_beside_the_keys_unless_the_environment_says(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("ZPLATFORM_PARAMS_DIR")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert params_path("flight") == tmp_path / "zplatform" / "params" / "flight.params"
    monkeypatch.setenv("ZPLATFORM_PARAMS_DIR", str(tmp_path / "p"))
    assert params_path(mission()) == tmp_path / "p" / "prmtest.params"


# --------------------------------------------------------------------------- the ground


def test_the_ground_refuses_before_sending_and_knows_what_needs_arm() -> None:
    m = mission()
    assert validate_command(m, "prm_set", "gain", "2") == ("PRM_SET", element_index(m, "gain"), 2.0)
    assert validate_command(m, "PRM_SAVE") == ("PRM_SAVE", 0, 0.0)
    for args, text in [
        (("gian", "2"), "prm_set: no parameter named 'gian'; did you mean gain?"),
        (("x", "2"), "no parameter named 'x'; parameters: gain, deploy_m, use_gps"),
        (("gain", "11"), "prm_set: 11 is outside gain's bounds [0.0, 10.0] 1/s"),
        (("deploy_m", "100.5"), "does not fit"),
        (("use_gps", "maybe"), "not a valid value"),
        (("gain",), "prm_set needs PARAMETER VALUE"),
    ]:
        with pytest.raises(CommandError) as info:
            validate_command(m, "prm_set", *args)
        assert text in str(info.value), (args, str(info.value))
    why = needs_arm(m, "prm_set", "deploy_m")
    assert why == "parameter deploy_m is hazardous (params: hazardous)"
    assert needs_arm(m, "prm_set", "gain") is None
    assert needs_arm(m, "write", "deploy_m") is None  # WRITE refuses it anyway


def test_scripts_take_prm_set_and_prm_save() -> None:
    cmds = parse_commands("at 2.0 prm_set apogee_target_m 550\nat 2.5 prm_save\n", "s")
    assert [(c.command, c.element, c.value) for c in cmds] == [
        ("PRM_SET", "apogee_target_m", "550"),
        ("PRM_SAVE", None, None),
    ]
    with pytest.raises(CommandError, match="s:1: prm_set takes PARAMETER VALUE"):
        parse_commands("at 1 prm_set gain\n", "s")
    with pytest.raises(CommandError, match="prm_save takes no arguments"):
        parse_commands("at 1 prm_save now\n", "s")


def test_the_console_completes_parameters_and_shows_them() -> None:
    m = mission()
    model = ConsoleModel(m)
    assert model.complete("prm_s") == "prm_set"
    assert model.complete("prm_set de") == "prm_set deploy_m"
    assert model.complete("par") == "params"
    assert model.toggle_params() == "parameters shown" and model.show_params
    rows = model.param_rows()
    assert [r.name for r in rows] == ["gain", "deploy_m", "use_gps"]
    assert rows[0].value == "-"  # no telemetry yet
    c = Cn(m)
    c.send("prm_set", "gain", "2.5")
    model.on_snapshot(c.dv, 1)
    rows = model.param_rows()
    assert (rows[0].value, rows[0].default, rows[0].bounds) == ("2.5", "1.5", "[0, 10] 1/s")
    assert (rows[1].states, rows[1].hazardous) == (["PAD"], True)
    assert (rows[2].bounds, rows[2].states, rows[2].value) == ("", ["PAD", "FLY"], "true")
    assert param_rows(m, None)[1].value == "-"


# --------------------------------------------------------------------------- property

_INDEXES = st.integers(0, 0xFFFF)
_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**64), 2**64).map(float),
    st.sampled_from([0.0, 1.0, -0.0, 10.0, 10.000001, 60.0, 350.0, 59.999, 2.0**53]),
)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    requests=st.lists(
        st.tuples(
            st.sampled_from(["PRM_SET", "PRM_SAVE", "ARM", "LAUNCH", "ABORT"]), _INDEXES, _VALUES
        ),
        max_size=12,
    ),
    saves=st.lists(st.tuples(st.integers(0, 20), st.booleans()), max_size=4),
)
def test_no_request_ever_sets_a_parameter_out_of_its_bounds_or_raises(
    requests: list[tuple[str, int, float]], saves: list[tuple[int, bool]]
) -> None:
    """Whatever the requests (any element index, any value), the loop never
    raises, every parameter stays within its type and bounds, and only an
    ACCEPTED PRM_SET changes one."""
    c = Cn()
    indexes = {s.handle.spec.index: s for s in c.cn.params.slots}
    for i, (cmd, index, value) in enumerate(requests):
        before = c.cn.params.values()
        c.seq += 1
        results = tuple(SaveResult(s, ok, "x") for s, ok in saves if s == i)
        c.step(bytes(c.up.frame(cmd, c.seq, index & 0xFFFF, value, 0, EPOCH)), saves=results)
        after = c.cn.params.values()
        for s in c.cn.params.slots:
            v = after[s.name]
            assert s.handle.spec.scalar.fits(v) and s.in_bounds(v), (s.name, v)
        changed = {k for k in after if after[k] != before[k]}
        if changed:
            assert cmd == "PRM_SET" and c.dv.get_name("cn_cmd_status") == "ACCEPTED"
            assert changed == {indexes[index].name}
