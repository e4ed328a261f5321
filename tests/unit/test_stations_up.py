"""Stations ``up`` starts (``ground.stations[].start``, ``operator``): the
config's checks, what ``up`` spawns for them, the status line's part, and
``zplatform station``'s refusals (issue 29)."""

from __future__ import annotations

import subprocess
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from zplatform.cli import supervisor
from zplatform.cli.main import main
from zplatform.errors import ConfigError
from zplatform.mission.load import decode_mission
from zplatform.node.ground import station_dir

BASE = """
mission: started
nodes:
  cn:  {listen: ['tcp/127.0.0.1:7447']}
  dn0: {connect: ['tcp/127.0.0.1:7447']}
  gn:  {connect: ['tcp/127.0.0.1:7447']}
regions:
  dn0_to_cn:
    - {name: v, type: f64}
ground:
  operators:
    - {name: fd, roles: [flight_director]}
    - {name: vic, roles: [viewer]}
  stations:
"""
STATIONS = """    - {name: pad, start: true, operator: fd}
    - {name: lounge, may: view, start: true}
    - {name: room}
"""


def mission(stations: str = STATIONS) -> Any:
    return decode_mission(BASE + stations)


@pytest.mark.parametrize(
    ("stations", "path", "text"),
    [
        (
            "    - {name: pad, start: true, operator: fred}\n",
            "$.ground.stations[0].operator",
            "runs as 'fred', who is no operator",
        ),
        (
            "    - {name: pad, operator: fd}\n",
            "$.ground.stations[0].operator",
            "say `start: true` too",
        ),
    ],
)
def test_a_bad_station_start_is_a_config_error_at_its_path(
    stations: str, path: str, text: str
) -> None:
    with pytest.raises(ConfigError) as exc:
        mission(stations)
    assert exc.value.path == path and text in str(exc.value)


def test_up_starts_the_stations_marked_start_each_in_its_own_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(BASE + STATIONS)
    m = decode_mission(path.read_text())
    seen: dict[str, Any] = {}

    def fake_supervise(mission: Any, spawn: Any, tmp: Any, reg: Any, **kw: Any) -> int:
        seen.update(spawn=spawn, stations=kw["stations"])
        return 0

    reg = SimpleNamespace(
        name="started", mission_file=str(path), update=lambda **kw: None, remove=lambda: None
    )
    monkeypatch.setattr(supervisor, "_supervise", fake_supervise)
    monkeypatch.setattr("zplatform.cli.registry.register", lambda *a: reg)
    p = str(path.resolve())
    assert supervisor.run_up(m, str(path), quiet=True, log=str(tmp_path / "tm.csv")) == 0
    assert seen["stations"] == {
        "station:pad": ["station", p, "pad", "--dir", str(station_dir(m, "pad")), "--log"],
        "station:lounge": ["station", p, "lounge", "--dir", str(station_dir(m, "lounge")), "--log"],
    }
    assert set(seen["spawn"]) == {"dn0", "gn", "cn"}  # stations are no nodes (no summary)
    assert station_dir(m, "pad") != station_dir(m, "lounge")
    assert station_dir(m, "pad").parent.name == "started.stations"


class _Proc:
    def __init__(self, code: int | None) -> None:
        self.returncode = code

    def poll(self) -> int | None:
        return self.returncode


def test_the_status_line_shows_each_started_station_up_or_dead() -> None:
    children = supervisor.Children()
    procs: dict[str, Any] = {
        "cn": _Proc(None),
        "station:pad": _Proc(None),
        "station:lounge": _Proc(-9),
    }
    children.procs = procs
    w = supervisor.Watch()
    assert supervisor.station_states(children, w) == "  stations pad=up lounge=died(-9)"
    children.procs = {"cn": procs["cn"]}
    assert supervisor.station_states(children, w) == ""


def test_zplatform_station_refuses_an_unknown_station_and_operator(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(BASE + STATIONS)
    assert main(["station", str(path), "pid"]) == 2
    assert "lists no station 'pid' (stations: pad, lounge, room)" in capsys.readouterr().err
    assert main(["station", str(path), "room", "--operator", "fdd"]) == 2
    assert "fd" in capsys.readouterr().err


def test_a_station_process_is_spawned_ready_once_its_session_opens(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``_supervise`` waits for a station's READY, as for a router's."""
    calls: list[tuple[str, float | None]] = []

    def spawn(self: Any, name: str, argv: list[str], *, ready: float | None = None) -> None:
        calls.append((name, ready))
        raise subprocess.SubprocessError("stop here")

    monkeypatch.setattr(supervisor.Children, "spawn", spawn)
    monkeypatch.setattr(supervisor.Children, "stop_all", lambda self: {})
    with pytest.raises(subprocess.SubprocessError):
        supervisor._supervise(
            mission(),
            {},
            Path("."),
            SimpleNamespace(update=lambda **kw: None),
            world=None,
            stations={"station:pad": ["station"]},
            summary=None,
            log=None,
            quiet=True,
            ready_timeout_s=7.0,
            end_after_script=False,
        )
    assert calls == [("station:pad", 7.0)]


def test_a_station_connects_through_its_router_and_sends_only_with_an_operator(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``run_station``: a client of its station's router whether or not it
    has an operator (before, only a signer's link took the router); with
    one, the uplink's publisher (to keep the lock), without, nothing to send."""
    import zplatform.ground.link as ground_link
    from zplatform.ground.identity import station_signer
    from zplatform.node.ground import run_station

    got: list[dict[str, Any]] = []

    class _Stop(Exception):
        pass

    def fake(mission: Any, node: Any, **kw: Any) -> None:
        got.append(dict(kw, node=node))
        raise _Stop

    monkeypatch.setattr(ground_link, "NodeSession", fake)
    m = mission(STATIONS + "    - {name: far, connect: ['tcp/10.2.0.2:7600']}\n")
    with pytest.raises(_Stop):
        run_station(m, "far", tmp_path / "far")
    with pytest.raises(_Stop):
        run_station(m, "far", tmp_path / "far", signer=station_signer(m, "fd", "far"))
    assert [(g["node"], g["via"], g["commands"]) for g in got] == [
        (None, ["tcp/10.2.0.2:7600"], False),
        (None, ["tcp/10.2.0.2:7600"], True),
    ]
    with pytest.raises(Exception, match="lists no station 'near'"):
        run_station(m, "near", tmp_path / "near")


def test_a_restarted_station_keeps_what_its_earlier_process_wrote(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Issue 29 follow-up: ``run_station`` twice into one directory (``up``
    restarting it, or a second run): its events and telemetry rows follow
    the first process's, under the CSV's one header; what a process killed
    mid-write left (a row and an event without their newline) is cut off,
    not glued to the next line. Before, each start truncated both files."""
    import json

    import zplatform.node.ground as node_ground
    from zplatform.core.datavector import DataVector, Layout
    from zplatform.core.events import EventLog
    from zplatform.node.ground import run_station
    from zplatform.runtime.process import StopFlag
    from zplatform.telemetry.logs import read_csv
    from zplatform.telemetry.records import EventRecord, TelemetryCounters

    m = mission(STATIONS + "archive: {enabled: false}\n")
    d = tmp_path / "pad"
    # What each station process receives: snapshots (their loop) and events (their seq).
    feeds = [[("tm", 1), ("ev", 1), ("tm", 2)], [("ev", 2), ("tm", 3), ("tm", 4)]]

    class Link:  # the station's GroundLink: feeds one process's share, then stops it
        def __init__(self, mission: Any, **kw: Any) -> None:
            layout = Layout.for_node(mission, "cn")
            counters = SimpleNamespace(  # TelemetryCounters' fields, writable
                **{f: getattr(TelemetryCounters(), f) for f in TelemetryCounters.__struct_fields__},
                rejected=0,
            )
            self.logic = SimpleNamespace(
                layout=layout,
                dv=DataVector(layout),
                received=False,
                counters=counters,
                player=None,
                finish=lambda t: None,
                events=EventLog("gn"),  # the ground's own events (its log's, its archive's)
            )
            self.clock = SimpleNamespace(now_ns=lambda: 0)
            self.on_event: Any = None
            self.feed = feeds.pop(0)

        def next(self, timeout: float) -> int | None:
            if not self.feed:
                stop.event.set()
                return None
            kind, k = self.feed.pop(0)
            if kind == "ev":
                self.on_event(EventRecord(k, "cn", k, k, "INFO", "cmd_accepted", f"ev {k}"))
                return None
            self.logic.dv.set("cn_loop", k)
            self.logic.received = True
            self.logic.counters.received += 1
            return 1000 + k

        def close(self) -> None:
            pass

    monkeypatch.setattr(node_ground, "GroundLink", Link)
    stop = StopFlag(install=False)
    assert run_station(m, "pad", d, log_csv=True, stop=stop).events_logged == 1
    with (d / "telemetry.csv").open("a") as f:  # the first process killed mid-write
        f.write("1003,3")
    with (d / "events.jsonl").open("a") as f:
        f.write('{"rx_time_ns":')
    stop = StopFlag(install=False)
    run_station(m, "pad", d, log_csv=True, stop=stop)
    assert [r["cn_loop"] for r in read_csv(d / "telemetry.csv")] == ["1", "2", "3", "4"]
    lines = (d / "events.jsonl").read_text().splitlines()
    assert [json.loads(line)["text"] for line in lines] == ["ev 1", "ev 2"]


# ------------------------------------------------- a dead station, restarted (issue 29)

PAD = "station:pad"


def test_a_dead_station_is_restarted_later_after_each_rapid_death_then_no_more() -> None:
    """``StationRestarts``: 1 s after a death that ends a long run, then
    2, 4, 8, 16 s after rapid deaths in a row (within 60 s of READY, or
    before it); the fifth rapid death is the last: no restart, said so.
    A station that then runs a while starts the count again."""
    r = supervisor.StationRestarts()
    r.ready(PAD, 0.0)
    assert r.state(PAD, None, 0.0) == "up"
    assert r.died(PAD, -9, 100.0) == supervisor.STATION_RESTART_S == 1.0  # up 100 s: not rapid
    assert r.state(PAD, -9, 100.2) == "died(-9; restart 1 in 1 s)"
    assert r.due(100.9) == []
    assert r.due(101.0) == [PAD] and r.due(101.0) == []  # each restart once
    assert r.starting() == [(PAD, 101.0)]
    assert r.state(PAD, None, 101.0) == "starting(restart 1)"
    r.ready(PAD, 102.0)
    assert r.starting() == [] and r.state(PAD, None, 102.0) == "up(1 restart)"
    now, delays = 110.0, []
    for _ in range(supervisor.STATION_RAPID_DEATHS):
        delay = r.died(PAD, 1, now)  # within 60 s of its READY, or before one
        delays.append(delay)
        if delay is not None:
            now += delay
            assert r.due(now) == [PAD]
    assert delays == [2.0, 4.0, 8.0, 16.0, None]
    assert r.state(PAD, 1, now + 1000) == "died(1; 5 rapid deaths: not restarted)"
    assert r.due(now + 1000) == [] and r.starting() == []
    assert r.restarts(PAD) == 5
    # Another station, never told of (its READY): up long before, a non-rapid death.
    assert r.died("station:room", 2, 5.0) == 1.0


class _FakeProc:
    def __init__(self, code: int | None = None) -> None:
        self.returncode = code

    def poll(self) -> int | None:
        return self.returncode


class _FakeChildren:
    """``up``'s children: the vehicle's nodes and station pad. ``respawned``
    says what a restarted station does: ``ready`` (says READY), ``dies``
    (at once) or ``hangs`` (never says a line)."""

    def __init__(self, respawned: str) -> None:
        self.procs: dict[str, Any] = {n: _FakeProc() for n in ("world", "dn0", "gn", "cn", PAD)}
        self.vehicle = {n: p for n, p in self.procs.items() if n != PAD}
        self.respawned = respawned
        self.calls: list[tuple[str, str]] = []

    def dead(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.returncode is not None]

    def respawn(self, name: str) -> None:
        self.calls.append(("respawn", name))
        self.procs[name] = _FakeProc(1 if self.respawned == "dies" else None)

    def said_ready(self, name: str) -> bool | None:
        return True if self.respawned == "ready" else None

    def kill(self, name: str) -> bool:
        self.calls.append(("kill", name))
        self.procs[name].returncode = -9
        return True


def _watch_station(
    monkeypatch: pytest.MonkeyPatch, respawned: str, run_s: float
) -> tuple[_FakeChildren, supervisor.Watch, str]:
    """``watch`` on a clock of its own (each empty read of the link is 0.2
    s) from 100 s: station pad, up since long before, is killed at 101 s;
    the watch runs until ``run_s``. Returns the children, the watch and
    what ``up`` said."""
    import contextlib
    import io

    from zplatform.core.datavector import DataVector, Layout

    m = mission()
    now = [100.0]
    monkeypatch.setattr(supervisor.time, "monotonic", lambda: now[0])
    children = _FakeChildren(respawned)
    w = supervisor.Watch()

    class Link:
        dv = DataVector(Layout.for_node(m, "gn"))
        logic = SimpleNamespace(received=True)

        def next(self, timeout: float) -> None:
            now[0] = round(now[0] + 0.2, 6)
            if now[0] == 101.0:
                children.procs[PAD].returncode = -9

    spawns: list[int] = []
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        supervisor.watch(
            m,
            children,  # type: ignore[arg-type]
            Link(),  # type: ignore[arg-type]
            w,
            lambda: now[0] >= 100.0 + run_s,
            quiet=True,
            ready_timeout_s=10.0,
            on_spawn=lambda: spawns.append(1),
        )
    assert len(spawns) == sum(c == "respawn" for c, _ in children.calls)
    # The vehicle's nodes: never restarted, killed or replaced, whatever the station did.
    assert {n: p for n, p in children.procs.items() if n != PAD} == children.vehicle
    assert all(p.returncode is None for p in children.vehicle.values())
    assert all(n == PAD for _, n in children.calls)
    return children, w, err.getvalue()


def test_up_restarts_a_dead_station_and_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 29 follow-up: station pad dies (-9); ``up`` reports it with
    its restart to come (1 s later), restarts it, sees its READY, and the
    status line shows it up again; the vehicle's nodes are never touched.
    Before, a dead station stayed dead."""
    children, w, said = _watch_station(monkeypatch, "ready", 10.0)
    assert children.calls == [("respawn", PAD)]
    assert "node station:pad died (exit code -9)" in said
    assert "; restart 1 in 1 s" in said
    assert "restarting station:pad (restart 1)" in said and "station:pad is up again" in said
    assert supervisor.station_states(children, w) == "  stations pad=up(1 restart)"  # type: ignore[arg-type]
    assert not w.ok  # a child died: the run ends non-zero, as for every child


@pytest.mark.parametrize("respawned", ["dies", "hangs"])
def test_a_station_in_a_crash_loop_is_restarted_no_more_after_five_rapid_deaths(
    monkeypatch: pytest.MonkeyPatch, respawned: str
) -> None:
    """Each restart of pad dies at once, or never says READY (killed
    after ``ready_timeout_s``): restarted 5 times (1 s after its first
    death, then 2, 4, 8 and 16 s after each rapid one); the fifth rapid
    death is its last, said on stderr and on the status line; the
    vehicle's nodes are never touched."""
    children, w, said = _watch_station(monkeypatch, respawned, 300.0)
    assert [c for c, _ in children.calls if c == "respawn"] == ["respawn"] * 5
    assert [c for c, _ in children.calls if c == "kill"] == (
        ["kill"] * 5 if respawned == "hangs" else []
    )
    for k, delay in enumerate((2, 4, 8, 16), start=2):
        assert f"; restart {k} in {delay} s" in said
    code = -9 if respawned == "hangs" else 1
    assert said.count("not ready in 10 s after its restart: killed") == (
        5 if respawned == "hangs" else 0
    )
    assert "it is not restarted again" in said
    assert supervisor.station_states(children, w) == (  # type: ignore[arg-type]
        f"  stations pad=died({code}; 5 rapid deaths: not restarted)"
    )


def test_a_respawned_station_is_read_for_its_ready_without_blocking(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``Children.respawn`` starts the child again (its argv kept), its
    dead process's pipes closed; ``said_ready`` reads what its pipe holds,
    never blocking: None before a whole line, then True for ``READY``,
    False for another line."""
    import select
    import sys

    lines = iter(["print('READY', flush=True)", "print('Traceback', flush=True)"])

    def popen(self: Any, argv: list[str], *, piped: bool) -> subprocess.Popen[bytes]:
        # A stand-in station: says its line, then waits for its stdin to close.
        code = f"import sys; {next(lines)}; sys.stdin.read()"
        return subprocess.Popen(
            [sys.executable, "-c", code],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE if piped else None,
        )

    monkeypatch.setattr(supervisor.Children, "_popen", popen)
    children = supervisor.Children()
    first = subprocess.Popen([sys.executable, "-c", "pass"], stdin=subprocess.PIPE)
    first.wait()
    children.procs[PAD] = first
    children._argv[PAD] = ["station", "m.yaml", "pad"]
    try:
        for want in (True, False):
            children.respawn(PAD)
            p = children.procs[PAD]
            assert p is not first and first.stdin is not None and first.stdin.closed
            assert p.stdout is not None
            said = None
            while said is None:  # None: no whole line yet (READY and its newline
                # come in two writes from an unbuffered child, as under `up`)
                assert select.select([p.stdout], [], [], 30)[0]
                said = children.said_ready(PAD)
            assert said is want
            first = p
            first.kill()
            first.wait()
    finally:
        for q in (first, children.procs[PAD]):
            if q.poll() is None:
                q.kill()
            q.wait()


def test_up_notes_its_stations_ready_and_records_a_restarted_ones_pid(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``_supervise``: a station spawned READY counts as up from then (its
    death within a minute is a rapid one), and each restart updates the
    run's record of the processes' PIDs (``ps``)."""
    import signal

    pids = iter(range(100, 200))

    def spawn(self: Any, name: str, argv: list[str], *, ready: float | None = None) -> None:
        self.procs[name] = SimpleNamespace(pid=next(pids), poll=lambda: None)

    recorded: list[dict[str, int]] = []
    got: dict[str, Any] = {}

    def watch(m: Any, children: Any, link: Any, w: Any, stopping: Any, **kw: Any) -> Any:
        got["rapid_restart_in"] = w.stations.died(PAD, -9, supervisor.time.monotonic())
        children.procs[PAD] = SimpleNamespace(pid=7, poll=lambda: None)  # restarted
        kw["on_spawn"]()
        return w

    monkeypatch.setattr(supervisor.Children, "spawn", spawn)
    monkeypatch.setattr(supervisor.Children, "stop_all", lambda self: {})
    monkeypatch.setattr(supervisor, "GroundLink", lambda *a, **kw: SimpleNamespace(close=None))
    monkeypatch.setattr(supervisor, "_close_link", lambda link: None)
    monkeypatch.setattr(supervisor, "watch", watch)
    monkeypatch.setattr(signal, "signal", lambda *a: None)  # pytest keeps its own
    supervisor._supervise(
        mission(),
        {},
        Path("."),
        SimpleNamespace(update=lambda **kw: recorded.append(kw["nodes"])),
        world=None,
        stations={PAD: ["station"]},
        summary=None,
        log=None,
        quiet=True,
        ready_timeout_s=7.0,
        end_after_script=False,
    )
    assert got["rapid_restart_in"] == 2 * supervisor.STATION_RESTART_S
    assert recorded == [{PAD: 100}, {PAD: 7}]
