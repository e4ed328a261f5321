"""Mission parameters: values a ground crew tunes without a rebuild (sans-IO core, file I/O).

Holds :class:`ParamTable` (each parameter is a ``cn`` element named after it,
so it is in telemetry, logs and replays like any element; PRM_SET and
PRM_SAVE, judged by :mod:`zplatform.control.commands`, change and save it), the
parameter file (:func:`params_path`: ``$ZPLATFORM_PARAMS_DIR`` or ``params/``
beside the key files, ``XDG_CONFIG_HOME`` respected; :func:`params_layout_id`;
:func:`write_atomic`), the savers (:class:`ParamSaver`, a writer thread, and
:class:`MemorySaver` for the lockstep runner) and the load-time checks.

Contract: the table runs on the CN's loop thread and never blocks; a save is
handed to a saver and its result comes back as an input of a later loop
(``ControlLogic.finish(saves=...)``), recorded for replay. :func:`write_atomic`
(temporary file, fsync, rename, fsync of the directory, under a lock file)
leaves the old file or the new one after a kill at any point.
:meth:`ParamTable.load` never raises for a bad file: a missing, corrupt or
foreign file leaves every default with an event, a value out of bounds alone.

The file format: codecs/FORMAT.md (section 10); operating it: docs/operations.md#parameters.
"""

from __future__ import annotations

import fcntl
import logging
import math
import os
import queue
import struct
import threading
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
import numpy as np

from ..config import Mission, ParamConfig
from ..config.codes import ParamLoad, ParamSave
from ..core.events import EV, EventLog
from ..core.health import Heartbeat
from ..errors import ConfigError, ZPlatformError

if TYPE_CHECKING:
    from ..core.datavector import DataVector, Handle

__all__ = [
    "FILE_MAGIC",
    "FILE_VERSION",
    "PARAMS_DIR_ENV",
    "SAVE_STEPS",
    "MemorySaver",
    "ParamFile",
    "ParamFileError",
    "ParamSaver",
    "ParamSlot",
    "ParamTable",
    "SaveResult",
    "check_config",
    "decode_params",
    "encode_params",
    "param_states",
    "params_layout_id",
    "params_path",
    "read_params_file",
    "write_atomic",
]

log = logging.getLogger("zplatform.params")

PARAMS_DIR_ENV = "ZPLATFORM_PARAMS_DIR"
FILE_MAGIC = b"ZPPRM\x00"
FILE_VERSION = 1
_HEAD = struct.Struct("<6sHII")  # magic, version, body length, body CRC-32
_LAYOUT_MAGIC = "zplatform-params-v1"
SAVE_STEPS = ("opened", "partial", "written", "synced", "renamed", "dir_synced")
"""The points of :func:`write_atomic` at which its ``step`` hook is called,
in order (a test kills the writer at each)."""

Value = int | float | bool


# ---------------------------------------------------------------------------
# configuration


def _state_names(mission: Mission) -> list[str]:
    sm = mission.state_machine
    return list(sm.states) if sm is not None else ["IDLE"]


def _allows(mission: Mission, state: str, command: str) -> bool:
    wl = mission.commands.whitelist
    return state not in wl or command in wl[state]


def param_states(mission: Mission, p: ParamConfig) -> list[str]:
    """The states in which ``p`` may change (its ``states``, or all)."""
    return list(p.states) if p.states is not None else _state_names(mission)


def check_config(mission: Mission, *, warn: bool = True) -> None:
    """Check ``params`` against the state machine and the command rules;
    raises ConfigError naming the YAML path.

    * every name in ``states`` is a state;
    * a hazardous parameter (or PRM_SET in ``commands.hazardous``) in a
      state whose whitelist allows PRM_SET needs ARM allowed there too.

    With ``warn``, logs a warning for a parameter that can change in no
    state (no state of its ``states`` allows PRM_SET).
    """
    states = _state_names(mission)
    hazardous_cmd = "PRM_SET" in mission.commands.hazardous
    for i, p in enumerate(mission.params):
        w = f"$.params[{i}]"
        for j, s in enumerate(p.states or ()):
            if s not in states:
                raise ConfigError(f"{s!r} is not a state; states: {states}", f"{w}.states[{j}]")
        open_in = [s for s in param_states(mission, p) if _allows(mission, s, "PRM_SET")]
        if p.hazardous or hazardous_cmd:
            for s in open_in:
                if not _allows(mission, s, "ARM"):
                    raise ConfigError(
                        f"parameter {p.name} is hazardous (ARM n, then PRM_SET n+1) and may "
                        f"change in state {s}, whose whitelist does not allow ARM",
                        f"{w}.hazardous" if p.hazardous else "$.commands.hazardous",
                    )
        if warn and not open_in:
            log.warning(
                "parameter %s can change in no state (none of its states allows PRM_SET) - at `%s`",
                p.name,
                w,
            )


def params_layout_id(mission: Mission) -> int:
    """A stable u32 of the parameters' names and types, in order: a file
    saved for another list is refused (``FOREIGN``). Bounds, defaults and
    states are not in it: they may change with the mission file, and a
    saved value outside new bounds falls back to its default alone."""
    text = ";".join([_LAYOUT_MAGIC, *(f"{p.name}:{p.type}" for p in mission.params)])
    return zlib.crc32(text.encode()) & 0xFFFFFFFF


def params_path(mission: Mission | str) -> Path:
    """The parameter file of a mission (or mission name): ``<dir>/<mission>.params``
    (module doc for ``<dir>``)."""
    name = mission if isinstance(mission, str) else mission.mission
    base = os.environ.get(PARAMS_DIR_ENV)
    if base:
        return Path(base) / f"{name}.params"
    config = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(config) / "zplatform" / "params" / f"{name}.params"


# ---------------------------------------------------------------------------
# the file


class ParamFileError(ZPlatformError):
    """A parameter file that cannot be used; ``status`` says how
    (``CORRUPT`` or ``FOREIGN``), the message why."""

    def __init__(self, status: ParamLoad, message: str) -> None:
        self.status = status
        super().__init__(message)


class ParamFile(msgspec.Struct, frozen=True):
    """The body of a parameter file: whose it is and the values.

    ``seq``: the PRM_SAVE request that wrote it; ``saved_ns``: the control
    node's loop time of that request."""

    mission: str
    layout_id: int
    seq: int
    saved_ns: int
    values: dict[str, Value]


_ENCODER = msgspec.msgpack.Encoder()
_DECODER = msgspec.msgpack.Decoder(ParamFile)


def encode_params(
    mission: Mission, values: Mapping[str, Value], *, seq: int = 0, saved_ns: int = 0
) -> bytes:
    """The bytes of a parameter file holding ``values`` (module doc)."""
    body = _ENCODER.encode(
        ParamFile(mission.mission, params_layout_id(mission), seq, saved_ns, dict(values))
    )
    return _HEAD.pack(FILE_MAGIC, FILE_VERSION, len(body), zlib.crc32(body)) + body


def decode_params(mission: Mission, data: bytes | bytearray | memoryview) -> ParamFile:
    """Check and decode a parameter file of ``mission``.

    Raises ParamFileError: ``CORRUPT`` for a bad magic, version, length
    (truncated or padded), checksum, encoding or a value list that is not
    the parameters' names; ``FOREIGN`` for another mission's file or another
    parameter list's. The values are not checked against their types or
    bounds (:meth:`ParamTable.load` does that, per parameter)."""
    data = bytes(data)
    corrupt = ParamLoad.CORRUPT
    if len(data) < _HEAD.size:
        raise ParamFileError(corrupt, f"{len(data)} bytes, shorter than the header")
    magic, version, n, crc = _HEAD.unpack_from(data)
    if magic != FILE_MAGIC:
        raise ParamFileError(corrupt, "not a zplatform parameter file (bad magic)")
    if version != FILE_VERSION:
        raise ParamFileError(corrupt, f"format version {version}, expected {FILE_VERSION}")
    body = data[_HEAD.size :]
    if len(body) != n:
        raise ParamFileError(corrupt, f"body of {len(body)} bytes, the header says {n}")
    if zlib.crc32(body) != crc:
        raise ParamFileError(corrupt, "checksum mismatch")
    try:
        f = _DECODER.decode(body)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ParamFileError(corrupt, f"undecodable body: {exc}") from None
    if f.mission != mission.mission:
        raise ParamFileError(
            ParamLoad.FOREIGN, f"saved by mission {f.mission!r}, not {mission.mission!r}"
        )
    if f.layout_id != params_layout_id(mission):
        raise ParamFileError(
            ParamLoad.FOREIGN,
            f"saved for another parameter list (layout {f.layout_id:#010x}, this mission's "
            f"{params_layout_id(mission):#010x}): names or types changed",
        )
    if set(f.values) != {p.name for p in mission.params}:
        raise ParamFileError(corrupt, "its values are not this mission's parameters")
    return f


def read_params_file(path: str | Path) -> bytes | OSError | None:
    """The bytes of the file at ``path``; None when there is none; the
    OSError when it cannot be read (for :meth:`ParamTable.load`). Blocks on
    file I/O: call it before the loop starts."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        return exc


def write_atomic(
    path: str | Path, data: bytes, *, step: Callable[[str], None] | None = None
) -> None:
    """Replace the file at ``path`` by ``data``, atomically and durably:
    write ``.<name>.tmp`` beside it, fsync it, rename it over ``path``,
    fsync the directory (its parent directories are made first). Writers of
    one path take turns (an exclusive ``flock`` on ``.<name>.lock``), so two
    control nodes of one mission on a host cannot interleave their bytes.

    ``step`` is called with each name of :data:`SAVE_STEPS` as that point is
    reached (tests kill the process there). Blocks on file I/O and on the
    lock; raises OSError. Whatever point a crash hits, ``path`` holds the
    old bytes or ``data``, never a mix.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.tmp")
    hook = step or (lambda _: None)
    lock = os.open(p.with_name(f".{p.name}.lock"), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when closed, or with the process
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            hook("opened")
            half = len(data) // 2
            _write_all(fd, data[:half])
            hook("partial")
            _write_all(fd, data[half:])
            hook("written")
            os.fsync(fd)
            hook("synced")
        finally:
            os.close(fd)
        os.replace(tmp, p)
        hook("renamed")
        dfd = os.open(p.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
        hook("dir_synced")
    finally:
        os.close(lock)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


# ---------------------------------------------------------------------------
# savers (the driver's side of PRM_SAVE)


class SaveResult(msgspec.Struct, frozen=True):
    """How a save ended: ``seq`` the PRM_SAVE's number, ``ok``, and
    ``detail``: where it went, or why it failed."""

    seq: int
    ok: bool
    detail: str


class ParamSaver:
    """Writes parameter files on a thread of its own, so the loop never
    waits for a disk.

    :meth:`submit` (loop thread) queues one save and returns at once;
    :meth:`poll` (loop thread) returns a finished one, or None; neither
    blocks. ``step`` is passed to :func:`write_atomic` (tests). :meth:`close`
    finishes the saves queued and stops the thread (idempotent; blocks).
    The thread checks in through :attr:`heartbeat` (``params``,
    :mod:`zplatform.core.health`): idle while it waits for a save, beating while
    it writes one, so a write stuck on a hung disk is a stalled thread.
    """

    def __init__(self, path: str | Path, *, step: Callable[[str], None] | None = None) -> None:
        self.path = Path(path)
        self._step = step
        self._todo: queue.SimpleQueue[tuple[int, bytes] | None] = queue.SimpleQueue()
        self._done: queue.SimpleQueue[SaveResult] = queue.SimpleQueue()
        self.heartbeat = Heartbeat("params")
        self._thread = threading.Thread(target=self._run, name="param-saver", daemon=True)
        self._thread.start()
        self._closed = False

    def submit(self, seq: int, data: bytes) -> None:
        """Queue ``data`` as save ``seq``. Never blocks."""
        self._todo.put((seq, data))

    def poll(self) -> SaveResult | None:
        """A finished save, or None. Never blocks; allocates nothing when
        none finished (the loop calls it every loop)."""
        if self._done.empty():
            return None
        return self._done.get_nowait()

    def _run(self) -> None:
        hb = self.heartbeat
        hb.idle()
        while (job := self._todo.get()) is not None:
            hb.beat()
            seq, data = job
            try:
                write_atomic(self.path, data, step=self._step)
                self._done.put(SaveResult(seq, True, str(self.path)))
            except OSError as exc:
                why = f"{self.path}: {exc.strerror or exc}"
                self._done.put(SaveResult(seq, False, why))
            finally:
                hb.idle()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._todo.put(None)
        self._thread.join()


class MemorySaver:
    """The lockstep runner's saver: a save is kept in memory (:attr:`data`)
    and answered by the next :meth:`poll`, so a run repeats exactly."""

    def __init__(self) -> None:
        self.data: bytes | None = None
        """The last file saved (bytes of :func:`encode_params`)."""
        self._done: SaveResult | None = None

    def submit(self, seq: int, data: bytes) -> None:
        self.data = data
        self._done = SaveResult(seq, True, "memory (a lockstep run writes no file)")

    def poll(self) -> SaveResult | None:
        done, self._done = self._done, None
        return done


# ---------------------------------------------------------------------------
# the control node's table


class ParamSlot:
    """One parameter as the command handler checks a PRM_SET of it.

    ``allowed[state]``: whether it may change in state index ``state``."""

    __slots__ = ("allowed", "config", "handle", "hazardous", "hi", "lo", "name")

    def __init__(self, config: ParamConfig, handle: Handle, allowed: tuple[bool, ...]) -> None:
        self.config = config
        self.name = config.name
        self.handle = handle
        self.allowed = allowed
        self.hazardous = config.hazardous
        self.lo = config.min
        self.hi = config.max

    def in_bounds(self, v: Value) -> bool:
        """Whether ``v`` lies within ``[min, max]`` (always, for a bool)."""
        if self.lo is None or self.hi is None:
            return True
        return self.lo <= v <= self.hi

    def text(self, v: Value) -> str:
        """``v`` as this parameter stores it, shortest form (an f32's
        ``2.2``, not the double nearest to it)."""
        if self.handle.spec.scalar.name == "f32" and isinstance(v, float):
            return str(np.float32(v))
        return repr(v)

    def bounds_text(self) -> str:
        units = f" {self.config.units}" if self.config.units else ""
        return f"[{self.lo!r}, {self.hi!r}]{units}"


class ParamTable:
    """The control node's parameters: slots for the command handler, the
    load at start, PRM_SAVE's snapshot and its result (module doc).

    Sans-IO: file bytes come in (:meth:`load`), save bytes go out
    (:meth:`take_save`), save results come in (:meth:`saved`). Every method
    runs on the loop thread and never raises for what comes in; only the
    rare ones (a load, a save) allocate.
    """

    def __init__(self, mission: Mission, dv: DataVector, events: EventLog) -> None:
        self.mission = mission
        self._events = events
        self.slots: tuple[ParamSlot, ...] = ()
        self._by_index: tuple[ParamSlot | None, ...] = ()
        self._pending: tuple[int, bytes] | None = None
        if not mission.params:
            return
        states = _state_names(mission)
        slots = []
        for p in mission.params:
            allowed = set(param_states(mission, p))
            slots.append(ParamSlot(p, dv.handle(p.name), tuple(s in allowed for s in states)))
        self.slots = tuple(slots)
        by_index: list[ParamSlot | None] = [None] * len(dv.layout.elements)
        for s in slots:
            by_index[s.handle.spec.index] = s
        self._by_index = tuple(by_index)
        self._h_load = dv.handle("cn_prm_load_status")
        self._h_save_seq = dv.handle("cn_prm_save_seq")
        self._h_save = dv.handle("cn_prm_save_status")
        self._h_unsaved = dv.handle("cn_prm_unsaved")

    def slot(self, index: int) -> ParamSlot | None:
        """The parameter whose element has index ``index``, or None."""
        return self._by_index[index] if index < len(self._by_index) else None

    def values(self) -> dict[str, Value]:
        """Every parameter's value now, by name."""
        return {s.name: s.handle.get() for s in self.slots}

    # -- PRM_SET ------------------------------------------------------------
    def changed(self) -> None:
        """A PRM_SET was applied: the values differ from the last save."""
        self._h_unsaved.set(True)

    # -- loading at start ---------------------------------------------------
    def load(self, data: bytes | OSError | None, t_ns: int, *, source: str) -> ParamLoad:
        """Apply a parameter file read at ``source`` before loop 1
        (:func:`read_params_file`'s result: the bytes, None for no file, or
        the OSError): the file's values, or the defaults with an event
        (module doc). Returns the status written to ``cn_prm_load_status``."""
        if not self.slots:
            return ParamLoad.DEFAULTS
        for s in self.slots:
            s.handle.set(s.config.default)
        self._h_unsaved.set(False)
        status = self._load(data, t_ns, source)
        self._h_load.set(status)
        return status

    def _load(self, data: bytes | OSError | None, t_ns: int, source: str) -> ParamLoad:
        if data is None:
            self._events.emit(EV.PRM_FILE_MISSING, t_ns, path=source)
            return ParamLoad.MISSING
        if isinstance(data, OSError):
            self._refused(ParamLoad.UNREADABLE, data.strerror or str(data), source, t_ns)
            return ParamLoad.UNREADABLE
        try:
            f = decode_params(self.mission, data)
        except ParamFileError as exc:
            self._refused(exc.status, str(exc), source, t_ns)
            return exc.status
        partial = False
        for s in self.slots:
            v = f.values[s.name]
            why = self._unusable(s, v)
            if why:
                partial = True
                self._events.emit(
                    EV.PRM_DEFAULTED, t_ns, name=s.name, why=why, default=s.config.default
                )
                continue
            s.handle.set(v)
        n = len(self.slots)
        self._events.emit(EV.PRM_LOADED, t_ns, path=source, n=n, seq=f.seq)
        return ParamLoad.PARTIAL if partial else ParamLoad.LOADED

    @staticmethod
    def _unusable(s: ParamSlot, v: Value) -> str:
        """Why a saved value cannot be used ("" when it can)."""
        st = s.handle.spec.scalar
        if isinstance(v, float) and not math.isfinite(v):
            return f"the saved value {v!r} is not finite"
        if st.kind == "bool" and not isinstance(v, bool):
            return f"the saved value {v!r} is not true or false"
        if not st.fits(v) or (st.kind == "int" and isinstance(v, float)):
            return f"the saved value {v!r} does not fit {st.name}"
        if not s.in_bounds(v):
            return f"the saved value {v!r} is outside {s.bounds_text()}"
        return ""

    def _refused(self, status: ParamLoad, why: str, source: str, t_ns: int) -> None:
        self._events.emit(EV.PRM_FILE_REFUSED, t_ns, path=source, status=status.name, why=why)

    # -- PRM_SAVE -----------------------------------------------------------
    @property
    def saving(self) -> int:
        """The number of the PRM_SAVE being written, or 0."""
        if self.slots and self._h_save.get() == ParamSave.PENDING:
            return int(self._h_save_seq.get())
        return 0

    def request_save(self, seq: int, t_ns: int) -> None:
        """PRM_SAVE ``seq`` was accepted: snapshot the values into file bytes
        for the driver (:meth:`take_save`); the save is pending."""
        data = encode_params(self.mission, self.values(), seq=seq, saved_ns=t_ns)
        self._pending = (seq, data)
        self._h_save_seq.set(seq)
        self._h_save.set(ParamSave.PENDING)
        self._h_unsaved.set(False)

    def adopt(self, t_ns: int) -> None:
        """Take up the parameter store's state from the Data Vector (a
        takeover, :meth:`zplatform.control.loop.ControlLogic.adopt`): a PRM_SAVE that
        the previous commander was still writing is written again, by this
        node, to its own file (the values are those the vector holds, which
        the save snapshot)."""
        self._pending = None
        seq = self.saving
        if seq:
            data = encode_params(self.mission, self.values(), seq=seq, saved_ns=t_ns)
            self._pending = (seq, data)

    def take_save(self) -> tuple[int, bytes] | None:
        """The save to write now ``(seq, file bytes)``, once; None when there
        is none (the common case: no allocation)."""
        pending, self._pending = self._pending, None
        return pending

    def saved(self, result: SaveResult, t_ns: int) -> None:
        """A save came back from the driver: ``cn_prm_save_status`` and an
        event. A result for another save than the pending one is ignored."""
        if self.saving != result.seq or result.seq == 0:
            return
        if result.ok:
            self._h_save.set(ParamSave.SAVED)
            self._events.emit(EV.PRM_SAVED, t_ns, seq=result.seq, where=result.detail)
        else:
            self._h_save.set(ParamSave.FAILED)
            self._h_unsaved.set(True)
            self._events.emit(EV.PRM_SAVE_FAILED, t_ns, seq=result.seq, why=result.detail)
