"""Controllers: the control logic of a mission (the thesis, ch. 4.6 and 6.2).

A :class:`Controller` is mission code that runs every loop (or every Nth loop,
its rate group) on one node and talks to the rest of the system only through
that node's Data Vector. Its mode is the platform element ``<name>_mode``,
which the state machine's actions write: ``enabled`` runs
:meth:`Controller.run_enabled`, ``safed`` :meth:`Controller.run_safed` (drive
outputs safe: safing the controller that feeds an actuator is how it is
safed), ``manual`` :meth:`Controller.run_manual` (nothing by default, so an
operator's WRITEs hold); any other value runs ``safed``. Each class declares a
typed ``Config`` struct, decoded at load with YAML paths; element handles are
taken once in :meth:`Controller.bind`, never by name in the loop.

Contract: :class:`ControllerSet` builds and runs one node's controllers on its
loop thread. A controller that raises never stops the loop: it is counted,
evented once per failure streak and safed at once; one whose ``run_safed``
raises too is disabled for good (a FATAL event); on the CN the streak goes to
the :class:`~zplatform.control.faults.FaultMonitor`. Rules: docs/architecture.md#errors-and-faults.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, ClassVar

from ..config import CONTROLLER_MODES, Mission
from ..core.components import (
    Component,
    Streak,
    build_component,
    component_indices,
    errors_element,
    load_component_class,
    mission_code_path,
)
from ..core.datavector import DataVector, Handle
from ..core.events import EV, EventLog, EventType
from ..errors import ConfigError, SchedulerError
from .faults import ErrorCode
from .rategroups import RateGroups

if TYPE_CHECKING:
    from .faults import FaultMonitor

__all__ = [
    "ENABLED",
    "MANUAL",
    "SAFED",
    "Controller",
    "ControllerSet",
    "check_config",
]

ENABLED = CONTROLLER_MODES.index("enabled")
SAFED = CONTROLLER_MODES.index("safed")
MANUAL = CONTROLLER_MODES.index("manual")

_CONTROLLER_ERROR = int(ErrorCode.CONTROLLER_ERROR)


class Controller(Component):
    """Base class of mission control logic (thesis Figure 16).

    Contract: ``run_*`` take the loop's single timestamp ``t_ns`` (the node's
    synchronised time) and must not block, sleep, read the wall clock or do
    I/O; they read and write the Data Vector through handles taken in
    :meth:`bind`. ``enabled_at_ns`` is the loop time at which the controller
    last entered ``enabled`` (set by :class:`ControllerSet` before that
    loop's ``run_enabled``). An exception is caught by the set (see the
    module docstring), never by the controller's caller.
    """

    enabled_at_ns: int = 0

    takeover_safe: ClassVar[bool] = False
    """Declares that the controller keeps every piece of state it carries from
    one loop to the next in Data Vector elements (those it writes: estimates,
    integrators, latches, counters), none in Python attributes, so that a
    standby control node that mirrors the vector can run it from any loop on
    (docs/architecture.md#failover). A mission with a standby refuses a
    control-node controller that does not declare it; and there the platform
    holds it to it: after :meth:`bind`, assigning an attribute of the
    controller raises (a controller failure, safed and reported) instead of
    silently keeping state a takeover would lose."""

    _sealed: bool = False

    def __setattr__(self, name: str, value: object) -> None:
        if self._sealed and name not in _PLATFORM_ATTRS:
            raise AttributeError(
                f"controller {self.name} ({type(self).__name__}) sets self.{name} after bind: "
                "in a mission with a standby control node a controller keeps its state in "
                "Data Vector elements (takeover_safe; docs/architecture.md#failover)"
            )
        object.__setattr__(self, name, value)

    @abc.abstractmethod
    def run_enabled(self, t_ns: int) -> None:
        """One loop of normal control."""

    @abc.abstractmethod
    def run_safed(self, t_ns: int) -> None:
        """One loop in the safe configuration: write every output's safe value."""

    def run_manual(self, t_ns: int) -> None:
        """One loop with control logic off (thesis 6.2): outputs are left alone."""


# What the platform itself sets on a controller after bind.
_PLATFORM_ATTRS = frozenset({"enabled_at_ns", "events", "bulk", "_sealed"})


class _Slot:
    """Run-time bookkeeping of one controller in a :class:`ControllerSet`."""

    __slots__ = ("controller", "disabled", "enabled_ns", "last", "latched", "mode", "streak")

    def __init__(self, controller: Controller, mode: Handle, enabled_ns: Handle | None) -> None:
        self.controller = controller
        self.mode = mode
        # Controller.enabled_at_ns, mirrored in a redundant mission (adopt()).
        self.enabled_ns = enabled_ns
        self.last = -1  # mode run on the previous due loop (-1: never ran)
        self.latched = -1  # commanded mode that failed; safed while it is still commanded
        self.streak = Streak()  # consecutive failing due loops
        self.disabled = False


class ControllerSet:
    """One node's controllers, built from the mission and run every loop.

    Construction imports each ``class`` (from the mission's ``pythonpath``),
    decodes its config and binds its handles; it raises ConfigError naming
    ``$.controllers[i]...`` for any problem and ControlError naming
    ``$.controllers[i]`` and the class when a controller's own constructor
    or ``bind`` raises anything else (:func:`~zplatform.core.components.build_component`). The
    rate groups come from ``rate_divisor`` / ``rate_phase``.

    :meth:`run` never raises for a controller's exception (see the module
    docstring); it allocates nothing unless a controller fails.
    """

    def __init__(
        self,
        mission: Mission,
        node: str,
        dv: DataVector,
        events: EventLog | None = None,
        faults: FaultMonitor | None = None,
    ) -> None:
        self.node = node
        self.dv = dv
        self.events = events
        self.faults = faults if node == "cn" else None
        self.controllers: list[Controller] = []
        self._groups: RateGroups[_Slot] = RateGroups()
        self._errors = dv.handle(errors_element(node))
        # cn_last_error is the CN's; a DN's errors are seen by the CN as dnX_errors.
        self._last_error = dv.handle("cn_last_error") if node == "cn" else None
        self._slots: dict[str, _Slot] = {}
        # On the CN the mode element holds the safed write; on a DN the CN's
        # next frame overwrites it, so the safing is latched locally.
        self._latch = node != "cn"
        code = mission_code_path(mission)
        for i in component_indices(mission, "controllers", node):
            c = mission.controllers[i]
            where = f"$.controllers[{i}]"
            cls = load_component_class(c.cls, Controller, f"{where}.class", pythonpath=code)
            redundant = node == "cn" and mission.standby is not None
            if redundant:
                _check_takeover_safe(cls, where)
            inst: Controller = build_component("controller", c, where, cls, c, dv)
            inst.events = events
            if redundant:
                inst._sealed = True
            ens = f"{c.name}_enabled_ns"
            slot = _Slot(
                inst,
                dv.handle(f"{c.name}_mode"),
                dv.handle(ens) if node == "cn" and ens in dv.layout.elements else None,
            )
            try:
                self._groups.add(slot, c.rate_divisor, c.rate_phase)
            except SchedulerError as exc:
                raise ConfigError(str(exc), f"{where}.rate_phase") from exc
            self.controllers.append(inst)
            self._slots[c.name] = slot

    def __len__(self) -> int:
        return len(self.controllers)

    def adopt(self) -> None:
        """Take up where the vector says the controllers are (a takeover,
        :meth:`zplatform.control.loop.ControlLogic.adopt`): each ran in the mode its
        ``<name>_mode`` shows, enabled since ``<name>_enabled_ns`` (kept on the
        control node of a redundant mission); failure streaks start over. A
        controller's own state is in elements it names (Controller doc)."""
        for s in self._slots.values():
            s.last = s.mode.get()
            s.latched = -1
            s.streak = Streak()
            if s.enabled_ns is not None:
                s.controller.enabled_at_ns = int(s.enabled_ns.get())

    def disabled(self, name: str) -> bool:
        """Whether controller ``name`` was disabled after its safing failed."""
        return self._slots[name].disabled

    def streak(self, name: str) -> int:
        """Consecutive failing due loops of controller ``name`` (0 when healthy)."""
        return self._slots[name].streak.length

    def run(self, loop: int, t_ns: int) -> None:
        """Run the controllers due on ``loop``, in configuration order."""
        for s in self._groups.due(loop):
            if s.disabled:
                self._still_disabled(s, t_ns)
                continue
            commanded = s.mode.get()
            mode = commanded
            if s.latched >= 0:
                if commanded == s.latched:
                    mode = SAFED
                else:
                    s.latched = -1
            c = s.controller
            try:
                if mode == ENABLED:
                    if s.last != ENABLED:
                        c.enabled_at_ns = t_ns
                        if s.enabled_ns is not None:
                            s.enabled_ns.set(t_ns)
                    c.run_enabled(t_ns)
                elif mode == MANUAL:
                    c.run_manual(t_ns)
                else:  # safed, or a value that is no mode: fail safe
                    mode = SAFED
                    c.run_safed(t_ns)
            except Exception as exc:
                self._failed(s, commanded, mode, exc, t_ns)
                continue
            s.last = mode
            s.streak.ok()

    # -- failure path (allocates; only when something went wrong) ------------
    def _count_error(self) -> None:
        self._errors.bump()
        if self._last_error is not None:
            self._last_error.set(_CONTROLLER_ERROR)

    def _emit(self, ev: EventType, t_ns: int, **args: object) -> None:
        if self.events is not None:
            self.events.emit(ev, t_ns, **args)

    def _failed(self, s: _Slot, commanded: int, mode: int, exc: Exception, t_ns: int) -> None:
        c = s.controller
        streak = s.streak.fail()
        self._count_error()
        mode_name = CONTROLLER_MODES[mode] if 0 <= mode < len(CONTROLLER_MODES) else str(mode)
        if streak == 1:
            self._emit(
                EV.CONTROLLER_FAILED,
                t_ns,
                name=c.name,
                exc_type=type(exc).__name__,
                mode=mode_name,
                exc=exc,
            )
        if self._latch:
            s.latched = commanded
        s.last = SAFED
        s.mode.set(SAFED)
        if self.faults is not None:
            self.faults.report_controller_failure(c.name, streak, t_ns)
        if mode != SAFED:
            try:
                c.run_safed(t_ns)
                return
            except Exception as exc2:
                exc = exc2
        s.disabled = True
        self._emit(EV.CONTROLLER_DISABLED, t_ns, name=c.name, exc_type=type(exc).__name__, exc=exc)

    def _still_disabled(self, s: _Slot, t_ns: int) -> None:
        streak = s.streak.fail()
        if self.faults is not None:
            self.faults.report_controller_failure(s.controller.name, streak, t_ns)


def _check_takeover_safe(cls: type[Controller], where: str) -> None:
    if not cls.takeover_safe:
        raise ConfigError(
            f"{cls.__module__}:{cls.__qualname__} does not declare takeover_safe: a mission "
            "with a standby control node (cn_b) runs only control-node controllers that keep "
            "their state in Data Vector elements, so the standby can take over in any loop "
            "(set takeover_safe = True once it does; docs/architecture.md#failover)",
            f"{where}.class",
        )


def check_config(mission: Mission) -> None:
    """Build every node's controllers on a scratch Data Vector (load-time check).

    Raises ConfigError with the YAML path of the first bad controller class,
    config field or element name.
    """
    from ..core.datavector import Layout

    for node in ["cn", *mission.device_nodes]:
        if not component_indices(mission, "controllers", node):
            continue
        dv = DataVector(Layout.for_node(mission, node))
        ControllerSet(mission, node, dv)
