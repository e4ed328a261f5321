"""Session-wide test set-up.

Every mission authenticates its traffic by default, so every node process a
test starts needs the mission key. The tests run with one random key in the
environment (``ZPLATFORM_KEY``), which the processes they spawn inherit;
nothing is written to the user's key directory.

Missions with a flight recorder (the shipped flight and recovery_igniter
ones) record into a temporary directory of the session
(``ZPLATFORM_RECORDER_DIR``, inherited too), removed at its end: nothing is
written to the user's state directory.
"""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile

import pytest

os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
os.environ.pop("ZPLATFORM_KEY_FILE", None)
_RECORDER_DIR = tempfile.mkdtemp(prefix="zplatform-recorder-")
os.environ["ZPLATFORM_RECORDER_DIR"] = _RECORDER_DIR


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    shutil.rmtree(_RECORDER_DIR, ignore_errors=True)
