"""zplatform: distributed avionics flight software on Eclipse Zenoh.

"The thesis" in these docstrings is the M.S. thesis the platform follows,
*A Distributed Avionics Software Platform for a Liquid-Fueled Rocket*;
"ch. N" and "§N" are its chapters.

The public API, re-exported from the modules that define it. Import from
here; module paths below ``zplatform.`` are implementation detail.
"""

from __future__ import annotations

from .boards import Board, SimBoard
from .boards.world import WorldLink
from .config import Mission
from .config.codes import Command, CommandStatus, Fault, ParamLoad, ParamSave, SafedWhy, Thread
from .control.commands import CommandHandler
from .control.controllers import Controller, ControllerSet
from .control.devices import Actuator, Device, DeviceSet, Sensor
from .control.faults import FaultMonitor
from .control.loop import ControlLogic, DeviceLogic
from .control.monitors import MonitorSet
from .control.params import (
    ParamFileError,
    ParamSaver,
    ParamTable,
    decode_params,
    encode_params,
    params_path,
)
from .control.rategroups import RateGroups
from .control.statemachine import StateMachine
from .control.uplink import ScriptCommand, fill_request, load_commands, parse_commands
from .control.watchdog import Watchdog
from .core.auth import KeySet, load_keys
from .core.codec import (
    Frame,
    FrameDecoder,
    FrameEncoder,
    RegionCodec,
    decode_frame,
    encode_frame,
)
from .core.components import Component
from .core.datavector import DataVector, ElementSpec, Handle, Layout, RegionSpec
from .core.events import EV, Event, EventLog, EventReader, EventType, Severity
from .core.health import FakeHealth, HealthPort, Heartbeat, Liveness
from .errors import (
    ArchiveError,
    ClockSyncError,
    CodecError,
    CommandError,
    ConfigError,
    ControlError,
    DataVectorError,
    EventError,
    FrameFormatError,
    FrameSizeError,
    IntraHostError,
    LayoutMismatchError,
    NodeError,
    RecordingError,
    SchedulerError,
    StateMachineError,
    TimebaseError,
    TransportError,
    ZPlatformError,
)
from .ground.gapfill import GapFill
from .ground.link import GroundLink
from .ground.logic import GroundLogic
from .ground.script import ScriptPlayer
from .mission.load import check_mission, decode_mission, load_mission
from .mission.safety import SafetyWarning, safety_warnings
from .mission.schema import mission_schema, reference_markdown
from .recorder import FlightRecorder, RecorderReader
from .runtime.scheduler import GcGuard, LoopStats, PeriodicLoop, setup_realtime
from .runtime.timebase import NodeClock, VirtualClock
from .runtime.transport import KeySpace
from .security.keyspace import (
    KEYSPACE,
    ExpandedKey,
    KeyFrames,
    KeyRow,
    expand_keys,
    key_of,
    key_row,
    keyspace_markdown,
    match_key,
)
from .sim.lockstep import LockstepRunner, ReplayResult, SimResult, replay
from .sim.replay_recording import Recorder
from .telemetry.logs import CsvLogger, read_csv
from .telemetry.records import CommandOutcome, EventRecord, TelemetryCounters
from .world.model import World, WorldBoard

__version__ = "0.1.0"

__all__ = [
    "EV",
    "KEYSPACE",
    "Actuator",
    "ArchiveError",
    "Board",
    "ClockSyncError",
    "CodecError",
    "Command",
    "CommandError",
    "CommandHandler",
    "CommandOutcome",
    "CommandStatus",
    "Component",
    "ConfigError",
    "ControlError",
    "ControlLogic",
    "Controller",
    "ControllerSet",
    "CsvLogger",
    "DataVector",
    "DataVectorError",
    "Device",
    "DeviceLogic",
    "DeviceSet",
    "ElementSpec",
    "Event",
    "EventError",
    "EventLog",
    "EventReader",
    "EventRecord",
    "EventType",
    "ExpandedKey",
    "FakeHealth",
    "Fault",
    "FaultMonitor",
    "FlightRecorder",
    "Frame",
    "FrameDecoder",
    "FrameEncoder",
    "FrameFormatError",
    "FrameSizeError",
    "GapFill",
    "GcGuard",
    "GroundLink",
    "GroundLogic",
    "Handle",
    "HealthPort",
    "Heartbeat",
    "IntraHostError",
    "KeyFrames",
    "KeyRow",
    "KeySet",
    "KeySpace",
    "Layout",
    "LayoutMismatchError",
    "Liveness",
    "LockstepRunner",
    "LoopStats",
    "Mission",
    "MonitorSet",
    "NodeClock",
    "NodeError",
    "ParamFileError",
    "ParamLoad",
    "ParamSave",
    "ParamSaver",
    "ParamTable",
    "PeriodicLoop",
    "RateGroups",
    "Recorder",
    "RecorderReader",
    "RecordingError",
    "RegionCodec",
    "RegionSpec",
    "ReplayResult",
    "SafedWhy",
    "SafetyWarning",
    "SchedulerError",
    "ScriptCommand",
    "ScriptPlayer",
    "Sensor",
    "Severity",
    "SimBoard",
    "SimResult",
    "StateMachine",
    "StateMachineError",
    "TelemetryCounters",
    "Thread",
    "TimebaseError",
    "TransportError",
    "VirtualClock",
    "Watchdog",
    "World",
    "WorldBoard",
    "WorldLink",
    "ZPlatformError",
    "__version__",
    "check_mission",
    "decode_frame",
    "decode_mission",
    "decode_params",
    "encode_frame",
    "encode_params",
    "expand_keys",
    "fill_request",
    "key_of",
    "key_row",
    "keyspace_markdown",
    "load_commands",
    "load_keys",
    "load_mission",
    "match_key",
    "mission_schema",
    "params_path",
    "parse_commands",
    "read_csv",
    "reference_markdown",
    "replay",
    "safety_warnings",
    "setup_realtime",
]
