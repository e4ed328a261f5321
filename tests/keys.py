"""Key set-up shared by the command-authority and key-file tests.

:func:`own_key_home` gives a test key files of its own; :data:`AUTH_VEHICLE`
is the small vehicle (a CN, one DN, a ground node) the authority, identity
and ground-operator tests put their ``ground:`` sections on."""

from __future__ import annotations

from pathlib import Path

import pytest

from zplatform.core.auth import KEY_ENV, KEY_FILE_ENV

AUTH_VEHICLE = """\
nodes: {cn: {}, dn0: {}, gn: {}}
health: null
regions:
  cn:
    - {name: x, type: u8}
  cn_to_dn0:
    - {name: valve, type: bool}
  dn0_to_cn:
    - {name: p, type: f32}
"""
"""A mission's nodes and regions, to follow its ``mission:`` line."""


def own_key_home(monkeypatch: pytest.MonkeyPatch, home: Path) -> Path:
    """No key from the environment (``ZPLATFORM_KEY`` and
    ``ZPLATFORM_KEY_FILE`` unset) and the user's configuration at ``home``
    (``XDG_CONFIG_HOME``, where key sets are found by default): the key
    files a test makes and reads are its own. Returns ``home`` (not made)."""
    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv(KEY_FILE_ENV, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home))
    return home
