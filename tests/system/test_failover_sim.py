"""The standby control node in lockstep (issue 21): kills, stops and partitions at any loop.

The flight mission (``configs/flight.yaml``) has a standby, ``cn_b``. Each
case flies it in the lockstep runner with a fault on a control node and
holds the outcome against the same flight without the fault: the same
states in the same order, both chutes out within one takeover of the
no-failure time, no device node ever safed, and no loop driven by two
terms (:attr:`LockstepRunner.driven`, each device node's term per loop).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zplatform import load_mission
from zplatform.config import Mission
from zplatform.control.uplink import load_commands, parse_commands
from zplatform.errors import ConfigError
from zplatform.mission.load import decode_mission
from zplatform.sim.lockstep import LockstepRunner, SimResult

ROOT = Path(__file__).resolve().parents[2]
FLIGHT_YAML = ROOT / "configs" / "flight.yaml"
FLIGHT_CMDS = ROOT / "configs" / "flight.commands"
FLIGHT = load_mission(FLIGHT_YAML)
PERIOD_S = FLIGHT.period_ns / 1e9
TAKEOVER = FLIGHT.takeover.takeover_loops
LANDED_BY = 5000  # loops: the shipped flight lands at about 47 s


@dataclass
class Flown:
    result: SimResult
    runner: LockstepRunner
    drogue_at: float | None
    main_at: float | None

    @property
    def states(self) -> list[str]:
        return self.result.states

    def ids(self, *ids: str) -> list[str]:
        return [f"{e.node} {e.id}: {e.text}" for e in self.result.events if e.id in ids]

    def two_term_loops(self) -> list[int]:
        """Loops that device nodes ran under more than one term."""
        return [n for n, by in self.runner.driven.items() if len(set(by.values())) > 1]


def fly(
    mission: Mission = FLIGHT,
    script: str | None = None,
    faults: dict[int, list[tuple[str, tuple[object, ...]]]] | None = None,
    loops: int = LANDED_BY,
) -> Flown:
    """Fly until LANDED (or ``loops``), calling the runner's fault methods
    ``faults[loop]`` = ``[(method, args), ...]`` before that loop runs."""
    cmds = load_commands(FLIGHT_CMDS) if script is None else parse_commands(script)
    r = LockstepRunner(mission, commands=cmds)
    faults = faults or {}
    for _ in range(loops):
        for method, args in faults.get(r.loop + 1, ()):
            getattr(r, method)(*args)
        r.step()
        if r.control.statemachine.state == "LANDED":
            break
    assert r.world is not None
    truth = r.world.truth
    return Flown(r.result(), r, truth.drogue_at, truth.main_at)


@pytest.fixture(scope="module")
def nominal() -> Flown:
    fl = fly()
    assert fl.states == ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED"]
    assert fl.runner.commanders == [(1, "cn", 1)]
    return fl


def _as_if_nothing_happened(fl: Flown, nominal: Flown) -> None:
    assert fl.states == nominal.states
    assert fl.result.final_state == "LANDED"
    assert fl.drogue_at is not None and fl.main_at is not None
    assert nominal.drogue_at is not None and nominal.main_at is not None
    # Within one takeover of the no-failure time.
    window = (TAKEOVER + 1) * PERIOD_S
    assert abs(fl.drogue_at - nominal.drogue_at) <= window, (fl.drogue_at, nominal.drogue_at)
    assert abs(fl.main_at - nominal.main_at) <= window, (fl.main_at, nominal.main_at)
    assert fl.ids("dn_safed") == []
    assert not any(d.safed for d in fl.runner.devices)
    assert fl.two_term_loops() == []
    assert fl.result.fault == "NONE" and fl.result.errors == 0


# -- kill ---------------------------------------------------------------------


@settings(
    max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(kill_at=st.integers(1, 4600))
def test_the_primary_killed_at_any_loop_changes_nothing(kill_at: int, nominal: Flown) -> None:
    """Killed after any loop of the flight: the standby takes over within
    ``takeover_loops + 1`` loops and the flight ends as if nothing happened."""
    fl = fly(faults={kill_at + 1: [("kill", ("cn",))]})
    _as_if_nothing_happened(fl, nominal)
    assert fl.runner.commanders == [(1, "cn", 1), (kill_at + TAKEOVER + 1, "cn_b", 2)]
    took = fl.ids("cn_took_command")
    assert len(took) == 1 and f"silent since loop {kill_at}" in took[0], took


@pytest.mark.slow
@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kill_at=st.integers(1, 4600))
def test_the_primary_killed_at_any_loop_changes_nothing_soak(kill_at: int, nominal: Flown) -> None:
    test_the_primary_killed_at_any_loop_changes_nothing.hypothesis.inner_test(  # type: ignore[attr-defined]
        kill_at, nominal
    )


# -- stop (SIGSTOP) -------------------------------------------------------------


@pytest.mark.parametrize(
    ("at", "loops"),
    [(150, 2), (150, 30), (1250, 6), (2000, 400)],
    ids=["pad-short", "pad-long", "coast-mid", "drogue-long"],
)
def test_a_stopped_primary_stands_down_when_it_wakes(at: int, loops: int, nominal: Flown) -> None:
    """Stopped for fewer loops than a takeover needs, the primary keeps
    command; stopped longer, the standby takes over, and the primary, woken
    with its old state, stands down at once: its triggers are fenced and the
    new commander's mirror tells it the term."""
    fl = fly(faults={at: [("stop", ("cn", loops))]})
    _as_if_nothing_happened(fl, nominal)
    if loops < TAKEOVER:
        assert fl.runner.commanders == [(1, "cn", 1)]
        return
    assert fl.runner.commanders == [(1, "cn", 1), (at + TAKEOVER, "cn_b", 2)]
    down = fl.ids("cn_stood_down")
    assert len(down) == 1 and "term 2 commands" in down[0], down
    cn = fl.runner.cns["cn"]
    assert cn.standby is not None and cn.standby.term == 2  # it follows cn_b now


# -- partitions -------------------------------------------------------------------


def test_a_primary_cut_off_from_the_standby_keeps_command(nominal: Flown) -> None:
    """The two control nodes cannot hear each other for 5 s in flight, both
    still reach the device nodes: the standby asks, the device nodes still
    run the primary's triggers and refuse it, and nothing changes."""
    fl = fly(faults={1200: [("partition", ("cn", "cn_b", 500))]})
    _as_if_nothing_happened(fl, nominal)
    assert fl.runner.commanders == [(1, "cn", 1)]
    held = fl.ids("cn_takeover_held")
    # Refused while the device nodes still ran the primary's triggers, then
    # blind: its last mirror too old to take command from.
    assert len(held) == 2, held
    assert "the commander still drives dn0" in held[0]
    assert f"is {2 * TAKEOVER + FLIGHT.takeover.lease_loops + 1} loops old" in held[1]
    # Promised nothing that lasted: the device nodes never left term 1.
    assert {t for by in fl.runner.driven.values() for t in by.values()} == {1}


def test_a_standby_cut_off_from_the_primary_never_takes_command_from_an_old_mirror() -> None:
    """The control nodes' link is cut in coast; 2 s later the primary dies.
    The standby's last mirror is 200 loops old: taking command from it would
    turn the flight back to where it was then, so it does not (the device
    nodes keep their loss-of-commander outputs: dn_watchdog, not modelled in
    lockstep). Nothing ever drives a device node again, and no term but the
    first ever ran."""
    fl = fly(
        faults={1200: [("partition", ("cn", "cn_b", 500))], 1400: [("kill", ("cn",))]},
        loops=2000,
    )
    assert fl.runner.commanders == [(1, "cn", 1)]
    assert fl.ids("cn_took_command") == []
    assert max(fl.runner.driven) == 1399
    assert {t for by in fl.runner.driven.values() for t in by.values()} == {1}
    held = fl.ids("cn_takeover_held")
    assert len(held) == 2 and "would turn the vehicle's state back" in held[1], held
    sb = fl.runner.cns["cn_b"].standby
    assert sb is not None and sb.mirrored == 1199 and sb.blind(2000)


def test_a_standby_follows_again_when_the_cut_heals_and_takes_over_from_a_fresh_mirror(
    nominal: Flown,
) -> None:
    """Blind for 5 s (the control nodes' link cut), the standby follows again
    from the first mirror after the cut heals; the primary dying later is
    taken over as if the cut had never been."""
    fl = fly(faults={1200: [("partition", ("cn", "cn_b", 500))], 1800: [("kill", ("cn",))]})
    _as_if_nothing_happened(fl, nominal)
    assert [(n, t) for _, n, t in fl.runner.commanders] == [("cn", 1), ("cn_b", 2)]
    took = fl.ids("cn_took_command")
    assert len(took) == 1 and "continuing from the mirror of loop 1799" in took[0], took


def test_a_primary_cut_off_from_the_device_nodes_is_replaced_and_stands_down(
    nominal: Flown,
) -> None:
    """The primary loses both device nodes in coast (it still hears the
    standby): its mirrors show it without replies, the standby asks, the
    device nodes have not heard it for the lease and grant; the primary hears
    the new term's mirror and stands down. When the cut heals nothing more
    changes."""
    fl = fly(faults={1200: [("partition", ("cn", "dn0", 300)), ("partition", ("cn", "dn1", 300))]})
    _as_if_nothing_happened(fl, nominal)
    assert [(n, t) for _, n, t in fl.runner.commanders] == [("cn", 1), ("cn_b", 2)]
    took = fl.ids("cn_took_command")
    assert len(took) == 1 and "cut off from the device nodes" in took[0], took
    assert len(fl.ids("cn_stood_down")) == 1


def test_a_primary_cut_off_from_everyone_stands_down_when_it_heals(nominal: Flown) -> None:
    """Cut off from the standby and the device nodes (its own host's link
    down) for 2 s: it flies on alone and drives nothing; the standby takes
    over; when the link comes back the primary's triggers are fenced and the
    new term's mirror reaches it: it stands down."""
    cut = [("partition", ("cn", n, 200)) for n in ("cn_b", "dn0", "dn1", "gn")]
    fl = fly(faults={1200: cut})
    _as_if_nothing_happened(fl, nominal)
    assert [(n, t) for _, n, t in fl.runner.commanders] == [("cn", 1), ("cn_b", 2)]
    down = fl.ids("cn_stood_down")
    assert len(down) == 1, down
    # It stood down only once the cut healed (its loop then is past the cut).
    loop = int(down[0].split("at loop ")[1].split(":")[0])
    assert loop >= 1200 + 200


def test_a_standby_cut_off_from_the_mirrors_never_takes_command_from_a_stale_one(
    nominal: Flown,
) -> None:
    """The control nodes cannot hear each other from loop 1000 for 5 s, both
    still reach the device nodes; at loop 1300 the commander stalls for 5
    loops (past the lease), so the device nodes grant the standby's next
    question. Its mirror is of loop 999, 3 s old: taking command from it
    would fly on from that state (today: the drogue 3 s late, the main never
    fired). The flight must end as if nothing happened."""
    fl = fly(faults={1000: [("partition", ("cn", "cn_b", 500))], 1300: [("stop", ("cn", 5))]})
    _as_if_nothing_happened(fl, nominal)


# -- the standby itself, and missions without one -----------------------------------


def test_a_standby_dying_changes_nothing(nominal: Flown) -> None:
    fl = fly(faults={800: [("kill", ("cn_b",))]})
    _as_if_nothing_happened(fl, nominal)
    assert fl.runner.commanders == [(1, "cn", 1)]
    assert fl.drogue_at == nominal.drogue_at and fl.main_at == nominal.main_at


def test_a_mission_without_a_standby_has_no_terms() -> None:
    m = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
    assert m.standby is None and m.control_nodes == ["cn"]
    r = LockstepRunner(m, commands=load_commands(ROOT / "configs" / "recovery_igniter.commands"))
    names = set(r.control.dv.layout.elements)
    assert not {"cn_term", "cn_commander", "dn0_term", "dn0_term_seen"} & names
    # cn_arm_seq stays: a restart in flight resumes an approved ARM from the
    # flight recorder, standby or not.
    assert "cn_arm_seq" in names
    r.run(3.0)
    assert r.commanders == [] and r.driven == {} and list(r.cns) == ["cn"]


# -- commands across a takeover ---------------------------------------------------------


def test_an_arm_survives_the_takeover_and_the_launch_goes_to_the_new_commander(
    nominal: Flown,
) -> None:
    """ARM accepted by cn, which dies before the LAUNCH: cn_b's mirror holds
    the ARM (cn_arm_seq), so the LAUNCH, armed, is accepted by cn_b, once."""
    script = "at 1.0 arm\nat 1.5 launch\nat 45 noop\n"
    fl = fly(script=script, faults={110: [("kill", ("cn",))]})
    assert [(c.command, c.status) for c in fl.result.commands] == [
        ("ARM", "ACCEPTED"), ("LAUNCH", "ACCEPTED"), ("NOOP", "ACCEPTED"),
    ]  # fmt: skip
    accepted = [e for e in fl.result.events if e.id == "cmd_accepted"]
    assert [(e.node, e.text.split()[1]) for e in accepted] == [
        ("cn", "ARM"), ("cn_b", "LAUNCH"), ("cn_b", "NOOP"),
    ]  # fmt: skip
    assert fl.result.final_state == "LANDED" and fl.two_term_loops() == []


def test_a_hold_survives_the_takeover(nominal: Flown) -> None:
    """HOLD in ARMED (its 2 s countdown frozen), cn killed during the hold,
    RESUME to cn_b: the countdown goes on from where it was held, and the
    flight flies, 2.5 s later than without the hold."""
    text = FLIGHT_YAML.read_text().replace(
        "ARMED: [NOOP, ABORT]", "ARMED: [NOOP, ABORT, HOLD, RESUME]"
    )
    assert "HOLD, RESUME" in text
    mission = decode_mission(text.encode(), base_dir=FLIGHT_YAML.parent)
    script = "at 1.0 arm\nat 1.1 launch\nat 1.5 hold\nat 4.0 resume\n"
    fl = fly(mission, script=script, faults={200: [("kill", ("cn",))]})
    assert [c.status for c in fl.result.commands] == ["ACCEPTED"] * 4
    assert fl.states == nominal.states
    boost = next(e for e in fl.result.events if "-> BOOST" in e.text)
    nominal_boost = next(e for e in nominal.result.events if "-> BOOST" in e.text)
    assert boost.node == "cn_b"
    assert boost.t_ns - nominal_boost.t_ns == pytest.approx(2.5e9, abs=0.02e9)


# -- controllers must keep their state in the vector --------------------------------------


def _redundant_with(controller_class: str) -> bytes:
    text = FLIGHT_YAML.read_text()
    return text.replace("class: nodes.flight:Airbrakes", f"class: {controller_class}").encode()


def test_a_redundant_mission_refuses_a_controller_that_keeps_state_outside_the_vector() -> None:
    with pytest.raises(ConfigError) as e:
        decode_mission(
            _redundant_with("nodes.recovery_igniter:ApogeeDetector"),
            base_dir=FLIGHT_YAML.parent,
        )
    assert e.value.path.startswith("$.controllers[") and e.value.path.endswith("].class")
    assert "takeover_safe" in e.value.reason


# -- a device node that comes back --------------------------------------------------------


@pytest.mark.parametrize("clears", [True, False])
def test_a_lost_device_nodes_fault_clears_when_it_rejoins_if_the_mission_says_so(
    clears: bool,
) -> None:
    """dn0 gone for 0.6 s on the pad: DN_LOST latches (after
    ``faults.dn_lost_loops``); once it answers again for
    ``faults.dn_reenable_loops`` loops, the fault clears with a
    ``dn_fault_cleared`` event when ``faults.dn_rejoin_clears`` says so, and
    stays latched (today's rule) when not."""
    text = (ROOT / "configs" / "recovery_igniter.yaml").read_text()
    text += f"\nfaults: {{dn_rejoin_clears: {str(clears).lower()}}}\n"
    m = decode_mission(text.encode(), base_dir=ROOT / "configs")
    r = LockstepRunner(m)
    r.run(0.5)
    r.lost.add("dn0")
    r.run(0.6)
    assert r.control.dv.get_name("cn_fault") == "DN_LOST"
    r.lost.discard("dn0")
    r.run(0.5)
    cleared = [e for e in r.result().events if e.id == "dn_fault_cleared"]
    if clears:
        assert r.control.dv.get_name("cn_fault") == "NONE"
        assert len(cleared) == 1 and "dn0" in cleared[0].text, cleared
    else:
        assert r.control.dv.get_name("cn_fault") == "DN_LOST" and not cleared
