"""The vehicle world's link carried from one network namespace's loopback to another's.

A mission's vehicle world (``zplatform world``, :mod:`zplatform.world.model`) is
the physics behind the device nodes' boards: each ``driver: world`` board
exchanges its pins with it in UDP datagrams on loopback (``world.listen``,
checked to be a loopback address). With the device nodes on hosts of their
own (network namespaces, one loopback each), a board not on the world's
host needs its datagrams carried to the world's loopback. That is
simulation plumbing, not a network link of the vehicle (on a vehicle each
node reads its own sensors): it must not cross the namespaces' veths, so a
cable cut in a test never cuts a node off from physics.

``python -m tests.faults.worldlink PORT WORLD_NETNS`` runs inside the board's
namespace (``NetnsHost.popen``): it binds ``127.0.0.1:PORT`` there (where the
board sends, as if the world were local), then enters ``WORLD_NETNS`` (a
name under ``/run/netns``) with ``setns(2)`` and opens a second socket on
that namespace's loopback; a socket keeps the namespace it was made in, so
one thread then carries each datagram from the board to the world's
``127.0.0.1:PORT`` and the world's answers back to the board. It prints
``ready`` once both sockets exist and ends when its stdin closes.
"""

from __future__ import annotations

import ctypes
import os
import select
import socket
import sys

__all__ = ["relay_main"]

CLONE_NEWNET = 0x40000000


def _enter_netns(name: str) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(f"/run/netns/{name}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"setns into {name}: {os.strerror(err)}")
    finally:
        os.close(fd)


def relay_main(port: int, world_netns: str) -> int:
    board_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    board_side.bind(("127.0.0.1", port))
    _enter_netns(world_netns)  # this thread (the only one) from here on
    world_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    world_side.bind(("127.0.0.1", 0))
    world = ("127.0.0.1", port)
    board: tuple[str, int] | None = None
    print("ready", flush=True)
    stdin = sys.stdin.fileno()
    fds = [board_side.fileno(), world_side.fileno(), stdin]
    while True:
        readable, _, _ = select.select(fds, [], [])
        for fd in readable:
            if fd == stdin:
                if not os.read(stdin, 4096):
                    return 0
                continue
            s = board_side if fd == board_side.fileno() else world_side
            try:
                data, src = s.recvfrom(4096)
            except OSError:
                continue
            try:
                if s is board_side:
                    board = src
                    world_side.sendto(data, world)
                elif board is not None:
                    board_side.sendto(data, board)
            except OSError:
                pass  # the world or the board is not there (yet): the next datagram tries again


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: python -m tests.faults.worldlink PORT WORLD_NETNS")
    raise SystemExit(relay_main(int(sys.argv[1]), sys.argv[2]))
