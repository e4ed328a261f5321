"""The mission key and frame authentication (zplatform.auth)."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from zplatform import load_mission
from zplatform.auth import (
    KEY_ENV,
    KEY_FILE_ENV,
    TAG_LEN,
    AuthError,
    Channel,
    KeyError_,
    default_key_path,
    load_key,
    write_key,
)
from zplatform.mission import decode_mission

ROOT = Path(__file__).resolve().parents[2]
MINIMAL = load_mission(ROOT / "configs" / "minimal.yaml")


@pytest.fixture
def no_env_key(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv(KEY_FILE_ENV, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    return tmp_path


def test_missing_key_says_how_to_make_one(no_env_key: Path) -> None:
    with pytest.raises(KeyError_) as ei:
        load_key(MINIMAL)
    msg = str(ei.value)
    assert "zplatform keygen minimal" in msg and str(default_key_path(MINIMAL)) in msg


def test_create_makes_a_private_key_once(no_env_key: Path) -> None:
    key = load_key(MINIMAL, create=True)
    p = default_key_path(MINIMAL)
    assert key is not None and len(key) == 32
    assert stat.S_IMODE(p.stat().st_mode) == 0o600
    assert load_key(MINIMAL, create=True) == key  # found, not remade
    with pytest.raises(KeyError_, match="exists"):
        write_key(p)


def test_lookup_order(no_env_key: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    f = write_key(no_env_key / "a.key")
    monkeypatch.setenv(KEY_ENV, "11" * 32)
    assert load_key(MINIMAL) == bytes([0x11]) * 32
    monkeypatch.setenv(KEY_FILE_ENV, str(f))
    assert load_key(MINIMAL) == bytes.fromhex(f.read_text())
    g = write_key(no_env_key / "b.key")
    assert load_key(MINIMAL, g) == bytes.fromhex(g.read_text())  # explicit wins


def test_bad_keys_are_refused(no_env_key: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(KEY_ENV, "not hex")
    with pytest.raises(KeyError_, match="hex"):
        load_key(MINIMAL)
    monkeypatch.setenv(KEY_ENV, "00" * 4)
    with pytest.raises(KeyError_, match="at least 16"):
        load_key(MINIMAL)


def test_a_mission_may_turn_authentication_off(no_env_key: Path) -> None:
    text = (ROOT / "configs" / "minimal.yaml").read_text() + "security: {auth: false}\n"
    assert load_key(decode_mission(text)) is None


def test_seal_and_open() -> None:
    ch = Channel(b"k" * 32, "rocket", "telemetry")
    sealed = bytes(ch.seal(b"hello"))
    assert len(sealed) == 5 + TAG_LEN and bytes(ch.open(sealed)) == b"hello"
    for bad in (sealed[:-1] + bytes([sealed[-1] ^ 1]), b"x" * 5, b"", sealed[1:]):
        with pytest.raises(AuthError):
            ch.open(bad)
    other = Channel(b"k" * 32, "other_vehicle", "telemetry")
    with pytest.raises(AuthError):
        other.open(sealed)


def test_keygen_verb(no_env_key: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in (KEY_ENV, KEY_FILE_ENV)}
    env["XDG_CONFIG_HOME"] = str(no_env_key)
    cmd = [sys.executable, "-m", "zplatform", "keygen", str(ROOT / "configs" / "minimal.yaml")]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0 and "wrote the key" in r.stdout
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 2 and "exists" in r.stderr and "Traceback" not in r.stderr


def test_keygen_takes_a_bare_mission_name(
    no_env_key: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The README's form, ``zplatform keygen led_test``, before the mission
    ever ran: the key of that name goes to the mission's key file, and the
    command says where; nodes then find it there."""
    from zplatform.cli import main

    monkeypatch.chdir(tmp_path)  # no file named like the mission here
    assert main(["keygen", "led_test"]) == 0
    out = capsys.readouterr().out
    path = no_env_key / "zplatform" / "keys" / "led_test.key"
    assert f"wrote the key of mission 'led_test' to {path}" in out
    assert path.stat().st_mode & 0o777 == 0o600
    assert default_key_path(load_mission(ROOT / "configs" / "led_test.yaml")) == path
    assert load_key(load_mission(ROOT / "configs" / "led_test.yaml")) == bytes.fromhex(
        path.read_text()
    )
    # A name the config would refuse, or a path that is not there: one error line.
    for bad, says in (("bad*name", "contains '*'"), ("missions/nope.yaml", "no such mission file")):
        assert main(["keygen", bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("zplatform: error: ") and says in err and err.count("\n") == 1, err


def test_the_tag_is_what_format_md_says() -> None:
    """codecs/FORMAT.md §6.1, computed by hand: a peer in another language
    can implement it from the document."""
    import hashlib
    import hmac

    key = bytes(range(32))
    frame = b"\x94\xce\x00\x00\x00\x01" + b"rest of a frame"
    ch_key = hmac.new(key, b"zplatform/1/rocket/telemetry", hashlib.sha256).digest()
    tag = hmac.new(ch_key, frame, hashlib.sha256).digest()[:16]
    assert bytes(Channel(key, "rocket", "telemetry").seal(frame)) == frame + tag
