"""The platform's numeric codes, defined once: commands, verdicts, faults, errors.

These enums are the values of the platform elements ``gn_cmd`` / ``cn_cmd``
(:class:`Command`), ``cn_cmd_status`` (:class:`CommandStatus`), ``cn_fault``
(:class:`Fault`), ``cn_last_error`` (:class:`ErrorCode`), the bits of
each node's ``<node>_threads_stalled`` (:class:`Thread`), and of a mission
with parameters ``cn_prm_load_status`` (:class:`ParamLoad`) and
``cn_prm_save_status`` (:class:`ParamSave`). The config
derives the enum names of those elements from them
(:data:`zplatform.config.CMD_NAMES` ...), the command handler and the fault
monitor compare against them: one definition, so the two can never disagree.

Contract: this module imports nothing from the package (every other module
may import it), and the values are part of the wire format (they travel in
frames and telemetry): append new members, never renumber.
"""

from __future__ import annotations

import enum

__all__ = [
    "Command",
    "CommandStatus",
    "ErrorCode",
    "Fault",
    "ParamLoad",
    "ParamSave",
    "SafedWhy",
    "Thread",
]


class Command(enum.IntEnum):
    """Operator commands (thesis 4.8, ARM-then-command); the values of ``gn_cmd`` and ``cn_cmd``.

    ``PRM_SET`` sets a mission parameter (``gn_cmd_element``: the
    parameter's element index, ``gn_cmd_value``: its value); ``PRM_SAVE``
    has the control node write every parameter to its parameter file
    (:mod:`zplatform.control.params`)."""

    NONE = 0
    NOOP = 1
    LAUNCH = 2
    ABORT = 3
    WRITE = 4
    HOLD = 5
    RESUME = 6
    ARM = 7
    PRM_SET = 8
    PRM_SAVE = 9
    LOCK = 10
    """Ask for (or renew) the command lock (a mission with ``ground:``;
    :mod:`zplatform.control.authority`)."""
    RELEASE = 11
    """Give the command lock up."""
    HANDOVER = 12
    """Hand the command lock to the operator numbered ``gn_cmd_element``
    (``ground.operators`` index + 1)."""
    TAKEOVER = 13
    """A flight director takes the command lock from whoever holds it."""
    APPROVE = 14
    """A second operator approves the ARM numbered ``gn_cmd_ref`` (two-person rule)."""


class CommandStatus(enum.IntEnum):
    """Outcome of the last request; the values of ``cn_cmd_status``.

    ``REJECTED_OUT_OF_BOUNDS``: a PRM_SET value outside the parameter's
    ``[min, max]``; ``REJECTED_PARAM_STATE``: the parameter may not change in
    the current state (its ``states``); ``REJECTED_BUSY``: a PRM_SAVE while
    the previous save is still being written."""

    NONE = 0
    ACCEPTED = 1
    REJECTED_UNKNOWN = 2
    REJECTED_NOT_ALLOWED = 3
    REJECTED_BAD_ARGUMENT = 4
    REJECTED_REPLAY = 5
    REJECTED_NOT_ARMED = 6
    REJECTED_AUTH = 7
    REJECTED_EPOCH = 8
    REJECTED_OUT_OF_BOUNDS = 9
    REJECTED_PARAM_STATE = 10
    REJECTED_BUSY = 11
    REJECTED_OPERATOR_UNKNOWN = 12
    """No operator, or one the mission's ``ground.operators`` does not list."""
    REJECTED_OPERATOR_REVOKED = 13
    """An operator (or that operator's key id) in ``ground.revoked``."""
    REJECTED_OPERATOR_AUTH = 14
    """The operator tag does not check under the operator's key (a forged
    or altered operator field, or an old key id)."""
    REJECTED_STATION = 15
    """An unknown station, or its station tag does not check."""
    REJECTED_VIEW_ONLY = 16
    """A viewer (role or station) never commands."""
    REJECTED_NOT_HOLDER = 17
    """Another operator holds the command lock, or nobody does (the detail names the holder)."""
    REJECTED_ROLE = 18
    """The operator's roles do not allow it (a takeover without ``flight_director``,
    an approval without an approving role, a handover to a non-commanding operator)."""
    REJECTED_APPROVAL_SELF = 19
    """An approval by the operator who armed, or by one who already approved."""
    REJECTED_APPROVAL_STALE = 20
    """An approval of an ARM that is not the current one (an earlier ARM's,
    or none open in its window)."""
    REJECTED_NOT_APPROVED = 21
    """A two-person command without a second operator's approval of its ARM."""


class Fault(enum.IntEnum):
    """Critical-error flag values (thesis 4.11.1); the values of ``cn_fault``."""

    NONE = 0
    DN_LOST = 1
    CONTROLLER_FAILED = 2
    SYNC_OVERRUNS = 3
    LOOP_OVERRUNS = 4
    CLOCK_DRIFT = 5
    DN_SAFED = 6
    """A device node the CN triggers reports that it safed itself because
    none of those triggers could run (``dnX_safed_why == CANNOT_RUN``): it
    answers, yet runs no loop (its clock is off, every trigger stale)."""
    MONITOR = 7
    """A mission monitor's response (``monitors:``), unless it names another fault."""
    THREAD_STALLED = 8
    """A thread of a node stopped checking in (a monitor on ``<node>_threads_stalled``)."""


class SafedWhy(enum.IntEnum):
    """Why a device node safed its actuators; the values of ``dnX_safed_why``."""

    NONE = 0
    CN_LOST = 1
    """No valid trigger for ``faults.dn_watchdog_loops`` periods (its watchdog)."""
    RUN_ENDED = 2
    """The CN's last loop (``dnX_final``): the run ended."""
    CANNOT_RUN = 3
    """The CN's triggers arrive, authentic and new, but none could run for
    ``faults.dn_watchdog_loops`` periods (stale, outside the node's clock
    window): the CN latches ``DN_SAFED``."""
    STOPPING = 4
    """The node is stopping (a clean exit)."""


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
    events use (``health.deadlines_ms.zenoh``). See :mod:`zplatform.core.health`."""

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
    PARAMS = 7
    """The CN's parameter saver (PRM_SAVE's file writes, :mod:`zplatform.control.params`)."""


class ParamLoad(enum.IntEnum):
    """What the control node's start made of its parameter file; the values
    of ``cn_prm_load_status`` (:mod:`zplatform.control.params`).

    Every status but ``LOADED`` and ``PARTIAL`` means every parameter is at
    its default; ``PARTIAL``: the file was read, and the values it held out
    of bounds (or not at all) are at their defaults (an event names each).
    """

    DEFAULTS = 0  # no file consulted (a lockstep run, or before the start)
    LOADED = 1
    PARTIAL = 2
    MISSING = 3
    CORRUPT = 4  # bad magic, version, checksum, length or encoding
    FOREIGN = 5  # another mission's file, or another parameter list's
    UNREADABLE = 6  # an OS error reading it


class ParamSave(enum.IntEnum):
    """The last PRM_SAVE (numbered by ``cn_prm_save_seq``); the values of
    ``cn_prm_save_status``."""

    NONE = 0
    PENDING = 1  # accepted, being written off the loop thread
    SAVED = 2  # in the file: written, synced, renamed, directory synced
    FAILED = 3  # not written; the file keeps what it had
