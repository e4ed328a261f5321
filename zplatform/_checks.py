"""Semantic checks of a mission's control sections, run by ``load_mission``.

These need the whole Data Vector (every element, platform ones included), so
they run after the platform elements are added. Each owning module exposes a
``check_config(mission)`` that raises :class:`~zplatform.errors.ConfigError`
with the YAML path; this module only calls them in order.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .config import Mission


def run_all(mission: Mission) -> None:
    """Run every module's ``check_config``; raises ConfigError on the first failure."""
    del mission  # filled as the control modules land
