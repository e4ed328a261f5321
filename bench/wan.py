"""A WAN between two routers, as a TCP relay: ``python -m bench.wan
LISTEN_HOST:PORT UPSTREAM_HOST:PORT [--delay-ms 80] [--loss 0.01] [--seed 0]``.

This kernel has no netem, so the WAN is made here: every chunk read from
either side is written to the other ``delay`` later (order kept). Loss on a
TCP path does not lose bytes, it delays them: the sender retransmits after
its retransmission timeout, and everything behind the lost segment waits
(head-of-line blocking). So a chunk is "lost" with probability ``loss`` (a
seeded draw per chunk and direction) and then waits ``rto`` more, and the
chunks behind it with it. Bytes are never dropped, altered or reordered: the
relay carries any stream, TLS included, and never parses it.

Prints ``READY HOST:PORT`` once it listens; runs until SIGTERM. Counts per
direction (chunks, bytes, lost) go to stderr at exit.
"""

from __future__ import annotations

import argparse
import heapq
import random
import signal
import socket
import sys
import threading
import time

__all__ = ["Wan"]


class Wan:
    """The relay (module doc). ``delay_s``: one way; ``rto_s``: what a lost
    chunk waits more. Threads: an acceptor, and per connection a reader and a
    writer each way."""

    def __init__(
        self,
        listen: tuple[str, int],
        upstream: tuple[str, int],
        *,
        delay_s: float = 0.08,
        loss: float = 0.01,
        rto_s: float = 0.2,
        seed: int = 0,
    ) -> None:
        self.upstream = upstream
        self.delay_s, self.loss, self.rto_s, self.seed = delay_s, loss, rto_s, seed
        self.stats: dict[str, list[int]] = {"up": [0, 0, 0], "down": [0, 0, 0]}
        self._lock = threading.Lock()
        self._sock = socket.create_server(listen, reuse_port=False)
        self.address = self._sock.getsockname()[:2]
        self._closed = False
        self._conns = 0
        threading.Thread(target=self._accept, name="wan-accept", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                a, _ = self._sock.accept()
            except OSError:
                return
            try:
                b = socket.create_connection(self.upstream, timeout=5)
            except OSError:
                a.close()
                continue
            b.settimeout(None)
            for s in (a, b):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            n = self._conns
            self._conns += 1
            self._pipe(a, b, "up", n)
            self._pipe(b, a, "down", n)

    def _pipe(self, src: socket.socket, dst: socket.socket, direction: str, n: int) -> None:
        rng = random.Random(f"{self.seed}/{direction}/{n}")
        cond = threading.Condition()
        queue: list[tuple[float, int, bytes | None]] = []
        order = [0]

        def reader() -> None:
            due_last = 0.0
            while True:
                try:
                    data = src.recv(65536)
                except OSError:
                    data = b""
                now = time.monotonic()
                due = now + self.delay_s
                lost = bool(data) and rng.random() < self.loss
                if lost:
                    due += self.rto_s
                due = max(due, due_last)  # FIFO: nothing overtakes a late chunk
                due_last = due
                with self._lock:
                    st = self.stats[direction]
                    if data:
                        st[0] += 1
                        st[1] += len(data)
                        st[2] += lost
                with cond:
                    order[0] += 1
                    heapq.heappush(queue, (due, order[0], data or None))
                    cond.notify()
                if not data:
                    return

        def writer() -> None:
            while True:
                with cond:
                    while not queue or queue[0][0] > time.monotonic():
                        cond.wait(None if not queue else max(queue[0][0] - time.monotonic(), 0))
                    _, _, data = heapq.heappop(queue)
                if data is None:
                    with_close(dst)
                    return
                try:
                    dst.sendall(data)
                except OSError:
                    with_close(src)
                    return

        threading.Thread(target=reader, name=f"wan-{direction}-r", daemon=True).start()
        threading.Thread(target=writer, name=f"wan-{direction}-w", daemon=True).start()

    def close(self) -> None:
        self._closed = True
        self._sock.close()


def with_close(s: socket.socket) -> None:
    try:
        s.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    s.close()


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.wan", description=__doc__)
    p.add_argument("listen", type=_hostport)
    p.add_argument("upstream", type=_hostport)
    p.add_argument("--delay-ms", type=float, default=80.0)
    p.add_argument("--loss", type=float, default=0.01)
    p.add_argument("--rto-ms", type=float, default=200.0)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    wan = Wan(
        a.listen,
        a.upstream,
        delay_s=a.delay_ms / 1000,
        loss=a.loss,
        rto_s=a.rto_ms / 1000,
        seed=a.seed,
    )
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    print(f"READY {wan.address[0]}:{wan.address[1]}", flush=True)
    done.wait()
    wan.close()
    print(f"wan stats {wan.stats}", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
