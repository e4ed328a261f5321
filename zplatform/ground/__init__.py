"""The ground side: receiving, checking, logging and commanding (one package).

:mod:`.logic` (:class:`GroundLogic`, the ground's sans-IO logic: telemetry
checks, counters, command requests and verdicts, the script player's host,
used by every driver), :mod:`.link` (the zenoh driver,
:class:`~.link.GroundLink`), :mod:`.script` (the command-script player),
:mod:`.status` (the status line and loop-rate meter), :mod:`.logger` (the
telemetry CSV and events file), :mod:`.tap` (``zplatform tap``) and
:mod:`.tools` (``zplatform cmd`` and the line prompt). The typed records
(counters, command outcomes, events) are :mod:`zplatform.telemetry.records`,
re-exported here. The ground node's process is :mod:`zplatform.node.ground`;
the console and ``up``'s watcher drive a :class:`~.link.GroundLink` too, and
the lockstep runner drives a :class:`GroundLogic` in virtual time.

Contract: importing this package imports only the sans-IO modules; the zenoh
driver and the tools are imported from their modules (``from
zplatform.ground.link import GroundLink``), so the lockstep runner and the
record types stay light. The design: docs/architecture.md#ground.
"""

from __future__ import annotations

from ..telemetry.records import (
    REFUSALS,
    CommandOutcome,
    EventRecord,
    TelemetryCounters,
    format_outcome,
)
from .logic import GroundLogic, needs_arm
from .script import ScriptPlayer
from .status import RateMeter, status_line

__all__ = [
    "REFUSALS",
    "CommandOutcome",
    "EventRecord",
    "GroundLogic",
    "RateMeter",
    "ScriptPlayer",
    "TelemetryCounters",
    "format_outcome",
    "needs_arm",
    "status_line",
]
