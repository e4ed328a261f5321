"""Script lines naming their sender (issue 29): ``as alice@pad: at 1 lock``
for one line, ``as alice@pad`` alone for the lines after it; each is signed
with that operator's and station's keys (their key files, read as ``cmd
--operator`` reads them; a lockstep run's own keys), and an unknown
operator or station, or a missing key file, is an error naming the line."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.unit.test_identities import MISSION, keygen
from tests.unit.test_stations_lockstep import flight_with_ground
from zplatform.control.uplink import ScriptCommand, parse_commands
from zplatform.errors import CommandError
from zplatform.ground.identity import line_signer
from zplatform.ground.script import ScriptPlayer
from zplatform.mission.load import load_mission
from zplatform.sim.lockstep import LockstepRunner

SCRIPT = """\
as pat@pad: at 0.5 lock
at 0.6 noop                  # names nobody: the ground's own signer
as fd@room
at 0.7 lock                  # fd, pat holds the lock: refused
as pat@pad: at 0.8 handover fd
at 0.9 noop                  # fd again (the header), now the holder
"""


def test_as_lines_name_the_sender_of_one_line_or_of_the_lines_after_a_header() -> None:
    got = [(c.command, c.operator, c.station, c.source) for c in parse_commands(SCRIPT, "s")]
    assert got == [
        ("LOCK", "pat", "pad", "s:1"),
        ("NOOP", None, None, "s:2"),
        ("LOCK", "fd", "room", "s:4"),
        ("HANDOVER", "pat", "pad", "s:5"),
        ("NOOP", "fd", "room", "s:6"),
    ]


@pytest.mark.parametrize(
    ("line", "said"),
    [
        ("as pat: at 1 lock", "s:2: expected 'as OPERATOR@STATION' or"),
        ("as pat@pad: lock", "s:2: expected 'at SECONDS COMMAND [ARGS]', got 'lock'"),
        ("as pat@pad:", "s:2: expected 'at SECONDS COMMAND [ARGS]', got ''"),
        ("as pat@pad@x", "s:2: expected 'as OPERATOR@STATION' or"),
        ("as pat@pad: at 1 flyy", "s:2: unknown command 'flyy'"),
    ],
)
def test_a_malformed_as_line_is_refused_naming_it(line: str, said: str) -> None:
    with pytest.raises(CommandError) as e:
        parse_commands("at 0 noop\n" + line + "\n", "s")
    assert str(e.value).startswith(said)


def test_flown_in_lockstep_each_line_goes_signed_as_its_operator() -> None:
    m = flight_with_ground()
    two_person = (  # fd arms, range safety approves ARM #5, fd launches
        "at 1.0 arm\nas rso@lounge: at 1.1 approve 5\nat 1.2 launch\n"
    )
    script = SCRIPT.replace("at 0.6 noop", "") + two_person
    r = LockstepRunner(m, commands=parse_commands(script, "s"))
    res = r.run(2.0)
    out = [(o.command, o.status, o.operator, o.source) for o in r.ground.outcomes]
    assert out == [
        ("LOCK", "ACCEPTED", "pat@pad", "s:1"),
        ("LOCK", "REJECTED_NOT_HOLDER", "fd@room", "s:4"),
        ("HANDOVER", "ACCEPTED", "pat@pad", "s:5"),
        ("NOOP", "ACCEPTED", "fd@room", "s:6"),
        ("ARM", "ACCEPTED", "fd@room", "s:7"),
        ("APPROVE", "ACCEPTED", "rso@lounge", "s:8"),
        ("LAUNCH", "ACCEPTED", "fd@room", "s:9"),
    ]
    assert [o.seq for o in r.ground.outcomes][-3:] == [5, 6, 7]
    assert r.control.dv.get_name("cn_lock_holder") == "fd"
    assert res.states[:2] == ["SAFE", "ARMED"]
    assert res.errors == 0


def test_a_line_naming_nobody_goes_as_the_grounds_own_operator() -> None:
    from tests.unit.test_stations_lockstep import sim_keys, sim_signer

    m = flight_with_ground()
    keys = sim_keys(m)
    assert keys is not None
    text = "at 0.5 lock\nas fd@room: at 0.6 noop\n"
    r = LockstepRunner(
        m, commands=parse_commands(text, "s"), signer=sim_signer(keys, m, "pat", "pad")
    )
    r.run(1.0)
    out = [(o.command, o.status, o.operator) for o in r.ground.outcomes]
    assert out == [("LOCK", "ACCEPTED", "pat@pad"), ("NOOP", "REJECTED_NOT_HOLDER", "fd@room")]


@pytest.mark.parametrize(
    ("line", "said"),
    [
        (
            "as eve@pad: at 1 lock",
            "s:2: as eve@pad: mission lists no operator 'eve' (ground.operators); operators: "
            "pat, fd, rso, vic",
        ),
        (
            "as fd@rooom: at 1 lock",
            "s:2: as fd@rooom: mission lists no station 'rooom' (ground.stations); did you "
            "mean room?",
        ),
    ],
)
def test_an_unknown_operator_or_station_is_an_error_naming_the_line(line: str, said: str) -> None:
    m = flight_with_ground()
    script = parse_commands("at 0 noop\n" + line + "\n", "s")
    with pytest.raises(CommandError) as e:
        ScriptPlayer(m, script, lambda op, st: pytest.fail("no signer for unknown names"))
    assert str(e.value) == said
    with pytest.raises(CommandError, match=r"^s:2: as "):
        LockstepRunner(m, commands=script)


def test_a_line_naming_an_operator_in_a_mission_without_ground_is_refused() -> None:
    from tests.unit.test_stations_lockstep import FLIGHT
    from zplatform import decode_mission

    m = decode_mission(FLIGHT.read_text(), source=str(FLIGHT), base_dir=FLIGHT.parent)
    with pytest.raises(CommandError, match=r"^s:1: as pat@pad: mission 'flight' has no `ground:`"):
        ScriptPlayer(m, [ScriptCommand(0, "NOOP", source="s:1", operator="pat", station="pad")])


def test_a_line_is_signed_with_the_key_files_cmd_operator_reads(
    tmp_path: Path,
    keydir: Path,
) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    m = load_mission(path)
    script = parse_commands("as alice@pad: at 1 noop\nas bob@pad: at 2 noop\n", "s")
    key_file = keydir / "gn.keys"
    player = ScriptPlayer(m, script, lambda op, st: line_signer(m, op, st, key_file))
    assert player.pending == ["s:1", "s:2"]
    (keydir / "operator-bob.keys").unlink()
    with pytest.raises(CommandError) as e:
        ScriptPlayer(m, script, lambda op, st: line_signer(m, op, st, key_file))
    assert str(e.value).startswith(f"s:2: as bob@pad: no key file {keydir / 'operator-bob.keys'}")
    with pytest.raises(
        CommandError, match=r"^s:1: as alice@pad: this ground has no operators. keys"
    ):
        ScriptPlayer(m, script)


def test_sim_plays_a_script_whose_every_line_names_its_sender_without_operator_flags(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from zplatform.cli.main import main

    path = tmp_path / "idtest.yaml"
    path.write_text(MISSION)
    script = tmp_path / "s.commands"
    script.write_text("as alice@pad\nat 0.1 lock\nat 0.2 handover bob\nas bob@pad: at 0.3 noop\n")
    args = ["sim", str(path), "--commands", str(script), "--duration", "1"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "LOCK #1 by alice@pad: ACCEPTED" in out, out
    assert "HANDOVER #2 by alice@pad: ACCEPTED" in out, out
    assert "NOOP #3 by bob@pad: ACCEPTED" in out, out
    # A line naming nobody still needs --operator/--station.
    script.write_text("as alice@pad: at 0.1 lock\nat 0.2 noop\n")
    assert main(args) == 2
    assert "--operator NAME --station NAME" in capsys.readouterr().err
