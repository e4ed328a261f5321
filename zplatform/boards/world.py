"""The ``world`` board driver: a node's board live, its pins exchanged with
the mission's vehicle world process over UDP on loopback.

Live (``zplatform up``) the vehicle world (:mod:`zplatform.world.model`) is its own
process (``zplatform world MISSION``, :mod:`zplatform.sim.world_server`); a
node's board (``board: {driver: world}``) is a :class:`WorldLink` that sends
its outputs over UDP on loopback and latches the newest inputs it received.
:func:`node_board` builds any device node's board from the mission (a
:class:`WorldLink` for ``driver: world``, else
:func:`~zplatform.boards.make_board`); :func:`world_nodes` and
:func:`link_address` give the link's node numbers and address.

Contract: nothing waits on anything: a late datagram is older sensor data,
as on real hardware, and only inputs older than ``world.stale_ms`` fail a
step (a :class:`~zplatform.boards.BoardError`). The link is simulation
plumbing: unauthenticated, loopback only (checked at load); malformed
datagrams are counted and dropped.

The datagrams: codecs/FORMAT.md (section 14); the world: docs/architecture.md#drivers.
"""

from __future__ import annotations

import ipaddress
import socket
import struct
import time

from ..config import Mission
from ..core.components import mission_code_path
from ..errors import ConfigError
from .base import Board, BoardError, BoardHealth, HealthCounters, PinCounts, check_pin
from .registry import make_board

__all__ = ["WorldLink", "link_address", "node_board", "world_nodes"]

HEADER = struct.Struct("<2sBBH")
"""Every world link datagram's header: magic, type, node index, sequence."""
MAGIC = b"ZW"
OUTPUTS, INPUTS = 2, 3
"""Datagram types: a board's outputs (board -> world), its inputs (world -> board)."""
U64 = struct.Struct("<Q")


def link_address(listen: str, where: str) -> tuple[str, int]:
    """``listen`` as a loopback ``(host, port)``; ConfigError at ``where`` otherwise."""
    host, sep, port = listen.rpartition(":")
    try:
        if not sep:
            raise ValueError
        addr = (host.strip("[]"), int(port))
        if not ipaddress.ip_address(addr[0]).is_loopback or not 0 < addr[1] < 65536:
            raise ValueError
    except ValueError:
        raise ConfigError(
            f"listen {listen!r} must be a loopback 'host:port' (the world link is "
            "simulation plumbing and is not authenticated)",
            where,
        ) from None
    return addr


def world_nodes(mission: Mission) -> tuple[str, ...]:
    """The nodes the mission's world spans, in device-node order (the link's node index)."""
    w = mission.world
    return tuple(n for n in mission.device_nodes if w is not None and n in w.boards)


class WorldLink(PinCounts):
    """A node's board, live: its pins exchanged with the world process over UDP.

    Construction touches nothing; :meth:`open` makes the socket and sends
    the outputs (so the world knows where to send the inputs). Outputs are
    kept here and sent when one changes and with every :meth:`step`, which
    never waits: it takes every INPUTS datagram that arrived and latches the
    newest. Inputs older than ``world.stale_ms`` (or none yet) are a
    :class:`~zplatform.boards.BoardError` (the inputs keep their last
    values). Allocates no buffers per step. Loop thread only.
    """

    def __init__(self, mission: Mission, node: str, *, where: str) -> None:
        cfg = mission.world
        if cfg is None or node not in cfg.boards:
            raise ConfigError(
                f"driver 'world' needs a world section whose boards include {node!r}",
                f"{where}.driver",
            )
        self.node = node
        self.index = world_nodes(mission).index(node)
        self.address = link_address(cfg.listen, "$.world.listen")
        self._stale_ns = round(cfg.stale_ms * 1e6)
        bc = cfg.boards[node]
        self._n_dig, self._n_ana = bc.digital_pins, bc.analog_pins
        self._dout = 0
        self._aout = [0.0] * self._n_ana
        self._din = 0
        self._ain = [0.0] * self._n_ana
        self._ana = struct.Struct(f"<{self._n_ana}f")
        self._len = HEADER.size + 8 + self._ana.size
        self._tx = bytearray(self._len)
        self._rx = bytearray(self._len + 64)
        self._seq = 0
        self._sock: socket.socket | None = None
        self._latched_ns: int | None = None  # when the newest inputs arrived
        self.counters = HealthCounters()
        self._ok = False

    def _dpin(self, pin: int) -> None:
        check_pin("digital", pin, self._n_dig)

    def _apin(self, pin: int) -> None:
        check_pin("analog", pin, self._n_ana)

    def set_digital(self, pin: int, value: bool) -> None:
        self._dpin(pin)
        new = self._dout | (1 << pin) if value else self._dout & ~(1 << pin)
        if new != self._dout:
            self._dout = new
            self._send()

    def get_digital(self, pin: int) -> bool:
        self._dpin(pin)
        return bool((self._din >> pin) & 1)

    def set_analog(self, pin: int, volts: float) -> None:
        self._apin(pin)
        v = float(volts)
        if v != self._aout[pin]:
            self._aout[pin] = v
            self._send()

    def get_analog(self, pin: int) -> float:
        self._apin(pin)
        return self._ain[pin]

    def _send(self) -> None:
        sock = self._sock
        if sock is None:
            return
        self._seq = (self._seq + 1) & 0xFFFF
        HEADER.pack_into(self._tx, 0, MAGIC, OUTPUTS, self.index, self._seq)
        U64.pack_into(self._tx, HEADER.size, self._dout)
        self._ana.pack_into(self._tx, HEADER.size + 8, *self._aout)
        try:
            sock.send(self._tx)
            self.counters.frames_sent += 1
        except OSError as exc:  # ECONNREFUSED from an earlier send: the world is not there
            self.counters.last_error = f"send failed: {exc}"

    def step(self, t_ns: int) -> None:
        """Send the outputs, latch the newest inputs (BoardError if stale). Never waits."""
        sock = self._sock
        if sock is None:
            raise self._fail("board is not open")
        self._send()
        got = False
        while True:
            try:
                n = sock.recv_into(self._rx)
            except BlockingIOError:
                break
            except OSError as exc:  # ECONNREFUSED: nobody listens on the world's port
                raise self._fail(f"the world at {self.address} is not there: {exc}") from exc
            if n != self._len:
                self.counters.bad_frames += 1
                continue
            magic, kind, node, _ = HEADER.unpack_from(self._rx, 0)
            if magic != MAGIC or kind != INPUTS or node != self.index:
                self.counters.bad_frames += 1
                continue
            self.counters.frames_received += 1
            got = True
            (self._din,) = U64.unpack_from(self._rx, HEADER.size)
            self._ain[:] = self._ana.unpack_from(self._rx, HEADER.size + 8)
        now = time.monotonic_ns()
        if got:
            self._latched_ns = now
        elif self._latched_ns is None or now - self._latched_ns > self._stale_ns:
            self.counters.timeouts += 1
            age = (
                "none yet"
                if self._latched_ns is None
                else (f"the newest is {(now - self._latched_ns) / 1e6:.0f} ms old")
            )
            raise self._fail(f"no inputs from the world at {self.address} ({age})")
        self.counters.consecutive_errors = 0
        self._ok = True

    def _fail(self, message: str) -> BoardError:
        """Record a failed step; returns the error for the caller to raise."""
        self.counters.failed(message)
        self._ok = False
        return BoardError(message)

    def open(self) -> None:
        """Make the UDP socket and announce the outputs (idempotent; never
        raises for an absent world)."""
        if self._sock is None:
            family = socket.AF_INET6 if ":" in self.address[0] else socket.AF_INET
            s = socket.socket(family, socket.SOCK_DGRAM)
            s.connect(self.address)
            s.setblocking(False)
            self._sock = s
            self._send()

    def close(self) -> None:
        """Send the safe outputs, close the socket (idempotent, never raises)."""
        self.safe()
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def safe(self) -> None:
        """Every output off / 0 V, sent at once (never blocks, never raises)."""
        self._dout = 0
        self._aout[:] = [0.0] * self._n_ana
        self._send()

    def health(self) -> BoardHealth:
        return self.counters.snapshot(
            ok=self._sock is not None and self._ok, connected=self._ok, safe_active=False
        )


def node_board(mission: Mission, node: str) -> Board:
    """Build (not open) the board of device node ``node``: a :class:`WorldLink`
    for ``driver: world``, else :func:`zplatform.boards.make_board`."""
    spec = mission.nodes[node].board
    where = f"$.nodes.{node}.board"
    if spec.get("driver") == "world":
        extra = sorted(k for k in spec if k != "driver")
        if extra:
            raise ConfigError(
                f"driver 'world' takes no other keys (pins are in $.world.boards.{node}); "
                f"got {extra}",
                f"{where}.{extra[0]}",
            )
        return WorldLink(mission, node, where=where)
    return make_board(spec, where=where, pythonpath=mission_code_path(mission))
