"""Event records and the event catalogue: what a node tells the operator, apart from telemetry.

Every event is declared once in the catalogue (:class:`EV`): a stable
numeric id, a name, a :class:`Severity` and a format string; call sites
name the entry and pass its arguments (``events.emit(EV.CMD_REJECTED,
t_ns, name=..., ...)``), never a severity. An :class:`Event` is one record,
published on ``{vehicle}/{node}/events``.

:meth:`EventLog.emit` is sans-IO and never blocks: it appends to a bounded
queue that the runtime takes after the loop (:meth:`EventLog.drain`) and
publishes. Full, it keeps the oldest and counts the new ones
(:attr:`EventLog.dropped`); every event takes the next ``seq``, dropped
ones too, so a drop shows as a gap. It raises only
:class:`~zplatform.errors.EventError` for an entry not in the catalogue (a
bug), never for its arguments. :func:`decode_event` raises
:class:`~zplatform.errors.FrameFormatError` on anything that is not an
event record; :class:`EventReader` checks tag and freshness.
Detail: docs/architecture.md#the-event-log; wire: codecs/FORMAT.md §6.4.
"""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING, Annotated, Any, ClassVar

import msgspec
from msgspec import Meta

from ..errors import EventError, FrameFormatError

if TYPE_CHECKING:
    from ..config import Mission
    from .auth import Channel, KeySet, Run

__all__ = [
    "EV",
    "MAX_TEXT",
    "Event",
    "EventLog",
    "EventReader",
    "EventType",
    "Severity",
    "StaleRecordError",
    "decode_event",
    "encode_event",
]


class Severity(enum.IntEnum):
    """How much an event matters (F Prime's seven severities), least to most.

    A higher value is more important, so ``severity >= Severity.WARNING_LO``
    selects the warnings and worse. The values are the wire encoding.

    * ``DIAGNOSTIC``: for developers, not shown to the operator by default;
    * ``ACTIVITY_LO`` / ``ACTIVITY_HI``: the system doing its job (a hold
      ended; a state change);
    * ``COMMAND``: an operator command was executed;
    * ``WARNING_LO``: something was refused or went wrong and was absorbed
      (a rejected command, a bad frame, a counted error);
    * ``WARNING_HI``: something failed and the platform acted (a component
      safed, a fault latched, which the state machine answers);
    * ``FATAL``: software could not make a part of the system safe.
    """

    DIAGNOSTIC = 0
    ACTIVITY_LO = 1
    ACTIVITY_HI = 2
    COMMAND = 3
    WARNING_LO = 4
    WARNING_HI = 5
    FATAL = 6


_SEVERITY_NAMES = tuple(s.name for s in Severity)
_MAX_SEVERITY = len(_SEVERITY_NAMES) - 1


class EventType(msgspec.Struct, frozen=True):
    """One catalogue entry: ``id`` (stable number), ``name``, ``severity``, ``format``.

    ``format`` is a :meth:`str.format` string with named fields only; the
    keyword arguments given to :meth:`EventLog.emit` fill it.
    """

    id: int
    name: str
    severity: Severity
    format: str

    def text(self, **args: Any) -> str:
        """The record text for ``args``; never raises.

        A missing or unformattable argument does not raise (an event in a
        failure path must not take the loop down with it): the text is then
        the format string followed by the arguments as given. Text longer
        than :data:`MAX_TEXT` characters is cut there and marked, so every
        event fits one small message (the lowlatency transport cannot
        fragment; :mod:`zplatform.runtime.transport`).
        """
        try:
            text = self.format.format(**args)
        except (KeyError, IndexError, ValueError, TypeError, AttributeError):
            text = f"{self.format} {args!r}"
        if len(text) > MAX_TEXT:
            text = text[: MAX_TEXT - len(_CUT)] + _CUT
        return text


#: Longest event text (characters); longer text is cut and ends in ``_CUT``.
MAX_TEXT = 2048
_CUT = " ...(cut)"


class EV:
    """The event catalogue: every event the platform emits, declared once.

    Ids are stable (records, logs and ground tools may key on them): add new
    entries with new ids, never renumber or reuse one.
    """

    # state machine (ACTIVITY: the system doing what the mission says)
    STATE_CHANGE = EventType(
        1, "state_change", Severity.ACTIVITY_HI, "state {src} -> {dst} ({why})"
    )
    HOLD = EventType(2, "hold", Severity.ACTIVITY_HI, "hold in state {state} at {tis_s:.3f} s")
    RESUME = EventType(
        3, "resume", Severity.ACTIVITY_HI, "resume in state {state} at {tis_s:.3f} s"
    )
    HOLD_ENDED = EventType(4, "hold_ended", Severity.ACTIVITY_LO, "hold ended by a transition")
    # operator commands
    CMD_ACCEPTED = EventType(
        10, "cmd_accepted", Severity.COMMAND, "command {name} #{seq} accepted{detail}"
    )
    CMD_REJECTED = EventType(
        11,
        "cmd_rejected",
        Severity.WARNING_LO,
        "command {name} #{seq} rejected ({status}): {detail}",
    )
    CMD_SUPERSEDED = EventType(
        12,
        "cmd_superseded",
        Severity.WARNING_LO,
        "pending command {name} superseded by {by} before a transition took it",
    )
    CMD_DROPPED = EventType(
        13,
        "cmd_dropped",
        Severity.WARNING_LO,
        "{n} command request frame(s) dropped: {why}",
    )
    CMD_LOCK = EventType(
        14,
        "cmd_lock",
        Severity.COMMAND,
        "command lock {what}: {text}",
    )
    # errors after start (thesis 4.11.1)
    FAULT = EventType(20, "fault", Severity.WARNING_HI, "fault {fault}: {text}")
    ERROR = EventType(21, "error", Severity.WARNING_LO, "{text}")
    # components
    CONTROLLER_FAILED = EventType(
        30,
        "controller_failed",
        Severity.WARNING_HI,
        "controller {name} raised {exc_type} in {mode}: {exc}; safed",
    )
    CONTROLLER_DISABLED = EventType(
        31,
        "controller_disabled",
        Severity.FATAL,
        "controller {name} cannot be safed ({exc_type} in safed: {exc}); "
        "disabled, its outputs are left as they are",
    )
    DEVICE_FAILED = EventType(
        32, "device_failed", Severity.WARNING_HI, "device {name} raised {exc_type}: {exc}"
    )
    BOARD_FAILED = EventType(
        33, "board_failed", Severity.WARNING_HI, "{node} board step raised {exc_type}: {exc}"
    )
    # a component's own report (Component.report): its text, in the mission's words
    COMPONENT_ACTIVITY = EventType(34, "component_activity", Severity.ACTIVITY_HI, "{name}: {text}")
    COMPONENT_WARNING = EventType(35, "component_warning", Severity.WARNING_HI, "{name}: {text}")
    # transport
    BAD_FRAME = EventType(40, "bad_frame", Severity.WARNING_LO, "{source} rejected: {reason}")
    # fail safe (a node without its control node)
    DN_SAFED = EventType(
        50,
        "dn_safed",
        Severity.WARNING_HI,
        "{node} safed its actuators: {why}",
    )
    DN_SAFED_AT_EXIT = EventType(
        53, "dn_safed_at_exit", Severity.ACTIVITY_HI, "{node} safed its actuators: {why}"
    )
    DN_SAFED_RUN_ENDED = EventType(
        54, "dn_safed_run_ended", Severity.ACTIVITY_HI, "{node} safed its actuators: {why}"
    )
    DN_REENABLED = EventType(
        51,
        "dn_reenabled",
        Severity.ACTIVITY_HI,
        "{node} re-enabled: the control node triggered it {n} loops in a row",
    )
    # health and monitors (zplatform.core.health, zplatform.control.monitors,
    # zplatform.control.watchdog)
    THREAD_STALLED = EventType(
        100,
        "thread_stalled",
        Severity.WARNING_HI,
        "{node}: thread {thread} has not checked in within its deadline ({deadline_ms:g} ms)",
    )
    THREAD_RESUMED = EventType(
        101, "thread_resumed", Severity.ACTIVITY_HI, "{node}: thread {thread} checks in again"
    )
    MONITOR_WARNING = EventType(
        102, "monitor_warning", Severity.WARNING_LO, "monitor {name}: {what}"
    )
    MONITOR_TRIPPED = EventType(
        103, "monitor_tripped", Severity.WARNING_HI, "monitor {name}: {what}; {response}"
    )
    MONITOR_CLEARED = EventType(
        104, "monitor_cleared", Severity.ACTIVITY_LO, "monitor {name}: clear ({what})"
    )
    WATCHDOG_WITHHELD = EventType(
        105,
        "watchdog_withheld",
        Severity.WARNING_HI,
        "{node}: watchdog no longer stroked, thread(s) {threads} stalled; {consequence}",
    )
    WATCHDOG_RESUMED = EventType(
        106, "watchdog_resumed", Severity.ACTIVITY_HI, "{node}: watchdog stroked again"
    )
    # the ground side (zplatform.ground.GroundLogic: what the ground believes)
    TM_JOINED = EventType(
        70,
        "tm_joined",
        Severity.ACTIVITY_LO,
        "following control node run {epoch} from loop {loop}",
    )
    CN_RESTARTED = EventType(
        71,
        "cn_restarted",
        Severity.WARNING_HI,
        "control node restarted: epoch {old} -> {new}; following the new run from loop {loop}",
    )
    TM_REFUSED = EventType(
        72,
        "tm_refused",
        Severity.WARNING_LO,
        "telemetry refused ({reason}): {detail}; further refusals are counted, not evented",
    )
    SCRIPT_DONE = EventType(
        73,
        "script_done",
        Severity.ACTIVITY_HI,
        "command script done: {n} command(s), {accepted} accepted; last verdict in loop {loop}",
    )
    GAP_FILLED = EventType(
        74,
        "gap_filled",
        Severity.ACTIVITY_LO,
        "filled loops {first}..{last} ({n} snapshot(s)) from the control node's recorder",
    )
    GAP_UNFILLED = EventType(
        75,
        "gap_unfilled",
        Severity.WARNING_LO,
        "loops {first}..{last}: {n} snapshot(s) not filled from the control node's recorder: {why}",
    )
    EVENTS_MISSED = EventType(
        77,
        "events_missed",
        Severity.WARNING_LO,
        "{n} event(s) of {what} did not arrive: {fate}",
    )
    EVENTS_FILLED = EventType(
        78,
        "events_filled",
        Severity.ACTIVITY_LO,
        "filled {n} event(s) of {node} (#{first}..#{last}) from the control node's recorder",
    )
    EVENTS_UNFILLED = EventType(
        79,
        "events_unfilled",
        Severity.WARNING_LO,
        "{n} event(s) of {node} ({which}) not filled from the control node's recorder: {why}",
    )
    # the flight recorder (zplatform.recorder), on the node that records
    RECORDER_DROPPING = EventType(
        80,
        "recorder_dropping",
        Severity.WARNING_LO,
        "{node}'s recorder drops loops from loop {loop}: {why}",
    )
    RECORDER_RESUMED = EventType(
        81,
        "recorder_resumed",
        Severity.ACTIVITY_LO,
        "{node}'s recorder keeps loops again from loop {loop}; {n} loop(s) dropped "
        "({first}..{last})",
    )
    RECORDER_EVICTED = EventType(
        82,
        "recorder_evicted",
        Severity.ACTIVITY_LO,
        "{node}'s recorder ring is full: removed its oldest file {file} ({size} bytes); "
        "{n} file(s) removed so far",
    )
    RECORDER_FAILED = EventType(
        83, "recorder_failed", Severity.WARNING_LO, "{node}'s recorder cannot {what}: {error}"
    )
    # the ground archive (zplatform.archive), on the ground node
    ARCHIVE_DROPPING = EventType(
        84,
        "archive_dropping",
        Severity.WARNING_LO,
        "the ground archive's queue is full: {n} snapshot(s) and {events} event(s) not "
        "archived so far",
    )
    ARCHIVE_FAILED = EventType(
        85, "archive_failed", Severity.WARNING_LO, "the ground archive cannot {what}: {error}"
    )
    ARCHIVE_DAMAGED = EventType(
        86, "archive_damaged", Severity.WARNING_LO, "the ground archive skipped damage: {what}"
    )
    ARCHIVE_REMOVED = EventType(
        87,
        "archive_removed",
        Severity.ACTIVITY_LO,
        "the ground archive removed run {run} ({size} bytes): {why}",
    )
    # clock sync (a device node's re-syncs, zplatform.runtime.clocksync)
    CLOCK_REFUSED = EventType(
        60,
        "clock_refused",
        Severity.WARNING_LO,
        "{node} refused {n} clock-sync replies ({auth} with a bad tag, {replay} for another "
        "exchange): a peer without the link key answers on the clock key, or replays",
    )
    CLOCK_TIMEOUT = EventType(
        62,
        "clock_timeout",
        Severity.WARNING_LO,
        "{node}'s clock sync went unanswered {n} more time(s), {total} in all: the clock "
        "is silent, slow or unreachable (each exchange gives up at its timeout)",
    )
    CLOCK_JUMP_REFUSED = EventType(
        61,
        "clock_jump_refused",
        Severity.WARNING_LO,
        "{node} refused a clock estimate of {new_ms:+.3f} ms: {jump_ms:+.3f} ms from the last "
        "({old_ms:+.3f} ms), beyond the bound of {bound_ms:g} ms; it keeps the last",
    )
    # mission parameters (zplatform.control.params)
    PRM_LOADED = EventType(
        90,
        "prm_loaded",
        Severity.ACTIVITY_HI,
        "parameters loaded from {path}: {n} value(s), saved by PRM_SAVE #{seq}",
    )
    PRM_FILE_MISSING = EventType(
        91,
        "prm_file_missing",
        Severity.WARNING_LO,
        "no parameter file at {path}: every parameter at its default",
    )
    PRM_FILE_REFUSED = EventType(
        92,
        "prm_file_refused",
        Severity.WARNING_HI,
        "parameter file {path} refused ({status}): {why}; every parameter at its default",
    )
    PRM_DEFAULTED = EventType(
        93,
        "prm_defaulted",
        Severity.WARNING_HI,
        "parameter {name}: {why}; its default {default!r} is used",
    )
    PRM_SAVED = EventType(
        94, "prm_saved", Severity.ACTIVITY_HI, "parameters saved (PRM_SAVE #{seq}) to {where}"
    )
    PRM_SAVE_FAILED = EventType(
        95,
        "prm_save_failed",
        Severity.WARNING_HI,
        "PRM_SAVE #{seq} failed: {why}; the parameter file keeps what it had",
    )

    # failover: terms, the standby control node, restarts in flight
    # (zplatform.control.fencing, zplatform.control.failover; docs/architecture.md#failover)
    CN_TOOK_COMMAND = EventType(
        110,
        "cn_took_command",
        Severity.WARNING_HI,
        "{node} took command in term {term} at loop {loop}: {why}",
    )
    CN_STOOD_DOWN = EventType(
        111,
        "cn_stood_down",
        Severity.WARNING_HI,
        "{node} stands down at loop {loop}: term {term} commands ({why}); it follows as standby",
    )
    CN_FOLLOWING = EventType(
        112,
        "cn_following",
        Severity.ACTIVITY_HI,
        "{node} follows {commander} (term {term}) from loop {loop}: ready to take over",
    )
    CN_TAKEOVER_HELD = EventType(
        113,
        "cn_takeover_held",
        Severity.WARNING_LO,
        "{node} hears nothing from the commander since loop {loop} but does not take command: "
        "{why}",
    )
    DN_TERM_FENCED = EventType(
        114,
        "dn_term_fenced",
        Severity.WARNING_LO,
        "{node} answered {n} trigger(s) of term {term} without running them: it follows term "
        "{seen} ({why})",
    )
    DN_NEW_TERM = EventType(
        115,
        "dn_new_term",
        Severity.ACTIVITY_HI,
        "{node} follows term {term} from loop {loop} (was term {old})",
    )
    CN_RESUMED = EventType(
        116,
        "cn_resumed",
        Severity.WARNING_HI,
        "{node} restarted in flight and resumed run {epoch} at loop {loop} in state {state}, "
        "from {source}",
    )
    CN_RESTARTED_IN_FLIGHT = EventType(
        117,
        "cn_restarted_in_flight",
        Severity.FATAL,
        "{node} restarted while the device nodes were mid-run (their last loop {loop}) and "
        "holds no state of that run ({why}): it starts over",
    )
    DN_FAULT_CLEARED = EventType(
        118,
        "dn_fault_cleared",
        Severity.ACTIVITY_HI,
        "{dn} answers again ({n} loops in a row): {fault} cleared (faults.dn_rejoin_clears)",
    )
    CN_STANDBY_READY = EventType(
        119,
        "cn_standby_ready",
        Severity.ACTIVITY_LO,
        "{node}: the standby {peer} is {what}",
    )
    DN_INTERLOCKED = EventType(
        120,
        "dn_interlocked",
        Severity.WARNING_HI,
        "{node} drove {n} hazardous output(s) to their safe value in state {state}, "
        "where they may not be driven: {names} (hazardous_outputs)",
    )
    QUERY_RECOVERED = EventType(
        125,
        "query_recovered",
        Severity.WARNING_LO,
        "{node} declared its querier again for {dns} ({n} time(s), {total} in all): a live "
        "device node's queries had no reply for {loops} loops in a row (a route lost in "
        "zenoh, eclipse-zenoh/zenoh#2517)",
    )
    SYNC_ON_SHM = EventType(
        126,
        "sync_on_shm",
        Severity.ACTIVITY_LO,
        "{node}: {dn}'s sync takes shared memory ({why}; transport.intra_host)",
    )
    SYNC_FALLBACK = EventType(
        127,
        "sync_fallback",
        Severity.WARNING_LO,
        "{node}: {dn}'s sync falls back to zenoh: {why} ({fallbacks} fallback(s) so far; "
        "shared memory is tried again later)",
    )
    BULK_ON_SHM = EventType(
        128,
        "bulk_on_shm",
        Severity.ACTIVITY_LO,
        "{node}: bulk channel {channel} takes iceoryx2 shared memory ({why}; transport.intra_host)",
    )
    BULK_FALLBACK = EventType(
        129,
        "bulk_fallback",
        Severity.WARNING_LO,
        "{node}: bulk channel {channel} falls back to zenoh: {why} ({fallbacks} fallback(s) "
        "so far; iceoryx2 is taken again when its samples come)",
    )
    BULK_REFUSED = EventType(
        130,
        "bulk_refused",
        Severity.WARNING_LO,
        "{node}: bulk samples refused: {bad} bad (size, tag or layout), {stale} stale (another "
        "run's, stamped ahead, beyond the rate bound); the last: {why}; further refusals are "
        "counted (bulk_<channel>_bad, _stale), evented at most once a second",
    )
    TM_ON_SHM = EventType(
        131,
        "tm_on_shm",
        Severity.ACTIVITY_LO,
        "{node}: telemetry takes iceoryx2 shared memory ({why}; transport.intra_host); zenoh "
        "still carries it, each snapshot taken once",
    )
    TM_FALLBACK = EventType(
        132,
        "tm_fallback",
        Severity.WARNING_LO,
        "{node}: telemetry falls back to zenoh: {why} ({fallbacks} fallback(s) so far; "
        "iceoryx2 is taken again when its frames come)",
    )
    GROUND_LOG_FAILED = EventType(
        133,
        "ground_log_failed",
        Severity.WARNING_LO,
        "the ground's log ({path}) cannot be written: {error}; what it cannot take is counted "
        "and lost from it (the archive keeps its own copy)",
    )
    GROUND_LOG_RESUMED = EventType(
        134,
        "ground_log_resumed",
        Severity.ACTIVITY_LO,
        "the ground's log ({path}) is written again: {lost} row(s) or event(s) lost from it so far",
    )
    TM_NEW_TERM = EventType(
        76,
        "tm_new_term",
        Severity.WARNING_HI,
        "{commander} commands from loop {loop} (term {old} -> {term}); following it",
    )

    ALL: ClassVar[tuple[EventType, ...]]
    """Every entry, in declaration order."""


EV.ALL = tuple(v for v in vars(EV).values() if isinstance(v, EventType))
# Keyed by identity: an EventType built elsewhere with the same fields is
# still not a catalogue entry.
_CATALOGUE = frozenset(id(e) for e in EV.ALL)


class Event(msgspec.Struct, frozen=True, gc=False):
    """One event record.

    ``node`` is the emitting node (``cn``, ``dn0``, ...), ``seq`` its event
    number (0, 1, 2, ... per node, gaps are drops), ``t_ns`` the loop time
    of the emitting node, ``severity`` a :class:`Severity` value, ``id`` the
    catalogue entry's name (``state_change``, ``cmd_rejected``, ...) and
    ``text`` the formatted message.
    """

    node: str
    seq: Annotated[int, Meta(ge=0)]
    t_ns: int
    severity: Annotated[int, Meta(ge=0, le=_MAX_SEVERITY)]
    id: str
    text: str

    @property
    def severity_name(self) -> str:
        """``"COMMAND"``, ``"WARNING_HI"``, ... (``str(severity)`` if out of range)."""
        if 0 <= self.severity < len(_SEVERITY_NAMES):
            return _SEVERITY_NAMES[self.severity]
        return str(self.severity)


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(Event)


def encode_event(e: Event) -> bytes:
    """The wire form of ``e`` (MessagePack map)."""
    return _encoder.encode(e)


def decode_event(b: bytes | bytearray | memoryview) -> Event:
    """Decode an event record; raises FrameFormatError on anything else."""
    try:
        return _decoder.decode(b)
    # DecodeError includes ValidationError; the others defensively: never leak them.
    except (msgspec.DecodeError, TypeError, ValueError, OverflowError) as exc:
        raise FrameFormatError(f"not an event record: {exc}") from exc


class StaleRecordError(FrameFormatError):
    """An authentic event record that is not fresh (:class:`EventReader`)."""


class EventReader:
    """Takes the event records of every node off the network, checking each
    node's tag (codecs/FORMAT.md §6.1, channel ``events_<node>``).

    ``keys``: the receiver's keys (None: it holds none). Records carry a tag
    when the mission authenticates (``security.auth``). :meth:`read` takes
    the sample's key expression (``{vehicle}/<node>/events``: whose key
    checks the tag), its payload and, when freshness is checked, the
    receiver's clock ``now_ns``, and returns ``(event, verified)``:
    ``verified`` True when the tag checked, False when this receiver holds
    no key for that node (the record is decoded from the bytes before the
    tag, unchecked: show it marked so), None when the mission does not
    authenticate. Raises
    :class:`~zplatform.errors.FrameFormatError` for anything that is not a
    record, :class:`~zplatform.core.auth.AuthError` (a FrameFormatError's
    sibling, both CodecErrors) for a bad tag, or a record that names
    another node than the key it came on. Channels are made once per node.

    **Freshness** (with ``now_ns`` and a ``max_age_ns``, the receiver's
    clock bound): a verified record is fresh when stamped within
    ``max_age_ns`` of ``now_ns`` (either side, or only ahead when bound to a
    known ``run``: then a record stamped long ago is of this run, a genuine
    one delivered late or a replay its number refuses; a record is published as it
    is emitted) and newer than every record of the same node taken before,
    in its number or in its time: a replay of any record taken is neither
    (both are at most the largest taken), while the node's next record is
    numbered up (the records of one loop share its time, and a node may
    stamp one with its loop's time after one with its clock's) and a
    restarted node's, numbered from 0 again, are later. Else
    :class:`StaleRecordError` (a FrameFormatError): a replay, or a stamp no
    clock of the mission can have made (which, taken, would lock every
    genuine record after it out). An unverified record
    (no key, or no authentication) is not checked: its stamp proves nothing.
    ``run``: the run the receiver is bound to (:class:`~zplatform.core.auth.Run`;
    None: none): a verified record of another run raises
    :class:`~zplatform.core.auth.RunError` (an AuthError: an earlier run's,
    replayed; its receiver counts it stale).
    Not thread-safe.
    """

    def __init__(
        self,
        mission: Mission,
        keys: KeySet | None,
        max_age_ns: int | None = None,
        *,
        run: Run | None = None,
    ) -> None:
        self._auth = mission.security.auth
        self._max_age = max_age_ns
        self._run = run
        # Per node with a key: the largest t_ns and the largest seq taken.
        self._newest: dict[str, tuple[int, int]] = {}
        # Made once, for the nodes whose event keys are held: a flood on
        # made-up keys costs no memory.
        self._channels: dict[str, Channel] = {}
        if keys is not None:
            for link in keys.links:
                if link.startswith("events-"):
                    node = link[len("events-") :]
                    self._channels[node] = keys.channel(f"events_{node}", run)

    def read(
        self,
        key_expr: str,
        payload: bytes | bytearray | memoryview,
        now_ns: int | None = None,
    ) -> tuple[Event, bool | None]:
        from .auth import TAG_LEN, AuthError

        if not self._auth:
            return decode_event(payload), None
        parts = str(key_expr).rsplit("/", 2)
        node = parts[-2] if len(parts) == 3 and parts[-1] == "events" else ""
        ch = self._channels.get(node)
        if ch is None:
            if len(payload) <= TAG_LEN:
                raise FrameFormatError(f"{len(payload)} bytes: too short for a tagged record")
            return decode_event(memoryview(payload)[:-TAG_LEN]), False
        e = decode_event(ch.open(payload))
        if e.node != node:
            raise AuthError(f"a record of {e.node!r} on {node!r}'s key")
        if now_ns is not None and self._max_age is not None:
            # Bound to a known run, an authentic record of it stamped long
            # ago is a genuine one delivered late (a starved receiver), or a
            # replay the numbers refuse: taken if newer. Without a run, its
            # age is what tells an earlier run's record.
            run = self._run
            late_ok = run is not None and run.known
            self._fresh(e, now_ns, self._max_age, late_ok=late_ok)
        return e, True

    def read_filled(self, node: str, payload: bytes | bytearray | memoryview) -> Event:
        """One record of ``node`` a gap fill brought (not off the network:
        :mod:`zplatform.ground.gapfill`): its tag checked with ``node``'s key
        as :meth:`read` checks it (RunError for another run's, on a bound
        reader; AuthError for a bad tag, none, no key held for ``node``, or
        a record naming another node; FrameFormatError for anything that is
        not a record), never its freshness: it is late by design, and its
        number is what its receiver checks (not one taken already). Reads
        nothing of :meth:`read`'s state, changes none."""
        from .auth import AuthError

        ch = self._channels.get(node)
        if ch is None:
            raise AuthError(f"no key for {node!r}'s events: a filled record cannot be checked")
        e = decode_event(ch.open(payload))
        if e.node != node:
            raise AuthError(f"a record of {e.node!r} on {node!r}'s key")
        return e

    def forged(self, key_expr: str, payload: bytes | bytearray | memoryview) -> bool:
        """Whether ``payload``, come on ``key_expr``, is refused by its tag
        alone: the mission authenticates, this reader holds the key of the
        key's node, and the header tag does not verify (or there is none);
        no MAC over the record's body (:meth:`read` computes it). Copies
        nothing, raises nothing; thread-safe (it reads only what
        ``__init__`` made), so a receiver checks it in zenoh's callback and
        queues no forged record (:class:`~zplatform.ground.link.GroundLink`).
        :meth:`read` checks the tag again: a record not forged here may
        still be refused there (not a record, another node's, stale)."""
        from .auth import AuthError, RunError

        if not self._auth:
            return False
        parts = str(key_expr).rsplit("/", 2)
        node = parts[-2] if len(parts) == 3 and parts[-1] == "events" else ""
        ch = self._channels.get(node)
        if ch is None:
            return False
        try:
            # The header tag alone (codecs/FORMAT.md §6.1): junk of any size
            # is refused here for microseconds; a genuine header on another
            # body, read() refuses by the MAC over the whole record.
            ch.open_header(payload)
        except RunError:  # genuine, of another run: read() refuses it as stale
            return False
        except AuthError:
            return True
        return False

    def _fresh(self, e: Event, now_ns: int, bound: int, *, late_ok: bool = False) -> None:
        if e.t_ns - now_ns > bound or (not late_ok and now_ns - e.t_ns > bound):
            raise StaleRecordError(
                f"{e.node}'s event #{e.seq} stamped {(e.t_ns - now_ns) / 1e9:+.3f} s from this "
                f"clock (bound {bound / 1e9:g} s): a replay, or a clock no node can have"
            )
        newest = self._newest.get(e.node)
        if newest is None:
            self._newest[e.node] = (e.t_ns, e.seq)
            return
        t, seq = newest
        if e.t_ns <= t and e.seq <= seq:
            raise StaleRecordError(
                f"{e.node}'s event #{e.seq} is not newer than #{seq} at its time: a replay"
            )
        self._newest[e.node] = (max(t, e.t_ns), max(seq, e.seq))


class EventLog:
    """A node's bounded queue of events awaiting publication.

    Not thread-safe: the loop thread emits and drains (the runtime drains
    after each loop). ``emit`` costs one :class:`Event` allocation and a list
    append; it is meant for things that happen (a state change, a rejected
    command), not for every loop.
    """

    __slots__ = ("_dropped", "_pending", "_seq", "capacity", "node")

    def __init__(self, node: str, capacity: int = 1024) -> None:
        if capacity < 1:
            raise ValueError(f"EventLog capacity must be at least 1, got {capacity}")
        self.node = node
        self.capacity = capacity
        self._pending: list[Event] = []
        self._seq = 0
        self._dropped = 0

    def emit(self, ev: EventType, t_ns: int, **args: Any) -> None:
        """Queue one event of catalogue entry ``ev`` at ``t_ns``; ``args`` fill its format.

        Never blocks. Raises :class:`~zplatform.errors.EventError` if ``ev``
        is not an entry of :class:`EV` (nothing is queued or numbered then);
        never raises for ``args`` (see :meth:`EventType.text`). When
        ``capacity`` events are already pending, the new event is not kept
        (nor formatted) and :attr:`dropped` grows by one (its ``seq`` is
        still used).
        """
        if id(ev) not in _CATALOGUE:
            raise EventError(
                f"{ev!r} is not an entry of the event catalogue (zplatform.core.events.EV)"
            )
        seq = self._seq
        self._seq = seq + 1
        if len(self._pending) >= self.capacity:
            self._dropped += 1
            return
        self._pending.append(
            Event(self.node, seq, t_ns, int(ev.severity), ev.name, ev.text(**args))
        )

    def drain(self) -> list[Event]:
        """Take every pending event, oldest first; the log is empty afterwards.

        Returns a new list (the caller owns it). Check :attr:`pending` first to
        skip the call in the common case of nothing to publish.
        """
        out = self._pending
        self._pending = []
        return out

    @property
    def pending(self) -> int:
        """Events emitted and not yet drained."""
        return len(self._pending)

    @property
    def dropped(self) -> int:
        """Events not kept because the log was full (since construction)."""
        return self._dropped

    @property
    def emitted(self) -> int:
        """Events emitted since construction, dropped ones included."""
        return self._seq
