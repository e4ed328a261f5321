"""Fixtures shared by the unit tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.keys import own_key_home


@pytest.fixture
def keydir(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """Where a test's ``keygen --out`` writes its key files
    (``tmp_path/keys``, not made), with no key from the environment and a
    configuration home of the test's own (:func:`tests.keys.own_key_home`)."""
    own_key_home(monkeypatch, tmp_path / "config")
    return tmp_path / "keys"
