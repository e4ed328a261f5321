"""Hazardous outputs and their interlocks (``hazardous_outputs``), sans-IO.

A mission names each hazardous output (an igniter, a motor, a valve: a scalar
element a device node drives an actuator from) and the states in which it may
be driven. Two guards keep that rule, each on its own: the control node
refuses a WRITE of the output in any other state (:mod:`zplatform.control.commands`),
and a state-machine action may set it to anything but its safe value only in
its states (:func:`check_config`, at load); and the device node holding it
(:class:`OutputInterlock`, run by :class:`~zplatform.control.loop.DeviceLogic`
between its controllers and its actuators) reads the vehicle's state from
the authenticated trigger it runs (``dnX_state``) and, in a state not the
output's, writes the safe value instead (``dnX_interlocked``, evented at most
once a second). So a control node told (or tricked) into commanding an output
out of its states still cannot drive it.

Contract: :func:`check_config` raises :class:`~zplatform.errors.ConfigError`
naming the YAML path; :class:`OutputInterlock` resolves everything at
construction, and :meth:`~OutputInterlock.apply` allocates nothing while no
output is refused and never raises. See docs/architecture.md#safety-rules.
"""

from __future__ import annotations

import difflib
from typing import TYPE_CHECKING

from ..config import element_spec, interlocked_nodes
from ..core.events import EV, EventLog
from ..errors import ConfigError
from .statemachine import config_value, platform_element_names

if TYPE_CHECKING:
    from ..config import ElementConfig, HazardousOutputConfig, Mission
    from ..core.datavector import DataVector, Handle

__all__ = ["OutputInterlock", "check_config", "output_states", "safe_value"]

_EVENT_NS = 1_000_000_000
"""At most one interlock event a second (loop time)."""


def _states(mission: Mission) -> list[str]:
    sm = mission.state_machine
    return list(sm.states) if sm is not None else ["IDLE"]


def output_states(mission: Mission) -> dict[str, list[str]]:
    """Each hazardous output's element and the states it may be driven in,
    in ``hazardous_outputs`` order. Pure."""
    return {h.element: list(h.states) for h in mission.hazardous_outputs}


def safe_value(e: ElementConfig, h: HazardousOutputConfig) -> int | float | bool:
    """What the element stores as the output's safe value: ``h.safe``, or
    ``false``, 0 or the enum's first name. ValueError when ``h.safe`` does
    not fit the element (:func:`check_config` reports it with its path)."""
    scalar, _ = element_spec(e)
    if h.safe is None:
        return False if scalar.kind == "bool" else 0.0 if scalar.kind == "float" else 0
    return config_value(e, scalar, h.safe, allow_nan=False)


def check_config(mission: Mission) -> None:
    """Check ``hazardous_outputs`` against the Data Vector and the state
    machine; raises ConfigError naming the YAML path:

    * each element exists, is a scalar of the mission's own in region
      ``cn_to_dnX`` or ``dnX_to_cn`` (the device node that drives it), and
      is named once;
    * its states are states, each named once; its ``safe`` value fits;
    * a state-machine action sets it to a value other than its safe value
      only in one of its states (else the control node itself would command
      what the device node refuses).
    """
    outputs = mission.hazardous_outputs
    if not outputs:
        return
    table = {e.name: (r, e) for r, es in mission.regions.items() for e in es}
    platform = platform_element_names(mission)
    states = _states(mission)
    dns = set(interlocked_nodes(mission))
    seen: set[str] = set()
    safe: dict[str, int | float | bool] = {}
    for i, h in enumerate(outputs):
        w = f"$.hazardous_outputs[{i}]"
        if h.element not in table:
            close = difflib.get_close_matches(h.element, list(table), n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ConfigError(
                f"no element named {h.element!r} in the Data Vector{hint}", f"{w}.element"
            )
        region, e = table[h.element]
        dn = region.removeprefix("cn_to_").removesuffix("_to_cn")
        if dn not in dns or h.element in platform:
            raise ConfigError(
                f"element {h.element!r} (region {region}) is not an output a device node "
                "drives: a hazardous output is a mission element of a `cn_to_dnX` or "
                "`dnX_to_cn` region",
                f"{w}.element",
            )
        if h.element in seen:
            raise ConfigError(f"output {h.element!r} is named twice", f"{w}.element")
        seen.add(h.element)
        if element_spec(e)[1]:
            raise ConfigError(
                f"element {h.element!r} is an array ({e.type}); a hazardous output is a scalar",
                f"{w}.element",
            )
        named: set[str] = set()
        for j, s in enumerate(h.states):
            if s not in states:
                raise ConfigError(f"{s!r} is not a state; states: {states}", f"{w}.states[{j}]")
            if s in named:
                raise ConfigError(f"state {s} is named twice", f"{w}.states[{j}]")
            named.add(s)
        try:
            safe[h.element] = safe_value(e, h)
        except ValueError as exc:
            raise ConfigError(str(exc), f"{w}.safe") from None
    sm = mission.state_machine
    if sm is None:
        return
    allowed = output_states(mission)
    for state, st in sm.states.items():
        for j, a in enumerate(st.actions):
            if a.element not in allowed or state in allowed[a.element]:
                continue
            _, e = table[a.element]
            try:
                v = config_value(e, element_spec(e)[0], a.value)
            except ValueError:
                continue  # the state machine's check reports it
            if v != safe[a.element]:
                raise ConfigError(
                    f"state {state} drives hazardous output {a.element!r} to {a.value!r}, but "
                    f"it may be driven only in {', '.join(allowed[a.element]) or 'no state'} "
                    "(hazardous_outputs): set it to its safe value here, or list the state",
                    f"$.state_machine.states.{state}.actions[{j}]",
                )


class OutputInterlock:
    """A device node's interlock on the hazardous outputs it holds (module doc).

    ``dv`` is the node's Data Vector. :attr:`active` is False for a node
    that holds none (then :meth:`apply` is never needed). Not thread-safe:
    the node's loop thread calls :meth:`apply` once per run, after the
    controllers and before the actuators.
    """

    def __init__(self, mission: Mission, node: str, dv: DataVector, events: EventLog) -> None:
        self.node = node
        self._events = events
        self.active = node in interlocked_nodes(mission)
        table = {e.name: e for es in mission.regions.values() for e in es}
        mine = {e.name for r in (f"cn_to_{node}", f"{node}_to_cn") for e in mission.regions[r]}
        outputs: list[tuple[Handle, tuple[bool, ...], int | float | bool]] = []
        states = _states(mission)
        for h in mission.hazardous_outputs:
            if h.element not in mine:
                continue
            ok = tuple(s in h.states for s in states)
            outputs.append((dv.handle(h.element), ok, safe_value(table[h.element], h)))
        self._outputs = tuple(outputs)
        self._states = tuple(states)
        self._h_state = dv.handle(f"{node}_state") if self.active else None
        self._h_count = dv.handle(f"{node}_interlocked") if self.active else None
        # One event a second at most (as zplatform.control.intake.RefusalLog, whose
        # module imports the command handler, which imports this one).
        self._pending = 0  # refused since the last event
        self._last_ev: int | None = None
        self._names: set[str] = set()

    def apply(self, t_ns: int) -> int:
        """Write the safe value of every output this node holds whose state
        (``dnX_state``, the trigger's) is not one of its states and that
        holds another value; returns how many it wrote (each counted in
        ``dnX_interlocked``; evented at most once a second). Never raises."""
        h_state = self._h_state
        if h_state is None:
            return 0
        state = h_state.get()
        n = 0
        for h, ok, safe in self._outputs:
            if state < len(ok) and ok[state]:
                continue
            v = h.get()
            if v == safe:
                continue
            h.set(safe)
            n += 1
            self._names.add(h.spec.name)
        if n:
            assert self._h_count is not None
            self._h_count.bump(n)
        self._pending += n
        if not self._pending or (self._last_ev is not None and t_ns - self._last_ev < _EVENT_NS):
            return n
        name = self._states[state] if state < len(self._states) else f"#{state}"
        self._events.emit(
            EV.DN_INTERLOCKED,
            t_ns,
            node=self.node,
            n=self._pending,
            state=name,
            names=", ".join(sorted(self._names)),
        )
        self._last_ev = t_ns
        self._pending = 0
        self._names = set()
        return n
