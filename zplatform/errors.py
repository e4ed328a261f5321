"""The zplatform error tree (the thesis, ch. 4.11, made Pythonic).

The thesis' C++ platform returns an ``Error_t`` status from every function and
has the node mains decide what to do with it. Here exceptions carry the same
contract: every error the platform raises on purpose is a subclass of
:class:`ZPlatformError`, so a node main can tell "ours, with a clear message"
from a bug with one ``except``. Low-level errors (msgspec, numpy, zenoh, OS)
are converted at the boundary with ``raise ... from exc``.

Holds the root and the shared branches (:class:`ConfigError`, whose message
names the YAML path; :class:`CodecError` and its frame errors;
:class:`NodeError`, :class:`RecordingError`, :class:`ArchiveError`, ...); a few leaves live with
their modules (``AuthError``, ``KeyError_``, ``BoardError``,
``DeploymentError``, ``CcsdsError``, ``ParamFileError``). The mains handle
them as the thesis does: during initialisation print and exit non-zero;
after start count, event and keep the rate, or latch a fault for the state
machine.

The whole tree and its handling: docs/architecture.md#errors-and-faults.
"""

from __future__ import annotations

__all__ = [
    "ArchiveError",
    "ClockSyncError",
    "CodecError",
    "CommandError",
    "ConfigError",
    "ControlError",
    "DataVectorError",
    "EventError",
    "FrameFormatError",
    "FrameSizeError",
    "IntraHostError",
    "LayoutMismatchError",
    "NodeError",
    "RecordingError",
    "SchedulerError",
    "StateMachineError",
    "TimebaseError",
    "TransportError",
    "ZPlatformError",
]


class ZPlatformError(Exception):
    """Root of every error zplatform raises on purpose."""


class ConfigError(ZPlatformError):
    """The mission configuration is invalid.

    ``path`` is the YAML path of the offending field (``$.regions.cn[2].type``),
    so the message can be acted on without reading the loader's code.
    """

    def __init__(self, message: str, path: str = "$") -> None:
        self.path = path
        self.reason = message
        super().__init__(f"{message} - at `{path}`")


class DataVectorError(ZPlatformError):
    """Unknown element or region, value that does not fit, buffer size mismatch."""


class CodecError(ZPlatformError):
    """A received frame was rejected before it touched the Data Vector."""


class FrameFormatError(CodecError):
    """The bytes are not a region frame (bad MessagePack, wrong shape or types)."""


class LayoutMismatchError(CodecError):
    """The frame was encoded for another region layout (``layout_id`` differs)."""


class FrameSizeError(CodecError):
    """The frame's data length differs from the region's size."""


class TimebaseError(ZPlatformError):
    """The node clock cannot start or cannot be adjusted as asked."""


class SchedulerError(ZPlatformError):
    """Invalid periodic-loop or rate-group parameters."""


class TransportError(ZPlatformError):
    """A zenoh session, declaration or key-space operation failed."""


class ClockSyncError(ZPlatformError):
    """Clock offset could not be estimated, or exceeds the mission bound."""


class StateMachineError(ZPlatformError):
    """The state machine was used in a way its configuration forbids."""


class CommandError(ZPlatformError):
    """An operator command was refused before it was sent."""


class ControlError(ZPlatformError):
    """A controller or device could not be built or wired to the Data Vector.

    ``path``, when given, is the YAML path of the component (``$.devices[3]``)
    and ends the message as in :class:`ConfigError`.
    """

    def __init__(self, message: str, path: str | None = None) -> None:
        self.path = path
        self.reason = message
        super().__init__(message if path is None else f"{message} - at `{path}`")


class EventError(ZPlatformError):
    """An event emitted that is not an entry of the catalogue (``zplatform.core.events.EV``)."""


class IntraHostError(ZPlatformError):
    """An intra-host (iceoryx2 shared-memory) link cannot open: bad names, too
    little shared memory on the host, or iceoryx2 refused (zplatform/runtime/intrahost.py)."""


class NodeError(ZPlatformError):
    """A node main could not start, or stopped on an unrecoverable error."""


class RecordingError(ZPlatformError):
    """A loop recording cannot be written, or read back for a replay."""


class ArchiveError(ZPlatformError):
    """The ground archive cannot be opened, or a query of it is refused (the reason says why)."""
