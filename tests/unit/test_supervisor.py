"""``up``'s stop: the world outlives the device nodes, and ``up``'s own
zenoh session never decides a node's fate.

The order: the CN first, then the device nodes and the ground at once, the
world once the device nodes are down. The nodes are processes (stand-ins
here: a CN that ends its run, a DN that runs until signalled); ``up``'s link
is a fake whose close hangs, as a mutual-TLS session's close can on a busy
host. ``up`` must signal every node before it closes its session, and
return without waiting on that close.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from zplatform import load_mission
from zplatform.cli import supervisor
from zplatform.core.datavector import DataVector, Layout
from zplatform.ground.script import MIN_DURATION_S, SETTLE_S

ROOT = Path(__file__).resolve().parents[2]
MISSION = ROOT / "configs" / "minimal.yaml"
# The CN's run ends by itself (as with --duration); the DN runs until signalled.
PROGRAMS = {"cn": "pass", "dn0": "import time; time.sleep(120)"}  # stimulus: dn0 hangs on


class _Registry:
    def update(self, **kw: Any) -> None:
        pass


def test_up_stops_its_nodes_before_closing_its_session_and_never_waits_on_the_close(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mission = load_mission(MISSION)
    release = threading.Event()  # the hung close, released at the end
    at_close: dict[str, int | None] = {}

    class HungLink:
        def __init__(self, m: Any, **kw: Any) -> None:
            self.dv = DataVector(Layout.for_node(m, "gn"))
            self.logic = SimpleNamespace(received=True)  # telemetry flows

        def next(self, timeout: float) -> None:
            return None

        def close(self) -> None:
            at_close.update({n: p.poll() for n, p in children.procs.items()})
            release.wait()

    children = supervisor.Children()

    def spawn(self: supervisor.Children, name: str, argv: list[str], **kw: Any) -> None:
        self.procs[name] = subprocess.Popen([sys.executable, "-c", PROGRAMS[name]])

    monkeypatch.setattr(supervisor.Children, "spawn", spawn)
    monkeypatch.setattr(supervisor, "Children", lambda **_kw: children)
    monkeypatch.setattr(supervisor, "GroundLink", HungLink)
    monkeypatch.setattr(supervisor, "LINK_CLOSE_S", 0.2)
    monkeypatch.setattr(signal, "signal", lambda *a: None)  # pytest keeps its own

    result: list[int] = []

    def run() -> None:
        result.append(
            supervisor._supervise(
                mission,
                {n: [] for n in PROGRAMS},
                tmp_path,
                _Registry(),
                world=None,
                summary=None,
                log=None,
                quiet=True,
                ready_timeout_s=10.0,
                end_after_script=False,
            )
        )

    up = threading.Thread(target=run, daemon=True)
    try:
        up.start()
        up.join(60)
        assert not up.is_alive(), "up waited on its own session's close"
    finally:
        release.set()
        for p in children.procs.values():
            if p.poll() is None:
                p.kill()
            p.wait()
    # Every node had been stopped when the close began: the DN by its signal.
    assert at_close == {"cn": 0, "dn0": -signal.SIGTERM}
    assert result == [0]


@pytest.mark.parametrize(
    ("verdict_at", "settle_s", "ends_at"),
    [
        # The default: SETTLE_S after the last verdict, at least MIN_DURATION_S in all.
        (1.0, None, max(1.0 + SETTLE_S, MIN_DURATION_S)),
        (0.2, None, max(0.2 + SETTLE_S, MIN_DURATION_S)),
        (0.2, 1.0, 1.2),  # --settle S: S after the verdict, no minimum
        (3.0, 0.5, 3.5),
    ],
)
def test_a_script_run_ends_its_settle_after_the_last_verdict(
    monkeypatch: pytest.MonkeyPatch, verdict_at: float, settle_s: float | None, ends_at: float
) -> None:
    """``watch`` with a script and no duration (``up --commands``, ``--settle``),
    on a clock of its own: each empty read of the link is 0.1 s."""
    mission = load_mission(MISSION)
    now = [100.0]
    monkeypatch.setattr(supervisor.time, "monotonic", lambda: now[0])
    w = supervisor.Watch()

    class Link:
        dv = DataVector(Layout.for_node(mission, "gn"))
        logic = SimpleNamespace(received=True)

        def next(self, timeout: float) -> None:
            now[0] = round(now[0] + 0.1, 6)
            if w.script_done_at is None and now[0] >= 100.0 + verdict_at:
                w.script_done_at = now[0]  # the ground node's script_done

    children = SimpleNamespace(dead=lambda: [])
    supervisor.watch(
        mission,
        children,  # type: ignore[arg-type]
        Link(),  # type: ignore[arg-type]
        w,
        lambda: False,
        quiet=True,
        end_after_script=True,
        settle_s=settle_s,
    )
    assert w.script_done
    assert now[0] == pytest.approx(100.0 + ends_at)


def test_up_stops_the_control_node_then_the_rest_and_the_world_once_the_device_nodes_are_down() -> (
    None
):
    """``stop_all``'s order: the CN signalled and gone first (its final loop
    tells the device nodes the run ended); then the device nodes and the
    ground at once; the world once the device nodes have stopped (they safe
    their outputs into it), not after the ground's archive is written."""
    events: list[str] = []

    class Proc:
        def __init__(self, name: str) -> None:
            self.name, self.stdin, self.code = name, None, None

        def poll(self) -> int | None:
            return self.code

        def send_signal(self, sig: int) -> None:
            events.append(f"signal {self.name}")

        def wait(self, timeout: float | None = None) -> int:
            events.append(f"gone {self.name}")
            self.code = 0
            return 0

    children = supervisor.Children()
    for n in ("world", "dn0", "dn1", "gn", "cn"):  # the order `up` spawns them
        children.procs[n] = Proc(n)  # type: ignore[assignment]
    assert children.stop_all() == {n: 0 for n in ("cn", "dn0", "dn1", "gn", "world")}
    assert events == [
        "signal cn",
        "gone cn",
        "signal dn0",
        "signal dn1",
        "signal gn",
        "gone dn0",
        "gone dn1",
        "signal world",
        "gone gn",
        "gone world",
    ]
