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

A line naming its sender (``as alice@pad: ...``) is signed by the driver's
``signers`` (key files; a lockstep run's keys), resolved at construction.
Without a fixed duration a run plays on :data:`SETTLE_S` past the script's
last command (at least :data:`MIN_DURATION_S`): ``sim`` in virtual time from
the command's time, ``up`` from its verdict (the ground node's
``script_done`` event).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import msgspec

from ..config import Mission
from ..control.authority import Signer
from ..control.uplink import CheckedCommand, ScriptCommand, did_you_mean, validate_command
from ..errors import CommandError, ZPlatformError
from ..telemetry.records import CommandOutcome

__all__ = ["MIN_DURATION_S", "SETTLE_S", "ScriptPlayer", "Signers", "script_duration_s"]

Signers = Callable[[str, str], Signer]
"""What signs a script line naming its sender: ``(operator, station)`` to
their :class:`~zplatform.control.authority.Signer` (CommandError or
KeyError_ when it cannot: :func:`zplatform.ground.identity.station_signer`)."""

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

    def submit(
        self,
        checked: CheckedCommand,
        *,
        now_ns: int,
        source: str = "",
        signer: Signer | None = None,
    ) -> int: ...

    def result(self, ticket: int) -> list[CommandOutcome] | None: ...


class _Entry(msgspec.Struct, frozen=True):
    due_loop: int
    command: ScriptCommand
    checked: CheckedCommand  # validated once, at construction
    signer: Signer | None  # who sends it (None: the ground's own signer)


def _line_signer(
    mission: Mission, c: ScriptCommand, signers: Signers | None, known: dict[str, Signer]
) -> Signer | None:
    """The signer of script line ``c`` naming its sender (None: it names
    nobody); CommandError naming the line when the mission has no such
    operator or station, or no key signs as them."""
    if c.operator is None or c.station is None:
        return None
    who = f"{c.operator}@{c.station}"
    if who in known:
        return known[who]
    g = mission.ground
    if g is None:
        raise CommandError(
            f"{c.source}: as {who}: mission {mission.mission!r} has no `ground:` operators"
        )
    for kind, name, listed in (
        ("operator", c.operator, [o.name for o in g.operators]),
        ("station", c.station, [s.name for s in g.stations]),
    ):
        if name not in listed:
            raise CommandError(
                f"{c.source}: as {who}: mission lists no {kind} {name!r} (ground.{kind}s)"
                + (did_you_mean(name, listed) or f"; {kind}s: {', '.join(listed)}")
            )
    if signers is None:
        raise CommandError(
            f"{c.source}: as {who}: this ground has no operators' keys to sign as another operator"
        )
    try:
        signer = signers(c.operator, c.station)
    except ZPlatformError as exc:  # a key file missing or refused
        raise CommandError(f"{c.source}: as {who}: {exc}") from exc
    known[who] = signer
    return signer


class ScriptPlayer:
    """Submits a script's commands to a :class:`~.logic.GroundLogic` when due
    (module doc). Construction resolves every line against the mission
    (CommandError naming ``file:line``), and the sender a line names by
    ``signers`` (module doc; None: a line naming one is refused). Never
    blocks, but for what ``signers`` reads (key files) at construction."""

    def __init__(
        self,
        mission: Mission,
        script: Sequence[ScriptCommand],
        signers: Signers | None = None,
    ) -> None:
        if script and not mission.has_ground:
            raise CommandError(
                f"{script[0].source}: mission {mission.mission!r} has no ground node 'gn' "
                "to send commands"
            )
        period = mission.period_ns
        entries = []
        known: dict[str, Signer] = {}
        for c in sorted(script, key=lambda c: c.at_ns):
            checked = validate_command(mission, c.command, c.element, c.value, c.source)
            signer = _line_signer(mission, c, signers, known)
            entries.append(_Entry(1 + -(-c.at_ns // period), c, checked, signer))
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
        self._tickets.append(
            logic.submit(e.checked, now_ns=now_ns, source=e.command.source, signer=e.signer)
        )

    def done(self, logic: _Logic) -> bool:
        """Every command was sent and its outcome released."""
        return self._next == len(self._script) and all(
            logic.result(t) is not None for t in self._tickets
        )

    def results(self, logic: _Logic) -> list[CommandOutcome]:
        """The released outcomes of the script's commands, in order."""
        return [o for t in self._tickets for o in (logic.result(t) or [])]
