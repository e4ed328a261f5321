"""Controllers: the control logic of a mission (thesis 000, ch. 4.6 and 6.2).

A :class:`Controller` is mission code that runs every loop (or every Nth
loop, its rate group) on one node and talks to the rest of the system only
through that node's Data Vector. Its mode lives in the Data Vector too, in
the platform element ``<name>_mode`` (``enabled`` / ``safed`` / ``manual``),
which the state machine's actions write (thesis 4.6.1):

* ``enabled`` -> :meth:`Controller.run_enabled`: normal control;
* ``safed``   -> :meth:`Controller.run_safed`: drive outputs to their safe
  values (actuator devices have no mode: safing the controller that feeds
  them is how an actuator is safed, thesis 4.7);
* ``manual``  -> :meth:`Controller.run_manual`: control logic off
  (thesis 6.2). By default it does nothing, so an operator's WRITE commands to
  the controller's outputs hold instead of being overwritten every loop.

A mode value outside the three names is treated as ``safed`` (fail safe).

Each controller class declares its own typed configuration: a nested
``Config`` ``msgspec.Struct`` (``forbid_unknown_fields=True``); the base
class decodes the YAML ``config:`` mapping into it, so a typo fails at load
with its YAML path (``$.controllers[2].config.step_s``). Element handles are
taken once in :meth:`Controller.bind`, never by name in the loop.

:class:`ControllerSet` builds and runs one node's controllers. A controller
that raises does not stop the loop (thesis 4.11.1, non-critical error after
start): the exception is counted in ``cn_errors`` (with ``cn_last_error =
CONTROLLER_ERROR``) or ``dnX_errors``, one ``ERROR`` event
(``controller_failed``) is emitted per failure streak (not every loop; the
set counts itself rather than calling ``FaultMonitor.error``, which would
add a WARNING event per failure), and the
controller is safed: its mode element is set to ``safed`` and
:meth:`~Controller.run_safed` is called at once. It stays safed until the
mode it failed in is commanded again after a change (on a device node the CN
keeps re-sending the old mode, so the set latches the safing locally until
the CN's commanded mode changes). If ``run_safed`` raises too, the
controller cannot be made safe by software: it is disabled for good and a
``CRITICAL`` event is emitted. On the CN every failing loop (and every due
loop of a disabled controller) is reported to the
:class:`~zplatform.faults.FaultMonitor` with the length of the streak, which
decides when that becomes a critical fault.
"""

from __future__ import annotations

import abc
import importlib
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import msgspec

from .config import CONTROLLER_MODES, ComponentConfig, Mission
from .datavector import DataVector, Handle
from .errors import ConfigError, ControlError, SchedulerError, ZPlatformError
from .events import EventLog, Severity
from .faults import ErrorCode
from .rategroups import RateGroups

if TYPE_CHECKING:
    from .faults import FaultMonitor

__all__ = [
    "ENABLED",
    "MANUAL",
    "SAFED",
    "Component",
    "Controller",
    "ControllerSet",
    "NoConfig",
    "check_config",
    "decode_component_config",
    "load_component_class",
    "owned_regions",
]

ENABLED = CONTROLLER_MODES.index("enabled")
SAFED = CONTROLLER_MODES.index("safed")
MANUAL = CONTROLLER_MODES.index("manual")

_U32_MAX = 0xFFFF_FFFF
_CONTROLLER_ERROR = int(ErrorCode.CONTROLLER_ERROR)


class NoConfig(msgspec.Struct, forbid_unknown_fields=True):
    """The ``Config`` of a component that takes no configuration."""


S = TypeVar("S", bound=msgspec.Struct)


def decode_component_config(cfg_type: type[S], raw: dict[str, Any], where: str) -> S:
    """Convert a YAML ``config:`` mapping into ``cfg_type``.

    Raises ConfigError whose path continues ``where`` (msgspec's ``$.x`` ->
    ``{where}.x``).
    """
    try:
        return msgspec.convert(raw, type=cfg_type)
    except msgspec.ValidationError as exc:
        msg, _, at = str(exc).partition(" - at `")
        at = at.rstrip("`")
        path = where + at[1:] if at.startswith("$") else where
        raise ConfigError(msg, path) from exc


def load_component_class(spec: str, base: type[Any], where: str) -> type[Any]:
    """Import ``"package.module:ClassName"`` and check it subclasses ``base``.

    Raises ConfigError (path ``where``) when the module or class cannot be
    imported, is not a class, is not a ``base`` subclass, or is abstract.
    """
    mod_name, sep, cls_name = spec.partition(":")
    if not sep or not mod_name or not cls_name:
        raise ConfigError(f"class {spec!r} must be 'package.module:ClassName'", where)
    try:
        module = importlib.import_module(mod_name)
    except ImportError as exc:
        raise ConfigError(
            f"cannot import module {mod_name!r} for class {spec!r}: {exc}", where
        ) from exc
    except Exception as exc:  # a bug in the mission module: say where it came from
        raise ConfigError(
            f"importing module {mod_name!r} for class {spec!r} raised {type(exc).__name__}: {exc}",
            where,
        ) from exc
    obj = getattr(module, cls_name, None)
    if obj is None:
        raise ConfigError(f"module {mod_name!r} has no attribute {cls_name!r}", where)
    if not isinstance(obj, type) or not issubclass(obj, base):
        raise ConfigError(
            f"{spec!r} is not a {base.__module__}.{base.__qualname__} subclass", where
        )
    abstract = getattr(obj, "__abstractmethods__", None)
    if abstract:
        missing = ", ".join(sorted(abstract))
        raise ConfigError(f"{spec!r} is abstract (does not implement {missing})", where)
    return obj


def owned_regions(dv: DataVector, node: str) -> tuple[str, ...]:
    """The regions of ``node``'s Data Vector that ``node`` writes.

    The CN owns ``cn`` and every ``cn_to_dnX``; a device node owns its
    ``dnX_to_cn``. Anything written elsewhere is overwritten by the next sync.
    """
    if node == "cn":
        return tuple(r for r in dv.layout.regions if r == "cn" or r.startswith("cn_to_"))
    return tuple(r for r in dv.layout.regions if r == f"{node}_to_cn")


class Component(abc.ABC):
    """What controllers and devices share: name, node, typed config, handles.

    Subclasses set ``Config`` to a ``msgspec.Struct`` with
    ``forbid_unknown_fields=True`` and take their element handles in
    :meth:`bind` with :meth:`input` / :meth:`output`. Construction raises
    ConfigError naming ``where`` (``$.controllers[i]``) for a bad config.
    """

    Config: ClassVar[type[msgspec.Struct]] = NoConfig
    config: Any

    def __init__(self, spec: ComponentConfig, dv: DataVector, *, where: str = "$") -> None:
        self.spec = spec
        self.name = spec.name
        self.node = spec.node
        self.dv = dv
        self.where = where
        self._owned = owned_regions(dv, spec.node)
        self.config = decode_component_config(type(self).Config, spec.config, f"{where}.config")
        self.bind(dv)

    def bind(self, dv: DataVector) -> None:  # noqa: B027 - optional hook, default no-op
        """Take element handles (override). Called once, after ``config`` is set."""

    # -- bind-time helpers ---------------------------------------------------
    def _lookup(self, name: str, field: str, kinds: tuple[str, ...] | None, array: bool) -> Handle:
        where = f"{self.where}.config.{field}" if field else f"{self.where}.config"
        if not isinstance(name, str) or name not in self.dv.layout.elements:
            regions = ", ".join(self.dv.layout.regions)
            raise ConfigError(
                f"{self.name}: element {name!r} is not in node {self.node}'s Data Vector "
                f"(regions {regions})",
                where,
            )
        h = self.dv.handle(name)
        spec = h.spec
        if spec.count and not array:
            raise ConfigError(
                f"{self.name}: element {name!r} is an array ({spec.type_text}); a scalar is needed",
                where,
            )
        if kinds is not None:
            kind = "enum" if spec.enum is not None else spec.scalar.kind
            if kind not in kinds:
                raise ConfigError(
                    f"{self.name}: element {name!r} is {spec.type_text}; expected "
                    f"{' or '.join(kinds)}",
                    where,
                )
        return h

    def input(
        self,
        name: str,
        field: str = "",
        *,
        kinds: tuple[str, ...] | None = None,
        array: bool = False,
    ) -> Handle:
        """A handle on element ``name`` to read (any region of this node's vector).

        ``field`` is the config field that named the element (for the error
        path); ``kinds`` limits the element's kind (``bool``, ``int``,
        ``float``, ``enum``). Raises ConfigError.
        """
        return self._lookup(name, field, kinds, array)

    def output(
        self,
        name: str,
        field: str = "",
        *,
        kinds: tuple[str, ...] | None = None,
        array: bool = False,
    ) -> Handle:
        """Like :meth:`input`, and the element must be in a region this node owns.

        Writing an element of a region the node receives (a DN writing
        ``cn_to_dnX``) would be undone by the next sync, so it is refused here.
        """
        h = self._lookup(name, field, kinds, array)
        if h.spec.region not in self._owned:
            where = f"{self.where}.config.{field}" if field else f"{self.where}.config"
            raise ConfigError(
                f"{self.name}: element {name!r} is in region {h.spec.region}, which node "
                f"{self.node} does not write (it writes {', '.join(self._owned) or 'nothing'})",
                where,
            )
        return h

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r} on {self.node}>"


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

    @abc.abstractmethod
    def run_enabled(self, t_ns: int) -> None:
        """One loop of normal control."""

    @abc.abstractmethod
    def run_safed(self, t_ns: int) -> None:
        """One loop in the safe configuration: write every output's safe value."""

    def run_manual(self, t_ns: int) -> None:
        """One loop with control logic off (thesis 6.2): outputs are left alone."""


class _Slot:
    """Run-time bookkeeping of one controller in a :class:`ControllerSet`."""

    __slots__ = ("controller", "disabled", "last", "latched", "mode", "streak")

    def __init__(self, controller: Controller, mode: Handle) -> None:
        self.controller = controller
        self.mode = mode
        self.last = -1  # mode run on the previous due loop (-1: never ran)
        self.latched = -1  # commanded mode that failed; safed while it is still commanded
        self.streak = 0  # consecutive failing due loops
        self.disabled = False


def _component_indices(mission: Mission, section: str, node: str) -> list[int]:
    return [i for i, c in enumerate(getattr(mission, section)) if c.node == node]


def _errors_element(node: str) -> str:
    return "cn_errors" if node == "cn" else f"{node}_errors"


class ControllerSet:
    """One node's controllers, built from the mission and run every loop.

    Construction imports each ``class``, decodes its config and binds its
    handles; it raises ConfigError naming ``$.controllers[i]...`` for any
    problem and ControlError when a controller's own constructor fails. The
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
        self._errors = dv.handle(_errors_element(node))
        # cn_last_error is the CN's; a DN's errors are seen by the CN as dnX_errors.
        self._last_error = dv.handle("cn_last_error") if node == "cn" else None
        self._slots: dict[str, _Slot] = {}
        # On the CN the mode element holds the safed write; on a DN the CN's
        # next frame overwrites it, so the safing is latched locally.
        self._latch = node != "cn"
        for i in _component_indices(mission, "controllers", node):
            c = mission.controllers[i]
            where = f"$.controllers[{i}]"
            cls = load_component_class(c.cls, Controller, f"{where}.class")
            try:
                inst: Controller = cls(c, dv, where=where)
            except ZPlatformError:
                raise
            except Exception as exc:
                raise ControlError(
                    f"controller {c.name!r} ({c.cls}) failed to build: {type(exc).__name__}: {exc}"
                ) from exc
            slot = _Slot(inst, dv.handle(f"{c.name}_mode"))
            try:
                self._groups.add(slot, c.rate_divisor, c.rate_phase)
            except SchedulerError as exc:
                raise ConfigError(str(exc), f"{where}.rate_phase") from exc
            self.controllers.append(inst)
            self._slots[c.name] = slot

    def __len__(self) -> int:
        return len(self.controllers)

    def disabled(self, name: str) -> bool:
        """Whether controller ``name`` was disabled after its safing failed."""
        return self._slots[name].disabled

    def streak(self, name: str) -> int:
        """Consecutive failing due loops of controller ``name`` (0 when healthy)."""
        return self._slots[name].streak

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
            if s.streak:
                s.streak = 0

    # -- failure path (allocates; only when something went wrong) ------------
    def _count_error(self) -> None:
        n = self._errors.get()
        if n < _U32_MAX:
            self._errors.set(n + 1)
        if self._last_error is not None:
            self._last_error.set(_CONTROLLER_ERROR)

    def _emit(self, severity: Severity, id: str, text: str, t_ns: int) -> None:
        if self.events is not None:
            self.events.emit(severity, id, text, t_ns)

    def _failed(self, s: _Slot, commanded: int, mode: int, exc: Exception, t_ns: int) -> None:
        c = s.controller
        s.streak += 1
        self._count_error()
        mode_name = CONTROLLER_MODES[mode] if 0 <= mode < len(CONTROLLER_MODES) else str(mode)
        if s.streak == 1:
            self._emit(
                Severity.ERROR,
                "controller_failed",
                f"controller {c.name} raised {type(exc).__name__} in {mode_name}: {exc}; safed",
                t_ns,
            )
        if self._latch:
            s.latched = commanded
        s.last = SAFED
        s.mode.set(SAFED)
        if self.faults is not None:
            self.faults.report_controller_failure(c.name, s.streak, t_ns)
        if mode != SAFED:
            try:
                c.run_safed(t_ns)
                return
            except Exception as exc2:
                exc = exc2
        s.disabled = True
        self._emit(
            Severity.CRITICAL,
            "controller_disabled",
            f"controller {c.name} cannot be safed ({type(exc).__name__} in safed: {exc}); "
            "disabled, its outputs are left as they are",
            t_ns,
        )

    def _still_disabled(self, s: _Slot, t_ns: int) -> None:
        s.streak += 1
        if self.faults is not None:
            self.faults.report_controller_failure(s.controller.name, s.streak, t_ns)


def check_config(mission: Mission) -> None:
    """Build every node's controllers on a scratch Data Vector (load-time check).

    Raises ConfigError with the YAML path of the first bad controller class,
    config field or element name.
    """
    from .datavector import Layout

    for node in ["cn", *mission.device_nodes]:
        if not _component_indices(mission, "controllers", node):
            continue
        dv = DataVector(Layout.for_node(mission, node))
        ControllerSet(mission, node, dv)
