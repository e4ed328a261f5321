"""A node under ``up`` also stops when ``up`` closes its stdin, beside SIGTERM
(zplatform/runtime/process.py StopFlag): a DN was seen looping on after its
SIGTERM until ``up``'s grace ran out and it was killed."""

from __future__ import annotations

import os
import subprocess
import sys

from zplatform.runtime.process import STOP_PIPE_ENV

_CHILD = (
    "from zplatform.runtime.process import StopFlag\n"
    "s = StopFlag()\n"
    "print('ready', flush=True)\n"
    "s.event.wait(30)\n"
    "print('stopped' if s.is_set() else 'not stopped', flush=True)\n"
)


def _child(env_value: str | None) -> subprocess.Popen[bytes]:
    env = dict(os.environ)
    env.pop(STOP_PIPE_ENV, None)
    if env_value is not None:
        env[STOP_PIPE_ENV] = env_value
    p = subprocess.Popen(
        [sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env
    )
    assert p.stdout is not None and p.stdout.readline() == b"ready\n"
    return p


def test_closing_stdin_stops_a_node_started_by_a_supervisor() -> None:
    p = _child("1")
    assert p.stdin is not None
    p.stdin.close()
    assert p.wait(timeout=30) == 0
    assert p.stdout is not None and p.stdout.read() == b"stopped\n"


def test_without_the_supervisor_s_flag_stdin_is_not_a_stop() -> None:
    p = _child(None)
    assert p.stdin is not None
    p.stdin.close()
    try:
        p.wait(timeout=0.5)  # it must still be waiting: a hang detector in reverse
        raise AssertionError("a node stopped on stdin EOF without the supervisor's flag")
    except subprocess.TimeoutExpired:
        pass
    finally:
        p.terminate()
        p.wait(timeout=30)
    assert p.stdout is not None and p.stdout.read() == b"stopped\n"  # SIGTERM stopped it
