"""System tests of the shipped missions, run in lockstep (the thesis, ch. 5.1.3).

Every check reads the telemetry CSV the way the thesis' operators read the
ground node's log: the LED states come from the *feedback* elements (the pin
read back through the board), not from the commands.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.drive import igniter_bench_copy
from zplatform import load_mission
from zplatform.config import Mission
from zplatform.control.uplink import ScriptCommand, load_commands, parse_commands
from zplatform.errors import CommandError
from zplatform.sim.lockstep import DEFAULT_START_NS, LockstepRunner, SimResult
from zplatform.telemetry.logs import CsvLogger, read_csv

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
LED_YAML = CONFIGS / "led_test.yaml"
LED_CMDS = CONFIGS / "led_test.commands"
IGN_YAML = CONFIGS / "recovery_igniter.yaml"
IGN_CMDS = CONFIGS / "recovery_igniter.commands"
IGN_DISARM = CONFIGS / "recovery_igniter_disarm.commands"
LOOP_S = 0.01

Row = dict[str, str]


def run(
    mission: Mission | Path,
    commands: list[ScriptCommand] | Path | None,
    duration_s: float,
    log: Path,
) -> tuple[SimResult, list[Row]]:
    m = load_mission(mission) if isinstance(mission, Path) else mission
    script = load_commands(commands) if isinstance(commands, Path) else commands
    runner = LockstepRunner(m, commands=script)
    with CsvLogger(log, runner.control.layout) as logger:
        res = runner.run(duration_s, log=logger)
    return res, read_csv(log)


def t_s(row: Row) -> float:
    return (int(row["rx_time_ns"]) - DEFAULT_START_NS) / 1e9


def on(row: Row, name: str) -> bool:
    return row[name] == "1"


def visited(rows: list[Row]) -> list[str]:
    out: list[str] = []
    for r in rows:
        if not out or out[-1] != r["cn_state"]:
            out.append(r["cn_state"])
    return out


def entered(rows: list[Row], state: str) -> int:
    """Index of the first row in ``state``."""
    return next(i for i, r in enumerate(rows) if r["cn_state"] == state)


def settled(rows: list[Row], state: str, skip: int = 3) -> list[Row]:
    """Rows in ``state`` after the first ``skip`` loops of it (a command takes
    two loops to come back as feedback: CN -> DN, DN -> CN)."""
    i = entered(rows, state)
    j = i
    while j < len(rows) and rows[j]["cn_state"] == state:
        j += 1
    return rows[i + skip : j]


def edges(rows: list[Row], name: str, rising: bool = True) -> list[float]:
    out = []
    for a, b in itertools.pairwise(rows):
        if on(a, name) != on(b, name) and on(b, name) is rising:
            out.append(t_s(b))
    return out


def assert_clean(res: SimResult, rows: list[Row], mission: Mission) -> None:
    """No errors, misses, late replies or overruns, in the result and in the log."""
    assert res.errors == 0, res.errors_by_node
    assert res.fault == "NONE"
    last = rows[-1]
    assert last["cn_errors"] == "0" and last["cn_fault"] == "NONE"
    for dn in mission.device_nodes:
        assert last[f"{dn}_errors"] == "0"
        assert last[f"cn_missed_{dn}"] == "0" and last[f"cn_late_{dn}"] == "0"
        assert int(last[f"cn_rx_{dn}"]) == len(rows)  # one reply per loop, none lost
        assert res.missed[dn] == 0 and res.late[dn] == 0
    assert last["cn_loop_overruns"] == "0" and last["cn_sync_overruns"] == "0"
    assert all(c.status == "ACCEPTED" for c in res.commands), res.commands
    assert not res.pending_commands


# ---------------------------------------------------------------------------
# LED platform test (5.1.3.1)

STATE_LEDS = {s: f"led_{s.lower()}_fb" for s in "ABCDE"}
SEQ = [f"led_seq{i}_fb" for i in range(5)]
FLASH = "led_flash_fb"


@pytest.fixture(scope="module")
def led(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimResult, list[Row], Mission]:
    log = tmp_path_factory.mktemp("led") / "led.csv"
    m = load_mission(LED_YAML)
    res, rows = run(m, LED_CMDS, 18.0, log)
    return res, rows, m


def test_led_walks_a_to_e_and_ends_in_e(led: tuple[SimResult, list[Row], Mission]) -> None:
    res, rows, m = led
    assert visited(rows) == ["A", "B", "C", "D", "E"]
    assert res.states == ["A", "B", "C", "D", "E"]
    assert res.final_state == "E" and rows[-1]["cn_state"] == "E"
    assert res.loops == len(rows) == 1800
    assert_clean(res, rows, m)
    changes = [e.text for e in res.events if e.id == "state_change"]
    assert len(changes) == 4


def test_led_state_leds_follow_the_state(led: tuple[SimResult, list[Row], Mission]) -> None:
    _, rows, _ = led
    for state, fb in STATE_LEDS.items():
        rs = settled(rows, state)
        assert rs, state
        for r in rs:
            lit = [name for name in STATE_LEDS.values() if on(r, name)]
            assert lit == [fb], (state, t_s(r), lit)


def test_led_transition_times(led: tuple[SimResult, list[Row], Mission]) -> None:
    _, rows, _ = led
    t = {s: t_s(rows[entered(rows, s)]) for s in "ABCDE"}
    assert t["A"] == 0.0
    assert t["B"] == pytest.approx(1.0)  # LAUNCH at 1.0 s
    assert 3.0 <= t["C"] - t["B"] <= 3.0 + 2 * LOOP_S  # 3 s flag, then the transition
    assert 4.0 <= t["D"] - t["C"] <= 4.0 + 4 * LOOP_S  # LED4 lit at 4 s, fed back
    assert t["E"] == pytest.approx(14.0)  # ABORT at 14.0 s


def test_led_sequence_lights_one_per_second_in_c(
    led: tuple[SimResult, list[Row], Mission],
) -> None:
    _, rows, _ = led
    t_c = t_s(rows[entered(rows, "C")])
    for r in rows[: entered(rows, "C")]:
        assert not any(on(r, n) for n in SEQ)
    for i, name in enumerate(SEQ):
        ups = edges(rows, name)
        assert len(ups) == 1, name  # comes on once, stays on until E
        assert ups[0] - t_c == pytest.approx(i * 1.0 + 2 * LOOP_S, abs=LOOP_S / 2)
    # cumulative: in C and D an LED is on only if every lower one is
    for r in rows[entered(rows, "C") : entered(rows, "E")]:
        bits = [on(r, n) for n in SEQ]
        assert bits == sorted(bits, reverse=True)


def test_led_flash_toggles_at_1hz_in_d(led: tuple[SimResult, list[Row], Mission]) -> None:
    _, rows, _ = led
    i_d, i_e = entered(rows, "D"), entered(rows, "E")
    assert not any(on(r, FLASH) for r in rows[:i_d])
    d_rows = rows[i_d : i_e + 1]
    ups, downs = edges(d_rows, FLASH), edges(d_rows, FLASH, rising=False)
    assert len(ups) >= 5
    periods = [b - a for a, b in itertools.pairwise(ups)]
    assert all(p == pytest.approx(1.0, abs=LOOP_S / 2) for p in periods), periods
    highs = [d - u for u, d in zip(ups, downs, strict=False)]
    assert all(h == pytest.approx(0.5, abs=LOOP_S / 2) for h in highs), highs
    # the seq LEDs stay on in D; in E only the state LED logic is left
    assert all(all(on(r, n) for n in SEQ) for r in settled(rows, "D"))
    for r in settled(rows, "E"):
        assert not any(on(r, n) for n in [*SEQ, FLASH])


# ---------------------------------------------------------------------------
# Recovery igniter test (5.1.3.2)

IGN_DURATION = 16.0


def assert_outputs_need_verdicts(rows: list[Row]) -> None:
    """On each DN the output is never on without its own verdict (same snapshot),
    and the igniter counts as fired only once both feedbacks read on."""
    both_seen = False
    for r in rows:
        for dn in ("dn0", "dn1"):
            if on(r, f"{dn}_ign_out"):
                assert on(r, f"{dn}_ign_ok"), (dn, t_s(r))
        both_seen = both_seen or (on(r, "dn0_ign_fb") and on(r, "dn1_ign_fb"))
        if on(r, "igniter_fired"):
            assert both_seen, t_s(r)


def test_igniter_fires_when_both_device_nodes_agree(tmp_path: Path) -> None:
    m = load_mission(IGN_YAML)
    res, rows = run(m, IGN_CMDS, IGN_DURATION, tmp_path / "ign.csv")
    assert visited(rows) == ["SAFE", "ARMED", "FIRE", "DEPLOYED"]
    assert_clean(res, rows, m)
    assert_outputs_need_verdicts(rows)
    i_fire = entered(rows, "FIRE")
    fire = rows[i_fire]
    assert 11.0 < t_s(fire) < 12.5  # below 250 m on the drogue, after apogee
    assert float(fire["apogee_m"]) == pytest.approx(326.2, abs=0.5)
    assert float(fire["alt_est_m"]) < 250.0
    # nothing fired before the CN commanded it
    for r in rows[:i_fire]:
        assert not any(on(r, n) for n in ("dn0_ign_fb", "dn1_ign_fb", "igniter_fired"))
    fired = next(r for r in rows if on(r, "igniter_fired"))
    assert t_s(fired) - t_s(fire) <= 4 * LOOP_S
    # 1 s later the CN safes ignition and disarms: the outputs drop
    assert not on(rows[-1], "dn0_ign_fb") and not on(rows[-1], "dn1_ign_fb")
    assert on(rows[-1], "igniter_fired")  # latched record


def test_igniter_does_not_fire_when_dn1_is_disarmed(tmp_path: Path) -> None:
    m = load_mission(igniter_bench_copy(tmp_path))
    res, rows = run(m, IGN_DISARM, IGN_DURATION, tmp_path / "ign.csv")
    assert visited(rows) == ["SAFE", "ARMED", "FIRE", "NO_FIRE"]
    assert_clean(res, rows, m)
    assert_outputs_need_verdicts(rows)
    assert not any(on(r, "igniter_fired") for r in rows)
    after_fire = rows[entered(rows, "FIRE") :]
    assert not any(on(r, "dn1_ign_fb") or on(r, "dn1_ign_ok") for r in after_fire)
    # dn0 agreed and drove its output: the pair, not one DN, decides
    assert any(on(r, "dn0_ign_fb") for r in rows)


def test_igniter_does_not_fire_when_dn1_reads_a_bad_altitude(tmp_path: Path) -> None:
    m = load_mission(IGN_YAML)
    assert m.world is not None
    m.world.params["bias_m"] = {"dn1": 5000.0}  # dn1's barometer reads far too high
    res, rows = run(m, IGN_CMDS, IGN_DURATION, tmp_path / "ign.csv")
    assert visited(rows) == ["SAFE", "ARMED", "FIRE", "NO_FIRE"]
    assert_clean(res, rows, m)
    assert_outputs_need_verdicts(rows)
    assert not any(on(r, "igniter_fired") or on(r, "dn1_ign_fb") for r in rows)
    assert float(rows[entered(rows, "FIRE")]["dn1_alt_m"]) > 5000.0


def test_igniter_deploy_altitude_is_a_parameter_set_armed_on_the_pad(tmp_path: Path) -> None:
    """``deploy_altitude_m`` (a hazardous parameter) moved from 250 m to 300 m
    before launch: the CN fires higher, and earlier, on the same flight. An
    unarmed PRM_SET of it is refused; after launch it cannot change."""
    m = load_mission(IGN_YAML)
    script = parse_commands(
        "at 0.1 prm_set deploy_altitude_m 300\n"  # hazardous: refused without ARM
        "at 0.2 arm\nat 0.3 prm_set deploy_altitude_m 300\n"
        "at 0.5 arm\nat 0.6 launch\n"
        "at 3.0 arm\n"  # ARMED: the whitelist refuses ARM and PRM_SET in flight
        "at 3.1 prm_set deploy_altitude_m 200\n"
    )
    res, rows = run(m, script, IGN_DURATION, tmp_path / "ign.csv")
    assert [c.status for c in res.commands] == [
        "REJECTED_NOT_ARMED", "ACCEPTED", "ACCEPTED", "ACCEPTED", "ACCEPTED",
        "REJECTED_NOT_ALLOWED", "REJECTED_NOT_ALLOWED",
    ]  # fmt: skip
    assert visited(rows) == ["SAFE", "ARMED", "FIRE", "DEPLOYED"]
    fire = rows[entered(rows, "FIRE")]
    assert float(rows[-1]["deploy_altitude_m"]) == 300.0
    assert 250.0 < float(fire["alt_est_m"]) < 300.0
    assert t_s(fire) < 11.0  # the nominal flight passes 250 m after 11 s


def test_igniter_flight_starts_at_launch_not_at_node_start(tmp_path: Path) -> None:
    """The flight is the vehicle world's, started by dn0's launch output: a
    LAUNCH sent 20 s after start lifts off then, and the mission still ends
    DEPLOYED (it used to be at 325 m on the pad, and stay ARMED for good)."""
    m = load_mission(IGN_YAML)
    script = parse_commands("at 19.9 arm\nat 20 launch\n")
    res, rows = run(m, script, 36.0, tmp_path / "ign.csv")
    assert visited(rows) == ["SAFE", "ARMED", "FIRE", "DEPLOYED"]
    assert_clean(res, rows, m)
    i_armed = entered(rows, "ARMED")
    assert t_s(rows[i_armed]) == pytest.approx(20.0, abs=2 * LOOP_S)
    pad = rows[: i_armed + 2]  # the launch output needs a loop, the reading one more
    assert all(float(r["dn0_alt_m"]) == 0.0 and float(r["dn1_alt_m"]) == 0.0 for r in pad)
    assert float(rows[i_armed + 100]["dn0_alt_m"]) > 50.0  # climbing a second later
    fire = rows[entered(rows, "FIRE")]
    assert 30.5 < t_s(fire) < 31.5  # 250 m on the drogue, ~10.7 s after lift-off
    assert float(fire["apogee_m"]) == pytest.approx(326.2, abs=0.5)


def test_launch_without_arm_is_refused(tmp_path: Path) -> None:
    m = load_mission(IGN_YAML)
    res, rows = run(m, parse_commands("at 0.6 launch\n"), 3.0, tmp_path / "ign.csv")
    assert [c.status for c in res.commands] == ["REJECTED_NOT_ARMED"]
    assert visited(rows) == ["SAFE"]
    assert not any(on(r, "dn0_ign_armed") or on(r, "dn1_ign_armed") for r in rows)


def test_abort_in_flight_safes_everything(tmp_path: Path) -> None:
    m = load_mission(IGN_YAML)
    script = parse_commands("at 0.5 arm\nat 0.6 launch\nat 5 abort\n")
    _, rows = run(m, script, 16.0, tmp_path / "ign.csv")
    assert visited(rows) == ["SAFE", "ARMED", "ABORTED"]
    last = rows[-1]
    assert last["safety0_mode"] == "safed" and last["safety1_mode"] == "safed"
    assert not any(on(r, "igniter_fired") for r in rows)


# ---------------------------------------------------------------------------
# Determinism (docs/architecture.md#the-loop)


def test_led_csv_is_byte_identical_across_runs_and_processes(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    run(LED_YAML, LED_CMDS, 16.0, a)
    run(LED_YAML, LED_CMDS, 16.0, b)
    assert a.read_bytes() == b.read_bytes()
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    proc = subprocess.run(
        [sys.executable, "-m", "zplatform", "sim", str(LED_YAML), "--commands", str(LED_CMDS),
         "--duration", "16", "--log", str(c)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert c.read_bytes() == a.read_bytes()


def test_igniter_csv_is_byte_identical_across_runs(tmp_path: Path) -> None:
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    run(IGN_YAML, IGN_CMDS, 14.0, a)
    run(IGN_YAML, IGN_CMDS, 14.0, b)
    assert a.read_bytes() == b.read_bytes()


def test_runs_can_continue_where_they_stopped(tmp_path: Path) -> None:
    """Two runs of 8 s log the same bytes as one of 16 s."""
    m = load_mission(LED_YAML)
    one, two = tmp_path / "one.csv", tmp_path / "two.csv"
    run(m, LED_CMDS, 16.0, one)
    runner = LockstepRunner(load_mission(LED_YAML), commands=load_commands(LED_CMDS))
    with CsvLogger(two, runner.control.layout) as log:
        runner.run(8.0, log=log)
        res = runner.run(8.0, log=log)
    assert res.loops == 1600
    assert one.read_bytes() == two.read_bytes()


# ---------------------------------------------------------------------------
# Command scripts


def test_script_syntax(tmp_path: Path) -> None:
    p = tmp_path / "s.commands"
    p.write_text(
        "# a comment\n\nat 2.0 ABORT   # trailing comment\nat 0.1 launch\n"
        "at 1.5 write seq_leds_mode manual\nat 0.1 noop\n"
    )
    cmds = load_commands(p)
    assert [(c.at_ns, c.command) for c in cmds] == [
        (100_000_000, "LAUNCH"),
        (100_000_000, "NOOP"),
        (1_500_000_000, "WRITE"),
        (2_000_000_000, "ABORT"),
    ]
    assert cmds[2].element == "seq_leds_mode" and cmds[2].value == "manual"
    assert cmds[0].source == f"{p}:4"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("launch\n", r"s\.commands:1: expected 'at SECONDS COMMAND"),
        ("\nat soon launch\n", r"s\.commands:2: time 'soon' is not a number"),
        ("at -1 launch\n", r":1: time '-1' must be a finite number >= 0"),
        ("at nan launch\n", r":1: time 'nan' must be a finite"),
        ("at 1 lunch\n", r":1: unknown command 'lunch'"),
        ("at 1 launch now\n", r":1: launch takes no arguments"),
        ("at 1 write x\n", r":1: write takes ELEMENT VALUE"),
    ],
)
def test_script_errors_name_file_and_line(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "s.commands"
    p.write_text(text)
    with pytest.raises(CommandError, match=match):
        load_commands(p)


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("at 1 write nope 1", "x:1: no element named 'nope'"),
        ("at 1 write led_a_cmd 2", "x:1: 2 does not fit led_a_cmd"),
        ("at 1 write seq_leds_mode sideways", "x:1: 'sideways' is not a valid value"),
    ],
)
def test_write_is_checked_against_the_mission(line: str, match: str) -> None:
    m = load_mission(LED_YAML)
    with pytest.raises(CommandError, match=match):
        LockstepRunner(m, commands=parse_commands(line, "x"))


def test_commands_due_together_go_one_per_loop(tmp_path: Path) -> None:
    m = load_mission(LED_YAML)
    script = parse_commands("at 0.004 noop\nat 0 noop\nat 0 noop\n")
    res, _ = run(m, script, 0.1, tmp_path / "x.csv")
    # The ground answers telemetry, so nothing can reach loop 1: commands due
    # then go in loop 2, then one per loop (each after the last verdict).
    assert [(c.seq, c.loop, c.status) for c in res.commands] == [
        (1, 2, "ACCEPTED"),
        (2, 3, "ACCEPTED"),
        (3, 4, "ACCEPTED"),
    ]


def test_write_through_the_script_holds_in_manual_mode(tmp_path: Path) -> None:
    """Control logic off (thesis 6.2): an operator WRITE to an output sticks."""
    m = load_mission(LED_YAML)
    script = parse_commands(
        "at 0.5 arm\nat 0.5 write state_leds_mode manual\nat 0.6 write led_c_cmd true\n"
    )  # a controller's mode is protected: ARM, then WRITE
    res, rows = run(m, script, 1.0, tmp_path / "x.csv")
    assert all(c.status == "ACCEPTED" for c in res.commands)
    last = rows[-1]
    assert on(last, "led_a_fb") and on(last, "led_c_fb")  # A's LED left as it was, C written


# ---------------------------------------------------------------------------
# The command line (in a subprocess: a fresh interpreter per invocation)


def sim(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", "sim", *args],
        cwd=ROOT, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


def test_cli_sim_writes_log_and_summary(tmp_path: Path) -> None:
    log, summary = tmp_path / "led.csv", tmp_path / "led.json"
    p = sim(str(LED_YAML), "--commands", str(LED_CMDS), "--duration", "15",
            "--log", str(log), "--summary", str(summary))  # fmt: skip
    assert p.returncode == 0, p.stdout + p.stderr
    assert "states: A -> B -> C -> D -> E; final state E" in p.stdout
    s = json.loads(summary.read_text())
    for key in ("loops", "duration_s", "rate_hz", "loop_overruns", "sync_overruns", "missed",
                "late", "telemetry_received", "errors", "final_state"):  # fmt: skip
        assert key in s
    assert s["loops"] == 1500 and s["final_state"] == "E" and s["errors"] == 0
    assert s["missed"] == {"dn0": 0, "dn1": 0, "dn2": 0}
    assert len(read_csv(log)) == 1500


def test_cli_sim_exit_codes(tmp_path: Path) -> None:
    bad = tmp_path / "bad.commands"
    bad.write_text("at 1 fly\n")
    p = sim(str(LED_YAML), "--commands", str(bad), "--log", str(tmp_path / "x.csv"))
    assert p.returncode == 2
    assert f"{bad}:1: unknown command 'fly'" in p.stderr
    rejected = tmp_path / "rej.commands"
    rejected.write_text("at 0.1 abort\nat 0.2 launch\n")  # E refuses LAUNCH
    p = sim(str(LED_YAML), "--commands", str(rejected), "--duration", "1",
            "--log", str(tmp_path / "y.csv"))  # fmt: skip
    assert p.returncode == 1
    assert "REJECTED_NOT_ALLOWED" in p.stdout


def test_default_duration_follows_the_script(tmp_path: Path) -> None:
    log = tmp_path / "led.csv"
    assert sim(str(LED_YAML), "--commands", str(LED_CMDS), "--log", str(log)).returncode == 0
    assert len(read_csv(log)) == 2900  # last command at 14 s, plus 15 s (ground.script.SETTLE_S)
