"""The worst day on real node processes (tests/faults/live.py has the cases
and what each proves). Loopback, dn0 behind a frame-tapping fault relay
where the case needs the link; every case is bounded in time and cleans up
its processes (``Live.close``) and relays."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.faults.live import CASES

pytestmark = [pytest.mark.faults, pytest.mark.timeout(150)]


@pytest.mark.parametrize("case", list(CASES))
def test_worst_day(case: str, tmp_path: Path) -> None:
    r = CASES[case](tmp_path, True)
    print(case, r.figures)
    assert r.ok, f"{case}: {r.failures()} figures={r.figures}"
