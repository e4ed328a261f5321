"""Monitors and responses: fault detection and fault response, as F Prime splits them (sans-IO).

A mission declares ``monitors:`` (:class:`~zplatform.config.MonitorConfig`),
each a condition on one scalar element of the CN's Data Vector (``limit``,
``stale``, ``rate``) that, holding for ``persistence`` loops in a row,
**trips** once and runs its response: ``event`` (``monitor_warning``),
``fault`` (:meth:`~zplatform.control.faults.FaultMonitor.raise_fault`), ``transition``
(:meth:`~zplatform.control.statemachine.StateMachine.request`) or ``safe`` (a
controller's mode set to ``safed``; each but ``event`` with ``monitor_tripped``).
It **clears** when the condition stops holding; outside its ``states``, neither.

Contract: :class:`MonitorSet` runs on the CN's loop thread in
``ControlLogic.finish``, after the fault monitor and before the command
handler and the state machine, so a response takes effect in the loop the
monitor trips. Everything is resolved at construction; a step allocates only
when a monitor trips or clears (its event) and never raises.
:func:`check_config` raises ConfigError with the YAML path at load.

The kinds and responses: docs/missions.md#health-monitors-and-the-watchdog.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from ..config import CONTROLLER_MODES, MonitorConfig
from ..config.codes import Fault
from ..core.events import EV, EventLog
from ..errors import ConfigError
from .limits import mission_limits

if TYPE_CHECKING:
    from ..config import Mission
    from ..core.datavector import DataVector, Handle
    from .faults import FaultMonitor
    from .statemachine import StateMachine

__all__ = ["MonitorSet", "check_config"]

_SAFED = CONTROLLER_MODES.index("safed")
_NAME_OK = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_")


def _fmt(x: float | None) -> str:
    return "open" if x is None else f"{x:g}"


def _states(mission: Mission) -> list[str]:
    sm = mission.state_machine
    return list(sm.states) if sm is not None else ["IDLE"]


def check_config(mission: Mission) -> None:
    """Check ``monitors`` against the mission (ConfigError naming the YAML path):
    unique names; a scalar element of the CN's Data Vector, numeric for
    ``limit`` and ``rate`` and an integer for ``max_age_ms``; each kind's keys
    and no other's; a ``band`` the element has limits for; known states;
    a response with its one argument (a fault, a state, a controller)."""
    from ..core.datavector import Layout

    layout = Layout.for_node(mission, "cn")
    limits = mission_limits(mission)
    states = _states(mission)
    controllers = {c.name for c in mission.controllers}
    faults = [f.name for f in Fault if f != Fault.NONE]
    seen: set[str] = set()
    for i, m in enumerate(mission.monitors):
        w = f"$.monitors[{i}]"
        if not m.name or not m.name[0].isalpha() or not set(m.name) <= _NAME_OK:
            raise ConfigError(f"monitor name {m.name!r} must match [a-z][a-z0-9_]*", f"{w}.name")
        if m.name in seen:
            raise ConfigError(f"duplicate monitor name {m.name!r}", f"{w}.name")
        seen.add(m.name)
        if m.element not in layout.elements:
            raise ConfigError(
                f"no element named {m.element!r} in the control node's Data Vector",
                f"{w}.element",
            )
        spec = layout.element(m.element)
        if spec.count:
            raise ConfigError(
                f"{m.element} is an array ({spec.type_text}); a monitor watches a scalar",
                f"{w}.element",
            )
        numeric = spec.enum is None and spec.scalar.kind != "bool"
        given = {
            k
            for k in ("lo", "hi", "band", "unchanged_loops", "max_age_ms")
            if getattr(m, k) is not None
        }
        allowed = {
            "limit": {"lo", "hi", "band"},
            "stale": {"unchanged_loops", "max_age_ms"},
            "rate": {"lo", "hi"},
        }[m.kind]
        extra = sorted(given - allowed)
        if extra:
            k = extra[0]
            raise ConfigError(f"`{k}` does not apply to a {m.kind} monitor", f"{w}.{k}")
        if m.kind in ("limit", "rate") and not numeric:
            raise ConfigError(
                f"{m.element} is {spec.type_text}: a {m.kind} monitor needs a number",
                f"{w}.element",
            )
        if m.kind == "limit":
            if m.band is not None and given & {"lo", "hi"}:
                raise ConfigError("give `band` or `lo`/`hi`, not both", f"{w}.band")
            if m.band is None and not given:
                raise ConfigError("a limit monitor needs `lo`, `hi` or `band`", w)
            if m.band is not None:
                lim = limits.get(m.element)
                rng = getattr(lim, m.band) if lim is not None else (None, None)
                if rng == (None, None):
                    raise ConfigError(
                        f"{m.element} has no {m.band} limits (regions' or health's `limits`)",
                        f"{w}.band",
                    )
        if m.kind == "rate" and m.lo is None and m.hi is None:
            raise ConfigError("a rate monitor needs `lo` or `hi` (per second)", w)
        if m.lo is not None and m.hi is not None and m.lo > m.hi:
            raise ConfigError(f"lo {m.lo:g} is above hi {m.hi:g}", f"{w}.lo")
        for k in ("lo", "hi"):
            v = getattr(m, k)
            if v is not None and math.isnan(v):
                raise ConfigError(
                    "nan compares with nothing; the monitor could never trip", f"{w}.{k}"
                )
        if m.kind == "stale":
            if len(given) != 1:
                raise ConfigError(
                    "a stale monitor needs exactly one of `unchanged_loops` and `max_age_ms`", w
                )
            if m.max_age_ms is not None and spec.scalar.kind != "int":
                raise ConfigError(
                    f"{m.element} is {spec.type_text}: `max_age_ms` needs an integer time stamp "
                    "(ns)",
                    f"{w}.element",
                )
        if m.kind != "rate" and m.window_loops != 1:
            raise ConfigError("`window_loops` applies to rate monitors", f"{w}.window_loops")
        for j, st in enumerate(m.states or ()):
            if st not in states:
                raise ConfigError(f"{st!r} is not a state; states: {states}", f"{w}.states[{j}]")
        _check_response(m, w, states, controllers, faults)


def _check_response(
    m: MonitorConfig, w: str, states: list[str], controllers: set[str], faults: list[str]
) -> None:
    args = {"fault": m.fault, "to": m.to, "controller": m.controller}
    needs = {"event": None, "fault": "fault", "transition": "to", "safe": "controller"}[m.response]
    for k, v in args.items():
        if v is not None and k != needs:
            raise ConfigError(f"`{k}` does not apply to response {m.response!r}", f"{w}.{k}")
    if m.response == "fault" and m.fault is not None and m.fault not in faults:
        raise ConfigError(f"{m.fault!r} is not a fault; faults: {faults}", f"{w}.fault")
    if m.response == "transition":
        if m.to is None:
            raise ConfigError("response `transition` needs `to`, the target state", w)
        if m.to not in states:
            raise ConfigError(f"{m.to!r} is not a state; states: {states}", f"{w}.to")
        if m.states is not None and m.states == [m.to]:
            raise ConfigError(
                f"the monitor runs only in {m.to!r}, its own target: it could never move the state",
                f"{w}.states",
            )
    if m.response == "safe":
        if m.controller is None:
            raise ConfigError("response `safe` needs `controller`", w)
        if m.controller not in controllers:
            raise ConfigError(
                f"no controller named {m.controller!r}; controllers: {sorted(controllers)}",
                f"{w}.controller",
            )


# -- run time ---------------------------------------------------------------------


class _Monitor:
    """One resolved monitor. ``test(t_ns)`` updates the kind's state and says
    whether the condition holds now."""

    __slots__ = (
        "active",
        "cfg",
        "fault",
        "get",
        "mode",
        "persistence",
        "run",
        "target",
        "tripped",
        "what",
    )

    def __init__(self, cfg: MonitorConfig, h: Handle, states: list[str]) -> None:
        self.cfg = cfg
        self.get = h.get
        self.persistence = cfg.persistence
        self.run = 0
        self.tripped = False
        on = set(cfg.states) if cfg.states is not None else set(states)
        self.active = tuple(s in on for s in states)
        self.fault = Fault[cfg.fault or "MONITOR"]
        self.target = states.index(cfg.to) if cfg.to is not None else -1
        self.mode: Handle | None = None
        self.what = ""

    def test(self, t_ns: int) -> bool:  # pragma: no cover - every kind overrides it
        raise NotImplementedError

    def describe(self) -> str:  # pragma: no cover - every kind overrides it
        raise NotImplementedError

    def adopt(self) -> None:
        """Start over from the element as it stands (a takeover): not
        tripped, no persistence run; each kind resets what it remembers."""
        self.run = 0
        self.tripped = False
        self.what = ""


class _Limit(_Monitor):
    __slots__ = ("hi", "lo")

    def __init__(
        self, cfg: MonitorConfig, h: Handle, states: list[str], lo: float | None, hi: float | None
    ) -> None:
        super().__init__(cfg, h, states)
        self.lo = -math.inf if lo is None else lo
        self.hi = math.inf if hi is None else hi

    def test(self, t_ns: int) -> bool:
        v = self.get()
        return v < self.lo or v > self.hi  # NaN: neither, never trips

    def describe(self) -> str:
        lo = None if self.lo == -math.inf else self.lo
        hi = None if self.hi == math.inf else self.hi
        return f"{self.cfg.element} = {self.get():g} outside [{_fmt(lo)}, {_fmt(hi)}]"


class _Unchanged(_Monitor):
    __slots__ = ("last", "limit", "same")

    def __init__(self, cfg: MonitorConfig, h: Handle, states: list[str]) -> None:
        super().__init__(cfg, h, states)
        assert cfg.unchanged_loops is not None
        self.limit = cfg.unchanged_loops
        self.last = h.get()
        self.same = 0

    def test(self, t_ns: int) -> bool:
        v = self.get()
        last = self.last
        if v == last or (v != v and last != last):  # NaN stays NaN: unchanged
            self.same += 1
        else:
            self.same = 0
            self.last = v
        return self.same >= self.limit

    def describe(self) -> str:
        return f"{self.cfg.element} unchanged for {self.same} loops"

    def adopt(self) -> None:
        super().adopt()
        self.last = self.get()
        self.same = 0


class _Age(_Monitor):
    __slots__ = ("armed", "initial", "max_age", "now")

    def __init__(self, cfg: MonitorConfig, h: Handle, states: list[str]) -> None:
        super().__init__(cfg, h, states)
        assert cfg.max_age_ms is not None
        self.max_age = round(cfg.max_age_ms * 1e6)
        self.initial = h.get()
        self.armed = False
        self.now = 0

    def test(self, t_ns: int) -> bool:
        v = self.get()
        self.now = t_ns
        if not self.armed:
            if v == self.initial:
                return False
            self.armed = True
        return t_ns - v > self.max_age

    def adopt(self) -> None:
        super().adopt()
        self.armed = self.get() != self.initial

    def describe(self) -> str:
        age = (self.now - self.get()) / 1e6
        return f"{self.cfg.element} is {age:.1f} ms old (at most {self.cfg.max_age_ms:g} ms)"


class _Rate(_Monitor):
    __slots__ = ("filled", "hi", "i", "last_rate", "lo", "ring", "window_s")

    def __init__(self, cfg: MonitorConfig, h: Handle, states: list[str], period_ns: int) -> None:
        super().__init__(cfg, h, states)
        self.lo = -math.inf if cfg.lo is None else cfg.lo
        self.hi = math.inf if cfg.hi is None else cfg.hi
        self.ring = [0.0] * cfg.window_loops
        self.i = 0
        self.filled = 0
        self.window_s = cfg.window_loops * period_ns / 1e9
        self.last_rate = 0.0

    def test(self, t_ns: int) -> bool:
        v = self.get()
        ring = self.ring
        i = self.i
        old = ring[i]
        ring[i] = v
        i += 1
        self.i = 0 if i == len(ring) else i
        if self.filled < len(ring):
            self.filled += 1
            return False
        r = (v - old) / self.window_s
        self.last_rate = r
        return r < self.lo or r > self.hi

    def adopt(self) -> None:
        super().adopt()
        self.i = 0
        self.filled = 0

    def describe(self) -> str:
        lo = None if self.lo == -math.inf else self.lo
        hi = None if self.hi == math.inf else self.hi
        return (
            f"{self.cfg.element} changes {self.last_rate:g}/s, outside [{_fmt(lo)}, {_fmt(hi)}]/s"
        )


class MonitorSet:
    """The mission's monitors on the CN's Data Vector (module doc).

    Construction resolves every monitor (the mission passed
    :func:`check_config`). :meth:`step` runs once per loop on the loop
    thread; it never raises for a checked mission.
    """

    def __init__(
        self,
        mission: Mission,
        dv: DataVector,
        events: EventLog,
        faults: FaultMonitor,
        statemachine: StateMachine,
    ) -> None:
        self._events = events
        self._faults = faults
        self._sm = statemachine
        self._h_state = dv.handle("cn_state")
        states = _states(mission)
        limits = mission_limits(mission) if any(m.band for m in mission.monitors) else {}
        out: list[_Monitor] = []
        for cfg in mission.monitors:
            h = dv.handle(cfg.element)
            mon: _Monitor
            if cfg.kind == "limit":
                lo, hi = cfg.lo, cfg.hi
                if cfg.band is not None:
                    lo, hi = getattr(limits[cfg.element], cfg.band)
                mon = _Limit(cfg, h, states, lo, hi)
            elif cfg.kind == "rate":
                mon = _Rate(cfg, h, states, mission.period_ns)
            elif cfg.unchanged_loops is not None:
                mon = _Unchanged(cfg, h, states)
            else:
                mon = _Age(cfg, h, states)
            if cfg.controller is not None:
                mon.mode = dv.handle(f"{cfg.controller}_mode")
            out.append(mon)
        self.monitors: tuple[_Monitor, ...] = tuple(out)

    def __len__(self) -> int:
        return len(self.monitors)

    def adopt(self) -> None:
        """Start every monitor over from the vector as it stands (a takeover,
        :meth:`zplatform.control.loop.ControlLogic.adopt`): a condition that still
        holds trips again after its persistence, with its event and response."""
        for m in self.monitors:
            m.adopt()

    def tripped(self, name: str) -> bool:
        """Whether monitor ``name`` is tripped now."""
        return next(m.tripped for m in self.monitors if m.cfg.name == name)

    def step(self, t_ns: int) -> None:
        """Evaluate every monitor at ``t_ns``; trip (and respond) or clear."""
        state = self._h_state.get()
        for m in self.monitors:
            holds = m.test(t_ns)
            if not m.active[state]:
                m.run = 0
                continue
            if holds:
                m.run += 1
                if m.run >= m.persistence and not m.tripped:
                    self._trip(m, t_ns)
            else:
                m.run = 0
                if m.tripped:
                    m.tripped = False
                    self._events.emit(EV.MONITOR_CLEARED, t_ns, name=m.cfg.name, what=m.what)

    # -- tripping (allocates: rare by definition) ------------------------------
    def _trip(self, m: _Monitor, t_ns: int) -> None:
        m.tripped = True
        cfg = m.cfg
        what = m.describe()
        if cfg.persistence > 1:
            what += f" for {cfg.persistence} loops"
        m.what = what
        r = cfg.response
        if r == "event":
            self._events.emit(EV.MONITOR_WARNING, t_ns, name=cfg.name, what=what)
            return
        if r == "fault":
            latched = self._faults.raise_fault(m.fault, f"monitor {cfg.name}: {what}", t_ns)
            response = (
                f"fault {m.fault.name} latched"
                if latched
                else f"fault {m.fault.name} not latched ({self._faults.fault} already is)"
            )
        elif r == "transition":
            self._sm.request(m.target, f"monitor {cfg.name}")
            response = f"transition to {cfg.to} requested"
        else:
            assert m.mode is not None
            m.mode.set(_SAFED)
            response = f"controller {cfg.controller} safed"
        self._events.emit(EV.MONITOR_TRIPPED, t_ns, name=cfg.name, what=what, response=response)
