"""Playing a command script from the ground, sans-IO.

A script (:func:`zplatform.control.uplink.parse_commands`) times each command from
the start of loop 1. A command at time ``T`` is due in the first loop ``n``
whose start ``(n - 1) * period`` is at or after ``T``: the player submits it
to the :class:`~.logic.GroundLogic` when the ground accepts the telemetry of
loop ``n - 1``, so the CN applies it in loop ``n`` in every driver (loop
numbers, not wall-clock times, so live runs and ``sim`` agree). The ground
answers telemetry, so a command due in loop 1 goes in loop 2. Commands go
out one at a time: the next is submitted only after the CN's verdict on the
previous one (the logic numbers them, resends lost frames and reads the
verdicts), so two commands due together go in consecutive loops.

Without a fixed duration a run plays on :data:`SETTLE_S` past the script's
last command (at least :data:`MIN_DURATION_S`): ``sim`` in virtual time from
the command's time, ``up`` from its verdict (the ground node's
``script_done`` event).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import msgspec

from ..config import Mission
from ..control.uplink import CheckedCommand, ScriptCommand, validate_command
from ..errors import CommandError
from ..telemetry.records import CommandOutcome

__all__ = ["MIN_DURATION_S", "SETTLE_S", "ScriptPlayer", "script_duration_s"]

SETTLE_S = 15.0
"""How long a run goes on past the script's last command, by default."""
MIN_DURATION_S = 10.0
"""The shortest run a script gets, by default."""


def script_duration_s(script: Sequence[ScriptCommand]) -> float:
    """Last command + :data:`SETTLE_S`, at least :data:`MIN_DURATION_S` (s)."""
    last = max((c.at_ns for c in script), default=0) / 1e9
    return max(MIN_DURATION_S, last + SETTLE_S)


class _Logic(Protocol):
    """What the player uses of the :class:`~.logic.GroundLogic` it is handed
    (a protocol, so this module does not import the logic that imports it)."""

    @property
    def idle(self) -> bool: ...

    def submit(self, checked: CheckedCommand, *, now_ns: int, source: str = "") -> int: ...

    def result(self, ticket: int) -> list[CommandOutcome] | None: ...


class _Entry(msgspec.Struct, frozen=True):
    due_loop: int
    command: ScriptCommand
    checked: CheckedCommand  # validated once, at construction


class ScriptPlayer:
    """Submits a script's commands to a :class:`~.logic.GroundLogic` when due
    (module doc). Construction resolves every line against the mission
    (CommandError naming ``file:line``). Never blocks."""

    def __init__(self, mission: Mission, script: Sequence[ScriptCommand]) -> None:
        if script and not mission.has_ground:
            raise CommandError(
                f"{script[0].source}: mission {mission.mission!r} has no ground node 'gn' "
                "to send commands"
            )
        period = mission.period_ns
        entries = []
        for c in sorted(script, key=lambda c: c.at_ns):
            checked = validate_command(mission, c.command, c.element, c.value, c.source)
            entries.append(_Entry(1 + -(-c.at_ns // period), c, checked))
        self._script = entries
        self._next = 0
        self._tickets: list[int] = []

    @property
    def pending(self) -> list[str]:
        """Sources (``file:line``) of the commands not sent yet."""
        return [e.command.source for e in self._script[self._next :]]

    def step(self, logic: _Logic, loop: int, now_ns: int, can_send: bool) -> None:
        """After the ground accepted the snapshot of ``loop``: submit the
        next command if it is due and nothing waits for a verdict."""
        if self._next == len(self._script) or not can_send or not logic.idle:
            return
        e = self._script[self._next]
        if e.due_loop > loop + 1:
            return
        self._next += 1
        self._tickets.append(logic.submit(e.checked, now_ns=now_ns, source=e.command.source))

    def done(self, logic: _Logic) -> bool:
        """Every command was sent and its outcome released."""
        return self._next == len(self._script) and all(
            logic.result(t) is not None for t in self._tickets
        )

    def results(self, logic: _Logic) -> list[CommandOutcome]:
        """The released outcomes of the script's commands, in order."""
        return [o for t in self._tickets for o in (logic.result(t) or [])]
