"""Live runs shared by the system tests (tests/live_runs.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.live_runs import led_script_run


@pytest.fixture(scope="session")
def led_live_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The LED platform's scripted run under ``up``, made once (its directory)."""
    return led_script_run(tmp_path_factory.mktemp("led_live"))


@pytest.fixture(scope="session")
def led_live_run_zenoh(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same run with every sync pinned to zenoh (``transport.intra_host:
    zenoh``), beside ``led_live_run``'s (``auto``: shared memory on one host)."""
    return led_script_run(tmp_path_factory.mktemp("led_live_zenoh"), intra_host="zenoh")
