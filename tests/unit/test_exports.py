"""The public API: ``zplatform/__init__.py`` is the one front door (trio's test_exports)."""

from __future__ import annotations

import importlib
import inspect

import pytest

import zplatform
from zplatform import errors

# The foundation's names; modules landing later add to __all__, never remove.
FOUNDATION = {
    # errors
    "ZPlatformError",
    "ConfigError",
    "DataVectorError",
    "CodecError",
    "FrameFormatError",
    "LayoutMismatchError",
    "FrameSizeError",
    "TimebaseError",
    "SchedulerError",
    "TransportError",
    "ClockSyncError",
    "StateMachineError",
    "CommandError",
    "ControlError",
    "NodeError",
    # config (the schema) and mission (loading with every check)
    "Mission",
    "check_mission",
    "decode_mission",
    "load_mission",
    # codes, components, events
    "Command",
    "CommandStatus",
    "Fault",
    "Component",
    "EV",
    "EventType",
    "EventError",
    # data vector
    "DataVector",
    "ElementSpec",
    "Handle",
    "Layout",
    "RegionSpec",
    # codec
    "Frame",
    "FrameDecoder",
    "FrameEncoder",
    "RegionCodec",
    "decode_frame",
    "encode_frame",
    # timebase
    "NodeClock",
    "VirtualClock",
    # scheduler and rate groups
    "GcGuard",
    "LoopStats",
    "PeriodicLoop",
    "RateGroups",
    "setup_realtime",
    "__version__",
}


def test_foundation_names_exported() -> None:
    assert set(zplatform.__all__) >= FOUNDATION


def test_no_duplicates() -> None:
    assert len(zplatform.__all__) == len(set(zplatform.__all__))


@pytest.mark.parametrize("name", sorted(zplatform.__all__))
def test_every_name_resolves(name: str) -> None:
    assert getattr(zplatform, name) is not None


def test_star_import() -> None:
    ns: dict[str, object] = {}
    exec("from zplatform import *", ns)
    assert set(zplatform.__all__) <= set(ns)


def test_public_classes_and_functions_come_from_submodules() -> None:
    # Re-exported objects are the submodules' own (no copies, no wrappers).
    for name in zplatform.__all__:
        obj = getattr(zplatform, name)
        if inspect.isclass(obj) or inspect.isfunction(obj):
            module = importlib.import_module(obj.__module__)
            assert getattr(module, obj.__name__) is obj, name


def test_every_error_is_exported() -> None:
    for name in errors.__all__:
        assert name in zplatform.__all__
        assert issubclass(getattr(zplatform, name), zplatform.ZPlatformError)


def test_version() -> None:
    assert isinstance(zplatform.__version__, str)
    assert zplatform.__version__.count(".") == 2
