"""Floods from a keyless peer (tests/faults/floods.py has the cases and what
each proves): the query flood and the rogue replier at 6,000 frames per
second for 3 s each, and the command-replay stream with the operator's NOOP
in it, in one recovery_igniter flight on plain TCP (about 20 s: ``-m slow``, as
the issue states it); and a restarted DN accepted beside a rogue replier
(the default suite's live flood test; tests/unit/test_intake.py holds the
intake's rules, the command replay's included)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.faults.floods import CASES

pytestmark = [pytest.mark.faults, pytest.mark.timeout(300)]


@pytest.mark.parametrize(
    "case", [pytest.param("floods_in_flight", marks=pytest.mark.slow), "restart_beside_rogue"]
)
def test_flood(case: str, tmp_path: Path) -> None:
    r = CASES[case](tmp_path, True)
    print(case, r.figures)
    assert r.ok, f"{case}: {r.failures()} figures={r.figures}"
