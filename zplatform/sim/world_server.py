"""The vehicle world process: ``zplatform world MISSION`` (:func:`main`).

Live (``zplatform up``, which starts it before the device nodes) the
mission's :class:`~zplatform.world.model.World` runs here on this process's
monotonic clock at ``world.rate_hz`` (:func:`serve`): after each advance it
sends every ``driver: world`` board it has heard from its inputs over the
world link (:mod:`zplatform.boards.world`, whose datagrams it speaks), and
plays the board firmware of every ``world.serve_serial`` node over the
serial board protocol on a pty (hardware in the loop,
:class:`~zplatform.boards.serial_sim.SimDevice`). Malformed datagrams and
frames are counted and dropped.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import struct
import sys
import time
from typing import Any

from ..boards import SimBoard, wire
from ..boards.serial_sim import SimDevice, open_pty_link, pump
from ..boards.world import HEADER, INPUTS, MAGIC, OUTPUTS, U64, link_address
from ..config import Mission
from ..errors import ConfigError
from ..world.model import World

__all__ = ["main", "serve"]

log = logging.getLogger("zplatform.world")


class _Peer:
    """One world board as the server sees it: its pins' wire layout."""

    def __init__(self, node: str, pins: SimBoard) -> None:
        self.node = node
        self.pins = pins
        self.address: Any = None  # where its board last spoke from
        self.ana = struct.Struct(f"<{pins.analog_pins}f")
        self.length = HEADER.size + 8 + self.ana.size
        self.tx = bytearray(self.length)

    def apply(self, data: bytes | bytearray) -> None:
        (dmask,) = U64.unpack_from(data, HEADER.size)
        p = self.pins
        for i in range(p.digital_pins):
            p.set_digital(i, bool((dmask >> i) & 1))
        for i, v in enumerate(self.ana.unpack_from(data, HEADER.size + 8)):
            p.set_analog(i, v)

    def inputs(self, index: int) -> bytearray:
        p = self.pins
        mask = 0
        for i in range(p.digital_pins):
            if p.get_digital(i):
                mask |= 1 << i
        HEADER.pack_into(self.tx, 0, MAGIC, INPUTS, index, 0)
        U64.pack_into(self.tx, HEADER.size, mask)
        self.ana.pack_into(
            self.tx, HEADER.size + 8, *(p.get_analog(i) for i in range(p.analog_pins))
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
    world = World(mission)
    assert mission.world is not None
    cfg = mission.world
    peers = [_Peer(n, world.boards[n]) for n in world.nodes]
    addr = link_address(cfg.listen, "$.world.listen")
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
        if got < HEADER.size:
            bad[0] += 1
            continue
        magic, kind, index, _ = HEADER.unpack_from(buf, 0)
        if magic != MAGIC or kind != OUTPUTS or index >= len(peers) or got != peers[index].length:
            bad[0] += 1
            continue
        peers[index].apply(buf)
        peers[index].address = src


def main(mission_path: str, *, realtime: bool = True) -> int:
    """``zplatform world MISSION``: serve the mission's world until SIGTERM/SIGINT,
    one real-time priority above the mission's nodes (``realtime``)."""
    from ..mission.load import load_mission
    from ..runtime.process import StopFlag, realtime_setup, setup_logging

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
