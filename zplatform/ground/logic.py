"""The ground's sans-IO logic: telemetry in, every check, requests out.

:class:`GroundLogic` is to the ground what :class:`~zplatform.control.loop.ControlLogic`
is to the control node: it owns the ground's Data Vector (the CN layout, as
the last accepted snapshot showed it), every check a snapshot passes before
it touches that vector (size, tag, layout, freshness, the run followed, order
within it), the counters, the command requests and the reading of their
verdicts, and the command-script player. It never touches zenoh or a clock:
every input comes with its receive time on the caller's clock. Drivers: the
zenoh link (:mod:`zplatform.ground.link`) and the lockstep runner, so a
script means the same thing live and in ``sim``. A verdict is read only from
a later snapshot of the same run echoing the request's number; an event (tagged,
but lossy) only explains it. The checks in order, the run rules and the
verdict rules: docs/architecture.md#ground ("The ground's checks").

Nothing here blocks or raises for what arrives: bad input is counted. Not
thread-safe: one driver thread calls everything.
"""

from __future__ import annotations

import re
import struct
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

import msgspec

from ..config import STANDBY, Mission
from ..control.authority import ARM_WINDOW_NS, Signer, two_person_targets
from ..control.commands import protected_elements
from ..control.uplink import CheckedCommand, ScriptCommand, Uplink, validate_command
from ..core.auth import TAG_LEN, AuthError, Channel, KeySet, Run, RunError, channel, link_of
from ..core.codec import Frame, RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.events import EV, Event, EventLog, EventReader, EventType, StaleRecordError
from ..errors import CodecError, CommandError
from ..telemetry.records import REFUSALS, CommandOutcome, EventRecord, TelemetryCounters
from .script import ScriptPlayer, Signers

__all__ = [
    "FRESH_MARGIN_NS",
    "REASON_GRACE_NS",
    "EventGap",
    "Gap",
    "GroundLogic",
    "default_max_age_ns",
    "needs_arm",
]

FRESH_MARGIN_NS = 1_000_000_000
"""Added to the mission's clock bound to make the freshness bound: room for
the network, a loaded host and the hand-off to the ground's thread."""

REASON_GRACE_NS = 500_000_000
"""How long a verdict waits for the CN's event that gives its reason."""

_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_RENEWAL = "lock renewal"
"""The source of the LOCKs :class:`GroundLogic` sends to keep its lease."""
_CMD_EVENTS = 64  # recent cmd_accepted/cmd_rejected events kept for matching
_GAPS_KEPT = 256
_TELL_NS = 1_000_000_000  # events_missed: at most one event this often
_TELL_PARTS = 8  # gaps named in one events_missed event (the rest counted)


class Gap(NamedTuple):
    """Telemetry loops ``first``..``last`` (every ``telemetry_divisor``-th)
    of CN run ``epoch`` that never arrived, between two accepted snapshots."""

    epoch: int
    first: int
    last: int


class EventGap(NamedTuple):
    """Events ``first``..``last`` (their numbers) of ``node`` that never
    arrived, between two verified records of run ``run`` (the run word of
    their tags); ``first_loop``..``last_loop``: the control node's loops they
    were filed under in its recorder, at most (estimated from the stamps of
    the records either side and the last snapshot; 0, 0 when not known)."""

    node: str
    run: int
    first: int
    last: int
    first_loop: int
    last_loop: int

    @property
    def which(self) -> str:
        """``#5..#7``, or ``#5`` for one."""
        return f"#{self.first}" if self.first == self.last else f"#{self.first}..#{self.last}"


def default_max_age_ns(mission: Mission) -> int:
    """The freshness bound: ``clock.offset_bound_ms`` plus :data:`FRESH_MARGIN_NS`."""
    return int(mission.clock.offset_bound_ms * 1_000_000) + FRESH_MARGIN_NS


def needs_arm(mission: Mission, command: str, element: str | None = None) -> str | None:
    """Why ``command`` (with ``element`` for WRITE, the parameter for
    PRM_SET) must go as ARM n, then the command n+1, or None when it need
    not: the command is hazardous (``commands.hazardous``), the WRITE sets a
    protected element (``commands.protected``,
    :func:`zplatform.control.commands.protected_elements`), or the PRM_SET a
    hazardous parameter (``params[i].hazardous``)."""
    cmd = command.upper()
    if cmd in mission.commands.hazardous:
        return f"{cmd} is hazardous (commands.hazardous)"
    if cmd == "WRITE" and element is not None and element in protected_elements(mission):
        return f"{element} is protected (commands.protected)"
    if cmd == "PRM_SET" and any(p.name == element and p.hazardous for p in mission.params):
        return f"parameter {element} is hazardous (params: hazardous)"
    return None


def _pattern(ev: EventType) -> re.Pattern[str]:
    """A regular expression that reads an event text back into its fields."""
    parts = re.split(r"\{(\w+)[^}]*\}", ev.format)
    rx = "".join(f"(?P<{p}>.*?)" if i % 2 else re.escape(p) for i, p in enumerate(parts))
    return re.compile(f"^{rx}$", re.S)


_ACCEPTED = _pattern(EV.CMD_ACCEPTED)
_REJECTED = _pattern(EV.CMD_REJECTED)
CONTROL_NODES = ("cn", STANDBY)


class _CmdEvent:
    """A ``cmd_accepted``/``cmd_rejected`` event of the CN, read back."""

    __slots__ = ("detail", "name", "seq", "status", "t_ns")

    def __init__(self, name: str, seq: int, status: str, detail: str, t_ns: int) -> None:
        self.name, self.seq, self.status, self.detail, self.t_ns = name, seq, status, detail, t_ns


def _read_cmd_event(e: Event) -> _CmdEvent | None:
    if e.node not in CONTROL_NODES:  # either control node of a redundant mission
        return None
    if e.id == EV.CMD_ACCEPTED.name:
        m = _ACCEPTED.match(e.text)
        status = "ACCEPTED"
    elif e.id == EV.CMD_REJECTED.name:
        m = _REJECTED.match(e.text)
        status = m.group("status") if m else ""
    else:
        return None
    if m is None or not m.group("seq").isdigit():
        return None
    detail = m.group("detail").strip()
    if status == "ACCEPTED" and detail.startswith("(") and detail.endswith(")"):
        detail = detail[1:-1]  # " (led_a_cmd = True)" -> "led_a_cmd = True"
    return _CmdEvent(m.group("name"), int(m.group("seq")), status, detail, e.t_ns)


class _Tally(msgspec.Struct):
    """The running counts behind :class:`~.records.TelemetryCounters`."""

    refused: dict[str, int]
    received: int = 0
    term_changes: int = 0
    gaps: int = 0
    bad: int = 0
    epoch_changes: int = 0
    first_seq: int = -1
    bad_events: int = 0
    stale_events: int = 0
    events_missed: int = 0
    iox: int = 0
    duplicates: int = 0
    path_fallbacks: int = 0
    unchecked: int = 0


class _Plan:
    """One operator command: its steps (ARM first when armed), its outcomes."""

    __slots__ = (
        "approval",
        "open",
        "operator",
        "outcomes",
        "sent",
        "source",
        "steps",
        "ticket",
        "uplink",
    )

    def __init__(
        self,
        ticket: int,
        steps: list[tuple[str, int, float]],
        source: str,
        uplink: Uplink | None = None,
        operator: str = "",
    ) -> None:
        self.ticket = ticket
        self.steps = steps
        self.source = source
        self.uplink = uplink  # who signs its requests (None: the ground's own uplink)
        self.operator = operator  # ``operator@station`` they name
        self.approval = False  # its command waits for its ARM's approval (two-person)
        self.sent = 0  # steps sent so far
        self.open = True  # more steps may still be sent
        self.outcomes: list[CommandOutcome] = []


class _Request:
    """One request on the wire, from sending to its released outcome."""

    __slots__ = (
        "cmd",
        "epoch",
        "holder",
        "index",
        "loop",
        "plan",
        "reason",
        "reason_from",
        "rejects0",
        "rx",
        "sent_loop",
        "seq",
        "shown_seq",
        "state",
        "status",
        "tries",
        "value",
    )

    def __init__(
        self, plan: _Plan, step: tuple[str, int, float], seq: int, epoch: int, loop: int
    ) -> None:
        self.plan = plan
        self.cmd, self.index, self.value = step
        self.seq = seq
        self.epoch = epoch
        self.sent_loop = loop  # the loop seen when sent: a verdict must come from a later one
        self.rejects0 = 0
        self.tries = 1
        self.status = ""
        self.loop = 0
        self.rx = 0
        self.state = ""
        self.shown_seq = 0
        self.holder = ""  # REJECTED_NOT_HOLDER: who held the lock at the verdict
        self.reason = ""
        self.reason_from = ""


class GroundLogic:
    """The ground's logic (module doc). Construction resolves the script
    against the mission (CommandError naming ``file:line``).

    ``keys``: the ground's keys (:func:`zplatform.core.auth.load_keys`: a ground
    node's or a commanding tool's hold the downlink, the uplink and every
    node's event key; a read-only tool's no uplink, so it frames no
    request); None: the mission does not authenticate. Only events whose
    tag verified (or any, when the mission does not authenticate) explain
    a verdict. ``node``: the name the ground's own events carry. ``max_age_ns``: the
    freshness bound (default :func:`default_max_age_ns`). ``script``: a
    command script to play (:class:`~.script.ScriptPlayer`). ``run``: the
    run the ground's channels are bound to (:class:`~zplatform.core.auth.Run`,
    learned by its driver from the commander's answer to a run hello,
    :class:`zplatform.runtime.clocksync.RunAsker`): telemetry, events and
    requests of another run are refused (counted as stale), and nothing is
    taken while it is unknown (:attr:`waiting_for_run`); None: bound to none
    (every run's authentic frame is taken, ordered by the run it names).
    ``signer``: the operator and station its requests name and are signed
    by (a mission with ``ground:``, :class:`~zplatform.control.uplink.Uplink`);
    every outcome then names them (:attr:`CommandOutcome.operator`).
    ``signers``: what signs a script line that names its sender (``as
    alice@pad: ...``; :class:`~.script.ScriptPlayer`); :meth:`submit`'s
    ``signer`` sends one command so.
    ``renew_lock``: with a signer, in a mission with command authority, keep
    the command lock while this station's operator holds it (docs/security.md
    #stations-and-operators): when a snapshot shows less than half the lease
    left and nothing waits for a verdict, a LOCK renews it (counted in
    :attr:`lock_renewals`; not while an ARM of this station may still be
    followed by its command, which a LOCK between would void). It stops by
    itself when the operator releases or hands the lock over, or when the
    driver stops calling (the station shut down: the lease then runs out).
    """

    def __init__(
        self,
        mission: Mission,
        *,
        keys: KeySet | None,
        node: str = "gn",
        max_age_ns: int | None = None,
        script: Sequence[ScriptCommand] = (),
        resend_loops: int = 100,
        tries: int = 3,
        reason_grace_ns: int = REASON_GRACE_NS,
        run: Run | None = None,
        signer: Signer | None = None,
        renew_lock: bool = True,
        signers: Signers | None = None,
    ) -> None:
        self.mission = mission
        self.run = run
        self._keys = keys
        self.operator = f"{signer.operator}@{signer.station}" if signer is not None else ""
        """``operator@station`` this ground's requests name ("" without a signer)."""
        self.node = node
        self.layout = Layout.for_node(mission, "cn")
        self.dv = DataVector(self.layout)
        """The last accepted snapshot (all zero before the first)."""
        self._codec = RegionCodec(self.dv)
        self._open = channel(keys, "telemetry", run)
        self._max_len = self._codec.max_frame_len + (TAG_LEN if self._open is not None else 0)
        self._epoch_at = self.layout.element("cn_epoch").offset
        # A redundant mission's term (docs/architecture.md#failover): the
        # ground follows the newest, whichever control node commands in it.
        self._term_at = (
            self.layout.element("cn_term").offset if mission.standby is not None else None
        )
        self._term = 0
        self.max_age_ns = default_max_age_ns(mission) if max_age_ns is None else max_age_ns
        self._events_in = EventReader(mission, keys, self.max_age_ns, run=run)
        self._period = mission.period_ns
        self._div = mission.telemetry_divisor
        self.events = EventLog(node)
        """The ground's own events (joined, restarted, refused, script done);
        the driver drains them."""
        # telemetry state
        self._epoch = -1
        self._last_seq = -1
        self._last_rx = 0
        self._last_t = 0
        self._n = _Tally(refused=dict.fromkeys(REFUSALS, 0))
        self._evented: set[str] = set()
        self.gaps: deque[Gap] = deque(maxlen=_GAPS_KEPT)
        """Runs of missing telemetry loops, oldest first, for a gap filler to
        take (the oldest are forgotten past a bound: nobody is taking them)."""
        # Event numbers (on_event_bytes): per node, the run, number and stamp
        # of the last verified record; the gaps open for a filler (each with
        # the numbers filled so far), told in one events_missed a second.
        self._ev_last: dict[str, tuple[int, int, int]] = {}
        self._ev_open: dict[EventGap, set[int]] = {}
        self._ev_tell: list[tuple[EventGap, str]] = []
        self._ev_told = -(1 << 63)
        self.event_gaps: deque[EventGap] = deque()
        """Gaps in the numbers of the events of :attr:`fill_events_of`, to be
        filled (:class:`~zplatform.ground.gapfill.GapFill` takes them);
        at most ``256`` open at once (more are told not filled)."""
        self.fill_events_of: frozenset[str] = frozenset()
        """The nodes whose missing events a gap filler asks of the control
        node's recorder (its driver sets it; none: every gap is only told)."""
        self.last_refusal = ""
        """The detail of the latest refused or bad snapshot ("" if none)."""
        self.waited = 0
        """Authentic snapshots and event records let go while
        :attr:`waiting_for_run` (not counted as refused: not replays, merely
        before the run was learned)."""
        h = self.dv.handle
        self._h_loop = h("cn_loop")
        self._h_state = h("cn_state")
        self._h_seq = h("cn_cmd_seq")  # the last request that consumed a number
        self._h_status = h("cn_cmd_status")
        self._h_rseq = h("cn_cmd_reject_seq")  # the last refused without consuming one
        self._h_rstatus = h("cn_cmd_reject_status")
        self._h_rejects = h("cn_cmd_rejects")
        # commands
        self._uplink = (
            Uplink(mission, keys, run, signer)
            if mission.has_ground and (keys is None or keys.has(link_of("gn_to_cn")))
            else None
        )
        self._plans: deque[_Plan] = deque()
        self._tickets: dict[int, _Plan] = {}
        self._next_ticket = 1
        self._inflight: _Request | None = None
        self._deciding: deque[_Request] = deque()
        self._last_sent = 0  # the last number sent in the run followed
        self._resend = resend_loops
        self._tries = tries
        self._grace = reason_grace_ns
        self._cmd_events: deque[_CmdEvent] = deque(maxlen=_CMD_EVENTS)
        self._out: list[bytes] = []
        self.outcomes: list[CommandOutcome] = []
        """Every released outcome, in verdict order."""
        self._uplinks: dict[str, Uplink] = {}  # per operator@station a script line names
        self.player = ScriptPlayer(mission, script, signers) if script else None
        # The command lock's lease (renew_lock): whose it is, when it ends.
        g = mission.ground
        self._renew: tuple[int, int, int] | None = None
        if renew_lock and signer is not None and g is not None and mission.authority:
            ops = [o.name for o in g.operators]
            sts = [s.name for s in g.stations]
            if signer.operator in ops and signer.station in sts:  # else Uplink refused it
                self._renew = (
                    ops.index(signer.operator) + 1,
                    sts.index(signer.station) + 1,
                    int(g.lease_s * 1_000_000_000),
                )
                self._h_holder = h("cn_lock_holder")
                self._h_lstation = h("cn_lock_station")
                self._h_until = h("cn_lock_until_ns")
        self._lock_h = (h("cn_lock_holder"), h("cn_lock_station")) if mission.authority else None
        # The two-person rule (ground.two_person): an armed command of these
        # waits for its ARM's approval before it goes (GroundLogic.submit).
        two_cmds, two_names = two_person_targets(mission)
        self._two_cmds = two_cmds
        self._two_elems = frozenset(
            self.layout.element(n).index for n in two_names if n in self.layout.elements
        )
        self._h_approvals = h("cn_arm_approvals") if mission.authority else None
        self._arm_until = 0  # the snapshot time up to which an ARM of ours may be followed
        self.lock_renewals = 0
        """LOCK renewals sent (``renew_lock``)."""
        self.lock_renewals_refused = 0
        """Renewals whose verdict was not ACCEPTED (the lock had moved on)."""

    # -- telemetry -----------------------------------------------------------
    @property
    def joined(self) -> bool:
        """Whether a snapshot was accepted (a CN run is followed)."""
        return self._epoch >= 0

    @property
    def waiting_for_run(self) -> bool:
        """Whether the ground is bound to a run it has not learned yet: then
        it takes nothing (module doc) and shows "waiting for the vehicle's run"."""
        run = self.run
        return run is not None and not run.known and self._open is not None

    @property
    def received(self) -> int:
        """Snapshots accepted so far (cheap; :attr:`counters` has them all)."""
        return self._n.received

    @property
    def max_frame_len(self) -> int:
        """The longest telemetry frame that can be valid (bytes, tag included)."""
        return self._max_len

    def refused(
        self,
        size: int,
        bad: int,
        stale: int,
        aged: int,
        rx_ns: int,
        ahead: int = 0,
        *,
        unchecked: int = 0,
    ) -> None:
        """Count snapshots the driver's intake refused as they arrived (module
        doc): ``size`` too long and ``bad`` with a bad tag count as bad;
        ``stale`` authentic ones that were not fresh: ``ahead`` of them
        stamped beyond the freshness bound after they arrived (refused
        ``ahead``), ``aged`` beyond it before (``stale``), the rest replays
        not newer than the newest let through (``not_newer``); ``unchecked``
        of them all were dropped after their header, their body's tag not
        checked for want of the body-MAC budget (``unchecked``). The first
        of each kind is an event, as for :meth:`on_telemetry`'s own."""
        n = self._n
        if unchecked:
            n.unchecked += unchecked
            self._note(
                "unchecked",
                f"{unchecked} snapshot(s) dropped after their header, unchecked: the "
                "body-MAC budget was spent (codecs/FORMAT.md)",
                rx_ns,
            )
        if ahead:
            n.refused["ahead"] += ahead
            stale -= ahead
            self._note(
                "ahead",
                f"{ahead} snapshot(s) stamped more than {self.max_age_ns / 1e9:g} s after they "
                "arrived",
                rx_ns,
            )
        if size:
            n.bad += size
            self._note("size", f"{size} snapshot(s) longer than any telemetry frame", rx_ns)
        if bad:
            n.bad += bad
            self._note("tag", f"{bad} snapshot(s) with a bad authentication tag", rx_ns)
        if aged:
            n.refused["stale"] += aged
            self._note(
                "stale",
                f"{aged} replayed snapshot(s) of another run than this ground's, or stamped "
                f"more than {self.max_age_ns / 1e9:g} s before they arrived",
                rx_ns,
            )
        if stale - aged:
            n.refused["not_newer"] += stale - aged
            self._note(
                "not_newer", f"{stale - aged} replayed snapshot(s), not newer than one taken", rx_ns
            )

    def count_paths(self, iox: int, duplicates: int, fallbacks: int) -> None:
        """The telemetry's paths as the driver counted them (totals: a ground
        on the CN's host, zplatform.runtime.tmiox): snapshots its intake
        admitted over iceoryx2, copies dropped as duplicates (the other
        path's copy of one taken: not refusals), fallbacks to zenoh."""
        n = self._n
        n.iox, n.duplicates, n.path_fallbacks = iox, duplicates, fallbacks

    def refused_events(self, n: int) -> None:
        """Count ``n`` event records the driver refused as they arrived: for
        their size, or their tag (:meth:`forged_event`)."""
        self._n.bad_events += n

    @property
    def counters(self) -> TelemetryCounters:
        """A snapshot of every counter (a new object per call)."""
        n = msgspec.structs.asdict(self._n)
        n["refused"] = dict(self._n.refused)
        return TelemetryCounters(
            **n, epoch=max(self._epoch, 0), last_seq=self._last_seq, term=self._term
        )

    def on_telemetry(
        self,
        payload: bytes | bytearray | memoryview,
        rx_ns: int,
        *,
        can_send: bool = True,
        authentic: bool = False,
    ) -> bool:
        """Check one telemetry frame received at ``rx_ns`` (module doc);
        returns whether it was accepted into :attr:`dv`. On acceptance,
        verdicts are read, the script player runs, and requests may be
        queued for :meth:`take_requests`. ``can_send``: the CN listens for
        requests now (else they wait). Never raises for the payload.

        ``authentic``: the caller checked this very payload's tag with the
        ground's telemetry key already (the link's intake,
        :class:`~zplatform.control.intake.TelemetryIntake`, as it arrived), so the
        tag is only stripped (:meth:`~zplatform.core.auth.Channel.strip`), not
        computed again: once per snapshot on the ground, as on a device
        node (:meth:`zplatform.control.loop.DeviceLogic.trigger`). Without it (the
        default: the lockstep runner, a replay) the tag is checked here."""
        if len(payload) > self._max_len:
            return self._reject_bad(
                "size",
                f"{len(payload)} bytes, longer than any telemetry frame ({self._max_len})",
                rx_ns,
            )
        ch = self._open
        try:
            body = payload if ch is None else ch.strip(payload) if authentic else ch.open(payload)
            frame = self._codec.check(body)
        except RunError as exc:  # another run's genuine frame: a replay, or a new run
            if self.waiting_for_run:  # not a replay: the run is not known yet
                self.waited += 1
                self.last_refusal = f"waiting for the vehicle's run: {exc}"
                return False
            return self._refuse(
                "stale", f"{exc}: an earlier run's snapshot, or the control node restarted", rx_ns
            )
        except AuthError as exc:
            return self._reject_bad("tag", str(exc), rx_ns)
        except CodecError as exc:
            return self._reject_bad("format", str(exc), rx_ns)
        epoch = _U64.unpack_from(frame.data, self._epoch_at)[0]
        seq, t = frame.seq, frame.t_ns
        age = rx_ns - t
        if age > self.max_age_ns:
            return self._refuse(
                "stale",
                f"snapshot of loop {seq} stamped {age / 1e9:.3f} s before this ground's clock "
                f"(bound {self.max_age_ns / 1e9:g} s): a replay of an earlier run, or this "
                "host's clock is ahead of the vehicle's",
                rx_ns,
            )
        if -age > self.max_age_ns:
            return self._refuse(
                "ahead",
                f"snapshot of loop {seq} stamped {-age / 1e9:.3f} s after this ground's clock "
                f"(bound {self.max_age_ns / 1e9:g} s): this host's clock is behind the "
                "vehicle's",
                rx_ns,
            )
        if epoch != self._epoch:
            if self._epoch >= 0 and epoch < self._epoch and rx_ns - self._last_t <= self.max_age_ns:
                return self._refuse(
                    "old_epoch",
                    f"snapshot of control node run {epoch}, older than run {self._epoch}, "
                    "which this ground follows",
                    rx_ns,
                )
            self._follow(epoch, seq, rx_ns)
            if self._term_at is not None:
                self._term = _U32.unpack_from(frame.data, self._term_at)[0]
        elif (
            self._term_at is not None
            and (term := _U32.unpack_from(frame.data, self._term_at)[0]) != self._term
        ):
            if term < self._term:
                return self._refuse(
                    "old_term",
                    f"snapshot of loop {seq} in term {term}: term {self._term} commands now "
                    "(a control node that stood down, or was replaced)",
                    rx_ns,
                )
            self._new_term(term, frame, rx_ns)
        elif seq <= self._last_seq:
            return self._refuse(
                "not_newer",
                f"snapshot of loop {seq} is not newer than loop {self._last_seq}",
                rx_ns,
            )
        else:
            allowed = 2 * (max(rx_ns - self._last_rx, 0) // self._period + 1) + 100
            if seq - self._last_seq > allowed:
                return self._refuse(
                    "jump",
                    f"snapshot of loop {seq} jumps {seq - self._last_seq} loops past loop "
                    f"{self._last_seq} in {(rx_ns - self._last_rx) / 1e6:.1f} ms",
                    rx_ns,
                )
        self._codec.write(frame)
        if self._last_seq >= 0 and seq > self._last_seq + self._div:
            self._n.gaps += (seq - self._last_seq) // self._div - 1
            self.gaps.append(Gap(epoch, self._last_seq + self._div, seq - self._div))
        if self._n.first_seq < 0:
            self._n.first_seq = seq
        self._n.received += 1
        self._last_seq = seq
        self._last_rx = rx_ns
        self._last_t = t
        self._on_snapshot(rx_ns, can_send)
        return True

    def _reject_bad(self, kind: str, detail: str, rx_ns: int) -> bool:
        self._n.bad += 1
        self._note(kind, detail, rx_ns)
        return False

    def _refuse(self, reason: str, detail: str, rx_ns: int) -> bool:
        self._n.refused[reason] += 1
        self._note(reason, detail, rx_ns)
        return False

    def _note(self, kind: str, detail: str, rx_ns: int) -> None:
        self.last_refusal = detail
        if kind not in self._evented:  # the first of each kind; the rest are counted
            self._evented.add(kind)
            self.events.emit(EV.TM_REFUSED, rx_ns, reason=kind, detail=detail)

    def _new_term(self, term: int, frame: Frame, rx_ns: int) -> None:
        """A newer term commands (a takeover): follow it from this snapshot,
        whatever the loop order of the old one (its request numbers, run and
        verdicts carry on; a request waiting for a verdict is sent again to
        the new commander as usual, :meth:`command`)."""
        old, self._term = self._term, term
        self._n.term_changes += 1
        who = self._codec_commander(frame)
        self.events.emit(EV.TM_NEW_TERM, rx_ns, commander=who, loop=frame.seq, old=old, term=term)
        self._last_seq = min(self._last_seq, frame.seq - self._div)

    def _codec_commander(self, frame: Frame) -> str:
        at = self.layout.element("cn_commander").offset
        i = frame.data[at]
        nodes = self.mission.control_nodes
        return nodes[i] if i < len(nodes) else f"control node {i}"

    def _follow(self, epoch: int, seq: int, rx_ns: int) -> None:
        """Follow CN run ``epoch`` from loop ``seq``: the first, or a restart."""
        old = self._epoch
        self._epoch = epoch
        self._last_seq = -1
        self._last_sent = 0
        if old < 0:
            self.events.emit(EV.TM_JOINED, rx_ns, epoch=epoch, loop=seq)
            return
        self._n.epoch_changes += 1
        self.events.emit(EV.CN_RESTARTED, rx_ns, old=old, new=epoch, loop=seq)
        r = self._inflight
        if r is not None:  # its CN is gone: nobody will answer it
            self._inflight = None
            self._decide(
                r,
                "NO_VERDICT",
                seq,
                rx_ns,
                f"the control node restarted (run {old} -> {epoch}) before its verdict "
                "showed; it may or may not have taken effect in the old run",
            )

    # -- commands ------------------------------------------------------------
    @property
    def idle(self) -> bool:
        """No request waits for its verdict and none is queued."""
        return self._inflight is None and not self._plans

    def command(
        self,
        command: str,
        element: str | None = None,
        value: str | None = None,
        *,
        now_ns: int,
        armed: bool = False,
        source: str = "",
        can_send: bool = True,
    ) -> int:
        """Check one operator command (:func:`~zplatform.control.uplink.validate_command`)
        and queue it (:meth:`submit`); returns its ticket (:meth:`result`).
        Raises CommandError for an unknown command, element or value
        (nothing is queued) or a mission without a ground node."""
        self._need_uplink()
        checked = validate_command(self.mission, command, element, value, source or None)
        return self._queue(checked, now_ns, armed, source, can_send)

    def submit(
        self,
        checked: CheckedCommand,
        *,
        now_ns: int,
        armed: bool = False,
        source: str = "",
        can_send: bool = True,
        signer: Signer | None = None,
    ) -> int:
        """Queue one operator command that
        :func:`~zplatform.control.uplink.validate_command` checked already (it is
        not checked again); returns its ticket (:meth:`result`).

        ``armed``: ARM n first, then the command n+1 once the ARM is
        accepted (one ticket). It goes out at once when the ground follows a
        run, nothing else waits for a verdict and ``can_send``; otherwise
        with a later snapshot (:meth:`take_requests`). Raises CommandError
        for a mission without a ground node, or a ground without the
        uplink's key. ``signer``: another operator and station its requests
        name and are signed by (a script line's ``as``; None: the ground's own).
        """
        self._need_uplink()
        return self._queue(checked, now_ns, armed, source, can_send, signer)

    def _need_uplink(self) -> None:
        if self._uplink is None:
            raise CommandError(
                f"mission {self.mission.mission!r} has no ground node 'gn'"
                if not self.mission.has_ground
                else "this ground holds no uplink key (a read-only tool's keys): commands "
                "need the ground's key file (gn.keys from `zplatform keygen`)"
            )

    def _queue(
        self,
        checked: CheckedCommand,
        now_ns: int,
        armed: bool,
        source: str,
        can_send: bool,
        signer: Signer | None = None,
    ) -> int:
        step = (checked.command, checked.element, checked.value)
        steps = [("ARM", 0, 0.0), step] if armed else [step]
        ticket = self._next_ticket
        self._next_ticket += 1
        uplink, operator = None, self.operator
        if signer is not None:
            operator = f"{signer.operator}@{signer.station}"
            uplink = self._uplinks.get(operator)
            if uplink is None:  # its own request vector, signed as them, in the ground's run
                uplink = Uplink(self.mission, self._keys, self.run, signer)
                self._uplinks[operator] = uplink
        plan = _Plan(ticket, steps, source, uplink, operator)
        plan.approval = armed and self._h_approvals is not None and self._two_person(checked)
        self._plans.append(plan)
        self._tickets[ticket] = plan
        self._dispatch(now_ns, can_send)
        return ticket

    def result(self, ticket: int) -> list[CommandOutcome] | None:
        """The outcomes of ``ticket`` once all are released (an armed command
        whose ARM was refused has only the ARM's), else None."""
        plan = self._tickets.get(ticket)
        if plan is None or not self._plan_done(plan):
            return None
        return list(plan.outcomes)

    def steps(self, ticket: int) -> list[str]:
        """The commands ``ticket`` sends, in order (``["ARM", "LAUNCH"]``)."""
        return [s[0] for s in self._tickets[ticket].steps]

    @staticmethod
    def _plan_done(plan: _Plan) -> bool:
        return not plan.open and len(plan.outcomes) == plan.sent

    def take_requests(self) -> Sequence[bytes]:
        """The request frames to publish now (and forget), oldest first.
        Allocates nothing when there are none (the common case)."""
        if not self._out:
            return ()
        out, self._out = self._out, []
        return out

    def _two_person(self, checked: CheckedCommand) -> bool:
        """Whether ``checked`` needs its ARM approved (``ground.two_person``)."""
        if checked.command in self._two_cmds:
            return True
        return checked.command in ("WRITE", "PRM_SET") and checked.element in self._two_elems

    @property
    def awaiting_approval(self) -> int | None:
        """The number of this ground's accepted ARM whose two-person command
        waits for a second operator's APPROVE (None: nothing waits)."""
        plan = self._plans[0] if self._plans else None
        if plan is None or not plan.approval or plan.sent != 1 or not plan.outcomes:
            return None
        return plan.outcomes[0].seq

    def partial(self, ticket: int) -> list[CommandOutcome]:
        """The outcomes of ``ticket`` released so far (the ARM's, while its
        command waits)."""
        plan = self._tickets.get(ticket)
        return list(plan.outcomes) if plan is not None else []

    def _dispatch(self, rx_ns: int, can_send: bool) -> None:
        """Send the next queued step when nothing waits for a verdict (nor, for
        a two-person command, for its ARM's approval: until a snapshot shows
        one, or the ARM's window has passed, when the CN will refuse it)."""
        if self._inflight is not None or not self._plans or not can_send or self._epoch < 0:
            return
        plan = self._plans[0]
        if (
            plan.approval
            and plan.sent == 1
            and self._h_approvals is not None
            and not self._h_approvals.get()
            and self._last_t < self._arm_until
        ):
            return
        step = plan.steps[plan.sent]
        plan.sent += 1
        if plan.sent == len(plan.steps):
            self._plans.popleft()
            plan.open = False
        # Above every number the CN showed, refused ones too: its intake
        # admits each number once, so a number another station's refused
        # request used (cn_cmd_reject_seq) would come back REJECTED_REPLAY.
        seq = max(int(self._h_seq.get()), int(self._h_rseq.get()), self._last_sent) + 1
        r = _Request(plan, step, seq, self._epoch, int(self._h_loop.get()))
        r.rejects0 = int(self._h_rejects.get())
        self._last_sent = seq
        self._inflight = r
        self._send(r, rx_ns)

    def _send(self, r: _Request, rx_ns: int) -> None:
        assert self._uplink is not None
        # APPROVE carries its ARM's number in the value (validate_command).
        ref = int(r.value) if r.cmd == "APPROVE" else 0
        uplink = r.plan.uplink if r.plan.uplink is not None else self._uplink
        frame = uplink.frame(r.cmd, r.seq, r.index, r.value, rx_ns, r.epoch, ref)
        self._out.append(bytes(frame))

    def _on_snapshot(self, rx_ns: int, can_send: bool) -> None:
        """After an accepted snapshot: verdicts, reasons due, the player, sends."""
        r = self._inflight
        if r is not None and r.epoch == self._epoch:
            loop = int(self._h_loop.get())
            if loop > r.sent_loop:
                if self._h_seq.get() == r.seq and self._h_status.get() != 0:
                    self._inflight = None
                    self._decide(r, self._h_status.spec.name_of(self._h_status.get()), loop, rx_ns)
                elif self._h_rseq.get() == r.seq and self._h_rejects.get() != r.rejects0:
                    self._inflight = None
                    status = self._h_rstatus.spec.name_of(self._h_rstatus.get())
                    self._decide(r, status, loop, rx_ns)
                elif loop - r.sent_loop >= self._resend:
                    if r.tries >= self._tries:
                        self._inflight = None
                        self._decide(
                            r,
                            "NO_VERDICT",
                            loop,
                            rx_ns,
                            f"no verdict after {r.tries} send(s) over {loop - r.sent_loop} loops",
                        )
                    elif can_send:  # a lost frame: again, same number (a duplicate is a replay)
                        r.tries += 1
                        r.sent_loop = loop
                        self._send(r, rx_ns)
        self._release(rx_ns)
        if self.player is not None:
            self.player.step(self, int(self._h_loop.get()), rx_ns, can_send)
        if self._renew is not None:
            self._renew_lock(rx_ns, can_send)
        self._dispatch(rx_ns, can_send)

    def _renew_lock(self, rx_ns: int, can_send: bool) -> None:
        """Queue a LOCK when this station's operator holds the lock and less
        than half the lease is left (class doc): never while another request
        is queued or waits for its verdict, nor while an ARM of ours is open."""
        assert self._renew is not None
        op, st, lease = self._renew
        if not can_send or not self.idle or self._last_t < self._arm_until:
            return
        if self._h_holder.get() != op or self._h_lstation.get() not in (0, st):
            return
        if int(self._h_until.get()) - self._last_t >= lease // 2:
            return
        self.lock_renewals += 1
        self._queue(CheckedCommand("LOCK", 0, 0.0), rx_ns, False, _RENEWAL, can_send)

    def _decide(
        self, r: _Request, status: str, loop: int, rx_ns: int, ground_reason: str = ""
    ) -> None:
        r.status, r.loop, r.rx = status, loop, rx_ns
        r.state = self._h_state.spec.name_of(self._h_state.get())
        if self._lock_h is not None and status == "REJECTED_NOT_HOLDER":
            # Who holds the lock, as the verdict's snapshot shows it: the
            # reason when the CN's event (evented at most once a second) is not there.
            holder, station = self._lock_h
            who = holder.spec.name_of(holder.get())
            where = station.spec.name_of(station.get())
            r.holder = "" if who == "NONE" else who if where == "NONE" else f"{who}@{where}"
        if status == "ACCEPTED":
            # An accepted ARM may be followed by its command within the window
            # (no renewal in between); any later accepted request closes it.
            self._arm_until = self._last_t + ARM_WINDOW_NS if r.cmd == "ARM" else 0
        elif r.plan.source == _RENEWAL:
            self.lock_renewals_refused += 1
        r.shown_seq = int(self._h_seq.get())
        if ground_reason:
            r.reason, r.reason_from = ground_reason, "ground"
        else:
            self._match(r)
        plan = r.plan
        if status != "ACCEPTED" and plan.open:
            # An ARM not accepted: the armed command is not sent.
            plan.open = False
            self._plans.remove(plan)
        self._deciding.append(r)

    def _match(self, r: _Request) -> None:
        for e in self._cmd_events:
            if (
                e.seq == r.seq
                and e.name == r.cmd
                and e.status == r.status
                and e.t_ns >= r.epoch  # this run's: its loops are after its start
            ):
                r.reason, r.reason_from = e.detail, "cn"
                return

    def _release(self, now_ns: int, *, all_: bool = False) -> None:
        """Release decided outcomes, in verdict order, once their reason is
        known or their grace has passed (then derived); ``all_``: all now."""
        released = False
        while self._deciding:
            r = self._deciding[0]
            if not r.reason_from:
                if not all_ and now_ns - r.rx < self._grace:
                    break
                r.reason, r.reason_from = _derived(r)
            self._deciding.popleft()
            o = CommandOutcome(
                r.cmd,
                r.seq,
                r.status,
                r.loop,
                (r.loop - 1) * self._period,
                r.plan.source,
                r.reason,
                r.reason_from,  # type: ignore[arg-type]
                r.plan.operator,
            )
            r.plan.outcomes.append(o)
            if r.plan.source == _RENEWAL:
                # Nobody waits for a renewal's ticket: forget it (a long
                # session renews every half lease).
                self._tickets.pop(r.plan.ticket, None)
            else:
                self.outcomes.append(o)
            released = True
        player = self.player
        if released and player is not None and player.done(self):
            results = player.results(self)
            self.events.emit(
                EV.SCRIPT_DONE,
                now_ns,
                n=len(results),
                accepted=sum(o.accepted for o in results),
                loop=results[-1].loop if results else 0,
            )

    def tick(self, now_ns: int) -> None:
        """Let time pass (the caller's clock): reasons whose grace ran out
        are derived and their outcomes released; event gaps not told yet
        are (:meth:`on_event_bytes`)."""
        self._release(now_ns)
        if self._ev_tell:
            self._tell_missed(now_ns)

    def finish(self, now_ns: int) -> None:
        """Release every decided outcome now (derived where the CN's event
        did not come): at the end of a run."""
        self._release(now_ns, all_=True)

    # -- events --------------------------------------------------------------
    def on_event(
        self, e: Event, rx_ns: int, verified: bool | None = None, *, filled: bool = False
    ) -> EventRecord:
        """Take one event received at ``rx_ns``: a CN command event whose tag
        verified (``verified`` True, or None when the mission does not
        authenticate) explains a verdict (module doc). Returns the record to
        show or log (``filled``: marked as filled from the recorder,
        :meth:`take_filled`)."""
        ce = _read_cmd_event(e) if verified is not False else None
        if ce is not None:
            self._cmd_events.append(ce)
            for r in self._deciding:
                if not r.reason_from:
                    self._match(r)
            self._release(rx_ns)
        return EventRecord.of(e, rx_ns, verified, filled)

    def forged_event(self, key_expr: str, payload: bytes | bytearray | memoryview) -> bool:
        """Whether an event record is refused by its tag alone
        (:meth:`zplatform.core.events.EventReader.forged`: thread-safe, no copy):
        its receiver's zenoh callback asks, and counts it with
        :meth:`refused_events` instead of queueing it."""
        return self._events_in.forged(key_expr, payload)

    def on_event_bytes(
        self, key_expr: str, payload: bytes | bytearray | memoryview, rx_ns: int
    ) -> EventRecord | None:
        """Check and take one event record that came on ``key_expr``
        (``{vehicle}/<node>/events``: whose key checks its tag); None
        (counted in ``bad_events``) if it is not one, or its tag fails;
        None (counted in ``stale_events``) if it is authentic but not fresh
        (:class:`~zplatform.core.events.EventReader`: a replay, or stamped beyond
        :attr:`max_age_ns` of ``rx_ns``).

        A verified record (its node's tag checked) numbered past the next of
        its node's run is a gap: the numbers skipped are counted in
        ``events_missed``, told in one ``events_missed`` event (at most one
        a second, naming every gap since the last) saying whether they will
        be filled, and a gap of a node in :attr:`fill_events_of` is queued
        in :attr:`event_gaps`. A record of another run than the node's last,
        or numbered at or below its last (a restarted node numbers from 0;
        :class:`~zplatform.core.events.EventReader` took it as later by its
        stamp), starts the count again: no gap. Unverified records (no key,
        no authentication) number nothing."""
        try:
            e, verified = self._events_in.read(key_expr, payload, rx_ns)
        except RunError:  # another run's genuine record
            if self.waiting_for_run:  # not a replay: the run is not known yet
                self.waited += 1
            else:
                self._n.stale_events += 1
            return None
        except StaleRecordError:
            self._n.stale_events += 1
            return None
        except CodecError:
            self._n.bad_events += 1
            return None
        if verified:
            self._number(e, Channel.run_of(payload), rx_ns)
        return self.on_event(e, rx_ns, verified)

    # -- event numbers: gaps detected, told, filled ----------------------------
    def _number(self, e: Event, run: int, rx_ns: int) -> None:
        """Follow ``e``'s node's numbers (:meth:`on_event_bytes`)."""
        last = self._ev_last.get(e.node)
        self._ev_last[e.node] = (run, e.seq, e.t_ns)
        if last is None or last[0] != run or e.seq <= last[1]:
            return  # the first seen, another run's, or a restarted node's
        if e.seq == last[1] + 1:
            return
        first, lastn = last[1] + 1, e.seq - 1
        self._n.events_missed += lastn - first + 1
        gap = EventGap(e.node, run, first, lastn, *self._loops_of(run, last[2], e.t_ns))
        if e.node not in self.fill_events_of:
            fate = f"not filled ({e.node} serves no recorder to ask)"
            if e.node in CONTROL_NODES:
                fate = "not filled (this ground does not ask the control node's recorder)"
        elif not gap.first_loop:
            fate = "not filled (no snapshot of that run places them in loops)"
        elif len(self._ev_open) >= _GAPS_KEPT:
            fate = f"not filled ({_GAPS_KEPT} gaps are being filled already)"
        else:
            fate = "asked of the control node's recorder"
            self._ev_open[gap] = set()
            self.event_gaps.append(gap)
        self._ev_tell.append((gap, fate))
        self._tell_missed(rx_ns)

    def _loops_of(self, run: int, t_from: int, t_to: int) -> tuple[int, int]:
        """The CN loops events stamped ``t_from``..``t_to`` of run ``run``
        were filed under, with a margin (a loop's events carry its stamp,
        or the clock's within it; the recorder files them under the loop's
        frame); (0, 0) when no snapshot of that run was accepted."""
        if run != self._epoch or self._last_seq < 0:
            return 0, 0
        margin = 2 + self._div
        first = self._last_seq + (t_from - self._last_t) // self._period - margin
        last = self._last_seq + (t_to - self._last_t) // self._period + margin
        return max(first, 1), max(last, first, 1)

    def _tell_missed(self, now_ns: int) -> None:
        """One ``events_missed`` event for the gaps not told yet, unless one
        was emitted less than a second ago (:meth:`tick` tells them then)."""
        if now_ns - self._ev_told < _TELL_NS:
            return
        tell, self._ev_tell = self._ev_tell, []
        self._ev_told = now_ns
        n = sum(g.last - g.first + 1 for g, _ in tell)
        named = tell[:_TELL_PARTS]
        what = ", ".join(f"{g.node} ({g.which})" for g, _ in named)
        if len(tell) > len(named):
            what += f" and {len(tell) - len(named)} more gap(s)"
        fates = dict.fromkeys(f for _, f in tell)
        if len(fates) == 1:
            fate = next(iter(fates))
        else:
            fate = "; ".join(f"{g.node} {g.which}: {f}" for g, f in named)
        self.events.emit(EV.EVENTS_MISSED, now_ns, n=n, what=what, fate=fate)

    def check_filled(self, gap: EventGap, payload: bytes | bytearray | memoryview) -> Event | None:
        """The record in ``payload`` (as a gap fill brought it, tag
        included) if it may fill ``gap``: its node's tag checks for the
        gap's run (:meth:`~zplatform.core.events.EventReader.read_filled`),
        and its number is one of the gap's not filled yet; None for a
        genuine record numbered outside the gap (one of the same loops that
        did arrive). Raises CodecError (why) otherwise: a bad tag, another
        run's, not a record, a number of the gap filled already (a replay),
        a gap no longer open. Changes nothing."""
        if gap not in self._ev_open:
            raise CodecError(f"{gap.node}'s events {gap.which} are not being filled")
        e = self._events_in.read_filled(gap.node, payload)
        run = Channel.run_of(payload)
        if run != gap.run:
            raise RunError(f"{gap.node}'s event #{e.seq} of run {run}, not {gap.run}")
        if not gap.first <= e.seq <= gap.last:
            return None  # a genuine one of the same loops that did arrive
        if e.seq in self._ev_open[gap]:
            raise CodecError(f"{gap.node}'s event #{e.seq} filled already (a replay)")
        return e

    def take_filled(self, gap: EventGap, e: Event, rx_ns: int) -> EventRecord | None:
        """Take ``e``, which :meth:`check_filled` passed, as filled at
        ``rx_ns`` (:meth:`on_event`, marked ``filled``); None when its
        number was filled since (nothing taken)."""
        taken = self._ev_open.get(gap)
        if taken is None or e.seq in taken:
            return None
        taken.add(e.seq)
        return self.on_event(e, rx_ns, True, filled=True)

    def close_event_gap(self, gap: EventGap) -> tuple[int, EventGap]:
        """Forget ``gap`` (its filling is over): how many of its numbers
        were not filled (0: none), and the gap from the first of them to the
        last. Costs what was filled, whatever the gap's size."""
        taken = self._ev_open.pop(gap, set())
        n = gap.last - gap.first + 1 - len(taken)
        if n <= 0:
            return 0, gap
        first, last = gap.first, gap.last
        while first in taken:
            first += 1
        while last in taken:
            last -= 1
        return n, gap._replace(first=first, last=last)


def _derived(r: _Request) -> tuple[str, str]:
    """A verdict's reason from the verdict snapshot, when the CN's event did not come."""
    why = {
        "ACCEPTED": "",
        "REJECTED_NOT_ALLOWED": f"not allowed in state {r.state} (the state its verdict showed)",
        "REJECTED_NOT_ARMED": f"{r.cmd} needs an accepted ARM #{r.seq - 1} just before it",
        "REJECTED_BAD_ARGUMENT": "the control node refused the element or the value",
        "REJECTED_UNKNOWN": "not a command the control node knows",
        "REJECTED_REPLAY": (
            f"number {r.seq} is not above the last the control node saw (#{r.shown_seq})"
        ),
        "REJECTED_EPOCH": "the request named another run of the control node",
        "REJECTED_AUTH": "the request's tag did not verify",
        "REJECTED_OUT_OF_BOUNDS": "the value is outside the parameter's bounds",
        "REJECTED_PARAM_STATE": (
            f"the parameter may not change in state {r.state} (the state its verdict showed)"
        ),
        "REJECTED_BUSY": "the previous PRM_SAVE was still being written",
        "REJECTED_NOT_HOLDER": (
            f"{r.holder} holds the command lock"
            if r.holder
            else "nobody holds the command lock: LOCK first"
        ),
        "REJECTED_VIEW_ONLY": "the operator or the station may only view",
    }.get(r.status, "")
    return why, ("derived" if why else "")
