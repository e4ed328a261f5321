"""The mission state machine (the thesis, ch. 4.5), sans-IO.

A state has a timed *action sequence* (writes of Data Vector elements at
given seconds into the state) and an ordered list of *transitions*, each
firing on a condition ``element op value`` (``cn_cmd == LAUNCH``,
``tank_pressure > 30.5``, ``cn_fault != NONE``) or after ``after_s`` seconds
in the state. The current state is ``cn_state``; the time in it
``cn_time_in_state_ns``; HOLD freezes that time, RESUME continues it.

Contract: :class:`StateMachine` resolves everything at construction (handles,
comparison functions, converted values); :meth:`StateMachine.step` runs on
the CN's loop thread once per loop, fires at most one transition (ABORT-class
first, then a monitor's request, then config order), runs the due actions of
the (possibly new) state at most once per visit, never raises for a valid
config and allocates only the event of a state change. :func:`check_config`
raises :class:`~zplatform.errors.ConfigError` with the YAML path of the first
bad field (a cycle of ``after_s: 0`` transitions included).

The step in order: docs/architecture.md#the-loop (the state machine).
"""

from __future__ import annotations

import difflib
import logging
import math
import operator
import re
import struct
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..config import CMD_NAMES, element_spec, platform_elements
from ..config.types import ScalarType
from ..core.events import EV, EventLog
from ..errors import ConfigError, StateMachineError

if TYPE_CHECKING:
    from ..config import ElementConfig, Mission, TransitionConfig
    from ..core.datavector import DataVector

__all__ = [
    "StateMachine",
    "check_config",
    "check_structure",
    "config_value",
    "logic_writable",
    "platform_element_names",
    "unreachable_states",
    "why_not_writable",
]

log = logging.getLogger("zplatform.statemachine")

_STATE_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_FLOAT_WORDS = ("inf", "+inf", "-inf", "infinity", "+infinity", "-infinity", "nan")
_F32 = struct.Struct("<f")

OPS: dict[str, Callable[[Any, Any], bool]] = {
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}
_EQUALITY_OPS = ("==", "!=")

# Platform elements that CN logic may write: a controller's mode is how the
# state machine enables and safes controllers (thesis 4.6.1), and cn_fault
# is cleared by writing NONE to it (thesis 4.11.1).
_LOGIC_WRITABLE_PLATFORM = ("cn_fault",)


# ---------------------------------------------------------------------------
# element tables shared with the command handler


def platform_element_names(mission: Mission) -> frozenset[str]:
    """Names of every element the platform adds, modes included
    (docs/architecture.md#data-vector)."""
    return frozenset(e.name for es in platform_elements(mission).values() for e in es)


def _received_regions(mission: Mission) -> frozenset[str]:
    """Regions the CN receives from peers: overwritten on every sync."""
    return frozenset(r for r in mission.region_names() if r.endswith("_to_cn"))


def logic_writable(mission: Mission) -> frozenset[str]:
    """Elements CN logic may write (state-machine actions, WRITE commands).

    Every element of the CN's own regions (``cn``, ``cn_to_dnX``) except the
    platform's bookkeeping (``cn_state``, ``cn_loop``, counters, ...);
    controller modes (``<name>_mode``) and ``cn_fault`` are writable.
    Elements of received regions (``dnX_to_cn``, ``gn_to_cn``) are not: the
    next sync would overwrite the write.
    """
    platform = platform_element_names(mission)
    modes = {f"{c.name}_mode" for c in mission.controllers}
    received = _received_regions(mission)
    out: set[str] = set()
    for region, elements in mission.regions.items():
        if region in received:
            continue
        for e in elements:
            if e.name not in platform or e.name in modes or e.name in _LOGIC_WRITABLE_PLATFORM:
                out.add(e.name)
    return frozenset(out)


def why_not_writable(mission: Mission, region: str, name: str) -> str:
    """Why CN logic may not write element ``name`` of ``region`` (for error messages)."""
    if any(p.name == name for p in mission.params):
        return (
            f"element {name!r} is a parameter: it changes only by an accepted PRM_SET "
            "(and at the control node's start, from its parameter file)"
        )
    if region in _received_regions(mission):
        peer = region[: -len("_to_cn")]
        return (
            f"element {name!r} is received from {peer} every loop (region {region}); "
            "a write on the CN would be overwritten"
        )
    return f"element {name!r} is maintained by the platform and cannot be written"


def _element_table(mission: Mission) -> dict[str, tuple[str, ElementConfig]]:
    return {e.name: (r, e) for r, es in mission.regions.items() for e in es}


def _no_element(name: str, table: dict[str, tuple[str, ElementConfig]]) -> str:
    close = difflib.get_close_matches(name, list(table), n=3)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    return f"no element named {name!r} in the Data Vector{hint}"


def config_value(
    e: ElementConfig, scalar: ScalarType, v: object, *, allow_nan: bool = True
) -> int | float | bool:
    """Convert a YAML value for element ``e`` to what the element stores.

    Enums take a name or an index, bools ``true``/``false`` (or 0/1), ints
    an integral number in range, floats a number or ``inf``/``-inf``/``nan``
    spelled out (``nan`` only when ``allow_nan``). A value for an ``f32``
    element is rounded to ``f32``, so it compares equal to what is stored.
    Raises ValueError with a message saying what was expected.
    """
    if e.enum is not None:
        if isinstance(v, str):
            if v in e.enum:
                return e.enum.index(v)
            raise ValueError(f"{v!r} is not one of {e.name}'s names {e.enum}")
        if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < len(e.enum):
            return v
        raise ValueError(f"expected one of {e.name}'s names {e.enum}, got {v!r}")
    if scalar.kind == "bool":
        if isinstance(v, bool):
            return v
        if isinstance(v, int) and v in (0, 1):
            return bool(v)
        raise ValueError(f"expected true or false for bool element {e.name!r}, got {v!r}")
    if isinstance(v, str):
        if scalar.kind == "float" and v.strip().lower() in _FLOAT_WORDS:
            v = float(v)
        else:
            raise ValueError(f"expected a number for {scalar.name} element {e.name!r}, got {v!r}")
    if isinstance(v, float) and math.isnan(v) and not allow_nan:
        raise ValueError("nan compares unequal to everything; the condition could never hold")
    if not scalar.fits(v):
        rng = f" (range {scalar.lo}..{scalar.hi})" if scalar.kind == "int" else ""
        raise ValueError(f"{v!r} does not fit {scalar.name} element {e.name!r}{rng}")
    assert isinstance(v, int | float)
    if scalar.kind == "int":
        return int(v)
    f = float(v)
    if scalar.size == 4:
        f = _F32.unpack(_F32.pack(f))[0]
    return f


# ---------------------------------------------------------------------------
# configuration checks


def check_structure(mission: Mission) -> None:
    """The checks that need no Data Vector: states, names, targets, shapes.

    Raises :class:`ConfigError` with the YAML path. Safe to call before the
    platform elements are added (``cn_state`` is built from these states).
    """
    sm = mission.state_machine
    if sm is None:
        return
    if not sm.states:
        raise ConfigError("a state machine needs at least one state", "$.state_machine.states")
    for name in sm.states:
        if not _STATE_NAME_RE.fullmatch(name):
            raise ConfigError(
                f"state name {name!r} is not an identifier (letters, digits, _)",
                f"$.state_machine.states.{name}",
            )
    states = list(sm.states)
    if sm.initial not in sm.states:
        raise ConfigError(
            f"initial state {sm.initial!r} is not a state; states: {states}",
            "$.state_machine.initial",
        )
    for name, st in sm.states.items():
        for i, t in enumerate(st.transitions):
            w = f"$.state_machine.states.{name}.transitions[{i}]"
            _check_transition_shape(t, w)
            if t.to not in sm.states:
                raise ConfigError(
                    f"target state {t.to!r} is not a state; states: {states}", f"{w}.to"
                )
    _check_zero_time_cycles(mission)


def _check_zero_time_cycles(mission: Mission) -> None:
    """Refuse a cycle of transitions that fire without time passing (``after_s: 0``).

    Such transitions always hold, so a cycle of them would change state on
    every loop forever (A -> B -> A ...) and never run a state's actions with
    time in it. A condition transition can be true forever too, but whether
    it is depends on the data: only the unconditional ones are refused.
    ConfigError names the states of the cycle, at the transition closing it.
    """
    sm = mission.state_machine
    assert sm is not None
    # The first zero-time transition out of each state (one per state is all
    # a cycle needs: the state machine takes the first one that holds).
    edges: dict[str, tuple[str, int]] = {}
    for name, st in sm.states.items():
        for i, t in enumerate(st.transitions):
            if t.after_s == 0:
                edges[name] = (t.to, i)
                break
    done: set[str] = set()
    for start in edges:
        path: list[str] = []
        on_path: set[str] = set()
        node: str | None = start
        while node is not None and node in edges and node not in done:
            if node in on_path:
                cycle = [*path[path.index(node) :], node]
                last = cycle[-2]
                raise ConfigError(
                    "transitions with after_s: 0 form a cycle "
                    f"{' -> '.join(cycle)}: the state would change on every loop without end",
                    f"$.state_machine.states.{last}.transitions[{edges[last][1]}]",
                )
            path.append(node)
            on_path.add(node)
            node = edges[node][0]
        done.update(path)


def _check_transition_shape(t: TransitionConfig, w: str) -> None:
    parts = {"element": t.element, "op": t.op, "value": t.value}
    given = [k for k, v in parts.items() if v is not None]
    if t.after_s is not None:
        if given:
            raise ConfigError(
                "a transition has either a condition (element, op, value) or after_s, "
                f"not both; got after_s and {', '.join(given)}",
                w,
            )
        return
    if not given:
        raise ConfigError("a transition needs a condition (element, op, value) or after_s", w)
    for k, v in parts.items():
        if v is None:
            raise ConfigError(
                f"a transition condition needs element, op and value; `{k}` is missing",
                f"{w}.{k}",
            )


def check_config(mission: Mission, *, warn: bool = True) -> None:
    """Check the ``state_machine`` section against the mission's Data Vector.

    Rules (each failure raises :class:`ConfigError` naming the YAML path):

    * at least one state; state names are identifiers; ``initial`` is a
      state (thesis 4.5.1: no duplicate states is enforced by the mapping);
    * a transition has exactly one of a condition (``element``, ``op``,
      ``value``, all three) or ``after_s``; its target ``to`` is a state;
      ``after_s: 0`` transitions form no cycle;
    * an action's or condition's element exists in the Data Vector;
    * a condition's element is a scalar; bools and enums compare only with
      ``==`` and ``!=``; the value fits the element's type (enum names or
      indices, ``true``/``false``, an int in range, a number; never ``nan``);
    * an action writes an element CN logic may write (:func:`logic_writable`)
      with a value that fits its type (an array element gets every item set).

    With ``warn``, states no transition path reaches from the initial state
    are logged as warnings (they are not errors: a state may be kept for a
    later revision of the mission).
    """
    sm = mission.state_machine
    if sm is None:
        return
    check_structure(mission)
    for i, c in enumerate(sm.priority):
        if c not in CMD_NAMES or c == "NONE":
            raise ConfigError(
                f"{c!r} is not a command; commands: {', '.join(CMD_NAMES[1:])}",
                f"$.state_machine.priority[{i}]",
            )
    table = _element_table(mission)
    writable = logic_writable(mission)
    for name, st in sm.states.items():
        base = f"$.state_machine.states.{name}"
        for i, a in enumerate(st.actions):
            w = f"{base}.actions[{i}]"
            if a.element not in table:
                raise ConfigError(_no_element(a.element, table), f"{w}.element")
            region, e = table[a.element]
            if a.element not in writable:
                raise ConfigError(
                    why_not_writable(mission, region, a.element) + " by an action",
                    f"{w}.element",
                )
            scalar, _ = element_spec(e)
            try:
                config_value(e, scalar, a.value)
            except ValueError as exc:
                raise ConfigError(str(exc), f"{w}.value") from None
        for i, t in enumerate(st.transitions):
            if t.after_s is not None:
                continue
            w = f"{base}.transitions[{i}]"
            assert t.element is not None and t.op is not None
            if t.element not in table:
                raise ConfigError(_no_element(t.element, table), f"{w}.element")
            _, e = table[t.element]
            scalar, count = element_spec(e)
            if count:
                raise ConfigError(
                    f"element {t.element!r} is an array ({e.type}); a condition compares a scalar",
                    f"{w}.element",
                )
            if t.op not in _EQUALITY_OPS and (e.enum is not None or scalar.kind == "bool"):
                kind = "an enum" if e.enum is not None else "a bool"
                raise ConfigError(
                    f"`{t.op}` on {kind} element {t.element!r}; bools and enums compare "
                    "only with == and !=",
                    f"{w}.op",
                )
            try:
                config_value(e, scalar, t.value, allow_nan=False)
            except ValueError as exc:
                raise ConfigError(str(exc), f"{w}.value") from None
    if warn:
        for s in unreachable_states(mission):
            log.warning(
                "state %r cannot be reached from the initial state %r - at `$.state_machine."
                "states.%s`",
                s,
                sm.initial,
                s,
            )


def unreachable_states(mission: Mission) -> list[str]:
    """States no chain of transitions reaches from the initial one, in config
    order; a monitor's ``transition`` response (:mod:`zplatform.control.monitors`) is
    a transition from each state it runs in."""
    sm = mission.state_machine
    if sm is None or sm.initial not in sm.states:
        return []
    requested = [
        (set(m.states) if m.states is not None else None, m.to)
        for m in mission.monitors
        if m.response == "transition" and m.to is not None
    ]
    seen = {sm.initial}
    todo = [sm.initial]
    while todo:
        name = todo.pop()
        st = sm.states.get(name)
        if st is None:
            continue
        targets = [t.to for t in st.transitions]
        targets += [to for states, to in requested if states is None or name in states]
        for to in targets:
            if to not in seen:
                seen.add(to)
                todo.append(to)
    return [s for s in sm.states if s not in seen]


# ---------------------------------------------------------------------------
# run time


class _Transition:
    """One resolved transition. ``after_ns < 0`` means a condition one."""

    __slots__ = ("after_ns", "get", "on_cmd", "op", "src", "target", "value", "why")

    def __init__(
        self,
        target: int,
        src: str,
        why: str,
        after_ns: int = -1,
        get: Callable[[], Any] | None = None,
        op: Callable[[Any, Any], bool] = operator.eq,
        value: Any = None,
    ) -> None:
        self.target = target
        self.on_cmd = False  # tests cn_cmd: firing consumes the pending command
        # The state_change event's arguments, built once at configure time.
        self.src = src
        self.why = why
        self.after_ns = after_ns
        self.get = get
        self.op = op
        self.value = value


class _Action:
    __slots__ = ("at_ns", "set", "value")

    def __init__(self, at_ns: int, set: Callable[[Any], None], value: Any) -> None:
        self.at_ns = at_ns
        self.set = set
        self.value = value


def _fmt_s(seconds: float) -> str:
    return f"{seconds:g} s"


class StateMachine:
    """The mission state machine on the CN's Data Vector (see module doc).

    ``dv`` must be the CN's Data Vector (it holds ``cn_state`` and every
    element the transitions and actions name). Construction runs
    :func:`check_config` (raises :class:`ConfigError` for an invalid
    mission) and resolves everything the step needs. A mission without a
    ``state_machine`` section has the single state ``IDLE`` and does nothing
    but keep the time in it.

    Not thread-safe: the CN loop thread calls :meth:`step`, :meth:`hold` and
    :meth:`resume` (the command handler calls the last two).
    """

    __slots__ = (
        "_actions",
        "_entered_ns",
        "_events",
        "_forced",
        "_forced_why",
        "_h_holding",
        "_h_state",
        "_h_tis",
        "_held_ns",
        "_hold_start",
        "_initial",
        "_n_prio",
        "_next_action",
        "_started",
        "_state",
        "_tis",
        "_transitions",
        "changed",
        "consumed_cmd",
        "states",
    )

    def __init__(self, mission: Mission, dv: DataVector, events: EventLog) -> None:
        check_config(mission, warn=False)
        self._events = events
        self._h_state = dv.handle("cn_state")
        self._h_tis = dv.handle("cn_time_in_state_ns")
        # A redundant mission mirrors whether a HOLD is in effect (adopt()).
        self._h_holding = dv.handle("cn_holding") if "cn_holding" in dv.layout.elements else None
        names = self._h_state.spec.enum
        assert names is not None, "cn_state is an enum"
        self.states: tuple[str, ...] = names
        index = {n: i for i, n in enumerate(names)}
        table = _element_table(mission)
        sm = mission.state_machine
        transitions: list[tuple[_Transition, ...]] = []
        n_prio: list[int] = []
        actions: list[tuple[_Action, ...]] = []
        # cn_cmd == X compares against X's code (config_value resolves names).
        priority = sm.priority if sm is not None else []
        prio = {(True, CMD_NAMES.index(c)): i for i, c in enumerate(priority)}
        self.changed = False
        """Whether the last :meth:`step` changed the state."""
        self.consumed_cmd = False
        """Whether the transition the last :meth:`step` fired tests ``cn_cmd``."""
        for name in names:
            st = sm.states[name] if sm is not None else None
            trs: list[_Transition] = []
            acts: list[_Action] = []
            if st is not None:
                for t in st.transitions:
                    target = index[t.to]
                    if t.after_s is not None:
                        why = f"after {_fmt_s(t.after_s)}"
                        trs.append(_Transition(target, name, why, after_ns=round(t.after_s * 1e9)))
                        continue
                    assert t.element is not None and t.op is not None
                    e = table[t.element][1]
                    value = config_value(e, element_spec(e)[0], t.value, allow_nan=False)
                    shown = t.value if isinstance(t.value, str) else repr(t.value).lower()
                    why = f"{t.element} {t.op} {shown}"
                    get = dv.handle(t.element).get
                    tr = _Transition(target, name, why, get=get, op=OPS[t.op], value=value)
                    tr.on_cmd = t.element == "cn_cmd"
                    trs.append(tr)
                for a in sorted(st.actions, key=lambda a: a.at_s):  # stable: config order ties
                    h = dv.handle(a.element)
                    e = table[a.element][1]
                    v = config_value(e, h.spec.scalar, a.value)
                    acts.append(_Action(round(a.at_s * 1e9), h.set, v))
            # ABORT-class first (sm.priority order), then config order: an
            # ABORT due in the same loop as a timer or a data transition wins.
            trs.sort(key=lambda tr: prio.get((tr.on_cmd, tr.value), len(prio)))
            transitions.append(tuple(trs))
            n_prio.append(sum(1 for tr in trs if (tr.on_cmd, tr.value) in prio))
            actions.append(tuple(acts))
        self._transitions = tuple(transitions)
        # How many of each state's transitions are ABORT-class: a requested
        # transition (request()) comes after them.
        self._n_prio = tuple(n_prio)
        self._forced = -1
        self._forced_why = ""
        self._actions = tuple(actions)
        initial = sm.initial if sm is not None else names[0]
        self._initial = index[initial]
        self._state = self._initial
        self._started = False
        self._entered_ns = 0
        self._held_ns = 0
        self._hold_start: int | None = None
        self._next_action = 0
        self._tis = 0

    # -- queries -----------------------------------------------------------
    @property
    def state(self) -> str:
        """The current state's name (the initial state before the first step)."""
        return self.states[self._state]

    @property
    def time_in_state_ns(self) -> int:
        """Time in the current state at the last step, holds excluded."""
        return self._tis

    @property
    def holding(self) -> bool:
        """Whether a HOLD is in effect."""
        return self._hold_start is not None

    # -- the loop ----------------------------------------------------------
    def _time_in_state(self, t_ns: int) -> int:
        held = self._held_ns
        if self._hold_start is not None:
            held += t_ns - self._hold_start
        return t_ns - self._entered_ns - held

    def _run_due(self, tis: int) -> None:
        acts = self._actions[self._state]
        i = self._next_action
        n = len(acts)
        while i < n and acts[i].at_ns <= tis:
            a = acts[i]
            a.set(a.value)
            i += 1
        self._next_action = i

    def step(self, t_ns: int) -> None:
        """Advance one loop at time ``t_ns`` (see the module doc for the order).

        Never raises for a mission that passed :func:`check_config`.
        """
        if not self._started:
            self._started = True
            self._entered_ns = t_ns
            self._held_ns = 0
            if self._hold_start is not None:  # held before the first step
                self._hold_start = t_ns
            self._run_due(0)
        tis = self._time_in_state(t_ns)
        self.changed = self.consumed_cmd = False
        forced = self._forced
        trs = self._transitions[self._state]
        if forced >= 0:  # a request: after the ABORT-class transitions, before the rest
            self._forced = -1
            n = self._n_prio[self._state]
            fired = self._first(trs[:n], tis, t_ns) is not None
            if not fired and forced != self._state:
                self._enter(forced, False, t_ns, self.states[self._state], self._forced_why)
                fired = True
            if not fired:
                fired = self._first(trs[n:], tis, t_ns) is not None
            if fired:
                tis = 0
        elif self._first(trs, tis, t_ns) is not None:
            tis = 0
        self._run_due(tis)
        self._tis = tis
        self._h_state.set(self._state)
        self._h_tis.set(tis)
        if self._h_holding is not None:
            self._h_holding.set(self._hold_start is not None)

    def adopt(self, t_ns: int) -> None:
        """Take up the state the Data Vector shows after a step at ``t_ns``
        (``cn_state``, ``cn_time_in_state_ns``, ``cn_holding``): the next
        step continues exactly as the step that wrote it would have
        (:meth:`zplatform.control.loop.ControlLogic.adopt`). Timed actions already
        due at that time in state count as done.

        Raises StateMachineError (nothing taken up) when the vector names no
        state of this machine or a negative time in state: a vector no
        control node of this mission wrote (a damaged recording)."""
        state = int(self._h_state.get())
        tis = int(self._h_tis.get())
        if not 0 <= state < len(self.states) or tis < 0:
            raise StateMachineError(
                f"cannot take up state {state} after {tis} ns in it: this machine has "
                f"{len(self.states)} states ({', '.join(self.states)})"
            )
        self._state = state
        self._started = True
        self._entered_ns = t_ns - tis
        self._held_ns = 0
        holding = self._h_holding is not None and bool(self._h_holding.get())
        self._hold_start = t_ns if holding else None
        acts = self._actions[self._state]
        self._next_action = sum(1 for a in acts if a.at_ns <= tis)
        self._tis = tis
        self._forced = -1
        self.changed = self.consumed_cmd = False

    def _first(self, trs: tuple[_Transition, ...], tis: int, t_ns: int) -> _Transition | None:
        """Fire the first of ``trs`` that holds (if any) and return it."""
        for tr in trs:
            if tr.after_ns >= 0:
                if tis < tr.after_ns:
                    continue
            elif not tr.op(tr.get(), tr.value):  # type: ignore[misc]
                continue
            self._enter(tr.target, tr.on_cmd, t_ns, tr.src, tr.why)
            return tr
        return None

    def _enter(self, target: int, on_cmd: bool, t_ns: int, src: str, why: str) -> None:
        self._state = target
        self.changed = True
        self.consumed_cmd = on_cmd
        self._entered_ns = t_ns
        self._held_ns = 0
        self._next_action = 0
        self._events.emit(EV.STATE_CHANGE, t_ns, src=src, dst=self.states[target], why=why)
        if self._hold_start is not None:
            self._hold_start = None
            self._events.emit(EV.HOLD_ENDED, t_ns)

    def request(self, state: int, why: str) -> None:
        """Ask for a transition to state index ``state`` in the next :meth:`step`
        (a monitor's response, :mod:`zplatform.control.monitors`): it fires after the
        current state's ABORT-class command transitions (``priority``; if one
        fires, the request is dropped: the operator's ABORT wins) and before
        its other transitions, unless the state machine is in ``state``
        already. ``why`` ends the ``state_change`` event. One request per
        step; a later one replaces it."""
        self._forced = state
        self._forced_why = why

    def hold(self, t_ns: int) -> bool:
        """Freeze the time in state from ``t_ns``; False if already holding.

        Timed actions and ``after_s`` transitions wait; condition transitions
        still fire (and end the hold).
        """
        if self._hold_start is not None:
            return False
        self._hold_start = t_ns
        tis = self._time_in_state(t_ns) if self._started else 0
        self._events.emit(EV.HOLD, t_ns, state=self.state, tis_s=tis / 1e9)
        return True

    def resume(self, t_ns: int) -> bool:
        """End a hold at ``t_ns``: the time in state continues where it
        stopped. False if no hold was in effect."""
        if self._hold_start is None:
            return False
        self._held_ns += t_ns - self._hold_start
        self._hold_start = None
        tis = self._time_in_state(t_ns) if self._started else 0
        self._events.emit(EV.RESUME, t_ns, state=self.state, tis_s=tis / 1e9)
        return True
