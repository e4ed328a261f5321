"""Who a ground tool commands as: ``--operator NAME --station NAME``.

:func:`station_signer` turns the two names into the
:class:`~zplatform.control.authority.Signer` every request is tagged by
(:class:`~zplatform.control.uplink.Uplink`), reading ``operator-NAME.keys``
and ``station-NAME.keys`` from the directory the tool's other keys come
from (the ``ZPLATFORM_KEY_FILE`` file's directory, or the mission's key set
directory: :func:`zplatform.core.auth.load_keys`), or, where the keys come
from one master key (``ZPLATFORM_KEY``), derives both from it. Rules:
docs/security.md#stations-and-operators.

Contract: blocks on file reads only; every refusal is one line before any
session opens: CommandError for a name the mission does not list (with the
closest names) or a missing ``--operator`` where the mission needs one,
KeyError_ for a missing or refused key file (naming it and what to do).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..config import Mission
from ..control.authority import IDENTITY_LINK, Signer
from ..control.uplink import did_you_mean
from ..core.auth import KEY_ENV, KEY_FILE_ENV, KeyError_, default_key_dir, load_keys
from ..errors import CommandError
from ..security.identities import identity_file_name, load_signer, sim_signer

__all__ = ["check_names", "identity_dir", "line_signer", "station_signer"]


def identity_dir(mission: Mission, key_file: str | Path | None = None) -> Path:
    """Where the operator's and station's key files are looked for: the
    directory of ``key_file`` (or ``ZPLATFORM_KEY_FILE``; itself when it is
    a directory), else the mission's key set directory."""
    src = key_file if key_file is not None else os.environ.get(KEY_FILE_ENV) or None
    if src is None:
        return default_key_dir(mission)
    p = Path(src)
    return p if p.is_dir() else p.parent


def _pick(kind: str, name: str, listed: list[str], flag: str) -> None:
    if name not in listed:
        raise CommandError(
            f"{flag} {name}: mission lists no {kind} {name!r} (ground.{kind}s)"
            + (did_you_mean(name, listed) or f"; {kind}s: {', '.join(listed)}")
        )


def check_names(mission: Mission, operator: str | None, station: str | None) -> bool:
    """Whether a request must name ``operator`` at ``station``: False when
    neither is given and the mission takes requests that name nobody (no
    ``ground:`` section, or ``single_operator``). CommandError: a name
    given in a mission without ``ground:``, one of the two without the
    other, a name the mission does not list (with the closest), or none in
    a mission with command authority."""
    g = mission.ground
    if operator is None and station is None:
        if mission.authority:
            assert g is not None
            raise CommandError(
                f"mission {mission.mission!r} has command authority (ground:): say who "
                f"commands with --operator NAME --station NAME (operators: "
                f"{', '.join(o.name for o in g.operators)}; stations: "
                f"{', '.join(s.name for s in g.stations)})"
            )
        return False
    if g is None:
        raise CommandError(
            f"mission {mission.mission!r} has no `ground:` section: --operator and --station "
            "name its operators and stations"
        )
    if operator is None or station is None:
        raise CommandError("--operator and --station go together: name both")
    _pick("operator", operator, [o.name for o in g.operators], "--operator")
    _pick("station", station, [s.name for s in g.stations], "--station")
    return True


def station_signer(
    mission: Mission,
    operator: str | None,
    station: str | None,
    key_file: str | Path | None = None,
) -> Signer | None:
    """The signer of ``operator`` at ``station`` (module doc), or None when
    none is needed (:func:`check_names`, whose CommandError it raises);
    KeyError_: a key file missing or refused."""
    if not check_names(mission, operator, station):
        return None
    assert operator is not None and station is not None
    if key_file is None and not os.environ.get(KEY_FILE_ENV) and os.environ.get(KEY_ENV):
        # Keys from one master (ZPLATFORM_KEY, as load_keys takes them): the
        # operator's and station's derive from its `operators` key, as the
        # control node's do; no key files.
        keys = load_keys(mission, "cn")
        if keys is not None and keys.has(IDENTITY_LINK):
            return sim_signer(keys, mission, operator, station)
    d = identity_dir(mission, key_file)
    paths = [
        d / identity_file_name("operator", operator),
        d / identity_file_name("station", station),
    ]
    for p in paths:
        if not p.exists():
            raise KeyError_(
                f"no key file {p}: `zplatform keygen MISSION_FILE` writes it beside cn.keys; "
                f"copy it to this host (the directory of {KEY_FILE_ENV}, or {d})"
            )
    return load_signer(mission, paths[0], paths[1])


def line_signer(
    mission: Mission, operator: str, station: str, key_file: str | Path | None = None
) -> Signer:
    """The signer of a script line naming ``operator`` at ``station`` (``as
    alice@pad: ...``, :class:`zplatform.ground.script.ScriptPlayer`): their
    key files read as :func:`station_signer` reads them. CommandError for a
    mission whose requests name nobody (no ``ground:``, or
    ``single_operator`` takes them unnamed: a name is still checked)."""
    signer = station_signer(mission, operator, station, key_file)
    if signer is None:  # pragma: no cover - check_names raises first for given names
        raise CommandError(f"mission {mission.mission!r} has no operators to sign as")
    return signer
