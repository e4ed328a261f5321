"""The checks of a mission's vehicle world section (:mod:`zplatform.world.model`)
against the rest of the mission, run by :func:`zplatform.mission.load.check_mission`.
"""

from __future__ import annotations

from ..boards.world import link_address
from ..config import Mission
from ..errors import ConfigError
from .model import World

__all__ = ["check_config"]


def check_config(mission: Mission, *, code: bool = True) -> None:
    """Check the world section against the mission (ConfigError with the path).

    Boards only of device nodes; the physics importable as ``(world, t_ns)``
    and its params decoded (by building the world: the hook does not run);
    a loopback ``listen``; every ``driver: world`` node among the boards;
    every ``serve_serial`` node a world board whose node runs a serial board
    on that port. ``code=False``: the same checks without importing the
    physics (ground verbs, :func:`zplatform.mission.load.load_mission`).
    """
    w = mission.world
    world_users = [
        n for n in mission.device_nodes if mission.nodes[n].board.get("driver") == "world"
    ]
    if w is None:
        if world_users:
            raise ConfigError(
                "driver 'world' needs a world section ($.world) in the mission",
                f"$.nodes.{world_users[0]}.board.driver",
            )
        return
    for n in w.boards:
        if n not in mission.device_nodes:
            raise ConfigError(
                f"{n!r} is not a device node; device nodes: {mission.device_nodes}",
                f"$.world.boards.{n}",
            )
    link_address(w.listen, "$.world.listen")
    if code:  # building the world imports the physics (the mission's code)
        World(mission)
    for n in world_users:
        if n not in w.boards:
            raise ConfigError(
                f"node {n} uses driver 'world' but $.world.boards has no {n}",
                f"$.nodes.{n}.board.driver",
            )
    for n, path in w.serve_serial.items():
        where = f"$.world.serve_serial.{n}"
        if n not in w.boards:
            raise ConfigError(f"{n!r} is not one of the world's boards", where)
        b = mission.nodes[n].board
        if b.get("driver") != "serial" or b.get("port") != path:
            raise ConfigError(
                f"node {n}'s board must be {{driver: serial, port: {path}}} to reach the "
                "world's serial board",
                where,
            )
