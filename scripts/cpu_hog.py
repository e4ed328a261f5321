#!/usr/bin/env python3
"""A CPU hog to run beside the test suite: one busy process per core.

The suite must pass on a loaded machine (CI runs on a shared 2-core VM,
possibly while other work is still running there). This script makes the
load on purpose, the same every time: one process per CPU this process may
run on, each spinning in a pure-Python loop, under the ordinary time-sharing
policy (SCHED_OTHER) at niceness 0, so it competes with the tests' processes
as any other busy program would::

    python3 scripts/cpu_hog.py -- ./scripts/test.sh   # the suite beside the hog
    python3 scripts/cpu_hog.py --duration 600 &        # or in the background
    stress-ng --cpu 2 --sched other                    # the same load with stress-ng

With a command after ``--`` the hog runs for the command's lifetime and the
script exits with the command's status; without one it runs until
``--duration`` seconds pass or it gets SIGINT/SIGTERM. The busy processes
die with the script, however it ends (a parent-death signal), so a killed
hog leaves nothing spinning. Needs only the standard library (Linux).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(name, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def _ordinary_policy() -> None:
    """SCHED_OTHER at niceness 0, whatever the shell that started us had."""
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError):  # raising priority back to 0 needs root
        os.setpriority(os.PRIO_PROCESS, 0, 0)


def _spin(cpu: int | None, parent: int) -> None:
    _die_with_parent()
    if os.getppid() != parent:  # the parent died before the signal was set
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when we stop
    if cpu is not None:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, {cpu})
    _ordinary_policy()
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def cpus() -> list[int]:
    """The CPUs this process may run on (all of them without an affinity API)."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    command: list[str] = []
    if "--" in args:
        i = args.index("--")
        args, command = args[:i], args[i + 1 :]
    p = argparse.ArgumentParser(prog="cpu_hog.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--procs", type=int, default=None, help="busy processes (default: one per usable CPU)"
    )
    p.add_argument(
        "--pin", action="store_true", help="pin each busy process to its own CPU (default: float)"
    )
    p.add_argument(
        "--duration", type=float, default=None, help="stop after this many seconds (no command)"
    )
    ns = p.parse_args(args)
    usable = cpus()
    n = ns.procs if ns.procs is not None else len(usable)
    if n < 1:
        p.error("--procs must be at least 1")
    if ns.duration is not None and ns.duration <= 0:
        p.error("--duration must be positive")
    _ordinary_policy()
    ctx = mp.get_context("fork")
    me = os.getpid()
    hogs = [
        ctx.Process(
            target=_spin, args=(usable[i % len(usable)] if ns.pin else None, me), daemon=True
        )
        for i in range(n)
    ]
    for h in hogs:
        h.start()
    print(
        f"cpu_hog: {n} busy process(es) (SCHED_OTHER, nice 0) on CPUs {usable}: "
        + " ".join(str(h.pid) for h in hogs),
        file=sys.stderr,
        flush=True,
    )
    stop = {"now": False}
    child: subprocess.Popen[bytes] | None = None

    def _stop(signum: int, _frame: object) -> None:
        stop["now"] = True
        if child is not None and child.poll() is None:
            child.terminate()  # a SIGTERM to the hog ends the command it runs too

    signal.signal(signal.SIGTERM, _stop)
    rc = 0
    try:
        if command:
            child = subprocess.Popen(command)
            while True:
                try:
                    rc = child.wait()
                    break
                except KeyboardInterrupt:  # Ctrl-C reaches the command too; wait for it
                    continue
        else:
            end = None if ns.duration is None else time.monotonic() + ns.duration
            while not stop["now"] and (end is None or time.monotonic() < end):
                time.sleep(0.2 if end is None else min(0.2, max(0.0, end - time.monotonic())))
    except KeyboardInterrupt:
        rc = 130
    finally:
        for h in hogs:
            h.kill()
        for h in hogs:
            h.join()
    return rc


if __name__ == "__main__":
    sys.exit(main())
