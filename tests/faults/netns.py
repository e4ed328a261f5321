"""Network namespaces joined by veth pairs, for the fault suite (README.md).

:class:`NetnsLab` makes ``n`` host namespaces, each with one interface
``eth0`` addressed ``10.77.0.<i+1>/24``:

* ``topology="bridge"`` (default): every ``eth0`` is one end of a veth pair
  whose other end (``p<i>``) sits on bridge ``br0`` in a separate bridge
  namespace. :meth:`NetnsHost.link_down` sets ``p<i>`` down: the host keeps
  its address and route, its packets just vanish (a cut cable, not an
  interface the host sees go away).
* ``topology="mesh"``: one veth pair per pair of hosts, host ``i`` reaching
  host ``j`` at ``10.77.<pair>.x`` (see :meth:`NetnsLab.addr_of`); used where
  no bridge module is available, and where a test cuts one pair of hosts
  apart and leaves each with its other links (:meth:`NetnsLab.set_pair`).

Names are unique per lab (``zf<pid><n>...``) so parallel workers never clash,
and every namespace the lab made is deleted by :meth:`NetnsLab.close`, after
killing every process started through :meth:`NetnsHost.popen` (by its process
group) and any other process still inside the lab's namespaces (by pid, from
``ip netns pids``). Addresses exist only inside the lab's own namespaces.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import signal
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["NetnsHost", "NetnsLab", "netns_unavailable"]

_counter = itertools.count()


def netns_unavailable() -> str | None:
    """Why the namespace fixtures cannot run here (None: they can)."""
    if os.geteuid() != 0:
        return "network namespaces need root (run the fault suite as root)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        return f"`ip netns` does not work here: {r.stderr.strip()}"
    return None


def _ip(*args: str, ns: str | None = None) -> None:
    cmd = ["ip", *(["-n", ns] if ns else []), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=10)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {r.stderr.strip()}")


def _ip_together(commands: list[list[str]]) -> None:
    """Run several ``ip`` commands at the same time; raise if any failed."""
    procs = [
        subprocess.Popen(["ip", *c], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        for c in commands
    ]
    failed = []
    for c, p in zip(commands, procs, strict=True):
        _, err = p.communicate(timeout=10)
        if p.returncode != 0:
            failed.append(f"ip {' '.join(c)} failed: {err.strip()}")
    if failed:
        raise RuntimeError("; ".join(failed))


@dataclass
class NetnsHost:
    lab: NetnsLab
    index: int
    ns: str
    addr: str
    procs: list[subprocess.Popen[Any]] = field(default_factory=list)

    def endpoint(self, port: int, proto: str = "tcp") -> str:
        return f"{proto}/{self.addr}:{port}"

    def popen(
        self,
        cmd: Sequence[str],
        *,
        log: Path | None = None,
        pipe_stdio: bool = False,
        env: dict[str, str] | None = None,
        cwd: str | Path | None = None,
    ) -> subprocess.Popen[Any]:
        """Start ``cmd`` inside this namespace (``ip netns exec``), in its own
        process group; killed by :meth:`NetnsLab.close`. ``pipe_stdio``: text
        pipes on stdin/stdout (stderr to ``log`` or inherited); otherwise stdout
        and stderr go to ``log``."""
        e = dict(os.environ, PYTHONUNBUFFERED="1")
        e.update(env or {})
        logf = open(log, "ab") if log is not None else None  # noqa: SIM115 - closed by close()
        p: subprocess.Popen[Any] = subprocess.Popen(
            ["ip", "netns", "exec", self.ns, *cmd],
            stdin=subprocess.PIPE if pipe_stdio else subprocess.DEVNULL,
            stdout=subprocess.PIPE if pipe_stdio else logf,
            stderr=logf if logf is not None else None,
            text=pipe_stdio,
            bufsize=1 if pipe_stdio else -1,
            env=e,
            cwd=cwd,
            start_new_session=True,
        )
        if logf is not None:
            logf.close()  # the child has its own copy
        self.procs.append(p)
        return p

    def run(self, cmd: Sequence[str], timeout: float = 10) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            ["ip", "netns", "exec", self.ns, *cmd],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def link_down(self) -> None:
        """Cut this host off (its bridge port or every mesh link goes down)."""
        self.lab.set_links(self.index, up=False)

    def link_up(self) -> None:
        self.lab.set_links(self.index, up=True)


class NetnsLab:
    """``n`` namespaces (module doc). Context manager; always cleans up."""

    def __init__(self, n: int, topology: str = "bridge") -> None:
        if topology not in ("bridge", "mesh"):
            raise ValueError(f"topology is bridge or mesh, not {topology!r}")
        self.topology = topology
        self.tag = f"zf{os.getpid() % 100000}x{next(_counter)}"
        self.namespaces: list[str] = []
        self.bridge_ns: str | None = None
        self.hosts: list[NetnsHost] = []
        # mesh: (i, j) -> (iface in i, iface in j, addr of i, addr of j)
        self.mesh: dict[tuple[int, int], tuple[str, str, str, str]] = {}
        try:
            self._build(n)
        except BaseException:
            self.close()
            raise

    def _add_ns(self, name: str) -> str:
        _ip("netns", "add", name)
        self.namespaces.append(name)
        _ip("link", "set", "lo", "up", ns=name)
        return name

    def _build(self, n: int) -> None:
        hosts = [self._add_ns(f"{self.tag}h{i}") for i in range(n)]
        if self.topology == "bridge":
            br = self.bridge_ns = self._add_ns(f"{self.tag}br")
            _ip("link", "add", "br0", "type", "bridge", ns=br)
            _ip("link", "set", "br0", "up", ns=br)
            for i, ns in enumerate(hosts):
                # Create inside the host namespace, move the peer end to the
                # bridge: nothing ever appears in the root namespace.
                _ip("link", "add", "eth0", "type", "veth", "peer", "name", f"p{i}", ns=ns)
                _ip("link", "set", f"p{i}", "netns", br, ns=ns)
                _ip("link", "set", f"p{i}", "master", "br0", ns=br)
                _ip("link", "set", f"p{i}", "up", ns=br)
                addr = f"10.77.0.{i + 1}"
                _ip("addr", "add", f"{addr}/24", "dev", "eth0", ns=ns)
                _ip("link", "set", "eth0", "up", ns=ns)
                self.hosts.append(NetnsHost(self, i, ns, addr))
        else:
            for i, ns in enumerate(hosts):
                self.hosts.append(NetnsHost(self, i, ns, ""))
            for k, (i, j) in enumerate(itertools.combinations(range(n), 2)):
                a, b = f"m{j}", f"m{i}"  # in i: link to j; in j: link to i
                _ip("link", "add", a, "type", "veth", "peer", "name", b, ns=hosts[i])
                _ip("link", "set", b, "netns", hosts[j], ns=hosts[i])
                ai, aj = f"10.77.{k + 1}.1", f"10.77.{k + 1}.2"
                _ip("addr", "add", f"{ai}/24", "dev", a, ns=hosts[i])
                _ip("addr", "add", f"{aj}/24", "dev", b, ns=hosts[j])
                _ip("link", "set", a, "up", ns=hosts[i])
                _ip("link", "set", b, "up", ns=hosts[j])
                self.mesh[(i, j)] = (a, b, ai, aj)
            for h in self.hosts:
                h.addr = self.addr_of(h.index, 1 - h.index if n == 2 else (h.index + 1) % n)

    def addr_of(self, i: int, seen_from: int) -> str:
        """Host ``i``'s address as host ``seen_from`` reaches it."""
        if self.topology == "bridge":
            return self.hosts[i].addr
        lo, hi = sorted((i, seen_from))
        _, _, a_lo, a_hi = self.mesh[(lo, hi)]
        return a_lo if i == lo else a_hi

    def set_links(self, i: int, *, up: bool) -> None:
        state = "up" if up else "down"
        if self.topology == "bridge":
            assert self.bridge_ns is not None
            _ip("link", "set", f"p{i}", state, ns=self.bridge_ns)
            return
        # All of the host's links at once (one `ip` per far end, run together):
        # one after the other, on a busy host, the last went down tens of ms
        # after the first, and a node saw part of a cut the test meant as one.
        ends = [
            (ib, self.hosts[b].ns) if i == a else (ia, self.hosts[a].ns)
            for (a, b), (ia, ib, _, _) in self.mesh.items()
            if i in (a, b)
        ]
        _ip_together([["-n", ns, "link", "set", iface, state] for iface, ns in ends])

    def set_pair(self, i: int, j: int, *, up: bool) -> None:
        """Cut (or restore) the one link between hosts ``i`` and ``j`` of a
        mesh, as :meth:`set_links` cuts all of a host's: the end in ``j`` goes
        down, so neither host reaches the other while both keep every other
        link (a bridge has no such link: ValueError)."""
        if self.topology != "mesh":
            raise ValueError("only a mesh has a link per pair of hosts")
        lo, hi = sorted((i, j))
        in_lo, in_hi, _, _ = self.mesh[(lo, hi)]
        iface, host = (in_hi, hi) if j == hi else (in_lo, lo)
        _ip("link", "set", iface, "up" if up else "down", ns=self.hosts[host].ns)

    def close(self) -> None:
        for h in self.hosts:
            for p in h.procs:
                if p.poll() is None:
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(p.pid, signal.SIGKILL)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=5)
                for f in (p.stdin, p.stdout):
                    if f is not None:
                        with contextlib.suppress(OSError):
                            f.close()
        for ns in self.namespaces:
            r = subprocess.run(
                ["ip", "netns", "pids", ns], capture_output=True, text=True, check=False
            )
            for pid in r.stdout.split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
        for ns in reversed(self.namespaces):
            # Deleting a namespace deletes its veth ends, and so their peers.
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)
        self.namespaces.clear()

    def __enter__(self) -> NetnsLab:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
