"""The vehicle world: one physical state behind the boards of several device nodes.

Each device node has its own board, and live each node is its own process;
but a vehicle has one physical state, which actuators on several nodes
change (both nodes' pyro switches deploy a chute) and every node's sensors
read. A :class:`World` is that state: the pins of every board it spans (a
:class:`~zplatform.devices.SimBoard` per node, as the world sees it) and one
physics hook, ``function(world, t_ns)``, that reads every board's outputs
and writes every board's inputs when time advances. Flight code never sees
it: a node's devices talk to pins, as they do on hardware.

Three ways in, one world (PX4/ArduPilot SITL's simulator bridge, in small):

* **lockstep** (``zplatform sim``, tests): one :class:`World` in the process;
  each node's board is a :class:`WorldBoard` port onto it.
  :meth:`World.advance` runs the physics once per new time, however many
  boards step at that time, so the run is deterministic;
* **live** (``zplatform up``): the world is its own process
  (``zplatform world MISSION``, :func:`serve`, started by ``up`` before the
  device nodes) that advances on its own monotonic clock at
  ``world.rate_hz``, as the physical world does, and after each advance
  sends every board it has heard from its inputs; a node's board
  (``board: {driver: world}``) is a :class:`WorldLink` that sends its
  outputs over UDP on loopback and latches the newest inputs it received
  (below). Nothing waits on anything: a late datagram is older sensor
  data, as on real hardware, and only inputs older than
  ``world.stale_ms`` fail a step;
* **hardware in the loop**: the same process also plays a node's board
  firmware over the serial board protocol on a pty
  (``world.serve_serial``, :class:`~zplatform.boards.serial_sim.SimDevice`),
  so that node runs the real :class:`~zplatform.boards.SerialBoard` and
  reads its sensors through the wire protocol (each WRITE is answered from
  the world brought up to that moment).

Semantics shared by all three: outputs reach the world when they are set
(a :class:`WorldLink` sends a changed output at once, and all of them with
every step); a board's step latches that board's inputs as the world last
made them (lockstep: after advancing the world to the loop's time).

World link datagrams (little-endian; ``A`` is the node's analog pin count,
``node`` its index in ``world.boards``)::

    b"ZW" type:u8 node:u8 seq:u16 | dout:u64 | A x aout:f32
      type 2 OUTPUTS (board -> world: its outputs; the world answers to
                      this address from then on)
      type 3 INPUTS  (world -> board, after each advance: din:u64 levels,
                      A x f32 volts)

The link is simulation plumbing: unauthenticated, loopback only (checked at
load). Malformed datagrams are counted by the server and dropped.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import select
import socket
import struct
import sys
import time
from typing import Any

import msgspec

from .boards import Board, SimBoard
from .boards.base import BoardError, BoardHealth, HealthCounters
from .components import decode_component_config, load_function, mission_code_path
from .config import Mission, WorldConfig
from .errors import ConfigError, ControlError

__all__ = [
    "World",
    "WorldBoard",
    "WorldLink",
    "check_config",
    "node_board",
    "serve",
    "world_nodes",
]

log = logging.getLogger("zplatform.world")

_HEADER = struct.Struct("<2sBBH")
_MAGIC = b"ZW"
_OUT, _INPUTS = 2, 3
_U64 = struct.Struct("<Q")


def _address(listen: str, where: str) -> tuple[str, int]:
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


class World:
    """The vehicle world of ``mission`` (module doc). Not thread-safe.

    Attributes the physics hook uses: ``boards`` (node -> SimBoard: read
    outputs with ``output_digital``/``output_analog``, write inputs with
    ``inject_*``), ``params`` (decoded), ``state`` (scratch, for the hook),
    ``start_ns`` (the first advance), ``t_ns`` (the last). A hook with a
    ``check`` attribute has ``check(world)`` called here, at load: it
    raises ValueError (or KeyError, OSError) for params the types cannot
    catch (pins that are not on the boards, a missing data file).
    Construction raises ConfigError (path under ``$.world``) for a bad
    world section.
    """

    def __init__(self, mission: Mission) -> None:
        cfg = mission.world
        if cfg is None:
            raise ConfigError("the mission has no world section", "$.world")
        self.config: WorldConfig = cfg
        self.nodes = world_nodes(mission)
        self.boards: dict[str, SimBoard] = {
            n: SimBoard(
                {"digital_pins": b.digital_pins, "analog_pins": b.analog_pins},
                where=f"$.world.boards.{n}",
            )
            for n, b in ((n, cfg.boards[n]) for n in self.nodes)
        }
        self._physics = load_function(
            cfg.physics,
            "$.world.physics",
            args=("world", "t_ns"),
            what="physics",
            pythonpath=mission_code_path(mission),
        )
        params_type = getattr(self._physics, "Params", None)
        self.params: Any = (
            decode_component_config(params_type, cfg.params, "$.world.params")
            if isinstance(params_type, type) and issubclass(params_type, msgspec.Struct)
            else cfg.params
        )
        check = getattr(self._physics, "check", None)
        if callable(check):  # the hook's own load-time check (its wiring, its files)
            try:
                check(self)
            except (ValueError, KeyError, OSError) as exc:
                raise ConfigError(f"{cfg.physics}: {exc}", "$.world.params") from exc
        self.state: dict[str, Any] = {}
        self.truth: Any = None
        """What the physics chooses to expose of its state (tests, plots)."""
        self.start_ns: int | None = None
        self.t_ns: int | None = None

    def advance(self, t_ns: int) -> None:
        """Run the physics up to ``t_ns`` once; a time not after the last does nothing."""
        if self.t_ns is not None and t_ns <= self.t_ns:
            return
        if self.start_ns is None:
            self.start_ns = t_ns
        self.t_ns = t_ns
        self._physics(self, t_ns)

    def board(self, node: str) -> WorldBoard:
        """An in-process port onto ``node``'s pins (the lockstep runner's board)."""
        return WorldBoard(self, node)


class WorldBoard:
    """A node's board as a port onto an in-process :class:`World` (lockstep).

    Pins are the world's board for the node; :meth:`step` advances the world
    to the loop's time. Satisfies :class:`~zplatform.boards.ManagedBoard`.
    """

    def __init__(self, world: World, node: str) -> None:
        self.world = world
        self.node = node
        self.pins = world.boards[node]

    @property
    def digital_pins(self) -> int:
        return self.pins.digital_pins

    @property
    def analog_pins(self) -> int:
        return self.pins.analog_pins

    def step(self, t_ns: int) -> None:
        self.world.advance(t_ns)

    def set_digital(self, pin: int, value: bool) -> None:
        self.pins.set_digital(pin, value)

    def get_digital(self, pin: int) -> bool:
        return self.pins.get_digital(pin)

    def set_analog(self, pin: int, volts: float) -> None:
        self.pins.set_analog(pin, volts)

    def get_analog(self, pin: int) -> float:
        return self.pins.get_analog(pin)

    def open(self) -> None:
        """Nothing to acquire."""

    def close(self) -> None:
        self.safe()

    def safe(self) -> None:
        """Every output of this node off / 0 V (the world sees it at once)."""
        self.pins.safe()

    def health(self) -> BoardHealth:
        return BoardHealth(ok=True)


class WorldLink:
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
        self.address = _address(cfg.listen, "$.world.listen")
        self._stale_ns = round(cfg.stale_ms * 1e6)
        bc = cfg.boards[node]
        self._n_dig, self._n_ana = bc.digital_pins, bc.analog_pins
        self._dout = 0
        self._aout = [0.0] * self._n_ana
        self._din = 0
        self._ain = [0.0] * self._n_ana
        self._ana = struct.Struct(f"<{self._n_ana}f")
        self._len = _HEADER.size + 8 + self._ana.size
        self._tx = bytearray(self._len)
        self._rx = bytearray(self._len + 64)
        self._seq = 0
        self._sock: socket.socket | None = None
        self._latched_ns: int | None = None  # when the newest inputs arrived
        self.counters = HealthCounters()
        self._ok = False

    @property
    def digital_pins(self) -> int:
        return self._n_dig

    @property
    def analog_pins(self) -> int:
        return self._n_ana

    def _dpin(self, pin: int) -> None:
        if not 0 <= pin < self._n_dig:
            raise ControlError(f"digital pin {pin} out of range (board has {self._n_dig})")

    def _apin(self, pin: int) -> None:
        if not 0 <= pin < self._n_ana:
            raise ControlError(f"analog pin {pin} out of range (board has {self._n_ana})")

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
        _HEADER.pack_into(self._tx, 0, _MAGIC, _OUT, self.index, self._seq)
        _U64.pack_into(self._tx, _HEADER.size, self._dout)
        self._ana.pack_into(self._tx, _HEADER.size + 8, *self._aout)
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
            magic, kind, node, _ = _HEADER.unpack_from(self._rx, 0)
            if magic != _MAGIC or kind != _INPUTS or node != self.index:
                self.counters.bad_frames += 1
                continue
            self.counters.frames_received += 1
            got = True
            (self._din,) = _U64.unpack_from(self._rx, _HEADER.size)
            self._ain[:] = self._ana.unpack_from(self._rx, _HEADER.size + 8)
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
    from .boards import make_board

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


def check_config(mission: Mission, *, code: bool = True) -> None:
    """Check the world section against the mission (ConfigError with the path).

    Boards only of device nodes; the physics importable as ``(world, t_ns)``
    and its params decoded (by building the world: the hook does not run);
    a loopback ``listen``; every ``driver: world`` node among the boards;
    every ``serve_serial`` node a world board whose node runs a serial board
    on that port. ``code=False``: the same checks without importing the
    physics (ground verbs, :func:`zplatform.mission.load_mission`).
    """
    w = mission.world
    world_users = [
        n for n in mission.device_nodes if mission.nodes[n].board.get("driver") == "world"
    ]
    if w is None:
        if world_users:
            raise ConfigError(
                "driver 'world' needs a world section ($.world) in the mission",
                f"$.nodes.{world_users[0]}.board.driver",
            )
        return
    for n in w.boards:
        if n not in mission.device_nodes:
            raise ConfigError(
                f"{n!r} is not a device node; device nodes: {mission.device_nodes}",
                f"$.world.boards.{n}",
            )
    _address(w.listen, "$.world.listen")
    if code:  # building the world imports the physics (the mission's code)
        World(mission)
    for n in world_users:
        if n not in w.boards:
            raise ConfigError(
                f"node {n} uses driver 'world' but $.world.boards has no {n}",
                f"$.nodes.{n}.board.driver",
            )
    for n, path in w.serve_serial.items():
        where = f"$.world.serve_serial.{n}"
        if n not in w.boards:
            raise ConfigError(f"{n!r} is not one of the world's boards", where)
        b = mission.nodes[n].board
        if b.get("driver") != "serial" or b.get("port") != path:
            raise ConfigError(
                f"node {n}'s board must be {{driver: serial, port: {path}}} to reach the "
                "world's serial board",
                where,
            )


# ---------------------------------------------------------------------------
# the world process


class _Peer:
    """One world board as the server sees it: its pins' wire layout."""

    def __init__(self, node: str, pins: SimBoard) -> None:
        self.node = node
        self.pins = pins
        self.address: Any = None  # where its board last spoke from
        self.ana = struct.Struct(f"<{pins.analog_pins}f")
        self.length = _HEADER.size + 8 + self.ana.size
        self.tx = bytearray(self.length)

    def apply(self, data: bytes | bytearray) -> None:
        (dmask,) = _U64.unpack_from(data, _HEADER.size)
        p = self.pins
        for i in range(p.digital_pins):
            p.set_digital(i, bool((dmask >> i) & 1))
        for i, v in enumerate(self.ana.unpack_from(data, _HEADER.size + 8)):
            p.set_analog(i, v)

    def inputs(self, index: int) -> bytearray:
        p = self.pins
        mask = 0
        for i in range(p.digital_pins):
            if p.get_digital(i):
                mask |= 1 << i
        _HEADER.pack_into(self.tx, 0, _MAGIC, _INPUTS, index, 0)
        _U64.pack_into(self.tx, _HEADER.size, mask)
        self.ana.pack_into(
            self.tx, _HEADER.size + 8, *(p.get_analog(i) for i in range(p.analog_pins))
        )
        return self.tx


def serve(mission: Mission, *, stop: Any = None, ready: Any = None) -> int:
    """Run the mission's world in real time until ``stop`` is set (the world process).

    Advances the world on this process's monotonic clock at
    ``world.rate_hz`` and after each advance sends every board it has heard
    from (an OUTPUTS datagram) its inputs; takes outputs whenever they come;
    serves every ``serve_serial`` pty. Calls ``ready()`` once the port and
    the ptys are in place (``zplatform world`` prints ``READY``). Blocks.
    Returns the number of malformed datagrams and frames it dropped.
    Raises OSError when the port is taken.
    """
    from .boards import wire
    from .boards.serial_sim import SimDevice, open_pty_link, pump

    world = World(mission)
    assert mission.world is not None
    cfg = mission.world
    peers = [_Peer(n, world.boards[n]) for n in world.nodes]
    addr = _address(cfg.listen, "$.world.listen")
    sock = socket.socket(socket.AF_INET6 if ":" in addr[0] else socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(addr)
    sock.setblocking(False)
    clock = time.monotonic_ns
    bad = [0]
    ptys: dict[int, tuple[SimDevice, wire.Deframer, list[bytes]]] = {}
    slaves: list[int] = []
    for n, link in cfg.serve_serial.items():
        master, slave = open_pty_link(link)
        slaves.append(slave)
        out: list[bytes] = []
        dev = SimDevice(world.boards[n], on_write=world.advance)

        def on_body(body: bytearray, dev: SimDevice = dev, out: list[bytes] = out) -> None:
            reply = dev.handle(body, clock())
            if reply:
                out.append(reply)

        def on_bad(reason: str, dev: SimDevice = dev, out: list[bytes] = out) -> None:
            bad[0] += 1
            out.append(dev.error(wire.ERR_BAD_CRC, 0, 0))

        ptys[master] = (dev, wire.Deframer(on_body, on_bad), out)
    if ready is not None:
        ready()
    buf = bytearray(2048)
    fds = [sock.fileno(), *ptys]
    tick = round(1e9 / cfg.rate_hz)
    due = clock()
    try:
        while stop is None or not stop.is_set():
            wait = max(0.0, (due - clock()) / 1e9)
            readable, _, _ = select.select(fds, [], [], min(wait, 0.05))
            for fd in readable:
                if fd == sock.fileno():
                    _take_outputs(sock, buf, peers, bad)
                    continue
                _, deframer, out = ptys[fd]
                pump(fd, deframer, out)
            now = clock()
            if now < due:
                continue
            world.advance(now)
            for i, peer in enumerate(peers):
                if peer.address is not None:
                    try:
                        sock.sendto(peer.inputs(i), peer.address)
                    except OSError:
                        pass  # the board went away; it is sent again next tick
            for dev, _, _ in ptys.values():
                dev.tick(now)
            due += tick
            if now - due > 100 * tick:  # stalled far behind: catch up, do not burst
                due = now + tick
    finally:
        sock.close()
        for fd in [*ptys, *slaves]:
            os.close(fd)
        for link in cfg.serve_serial.values():
            try:
                os.unlink(link)
            except OSError:
                pass
    return bad[0]


def _take_outputs(sock: socket.socket, buf: bytearray, peers: list[_Peer], bad: list[int]) -> None:
    """Apply every OUTPUTS datagram waiting on ``sock``; count malformed ones."""
    while True:
        try:
            got, src = sock.recvfrom_into(buf)
        except BlockingIOError:
            return
        if got < _HEADER.size:
            bad[0] += 1
            continue
        magic, kind, index, _ = _HEADER.unpack_from(buf, 0)
        if magic != _MAGIC or kind != _OUT or index >= len(peers) or got != peers[index].length:
            bad[0] += 1
            continue
        peers[index].apply(buf)
        peers[index].address = src


def main(mission_path: str, *, realtime: bool = True) -> int:
    """``zplatform world MISSION``: serve the mission's world until SIGTERM/SIGINT,
    one real-time priority above the mission's nodes (``realtime``)."""
    from .mission import load_mission
    from .node.runtime import StopFlag, realtime_setup, setup_logging

    setup_logging()
    mission = load_mission(mission_path)
    if mission.world is None:
        raise ConfigError(f"mission {mission.mission!r} has no world section", "$.world")
    # The world is the nodes' hardware, which real hardware never waits for
    # the flight software: it runs one real-time priority above the highest
    # the mission gives a node, or SCHED_FIFO nodes (and their zenoh threads)
    # starve it and the boards waiting on it time out.
    prios = [n.priority for n in mission.nodes.values() if n.priority is not None]
    if realtime and prios:
        realtime_setup(min(max(prios) + 1, 99), None)
    stop = StopFlag()
    bad = serve(mission, stop=stop.event, ready=lambda: print("READY", flush=True))
    if bad:
        log.warning("world: dropped %d malformed datagrams or frames", bad)
    print("world stopped", file=sys.stderr)
    return 0
