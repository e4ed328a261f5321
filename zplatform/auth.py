"""Authentication of every frame a node takes from the network (DESIGN.md §1).

With ``security.auth`` on (the default), every region frame, telemetry
snapshot and command request travels as ``frame || tag``: ``tag`` is the
first :data:`TAG_LEN` bytes of HMAC-SHA256 over the frame, keyed by a
*channel key* derived from the mission key and the channel's name::

    channel_key = HMAC-SHA256(mission_key, "zplatform/1/" + vehicle + "/" + channel)

Channels are directions of the key space: ``cn_to_dnX`` (the sync query),
``dnX_to_cn`` (its reply), ``telemetry`` and ``gn_to_cn`` (command
requests). A frame tagged for one channel fails on every other, so a reply
cannot be replayed as a query, nor telemetry as a command. Replays *within*
a channel are the receivers' to refuse, and they do: a DN runs a trigger
only for a newer loop stamped within a window of its own clock, the CN
applies a reply only for the loop it asked, the ground only newer
telemetry, and commands carry the CN's epoch and a growing number.

The mission key is 32 random bytes, never in the mission YAML. It is read,
first match wins, from: an explicit path (``--key-file``), the file named
by ``ZPLATFORM_KEY_FILE``, hex in ``ZPLATFORM_KEY``, or the mission's
default key file ``~/.config/zplatform/keys/<mission>.key``.
``zplatform keygen MISSION`` writes that file (mode 0600); ``zplatform up``
creates it on first use, so a single-host run needs no set-up. Copy it to
every host of a multi-host mission and to the ground station.

Cost: one ``hmac.digest`` per frame (about 1-2 us for a few hundred bytes)
and :data:`TAG_LEN` bytes on the wire.
"""

from __future__ import annotations

import hmac
import os
import secrets
from pathlib import Path

from .config import Mission
from .errors import CodecError, ZPlatformError

__all__ = [
    "KEY_ENV",
    "KEY_FILE_ENV",
    "TAG_LEN",
    "AuthError",
    "Channel",
    "KeyError_",
    "default_key_path",
    "load_key",
    "mission_channels",
    "write_key",
]

TAG_LEN = 16
"""HMAC-SHA256 truncated to 128 bits (as in RFC 4868's HMAC-SHA-256-128)."""
KEY_ENV = "ZPLATFORM_KEY"
KEY_FILE_ENV = "ZPLATFORM_KEY_FILE"
_KEY_LEN = 32


class AuthError(CodecError):
    """A frame without a valid tag for its channel: never applied, counted
    as a bad frame like any other malformed input."""


class KeyError_(ZPlatformError):
    """The mission key is missing or unreadable; the message says how to make one."""


def default_key_path(mission: Mission | str) -> Path:
    """``~/.config/zplatform/keys/<mission>.key`` (XDG_CONFIG_HOME respected)
    of a mission, or of a mission name (checked by the caller)."""
    name = mission if isinstance(mission, str) else mission.mission
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "zplatform" / "keys" / f"{name}.key"


def _parse(text: str, where: str) -> bytes:
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise KeyError_(f"{where}: the mission key must be hex (64 hex digits)") from None
    if len(key) < 16:
        raise KeyError_(f"{where}: the mission key is {len(key)} bytes; at least 16 are needed")
    return key


def write_key(path: str | Path) -> Path:
    """Write a new random mission key to ``path`` (mode 0600, parents made).

    Refuses to overwrite an existing file (KeyError_): a new key locks
    every node that still has the old one out."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise KeyError_(f"{p} exists; remove it first to make a new key") from None
    except OSError as exc:
        raise KeyError_(f"cannot write a key to {p}: {exc.strerror}") from exc
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_hex(_KEY_LEN) + "\n")
    return p


def load_key(
    mission: Mission, key_file: str | Path | None = None, *, create: bool = False
) -> bytes | None:
    """The mission key (module doc for where it is looked up), or None when
    the mission turns authentication off.

    ``create``: make the default key file if no key is found anywhere (what
    ``zplatform up`` does on first use). Raises KeyError_ naming every
    place it looked when there is none."""
    if not mission.security.auth:
        return None
    if key_file is not None:
        p = Path(key_file)
    elif os.environ.get(KEY_FILE_ENV):
        p = Path(os.environ[KEY_FILE_ENV])
    elif os.environ.get(KEY_ENV):
        return _parse(os.environ[KEY_ENV], KEY_ENV)
    else:
        p = default_key_path(mission)
        if create and not p.exists():
            write_key(p)
    try:
        return _parse(p.read_text(), str(p))
    except FileNotFoundError:
        raise KeyError_(
            f"mission {mission.mission!r} authenticates its traffic and no key was found at "
            f"{p}: make one with `zplatform keygen {mission.mission}` (or point "
            f"{KEY_FILE_ENV} at a key file) and copy it to every host"
        ) from None
    except OSError as exc:
        raise KeyError_(f"cannot read the mission key {p}: {exc.strerror}") from exc


class Channel:
    """Tags and checks the frames of one channel (module doc).

    :meth:`seal` returns this channel's own buffer (overwritten by the next
    call; resized only if the frame length changes). :meth:`open` returns a
    view of the frame inside ``payload`` (no copy) or raises AuthError. Not
    thread-safe: one per sending or receiving loop.
    """

    __slots__ = ("_buf", "_key", "name")

    def __init__(self, key: bytes, vehicle: str, name: str) -> None:
        self.name = name
        self._key = hmac.digest(key, f"zplatform/1/{vehicle}/{name}".encode(), "sha256")
        self._buf = bytearray()

    def tag(self, frame: bytes | bytearray | memoryview) -> bytes:
        return hmac.digest(self._key, frame, "sha256")[:TAG_LEN]

    def seal(self, frame: bytes | bytearray | memoryview) -> bytearray:
        n = len(frame)
        if len(self._buf) != n + TAG_LEN:
            self._buf = bytearray(n + TAG_LEN)
        buf = self._buf
        buf[:n] = frame
        buf[n:] = self.tag(frame)
        return buf

    def open(self, payload: bytes | bytearray | memoryview) -> memoryview:
        mv = memoryview(payload)
        n = len(mv) - TAG_LEN
        if n <= 0:
            raise AuthError(f"{self.name}: {len(mv)} bytes, too short to carry a tag")
        body = mv[:n]
        if not hmac.compare_digest(self.tag(body), mv[n:]):
            raise AuthError(f"{self.name}: bad authentication tag (wrong key, or forged)")
        return body


def mission_channels(mission: Mission, key: bytes | None) -> dict[str, Channel | None]:
    """Every channel of the mission, by name; all None when ``key`` is None."""
    names = ["telemetry"]
    if mission.has_ground:
        names.append("gn_to_cn")
    for dn in mission.device_nodes:
        names += [f"cn_to_{dn}", f"{dn}_to_cn"]
    return {n: (Channel(key, mission.vehicle, n) if key is not None else None) for n in names}
