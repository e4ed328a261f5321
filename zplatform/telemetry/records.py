"""The ground side's typed records: telemetry counters, command outcomes, events, parameters.

Frozen ``msgspec.Struct``\\ s, snapshots in the manner of trio's statistics
objects: a :class:`TelemetryCounters` is what :class:`~zplatform.ground.logic.GroundLogic`
counted up to the moment it was taken, a :class:`CommandOutcome` the CN's
verdict on one request with its reason, an :class:`EventRecord` one event as
the ground received it (the line of the events JSONL, the ``event`` of
``tap --json``), a :class:`ParamRow` one mission parameter as ``zplatform
params`` and the console's parameter view show it. Their encodings are the
file formats: nothing else defines those fields.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import msgspec

from ..core.events import Event

if TYPE_CHECKING:
    from collections.abc import Mapping

    from ..config import Mission

__all__ = [
    "EPOCH_TIME_NS",
    "REFUSALS",
    "CommandOutcome",
    "EventRecord",
    "ParamRow",
    "TelemetryCounters",
    "format_outcome",
    "ns_text",
    "param_rows",
    "value_text",
]

REFUSALS = ("stale", "ahead", "old_epoch", "old_term", "not_newer", "jump")
"""Why an authentic, well-formed telemetry snapshot is refused:

* ``stale``: stamped further before this ground's clock than the freshness
  bound allows (a replay of an old run, or this host's clock is ahead);
* ``ahead``: stamped further after this ground's clock than the bound allows
  (this host's clock is behind);
* ``old_epoch``: of a control node run older than the one the ground follows;
* ``old_term``: of a term older than the one the ground follows (a control
  node that no longer commands: docs/architecture.md#failover);
* ``not_newer``: not newer than the last snapshot of the run followed (a
  duplicate, a reordered or replayed frame);
* ``jump``: further ahead of the last snapshot than the time since allows.
"""


class TelemetryCounters(msgspec.Struct, frozen=True):
    """What the ground counted, at one moment (:attr:`GroundLogic.counters`).

    ``received``: snapshots accepted; ``gaps``: loop numbers missing between
    accepted snapshots of one run (telemetry lost on the way); ``bad``:
    frames refused as malformed or unauthenticated (size, tag, layout,
    encoding); ``refused``: authentic snapshots refused, by reason
    (:data:`REFUSALS`); ``epoch``: the control node run followed (its
    ``cn_epoch``; 0 before the first accepted snapshot); ``epoch_changes``:
    times the ground followed a restarted control node to a newer run;
    ``term``/``term_changes``: the term followed and the takeovers followed;
    ``first_seq``/``last_seq``: loop numbers of the first and the last
    accepted snapshot (-1 before any); ``bad_events``: event records that
    did not decode; ``stale_events``: authentic event records refused as
    not fresh (a replay, or a stamp beyond the clock bound).
    """

    received: int = 0
    gaps: int = 0
    bad: int = 0
    refused: dict[str, int] = {}
    epoch: int = 0
    epoch_changes: int = 0
    first_seq: int = -1
    last_seq: int = -1
    bad_events: int = 0
    stale_events: int = 0
    """Authentic event records refused as not fresh (replayed, or stamped
    beyond the freshness bound of the ground's clock)."""
    term: int = 0
    """A redundant mission's term followed (0: no terms, or none yet)."""
    term_changes: int = 0
    """Takeovers the ground followed: a newer term's snapshots."""
    events_missed: int = 0
    """Verified event records that did not arrive: numbers skipped between
    two of one node's run (:meth:`~zplatform.ground.logic.GroundLogic.on_event_bytes`),
    whether filled later from the control node's recorder or not."""
    iox: int = 0
    """Snapshots that came over iceoryx2 (a ground node on the CN's host,
    zplatform.runtime.tmiox), of those its intake admitted; the rest came by zenoh."""
    duplicates: int = 0
    """Snapshots dropped as the other path's copy of one taken (iceoryx2 and
    zenoh both carry each): not refusals."""
    path_fallbacks: int = 0
    """Times the telemetry fell back from iceoryx2 to zenoh."""
    unchecked: int = 0
    """Snapshots dropped after their authentic-looking header without their
    body's tag checked, the body-MAC budget spent (also counted in ``bad``
    or ``refused``): a flood of junk or replays behind genuine headers."""

    @property
    def rejected(self) -> int:
        """Every snapshot not applied: bad frames and refusals."""
        return self.bad + sum(self.refused.values())


class CommandOutcome(msgspec.Struct, frozen=True):
    """The CN's verdict on one command request, with its reason.

    ``seq`` is the request's number, ``status`` a ``cn_cmd_status`` name as
    a telemetry snapshot provably after the request showed it (same run,
    a later loop, the number echoed in ``cn_cmd_seq`` or
    ``cn_cmd_reject_seq``), or ``NO_VERDICT`` when none came. ``loop`` is
    the loop of that snapshot, ``t_ns`` its time after the start of loop 1.
    ``reason`` says why (the detail of the CN's ``cmd_accepted`` /
    ``cmd_rejected`` event); ``reason_from`` is ``"cn"`` when it came from
    that event, ``"derived"`` when the event did not arrive and the ground
    derived it from the verdict snapshot, ``"ground"`` for the ground's own
    (``NO_VERDICT``), ``""`` when there is nothing to say (an ACCEPTED with
    no detail). ``source`` is the script line (``file:line``), if any.
    ``operator``: ``operator@station`` the request named (a mission with
    ``ground:``; "" when it named nobody).
    """

    command: str
    seq: int
    status: str
    loop: int = 0
    t_ns: int = 0
    source: str = ""
    reason: str = ""
    reason_from: Literal["cn", "derived", "ground", ""] = ""
    operator: str = ""

    @property
    def accepted(self) -> bool:
        return self.status == "ACCEPTED"


def format_outcome(o: CommandOutcome) -> str:
    """One line for the operator: ``LAUNCH #2: ACCEPTED``, ``WRITE #4:
    ACCEPTED (led_a_cmd = True)``, ``NOOP #3: REJECTED_NOT_ALLOWED: not
    allowed in state B``; ``LOCK #5 by pat@pad: ACCEPTED`` when the request
    named its operator; a derived reason says so."""
    by = f" by {o.operator}" if o.operator else ""
    text = f"{o.command} #{o.seq}{by}: {o.status}"
    if not o.reason or (by and o.reason == by[1:]):  # the CN's detail names them too
        return text
    text += f" ({o.reason})" if o.accepted else f": {o.reason}"
    if o.reason_from == "derived":
        text += " [derived from telemetry: the control node's event did not arrive]"
    return text


class EventRecord(msgspec.Struct, frozen=True):
    """One event as the ground received it: ``rx_time_ns`` (the receiver's
    clock, as in the telemetry CSV), then the :class:`~zplatform.core.events.Event`'s
    ``node``, ``seq``, ``t_ns``, ``severity`` (by name), ``id`` and ``text``,
    and ``verified``: True when its node's tag checked, False when the
    receiver holds no key for that node (shown marked unverified), None when
    the mission does not authenticate; ``filled``: True when it did not
    arrive live but was filled from the control node's flight recorder
    (:mod:`zplatform.ground.gapfill`: later than the events after it, same
    checks). One line of the events JSONL, in this field order."""

    rx_time_ns: int
    node: str
    seq: int
    t_ns: int
    severity: str
    id: str
    text: str
    verified: bool | None = None
    filled: bool = False

    @classmethod
    def of(
        cls, e: Event, rx_time_ns: int, verified: bool | None = None, filled: bool = False
    ) -> EventRecord:
        return cls(
            rx_time_ns, e.node, e.seq, e.t_ns, e.severity_name, e.id, e.text, verified, filled
        )


class ParamRow(msgspec.Struct, frozen=True):
    """One mission parameter as the ground shows it: ``value`` as read
    (``"-"`` when unknown), ``default``, ``bounds`` with units
    (``"[300, 1000] m"``; ``""`` for a bool), ``states`` in which it may
    change, ``hazardous`` (PRM_SET needs ARM first), ``doc``."""

    name: str
    type: str
    value: str
    default: str
    bounds: str
    states: list[str]
    hazardous: bool
    doc: str


def param_rows(mission: Mission, values: Mapping[str, object] | None) -> list[ParamRow]:
    """Every parameter of ``mission`` in declaration order, with its value
    from ``values`` (by name: a telemetry snapshot, a parameter file; None
    or a name missing: unknown)."""
    from ..control.params import param_states

    rows = []
    for p in mission.params:
        units = f" {p.units}" if p.units else ""
        bounds = (
            f"[{value_text(p.min)}, {value_text(p.max)}]{units}" if p.min is not None else units[1:]
        )
        rows.append(
            ParamRow(
                name=p.name,
                type=p.type,
                value=value_text(values[p.name])
                if values is not None and p.name in values
                else "-",
                default=value_text(p.default),
                bounds=bounds,
                states=param_states(mission, p),
                hazardous=p.hazardous,
                doc=p.doc,
            )
        )
    return rows


EPOCH_TIME_NS = 10**17
"""An ``*_ns`` value at or above this (1973) is a time of day (the node
clock counts from the Unix epoch); below it, a duration or an offset."""


def ns_text(v: int) -> str:
    """An ``*_ns`` element's value for a person: a time of day as UTC
    ``HH:MM:SS.mmm``, a duration or offset in s, ms or us (``0`` as ``0``)."""
    if v >= EPOCH_TIME_NS:
        s, ns = divmod(v, 1_000_000_000)
        return f"{(s // 3600) % 24:02d}:{(s // 60) % 60:02d}:{s % 60:02d}.{ns // 1_000_000:03d}"
    a = abs(v)
    if a == 0:
        return "0"
    if a < 1_000_000:
        return f"{v / 1e3:.1f} us"
    if a < 1_000_000_000:
        return f"{v / 1e6:.3f} ms"
    return f"{v / 1e9:.3f} s"


def value_text(v: object, *, bools: tuple[str, str] = ("false", "true"), digits: int = 7) -> str:
    """A value as the ground shows it: a bool as ``bools`` (false, true), a float to ``digits``.

    The defaults are the parameter table's (the words of a mission file);
    the console shows Data Vector values as the telemetry CSV spells bools,
    ``bools=("0", "1")``, to 6 digits. Anything else is ``str(v)``.
    """
    if isinstance(v, bool):
        return bools[1] if v else bools[0]
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)
