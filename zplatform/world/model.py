"""The vehicle world: one physical state behind the boards of several device nodes.

A vehicle has one physical state, which actuators on several nodes change
(both nodes' pyro switches deploy a chute) and every node's sensors read.
:class:`World` is that state: the pins of every board it spans (a
:class:`~zplatform.control.devices.SimBoard` per node, as the world sees it) and one
physics hook, ``function(world, t_ns)``, that reads every board's outputs and
writes every board's inputs when time advances. :class:`WorldBoard` is a
node's board as a port onto it in the lockstep runner. Flight code never sees
it: a node's devices talk to pins, as on hardware.

Contract: this module is the model, sans-IO and deterministic:
:meth:`World.advance` runs the physics once per new time, however many boards
step at that time, and a board's step latches its inputs as the world last
made them. Not thread-safe (one thread drives a world). The live board driver
and its datagrams are :mod:`zplatform.boards.world`, the checks
:mod:`zplatform.world.checks`, the world process :mod:`zplatform.sim.world_server`.

Lockstep, live and hardware in the loop: docs/architecture.md#drivers.
"""

from __future__ import annotations

from typing import Any

import msgspec

from ..boards import SimBoard
from ..boards.base import BoardHealth
from ..boards.world import world_nodes
from ..config import Mission, WorldConfig
from ..core.components import decode_component_config, load_function, mission_code_path
from ..errors import ConfigError

__all__ = ["World", "WorldBoard", "world_nodes"]


class World:
    """The vehicle world of ``mission`` (module doc). Not thread-safe.

    Attributes the physics hook uses: ``boards`` (node -> SimBoard: read
    outputs with ``output_digital``/``output_analog``, write inputs with
    ``inject_*``), ``params`` (decoded), ``state`` (scratch, for the hook),
    ``start_ns`` (the first advance), ``t_ns`` (the last). A hook with a
    ``check`` attribute has ``check(world)`` called here, at load: it
    raises ValueError (or KeyError, OSError) for params the types cannot
    catch (pins that are not on the boards, a missing data file).
    Construction raises ConfigError (path under ``$.world``) for a bad
    world section.
    """

    def __init__(self, mission: Mission) -> None:
        cfg = mission.world
        if cfg is None:
            raise ConfigError("the mission has no world section", "$.world")
        self.config: WorldConfig = cfg
        self.nodes = world_nodes(mission)
        self.boards: dict[str, SimBoard] = {
            n: SimBoard(
                {"digital_pins": b.digital_pins, "analog_pins": b.analog_pins},
                where=f"$.world.boards.{n}",
            )
            for n, b in ((n, cfg.boards[n]) for n in self.nodes)
        }
        self._physics = load_function(
            cfg.physics,
            "$.world.physics",
            args=("world", "t_ns"),
            what="physics",
            pythonpath=mission_code_path(mission),
        )
        params_type = getattr(self._physics, "Params", None)
        self.params: Any = (
            decode_component_config(params_type, cfg.params, "$.world.params")
            if isinstance(params_type, type) and issubclass(params_type, msgspec.Struct)
            else cfg.params
        )
        check = getattr(self._physics, "check", None)
        if callable(check):  # the hook's own load-time check (its wiring, its files)
            try:
                check(self)
            except (ValueError, KeyError, OSError) as exc:
                raise ConfigError(f"{cfg.physics}: {exc}", "$.world.params") from exc
        self.state: dict[str, Any] = {}
        self.truth: Any = None
        """What the physics chooses to expose of its state (tests, plots)."""
        self.start_ns: int | None = None
        self.t_ns: int | None = None

    def advance(self, t_ns: int) -> None:
        """Run the physics up to ``t_ns`` once; a time not after the last does nothing."""
        if self.t_ns is not None and t_ns <= self.t_ns:
            return
        if self.start_ns is None:
            self.start_ns = t_ns
        self.t_ns = t_ns
        self._physics(self, t_ns)

    def board(self, node: str) -> WorldBoard:
        """An in-process port onto ``node``'s pins (the lockstep runner's board)."""
        return WorldBoard(self, node)


class WorldBoard:
    """A node's board as a port onto an in-process :class:`World` (lockstep).

    Pins are the world's board for the node; :meth:`step` advances the world
    to the loop's time. Satisfies :class:`~zplatform.boards.ManagedBoard`.
    """

    def __init__(self, world: World, node: str) -> None:
        self.world = world
        self.node = node
        self.pins = world.boards[node]

    @property
    def digital_pins(self) -> int:
        return self.pins.digital_pins

    @property
    def analog_pins(self) -> int:
        return self.pins.analog_pins

    def step(self, t_ns: int) -> None:
        self.world.advance(t_ns)

    def set_digital(self, pin: int, value: bool) -> None:
        self.pins.set_digital(pin, value)

    def get_digital(self, pin: int) -> bool:
        return self.pins.get_digital(pin)

    def set_analog(self, pin: int, volts: float) -> None:
        self.pins.set_analog(pin, volts)

    def get_analog(self, pin: int) -> float:
        return self.pins.get_analog(pin)

    def open(self) -> None:
        """Nothing to acquire."""

    def close(self) -> None:
        self.safe()

    def safe(self) -> None:
        """Every output of this node off / 0 V (the world sees it at once)."""
        self.pins.safe()

    def health(self) -> BoardHealth:
        return BoardHealth(ok=True)
