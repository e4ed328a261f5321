"""The ground's operator and station (issue 29, ground side): ``--operator
NAME --station NAME`` read their key files from the key directory (a clear
error for a missing file, an unknown name, a mission with command authority
and no operator), a station keeps the command lock while its operator holds
it (a counted LOCK renewal before the lease runs out, none once released or
once the station is silent), and every verdict names its operator."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from tests.unit.test_identities import MISSION, keygen
from tests.unit.test_stations_lockstep import Stations, flight_with_ground
from zplatform.cli.main import main
from zplatform.control.authority import Signer
from zplatform.core.auth import KEY_ENV, KEY_FILE_ENV, KeyError_, load_keys
from zplatform.errors import CommandError
from zplatform.ground.identity import check_names, station_signer
from zplatform.mission.load import load_mission
from zplatform.security.identities import sim_signer
from zplatform.sim.lockstep import LockstepRunner, sim_keys
from zplatform.telemetry.records import format_outcome


def test_the_signer_comes_from_the_key_files_beside_the_tools_key(
    keydir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = load_mission(keygen(tmp_path, MISSION, keydir), code=False)
    monkeypatch.setenv(KEY_FILE_ENV, str(keydir / "gn.keys"))
    s = station_signer(m, "alice", "pad")
    assert isinstance(s, Signer)
    assert (s.operator, s.station) == ("alice", "pad")
    # The same lookup with the directory itself.
    assert station_signer(m, "bob", "lounge", keydir) is not None


def test_with_a_master_key_the_signer_derives_from_it_as_the_cns_keys_do(
    keydir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = load_mission(keygen(tmp_path, MISSION, keydir), code=False)
    monkeypatch.setenv(KEY_ENV, "5f0c9a7e13d2b8466a91e0c3f57d28b4c61a0e9f3b7d52c8e4a16f903bd7e25a")
    s = station_signer(m, "alice", "pad")
    keys = load_keys(m, "cn")
    assert keys is not None
    assert s == sim_signer(keys, m, "alice", "pad")  # no key file read: the CN's derivation


def test_refusals_name_the_file_the_name_and_what_to_do(keydir: Path, tmp_path: Path) -> None:
    m = load_mission(keygen(tmp_path, MISSION, keydir), code=False)
    with pytest.raises(CommandError, match=r"say who commands with --operator NAME --station"):
        station_signer(m, None, None, keydir)
    with pytest.raises(CommandError, match=r"no operator 'alcie'.*did you mean alice\?"):
        station_signer(m, "alcie", "pad", keydir)
    with pytest.raises(CommandError, match=r"no station 'pda'.*did you mean pad\?"):
        station_signer(m, "alice", "pda", keydir)
    with pytest.raises(CommandError, match="go together"):
        station_signer(m, "alice", None, keydir)
    (keydir / "operator-bob.keys").unlink()
    with pytest.raises(KeyError_, match=r"no key file .*operator-bob\.keys: `zplatform keygen"):
        station_signer(m, "bob", "pad", keydir)


def test_a_mission_without_authority_needs_no_operator_and_takes_none_without_ground(
    tmp_path: Path,
) -> None:
    single = MISSION + "  single_operator: true\n"
    m = load_mission(_write(tmp_path / "single.yaml", single), code=False)
    assert check_names(m, None, None) is False
    plain = MISSION.split("ground:")[0]
    m2 = load_mission(_write(tmp_path / "plain.yaml", plain), code=False)
    assert check_names(m2, None, None) is False
    with pytest.raises(CommandError, match="has no `ground:` section"):
        check_names(m2, "alice", "pad")


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_cmd_refuses_a_mission_with_authority_without_operator_before_any_session(
    keydir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    capsys.readouterr()
    assert main(["cmd", str(path), "noop", "--timeout", "0.1"]) == 2
    assert "--operator NAME --station NAME" in capsys.readouterr().err
    assert main(["cmd", str(path), "noop", "--operator", "alise", "--station", "pad"]) == 2
    assert "did you mean alice?" in capsys.readouterr().err


def _runner(op: str = "pat", st: str = "pad", lease_s: float = 2) -> LockstepRunner:
    m = flight_with_ground()
    if lease_s != 2:
        assert m.ground is not None
        m = msgspec.structs.replace(m, ground=msgspec.structs.replace(m.ground, lease_s=lease_s))
    keys = sim_keys(m)
    assert keys is not None
    return LockstepRunner(m, signer=sim_signer(keys, m, op, st))


def test_the_station_renews_the_lock_while_its_operator_holds_it_and_stops_on_release() -> None:
    r = _runner()
    r.run(0.5)
    g = r.ground
    lock = g.command("LOCK", now_ns=r.clock.now_ns())
    r.run(0.1)
    (granted,) = g.result(lock) or []
    assert granted.accepted and granted.operator == "pat@pad"
    assert format_outcome(granted) == f"LOCK #{granted.seq} by pat@pad: ACCEPTED"
    dv = r.control.dv
    # lease_s 2: a LOCK goes in the loop after the one whose snapshot shows
    # less than 1 s left, and renews 2 s from its own loop: one per 1.02 s
    # or so, 9 in the next 10 s.
    r.run(10.0)
    assert dv.get_name("cn_lock_holder") == "pat" and dv.get_name("cn_lock_station") == "pad"
    assert g.lock_renewals == 9 and g.lock_renewals_refused == 0
    assert g.outcomes == [granted]  # renewals are not the operator's outcomes
    lock_events = [e.text for e in r.run(0.0).events if e.id == "cmd_lock"]
    assert lock_events == ["command lock granted: pat@pad holds the command lock"]
    release = g.command("RELEASE", now_ns=r.clock.now_ns())
    r.run(0.1)
    assert (g.result(release) or [])[0].accepted
    r.run(5.0)
    assert dv.get_name("cn_lock_holder") == "NONE"
    assert g.lock_renewals == 9


def test_a_silent_station_stops_renewing_and_the_lease_runs_out() -> None:
    r = _runner()
    r.run(0.5)
    r.ground.command("LOCK", now_ns=r.clock.now_ns())
    r.run(3.0)
    assert r.control.dv.get_name("cn_lock_holder") == "pat"
    r.partition("cn", "gn")  # the station's link is gone: nothing it sends arrives
    r.run(2.5)
    assert r.control.dv.get_name("cn_lock_holder") == "NONE"
    expired = [e.text for e in r.run(0.0).events if e.id == "cmd_lock"]
    assert expired[-1] == (
        "command lock expired: pat@pad's command lock expired (no request in its lease)"
    )


def test_no_renewal_between_an_arm_and_its_approved_command() -> None:
    """The holder's ARM waits for a second operator's approval past half the
    lease: a renewal there would void the ARM; the station sends none, and
    the approved LAUNCH is accepted."""
    r = _runner("fd", "room")
    s = Stations(r)
    g = r.ground
    r.run(0.5)
    g.command("LOCK", now_ns=r.clock.now_ns())
    r.run(0.1)
    arm = g.command("ARM", now_ns=r.clock.now_ns())
    r.run(0.1)
    (armed,) = g.result(arm) or []
    assert armed.accepted
    renewals = g.lock_renewals
    r.run(1.2)  # past half the lease (lease_s 2) since the ARM
    assert g.lock_renewals == renewals
    assert s.send("rso@lounge", "APPROVE", ref=armed.seq) == "ACCEPTED"
    launch = g.command("LAUNCH", now_ns=r.clock.now_ns())
    r.run(0.1)
    (launched,) = g.result(launch) or []
    assert launched.status == "ACCEPTED" and launched.operator == "fd@room"


def test_a_request_is_numbered_above_another_stations_refused_one() -> None:
    """The CN's request intake admits each number once, whatever the
    authority then says: after a viewer's request numbered n was refused
    (``cn_cmd_reject_seq`` n, no number consumed), this station numbers its
    next one n + 1, not n (which the live CN refuses as REJECTED_REPLAY)."""
    r = _runner()
    s = Stations(r)
    r.run(0.5)
    assert s.send("vic@lounge", "NOOP") == "REJECTED_VIEW_ONLY"
    refused = r.control.dv.get("cn_cmd_reject_seq")
    assert r.control.dv.get("cn_cmd_seq") == refused - 1
    t = r.ground.command("LOCK", now_ns=r.clock.now_ns())
    r.run(0.1)
    (o,) = r.ground.result(t) or []
    assert o.seq == refused + 1 and o.accepted


def test_up_with_a_script_refuses_a_mission_with_authority_without_operator(
    keydir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    script = tmp_path / "s.txt"
    script.write_text("at 1.0 noop\n")
    capsys.readouterr()
    assert main(["up", str(path), "--commands", str(script), "--free-ports"]) == 2
    assert "--operator NAME --station NAME" in capsys.readouterr().err


def test_the_console_refuses_an_operator_it_cannot_sign_for_before_it_opens(
    keydir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The console signs as --operator at --station (tests/unit/test_console_operator.py);
    # a misspelt name or a missing key file is refused in one line, nothing opened.
    path = keygen(tmp_path, MISSION, keydir)
    capsys.readouterr()
    assert main(["ground", str(path), "--console", "--operator", "alise", "--station", "pad"]) == 2
    assert "did you mean alice?" in capsys.readouterr().err
    (keydir / "operator-bob.keys").unlink()
    monkeypatch.setenv(KEY_FILE_ENV, str(keydir / "gn.keys"))
    assert main(["ground", str(path), "--console", "--operator", "bob", "--station", "pad"]) == 2
    assert "operator-bob.keys" in capsys.readouterr().err


def test_a_command_returns_when_its_outcome_is_released_not_a_snapshot_later() -> None:
    """The verdict's snapshot decides, the CN's event with the reason releases
    the outcome: GroundLink.command returns then, without waiting for the
    next snapshot (a loop later)."""
    from types import SimpleNamespace

    from zplatform.control.uplink import CheckedCommand
    from zplatform.ground.link import GroundLink
    from zplatform.telemetry.records import CommandOutcome

    done = CommandOutcome("NOOP", 2, "ACCEPTED")
    items = [("tm", "verdict"), ("ev", "cmd_accepted"), ("tm", "next loop"), ("tm", "and one more")]
    taken: list[str] = []

    class Logic:
        awaiting_approval = None

        def result(self, ticket: int) -> list[CommandOutcome] | None:
            return [done] if "cmd_accepted" in taken else None

    def pop(deadline: float) -> tuple[str, str, int, str] | None:
        kind, what = items.pop(0)
        return kind, what, 0, ""

    def take(kind: str, what: str, rx: int, key: str) -> bool:
        taken.append(what)
        return kind == "tm"

    def next_(timeout_s: float) -> int | None:  # what command() used: until a snapshot
        while item := pop(0.0):
            if take(*item):
                return 0
        return None

    fake = SimpleNamespace(
        logic=Logic(),
        wait_joined=lambda t: None,
        wait_cn_listening=lambda t: None,
        submit=lambda checked, armed: 1,
        _pop=pop,
        _take=take,
        next=next_,
    )
    assert GroundLink.command(fake, CheckedCommand("NOOP", 0, 0.0), timeout_s=5) == [done]  # type: ignore[arg-type]
    assert taken == ["verdict", "cmd_accepted"]


def test_a_not_holder_verdict_names_the_holder_when_the_cns_event_is_not_there() -> None:
    """The CN events a refusal at most once a second: the second of two
    quick REJECTED_NOT_HOLDER verdicts has no event, and the ground names
    the holder from the verdict's snapshot (``cn_lock_holder``/``station``)."""
    r = _runner()
    s = Stations(r)
    r.run(0.5)
    assert s.send("fd@room", "LOCK") == "ACCEPTED"
    g = r.ground
    first = g.command("NOOP", now_ns=r.clock.now_ns())
    r.run(0.1)
    second = g.command("NOOP", now_ns=r.clock.now_ns())
    r.run(1.0)
    (a,) = g.result(first) or []
    (b,) = g.result(second) or []
    assert a.status == b.status == "REJECTED_NOT_HOLDER"
    assert a.reason_from == "cn" and "fd@room holds the command lock" in a.reason
    assert (b.reason_from, b.reason) == ("derived", "fd@room holds the command lock")


def test_an_armed_two_person_command_waits_for_the_approval_then_goes() -> None:
    """``cmd launch --arm`` in a mission whose LAUNCH is two-person: ARM n,
    then nothing until a second operator's APPROVE of n shows in telemetry
    (``cn_arm_approvals``), then LAUNCH, accepted."""
    r = _runner("fd", "room")
    s = Stations(r)
    g = r.ground
    r.run(0.5)
    g.command("LOCK", now_ns=r.clock.now_ns())
    r.run(0.1)
    t = g.command("LAUNCH", armed=True, now_ns=r.clock.now_ns())
    r.run(2.0)
    arm = g.awaiting_approval
    assert arm is not None and [o.command for o in g.partial(t)] == ["ARM"]
    assert g.result(t) is None and r.control.dv.get_name("cn_state") == "SAFE"
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "ACCEPTED"
    r.run(1.0)
    arm_o, launch = g.result(t) or []
    assert (arm_o.seq, arm_o.status) == (arm, "ACCEPTED")
    assert (launch.seq, launch.status, launch.operator) == (arm + 2, "ACCEPTED", "fd@room")
    assert r.control.dv.get_name("cn_state") == "ARMED"


def test_without_an_approval_the_command_goes_when_the_window_closes_and_is_refused() -> None:
    """A lease longer than the ARM's window (no renewal voids the ARM): the
    command goes when the window has closed, and the CN refuses it (no ARM
    open any more)."""
    r = _runner("fd", "room", lease_s=20)
    g = r.ground
    r.run(0.5)
    g.command("LOCK", now_ns=r.clock.now_ns())
    r.run(0.1)
    t = g.command("LAUNCH", armed=True, now_ns=r.clock.now_ns())
    r.run(12.0)  # the ARM's 10 s window, and the verdict
    arm_o, launch = g.result(t) or []
    assert arm_o.accepted and launch.status == "REJECTED_NOT_ARMED"  # the ARM ran out
    assert r.control.dv.get_name("cn_state") == "SAFE"


def test_sim_plays_a_script_as_the_named_operator(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import yaml

    from tests.unit.test_stations_lockstep import FLIGHT, GROUND
    from zplatform.config import relocate_mission

    raw = yaml.safe_load(FLIGHT.read_text() + GROUND)
    relocate_mission(raw, FLIGHT)
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    script = tmp_path / "s.txt"
    script.write_text("at 1.0 lock\nat 2.0 noop\n")
    argv = ["sim", str(path), "--commands", str(script), "--duration", "3"]
    assert main(argv) == 2  # a mission with authority: who commands?
    assert "--operator NAME --station NAME" in capsys.readouterr().err
    assert main([*argv, "--operator", "pat", "--station", "pad"]) == 0
    out = capsys.readouterr().out
    assert "LOCK #1 by pat@pad: ACCEPTED" in out and "NOOP #2 by pat@pad: ACCEPTED" in out
