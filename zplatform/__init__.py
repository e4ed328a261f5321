"""zplatform: distributed avionics flight software on Eclipse Zenoh.

The public API, re-exported from the modules that define it. Import from
here; module paths below ``zplatform.`` are implementation detail.
"""

from __future__ import annotations

from .codec import (
    Frame,
    FrameDecoder,
    FrameEncoder,
    RegionCodec,
    VectorCodec,
    decode_frame,
    encode_frame,
)
from .config import Mission, decode_mission, load_mission
from .datavector import DataVector, ElementSpec, Handle, Layout, RegionSpec
from .errors import (
    ClockSyncError,
    CodecError,
    CommandError,
    ConfigError,
    ControlError,
    DataVectorError,
    FrameFormatError,
    FrameSizeError,
    LayoutMismatchError,
    NodeError,
    SchedulerError,
    StateMachineError,
    TimebaseError,
    TransportError,
    ZPlatformError,
)
from .scheduler import GcGuard, LoopStats, PeriodicLoop, RateGroups, setup_realtime
from .timebase import NodeClock, VirtualClock

__version__ = "0.1.0"

__all__ = [
    "ClockSyncError",
    "CodecError",
    "CommandError",
    "ConfigError",
    "ControlError",
    "DataVector",
    "DataVectorError",
    "ElementSpec",
    "Frame",
    "FrameDecoder",
    "FrameEncoder",
    "FrameFormatError",
    "FrameSizeError",
    "GcGuard",
    "Handle",
    "Layout",
    "LayoutMismatchError",
    "LoopStats",
    "Mission",
    "NodeClock",
    "NodeError",
    "PeriodicLoop",
    "RateGroups",
    "RegionCodec",
    "RegionSpec",
    "SchedulerError",
    "StateMachineError",
    "TimebaseError",
    "TransportError",
    "VectorCodec",
    "VirtualClock",
    "ZPlatformError",
    "__version__",
    "decode_frame",
    "decode_mission",
    "encode_frame",
    "load_mission",
    "setup_realtime",
]
