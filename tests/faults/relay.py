"""A seeded fault-injecting relay between two zenoh peers (README.md).

The relay listens on ``127.0.0.1:<free port>`` (or a given host) and forwards
to one upstream zenoh endpoint. One peer connects to :attr:`FaultRelay.endpoint`
instead of the other peer's own endpoint; the other peer does not know the
relay exists.

A *message* is the unit zenoh hands to its link:

* ``proto="tcp"``: one zenoh batch, framed on TCP by a 2-byte little-endian
  length prefix. The relay reassembles whole batches from the byte stream and
  drops, delays or reorders whole batches, never bytes. On zenoh's lowlatency
  transport (``lowlatency=True``) only the two handshake messages each way
  have that prefix; every later message has a 4-byte one (seen on the wire
  with zenoh 1.10).
* ``proto="udp"``: one datagram (zenoh's UDP unicast link sends one batch per
  datagram, no prefix).

Faults, decided per direction (``"up"``: connecting peer -> upstream,
``"down"``: upstream -> connecting peer) by a ``random.Random`` seeded with
``(seed, direction)``, so the same message sequence always gets the same
decisions (:meth:`FaultPlan.expected` replays them):

* ``drop``: probability a message vanishes;
* ``delay_s``/``jitter_s``: every message waits ``delay_s +- jitter_s``
  (uniform) before it is written; delivery order stays FIFO;
* ``reorder``: probability a message is held back and written just after the
  next one of the same direction (a swap); if none comes within
  ``hold_flush_s`` (50 ms) it is written alone, late but in order;
* :meth:`FaultRelay.partition`/:meth:`FaultRelay.heal`: while partitioned
  every message is discarded (counted as ``blocked``, no random draw), in both
  directions; with ``reset=True`` the open TCP connections are also closed.
  A partitioned TCP relay closes every new connection at once (counted in
  :attr:`FaultRelay.refused`), so zenoh's connect retry rejoins soon after
  heal.

Faults apply only while :attr:`FaultRelay.armed` (set by :meth:`arm`, or
``armed=True``); before that the relay forwards everything, so tests can let
zenoh finish its handshake and wait for readiness first. Counts
(:attr:`FaultRelay.stats`) are exact: every message the relay read is counted
once as ``seen`` and as exactly one of ``forwarded``/``dropped``/``blocked``;
``delayed`` and ``reordered`` count forwarded messages that were delayed or
swapped.
"""

from __future__ import annotations

import contextlib
import heapq
import random
import select
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

__all__ = ["DirStats", "FaultPlan", "FaultRelay", "RelayProcess", "parse_endpoint"]

Direction = Literal["up", "down"]
_LEN = struct.Struct("<H")
_LEN32 = struct.Struct("<I")
_HANDSHAKE = 2  # messages each way before a lowlatency link switches to _LEN32


def parse_endpoint(ep: str) -> tuple[str, str, int]:
    """``"tcp/127.0.0.1:7450"`` -> ``("tcp", "127.0.0.1", 7450)``."""
    proto, _, rest = ep.partition("/")
    host, _, port = rest.rpartition(":")
    return proto, host, int(port.split("#")[0])


@dataclass
class DirStats:
    seen: int = 0
    forwarded: int = 0
    dropped: int = 0
    blocked: int = 0
    delayed: int = 0
    reordered: int = 0
    bytes_seen: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)

    def decisions(self) -> dict[str, int]:
        """The counts a :class:`FaultPlan` determines (all but ``bytes_seen``)."""
        d = self.as_dict()
        del d["bytes_seen"]
        return d


@dataclass
class FaultPlan:
    """The fault probabilities and the seeded decision stream of one direction."""

    seed: int = 0
    drop: float = 0.0
    delay_s: float = 0.0
    jitter_s: float = 0.0
    reorder: float = 0.0
    _rng: dict[str, random.Random] = field(default_factory=dict, repr=False)

    def rng(self, direction: str) -> random.Random:
        if direction not in self._rng:
            self._rng[direction] = random.Random(f"{self.seed}/{direction}")
        return self._rng[direction]

    def decide(self, direction: str) -> tuple[str, float]:
        """The next decision: ``("drop"|"reorder"|"pass", delay_s)``.

        Always draws the same three numbers per message so one decision never
        shifts the stream of later ones."""
        r = self.rng(direction)
        u_drop, u_reorder, u_delay = r.random(), r.random(), r.random()
        delay = max(0.0, self.delay_s + (2 * u_delay - 1) * self.jitter_s)
        if u_drop < self.drop:
            return "drop", 0.0
        if u_reorder < self.reorder:
            return "reorder", delay
        return "pass", delay

    def expected(self, n: int, direction: str) -> DirStats:
        """The counts a fresh plan with the same settings gives ``n`` armed
        messages of ``direction`` (what :class:`FaultRelay` must report)."""
        fresh = FaultPlan(self.seed, self.drop, self.delay_s, self.jitter_s, self.reorder)
        st = DirStats(seen=n)
        for _ in range(n):
            what, delay = fresh.decide(direction)
            if what == "drop":
                st.dropped += 1
                continue
            st.forwarded += 1
            if delay > 0:
                st.delayed += 1
            if what == "reorder":
                st.reordered += 1
        return st


class _Pipe:
    """One direction of one connection: decide, schedule, write in order."""

    def __init__(self, relay: FaultRelay, direction: Direction, send: _Sender) -> None:
        self.relay = relay
        self.direction = direction
        self.send = send
        self.held: bytes | None = None  # a message waiting to be swapped
        self.held_delay = 0.0
        self.held_at = 0.0
        self.last_due = 0.0

    def on_message(self, msg: bytes) -> None:
        r = self.relay
        with r.lock:
            st = r.stats_of(self.direction)
            st.seen += 1
            st.bytes_seen += len(msg)
            if not r.armed:
                st.forwarded += 1
                self._schedule(msg, 0.0)
                return
            if r.partitioned:
                st.blocked += 1
                return
            what, delay = r.plan.decide(self.direction)
            if what == "drop":
                st.dropped += 1
                return
            st.forwarded += 1
            if delay > 0:
                st.delayed += 1
            if what == "reorder":
                st.reordered += 1
                if self.held is None:
                    self.held, self.held_delay = msg, delay
                    self.held_at = time.monotonic()
                    self.relay.wake()
                    return
                # Already holding one: release the older behind this one.
            self._schedule(msg, delay)
            if self.held is not None:
                held, hd = self.held, self.held_delay
                self.held = None
                self._schedule(held, hd)

    def flush_held(self) -> None:
        """Write a held message now (no successor came, or disarmed)."""
        with self.relay.lock:
            if self.held is not None:
                held, self.held = self.held, None
                self._schedule(held, self.held_delay)

    def _schedule(self, msg: bytes, delay: float) -> None:
        due = max(time.monotonic() + delay, self.last_due)  # FIFO
        self.last_due = due
        self.relay.schedule(due, self.send, msg)


class _Sender:
    """Writes messages to one socket (TCP: with the length prefix)."""

    def __init__(
        self,
        sock: socket.socket,
        addr: tuple[str, int] | None,
        framed: bool,
        lowlatency: bool = False,
    ) -> None:
        self.sock = sock
        self.addr = addr
        self.framed = framed
        self.lowlatency = lowlatency
        self.written = 0
        self.closed = False

    def write(self, msg: bytes) -> None:
        if self.closed:
            return
        try:
            if self.addr is not None:
                self.sock.sendto(msg, self.addr)
            elif self.framed:
                wide = self.lowlatency and self.written >= _HANDSHAKE
                self.written += 1
                self.sock.sendall((_LEN32 if wide else _LEN).pack(len(msg)) + msg)
            else:
                self.sock.sendall(msg)
        except OSError:
            self.closed = True


class FaultRelay:
    """The relay (module doc). Context manager; runs on daemon threads.

    ``upstream``: the zenoh endpoint to forward to (``"tcp/127.0.0.1:7450"``
    or ``"udp/..."``). The protocol of the upstream endpoint is the relay's.
    """

    def __init__(
        self,
        upstream: str,
        *,
        seed: int = 0,
        drop: float = 0.0,
        delay_s: float = 0.0,
        jitter_s: float = 0.0,
        reorder: float = 0.0,
        armed: bool = False,
        listen_host: str = "127.0.0.1",
        hold_flush_s: float = 0.05,
        lowlatency: bool = False,
    ) -> None:
        proto, host, port = parse_endpoint(upstream)
        self.lowlatency = lowlatency
        if proto not in ("tcp", "udp"):
            raise ValueError(f"relay supports tcp and udp endpoints, not {upstream!r}")
        self.proto = proto
        self.upstream = (host, port)
        self.plan = FaultPlan(seed, drop, delay_s, jitter_s, reorder)
        self.armed = armed
        self.partitioned = False
        self.hold_flush_s = hold_flush_s
        self.lock = threading.RLock()
        self.stats: dict[str, DirStats] = {"up": DirStats(), "down": DirStats()}
        self.connections = 0
        self.refused = 0
        self._stop = threading.Event()
        self._heap: list[tuple[float, int, _Sender, bytes]] = []
        self._heap_seq = 0
        self._cv = threading.Condition(self.lock)
        self._socks: list[socket.socket] = []
        self._pipes: list[_Pipe] = []
        self._threads: list[threading.Thread] = []
        kind = socket.SOCK_STREAM if proto == "tcp" else socket.SOCK_DGRAM
        self._lsock = socket.socket(socket.AF_INET, kind)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._lsock.bind((listen_host, 0))
        if proto == "tcp":
            self._lsock.listen(16)
        self.host = listen_host
        self.port = int(self._lsock.getsockname()[1])
        self._start(self._writer_loop, "relay-writer")
        self._start(self._tcp_accept if proto == "tcp" else self._udp_loop, "relay-rx")

    # -- control -----------------------------------------------------------
    @property
    def endpoint(self) -> str:
        """The zenoh endpoint a peer connects to instead of ``upstream``."""
        return f"{self.proto}/{self.host}:{self.port}"

    def arm(self, *, fresh: bool = True, **plan: float) -> None:
        """Start injecting faults; keyword arguments change the plan's
        probabilities (``drop``, ``delay_s``, ``jitter_s``, ``reorder``).

        ``fresh`` (default): in the same step, zero the counts and restart
        the seeded decision streams, so that while the relay stays armed (and
        not partitioned) ``counts()[d]`` equals ``plan.expected(seen, d)``."""
        with self.lock:
            for k, v in plan.items():
                if k not in ("drop", "delay_s", "jitter_s", "reorder"):
                    raise TypeError(f"unknown fault {k!r}")
                setattr(self.plan, k, v)
            if fresh:
                self.plan._rng.clear()
                self.stats = {"up": DirStats(), "down": DirStats()}
            self.armed = True

    def disarm(self) -> None:
        with self.lock:
            self.armed = False
            pipes = list(self._pipes)
        for p in pipes:
            p.flush_held()

    def partition(self, *, reset: bool = False) -> None:
        """Discard every message from now on (both directions). ``reset``: also
        close every open TCP connection (peers see the link fail at once)."""
        with self.lock:
            self.armed = True
            self.partitioned = True
            socks = list(self._socks) if reset else []
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)

    def heal(self) -> None:
        with self.lock:
            self.partitioned = False

    def counts(self) -> dict[str, DirStats]:
        """A consistent snapshot (copies) of :attr:`stats`."""
        with self.lock:
            return {d: DirStats(**s.as_dict()) for d, s in self.stats.items()}

    def stats_of(self, direction: str) -> DirStats:
        return self.stats[direction]

    def reset_counts(self) -> None:
        with self.lock:
            self.stats = {"up": DirStats(), "down": DirStats()}

    def close(self) -> None:
        self._stop.set()
        with self.lock:
            self._cv.notify_all()
            socks = [self._lsock, *self._socks]
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                s.close()
        for t in self._threads:
            t.join(timeout=2)

    def __enter__(self) -> FaultRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals -----------------------------------------------------------
    def _start(self, target: object, name: str, *args: object) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)  # type: ignore[arg-type]
        self._threads.append(t)
        t.start()

    def schedule(self, due: float, sender: _Sender, msg: bytes) -> None:
        with self.lock:
            self._heap_seq += 1
            heapq.heappush(self._heap, (due, self._heap_seq, sender, msg))
            self._cv.notify()

    def wake(self) -> None:
        with self.lock:
            self._cv.notify()

    def _writer_loop(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                now = time.monotonic()
                # A held message whose successor did not come within
                # hold_flush_s is written alone (late, but not swapped).
                wake = now + self.hold_flush_s
                for p in self._pipes:
                    if p.held is not None:
                        if now - p.held_at >= self.hold_flush_s:
                            p.flush_held()
                        else:
                            wake = min(wake, p.held_at + self.hold_flush_s)
                if not self._heap or self._heap[0][0] > now:
                    due = self._heap[0][0] if self._heap else wake
                    self._cv.wait(timeout=max(0.0, min(due, wake) - now))
                    continue
                _, _, sender, msg = heapq.heappop(self._heap)
            sender.write(msg)

    # TCP: one thread per direction per connection, reading whole batches.
    def _tcp_accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._lsock.accept()
            except OSError:
                return
            if self.partitioned:
                # A partitioned link refuses new connections: zenoh retries
                # its connect and rejoins soon after heal().
                with self.lock:
                    self.refused += 1
                with contextlib.suppress(OSError):
                    client.close()
                continue
            try:
                up = socket.create_connection(self.upstream, timeout=2)
            except OSError:
                client.close()
                continue
            up.settimeout(None)
            for s in (client, up):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self.lock:
                self.connections += 1
                self._socks += [client, up]
                ll = self.lowlatency
                p_up = _Pipe(self, "up", _Sender(up, None, True, ll))
                p_down = _Pipe(self, "down", _Sender(client, None, True, ll))
                self._pipes += [p_up, p_down]
            self._start(self._tcp_pump, "relay-up", client, up, p_up)
            self._start(self._tcp_pump, "relay-down", up, client, p_down)

    def _tcp_pump(self, src: socket.socket, dst: socket.socket, pipe: _Pipe) -> None:
        try:
            for msg in _read_batches(src, self.lowlatency):
                pipe.on_message(msg)
        finally:
            pipe.send.closed = True
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    # UDP: client address -> its own upstream socket.
    def _udp_loop(self) -> None:
        ups: dict[tuple[str, int], tuple[socket.socket, _Pipe]] = {}
        back: dict[socket.socket, tuple[tuple[str, int], _Pipe]] = {}
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._lsock, *back], [], [], 0.1)
            except (OSError, ValueError):
                return
            for s in ready:
                try:
                    msg, addr = s.recvfrom(65536)
                except OSError:
                    continue
                if s is self._lsock:
                    if addr not in ups:
                        u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                        u.connect(self.upstream)
                        with self.lock:
                            self.connections += 1
                            self._socks.append(u)
                            p_up = _Pipe(self, "up", _Sender(u, None, False))
                            p_down = _Pipe(self, "down", _Sender(self._lsock, addr, False))
                            self._pipes += [p_up, p_down]
                        ups[addr] = (u, p_up)
                        back[u] = (addr, p_down)
                    ups[addr][1].on_message(msg)
                else:
                    back[s][1].on_message(msg)


def _read_batches(sock: socket.socket, lowlatency: bool = False) -> Iterator[bytes]:
    """Whole zenoh batches from a TCP stream (2-byte LE length prefix; a
    4-byte one after the handshake on a lowlatency link)."""
    buf = bytearray()
    seen = 0
    while True:
        try:
            chunk = sock.recv(65536)
        except OSError:
            return
        if not chunk:
            return
        buf += chunk
        while True:
            hdr = _LEN32 if lowlatency and seen >= _HANDSHAKE else _LEN
            if len(buf) < hdr.size:
                break
            (n,) = hdr.unpack_from(buf)
            if len(buf) < hdr.size + n:
                break
            yield bytes(buf[hdr.size : hdr.size + n])
            del buf[: hdr.size + n]
            seen += 1


# -- subprocess mode ---------------------------------------------------------
#
# ``python -m tests.faults.relay UPSTREAM [--seed N] [--listen-host H]`` runs a
# relay in its own process (e.g. inside a namespace with ``NetnsHost.popen(...,
# pipe_stdio=True)``). It prints ``ready <endpoint>``, then answers one line
# per command read on stdin:
#
#   arm [drop=P] [delay_s=S] [jitter_s=S] [reorder=P]   -> ok
#   disarm | partition | partition reset | heal | reset  -> ok
#   counts   -> one JSON line {"up": {...}, "down": {...}, "connections": N, "refused": N}
#
# and exits when stdin closes. :class:`RelayProcess` drives it.


def _serve(argv: list[str] | None = None) -> int:
    import argparse
    import json
    import sys

    ap = argparse.ArgumentParser(prog="python -m tests.faults.relay")
    ap.add_argument("upstream")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--listen-host", default="127.0.0.1")
    ap.add_argument("--lowlatency", action="store_true", help="zenoh's lowlatency framing")
    a = ap.parse_args(argv)
    with FaultRelay(
        a.upstream, seed=a.seed, listen_host=a.listen_host, lowlatency=a.lowlatency
    ) as r:
        print(f"ready {r.endpoint}", flush=True)
        for line in sys.stdin:
            cmd, *args = line.split()
            out = "ok"
            try:
                if cmd == "arm":
                    r.arm(**{k: float(v) for k, v in (x.split("=", 1) for x in args)})
                elif cmd == "disarm":
                    r.disarm()
                elif cmd == "partition":
                    r.partition(reset=args == ["reset"])
                elif cmd == "heal":
                    r.heal()
                elif cmd == "reset":
                    r.reset_counts()
                elif cmd == "counts":
                    c = {d: st.as_dict() for d, st in r.counts().items()}
                    out = json.dumps({**c, "connections": r.connections, "refused": r.refused})
                else:
                    out = f"error unknown command {cmd!r}"
            except (TypeError, ValueError) as exc:
                out = f"error {exc}"
            print(out, flush=True)
    return 0


class RelayProcess:
    """Drives a relay subprocess (``python -m tests.faults.relay``) over its
    stdin/stdout. ``popen`` starts the process (e.g. ``NetnsHost.popen`` with
    ``pipe_stdio=True``, or :func:`subprocess.Popen` with text pipes)."""

    def __init__(self, proc: Any, timeout_s: float = 20.0) -> None:
        self.proc = proc
        self.timeout_s = timeout_s
        word, _, self.endpoint = self._line().partition(" ")
        if word != "ready":
            raise RuntimeError(f"relay process said {word!r}")

    def _line(self) -> str:
        ready, _, _ = select.select([self.proc.stdout], [], [], self.timeout_s)
        if not ready:
            raise TimeoutError(f"relay process silent for {self.timeout_s} s")
        line = str(self.proc.stdout.readline())
        if not line:
            raise RuntimeError(f"relay process exited ({self.proc.wait()})")
        return line.strip()

    def command(self, *words: str) -> str:
        self.proc.stdin.write(" ".join(words) + "\n")
        self.proc.stdin.flush()
        out = self._line()
        if out.startswith("error"):
            raise ValueError(out)
        return out

    def arm(self, **plan: float) -> None:
        self.command("arm", *(f"{k}={v}" for k, v in plan.items()))

    def disarm(self) -> None:
        self.command("disarm")

    def partition(self, *, reset: bool = False) -> None:
        self.command("partition", *(["reset"] if reset else []))

    def heal(self) -> None:
        self.command("heal")

    def counts(self) -> dict[str, Any]:
        import json

        c: dict[str, Any] = json.loads(self.command("counts"))
        for d in ("up", "down"):
            c[d] = DirStats(**c[d])
        return c

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=5)
        except Exception:
            self.proc.kill()
            self.proc.wait()


if __name__ == "__main__":
    raise SystemExit(_serve())
