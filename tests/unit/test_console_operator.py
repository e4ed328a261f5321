"""The console as an operator (issue 29): it signs as ``--operator NAME
--station NAME``, shows who holds the command lock and until when and this
console's ARM awaiting approval, sends ``approve N``, and refuses locally,
in the CN's own words, what the CN would refuse (a viewer commanding, a
view-only station, a command while another operator holds the lock)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from textual.widgets import Static

from tests.unit.test_authority import Rig, S, mission, signer
from zplatform.config import CMD_STATUS_NAMES
from zplatform.config.codes import Command
from zplatform.console import ConsoleApp, ConsoleModel
from zplatform.console.app import _status_text
from zplatform.console.link import Link
from zplatform.console.model import StationRow
from zplatform.control.authority import Identity
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import CommandError
from zplatform.telemetry.records import CommandOutcome

ROOT = Path(__file__).resolve().parents[2]


def _console(rig: Rig, who: str) -> ConsoleModel:
    """A console signed as ``who`` (``op@station``), fed the rig's CN vector."""
    model = ConsoleModel(rig.m)
    model.operator = who
    _feed(rig, model)
    return model


def _feed(rig: Rig, model: ConsoleModel) -> None:
    rig.dv.set("cn_time_ns", rig.t)  # the loop's time, as the CN's loop writes it
    model.on_snapshot(rig.dv, rig.t)
    model.tick(rig.t)


def _run(model: ConsoleModel, body: Callable[[ConsoleApp], None]) -> list[str]:
    """Drive a console (no link) with textual's pilot; the event pane's texts."""

    async def go() -> None:
        app = ConsoleApp(model, now_ns=lambda: model.now_ns or 0)
        async with app.run_test(size=(120, 30)) as pilot:
            await pilot.pause()
            body(app)
            await pilot.pause()

    asyncio.run(go())
    return [x.text for x in model.log]


def _cn_says(rig: Rig, who: str, cmd: Command, *, ref: int = 0) -> str:
    """What the CN's authority refuses ``who``'s ``cmd`` with, ``STATUS: detail``."""
    op, st = who.split("@")
    g = rig.m.ground
    assert g is not None and rig.ch.authority is not None
    ident = Identity(
        [o.name for o in g.operators].index(op), [s.name for s in g.stations].index(st)
    )
    got = rig.ch.authority.check(ident, cmd, rig.t, ref=ref)
    assert got is not None
    return f"{CMD_STATUS_NAMES[got[0]]}: {got[1]}"


def test_a_command_while_another_holds_the_lock_is_refused_here_in_the_cns_words() -> None:
    rig = Rig()
    assert rig.send("alice@pad", "LOCK") == "ACCEPTED"
    model = _console(rig, "bob@room")
    texts = _run(model, lambda app: app.run_command("write x 3"))
    said = "REJECTED_NOT_HOLDER: alice@pad holds the command lock (5.0 s left)"
    assert _cn_says(rig, "bob@room", Command.WRITE) == said
    assert texts[-1] == f"WRITE x 3 by bob@room: {said} (not sent)"
    # The CN refuses it so too, had it been sent.
    assert rig.send("bob@room", "WRITE", 0) == "REJECTED_NOT_HOLDER"
    # A LOCK of bob's too; the holder herself commands (no link here: not sent).
    assert model.refusal("LOCK") == said
    alice = _console(rig, "alice@pad")
    texts = _run(alice, lambda app: app.run_command("write x 3"))
    assert texts[-1] == "no link: WRITE x 3 not sent"


def test_nobody_holding_the_lock_refuses_a_command_but_not_a_lock() -> None:
    rig = Rig()
    model = _console(rig, "bob@room")
    said = "REJECTED_NOT_HOLDER: nobody holds the command lock"
    assert _cn_says(rig, "bob@room", Command.WRITE) == said
    assert model.refusal("WRITE") == said
    assert model.refusal("LOCK") is None
    texts = _run(model, lambda app: app.run_command("lock"))
    assert texts[-1] == "no link: LOCK not sent"


def test_a_viewer_and_a_view_only_station_are_refused_here_in_the_cns_words() -> None:
    rig = Rig()
    assert rig.send("alice@pad", "LOCK") == "ACCEPTED"
    viewer = _console(rig, "vic@pad")
    texts = _run(viewer, lambda app: app.run_command("lock"))
    said = "REJECTED_VIEW_ONLY: vic may not command (roles)"
    assert _cn_says(rig, "vic@pad", Command.LOCK) == said
    assert texts[-1] == f"LOCK by vic@pad: {said} (not sent)"
    lounge = _console(rig, "alice@lounge")
    texts = _run(lounge, lambda app: app.run_command("write x 1"))
    said = "REJECTED_VIEW_ONLY: station lounge may only view (ground.stations)"
    assert _cn_says(rig, "alice@lounge", Command.WRITE) == said
    assert texts[-1] == f"WRITE x 1 by alice@lounge: {said} (not sent)"
    # An operator who is no flight director cannot take the lock over.
    said = "REJECTED_ROLE: bob is no flight director"
    assert _cn_says(rig, "bob@room", Command.TAKEOVER) == said
    assert _console(rig, "bob@room").refusal("TAKEOVER") == said
    # Range safety's ABORT goes from any station, lock or not; approving is the CN's call.
    assert _console(rig, "rso@lounge").refusal("ABORT") is None
    assert _cn_says(rig, "vic@pad", Command.WRITE).startswith("REJECTED_VIEW_ONLY")


def test_the_status_line_shows_who_commands_the_lock_and_the_arm_awaiting_approval() -> None:
    rig = Rig()
    assert rig.send("fd@pad", "LOCK") == "ACCEPTED"
    rig.wait(2.0)
    model = _console(rig, "fd@pad")
    line = _status_text(model.status()).plain
    assert "as fd@pad  fd@pad holds the command lock (3.0 s left)" in line
    assert rig.send("fd@pad", "ARM") == "ACCEPTED"
    n = rig.ch.last_seq
    model.on_result(rig.t, CommandOutcome("ARM", n, "ACCEPTED", operator="fd@pad"))
    assert model.last_command == f"ARM #{n} by fd@pad: ACCEPTED"  # the verdict names them
    model.set_awaiting(rig.t, n)  # as the link tells it from GroundLogic.awaiting_approval
    said = f"ARM #{n} awaits a second operator's approval: `approve {n}` at another console"
    assert model.status().pending_arm == said
    assert said in _status_text(model.status()).plain
    assert [x.text for x in model.log][-1] == said  # noted once
    model.set_awaiting(rig.t, n)
    assert [x.text for x in model.log].count(said) == 1
    model.set_awaiting(rig.t, None)
    assert model.status().pending_arm == ""
    # Ten seconds on, the lease ran out.
    rig.wait(10.0)
    _feed(rig, model)
    assert model.status().lock == "nobody holds the command lock"


def test_approve_n_goes_to_the_vehicle_from_any_operator() -> None:
    rig = Rig()
    assert rig.send("fd@pad", "LOCK") == "ACCEPTED"
    assert rig.send("fd@pad", "ARM") == "ACCEPTED"
    n = rig.ch.last_seq
    model = _console(rig, "rso@lounge")  # an approver, not the holder, at a view-only station
    texts = _run(model, lambda app: app.run_command(f"approve {n}"))
    assert texts[-1] == f"no link: APPROVE {n} not sent"


def test_an_out_of_date_approval_and_approving_ones_own_arm_are_refused_here() -> None:
    """The two approval cases the CN judges from its ARM: the console has
    the open ARM in telemetry (cn_arm_open, cn_arm_operator, cn_arm_open_ns,
    cn_arm_approvers) and refuses them in the CN's words."""
    rig = Rig()
    assert rig.send("fd@pad", "LOCK") == "ACCEPTED"
    rso = _console(rig, "rso@lounge")
    said = "REJECTED_APPROVAL_STALE: approval of ARM #7: no ARM is open"
    assert rso.refusal("APPROVE", ref=7) == said
    assert _cn_says(rig, "rso@lounge", Command.APPROVE, ref=7) == said
    assert rig.send("fd@pad", "ARM") == "ACCEPTED"
    n = rig.ch.last_seq
    _feed(rig, rso)
    said = f"REJECTED_APPROVAL_STALE: approval of ARM #{n - 1}: the current ARM is #{n}"
    assert rso.refusal("APPROVE", ref=n - 1) == said
    assert _cn_says(rig, "rso@lounge", Command.APPROVE, ref=n - 1) == said
    # The director armed it: approving it from another station is approving one's own.
    fd = _console(rig, "fd@room")
    said = f"REJECTED_APPROVAL_SELF: fd armed or approved ARM #{n} already: a second operator must"
    texts = _run(fd, lambda app: app.run_command(f"approve {n}"))
    assert texts[-1] == f"APPROVE {n} by fd@room: {said} (not sent)"
    assert _cn_says(rig, "fd@room", Command.APPROVE, ref=n) == said
    assert rig.send("fd@room", "APPROVE", ref=n) == "REJECTED_APPROVAL_SELF"
    # Range safety approves; a second approval of theirs is refused here too.
    assert rso.refusal("APPROVE", ref=n) is None
    assert rig.send("rso@lounge", "APPROVE", ref=n) == "ACCEPTED"
    _feed(rig, rso)
    assert rso.refusal("APPROVE", ref=n) == _cn_says(rig, "rso@lounge", Command.APPROVE, ref=n)
    assert rso.refusal("APPROVE", ref=n).startswith("REJECTED_APPROVAL_SELF")  # type: ignore[union-attr]
    # Ten seconds on, the ARM is too old to approve, here as at the CN.
    rig.wait(4.0)
    assert rig.send("fd@pad", "NOOP") == "ACCEPTED"  # renews the lease; the ARM stays open
    rig.wait(7.0)
    _feed(rig, rso)
    assert rso.refusal("APPROVE", ref=n) == _cn_says(rig, "rso@lounge", Command.APPROVE, ref=n)


def test_a_watching_console_and_a_mission_without_authority_refuse_nothing_here() -> None:
    rig = Rig()
    assert rig.send("alice@pad", "LOCK") == "ACCEPTED"
    watcher = _console(rig, "")
    assert watcher.refusal("WRITE") is None
    assert "holds the command lock" in watcher.status().lock
    assert "as viewer" in _status_text(watcher.status()).plain
    plain = ConsoleModel(mission(ground=""))  # no `ground:`: no authority to mirror
    plain.operator = "alice@pad"
    assert plain.refusal("WRITE") is None and plain.status().lock == ""


def test_the_link_signs_as_its_operator(monkeypatch: pytest.MonkeyPatch) -> None:
    import zplatform.ground.link as ground_link

    rig = Rig()
    s = signer(rig.m, "alice", "pad")
    got: dict[str, Any] = {}

    class _Stop(Exception):
        pass

    def fake(mission: Any, **kw: Any) -> None:
        got.update(kw)
        raise _Stop

    monkeypatch.setattr(ground_link, "GroundLink", fake)
    model = ConsoleModel(rig.m)
    link = Link(model, signer=s)
    assert model.operator == "alice@pad"
    with pytest.raises(_Stop):
        link._run()
    assert got["signer"] is s and got["commands"] is True


def test_ground_console_takes_operator_and_station(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import zplatform.console as console
    from tests.keys import own_key_home
    from tests.unit.test_identities import MISSION, keygen
    from zplatform.cli.main import _load_extras, build_parser
    from zplatform.core.auth import KEY_FILE_ENV

    own_key_home(monkeypatch, tmp_path / "config")
    keydir = tmp_path / "keys"
    path = str(keygen(tmp_path, MISSION, keydir))
    monkeypatch.setenv(KEY_FILE_ENV, str(keydir / "gn.keys"))
    _load_extras()
    got: dict[str, Any] = {}
    monkeypatch.setattr(console, "run_console", lambda path, **kw: got.update(kw) or 0)
    args = build_parser().parse_args(
        ["ground", path, "--console", "--operator", "alice", "--station", "pad"]
    )
    assert args.func(args) == 0
    assert (got["signer"].operator, got["signer"].station) == ("alice", "pad")
    args = build_parser().parse_args(["ground", path, "--console"])
    assert args.func(args) == 0 and got["signer"] is None  # a console that only watches
    args = build_parser().parse_args(
        ["ground", path, "--console", "--operator", "alise", "--station", "pad"]
    )
    with pytest.raises(CommandError, match=r"no operator 'alise'.*did you mean alice\?"):
        args.func(args)


def test_the_link_shows_the_arm_awaiting_approval_once_and_waits_its_window_more(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The link's thread reads GroundLogic.awaiting_approval each turn: the
    model notes it once, clears it when the command went, and the command's
    "no verdict" warning waits the ARM's window more."""
    import zplatform.ground.link as ground_link
    from zplatform.control.uplink import validate_words

    rig = Rig()
    model = ConsoleModel(rig.m)
    link = Link(model, timeout_s=0.0, signer=signer(rig.m, "fd", "pad"))
    arms = iter([7, 7, 7, None])

    class _Logic:
        joined = True
        counters = None

        @property
        def awaiting_approval(self) -> int | None:
            try:
                return next(arms)
            except StopIteration:
                link._stop.set()
                return None

        def result(self, ticket: int) -> None:
            return None

    class _Fake:
        def __init__(self, mission: Any, **kw: Any) -> None:
            self.logic = _Logic()
            self.waiting_for_run = False

        def next(self, timeout_s: float) -> None:
            return None

        def submit(self, checked: Any, *, armed: bool) -> int:
            return 1

        def close(self) -> None:
            pass

    monkeypatch.setattr(ground_link, "GroundLink", _Fake)
    link.send(validate_words(rig.m, "launch", []), "LAUNCH", True)
    link._run()
    said = "ARM #7 awaits a second operator's approval: `approve 7` at another console"
    texts = [x.text for x in model.log]
    assert texts.count(said) == 1
    assert model.awaiting_arm is None
    # timeout 0: without the ARM's window the warning would have come at once.
    assert not any("no verdict" in t for t in texts)
    assert link.busy


def test_the_web_console_signs_each_browser_session_as_the_operator(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import zplatform.console.web as web
    from zplatform.console import serve_console

    got: list[list[str]] = []

    class _Web:
        def __init__(self, argv: list[str], **kw: Any) -> None:
            got.append(argv)

        def serve(self) -> None:
            pass

    monkeypatch.setattr(web, "WebConsole", _Web)
    serve_console(str(ROOT / "configs" / "led_test.yaml"), 0, operator="alice", station="pad")
    assert got[0][-4:] == ["--operator", "alice", "--station", "pad"]


def test_another_consoles_open_arm_is_shown_to_the_approver_until_approved() -> None:
    rig = Rig()
    assert rig.send("fd@pad", "LOCK") == "ACCEPTED"
    assert rig.send("fd@pad", "ARM") == "ACCEPTED"
    n = rig.ch.last_seq
    rso = _console(rig, "rso@room")
    said = f"ARM #{n} by fd is open: `approve {n}` if it is yours to approve"
    assert rso.status().pending_arm == said
    assert said in _status_text(rso.status()).plain
    assert _console(rig, "fd@pad").status().pending_arm == ""  # the armer's own: the link says
    # A refused approval leaves it open; an accepted one closes it.
    assert rig.send("alice@pad", "APPROVE", ref=n) == "REJECTED_ROLE"
    _feed(rig, rso)
    assert rso.status().pending_arm == said
    assert rig.send("rso@room", "APPROVE", ref=n) == "ACCEPTED"
    _feed(rig, rso)
    assert rso.status().pending_arm == ""
    # An operator without an approving role is refused here, in the CN's words.
    said = "REJECTED_ROLE: alice has no approving role"
    assert _cn_says(rig, "alice@pad", Command.APPROVE) == said
    alice = _console(rig, "alice@pad")
    texts = _run(alice, lambda app: app.run_command(f"approve {n}"))
    assert texts[-1] == f"APPROVE {n} by alice@pad: {said} (not sent)"


def test_an_open_arm_closes_with_its_window_or_the_next_accepted_command() -> None:
    rig = Rig()
    assert rig.send("fd@pad", "LOCK") == "ACCEPTED"
    assert rig.send("fd@pad", "ARM") == "ACCEPTED"
    rso = _console(rig, "rso@room")
    assert rso.status().pending_arm != ""
    rig.wait(10.5)
    _feed(rig, rso)
    assert rso.status().pending_arm == ""  # older than the ARM's 10 s window
    assert rig.send("fd@pad", "LOCK") == "ACCEPTED"
    assert rig.send("fd@pad", "ARM") == "ACCEPTED"
    _feed(rig, rso)
    assert rso.status().pending_arm != ""
    assert rig.send("fd@pad", "NOOP") == "ACCEPTED"
    _feed(rig, rso)
    assert rso.status().pending_arm == ""


def test_a_lockstep_flight_the_console_shows_the_signed_lock_kept_by_renewals() -> None:
    """The whole mission in lockstep, its ground logic signed as pat@pad (the
    console's path): the verdict names pat@pad, and the status line shows the
    lock held by renewals ten seconds on."""
    from tests.unit.test_ground_operator import _runner
    from tests.unit.test_stations_lockstep import Stations

    r = _runner()
    r.run(0.5)
    g = r.ground
    lock = g.command("LOCK", now_ns=r.clock.now_ns())
    r.run(0.1)
    (granted,) = g.result(lock) or []
    model = ConsoleModel(r.mission)
    model.operator = g.operator
    model.on_result(0, granted)
    assert model.last_command == f"LOCK #{granted.seq} by pat@pad: ACCEPTED"
    r.run(10.0)
    dv = r.control.dv
    model.on_snapshot(dv, 1)
    assert g.lock_renewals == 9
    left = (int(dv.get("cn_lock_until_ns")) - int(dv.get("cn_time_ns"))) / 1e9
    assert model.status().lock == f"pat@pad holds the command lock ({left:.1f} s left)"
    assert model.refusal("NOOP") is None
    # Another operator's console refuses what the CN refuses, for the same reason.
    other = ConsoleModel(r.mission)
    other.operator = "fd@room"
    other.on_snapshot(dv, 1)
    assert other.status().lock == model.status().lock
    assert other.refusal("NOOP") == f"REJECTED_NOT_HOLDER: {model.status().lock}"
    assert Stations(r).send("fd@room", "NOOP") == "REJECTED_NOT_HOLDER"


# ---------------------------------------------------- every station, heard


def test_the_status_lists_every_station_with_the_holder_and_when_last_heard() -> None:
    """From a hand-made vector: every station of the mission, its right, the
    lock's holder at its station, and the heard age in loop time (a view
    station that sent nothing is "not heard")."""
    rig = Rig()
    model = ConsoleModel(rig.m)
    dv = DataVector(Layout.for_node(rig.m, "cn"))
    t = 50 * S
    dv.set("cn_time_ns", t)
    dv.set("cn_lock_holder", "alice")
    dv.set("cn_lock_station", "pad")
    dv.set("cn_lock_until_ns", t + 3 * S)
    dv.set("cn_heard_pad_ns", t - S // 2)
    dv.set("cn_heard_room_ns", t - 12 * S)
    model.on_snapshot(dv, t)
    model.tick(t)
    rows = model.status().stations
    assert rows == (
        StationRow("pad", "command", "alice", 0.5),
        StationRow("room", "command", "", 12.0),
        StationRow("lounge", "view", "", None),
    )
    assert [r.text() for r in rows] == [
        "pad (command) alice holds the lock, heard 0.5 s ago",
        "room (command), heard 12.0 s ago",
        "lounge (view), not heard",
    ]
    # A lease that ran out marks no holder.
    dv.set("cn_time_ns", t + 4 * S)
    model.on_snapshot(dv, t + 4 * S)
    assert [r.holder for r in model.status().stations] == ["", "", ""]


def test_a_mission_without_authority_lists_no_stations() -> None:
    model = ConsoleModel(mission(""))
    rig = Rig()
    model.on_snapshot(DataVector(Layout.for_node(model.mission, "cn")), rig.t)
    assert model.status().stations == ()


def test_the_console_app_shows_every_station_and_when_it_was_heard() -> None:
    rig = Rig()
    assert rig.send("alice@pad", "LOCK") == "ACCEPTED"
    rig.wait(1.0)
    model = _console(rig, "bob@room")
    shown: list[str] = []

    def look(app: ConsoleApp) -> None:
        app.refresh_view()
        shown.append(str(app.query_one("#status", Static).content))

    _run(model, look)
    assert (
        "stations: pad (command) alice holds the lock, heard 1.0 s ago; "
        "room (command), not heard; lounge (view), not heard"
    ) in shown[0]
