"""The sans-IO loop step of each node (DESIGN.md §1).

:class:`ControlLogic` and :class:`DeviceLogic` own a node's Data Vector and
everything that runs on it each loop. They never touch zenoh or the wall
clock: a driver (the zenoh runtime or the lockstep runner) moves regions in
and out of ``dv`` with :class:`~zplatform.codec.RegionCodec`\\ s and calls
``step`` with the loop's number and its single timestamp.

Protocol order around the steps (what both drivers do):

* CN, each loop: send ``cn_to_dnX`` to every DN, apply their ``dnX_to_cn``
  replies, apply at most one ``gn_to_cn`` frame, then
  :meth:`ControlLogic.step` (``new_request=True`` if a ground frame was
  applied this loop), then publish telemetry (the whole vector).
* DN, each loop: apply the CN's ``cn_to_dnX``, reply at once with
  ``dnX_to_cn`` as it stood *before* this loop's step, then
  :meth:`DeviceLogic.step`. So what a DN's step writes reaches the CN one
  loop later.

``loop`` is the CN's loop number (on a DN, the ``seq`` of the CN frame that
triggered the step), so loop numbers agree across the nodes.
"""

from __future__ import annotations

from ..commands import CommandHandler
from ..components import Streak
from ..config import Mission
from ..controllers import ControllerSet
from ..datavector import DataVector, Layout
from ..devices import Board, DeviceSet, SimBoard
from ..errors import ConfigError
from ..events import EV, EventLog
from ..faults import FaultMonitor
from ..statemachine import StateMachine

__all__ = ["ControlLogic", "DeviceLogic"]


class ControlLogic:
    """The control node's loop step: faults, commands, state machine, controllers.

    Construction builds the CN's Data Vector (every region) and every
    component, checking the mission (ConfigError naming the YAML path).
    :meth:`step` never raises for a valid mission: controller exceptions are
    caught by the :class:`~zplatform.controllers.ControllerSet`.
    """

    def __init__(self, mission: Mission, *, events: EventLog | None = None) -> None:
        self.mission = mission
        self.layout = Layout.for_node(mission, "cn")
        self.dv = DataVector(self.layout)
        self.events = events if events is not None else EventLog("cn")
        self.faults = FaultMonitor(mission, self.dv, self.events)
        self.statemachine = StateMachine(mission, self.dv, self.events)
        self.commands = CommandHandler(mission, self.dv, self.events, self.statemachine)
        self.controllers = ControllerSet(mission, "cn", self.dv, self.events, self.faults)
        self._loop = self.dv.handle("cn_loop")
        self._time = self.dv.handle("cn_time_ns")

    def step(self, loop: int, t_ns: int, new_request: bool) -> None:
        """One CN loop at time ``t_ns``, after the DN regions (and at most one
        ground frame, then ``new_request=True``) were applied."""
        self._loop.set(loop)
        self._time.set(t_ns)
        self.faults.step(t_ns)
        self.commands.step(new_request, t_ns)
        self.statemachine.step(t_ns)
        self.controllers.run(loop, t_ns)


class DeviceLogic:
    """A device node's loop step: board, sensors, controllers, actuators.

    ``board`` defaults to a :class:`~zplatform.devices.SimBoard` built from
    the node's ``board`` config. Construction raises ConfigError (YAML path)
    for a bad device or controller. :meth:`step` never raises: device and
    controller exceptions are caught by their sets, and an exception of the
    board's own ``step`` (a physics hook bug, a board that cannot latch its
    inputs) is counted in ``dnX_errors`` and reported once per streak, after
    which the loop goes on with the inputs as they are.
    """

    def __init__(
        self,
        mission: Mission,
        node: str,
        *,
        board: Board | None = None,
        events: EventLog | None = None,
    ) -> None:
        if node not in mission.device_nodes:
            raise ConfigError(
                f"{node!r} is not a device node of mission {mission.mission!r}; device nodes: "
                f"{mission.device_nodes}",
                "$.nodes",
            )
        self.mission = mission
        self.node = node
        self.layout = Layout.for_node(mission, node)
        self.dv = DataVector(self.layout)
        self.events = events if events is not None else EventLog(node)
        self.board: Board = (
            board
            if board is not None
            else SimBoard(mission.nodes[node].board, where=f"$.nodes.{node}.board")
        )
        self.devices = DeviceSet(mission, node, self.dv, self.board, self.events)
        self.controllers = ControllerSet(mission, node, self.dv, self.events)
        self._loop = self.dv.handle(f"{node}_loop")
        self._time = self.dv.handle(f"{node}_time_ns")
        self._errors = self.dv.handle(f"{node}_errors")
        self._board_streak = Streak()

    def step(self, loop: int, t_ns: int) -> None:
        """One DN loop at time ``t_ns``, after the CN's region was applied and replied to."""
        self._loop.set(loop)
        self._time.set(t_ns)
        try:
            self.board.step(t_ns)
            self._board_streak.ok()
        except Exception as exc:
            self._board_failed(exc, t_ns)
        self.devices.run_sensors(loop, t_ns)
        self.controllers.run(loop, t_ns)
        self.devices.run_actuators(loop, t_ns)

    def _board_failed(self, exc: Exception, t_ns: int) -> None:
        self._errors.bump()
        if self._board_streak.fail() == 1:
            self.events.emit(
                EV.BOARD_FAILED, t_ns, node=self.node, exc_type=type(exc).__name__, exc=exc
            )
