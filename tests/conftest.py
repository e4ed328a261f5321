"""Session-wide test set-up.

Every mission authenticates its traffic by default, so every node process a
test starts needs the mission key. The tests run with one random key in the
environment (``ZPLATFORM_KEY``), which the processes they spawn inherit;
nothing is written to the user's key directory.
"""

from __future__ import annotations

import os
import secrets

os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
os.environ.pop("ZPLATFORM_KEY_FILE", None)
