"""Tests of zplatform.control.controllers: modes, failure handling, typed configs, rate groups,
and the shipped missions' controllers in isolation."""

from __future__ import annotations

import textwrap

import msgspec
import pytest

from zplatform import DataVector, Layout, decode_mission
from zplatform.config import Mission, parse_mission
from zplatform.control.controllers import (
    ENABLED,
    MANUAL,
    SAFED,
    Controller,
    ControllerSet,
    check_config,
)
from zplatform.control.faults import ErrorCode, FaultMonitor
from zplatform.control.loop import ControlLogic
from zplatform.core.events import EventLog, Severity
from zplatform.errors import ConfigError, ControlError

PERIOD = 10_000_000
HERE = __name__


class Recorder(Controller):
    """Writes ``out`` true when enabled, false when safed; can be told to raise."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        out: str
        fail_enabled: bool = False
        fail_safed: bool = False

    config: Config

    def bind(self, dv: DataVector) -> None:
        self.out = self.output(self.config.out, "out", kinds=("bool",))
        self.calls: list[tuple[str, int]] = []
        self.fail_enabled = self.config.fail_enabled
        self.fail_safed = self.config.fail_safed

    def run_enabled(self, t_ns: int) -> None:
        self.calls.append(("enabled", t_ns))
        if self.fail_enabled:
            raise RuntimeError("boom in enabled")
        self.out.set(True)

    def run_safed(self, t_ns: int) -> None:
        self.calls.append(("safed", t_ns))
        if self.fail_safed:
            raise RuntimeError("boom in safed")
        self.out.set(False)


class NotAController:
    pass


class Abstract(Controller):
    def run_enabled(self, t_ns: int) -> None:
        pass


class BadBind(Controller):
    def bind(self, dv: DataVector) -> None:
        raise ZeroDivisionError("bind bug")

    def run_enabled(self, t_ns: int) -> None:
        pass

    def run_safed(self, t_ns: int) -> None:
        pass


class IndexBind(Controller):
    """A team's bind that looks a name up the Python way (the issue's case)."""

    def bind(self, dv: DataVector) -> None:
        ("A", "B").index("C")

    def run_enabled(self, t_ns: int) -> None:
        pass

    def run_safed(self, t_ns: int) -> None:
        pass


BASE = """
mission: ctltest
nodes: {cn: {}, dn0: {}, gn: {}}
regions:
  cn:
    - {name: out_a, type: bool}
    - {name: out_b, type: bool}
    - {name: level, type: f64}
  cn_to_dn0:
    - {name: dn_cmd, type: bool}
  dn0_to_cn:
    - {name: dn_out, type: bool}
faults: {controller_fail_loops: 3}
"""


def mission(controllers: str) -> Mission:
    body = textwrap.indent(textwrap.dedent(controllers), "  ")
    return decode_mission(BASE + "controllers:\n" + body)


def recorder(
    name: str = "a", out: str = "out_a", node: str = "cn", rate: str = "", **kw: object
) -> str:
    """One YAML controller entry of class Recorder; ``rate`` adds fields."""
    cfg = ", ".join([f"out: {out}", *(f"{k}: {str(v).lower()}" for k, v in kw.items())])
    return (
        f"- {{name: {name}, class: '{HERE}:Recorder', node: {node}, "
        f"initial_mode: enabled, config: {{{cfg}}}{rate}}}\n"
    )


class Rig:
    def __init__(self, m: Mission, node: str = "cn") -> None:
        self.m = m
        self.dv = DataVector(Layout.for_node(m, node))
        self.events = EventLog(node)
        self.faults = FaultMonitor(m, self.dv, self.events) if node == "cn" else None
        self.set = ControllerSet(m, node, self.dv, self.events, self.faults)
        self.loop = 0
        self.t = 1_000 * PERIOD

    def ctl(self, i: int = 0) -> Recorder:
        c = self.set.controllers[i]
        assert isinstance(c, Recorder)
        return c

    def run(self, n: int = 1) -> None:
        for _ in range(n):
            self.set.run(self.loop, self.t)
            self.loop += 1
            self.t += PERIOD

    def severities(self) -> list[tuple[str, str]]:
        return [(Severity(e.severity).name, e.id) for e in self.events.drain()]


# -- modes --------------------------------------------------------------------


def test_mode_element_selects_run_method() -> None:
    r = Rig(mission(recorder()))
    r.run()
    assert r.ctl().calls == [("enabled", r.t - PERIOD)]
    assert r.dv.get("out_a") is True
    r.dv.set("a_mode", "safed")
    r.run()
    assert r.ctl().calls[-1][0] == "safed"
    assert r.dv.get("out_a") is False


def test_manual_mode_leaves_outputs_alone_so_writes_hold() -> None:
    r = Rig(mission(recorder()))
    r.run()
    r.dv.set("a_mode", "manual")
    n = len(r.ctl().calls)
    r.dv.set("out_a", False)  # an operator WRITE
    r.run(5)
    assert r.dv.get("out_a") is False
    assert len(r.ctl().calls) == n  # run_manual is the base's no-op
    r.dv.set("out_a", True)
    r.run()
    assert r.dv.get("out_a") is True


def test_invalid_mode_value_runs_safed() -> None:
    r = Rig(mission(recorder()))
    r.dv.handle("a_mode").set(7)
    r.run()
    assert r.ctl().calls[-1][0] == "safed"


def test_enabled_at_is_set_on_each_entry_into_enabled() -> None:
    r = Rig(mission(recorder()))
    t0 = r.t
    r.run(3)
    assert r.ctl().enabled_at_ns == t0
    r.dv.set("a_mode", "safed")
    r.run(2)
    t1 = r.t
    r.dv.set("a_mode", "enabled")
    r.run(2)
    assert r.ctl().enabled_at_ns == t1


def test_mode_constants_match_config() -> None:
    assert (ENABLED, SAFED, MANUAL) == (0, 1, 2)


# -- failures -----------------------------------------------------------------


def test_raising_controller_is_counted_safed_and_reported_once() -> None:
    r = Rig(mission(recorder("a", "out_a") + recorder("b", "out_b")))
    r.run()
    a, b = r.ctl(0), r.ctl(1)
    a.fail_enabled = True
    r.run()
    # counted, last error code, mode written safed, run_safed called in the same loop
    assert r.dv.get("cn_errors") == 1
    assert r.dv.get("cn_last_error") == ErrorCode.CONTROLLER_ERROR
    assert r.dv.get_name("a_mode") == "safed"
    assert [c[0] for c in a.calls[-2:]] == ["enabled", "safed"]
    assert r.dv.get("out_a") is False
    # the loop went on: the next controller ran
    assert b.calls[-1] == ("enabled", r.t - PERIOD)
    events = r.severities()
    assert events == [("WARNING_HI", "controller_failed")]
    # stays safed (no retry) until the state machine enables it again
    r.run(10)
    assert r.dv.get("cn_errors") == 1
    assert r.severities() == []
    assert r.dv.get_name("cn_fault") == "NONE"
    assert not r.set.disabled("a")


def test_safing_failure_disables_controller_and_raises_fault() -> None:
    r = Rig(mission(recorder(fail_enabled="true", fail_safed="true")))
    r.run()
    assert r.set.disabled("a")
    assert r.dv.get("cn_errors") == 1
    assert r.severities() == [("WARNING_HI", "controller_failed"), ("FATAL", "controller_disabled")]
    n = len(r.ctl().calls)
    r.run(5)
    assert len(r.ctl().calls) == n  # never called again
    # every due loop of a disabled controller is a failing loop for the fault monitor
    assert r.dv.get_name("cn_fault") == "CONTROLLER_FAILED"
    assert r.set.streak("a") == 6


def test_controller_failing_in_safed_mode_is_disabled() -> None:
    r = Rig(mission(recorder(fail_safed="true")))
    r.dv.set("a_mode", "safed")
    r.run()
    assert r.set.disabled("a")
    assert [s for s, _ in r.severities()] == ["WARNING_HI", "FATAL"]


def test_reenabled_controller_runs_again_and_failures_count_each_time() -> None:
    r = Rig(mission(recorder(fail_enabled="true")))
    r.run()
    assert r.dv.get_name("a_mode") == "safed"
    r.ctl().fail_enabled = False
    r.dv.set("a_mode", "enabled")
    r.run()
    assert r.dv.get("out_a") is True
    r.ctl().fail_enabled = True
    r.run()
    assert r.dv.get("cn_errors") == 2
    assert [i for _, i in r.severities()] == ["controller_failed", "controller_failed"]


def test_dn_controller_failure_latches_safed_while_cn_keeps_commanding() -> None:
    m = mission(recorder("d", "dn_out", node="dn0"))
    r = Rig(m, node="dn0")
    r.run()
    r.ctl().fail_enabled = True
    r.run()
    assert r.dv.get("dn0_errors") == 1
    for _ in range(5):
        r.dv.set("d_mode", "enabled")  # the CN's frame rewrites the mode every loop
        r.run()
    assert r.dv.get("dn0_errors") == 1  # not retried: latched safe
    assert r.ctl().calls[-1][0] == "safed"
    assert r.severities() == [("WARNING_HI", "controller_failed")]
    # the CN safes and re-enables it: the latch is released
    r.ctl().fail_enabled = False
    r.dv.set("d_mode", "safed")
    r.run()
    r.dv.set("d_mode", "enabled")
    r.run()
    assert r.ctl().calls[-1][0] == "enabled"
    assert r.dv.get("dn_out") is True


def test_failure_in_control_logic_does_not_stop_the_loop() -> None:
    m = mission(recorder(fail_enabled="true"))
    logic = ControlLogic(m)
    for k in range(1, 6):
        logic.begin(k, 1_000 * PERIOD + k * PERIOD)
        logic.finish()
    assert logic.dv.get("cn_loop") == 5
    assert logic.dv.get("cn_errors") == 1


# -- construction and typed config ---------------------------------------------


def build(controllers: str, node: str = "cn") -> ControllerSet:
    m = mission(controllers)
    return ControllerSet(m, node, DataVector(Layout.for_node(m, node)))


def test_unknown_config_field_names_its_path() -> None:
    with pytest.raises(ConfigError) as ei:
        build(recorder(bogus=1))
    assert ei.value.path == "$.controllers[0].config"
    assert "bogus" in str(ei.value)


def test_wrong_config_type_names_the_field() -> None:
    with pytest.raises(ConfigError) as ei:
        build(recorder("a", "out_a") + recorder("b", "out_b", fail_enabled="maybe"))
    assert ei.value.path == "$.controllers[1].config.fail_enabled"


def test_missing_element_names_field_and_node() -> None:
    with pytest.raises(ConfigError) as ei:
        build(recorder(out="nope"))
    assert ei.value.path == "$.controllers[0].config.out"
    assert "'nope' is not in node cn's Data Vector" in str(ei.value)


def test_element_of_another_node_is_not_in_this_vector() -> None:
    with pytest.raises(ConfigError, match="not in node dn0's Data Vector"):
        build(recorder("d", "level", node="dn0"), node="dn0")


def test_output_to_a_received_region_is_refused() -> None:
    with pytest.raises(ConfigError, match="does not write") as ei:
        build(recorder(out="dn_out"))
    assert ei.value.path == "$.controllers[0].config.out"
    with pytest.raises(ConfigError, match="region cn_to_dn0"):
        build(recorder("d", "dn_cmd", node="dn0"), node="dn0")


def test_element_kind_is_checked() -> None:
    with pytest.raises(ConfigError, match="expected bool"):
        build(recorder(out="level"))


@pytest.mark.parametrize(
    ("cls", "match"),
    [
        ("no_such_module_zp:X", "cannot import module 'no_such_module_zp'"),
        (f"{HERE}:Missing", "has no attribute 'Missing'"),
        (f"{HERE}:NotAController", "is not a zplatform.control.controllers.Controller subclass"),
        (f"{HERE}:Abstract", "is abstract"),
    ],
)
def test_class_errors_name_the_class_field(cls: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as ei:
        build(f"- {{name: x, class: '{cls}', node: cn}}\n")
    assert ei.value.path == "$.controllers[0].class"


def test_constructor_bug_is_a_control_error() -> None:
    with pytest.raises(ControlError, match="failed to build: ZeroDivisionError") as ei:
        build(f"- {{name: x, class: '{HERE}:BadBind', node: cn}}\n")
    assert ei.value.path == "$.controllers[0]"


def test_every_build_error_names_the_yaml_path_and_the_class() -> None:
    """A constructor's ValueError comes out naming where the controller is in
    the YAML and its class, with the original message; a config that names a
    missing element names the field, the controller and its class."""
    with pytest.raises(ControlError) as ei:
        build(recorder() + f"- {{name: pick, class: '{HERE}:IndexBind', node: cn}}\n")
    assert ei.value.path == "$.controllers[1]"
    msg = str(ei.value)
    assert msg == (
        f"controller 'pick' ({HERE}:IndexBind) failed to build: ValueError: "
        "tuple.index(x): x not in tuple - at `$.controllers[1]`"
    )
    assert isinstance(ei.value.__cause__, ValueError)
    with pytest.raises(ConfigError) as ei2:
        build(recorder() + recorder("b", out="nope"))
    assert ei2.value.path == "$.controllers[1].config.out"
    assert str(ei2.value).startswith(f"controller 'b' ({HERE}:Recorder): element 'nope' is not")
    # Through the loader, as `zplatform check` reports it.
    at = r"IndexBind\) failed to build.* - at `\$\.controllers\[0\]`"
    with pytest.raises(ControlError, match=at):
        check_config(mission(f"- {{name: pick, class: '{HERE}:IndexBind', node: cn}}\n"))


def test_check_config_builds_every_node() -> None:
    check_config(mission(recorder() + recorder("d", "dn_out", node="dn0")))
    with pytest.raises(ConfigError):
        check_config(mission(recorder("d", "nope", node="dn0")))


# -- rate groups ----------------------------------------------------------------


def test_rate_divisor_and_phase() -> None:
    m = mission(
        recorder("a", "out_a", rate=", rate_divisor: 2, rate_phase: 1") + recorder("b", "out_b")
    )
    r = Rig(m)
    r.run(6)
    assert len(r.ctl(0).calls) == 3  # loops 1, 3, 5
    assert len(r.ctl(1).calls) == 6


def test_rate_phase_out_of_range_is_a_config_error() -> None:
    body = recorder(rate=", rate_divisor: 2, rate_phase: 2")
    with pytest.raises(ConfigError) as ei:
        mission(body)  # refused at load ...
    assert ei.value.path == "$.controllers[0].rate_phase"
    m = parse_mission(BASE + "controllers:\n" + body)
    with pytest.raises(ConfigError) as ei:  # ... and by the set itself
        ControllerSet(m, "cn", DataVector(Layout.for_node(m, "cn")))
    assert ei.value.path == "$.controllers[0].rate_phase"


# -- the shipped missions' controllers ------------------------------------------


def test_sequential_leds_light_cumulatively_from_enable_time() -> None:
    from nodes.led_test import SequentialLedController

    leds = "\n    ".join(f"- {{name: l{i}, type: bool}}" for i in range(3))
    m = decode_mission(
        BASE.replace("- {name: level, type: f64}", leds)
        + "controllers:\n  - {name: s, class: 'nodes.led_test:SequentialLedController', node: cn,"
        " initial_mode: enabled, config: {leds: [l0, l1, l2], step_s: 0.5}}\n"
    )
    r = Rig(m)
    assert isinstance(r.set.controllers[0], SequentialLedController)
    lit = []
    for _ in range(120):
        r.run()
        lit.append(sum(r.dv.get(n) for n in ("l0", "l1", "l2")))
    assert lit[0] == 1 and lit[49] == 1 and lit[50] == 2 and lit[100] == 3 and lit[-1] == 3
    r.dv.set("s_mode", "safed")
    r.run()
    assert not any(r.dv.get(n) for n in ("l0", "l1", "l2"))


def test_led_test_config_errors_have_paths() -> None:
    m = parse_mission(
        BASE + "controllers:\n  - {name: s, class: 'nodes.led_test:StateLedController',"
        " node: cn, config: {leds: {Z: out_a}}}\n"
    )
    with pytest.raises(ConfigError) as ei:
        ControllerSet(m, "cn", DataVector(Layout.for_node(m, "cn")))
    assert ei.value.path == "$.controllers[0].config.leds.Z"


IGN = """
mission: igntest
nodes: {cn: {}, dn0: {}}
regions:
  cn_to_dn0:
    - {name: cmd, type: bool}
    - {name: cmd_loop, type: u64}
    - {name: armed, type: bool}
  dn0_to_cn:
    - {name: alt, type: f32}
    - {name: ok, type: bool}
    - {name: out, type: bool}
controllers:
  - name: safety
    class: nodes.recovery_igniter:IgniterSafetyController
    node: dn0
    initial_mode: enabled
    config: {command: cmd, command_loop: cmd_loop, armed: armed, altitude: alt, loop: dn0_loop,
             verdict: ok, output: out, min_altitude_m: 50, max_altitude_m: 400, max_age_loops: 5}
"""


@pytest.mark.parametrize(
    ("armed", "age", "alt", "fires"),
    [
        (True, 1, 250.0, True),
        (True, 0, 50.0, True),
        (True, 5, 400.0, True),
        (False, 1, 250.0, False),  # not armed
        (True, 6, 250.0, False),  # stale command
        (True, -1, 250.0, False),  # stamped in the future
        (True, 1, 40.0, False),  # too low
        (True, 1, 450.0, False),  # too high
        (True, 1, float("nan"), False),  # no altitude
    ],
)
def test_igniter_safety_rules(armed: bool, age: int, alt: float, fires: bool) -> None:
    m = decode_mission(IGN)
    dv = DataVector(Layout.for_node(m, "dn0"))
    cs = ControllerSet(m, "dn0", dv, EventLog("dn0"))
    loop = 1000
    dv.set("dn0_loop", loop)
    dv.set("cmd", True)
    dv.set("cmd_loop", loop - age)
    dv.set("armed", armed)
    dv.set("alt", alt)
    cs.run(loop, 0)
    assert dv.get("ok") is fires
    assert dv.get("out") is fires
    dv.set("cmd", False)
    cs.run(loop, 0)
    assert dv.get("out") is False  # a verdict alone never fires
    dv.set("cmd", True)
    dv.set("safety_mode", "safed")
    cs.run(loop, 0)
    assert dv.get("ok") is False and dv.get("out") is False


def test_invalid_mode_with_failing_safed_is_disabled_without_a_second_call() -> None:
    r = Rig(mission(recorder(fail_safed="true")))
    r.dv.handle("a_mode").set(9)
    r.run()
    assert r.set.disabled("a")
    assert [c for c, _ in r.ctl().calls] == ["safed"]
