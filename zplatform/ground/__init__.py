"""The ground side: receiving, checking, logging and commanding (one package).

* :mod:`.logic`: :class:`GroundLogic`, the ground's sans-IO logic (telemetry
  checks, counters, command requests and verdicts, the script player's
  host), used by every driver;
* :mod:`.link`: :class:`~.link.GroundLink`, the zenoh driver (one session,
  one telemetry subscriber, one event intake, one command publisher);
* the typed records (counters, command outcomes, events) are
  :mod:`zplatform.records` (re-exported here), below every layer that logs
  or shows them;
* :mod:`.script`: the command-script player;
* :mod:`.status`: the status line and the loop-rate meter;
* :mod:`.logger`: the telemetry CSV and the events file;
* :mod:`.tap`: ``zplatform tap``'s decoder and loop;
* :mod:`.tools`: ``zplatform cmd`` and the line prompt.

The ground node's process is :mod:`zplatform.node.ground`; the console
(:mod:`zplatform.console`) and ``up``'s watcher (:mod:`zplatform.supervisor`)
drive a :class:`~.link.GroundLink` too, and the lockstep runner drives a
:class:`GroundLogic` in virtual time.

Only the sans-IO modules are imported here; the zenoh driver and the tools
are imported from their modules (``from zplatform.ground.link import
GroundLink``), so the lockstep runner and the record types stay light.
"""

from __future__ import annotations

from ..records import REFUSALS, CommandOutcome, EventRecord, TelemetryCounters, format_outcome
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
