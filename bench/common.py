"""Shared helpers for the benchmarks: machine facts, statistics, result files, child processes.

Nothing here blocks for long except :func:`terminate_all`, which waits at most
about 2 s for children to exit after SIGTERM before it SIGKILLs them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
RESULTS_DIR = BENCH_DIR / "results"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> dict[str, Any]:
    """Describe the machine a result was measured on (cheap; reads /proc and package metadata)."""
    try:
        import psutil

        physical: int | None = psutil.cpu_count(logical=False)
    except ImportError:  # pragma: no cover - psutil is a dependency
        physical = None
    return {
        "cpu_model": _cpu_model(),
        "cores_logical": os.cpu_count(),
        "cores_physical": physical,
        "python": platform.python_version(),
        "zenoh": _version("eclipse-zenoh"),
        "numpy": _version("numpy"),
        "kernel": platform.release(),
        "system": platform.system(),
        "loadavg_1m": round(os.getloadavg()[0], 2),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def summarize(samples_ns: Sequence[int], deadline_ns: int | None = None) -> dict[str, Any]:
    """Reduce latency samples (ns) to the docs/architecture.md#files figures (in microseconds).

    ``msgs`` is the number of samples; ``deadline_miss_rate`` is the fraction of
    samples at or above ``deadline_ns`` (``None`` without a deadline). A loop that
    missed its deadline is expected to be recorded as exactly the deadline value.
    """
    if len(samples_ns) == 0:
        return {
            "p50_us": None,
            "p99_us": None,
            "max_us": None,
            "min_us": None,
            "mean_us": None,
            "msgs": 0,
            "deadline_miss_rate": None,
        }
    a = np.asarray(samples_ns, dtype=np.int64)
    p50, p99 = np.percentile(a, [50.0, 99.0])
    miss: float | None = None
    if deadline_ns is not None:
        miss = float(np.count_nonzero(a >= deadline_ns)) / float(a.size)
    return {
        "p50_us": round(float(p50) / 1e3, 2),
        "p99_us": round(float(p99) / 1e3, 2),
        "max_us": round(float(a.max()) / 1e3, 2),
        "min_us": round(float(a.min()) / 1e3, 2),
        "mean_us": round(float(a.mean()) / 1e3, 2),
        "msgs": int(a.size),
        "deadline_miss_rate": miss,
    }


def _fmt(value: Any, width: int) -> str:
    if value is None:
        return "-".rjust(width)
    if isinstance(value, float):
        return f"{value:{width}.1f}"
    return str(value).rjust(width)


def write_result(
    bench: str,
    params: dict[str, Any],
    variants: dict[str, dict[str, Any]],
    json_path: str | None,
) -> dict[str, Any]:
    """Write ``{"bench","machine","params","variants"}`` as JSON and print a table.

    The file goes to ``json_path`` or to ``bench/results/<bench>.json``. The table
    shows p50/p99/max/miss rate of every variant and its p50 relative to the best
    (lowest) p50 ("vs best"). Returns the written document.
    """
    doc: dict[str, Any] = {
        "bench": bench,
        "machine": machine_info(),
        "params": params,
        "variants": variants,
    }
    path = Path(json_path) if json_path else RESULTS_DIR / f"{bench}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, sort_keys=False) + "\n", encoding="utf-8")

    p50s = [v["p50_us"] for v in variants.values() if v.get("p50_us") is not None]
    best = min(p50s) if p50s else None
    name_w = max([len("variant"), *(len(n) for n in variants)])
    print(f"\n{bench}  ({path})")
    print(
        f"{'variant':<{name_w}}  {'p50_us':>8}  {'p99_us':>8}  {'max_us':>8}  "
        f"{'miss':>7}  {'msgs':>6}  {'vs best':>7}"
    )
    for name, fig in variants.items():
        p50 = fig.get("p50_us")
        ratio = f"{p50 / best:6.2f}x" if best and p50 is not None else "      -"
        miss = fig.get("deadline_miss_rate")
        miss_s = f"{miss * 100:6.2f}%" if miss is not None else "      -"
        print(
            f"{name:<{name_w}}  {_fmt(p50, 8)}  {_fmt(fig.get('p99_us'), 8)}  "
            f"{_fmt(fig.get('max_us'), 8)}  {miss_s:>7}  {_fmt(fig.get('msgs'), 6)}  {ratio:>7}"
        )
    return doc


def bench_argparser(description: str) -> argparse.ArgumentParser:
    """An argument parser with the flags every benchmark takes: ``--quick`` and ``--json PATH``."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--quick", action="store_true", help="short run (smoke test / CI)")
    p.add_argument(
        "--json",
        metavar="PATH",
        default=None,
        help="result file (default: bench/results/<bench>.json)",
    )
    return p


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind port 0, read it, close).

    zenoh cannot report the port a ``tcp/127.0.0.1:0`` listener got, so callers
    pick the port first. Another process could take it in between (rare).
    """
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def spawn(args: list[str]) -> subprocess.Popen[bytes]:
    """Start ``sys.executable *args`` in its own process group, cwd = repo root.

    Does not block. Uses fork+exec (``subprocess``), which is safe after
    ``zenoh.open()``; a bare ``os.fork`` is not (docs/architecture.md#zenoh).
    """
    return subprocess.Popen([sys.executable, *args], cwd=REPO_ROOT, process_group=0)


def _signal_group(proc: subprocess.Popen[bytes], sig: signal.Signals) -> None:
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        try:
            proc.send_signal(sig)
        except ProcessLookupError:
            pass


def terminate_all(procs: Iterable[subprocess.Popen[bytes]], grace_s: float = 2.0) -> None:
    """Stop children: SIGTERM to each process group, SIGKILL what is left after ``grace_s``.

    Blocks until all children are reaped (at most about ``grace_s`` plus the
    SIGKILL reaping time).
    """
    plist = list(procs)
    for p in plist:
        if p.poll() is None:
            _signal_group(p, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in plist:
        remaining = deadline - time.monotonic()
        try:
            p.wait(timeout=max(remaining, 0.0))
        except subprocess.TimeoutExpired:
            pass
    for p in plist:
        if p.poll() is None:
            _signal_group(p, signal.SIGKILL)
            p.wait()


class TmPutStamps:
    """A :class:`zplatform.trace.Tracer` keeping, per loop, when the control
    node was about to publish its telemetry (the ``tm.put`` point): on
    ``CLOCK_MONOTONIC`` (``mono``) and on ``clock`` (``ns``: the node's
    clock, ``ControlNode.clock.now_ns``). Install it with
    :func:`zplatform.trace.install` around the run."""

    def __init__(self, now_ns: Callable[[], int]) -> None:
        self.mono: dict[int, int] = {}
        self.ns: dict[int, int] = {}
        self._now = now_ns

    def mark(self, name: str, n: int = 0, v: int = 0) -> None:
        if name == "tm.put":
            self.mono[n] = time.monotonic_ns()
            self.ns[n] = self._now()


# -- a bench's own child processes: JSON lines both ways ----------------------

#: What starts a child's protocol lines on its stdout (libraries may print there too).
TAG = "@@"


def two_node_mission(name: str, cn_port: int, dn_port: int) -> str:
    """The mission text of a two-node bench (a CN and ``dn0`` on loopback TCP,
    one one-byte region): what the child processes of ``bench.shm`` and
    ``bench.intrahost`` load."""
    return (
        f"mission: {name}\n"
        "nodes:\n"
        f"  cn: {{listen: ['tcp/127.0.0.1:{cn_port}']}}\n"
        f"  dn0: {{listen: ['tcp/127.0.0.1:{dn_port}'], connect: ['tcp/127.0.0.1:{cn_port}']}}\n"
        "regions:\n  cn_to_dn0:\n    - {name: x, type: u8}\n"
    )


def say(obj: dict[str, Any]) -> None:
    """In a child: write ``obj`` as one tagged JSON line to stdout and flush."""
    sys.stdout.write(TAG + json.dumps(obj) + "\n")
    sys.stdout.flush()


def commands() -> Iterator[dict[str, Any]]:
    """In a child: the parent's commands, one JSON object per non-blank
    stdin line (blocks for each; ends at EOF)."""
    for line in sys.stdin:
        if line.strip():
            yield json.loads(line)


def next_command() -> dict[str, Any]:
    """In a child: the next command on stdin (blocks), ``{"cmd": "quit"}`` at EOF.
    Reads the same stream as :func:`commands` (stdin is its own iterator)."""
    for line in sys.stdin:
        if line.strip():
            out: dict[str, Any] = json.loads(line)
            return out
    return {"cmd": "quit"}


class Child:
    """A bench's child process (``python -m MODULE *args``, cwd the repo root,
    ``ZP_BENCH_MISSION`` set to ``mission_text``) spoken to in JSON lines:
    :meth:`send` a command, :meth:`read` its next tagged reply, :meth:`close`."""

    def __init__(self, module: str, args: list[str], mission_text: str) -> None:
        self.module = module
        self.p = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            cwd=REPO_ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=dict(os.environ, ZP_BENCH_MISSION=mission_text, PYTHONUNBUFFERED="1"),
            text=True,
        )

    def send(self, obj: dict[str, Any]) -> None:
        """Write one command line (blocks only if the child's stdin pipe is full)."""
        assert self.p.stdin is not None
        self.p.stdin.write(json.dumps(obj) + "\n")
        self.p.stdin.flush()

    def read(self) -> dict[str, Any]:
        """The next tagged line, decoded (blocks); RuntimeError if the child exits first."""
        assert self.p.stdout is not None
        for line in self.p.stdout:
            if line.startswith(TAG):
                out: dict[str, Any] = json.loads(line[len(TAG) :])
                return out
        raise RuntimeError(f"{self.module} child exited ({self.p.wait()})")

    def close(self) -> None:
        """Ask the child to quit; kill it if it has not within 10 s. Reaps it."""
        try:
            self.send({"cmd": "quit"})
            self.p.wait(timeout=10)
        except Exception:
            self.p.kill()
            self.p.wait()
