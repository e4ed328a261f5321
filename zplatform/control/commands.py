"""The operator command handler (thesis ch. 4.8 and 6.1), sans-IO.

Holds :class:`CommandHandler` (one request per ``gn_to_cn`` frame:
``gn_cmd``, ``gn_cmd_seq``, and for WRITE and PRM_SET ``gn_cmd_element`` and
``gn_cmd_value``), the request-number rule (:func:`request_refusal`, the
one the CN's intake applies too, with :class:`RequestNumber`), and the
load-time checks of the ``commands`` section (:func:`check_config`, ...).

Contract: on the CN's loop thread, :meth:`CommandHandler.admit` refuses a
request for another run or numbered not above the last (that rule), and
:meth:`CommandHandler.step` validates the admitted one (first failure wins:
unknown, the state's whitelist, a latched fault (:func:`refused_while_faulted`),
ARM for hazardous commands, argument, the element's or parameter's states
and bounds, a save still being written), writes the verdict to ``cn_cmd_seq``
/ ``cn_cmd_status`` with a ``cmd_accepted`` or ``cmd_rejected`` event, and keeps
an accepted command in ``cn_cmd`` until a transition consumes it or a state
that does not handle it steps. Nothing in a request can make it raise.
What the intake refused is counted by :meth:`CommandHandler.count_refused`.
The rules: docs/architecture.md#safety-rules, docs/mission-reference.md#key-commands.
"""

from __future__ import annotations

import difflib
import logging
import math
import struct
from typing import TYPE_CHECKING, Any

from ..config import CMD_NAMES
from ..config.codes import Command, CommandStatus, Fault
from ..core.events import EV, EventLog
from ..errors import ConfigError
from . import authority as _authority
from .authority import Authority, Identity, read_lock_state
from .interlocks import output_states
from .params import ParamSlot, ParamTable
from .statemachine import logic_writable, why_not_writable

if TYPE_CHECKING:
    from ..config import Mission
    from ..core.datavector import DataVector, ElementSpec, Handle, Layout
    from .statemachine import StateMachine

__all__ = [
    "ARM_WINDOW_NS",
    "Command",
    "CommandHandler",
    "CommandStatus",
    "RequestNumber",
    "check_config",
    "protected_elements",
    "request_refusal",
    "request_refusal_detail",
    "transition_readers",
    "writable_elements",
    "write_states",
]

log = logging.getLogger("zplatform.commands")

ARM_WINDOW_NS = _authority.ARM_WINDOW_NS
"""How long an accepted ARM confirms the next (hazardous) command: 10 s."""

SEQ_WINDOW = 1 << 20
"""How far past the last number a request may jump. Numbers are u64, so
even a forger walking them up by this much per request would need 2**44
requests to exhaust them."""


_OTHER_RUN, _NOT_ABOVE, _TOO_FAR = 1, 2, 3
_STATUS_OF = (
    0,
    CommandStatus.REJECTED_EPOCH,
    CommandStatus.REJECTED_REPLAY,
    CommandStatus.REJECTED_REPLAY,
)


def _number_rule(epoch: int, seq: int, cn_epoch: int, last_seq: int) -> int:
    """The request-number rule, the one place it is written: 0 (may go
    on), or why not: another run, a number not above the last, or one too
    far past it (:data:`SEQ_WINDOW`)."""
    if epoch != cn_epoch:
        return _OTHER_RUN
    if seq <= last_seq:
        return _NOT_ABOVE
    if seq - last_seq > SEQ_WINDOW:
        return _TOO_FAR
    return 0


def request_refusal(epoch: int, seq: int, cn_epoch: int, last_seq: int) -> int:
    """The refusal that consumes no number (module doc), for a request
    numbered ``seq`` for CN run ``epoch``, on a CN whose run is
    ``cn_epoch`` and whose highest number seen is ``last_seq``:
    ``REJECTED_EPOCH``, ``REJECTED_REPLAY``, or 0 when it may go on to be
    validated. Pure, constant time, allocates nothing: the CN's intake
    applies it to a request as it arrives (so a replayed frame never
    displaces a fresh one), :meth:`CommandHandler.admit` to each request
    the loop may take (:func:`request_refusal_detail` says why)."""
    return _STATUS_OF[_number_rule(epoch, seq, cn_epoch, last_seq)]


def request_refusal_detail(
    epoch: int, seq: int, cn_epoch: int, last_seq: int
) -> tuple[int, str] | None:
    """:func:`request_refusal`'s status and the detail its event gives, or
    None when the request may go on. Pure."""
    why = _number_rule(epoch, seq, cn_epoch, last_seq)
    if why == _OTHER_RUN:
        detail = (
            f"epoch {epoch} is not this control node's ({cn_epoch}): a request for an earlier run"
        )
    elif why == _NOT_ABOVE:
        detail = f"number {seq} is not above the last one seen ({last_seq})"
    elif why == _TOO_FAR:
        detail = f"number {seq} jumps more than {SEQ_WINDOW} past the last one ({last_seq})"
    else:
        return None
    return _STATUS_OF[why], detail


class RequestNumber:
    """Reads a request's ``gn_cmd_epoch`` and ``gn_cmd_seq`` (and its
    ``gn_cmd``) out of a ``gn_to_cn`` region's data, at their fixed offsets:
    what :func:`request_refusal` needs, without applying the frame."""

    __slots__ = ("_cmd", "_epoch", "_seq")

    def __init__(self, layout: Layout) -> None:
        base = layout.region("gn_to_cn").offset

        def field(name: str) -> struct.Struct:
            e = layout.element(name)
            return struct.Struct(f"<{e.offset - base}x{e.scalar.struct}")

        self._epoch = field("gn_cmd_epoch")
        self._seq = field("gn_cmd_seq")
        self._cmd = field("gn_cmd")

    def read(self, data: bytes | bytearray | memoryview) -> tuple[int, int]:
        """``(epoch, seq)`` of one request's region data (struct.error if too short)."""
        return self._epoch.unpack_from(data)[0], self._seq.unpack_from(data)[0]

    def command(self, data: bytes | bytearray | memoryview) -> str:
        """The name of the command a request's region data asks for."""
        cmd = int(self._cmd.unpack_from(data)[0])
        return CMD_NAMES[cmd] if cmd < len(CMD_NAMES) else f"code {cmd}"


_N_CMDS = len(CMD_NAMES)
_LOCK_CMDS = frozenset(
    {Command.LOCK, Command.RELEASE, Command.HANDOVER, Command.TAKEOVER, Command.APPROVE}
)
"""The commands of the command lock and the two-person rule
(:mod:`zplatform.control.authority`): they move no vehicle state, so no
state's whitelist refuses them."""
_LOCK_NAMES = frozenset(Command(c).name for c in _LOCK_CMDS)
_REFUSAL_EVENT_NS = 1_000_000_000
"""Authority refusals are evented at most once per this (the rest counted)."""
_F32_MAX = 3.4028234663852886e38


# ---------------------------------------------------------------------------
# configuration


def _all_element_names(mission: Mission) -> list[str]:
    """The CN's element list, in ``ElementSpec.index`` order."""
    return [e.name for r in mission.region_names() for e in mission.regions[r]]


def protected_elements(mission: Mission) -> list[str]:
    """Elements a WRITE may set only as a hazardous command (ARM n, WRITE n+1).

    ``commands.protected`` when given; otherwise every controller mode when
    the mission has hazardous commands (switching a safety controller off is
    as hazardous as the command it guards), else none."""
    cfg = mission.commands
    if cfg.protected is not None:
        return list(cfg.protected)
    if not cfg.hazardous:
        return []
    return [f"{c.name}_mode" for c in mission.controllers]


def writable_elements(mission: Mission) -> list[str]:
    """Elements a WRITE command may write, in Data Vector order: those
    ``commands.writable`` lists, and no other (deny by default)."""
    # Never a parameter: check_config refuses one here, and this list
    # must not let one through whoever calls it before that check.
    chosen = set(mission.commands.writable) - {p.name for p in mission.params}
    return [n for n in _all_element_names(mission) if n in chosen]


def write_states(mission: Mission) -> dict[str, list[str]]:
    """Each writable element (:func:`writable_elements`, in that order) and
    the states in which a WRITE may set it, in state order: the states
    whose whitelist allows WRITE, narrowed to ``commands.write_states``'s
    list for the element when it has one, and to a hazardous output's
    states (``hazardous_outputs``). Pure."""
    cfg = mission.commands
    outputs = output_states(mission)
    wl = cfg.whitelist
    states = [s for s in _state_names(mission) if s not in wl or "WRITE" in wl[s]]
    out: dict[str, list[str]] = {}
    for name in writable_elements(mission):
        listed = cfg.write_states.get(name)
        out[name] = [
            s
            for s in states
            if (listed is None or s in listed) and (name not in outputs or s in outputs[name])
        ]
    return out


def transition_readers(mission: Mission) -> dict[str, list[tuple[str, int]]]:
    """Each element a transition condition reads, and where: ``(state,
    index of the transition)`` pairs in YAML order. Pure."""
    out: dict[str, list[tuple[str, int]]] = {}
    sm = mission.state_machine
    if sm is None:
        return out
    for state, st in sm.states.items():
        for i, t in enumerate(st.transitions):
            if t.element is not None:
                out.setdefault(t.element, []).append((state, i))
    return out


def _state_names(mission: Mission) -> list[str]:
    sm = mission.state_machine
    return list(sm.states) if sm is not None else ["IDLE"]


_FAULT_PROOF = {
    "ABORT": "it is the response to one",
    "NOOP": "it moves nothing",
    "ARM": "it confirms the next command, which is checked itself",
    "WRITE": "WRITE cn_fault NONE is how an operator clears it",
    **{
        c: "it moves the command lock, no vehicle state"
        for c in ("LOCK", "RELEASE", "HANDOVER", "TAKEOVER", "APPROVE")
    },
}
"""Commands ``commands.refused_while_faulted`` may not list, and why."""


def refused_while_faulted(mission: Mission) -> list[str]:
    """The commands refused while ``cn_fault`` holds a fault:
    ``commands.refused_while_faulted``, by default the hazardous ones. Pure."""
    cfg = mission.commands
    if cfg.refused_while_faulted is not None:
        return list(cfg.refused_while_faulted)
    return [c for c in cfg.hazardous if c not in _FAULT_PROOF]  # a hazardous WRITE still clears


def check_config(mission: Mission, *, warn: bool = True) -> None:
    """Check the ``commands`` section; raises ConfigError naming the YAML path.

    * whitelist keys are states, values are command names (not ``NONE``);
    * hazardous entries are command names other than ``NONE`` and ``ARM``
      (ARM is the confirmation), and a state that allows a hazardous
      command also allows ARM (else it could never be accepted there);
    * ``writable`` elements exist, are scalars, are listed once, and may be
      written by CN logic (not platform bookkeeping, not received from a
      peer, not a parameter);
    * ``write_states`` names writable elements and states whose whitelist
      allows WRITE (for a hazardous output, only its own states); every
      writable element may be written in some state (:func:`write_states`);
    * no writable element may be written in a state whose transitions read
      it (:func:`transition_readers`): a WRITE must never fire a transition
      (the ground would drive the flight's events).

    * ``refused_while_faulted`` entries are command names, never ABORT,
      NOOP, ARM, WRITE (it clears the fault) or a lock command;

    With ``warn``, logs a warning for a ``cn_cmd == X`` transition in a
    state whose whitelist refuses ``X`` (the transition can never fire).
    """
    cfg = mission.commands
    states = _state_names(mission)
    commands = [c for c in CMD_NAMES if c != "NONE"]
    for i, h in enumerate(cfg.hazardous):
        w = f"$.commands.hazardous[{i}]"
        if h not in commands:
            raise ConfigError(f"{h!r} is not a command; commands: {', '.join(commands)}", w)
        if h == "ARM":
            raise ConfigError("ARM cannot be hazardous: it is the confirmation itself", w)
        if h in _LOCK_NAMES:
            raise ConfigError(f"{h} moves the command lock, it cannot be hazardous", w)
    for i, c in enumerate(cfg.refused_while_faulted or ()):
        w = f"$.commands.refused_while_faulted[{i}]"
        if c not in commands:
            raise ConfigError(f"{c!r} is not a command; commands: {', '.join(commands)}", w)
        if c in _FAULT_PROOF:
            raise ConfigError(f"{c} is never refused for a fault: {_FAULT_PROOF[c]}", w)
    for state, allowed in cfg.whitelist.items():
        w = f"$.commands.whitelist.{state}"
        if state not in states:
            raise ConfigError(f"the whitelist names state {state!r}; states: {states}", w)
        for j, c in enumerate(allowed):
            if c not in commands:
                raise ConfigError(
                    f"{c!r} is not a command; commands: {', '.join(commands)}", f"{w}[{j}]"
                )
        for h in cfg.hazardous:
            if h in allowed and "ARM" not in allowed:
                raise ConfigError(
                    f"{h} is hazardous and needs an ARM first, but state {state} does not "
                    "allow ARM",
                    w,
                )
    params = {p.name for p in mission.params}
    if cfg.protected is not None:
        allowed_w = set(writable_elements(mission))
        for i, name in enumerate(cfg.protected):
            if name in params:
                raise ConfigError(
                    f"{name!r} is a parameter: WRITE never sets it; make it hazardous in "
                    "`params` instead (ARM n, then PRM_SET n+1)",
                    f"$.commands.protected[{i}]",
                )
            if name not in allowed_w:
                raise ConfigError(
                    f"{name!r} is not an element WRITE may set, so protecting it means nothing; "
                    f"writable: {sorted(allowed_w)}",
                    f"$.commands.protected[{i}]",
                )
        if cfg.protected and "ARM" not in {c for v in cfg.whitelist.values() for c in v} | (
            {"ARM"} if set(states) - set(cfg.whitelist) else set()
        ):
            raise ConfigError(
                "protected elements need an ARM first, but no state allows ARM",
                "$.commands.protected",
            )
    table = {e.name: (r, e) for r, es in mission.regions.items() for e in es}
    can = logic_writable(mission)
    index: dict[str, int] = {}
    for i, name in enumerate(cfg.writable):
        w = f"$.commands.writable[{i}]"
        if name not in table:
            close = difflib.get_close_matches(name, list(table), n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ConfigError(f"no element named {name!r} in the Data Vector{hint}", w)
        region, e = table[name]
        if "[" in e.type:
            raise ConfigError(f"element {name!r} is an array ({e.type}); WRITE sets one scalar", w)
        if name not in can:
            raise ConfigError(why_not_writable(mission, region, name), w)
        if name in index:
            raise ConfigError(f"element {name!r} is listed twice", w)
        index[name] = i
    outputs = output_states(mission)
    wl = cfg.whitelist
    for name, named in cfg.write_states.items():
        w = f"$.commands.write_states.{name}"
        if name not in index:
            raise ConfigError(
                f"{name!r} is not in commands.writable: a WRITE never sets it, so its states "
                "mean nothing",
                w,
            )
        for j, state in enumerate(named):
            if state not in states:
                raise ConfigError(f"{state!r} is not a state; states: {states}", f"{w}[{j}]")
            if state in wl and "WRITE" not in wl[state]:
                raise ConfigError(f"state {state}'s whitelist does not allow WRITE", f"{w}[{j}]")
            if name in outputs and state not in outputs[name]:
                raise ConfigError(
                    f"{name!r} is a hazardous output that may be driven only in "
                    f"{', '.join(outputs[name]) or 'no state'} (hazardous_outputs), not in "
                    f"{state}",
                    f"{w}[{j}]",
                )
    may = write_states(mission)
    readers = transition_readers(mission)
    for name, i in index.items():
        w = (
            f"$.commands.write_states.{name}"
            if name in cfg.write_states
            else f"$.commands.writable[{i}]"
        )
        if not may[name]:
            also = (
                f", and it is a hazardous output of {', '.join(outputs[name]) or 'no state'}"
                if name in outputs
                else ""
            )
            raise ConfigError(
                f"element {name!r} may be written in no state (none of its states allows "
                f"WRITE{also}): drop it from commands.writable",
                w,
            )
        for state, k in readers.get(name, ()):
            if state in may[name]:
                raise ConfigError(
                    f"element {name!r} is read by a transition of state {state} "
                    f"(`$.state_machine.states.{state}.transitions[{k}]`) and a WRITE may set it "
                    f"in {state}: one command would fire that transition; name the states where "
                    f"it may be written in commands.write_states.{name} (without {state}), or "
                    "leave it out of commands.writable",
                    w,
                )
    _authority.check_config(mission, protected_elements(mission))
    sm = mission.state_machine
    if warn and sm is not None:
        for state, st in sm.states.items():
            listed = cfg.whitelist.get(state)
            if listed is None:
                continue
            for i, t in enumerate(st.transitions):
                if (
                    t.element == "cn_cmd"
                    and t.op == "=="
                    and isinstance(t.value, str)
                    and t.value not in listed
                ):
                    log.warning(
                        "state %s refuses command %s, so this transition never fires - at "
                        "`$.state_machine.states.%s.transitions[%d]`",
                        state,
                        t.value,
                        state,
                        i,
                    )


# ---------------------------------------------------------------------------
# the handler


def _write_value(spec: ElementSpec, v: float) -> tuple[Any, str]:
    """``(stored value, "")`` for a WRITE of ``v`` to ``spec``, or
    ``(None, reason)`` when it does not fit."""
    st = spec.scalar
    if math.isnan(v) or math.isinf(v):
        return None, f"value {v} is not finite"
    if spec.enum is not None:
        if v.is_integer() and 0 <= v < len(spec.enum):
            return int(v), ""
        return None, f"{v:g} is not an index of {spec.name}'s names 0..{len(spec.enum) - 1}"
    if st.kind == "bool":
        if v in (0.0, 1.0):
            return v == 1.0, ""
        return None, f"{v:g} is not 0 or 1 for bool element {spec.name}"
    if st.kind == "int":
        assert st.lo is not None and st.hi is not None
        if v.is_integer() and st.lo <= int(v) <= st.hi:
            return int(v), ""
        return None, f"{v!r} is not an integer in {st.lo}..{st.hi} for {st.name} {spec.name}"
    if st.size == 4 and abs(v) > _F32_MAX:
        return None, f"{v!r} does not fit f32 element {spec.name}"
    return v, ""


class CommandHandler:
    """Validates and applies operator command requests on the CN (module doc).

    ``dv`` is the CN's Data Vector. ``statemachine`` receives HOLD and
    RESUME (without one, they are refused). ``params``: the CN's parameter
    table (PRM_SET, PRM_SAVE; default: one of its own). Construction runs
    :func:`check_config` and resolves the whitelist, the hazardous set and
    the writable elements into tables indexed by state and command code, so
    a loop without a request costs one attribute test.

    Not thread-safe: the CN loop calls :meth:`step` once per loop, before
    the state machine's step.
    """

    def __init__(
        self,
        mission: Mission,
        dv: DataVector,
        events: EventLog,
        statemachine: StateMachine | None = None,
        params: ParamTable | None = None,
        operators_key: bytes | None = None,
    ) -> None:
        check_config(mission, warn=False)
        self._events = events
        self._sm = statemachine
        self.params = params if params is not None else ParamTable(mission, dv, events)
        self._h_cmd = dv.handle("cn_cmd")
        self._h_seq = dv.handle("cn_cmd_seq")
        self._h_status = dv.handle("cn_cmd_status")
        self._h_rejects = dv.handle("cn_cmd_rejects")
        self._h_reject_status = dv.handle("cn_cmd_reject_status")
        self._h_reject_seq = dv.handle("cn_cmd_reject_seq")
        self._h_epoch = dv.handle("cn_epoch")
        self._h_state = dv.handle("cn_state")
        self._has_ground = "gn_to_cn" in dv.layout.regions
        if self._has_ground:
            self._g_cmd = dv.handle("gn_cmd")
            self._g_seq = dv.handle("gn_cmd_seq")
            self._g_elem = dv.handle("gn_cmd_element")
            self._g_value = dv.handle("gn_cmd_value")
        states = self._h_state.spec.enum or ()
        self._states = states
        wl = mission.commands.whitelist
        self._allowed: tuple[tuple[bool, ...], ...] = tuple(
            tuple(s not in wl or c in wl[s] for c in CMD_NAMES) for s in states
        )
        self._hazardous = tuple(c in mission.commands.hazardous for c in CMD_NAMES)
        faulted = refused_while_faulted(mission)
        self._fault_refuses = tuple(c in faulted for c in CMD_NAMES)
        self._h_fault = dv.handle("cn_fault")
        self._fault_names = self._h_fault.spec.enum or ()
        targets: list[Handle | None] = [None] * len(dv.layout.elements)
        # Per element index, the states (by cn_state's index) a WRITE may set it in.
        may: list[tuple[bool, ...]] = [()] * len(dv.layout.elements)
        for name, ok in write_states(mission).items():
            h = dv.handle(name)
            targets[h.spec.index] = h
            may[h.spec.index] = tuple(s in ok for s in states)
        self._targets = tuple(targets)
        self._may_write = tuple(may)
        self._param_names = frozenset(p.name for p in mission.params)
        protected = [False] * len(dv.layout.elements)
        for name in protected_elements(mission):
            protected[dv.layout.element(name).index] = True
        self._protected = tuple(protected)
        self._names_by_index = tuple(
            sorted(dv.layout.elements, key=lambda n: dv.layout.elements[n].index)
        )
        self._active = False
        self._last_seq = 0
        self._arm_seq = -1
        self._arm_t_ns = 0
        # A redundant or recording mission keeps the last ARM in the vector
        # (a standby's mirror, the recorder's frames: adopt()).
        arm = "cn_arm_seq" in dv.layout.elements
        self._h_arm_seq = dv.handle("cn_arm_seq") if arm else None
        self._h_arm_t = dv.handle("cn_arm_t_ns") if arm else None
        # Command authority (a `ground:` section without single_operator).
        g = mission.ground
        self._auth: Authority | None = None
        self._tick_t: int | None = None
        self._refusal_t: int | None = None
        self._refusals_quiet = 0
        if g is not None and not g.single_operator and self._has_ground:
            self._init_authority(mission, dv, operators_key)

    def _init_authority(self, mission: Mission, dv: DataVector, key: bytes | None) -> None:
        assert mission.ground is not None
        self._auth = Authority(mission.ground, mission.vehicle, mission.security.mac, key)
        lay = dv.layout
        base = lay.region("gn_to_cn").offset

        def at(name: str) -> int:
            return lay.element(name).offset - base

        def field(name: str) -> struct.Struct:
            return struct.Struct(f"<{at(name)}x{lay.element(name).scalar.struct}")

        # The request's fields read straight out of a frame's region data
        # (admit: before it is applied) or out of the vector (step).
        self._f_cmd = field("gn_cmd")
        self._f_elem = field("gn_cmd_element")
        self._f_op = field("gn_cmd_operator")
        self._f_st = field("gn_cmd_station")
        self._f_ref = field("gn_cmd_ref")
        self._op_tag_at = at("gn_cmd_op_tag")
        self._st_tag_at = at("gn_cmd_st_tag")
        self._g_region = dv.region_view("gn_to_cn")
        self._h_cmd_operator = dv.handle("cn_cmd_operator")
        self._h_lock_holder = dv.handle("cn_lock_holder")
        self._h_lock_station = dv.handle("cn_lock_station")
        self._h_lock_until = dv.handle("cn_lock_until_ns")
        self._h_approvals = dv.handle("cn_arm_approvals")
        self._h_arm_open = dv.handle("cn_arm_open")
        self._h_arm_operator = dv.handle("cn_arm_operator")
        self._h_arm_open_ns = dv.handle("cn_arm_open_ns")
        self._h_arm_approvers = dv.handle("cn_arm_approvers")
        self._dv = dv
        self._h_auth_refused = dv.handle("cn_auth_refused")
        # Per station of ground.stations: when its last genuine request came.
        self._h_heard = tuple(dv.handle(f"cn_heard_{s}_ns") for s in self._auth.stations)
        cmds, elems = _authority.two_person_targets(mission)
        self._two_cmd = tuple(c in cmds for c in CMD_NAMES)
        two = [False] * len(lay.elements)
        for name in elems:
            two[lay.element(name).index] = True
        self._two_elem = tuple(two)

    @property
    def authority(self) -> Authority | None:
        """The command lock and two-person rule (None: a mission without them)."""
        return self._auth

    def _tick(self, t_ns: int) -> None:
        """Once per loop time: end a lease that ran out (and publish that).
        The lock's elements change only here and after a request (:meth:`step`)."""
        auth = self._auth
        if auth is None or t_ns == self._tick_t:
            return
        self._tick_t = t_ns
        ch = auth.expire(t_ns)
        if ch is not None:  # else nothing changed: the vector shows it already
            self._events.emit(EV.CMD_LOCK, t_ns, what=ch.what, text=ch.text)
            self._publish()  # the lock and its holder's ARM ended (Authority.expire)

    def _publish(self) -> None:
        """The authority's whole state into the vector (what
        :func:`~zplatform.control.authority.read_lock_state` reads back: a
        console's verdicts, a standby's or a restarted CN's :meth:`adopt`)."""
        auth = self._auth
        assert auth is not None
        self._h_lock_holder.set(auth.holder + 1)
        self._h_lock_station.set(auth.station + 1)
        self._h_lock_until.set(auth.until_ns)
        self._h_approvals.set(min(auth.approvals(), 255))
        self._h_arm_open.set(max(auth.arm_seq, 0))
        self._h_arm_operator.set(auth.arm_operator + 1)
        self._h_arm_open_ns.set(auth.arm_t_ns if auth.arm_seq >= 0 else 0)
        self._h_arm_approvers.set(auth.approvers)

    def _authorize(
        self, data: bytes | bytearray | memoryview, t_ns: int
    ) -> Identity | tuple[int, str]:
        """Who sent the request in ``data`` (its region data), checked, and
        whether the authority lets its command go on; else ``(status, detail)``."""
        auth = self._auth
        assert auth is not None
        try:
            op = int(self._f_op.unpack_from(data)[0])
            st = int(self._f_st.unpack_from(data)[0])
            cmd = int(self._f_cmd.unpack_from(data)[0])
            target = int(self._f_elem.unpack_from(data)[0])
            ref = int(self._f_ref.unpack_from(data)[0])
        except struct.error:
            return (
                CommandStatus.REJECTED_OPERATOR_UNKNOWN,
                "a request too short to name its operator",
            )
        mv = memoryview(data)
        o, s_ = self._op_tag_at, self._st_tag_at
        tb = _authority.TAG_BYTES
        who = auth.identify(op, st, mv[:o], mv[o : o + tb], mv[s_ : s_ + tb])
        if not isinstance(who, Identity):
            return who
        # Its tags verified: it was genuinely that station, whatever the
        # authority's verdict (a lease renewal, a refused request included).
        self._h_heard[who.station].set(t_ns)
        why = auth.check(who, cmd, t_ns, target=target, ref=ref)
        if why is not None:
            return why[0], f"{auth.who(*who)}: {why[1]}"
        return who

    def _refuse(self, status: int, t_ns: int, name: str, seq: int, detail: str) -> None:
        """Refuse a request by the authority (operator, station, lock,
        two-person) without consuming its number: counted in
        ``cn_cmd_rejects`` and ``cn_auth_refused``, shown in
        ``cn_cmd_reject_status``/``_seq``; evented at most once a second (a
        peer holding one operator's key cannot flood the event stream).
        The CN's intake admitted its number, so no request can use it again:
        one numbered just after an open ARM's chain (the ARM's or its last
        approval's number) moves the chain on, as an approval does, so the
        armed command still follows it (ARM n, another station's refused
        request n+1, APPROVE n+2, the command n+3). It confirms nothing: the
        command must still be the ARM's operator's, inside its window."""
        self._h_rejects.bump()
        self._h_reject_status.set(status)
        self._h_reject_seq.set(seq)
        self._h_auth_refused.bump()
        if self._arm_seq >= 0 and seq == self._arm_seq + 1:
            self._armed_at(seq, self._arm_t_ns)
        last = self._refusal_t
        if last is not None and 0 <= t_ns - last < _REFUSAL_EVENT_NS:
            self._refusals_quiet += 1
            return
        quiet, self._refusals_quiet, self._refusal_t = self._refusals_quiet, 0, t_ns
        more = f" (and {quiet} more refused in the second before)" if quiet else ""
        self._emit_rejected(status, t_ns, name, seq, detail + more)

    def adopt(self) -> None:
        """Take up the handler's state from the Data Vector (a takeover, or a
        restart's resume from its recorder's frame:
        :meth:`zplatform.control.loop.ControlLogic.adopt`): the pending command
        (``cn_cmd``), the last number (``cn_cmd_seq``), in a redundant or
        recording mission the last ARM (``cn_arm_seq``, ``cn_arm_t_ns``), and with
        command authority the lock and the ARM open for approvals with its
        approvals (:func:`~zplatform.control.authority.read_lock_state`)."""
        self._active = self._h_cmd.get() != 0
        self._last_seq = int(self._h_seq.get())
        if self._h_arm_seq is not None and self._h_arm_t is not None:
            seq = int(self._h_arm_seq.get())
            self._arm_seq = seq if seq else -1
            self._arm_t_ns = int(self._h_arm_t.get())
        if self._auth is not None:
            # The lock, and an ARM open for approvals with the approvals given:
            # the new commander resumes them (docs/architecture.md#failover).
            self._auth.adopt(read_lock_state(self._dv))

    def _armed_at(self, seq: int, t_ns: int) -> None:
        self._arm_seq = seq
        self._arm_t_ns = t_ns
        if self._h_arm_seq is not None and self._h_arm_t is not None:
            self._h_arm_seq.set(max(seq, 0))
            self._h_arm_t.set(t_ns)

    @property
    def active(self) -> bool:
        """Whether an accepted command is in ``cn_cmd`` this loop."""
        return self._active

    @property
    def last_seq(self) -> int:
        """The highest request number seen (0 before the first request)."""
        return self._last_seq

    def step(self, new_request: bool, t_ns: int) -> None:
        """One loop, before the state machine's step: settle last loop's
        pending command (module doc), then handle the request the runtime
        applied this loop (``new_request``), one :meth:`admit` let through:
        its number is not checked again here. Never raises."""
        if self._active:
            sm = self._sm
            # Pending until a transition consumed it, or a step left the state
            # unchanged (that state does not handle it). A state change by
            # another transition keeps it for the new state's next step.
            if sm is None or sm.consumed_cmd or not sm.changed:
                self._h_cmd.set(0)
                self._active = False
        auth = self._auth
        if auth is not None:
            self._tick(t_ns)
        if not new_request or not self._has_ground:
            return
        cmd = self._g_cmd.get()
        seq = self._g_seq.get()
        name = CMD_NAMES[cmd] if cmd < _N_CMDS else f"code {cmd}"
        who: Identity | None = None
        if auth is not None:
            # Checked again on the applied bytes (admit checked the frame):
            # the same rules, so it passes unless the loop's time ended a lease.
            r = self._authorize(self._g_region, t_ns)
            if not isinstance(r, Identity):
                self._refuse(r[0], t_ns, name, seq, r[1])
                return
            who = r
        self._last_seq = seq
        status, detail = self._validate(cmd, seq, t_ns, who)
        self._h_seq.set(seq)
        self._h_status.set(status)
        if auth is not None and who is not None:
            self._h_cmd_operator.set(who.operator + 1)
            detail += f" by {auth.who(*who)}"
            if status == CommandStatus.ACCEPTED and cmd not in _LOCK_CMDS:
                ch = auth.apply(who, cmd, t_ns, seq=seq)
                if ch is not None:
                    self._events.emit(EV.CMD_LOCK, t_ns, what=ch.what, text=ch.text)
            self._publish()
        if status == CommandStatus.ACCEPTED and cmd in _LOCK_CMDS:
            self._events.emit(EV.CMD_ACCEPTED, t_ns, name=name, seq=seq, detail=detail)
            return
        if status == CommandStatus.ACCEPTED:
            if self._active:
                prev = CMD_NAMES[self._h_cmd.get()]
                self._events.emit(EV.CMD_SUPERSEDED, t_ns, name=prev, by=name)
            self._h_cmd.set(cmd)
            self._active = True
            self._events.emit(EV.CMD_ACCEPTED, t_ns, name=name, seq=seq, detail=detail)
        else:
            self._emit_rejected(status, t_ns, name, seq, detail)

    def reject(
        self, status: int, t_ns: int, *, name: str = "request", seq: int = 0, detail: str = ""
    ) -> None:
        """Refuse a request without consuming a number: counted in
        ``cn_cmd_rejects``, reason in ``cn_cmd_reject_status``, its number in
        ``cn_cmd_reject_seq`` (so the ground can tell its request was
        refused), an event; ``cn_cmd_seq`` and ``cn_cmd_status`` keep the
        last real verdict (so a replayed or forged frame cannot disturb the
        operator's numbering). Also what the loop calls for a request frame
        that fails authentication, with ``seq`` 0: the number of a frame
        that is not authentic cannot be trusted."""
        self._h_rejects.bump()
        self._h_reject_status.set(status)
        self._h_reject_seq.set(seq)
        self._emit_rejected(status, t_ns, name, seq, detail)

    def count_refused(self, n: int, status: int, seq: int) -> None:
        """Count ``n`` requests the CN's intake refused as they arrived
        (:class:`zplatform.control.intake.RequestIntake`: bad tags, other runs,
        numbers not above the last): as :meth:`reject` does, without an
        event each (the loop reports them together): ``cn_cmd_rejects``
        grows by ``n``, ``cn_cmd_reject_status``/``cn_cmd_reject_seq`` show
        ``status``/``seq`` (the highest number refused; ``REJECTED_AUTH`` and
        0 when only bad tags came)."""
        self._h_rejects.bump(n)
        self._h_reject_status.set(status)
        self._h_reject_seq.set(seq)

    def _emit_rejected(self, status: int, t_ns: int, name: str, seq: int, detail: str) -> None:
        self._events.emit(
            EV.CMD_REJECTED,
            t_ns,
            name=name,
            seq=seq,
            status=CommandStatus(status).name,
            detail=detail,
        )

    def refusal(self, epoch: int, seq: int) -> tuple[int, str] | None:
        """``(status, detail)`` when a request numbered ``seq`` for CN run
        ``epoch`` is refused without consuming a number
        (:func:`request_refusal_detail`: epoch, then number), else None.
        Changes nothing."""
        return request_refusal_detail(epoch, seq, self._h_epoch.get(), self._last_seq)

    def admit(
        self,
        epoch: int,
        seq: int,
        t_ns: int,
        name: str = "request",
        data: bytes | bytearray | memoryview | None = None,
    ) -> bool:
        """Whether the request ``name`` numbered ``seq`` for CN run ``epoch``
        may be taken (:meth:`refusal`); when not, it is rejected now
        (:meth:`reject`: counted, evented, no number consumed). With command
        authority and the request's region ``data``, also its operator,
        station and the lock (:class:`~zplatform.control.authority.Authority`;
        refused without consuming a number, evented at most once a second):
        a request the authority refuses never displaces another in the same
        loop. The runtime admits every request frame before it picks the
        one to apply (:meth:`step`'s ``new_request``). Never raises."""
        refused = self.refusal(epoch, seq)
        if refused is not None:
            self.reject(refused[0], t_ns, name=name, seq=seq, detail=refused[1])
            return False
        if self._auth is not None and data is not None:
            self._tick(t_ns)
            r = self._authorize(data, t_ns)
            if not isinstance(r, Identity):
                self._refuse(r[0], t_ns, name, seq, r[1])
                return False
        return True

    def _validate(
        self, cmd: int, seq: int, t_ns: int, who: Identity | None = None
    ) -> tuple[int, str]:
        """``(status, detail)``; performs the command when it is accepted.
        ``who``: the request's checked operator (with command authority)."""
        if cmd == Command.NONE or cmd >= _N_CMDS:
            return CommandStatus.REJECTED_UNKNOWN, f"{cmd} is not a command code"
        if cmd in _LOCK_CMDS:
            return self._lock(cmd, seq, t_ns, who)
        state = self._h_state.get()
        if state < len(self._allowed) and not self._allowed[state][cmd]:
            return (
                CommandStatus.REJECTED_NOT_ALLOWED,
                f"not allowed in state {self._states[state]}",
            )
        if self._fault_refuses[cmd]:
            fault = int(self._h_fault.get())
            if fault != Fault.NONE:
                names = self._fault_names
                may = self._may_write[self._h_fault.spec.index]
                how = (
                    "clear cn_fault first (WRITE cn_fault NONE)"
                    if state < len(may) and may[state]
                    else f"no WRITE may clear cn_fault in {self._states[state]}: restart the "
                    "control node (zplatform check: fault_never_cleared)"
                )
                return (
                    CommandStatus.REJECTED_NOT_ALLOWED,
                    f"a fault is latched ({names[fault] if fault < len(names) else fault}): {how}",
                )
        slot = self.params.slot(self._g_elem.get()) if cmd == Command.PRM_SET else None
        hazardous = (
            self._hazardous[cmd]
            or (cmd == Command.WRITE and self._protected_write())
            or (slot is not None and slot.hazardous)
        )
        if hazardous:
            armed = self._arm_seq == seq - 1 and 0 <= t_ns - self._arm_t_ns <= ARM_WINDOW_NS
            approved = True
            auth = self._auth
            if auth is not None:
                # The ARM must be this operator's own, and a two-person
                # command's ARM approved by a second operator.
                armed = armed and who is not None and auth.arm_operator == who.operator
                if self._two_person(cmd, slot):
                    approved = auth.approved()
                auth.disarm()
            self._armed_at(-1, self._arm_t_ns)
            if not armed:
                return (
                    CommandStatus.REJECTED_NOT_ARMED,
                    f"hazardous: needs an accepted ARM #{seq - 1} within the last "
                    f"{ARM_WINDOW_NS // 1_000_000_000} s"
                    + (" by the same operator" if auth is not None else ""),
                )
            if not approved:
                return (
                    CommandStatus.REJECTED_NOT_APPROVED,
                    "two-person (ground.two_person): its ARM has no APPROVE by a second "
                    "operator with an approving role",
                )
        if cmd == Command.WRITE:
            return self._write(state)
        if cmd == Command.PRM_SET:
            return self._prm_set(slot, state)
        if cmd == Command.PRM_SAVE:
            return self._prm_save(seq, t_ns)
        if cmd == Command.HOLD or cmd == Command.RESUME:
            if self._sm is None:
                return CommandStatus.REJECTED_NOT_ALLOWED, "no state machine to hold or resume"
            changed = self._sm.hold(t_ns) if cmd == Command.HOLD else self._sm.resume(t_ns)
            if not changed:
                return CommandStatus.ACCEPTED, " (no change: already so)"
        elif cmd == Command.ARM:
            self._armed_at(seq, t_ns)
        return CommandStatus.ACCEPTED, ""

    def _two_person(self, cmd: int, slot: ParamSlot | None) -> bool:
        if self._two_cmd[cmd]:
            return True
        if cmd == Command.WRITE or slot is not None:
            idx = self._g_elem.get()
            return idx < len(self._two_elem) and self._two_elem[idx]
        return False

    def _lock(self, cmd: int, seq: int, t_ns: int, who: Identity | None) -> tuple[int, str]:
        """LOCK, RELEASE, HANDOVER, TAKEOVER, APPROVE: checked by :meth:`_authorize`."""
        auth = self._auth
        if auth is None or who is None:
            return (
                CommandStatus.REJECTED_NOT_ALLOWED,
                "no command lock in this mission (a `ground:` section without single_operator)",
            )
        ch = auth.apply(who, cmd, t_ns, seq=seq, target=self._g_elem.get())
        if cmd == Command.APPROVE and self._arm_seq == seq - 1:
            # The armed command may follow its approval (ARM n, APPROVE n+1, cmd n+2).
            self._armed_at(seq, self._arm_t_ns)
        if ch is not None:
            self._events.emit(EV.CMD_LOCK, t_ns, what=ch.what, text=ch.text)
        return CommandStatus.ACCEPTED, ""

    def _protected_write(self) -> bool:
        idx = self._g_elem.get()
        return idx < len(self._protected) and self._protected[idx]

    def _write(self, state: int) -> tuple[int, str]:
        idx = self._g_elem.get()
        value = self._g_value.get()
        target = self._targets[idx] if idx < len(self._targets) else None
        if target is None:
            if idx < len(self._names_by_index):
                name = self._names_by_index[idx]
                if name in self._param_names:
                    why = "it is a parameter: set it with PRM_SET"
                else:
                    why = "commands.writable does not list it (a WRITE sets only those)"
                return (
                    CommandStatus.REJECTED_BAD_ARGUMENT,
                    f"element {name} is not writable: {why}",
                )
            return CommandStatus.REJECTED_BAD_ARGUMENT, f"no element with index {idx}"
        may = self._may_write[idx]
        if state < len(may) and not may[state]:
            allowed = [s for s, ok in zip(self._states, may, strict=False) if ok]
            return (
                CommandStatus.REJECTED_NOT_ALLOWED,
                f"a WRITE of {target.spec.name} is not allowed in state {self._states[state]} "
                f"(only in {', '.join(allowed)}: commands.write_states, hazardous_outputs)",
            )
        v, reason = _write_value(target.spec, value)
        if reason:
            return CommandStatus.REJECTED_BAD_ARGUMENT, reason
        target.set(v)
        shown = target.spec.name_of(v) if target.spec.enum is not None else repr(v)
        return CommandStatus.ACCEPTED, f" ({target.spec.name} = {shown})"

    def _prm_set(self, slot: ParamSlot | None, state: int) -> tuple[int, str]:
        if slot is None:
            idx = self._g_elem.get()
            if not self.params.slots:
                return CommandStatus.REJECTED_NOT_ALLOWED, "this mission has no parameters"
            what = (
                f"element {self._names_by_index[idx]}"
                if idx < len(self._names_by_index)
                else f"index {idx}"
            )
            return CommandStatus.REJECTED_BAD_ARGUMENT, f"{what} is not a parameter"
        v, reason = _write_value(slot.handle.spec, self._g_value.get())
        if reason:
            return CommandStatus.REJECTED_BAD_ARGUMENT, reason
        if state < len(slot.allowed) and not slot.allowed[state]:
            allowed = [s for s, ok in zip(self._states, slot.allowed, strict=False) if ok]
            return (
                CommandStatus.REJECTED_PARAM_STATE,
                f"parameter {slot.name} may not change in state {self._states[state]} "
                f"(only in {', '.join(allowed) or 'no state'})",
            )
        if not slot.in_bounds(v):
            return (
                CommandStatus.REJECTED_OUT_OF_BOUNDS,
                f"{v!r} is outside {slot.name}'s bounds {slot.bounds_text()}",
            )
        was = slot.handle.get()
        slot.handle.set(v)
        self.params.changed()
        now = slot.handle.get()
        return CommandStatus.ACCEPTED, f" ({slot.name} = {slot.text(now)}, was {slot.text(was)})"

    def _prm_save(self, seq: int, t_ns: int) -> tuple[int, str]:
        params = self.params
        if not params.slots:
            return CommandStatus.REJECTED_NOT_ALLOWED, "this mission has no parameters"
        busy = params.saving
        if busy:
            return (
                CommandStatus.REJECTED_BUSY,
                f"PRM_SAVE #{busy} is still being written; send it again when "
                "cn_prm_save_status is no longer PENDING",
            )
        params.request_save(seq, t_ns)
        return CommandStatus.ACCEPTED, " (queued: cn_prm_save_status tells when it is written)"
