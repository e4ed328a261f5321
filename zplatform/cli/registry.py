"""Running missions: what ``zplatform up`` registers and every verb can find.

Each running ``up`` writes one JSON file, ``{name}.json``, into the runtime
directory (:func:`runtime_dir`): ``$XDG_RUNTIME_DIR/zplatform`` when that is
set, ``/run/zplatform`` for root, else ``/tmp/zplatform-{uid}``. The name is
the mission's name, with ``-2``, ``-3``, ... when another ``up`` of the same
mission already runs. The entry (:class:`Entry`) holds the ``up`` PID, the
effective mission file (the remapped copy for ``--free-ports``, kept in the
runtime directory for the run's lifetime), the nodes' PIDs and endpoints,
the log paths and the start time.

``up`` removes its entry on exit (also after Ctrl-C or SIGTERM). An entry
whose ``up`` process is gone (``kill -9``, a crash) is stale:
:func:`running` deletes it, and its mission copy, when it reads it.

:func:`resolve_mission` is what every verb does with its MISSION argument:
an existing file wins, else the name of a running mission, else a
:class:`~zplatform.errors.CommandError` saying what runs.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from pathlib import Path

import msgspec

from ..errors import CommandError

__all__ = [
    "ENV_DIR",
    "Entry",
    "Registration",
    "entries_json",
    "register",
    "resolve_mission",
    "running",
    "runtime_dir",
]

ENV_DIR = "ZPLATFORM_RUNTIME_DIR"  # overrides the directory (tests, several users)


class Entry(msgspec.Struct, frozen=True):
    """One running ``up``."""

    name: str
    mission: str
    pid: int
    mission_file: str
    source_file: str
    started: float
    endpoints: dict[str, list[str]] = msgspec.field(default_factory=dict)
    nodes: dict[str, int] = msgspec.field(default_factory=dict)
    logs: dict[str, str] = msgspec.field(default_factory=dict)


def runtime_dir() -> Path:
    """Where entries live (created 0700 on first use)."""
    override = os.environ.get(ENV_DIR)
    if override:
        d = Path(override)
    elif os.environ.get("XDG_RUNTIME_DIR"):
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "zplatform"
    elif os.geteuid() == 0:
        d = Path("/run/zplatform")
    else:
        d = Path(tempfile.gettempdir()) / f"zplatform-{os.getuid()}"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    return d


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(path: Path, entry: Entry | None) -> None:
    with contextlib.suppress(OSError):
        path.unlink()
    if entry is not None:
        mf = Path(entry.mission_file)
        if mf.parent == path.parent and mf.name.startswith(path.stem + "."):
            with contextlib.suppress(OSError):
                mf.unlink()


def running() -> list[Entry]:
    """Every registered mission whose ``up`` still runs, by start time.

    Stale entries (the ``up`` process is gone) are deleted on the way.
    """
    d = runtime_dir()
    out: list[Entry] = []
    for p in sorted(d.glob("*.json")):
        try:
            e = msgspec.json.decode(p.read_bytes(), type=Entry)
        except (OSError, msgspec.DecodeError, msgspec.ValidationError):
            # A half-written entry of an `up` starting right now is not stale.
            if time.time() - _mtime(p) > 60:
                _remove(p, None)
            continue
        if not _alive(e.pid):
            _remove(p, e)
            continue
        out.append(e)
    return sorted(out, key=lambda e: e.started)


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except OSError:
        return 0.0


class Registration:
    """The entry of this ``up``: :meth:`update` rewrites it, :meth:`remove` deletes it.

    Construction claims a name atomically (``O_EXCL``), so two ``up`` of one
    mission started together get distinct names.
    """

    def __init__(self, mission: str, source_file: str) -> None:
        running()  # clean stale entries first: their names become free
        d = runtime_dir()
        n = 1
        while True:
            name = mission if n == 1 else f"{mission}-{n}"
            path = d / f"{name}.json"
            try:
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            except FileExistsError:
                n += 1
                continue
            os.close(fd)
            break
        self.name = name
        self.path = path
        self.dir = d
        self.mission_file = str(d / f"{name}.mission.yaml")
        self._entry = Entry(
            name=name,
            mission=mission,
            pid=os.getpid(),
            mission_file=str(Path(source_file).resolve()),
            source_file=str(Path(source_file).resolve()),
            started=time.time(),
        )
        self._write()

    @property
    def entry(self) -> Entry:
        return self._entry

    def update(self, **fields: object) -> None:
        self._entry = msgspec.structs.replace(self._entry, **fields)
        self._write()

    def _write(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_bytes(msgspec.json.encode(self._entry))
        os.replace(tmp, self.path)

    def remove(self) -> None:
        """Delete the entry and the mission copy it owns. Idempotent."""
        _remove(self.path, self._entry)


def register(mission: str, source_file: str) -> Registration:
    """Claim a name for a running ``up`` of ``mission`` (see :class:`Registration`)."""
    return Registration(mission, source_file)


def _describe(entries: list[Entry]) -> str:
    if not entries:
        return "no mission is running (`zplatform up MISSION` starts one)"
    return "running: " + ", ".join(e.name for e in entries)


def resolve_mission(arg: str) -> str:
    """The mission file ``arg`` means: a file path, else a running mission's name.

    Raises CommandError naming what runs when ``arg`` is neither.
    """
    p = Path(arg)
    if p.is_file():
        return arg
    entries = running()
    # A running mission's name wins over a directory of that name (a team's
    # checkout holds `flight/` beside `configs/flight.yaml`): the directory
    # can never be a mission file, the running mission is what was meant.
    for e in entries:
        if e.name == arg:
            return e.mission_file
    if p.exists():
        kind = "a directory" if p.is_dir() else "a device, pipe or socket"
        raise CommandError(
            f"{arg} is {kind}, not a mission file, and no running mission is named "
            f"{arg!r}; {_describe(entries)}"
        )
    looks_like_path = os.sep in arg or arg.endswith((".yaml", ".yml"))
    what = "no such mission file" if looks_like_path else "no such file or running mission"
    # A bare name that is a mission file nearby (`led_test` for
    # configs/led_test.yaml, the form a new user types first): say which.
    near = [] if looks_like_path else _nearby_files(arg)
    hint = f"; did you mean the file {near[0]}?" if near else ""
    raise CommandError(f"{what}: {arg!r}{hint}; {_describe(entries)}")


def _nearby_files(name: str) -> list[str]:
    """Mission files named ``name`` in the current directory or its ``configs/``."""
    return [
        str(p)
        for d in (Path("."), Path("configs"))
        for p in (d / f"{name}.yaml", d / f"{name}.yml")
        if p.is_file()
    ]


def entries_json(entries: list[Entry]) -> str:
    """``zplatform ps --json``: a JSON list of the entries."""
    return json.dumps([msgspec.to_builtins(e) for e in entries], indent=2)
