"""What controllers and devices share: the component base, typed config, loading.

A *component* is mission code placed on one node (a controller of
:mod:`zplatform.control.controllers` or a device of :mod:`zplatform.control.devices`). This
module holds what both need, so neither imports the other's internals:
:class:`Component` (name, node, a typed ``Config`` decoded from the YAML
``config:``, element handles taken once in :meth:`Component.bind`,
:meth:`Component.tunable` for a number or an element such as a parameter),
:func:`decode_component_config`, :func:`load_component_class` and
:func:`load_function` (the platform's only import of mission code: the
mission's ``pythonpath`` is at the front of ``sys.path`` while they import,
:func:`mission_code_path`, and only then), :func:`build_component` and
:class:`Streak` (the counter behind "one event per failure streak").

Contract: a bad mission raises :class:`~zplatform.errors.ConfigError` naming
the YAML path (a constructor's other errors: ControlError with path and class);
nothing here runs in the loop except :class:`Streak`, which allocates nothing.

Writing your own: docs/mission-reference.md#your-own-controllers-devices-boards-and-physics.
"""

from __future__ import annotations

import abc
import contextlib
import importlib
import inspect
import sys
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import msgspec

from ..errors import ConfigError, ControlError

if TYPE_CHECKING:
    from ..config import ComponentConfig, Mission
    from .datavector import DataVector, Handle
    from .events import EventLog

__all__ = [
    "Component",
    "Fixed",
    "NoConfig",
    "Streak",
    "build_component",
    "component_indices",
    "decode_component_config",
    "errors_element",
    "load_component_class",
    "load_function",
    "mission_code_path",
    "owned_regions",
]


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


def mission_code_path(mission: Mission) -> tuple[str, ...]:
    """The directories the mission's code is imported from (its resolved
    ``pythonpath``, see :func:`zplatform.mission.load.load_mission`); empty for a
    mission that names none."""
    return tuple(mission.pythonpath or ())


_PATH_LOCK = threading.Lock()


@contextlib.contextmanager
def _on_sys_path(dirs: Sequence[str]) -> Iterator[None]:
    """``dirs`` at the front of ``sys.path`` for the block, then taken out
    again (a module the block imported stays imported: its package's own
    submodules keep resolving through the package)."""
    if not dirs:
        yield
        return
    with _PATH_LOCK:
        added = list(dirs)
        sys.path[:0] = added
        try:
            yield
        finally:
            for d in added:
                with contextlib.suppress(ValueError):
                    sys.path.remove(d)


MOVED_MODULES: dict[str, str] = {
    "zplatform.devices": "zplatform.control.devices",
    "zplatform.controllers": "zplatform.control.controllers",
    "zplatform.components": "zplatform.core.components",
    "zplatform.watchdog": "zplatform.control.watchdog",
}
"""The platform modules a mission file may name (``class:``) by their paths
before the packages (issue 26): existing mission files keep loading."""


def _import_attr(
    spec: str,
    where: str,
    *,
    what: str,
    form: str,
    module_noun: str,
    pythonpath: Sequence[str] = (),
) -> object:
    """Import ``"package.module:name"`` and return the attribute (ConfigError at ``where``).

    ``what`` names the kind of thing for messages (``class``, ``physics``),
    ``form`` the expected spelling of the name (``ClassName``, ``function``),
    and ``module_noun`` how the module is called in an import error.
    ``pythonpath``: directories put at the front of ``sys.path`` while the
    module is imported (the mission's, :func:`mission_code_path`).
    """
    mod_name, sep, name = spec.partition(":")
    if not sep or not mod_name or not name:
        raise ConfigError(f"{what} {spec!r} must be 'package.module:{form}'", where)
    mod_name = MOVED_MODULES.get(mod_name, mod_name)
    try:
        with _on_sys_path(pythonpath):
            module = importlib.import_module(mod_name)
    except ImportError as exc:
        searched = f" (the mission's pythonpath: {', '.join(pythonpath)})" if pythonpath else ""
        raise ConfigError(
            f"cannot import {module_noun} {mod_name!r} for {what} {spec!r}: {exc}{searched}",
            where,
        ) from exc
    except Exception as exc:  # a bug in the mission module: say where it came from
        raise ConfigError(
            f"importing module {mod_name!r} for {what} {spec!r} raised {type(exc).__name__}: {exc}",
            where,
        ) from exc
    obj = getattr(module, name, None)
    if obj is None:
        noun = "attribute" if form == "ClassName" else form
        raise ConfigError(f"module {mod_name!r} has no {noun} {name!r}", where)
    return obj


def load_component_class(
    spec: str, base: type[Any], where: str, *, pythonpath: Sequence[str] = ()
) -> type[Any]:
    """Import ``"package.module:ClassName"`` and check it subclasses ``base``.

    ``pythonpath``: the mission's code directories (:func:`mission_code_path`).
    Raises ConfigError (path ``where``) when the module or class cannot be
    imported, is not a class, is not a ``base`` subclass, or is abstract.
    """
    obj = _import_attr(
        spec, where, what="class", form="ClassName", module_noun="module", pythonpath=pythonpath
    )
    if not isinstance(obj, type) or not issubclass(obj, base):
        raise ConfigError(
            f"{spec!r} is not a {base.__module__}.{base.__qualname__} subclass", where
        )
    abstract = getattr(obj, "__abstractmethods__", None)
    if abstract:
        missing = ", ".join(sorted(abstract))
        raise ConfigError(f"{spec!r} is abstract (does not implement {missing})", where)
    return obj


def load_function(
    spec: str,
    where: str,
    *,
    args: tuple[str, ...],
    what: str = "function",
    pythonpath: Sequence[str] = (),
) -> Callable[..., Any]:
    """Import ``"package.module:function"`` and check it can be called with ``args``.

    ``args`` names the positional parameters the caller will pass (for a
    SimBoard physics hook ``("board", "t_ns")``). Raises ConfigError (path
    ``where``) when the module cannot be imported, the name is missing, is a
    class or not callable, or its signature cannot take ``len(args)``
    positional arguments (``os:getcwd`` is refused here, at load, not in the
    first loop). A callable whose signature Python cannot inspect (some
    builtins) is accepted: the check is made where it can be. ``pythonpath``
    as for :func:`load_component_class`.
    """
    obj = _import_attr(
        spec,
        where,
        what=what,
        form="function",
        module_noun=f"{what} module",
        pythonpath=pythonpath,
    )
    if isinstance(obj, type) or not callable(obj):
        raise ConfigError(
            f"{spec!r} is a {type(obj).__name__}, not a function taking ({', '.join(args)})",
            where,
        )
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):  # no signature to check (some builtins)
        return obj
    try:
        sig.bind(*([None] * len(args)))
    except TypeError as exc:
        raise ConfigError(
            f"{spec!r} cannot be called as {what}({', '.join(args)}): its signature is "
            f"{sig} ({exc})",
            where,
        ) from exc
    return obj


C = TypeVar("C")


def build_component(
    kind: str, spec: ComponentConfig, where: str, cls: Callable[..., C], *args: Any
) -> C:
    """``cls(*args, where=where)``: a component's constructor (which runs its
    ``bind``), with every exception naming the component's YAML path and class.

    ``kind`` is ``controller`` or ``device``; ``where`` its YAML path
    (``$.controllers[2]``). A ConfigError keeps its own, deeper path
    (``$.controllers[2].config.gain``) and gains the component's name and
    class; anything else (a ``ValueError`` in the team's ``bind``, a
    DataVectorError) becomes a ControlError at ``where`` with the original
    type and message, chained.
    """
    label = f"{kind} {spec.name!r} ({spec.cls})"
    try:
        return cls(*args, where=where)
    except ConfigError as exc:
        raise ConfigError(f"{label}: {exc.reason}", exc.path) from exc
    except Exception as exc:
        raise ControlError(f"{label} failed to build: {type(exc).__name__}: {exc}", where) from exc


def owned_regions(dv: DataVector, node: str) -> tuple[str, ...]:
    """The regions of ``node``'s Data Vector that ``node`` writes.

    The CN owns ``cn`` and every ``cn_to_dnX``; a device node owns its
    ``dnX_to_cn``. Anything written elsewhere is overwritten by the next sync.
    """
    if node == "cn":
        return tuple(r for r in dv.layout.regions if r == "cn" or r.startswith("cn_to_"))
    return tuple(r for r in dv.layout.regions if r == f"{node}_to_cn")


def component_indices(mission: Mission, section: str, node: str) -> list[int]:
    """Indices into ``mission.<section>`` (``controllers``/``devices``) placed on ``node``."""
    return [i for i, c in enumerate(getattr(mission, section)) if c.node == node]


def errors_element(node: str) -> str:
    """The element counting ``node``'s non-critical errors (``cn_errors``, ``dnX_errors``)."""
    return "cn_errors" if node == "cn" else f"{node}_errors"


class Streak:
    """Consecutive failures of one thing (a controller, a device, a board).

    The loop calls :meth:`fail` on each failing run and :meth:`ok` on each
    good one. Events are reported once per streak (when :meth:`fail` returns
    1), the fault monitor reads the length. Allocates nothing.
    """

    __slots__ = ("length",)

    def __init__(self) -> None:
        self.length = 0

    def fail(self) -> int:
        """Count one more failure; return the streak's new length (1 = a new streak)."""
        self.length += 1
        return self.length

    def ok(self) -> bool:
        """A good run: end the streak. Returns whether a streak was running."""
        if self.length:
            self.length = 0
            return True
        return False


class Fixed:
    """A setting fixed in the config, read like an element (``get()``), so a
    component reads a number and a parameter the same way
    (:meth:`Component.tunable`). Allocates nothing."""

    __slots__ = ("value",)

    def __init__(self, value: float) -> None:
        self.value = value

    def get(self) -> float:
        return self.value


class Component(abc.ABC):
    """What controllers and devices share: name, node, typed config, handles.

    Subclasses set ``Config`` to a ``msgspec.Struct`` with
    ``forbid_unknown_fields=True`` and take their element handles in
    :meth:`bind` with :meth:`input` / :meth:`output`. Construction raises
    ConfigError naming ``where`` (``$.controllers[i]``) for a bad config.
    """

    Config: ClassVar[type[msgspec.Struct]] = NoConfig
    config: Any
    events: EventLog | None = None
    """The node's event log (set by the set that built the component;
    None in a bare construction). Use :meth:`report`."""
    bulk: Mapping[str, Any] = {}
    """The node's bulk channel arrays by channel name (numpy arrays of the
    channel's dtype and shape): the ones this node publishes, which a
    component fills, and the ones it reads, which hold the latest sample.
    Set by the node's loop before the first run; read them in ``run``."""

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
                f"element {name!r} is not in node {self.node}'s Data Vector (regions {regions})",
                where,
            )
        h = self.dv.handle(name)
        spec = h.spec
        if spec.count and not array:
            raise ConfigError(
                f"element {name!r} is an array ({spec.type_text}); a scalar is needed",
                where,
            )
        if kinds is not None:
            kind = "enum" if spec.enum is not None else spec.scalar.kind
            if kind not in kinds:
                raise ConfigError(
                    f"element {name!r} is {spec.type_text}; expected {' or '.join(kinds)}",
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
                f"element {name!r} is in region {h.spec.region}, which node "
                f"{self.node} does not write (it writes {', '.join(self._owned) or 'nothing'})",
                where,
            )
        return h

    def tunable(
        self,
        value: float | str,
        field: str,
        *,
        kinds: tuple[str, ...] = ("float", "int"),
    ) -> Handle | Fixed:
        """A setting the config gives as a number (fixed) or as the name of an
        element, typically a mission parameter (``target_m:
        apogee_target_m``), which a PRM_SET may change between two loops.
        Read it with ``get()`` every loop, never once in :meth:`bind`.

        Declare the config field ``float | str`` (bounds on the number, e.g.
        ``Annotated[float, Meta(gt=0)] | str``: a parameter's own bounds keep
        its values valid). ``field`` names it for errors; ``kinds`` limits the
        element's kind. Raises ConfigError like :meth:`input`."""
        if isinstance(value, str):
            return self.input(value, field, kinds=kinds)
        return Fixed(value)

    def report(self, t_ns: int, text: str, *, warning: bool = False) -> None:
        """Tell the operator something in the mission's words: an event
        ``component_warning`` (WARNING_HI: something failed and the component
        acted) or ``component_activity`` (ACTIVITY_HI), text ``"<name>: text"``.

        For rare moments (a change of mode), not every loop: it allocates.
        Never raises; does nothing without an event log.
        """
        if self.events is not None:
            from .events import EV

            ev = EV.COMPONENT_WARNING if warning else EV.COMPONENT_ACTIVITY
            self.events.emit(ev, t_ns, name=self.name, text=text)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r} on {self.node}>"
