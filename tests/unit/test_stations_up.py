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
    from zplatform.node.ground import run_station
    from zplatform.runtime.process import StopFlag
    from zplatform.telemetry.logs import read_csv
    from zplatform.telemetry.records import EventRecord

    m = mission(STATIONS + "archive: {enabled: false}\n")
    d = tmp_path / "pad"
    # What each station process receives: snapshots (their loop) and events (their seq).
    feeds = [[("tm", 1), ("ev", 1), ("tm", 2)], [("ev", 2), ("tm", 3), ("tm", 4)]]

    class Link:  # the station's GroundLink: feeds one process's share, then stops it
        def __init__(self, mission: Any, **kw: Any) -> None:
            layout = Layout.for_node(mission, "cn")
            counters = SimpleNamespace(
                received=0, gaps=0, rejected=0, first_seq=0, last_seq=0, refused={}, epoch_changes=0
            )
            self.logic = SimpleNamespace(
                layout=layout,
                dv=DataVector(layout),
                received=False,
                counters=counters,
                player=None,
                finish=lambda t: None,
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
