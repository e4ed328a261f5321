"""Operator and station key files: one per operator and per station of a
mission's ``ground:`` section (docs/security.md#stations-and-operators).

Each key derives from the ``operators`` key of ``cn.keys``
(:func:`zplatform.control.authority.identity_key`): ``zplatform keygen``
writes a new operator's file (or a new ``key_id``'s) without touching the
vehicle's keys. A file (mode 0600, text) holds the lines ``mission NAME``,
``operator NAME`` (or ``station NAME``), ``key_id N`` and ``key HEX``
(32 bytes), and ``#`` comments.

Contract: functions block on file I/O only; a bad file raises
:class:`~zplatform.core.auth.KeyError_` (one line, naming the file and what
to do); files are written aside and renamed (never half a file).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import NamedTuple

from ..config import Mission
from ..control.authority import IDENTITY_LINK, Signer, identity_key
from ..core.auth import KEY_LEN, KeyError_, KeySet, key_file_name, read_key_file

__all__ = [
    "IdentityFile",
    "Signer",
    "identity_file_name",
    "load_signer",
    "read_identity_file",
    "sim_signer",
    "write_identity_files",
]

_MAX_FILE = 4096


class IdentityFile(NamedTuple):
    """One operator's or station's key, as read from its file."""

    kind: str
    """``operator`` or ``station``."""
    name: str
    key_id: int
    key: bytes


def identity_file_name(kind: str, name: str) -> str:
    """``operator-<name>.keys`` or ``station-<name>.keys``."""
    return f"{kind}-{name}.keys"


def _entries(mission: Mission) -> list[tuple[str, str, int]]:
    g = mission.ground
    if g is None:
        return []
    return [("operator", o.name, o.key_id) for o in g.operators] + [
        ("station", s.name, s.key_id) for s in g.stations
    ]


def _write_private(path: Path, text: str) -> None:
    aside = path.with_name(path.name + ".new")
    try:
        aside.unlink(missing_ok=True)
        fd = os.open(aside, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise KeyError_(f"cannot write a key file {path}: {exc.strerror}") from exc
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(aside, path)


def write_identity_files(
    mission: Mission, directory: str | Path, *, replace: bool = False
) -> dict[str, Path]:
    """Write the key file of every operator and station of ``mission``'s
    ``ground:`` section that ``directory`` lacks (all of them with
    ``replace``), each derived from the ``operators`` key in the
    directory's ``cn.keys``; returns ``{file name: path}`` of those written.
    A file whose key id the mission has since raised is rewritten (the old
    key no longer verifies). KeyError_ when ``cn.keys`` is missing or holds
    no ``operators`` key (make the set with `zplatform keygen --rotate`)."""
    if mission.ground is None:
        return {}
    d = Path(directory)
    cn = read_key_file(d / key_file_name("cn"), mission)
    if not cn.has(IDENTITY_LINK):
        raise KeyError_(
            f"{d / key_file_name('cn')} holds no `{IDENTITY_LINK}` key (a key set made before "
            "the mission had `ground:`): `zplatform keygen --rotate` makes a new set with it"
        )
    base = cn.link_key(IDENTITY_LINK)
    out: dict[str, Path] = {}
    for kind, name, key_id in _entries(mission):
        p = d / identity_file_name(kind, name)
        if p.exists() and not replace:
            try:
                if read_identity_file(p, mission).key_id == key_id:
                    continue
            except KeyError_:
                pass  # damaged or stale: written anew
        key = identity_key(base, mission.vehicle, kind, name, key_id)
        _write_private(
            p,
            "\n".join(
                [
                    f"# zplatform {kind} key of mission {mission.mission!r}: {kind} {name!r}, "
                    f"key {key_id}.",
                    "# Secret: keep it mode 0600, with that "
                    + ("operator only." if kind == "operator" else "station's host only."),
                    f"mission {mission.mission}",
                    f"{kind} {name}",
                    f"key_id {key_id}",
                    f"key {key.hex()}",
                ]
            )
            + "\n",
        )
        out[p.name] = p
    return out


def read_identity_file(path: str | Path, mission: Mission) -> IdentityFile:
    """The operator's or station's key in ``path`` (module doc). KeyError_
    when it is missing, open to others, malformed, another mission's, names
    someone the mission does not list, or holds an old key id."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        raise KeyError_(f"cannot read the key file {p}: {exc.strerror}") from exc
    if not stat.S_ISREG(st.st_mode) or st.st_size > _MAX_FILE:
        raise KeyError_(f"{p} is no operator or station key file")
    if stat.S_IMODE(st.st_mode) & 0o077:
        raise KeyError_(f"{p} is open to others: run `chmod 600 {p}`")
    try:
        text = p.read_bytes().decode("ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise KeyError_(f"cannot read the key file {p}: {exc}") from exc
    fields: dict[str, str] = {}
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        k, _, v = line.partition(" ")
        if k not in ("mission", "operator", "station", "key_id", "key") or not v or k in fields:
            raise KeyError_(f"{p}:{n}: expected `mission`, `operator`/`station`, `key_id`, `key`")
        fields[k] = v.strip()
    kinds = [k for k in ("operator", "station") if k in fields]
    if len(kinds) != 1 or not {"mission", "key_id", "key"} <= set(fields):
        raise KeyError_(f"{p} is no operator or station key file")
    kind = kinds[0]
    name = fields[kind]
    if fields["mission"] != mission.mission:
        raise KeyError_(f"{p} is a key of mission {fields['mission']!r}, not {mission.mission!r}")
    listed = {(k, n): i for k, n, i in _entries(mission)}
    if (kind, name) not in listed:
        raise KeyError_(f"{p}: mission {mission.mission!r} lists no {kind} {name!r} (ground:)")
    try:
        key_id = int(fields["key_id"])
        key = bytes.fromhex(fields["key"])
    except ValueError:
        raise KeyError_(f"{p}: key_id must be a number, key {2 * KEY_LEN} hex digits") from None
    if len(key) != KEY_LEN:
        raise KeyError_(f"{p}: the key must be {KEY_LEN} bytes")
    if key_id != listed[(kind, name)]:
        raise KeyError_(
            f"{p} holds key {key_id} of {kind} {name}, the mission names key "
            f"{listed[(kind, name)]}: an old key (`zplatform keygen` writes the new one)"
        )
    return IdentityFile(kind, name, key_id, key)


def load_signer(mission: Mission, operator_file: str | Path, station_file: str | Path) -> Signer:
    """The :class:`Signer` of an operator's and a station's key files
    (KeyError_ when either is refused, or they are swapped)."""
    op = read_identity_file(operator_file, mission)
    st = read_identity_file(station_file, mission)
    if op.kind != "operator" or st.kind != "station":
        raise KeyError_(
            f"expected an operator's then a station's key file, got {op.kind}, {st.kind}"
        )
    return Signer(op.name, op.key, st.name, st.key)


def sim_signer(keys: KeySet, mission: Mission, operator: str, station: str) -> Signer:
    """The :class:`Signer` of ``operator`` at ``station`` derived from a key
    set holding the ``operators`` key (a lockstep run's, tests)."""
    g = mission.ground
    assert g is not None
    base = keys.link_key(IDENTITY_LINK)
    op = next(o for o in g.operators if o.name == operator)
    st = next(s for s in g.stations if s.name == station)
    return Signer(
        operator,
        identity_key(base, mission.vehicle, "operator", operator, op.key_id),
        station,
        identity_key(base, mission.vehicle, "station", station, st.key_id),
    )
