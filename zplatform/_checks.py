"""Semantic checks of a mission's control sections, run by ``load_mission``.

These need the whole Data Vector (every element, platform ones included), so
they run after the platform elements are added. Each owning module exposes a
``check_config(mission)`` that raises :class:`~zplatform.errors.ConfigError`
with the YAML path; this module only calls them in order.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .errors import ConfigError

if TYPE_CHECKING:
    from .config import Mission


def run_all(mission: Mission) -> None:
    """Run every module's ``check_config``; raises ConfigError on the first failure.

    Order: controllers' ``initial_mode``, the state machine, the commands.
    The control modules are imported here, not at the top: they import
    ``config``, which imports this module.
    """
    from . import commands, statemachine
    from .config import CONTROLLER_MODES

    for i, c in enumerate(mission.controllers):
        if c.initial_mode not in CONTROLLER_MODES:
            raise ConfigError(
                f"initial_mode {c.initial_mode!r} is not one of {list(CONTROLLER_MODES)}",
                f"$.controllers[{i}].initial_mode",
            )
    statemachine.check_config(mission)
    commands.check_config(mission)
