"""Session-wide test set-up.

Every mission authenticates its traffic by default, so every node process a
test starts needs the mission key. The tests run with one random key in the
environment (``ZPLATFORM_KEY``), which the processes they spawn inherit;
nothing is written to the user's key directory.

Hypothesis runs without its per-example deadline (200 ms by default): the
suite must pass on a busy 2-core box beside a CPU hog, where one example may
wait that long for a CPU, and a test asserts behaviour, not the box's speed
(tests/budget.py).
"""

from __future__ import annotations

import os
import secrets

from hypothesis import settings

os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
os.environ.pop("ZPLATFORM_KEY_FILE", None)

settings.register_profile("zplatform", deadline=None)
settings.load_profile("zplatform")
