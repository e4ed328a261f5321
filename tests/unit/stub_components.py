"""Importable stand-ins for missions in unit tests (not collected: no ``test_`` prefix).

``load_mission`` imports every controller class, so a test mission names a
real one: ``stub_components:Idle`` where the class does not matter.
"""

from __future__ import annotations

from zplatform.control.controllers import Controller


class Idle(Controller):
    """A controller that does nothing in every mode (no config, no elements)."""

    def run_enabled(self, t_ns: int) -> None:
        pass

    def run_safed(self, t_ns: int) -> None:
        pass


class Counter(Controller):
    """Declares takeover_safe but counts in an attribute: what a redundant
    mission must catch (tests/unit/test_fencing.py)."""

    takeover_safe = True
    n = 0

    def run_enabled(self, t_ns: int) -> None:
        self.n += 1

    def run_safed(self, t_ns: int) -> None:
        pass
