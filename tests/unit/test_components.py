"""Tests of zplatform.core.components: the shared loaders and the failure streak."""

from __future__ import annotations

import pytest

from zplatform.control.controllers import Controller
from zplatform.control.devices import Device, DigitalOutput
from zplatform.core.components import Streak, load_component_class, load_function
from zplatform.errors import ConfigError


def two_args(board: object, t_ns: int) -> None:
    pass


def with_default(board: object, t_ns: int, gain: float = 1.0) -> None:
    pass


def varargs(*args: object) -> None:
    pass


def one_arg(board: object) -> None:
    pass


NOT_CALLABLE = 3

HERE = __name__


@pytest.mark.parametrize("fn", ["two_args", "with_default", "varargs"])
def test_load_function_accepts_what_can_take_the_arguments(fn: str) -> None:
    f = load_function(f"{HERE}:{fn}", "$.p", args=("board", "t_ns"))
    assert f is globals()[fn]


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("os:getcwd", r"cannot be called as physics\(board, t_ns\)"),
        (f"{HERE}:one_arg", r"cannot be called as physics\(board, t_ns\)"),
        (f"{HERE}:NOT_CALLABLE", "is a int, not a function"),
        (f"{HERE}:Streak", "is a type, not a function"),
        ("no_such_zp_mod:f", "cannot import physics module 'no_such_zp_mod'"),
        (f"{HERE}:nope", "has no function 'nope'"),
        ("no_colon", "must be 'package.module:function'"),
    ],
)
def test_load_function_refuses_at_load(spec: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as ei:
        load_function(spec, "$.nodes.dn0.board.physics", args=("board", "t_ns"), what="physics")
    assert ei.value.path == "$.nodes.dn0.board.physics"


def test_load_component_class_names_the_path() -> None:
    assert (
        load_component_class("zplatform.control.devices:DigitalOutput", Device, "$.x")
        is DigitalOutput
    )
    with pytest.raises(ConfigError, match="is abstract") as ei:
        load_component_class("zplatform.control.controllers:Controller", Controller, "$.c[0].class")
    assert ei.value.path == "$.c[0].class"


def test_streak_counts_and_reports_its_end() -> None:
    s = Streak()
    assert s.ok() is False and s.length == 0
    assert [s.fail(), s.fail(), s.fail()] == [1, 2, 3]
    assert s.ok() is True and s.length == 0
    assert s.ok() is False
    assert s.fail() == 1  # a new streak starts at 1


def test_a_mission_may_name_a_class_by_its_path_before_the_packages() -> None:
    # issue 26 moved zplatform/devices.py to zplatform/control/devices.py: a
    # team's mission file written before still names zplatform.devices
    import importlib

    from zplatform.control import controllers as ctl
    from zplatform.control import devices as dev
    from zplatform.core import components

    load = components.load_component_class
    assert load("zplatform.devices:DigitalOutput", dev.Device, "$.x") is dev.DigitalOutput
    with pytest.raises(ConfigError, match="is abstract"):  # found, at its old path
        load("zplatform.controllers:Controller", ctl.Controller, "$.c")
    with pytest.raises(ConfigError, match="cannot import"):
        load("zplatform.nowhere:Thing", dev.Device, "$.x")
    for old, new in components.MOVED_MODULES.items():
        assert importlib.import_module(new).__name__ == new, old
