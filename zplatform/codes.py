"""The platform's numeric codes, defined once: commands, verdicts, faults, errors.

These enums are the values of the platform elements ``gn_cmd`` / ``cn_cmd``
(:class:`Command`), ``cn_cmd_status`` (:class:`CommandStatus`), ``cn_fault``
(:class:`Fault`) and ``cn_last_error`` (:class:`ErrorCode`), and the bits of
each node's ``<node>_threads_stalled`` (:class:`Thread`). The config
derives the enum names of those elements from them
(:data:`zplatform.config.CMD_NAMES` ...), the command handler and the fault
monitor compare against them: one definition, so the two can never disagree.

Contract: this module imports nothing from the package (every other module
may import it), and the values are part of the wire format (they travel in
frames and telemetry): append new members, never renumber.
"""

from __future__ import annotations

import enum

__all__ = ["Command", "CommandStatus", "ErrorCode", "Fault", "Thread"]


class Command(enum.IntEnum):
    """Operator commands (thesis 4.8, seed 003 ARM); the values of ``gn_cmd`` and ``cn_cmd``."""

    NONE = 0
    NOOP = 1
    LAUNCH = 2
    ABORT = 3
    WRITE = 4
    HOLD = 5
    RESUME = 6
    ARM = 7


class CommandStatus(enum.IntEnum):
    """Outcome of the last request; the values of ``cn_cmd_status``."""

    NONE = 0
    ACCEPTED = 1
    REJECTED_UNKNOWN = 2
    REJECTED_NOT_ALLOWED = 3
    REJECTED_BAD_ARGUMENT = 4
    REJECTED_REPLAY = 5
    REJECTED_NOT_ARMED = 6
    REJECTED_AUTH = 7
    REJECTED_EPOCH = 8


class Fault(enum.IntEnum):
    """Critical-error flag values (thesis 4.11.1); the values of ``cn_fault``."""

    NONE = 0
    DN_LOST = 1
    CONTROLLER_FAILED = 2
    SYNC_OVERRUNS = 3
    LOOP_OVERRUNS = 4
    CLOCK_DRIFT = 5
    MONITOR = 6
    """A mission monitor's response (``monitors:``), unless it names another fault."""
    THREAD_STALLED = 7
    """A thread of a node stopped checking in (a monitor on ``<node>_threads_stalled``)."""


class ErrorCode(enum.IntEnum):
    """Codes for ``cn_last_error`` (non-critical errors). 0 = none yet.

    Missions may use their own codes from 1000 up.
    """

    NONE = 0
    SYNC_TIMEOUT = 1
    BAD_FRAME = 2
    LOOP_OVERRUN = 3
    CONTROLLER_ERROR = 4
    DEVICE_ERROR = 5
    CLOCK_SYNC = 6
    TELEMETRY = 7
    EVENTS_DROPPED = 8


class Thread(enum.IntEnum):
    """The threads whose liveness a node reports: bit ``1 << value`` of
    ``<node>_threads_stalled``; the lowercase names are what missions and
    events use (``health.deadlines_ms.zenoh``). See :mod:`zplatform.health`."""

    LOOP = 0
    """The node's loop thread."""
    ZENOH = 1
    """Zenoh's runtime running the node's callbacks (the health thread's probe)."""
    HEALTH = 2
    """The health thread."""
    CLOCK = 3
    """The CN's clock server; a DN's clock re-sync."""
    BOARD = 4
    """The board's I/O thread (the serial board's, or a board with a ``heartbeat``)."""
    RECORD = 5
    """The CN's ``--record`` writer."""
    RECORDER = 6
    """The on-board flight recorder's writer."""
