"""The console's state, without zenoh and without textual (sans-IO).

:class:`ConsoleModel` is fed by a telemetry source: :meth:`on_snapshot` after
each accepted snapshot (a CN-layout Data Vector, with the ground's counters),
:meth:`on_event` per event record, :meth:`on_result` per command outcome
(:class:`~zplatform.telemetry.records.CommandOutcome`); the archive's history by
:meth:`seed_series` and :meth:`seed_events` (live wins). The screen asks it what to draw
at a human rate (:meth:`status`, :meth:`region_rows`, :meth:`events`,
:meth:`plot_series`); :meth:`tick` with the current time decides loss of
signal. Limits come from :func:`zplatform.control.limits.mission_limits`; severities
are handled by member *name* (:func:`severity_rank`, :func:`severity_style`;
an unknown name ranks as informational).

Contract: nothing here blocks, reads a clock (every time is an argument, in
ns) or allocates per snapshot beyond one buffer copy and, for plotted
elements, one tuple. Not thread-safe: the owner
(:class:`~zplatform.console.link.Link`) holds :attr:`lock` around every call
from its threads, and the screen holds it while it reads.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from ..config import CMD_NAMES, Mission
from ..config.codes import Command, CommandStatus
from ..control.authority import (
    ARM_WINDOW_NS,
    STATE_DEPENDENT,
    AuthorityRules,
    LockState,
    read_lock_state,
)
from ..control.commands import writable_elements
from ..control.limits import Limits, mission_limits
from ..core.datavector import DataVector, ElementSpec, Layout
from ..core.events import Severity
from ..core.health import stalled_names
from ..errors import CommandError
from ..ground.status import RateMeter
from ..telemetry.records import (
    CommandOutcome,
    EventRecord,
    ParamRow,
    TelemetryCounters,
    format_outcome,
    ns_text,
    param_rows,
    value_text,
)

__all__ = [
    "ConsoleModel",
    "Limits",
    "LogLine",
    "StationRow",
    "Status",
    "archived_event_line",
    "severity_rank",
    "severity_style",
]

# Rank by name: higher is worse. Old and new names side by side.
_RANKS = {
    "FATAL": 6,
    "CRITICAL": 6,
    "ERROR": 5,
    "WARNING_HI": 5,
    "WARNING": 4,
    "WARNING_LO": 4,
    "COMMAND": 3,
    "ACTIVITY_HI": 2,
    "INFO": 2,
    "ACTIVITY_LO": 1,
    "DIAGNOSTIC": 0,
    "DEBUG": 0,
}
_STYLES = {6: "bold white on red", 5: "bold red", 4: "yellow", 3: "cyan", 2: "", 1: "dim", 0: "dim"}

#: Console-side commands (not sent to the vehicle).
LOCAL_COMMANDS = ("filter", "plot", "params", "history", "runs", "clear", "help", "quit")
PLOT_POINTS = 600
"""Most points of a live plot's series (module doc)."""
OPERATOR_COMMANDS = tuple(c.lower() for c in CMD_NAMES[1:])

HELP = (
    "vehicle: " + " | ".join(OPERATOR_COMMANDS) + " (write ELEMENT VALUE, "
    "prm_set PARAMETER VALUE, handover OPERATOR, approve ARM_NUMBER); "
    "console: filter [SEVERITY|all] | plot ELEMENT... | "
    "params (show/hide the parameters) | history ELEMENTS [FROM [TO]] [every=1s|raw] "
    "[agg=min,max,mean] [run=R] (the archive) | runs (pick a past run) | clear | quit"
)


def severity_rank(name: str) -> int:
    """How bad a severity is (0 diagnostic .. 6 fatal), by member name."""
    return _RANKS.get(name.upper(), 2)


def severity_style(name: str) -> str:
    """A rich style for a severity name."""
    return _STYLES[severity_rank(name)]


@dataclass(frozen=True, slots=True)
class LogLine:
    """One line of the event pane: an event, a command verdict or a console note."""

    t_ns: int
    severity: str
    source: str
    text: str
    seq: int = -1
    """The event's number (its node's; -1: not an event)."""


@dataclass(frozen=True, slots=True)
class StationRow:
    """One station of the mission's ``ground.stations``, as the last snapshot
    showed it: listed from the mission, not discovered (a station has no
    presence of its own on the wire; docs/operations.md)."""

    name: str
    may: str
    """``command`` or ``view`` (``ground.stations[].may``)."""
    holder: str
    """The operator holding the command lock from this station ("": none)."""
    heard_s: float | None
    """Seconds (loop time) since the CN last heard a genuine request from it
    (``cn_heard_<station>_ns``); None: not heard since the CN started."""

    def text(self) -> str:
        """``pad (command) alice holds the lock, heard 1.2 s ago``, in words."""
        t = f"{self.name} ({self.may})"
        if self.holder:
            t += f" {self.holder} holds the lock"
        heard = "not heard" if self.heard_s is None else f"heard {self.heard_s:.1f} s ago"
        return f"{t}, {heard}"


@dataclass(frozen=True, slots=True)
class Status:
    """The header line's facts, at one moment."""

    connected: bool
    los: bool
    silence_s: float | None
    loop: int
    state: str
    time_in_state_s: float
    fault: str
    loop_hz: float | None
    received: int
    gaps: int
    bad: int
    per_dn: tuple[tuple[str, int, int, int, int], ...]  # dn, rx, missed, late, clock offset ns
    cmd_seq: int
    cmd_status: str
    last_command: str
    commander: str = ""
    """A redundant mission's control node in command ("" without a standby)."""
    term: int = 0
    standby_ready: bool = False
    waiting_for_run: bool = False
    """The link has not learned the vehicle's run yet (zplatform.ground.link):
    nothing is shown until it has."""
    history: str = ""
    operator: str = ""
    """``operator@station`` this console commands as ("": it only watches)."""
    lock: str = ""
    """Who holds the command lock and until when, in words ("": no authority)."""
    pending_arm: str = ""
    """This console's ARM awaiting approval, in words ("": none)."""
    stations: tuple[StationRow, ...] = ()
    """Every station of the mission, its right, the lock's holder, when last
    heard (empty: no command authority, or no telemetry yet)."""
    events_missed: int = 0
    """Verified events that did not arrive (the ground's ``events_missed``;
    the control node's are filled from its recorder when it has one)."""
    """The history fill's state ("filling history...", what it filled, or why
    it could not); "" when the console opened without history."""


class ConsoleModel:
    """See the module doc. ``los_s``: silence after which the link is lost."""

    def __init__(
        self,
        mission: Mission,
        *,
        los_s: float = 0.3,
        limits: Mapping[str, Any] | None = None,
        max_events: int = 500,
        plot_window_s: float = 30.0,
        history_s: float = 0.0,
    ) -> None:
        self.mission = mission
        self.lock = threading.Lock()
        self.layout = Layout.for_node(mission, "cn")
        self.dv = DataVector(self.layout)
        self.los_ns = int(los_s * 1e9)
        self.limits: dict[str, Limits] = mission_limits(mission, limits)
        # Health's stalled-thread masks are shown with the threads' names.
        self._masks = frozenset(
            f"{n}_threads_stalled" for n in ["cn", *mission.device_nodes] if mission.health
        )
        self.writable = writable_elements(mission)
        """What ``write`` completes: the elements a WRITE may set, by the
        platform's one rule (:func:`zplatform.control.commands.writable_elements`)."""
        self.log: deque[LogLine] = deque(maxlen=max_events)
        self.min_rank = 0
        self.received = 0
        self.gaps = 0
        self.bad = 0
        self.events_missed = 0
        self.last_rx_ns: int | None = None
        self.now_ns: int | None = None
        self.waiting_for_run = False
        """Set by the driver: its link has not learned the vehicle's run yet."""
        self.last_command = "-"
        self._los = False
        self._rate = RateMeter()
        self.plotted: list[str] = []
        self.show_params = False
        """Whether the parameter view is shown (the ``params`` command)."""
        self.history_s = history_s
        """Seconds of history the console opens with (0: none): the plot's
        window is at least as long, so what the fill brought stays shown."""
        self.history = ""
        """The history fill's state, for the status line (Status.history)."""
        window_ns = int(max(plot_window_s, history_s) * 1e9)
        # At most PLOT_POINTS points a series, whatever the window: a long
        # window samples (and fills) more coarsely, never draws more.
        self.plot_step_ns = max(50_000_000, window_ns // PLOT_POINTS)
        self._plot_len = max(1, window_ns // self.plot_step_ns)
        self._series: dict[str, deque[tuple[float, float]]] = {}
        self._last_plot_ns = 0
        self.version = 0  # bumped on every change the screen should redraw for
        self.operator = ""
        """``operator@station`` the console's commands are signed as (set by
        its driver; "": a console that only watches)."""
        g = mission.ground
        self._two_person = bool(mission.authority and g is not None and g.two_person)
        self._rules = AuthorityRules(g) if mission.authority and g is not None else None
        """The CN's rules (:class:`~zplatform.control.authority.AuthorityRules`):
        this console's verdicts are the CN's own function's."""
        self.open_arm: tuple[int, str, int] | None = None
        """The last ARM telemetry showed accepted (two-person missions): its
        number, its operator and the loop time it was seen at."""
        self._seen_seq = -1
        self.awaiting_arm: int | None = None
        """The number of this console's accepted ARM whose two-person command
        waits for a second operator's APPROVE (set by the driver from
        :attr:`~zplatform.ground.logic.GroundLogic.awaiting_approval`)."""

    # -- feeding ------------------------------------------------------------
    def on_snapshot(
        self, dv: DataVector, rx_ns: int, counters: TelemetryCounters | None = None
    ) -> None:
        """Take an accepted snapshot (copied; ``dv`` stays the caller's) and
        the ground's counters (None: count it here)."""
        self.dv.write_all(dv.view())
        if counters is None:
            self.received += 1
        else:
            self.received, self.gaps, self.bad = counters.received, counters.gaps, counters.rejected
            self.events_missed = counters.events_missed
        self.last_rx_ns = rx_ns
        if self._los:
            self._los = False
            self._note(rx_ns, "ACTIVITY_HI", "link", "signal acquired")
        self._rate.add_snapshot(self.dv)
        if self._two_person:
            self._see_arm()
        t = int(self.dv.get("cn_time_ns"))
        if self.plotted and rx_ns - self._last_plot_ns >= self.plot_step_ns:
            self._last_plot_ns = rx_ns
            ts = t / 1e9
            for name in self.plotted:
                self._series[name].append((ts, float(self.dv.get(name))))
        self.version += 1

    def seed_series(
        self, name: str, points: Iterable[tuple[float, float]], span_s: float = 0.0
    ) -> int:
        """Put archived ``points`` (vehicle time in s, value; oldest first),
        each standing for ``span_s`` from its time (a bucket), before plotted
        element ``name``'s live ones: a point whose span reaches the first
        live point is dropped (live wins). Returns the points kept; 0 when
        ``name`` is no longer plotted."""
        series = self._series.get(name)
        if series is None:
            return 0
        first = series[0][0] if series else None
        old = [p for p in points if first is None or p[0] + span_s <= first]
        live = list(series)
        series.clear()
        series.extend(old)
        series.extend(live)  # a full window lets the oldest archived points go
        self.version += 1
        return max(0, len(series) - len(live))

    def seed_events(self, lines: Iterable[LogLine]) -> int:
        """Put archived event lines (oldest first) before the live ones,
        skipping any the event pane holds already. Returns the lines added."""
        have = {(x.t_ns, x.source, x.text) for x in self.log}
        old = [x for x in lines if (x.t_ns, x.source, x.text) not in have]
        if old:
            merged = sorted(old, key=lambda x: x.t_ns) + list(self.log)
            self.log.clear()
            self.log.extend(merged[-(self.log.maxlen or len(merged)) :])
            self.version += 1
        return len(old)

    def on_event(self, rec: EventRecord) -> None:
        """One event: appended; one filled from the recorder (``filled``,
        late by design) is put in its place among its node's events, after
        the last numbered below it, and marked so."""
        mark = " (unverified)" if rec.verified is False else " (filled)" if rec.filled else ""
        line = LogLine(rec.t_ns, rec.severity, rec.node, f"{rec.id}: {rec.text}{mark}", rec.seq)
        self.version += 1
        if not rec.filled:
            self.log.append(line)
            return
        lines = list(self.log)
        at = len(lines)
        for i in range(len(lines) - 1, -1, -1):
            x = lines[i]
            if x.source == rec.node and x.seq >= 0:
                if x.seq < rec.seq:
                    break
                at = i  # a later one of its node: before it
        lines.insert(at, line)
        self.log.clear()
        self.log.extend(lines[-(self.log.maxlen or len(lines)) :])

    def on_result(self, t_ns: int, outcome: CommandOutcome) -> None:
        """A command outcome: the CN's verdict with its reason."""
        self.last_command = format_outcome(outcome)
        sev = "COMMAND" if outcome.accepted else "WARNING_HI"
        self._note(t_ns, sev, "cmd", self.last_command)

    def on_refusal(self, t_ns: int, command: str, text: str) -> None:
        """A command the ground did not send, and why."""
        self.last_command = f"{command}: {text}"
        self._note(t_ns, "WARNING_HI", "cmd", self.last_command)

    def note(self, t_ns: int, text: str, severity: str = "ACTIVITY_LO") -> None:
        """A console message in the event pane."""
        self._note(t_ns, severity, "console", text)

    def _note(self, t_ns: int, sev: str, source: str, text: str) -> None:
        self.log.append(LogLine(t_ns, sev, source, text))
        self.version += 1

    def tick(self, now_ns: int) -> bool:
        """Advance the model's clock; returns whether the link is lost now."""
        self.now_ns = now_ns
        lost = self.last_rx_ns is None or now_ns - self.last_rx_ns > self.los_ns
        if lost and not self._los and self.last_rx_ns is not None:
            self._note(now_ns, "WARNING_HI", "link", "LOSS OF SIGNAL")
        self._los = lost
        return lost

    # -- reading ------------------------------------------------------------
    def status(self) -> Status:
        dv = self.dv
        redundant = self.mission.standby is not None
        los = self._los or self.last_rx_ns is None
        silence = (
            None
            if self.last_rx_ns is None or self.now_ns is None
            else (self.now_ns - self.last_rx_ns) / 1e9
        )
        dns = tuple(
            (
                dn,
                int(dv.get(f"cn_rx_{dn}")),
                int(dv.get(f"cn_missed_{dn}")),
                int(dv.get(f"cn_late_{dn}")),
                int(dv.get(f"{dn}_clock_offset_ns")),
            )
            for dn in self.mission.device_nodes
        )
        return Status(
            connected=self.last_rx_ns is not None,
            los=los,
            silence_s=silence,
            loop=int(dv.get("cn_loop")),
            state=dv.get_name("cn_state"),
            time_in_state_s=int(dv.get("cn_time_in_state_ns")) / 1e9,
            fault=dv.get_name("cn_fault"),
            loop_hz=self._rate.hz,
            received=self.received,
            gaps=self.gaps,
            bad=self.bad,
            events_missed=self.events_missed,
            per_dn=dns,
            cmd_seq=int(dv.get("cn_cmd_seq")),
            cmd_status=dv.get_name("cn_cmd_status"),
            last_command=self.last_command,
            commander=dv.get_name("cn_commander") if redundant else "",
            term=int(dv.get("cn_term")) if redundant else 0,
            standby_ready=bool(dv.get("cn_standby_ready")) if redundant else False,
            waiting_for_run=self.waiting_for_run,
            history=self.history,
            operator=self.operator,
            lock=self.lock_text(),
            pending_arm=self._arm_text(),
            stations=self.station_rows(),
        )

    # -- command authority (docs/security.md "Stations and operators") -------
    def lock_state(self) -> LockState:
        """The authority's state the last snapshot showed
        (:func:`~zplatform.control.authority.read_lock_state`)."""
        return read_lock_state(self.dv)

    def lock_text(self) -> str:
        """The CN's words for the lock's holder at the last snapshot's loop
        time (:meth:`AuthorityRules.lock_text
        <zplatform.control.authority.AuthorityRules.lock_text>`); "" in a
        mission without command authority or before any telemetry."""
        if self._rules is None or self.last_rx_ns is None:
            return ""
        return self._rules.lock_text(self.lock_state(), int(self.dv.get("cn_time_ns")))

    def station_rows(self) -> tuple[StationRow, ...]:
        """Every station of ``ground.stations`` at the last snapshot's loop
        time: its right, the operator holding the lock from it (a lease that
        ran out holds nothing), and how long ago the CN last heard it
        (``cn_heard_<station>_ns``, 0: not heard). Empty in a mission without
        command authority or before any telemetry. Allocates the rows."""
        g = self.mission.ground
        if self._rules is None or g is None or self.last_rx_ns is None:
            return ()
        dv = self.dv
        now = int(dv.get("cn_time_ns"))
        lock = self.lock_state()
        held = lock.holder >= 0 and now <= lock.until_ns
        rows = []
        for i, st in enumerate(g.stations):
            heard = int(dv.get(f"cn_heard_{st.name}_ns"))
            holder = self._rules.operators[lock.holder] if held and lock.station == i else ""
            age = None if heard == 0 else max(0, now - heard) / 1e9
            rows.append(StationRow(st.name, st.may, holder, age))
        return tuple(rows)

    def _see_arm(self) -> None:
        """Note an ARM the snapshot shows accepted (anyone's): the approver's
        console shows it (:meth:`_arm_text`)."""
        dv = self.dv
        seq = int(dv.get("cn_cmd_seq"))
        if seq == self._seen_seq:
            return
        self._seen_seq = seq
        if dv.get_name("cn_cmd_status") != "ACCEPTED":
            return  # a refused request leaves the ARM open
        cmd = dv.get_name("cn_cmd")
        if cmd == "ARM":
            self.open_arm = (seq, dv.get_name("cn_cmd_operator"), int(dv.get("cn_time_ns")))
        elif cmd != "APPROVE":  # its command came (or another): the ARM is spent
            self.open_arm = None

    def _arm_text(self) -> str:
        n = self.awaiting_arm
        if n is not None:
            return f"ARM #{n} awaits a second operator's approval: `approve {n}` at another console"
        arm = self.open_arm
        if arm is None or self.operator.split("@")[0] == arm[1]:
            return ""
        dv = self.dv
        if int(dv.get("cn_arm_approvals")) or int(dv.get("cn_time_ns")) - arm[2] > ARM_WINDOW_NS:
            return ""
        return f"ARM #{arm[0]} by {arm[1]} is open: `approve {arm[0]}` if it is yours to approve"

    def set_awaiting(self, t_ns: int, arm: int | None) -> None:
        """The driver's ARM awaiting approval (None: none); noted once when it opens."""
        if arm == self.awaiting_arm:
            return
        self.awaiting_arm = arm
        if arm is not None:
            self._note(t_ns, "ACTIVITY_HI", "cmd", self._arm_text())
        self.version += 1

    def refusal(self, command: str, *, target: int = 0, ref: int = 0) -> str | None:
        """What the CN would refuse ``command`` (a command name; ``target``:
        HANDOVER's operator number, ``ref``: APPROVE's ARM number) from this
        console's operator with, in its words (``STATUS: reason``); None when
        it may go (the CN judges again). The CN's own verdict
        (:meth:`AuthorityRules.verdict
        <zplatform.control.authority.AuthorityRules.verdict>`) over the state
        the last snapshot published, at its loop time: roles, a view-only
        station, the lock, and an APPROVE of no open ARM, of one too old, or
        of one's own. Before any telemetry only what the state cannot change
        is refused."""
        rules = self._rules
        if rules is None or not self.operator or command not in Command.__members__:
            return None
        name, _, station = self.operator.partition("@")
        if name not in rules.operators or station not in rules.stations:
            return None  # the signer refused the unknown names already
        got = rules.verdict(
            self.lock_state(),
            rules.operators.index(name),
            rules.stations.index(station),
            Command[command],
            int(self.dv.get("cn_time_ns")),
            target=target,
            ref=ref,
        )
        if got is None or (self.last_rx_ns is None and got[0] in STATE_DEPENDENT):
            return None  # no telemetry yet: the lock and the ARM are unknown here
        return f"{CommandStatus(got[0]).name}: {got[1]}"

    def format_value(self, spec: ElementSpec) -> str:
        v = self.dv.get(spec.name)
        if spec.enum is not None:
            return spec.name_of(int(v))
        if spec.name in self._masks and v:
            return f"{v} ({', '.join(stalled_names(int(v)))})"
        if spec.count:
            items = v[:8].tolist()
            text = ", ".join(_fmt(x) for x in items)
            return f"[{text}{', ...' if spec.count > 8 else ''}]"
        if spec.name.endswith("_ns") and spec.scalar.kind == "int":
            return ns_text(int(v))  # a time of day or a duration, never raw ns
        return _fmt(v)

    def level(self, spec: ElementSpec) -> str:
        lim = self.limits.get(spec.name)
        if lim is None or spec.count or spec.enum is not None:
            return ""
        return lim.level(float(self.dv.get(spec.name)))

    def region_rows(self) -> list[tuple[str, list[tuple[str, str, str]]]]:
        """``[(region, [(element, value text, limit level), ...]), ...]`` in buffer order."""
        return [
            (r.name, [(e.name, self.format_value(e), self.level(e)) for e in r.elements])
            for r in self.layout.regions.values()
            if r.elements
        ]

    def param_rows(self) -> list[ParamRow]:
        """Every parameter of the mission with its value in the last
        snapshot ("-" before the first)."""
        if self.last_rx_ns is None:
            return param_rows(self.mission, None)
        return param_rows(self.mission, {p.name: self.dv.get(p.name) for p in self.mission.params})

    def toggle_params(self) -> str:
        """Show or hide the parameter view."""
        if not self.mission.params:
            raise CommandError(f"mission {self.mission.mission!r} has no parameters")
        self.show_params = not self.show_params
        self.version += 1
        return "parameters shown" if self.show_params else "parameters hidden"

    def events(self) -> list[LogLine]:
        """The log lines that pass the severity filter, oldest first."""
        return [x for x in self.log if severity_rank(x.severity) >= self.min_rank]

    def plot_series(self) -> dict[str, tuple[list[float], list[float]]]:
        return {n: ([p[0] for p in s], [p[1] for p in s]) for n, s in self._series.items() if s}

    # -- operator input -----------------------------------------------------
    def set_filter(self, words: list[str]) -> str:
        """``filter`` (show all) or ``filter NAME``: NAME and worse."""
        if not words or words[0].lower() == "all":
            self.min_rank = 0
            return "showing every event"
        name = words[0].upper()
        if name not in _RANKS and name not in Severity.__members__:
            names = [s.name for s in Severity]
            raise CommandError(f"unknown severity {words[0]!r}; one of {names} or all")
        self.min_rank = severity_rank(name)
        self.version += 1
        return f"showing {name} and worse"

    def set_plot(self, names: Iterable[str]) -> str:
        names = list(names)
        for n in names:
            spec = self.layout.element(n)
            if spec.count:
                raise CommandError(f"{n} is an array; plot scalars")
        self.plotted = names
        self._series = {n: deque(maxlen=self._plot_len) for n in names}
        self.version += 1
        return f"plotting {', '.join(names)}" if names else "plot cleared"

    def complete(self, text: str) -> str | None:
        """The completion of ``text`` (the whole line) or None.

        Completes the first word against operator and console commands, the
        element of ``write`` against writable elements, the parameter of
        ``prm_set`` against the mission's parameters, ``plot`` against every
        scalar element and ``filter`` against severity names.
        """
        words = text.split(" ")
        if len(words) == 1:
            pool: Iterable[str] = (*OPERATOR_COMMANDS, *LOCAL_COMMANDS)
        else:
            head = words[0].lower()
            if head == "write" and len(words) == 2:
                pool = self.writable
            elif head == "prm_set" and len(words) == 2:
                pool = [p.name for p in self.mission.params]
            elif head in ("plot", "history"):
                pool = [e.name for e in self.layout.elements.values() if not e.count]
            elif head == "filter" and len(words) == 2:
                pool = [*(s.name for s in Severity), "all"]
            else:
                return None
        last = words[-1]
        if not last:
            return None
        for cand in pool:
            if cand.lower().startswith(last.lower()) and cand != last:
                return " ".join([*words[:-1], cand])
        return None


def archived_event_line(row: Mapping[str, Any]) -> LogLine:
    """An event the archive kept (a row of ``Archive.events``) as the event
    pane shows a live one."""
    mark = " (unverified)" if row.get("verified") is False else ""
    return LogLine(
        int(row["t_ns"]),
        str(row["severity"]),
        str(row["node"]),
        f"{row['id']}: {row['text']}{mark}",
    )


def _fmt(v: Any) -> str:
    """A Data Vector value: bools as the telemetry CSV spells them, floats to 6 digits."""
    return value_text(v, bools=("0", "1"), digits=6)
