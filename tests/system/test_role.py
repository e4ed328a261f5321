"""The control role in lockstep (zplatform/control/role.py): restarts in flight and every failover
case.

What was testable only live (a control node restarted mid-flight resuming
from its flight recorder, or starting over) runs here in virtual time:
:meth:`LockstepRunner.restart` starts a control node again as a new
process would, and its :class:`~zplatform.control.role.ControlRole` is fed what it
would be fed live (the device nodes' STATUS answers, the warm-up's loops,
what its recorder holds). The failover cases check the role's actions
themselves (a recording wrapper around :meth:`ControlRole.round_over`),
and a property flies random fault sequences against the two invariants:
never two commanders in one term, never a term asked while the
commander's mirrors are fresh.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zplatform import load_mission
from zplatform.control.fencing import ASK, STATUS
from zplatform.control.role import ControlRole, Probe, Release, Take
from zplatform.control.uplink import load_commands
from zplatform.errors import NodeError
from zplatform.sim.lockstep import DEFAULT_START_NS, LockstepRunner

ROOT = Path(__file__).resolve().parents[2]
IGNITER = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
IGNITER_CMDS = load_commands(ROOT / "configs" / "recovery_igniter.commands")
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
FLIGHT_CMDS = load_commands(ROOT / "configs" / "flight.commands")
TAKEOVER = FLIGHT.takeover.takeover_loops
NOMINAL = ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED"]


def _run(
    r: LockstepRunner, faults: dict[int, list[tuple[str, tuple[Any, ...]]]], loops: int
) -> list[Any]:
    """Run ``loops`` loops (stopping at LANDED), calling ``faults[loop]``
    before that loop; returns what each fault call returned."""
    out = []
    for _ in range(loops):
        for method, args in faults.get(r.loop + 1, ()):
            out.append(getattr(r, method)(*args))
        r.step()
        if r.control.statemachine.state == "LANDED":
            break
    return out


def _texts(r: LockstepRunner, event: str) -> list[str]:
    return [f"{e.node}: {e.text}" for e in r.result().events if e.id == event]


def _two_term_loops(r: LockstepRunner) -> list[int]:
    return [n for n, by in r.driven.items() if len(set(by.values())) > 1]


@pytest.fixture
def rounds(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[tuple[str, int, Any]]]:
    """Every round's outcome of every role: ``(node, slot, action)``."""
    seen: list[tuple[str, int, Any]] = []
    original = ControlRole.round_over

    def recorded(self: ControlRole, slot: int, now_ns: int) -> Any:
        action = original(self, slot, now_ns)
        seen.append((self.name, slot, action))
        return action

    monkeypatch.setattr(ControlRole, "round_over", recorded)
    yield seen


# -- restarts in flight (a mission without a standby) ---------------------------------


def test_a_control_node_restarted_in_flight_resumes_from_its_recorder() -> None:
    """recovery_igniter: the control node dies ARMED at loop 150 and starts
    again 100 loops later. The device nodes are mid-run and its recorder
    holds loop 150's frame: it resumes the run (the same epoch, ARMED), its
    loop numbers going on by time (the 100 loops no one ran are its
    overruns), and the flight deploys as planned."""
    r = LockstepRunner(IGNITER, commands=IGNITER_CMDS)
    assert _run(r, {151: [("kill", ("cn",))], 251: [("restart", ("cn",))]}, 2500) == [
        None,
        "resume",
    ]
    res = r.result()
    assert res.states == ["SAFE", "ARMED", "FIRE", "DEPLOYED"], res.states
    assert int(r.control.dv.get("cn_epoch")) == DEFAULT_START_NS
    assert int(r.control.dv.get("cn_loop_overruns")) == 100
    assert res.fault == "NONE"
    resumed = _texts(r, "cn_resumed")
    assert len(resumed) == 1 and "at loop 150 in state ARMED" in resumed[0], resumed
    assert _texts(r, "cn_restarted_in_flight") == []


@pytest.mark.parametrize(
    ("record", "why"),
    [
        (False, "the mission has no flight recorder for it"),
        (None, "its flight recorder holds no frame"),
        ("late", "is not of the device nodes' run (loop 150)"),
    ],
    ids=["no-recorder", "empty-recorder", "another-run"],
)
def test_a_control_node_restarted_without_a_usable_record_starts_over(
    record: object, why: str
) -> None:
    """The same restart, but the recorder is missing, empty, or holds a frame
    that is not of the device nodes' run (a later loop than they ran): the
    control node starts over, a new run in SAFE, and says why
    (``cn_restarted_in_flight``)."""
    if record == "late":
        other = LockstepRunner(IGNITER, commands=IGNITER_CMDS)
        _run(other, {}, 400)
        record = other.cns["cn"].recorded
        assert record is not None
    r = LockstepRunner(IGNITER, commands=IGNITER_CMDS)
    _run(r, {151: [("kill", ("cn",))]}, 250)
    assert r.restart("cn", record=record) == "start_over"  # type: ignore[arg-type]
    _run(r, {}, 100)
    res = r.result()
    assert res.states == ["SAFE", "ARMED", "SAFE"], res.states
    assert int(r.control.dv.get("cn_epoch")) == DEFAULT_START_NS + 250 * IGNITER.period_ns
    over = _texts(r, "cn_restarted_in_flight")
    assert len(over) == 1 and why in over[0], over
    assert _texts(r, "cn_resumed") == []


# -- restarts in a redundant mission ---------------------------------------------------


def test_a_restarted_commander_rejoins_as_the_standby_of_the_new_term(
    rounds: list[tuple[str, int, Any]],
) -> None:
    """flight: cn dies in coast, cn_b takes command (term 2); cn started
    again 300 loops later finds the device nodes driven (its STATUS round)
    and follows cn_b. The flight lands; no loop is driven by two terms."""
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    assert _run(r, {1000: [("kill", ("cn",))], 1300: [("restart", ("cn",))]}, 5000) == [
        None,
        "follow",
    ]
    assert r.result().states == NOMINAL
    assert r.commanders == [(1, "cn", 1), (1000 + TAKEOVER, "cn_b", 2)]
    assert [(n, s, a) for n, s, a in rounds if isinstance(a, Take)] == [
        ("cn_b", 1000 + TAKEOVER - 1, Take(1000 + TAKEOVER))
    ]
    sb = r.cns["cn"].standby
    assert sb is not None and sb.following and sb.term == 2
    assert _texts(r, "cn_following")[-1].startswith("cn: cn follows cn_b (term 2)")
    assert _two_term_loops(r) == []


def test_both_control_nodes_lost_the_first_back_resumes_in_the_next_term() -> None:
    """flight: both control nodes die in coast; cn comes back 100 loops later.
    No one has driven the device nodes for longer than the lease: it resumes
    the run from its recorder in term 2, and the flight lands."""
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    faults = {1000: [("kill", ("cn",)), ("kill", ("cn_b",))], 1100: [("restart", ("cn",))]}
    assert _run(r, faults, 5000) == [None, None, "resume"]
    assert r.result().states == NOMINAL
    assert r.commanders == [(1, "cn", 1), (1100, "cn", 2)]
    assert len(_texts(r, "cn_resumed")) == 1
    assert {t for by in r.driven.values() for t in by.values()} == {1, 2}
    assert _two_term_loops(r) == []


def test_a_control_node_no_device_node_answers_cannot_start() -> None:
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    _run(r, {500: [("kill", ("cn",)), ("kill", ("dn0",)), ("kill", ("dn1",))]}, 600)
    with pytest.raises(NodeError, match="no device node answers its probe"):
        r.restart("cn")


# -- the failover cases, by the role's actions ----------------------------------------


def test_a_standby_stands_down_on_a_newer_mirror() -> None:
    """cn stopped for 30 loops: cn_b takes command in term 2; cn, woken, hears
    term 2's mirror before it sends anything and stands down, following cn_b."""
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    _run(r, {1200: [("stop", ("cn", 30))]}, 5000)
    assert r.result().states == NOMINAL
    down = _texts(r, "cn_stood_down")
    assert len(down) == 1 and "a mirror of term 2 came from cn_b" in down[0], down
    cn = r.cns["cn"]
    assert cn.standby is not None and cn.standby.following and cn.standby.term == 2
    assert not cn.role.commanding and r.cns["cn_b"].role.commanding
    assert _two_term_loops(r) == []


def test_a_commander_the_device_nodes_left_stands_down_by_their_replies() -> None:
    """cn cut off from cn_b and both device nodes for 2 s: cn_b takes over;
    when the cut heals cn's triggers come back fenced by term 2 and its
    mirror reaches it: it stands down once."""
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    cut = [("partition", ("cn", n, 200)) for n in ("cn_b", "dn0", "dn1", "gn")]
    _run(r, {1200: cut}, 5000)
    assert r.result().states == NOMINAL
    assert [(n, t) for _, n, t in r.commanders] == [("cn", 1), ("cn_b", 2)]
    assert len(_texts(r, "cn_stood_down")) == 1
    assert r.cns["cn"].standby is not None


def test_a_standby_cut_off_from_a_working_commander_asks_nothing_and_never_takes(
    rounds: list[tuple[str, int, Any]],
) -> None:
    """The control nodes' link cut for 5 s: the standby's STATUS round shows
    the commander still driving the device nodes, so it asks for no term
    (no Probe(ASK), no Release, no Take), and nothing changes."""
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    _run(r, {1200: [("partition", ("cn", "cn_b", 500))]}, 5000)
    assert r.commanders == [(1, "cn", 1)]
    assert rounds and all(n == "cn_b" and a is None for n, _, a in rounds), rounds


def test_a_standby_without_a_majority_of_grants_releases_them(
    rounds: list[tuple[str, int, Any]],
) -> None:
    """The commander dies; both device nodes answer the standby's STATUS
    (the commander silent to both), but dn1's answers to the ASK are lost:
    one grant of two is no majority. The standby releases the promise (to
    every device node asked), holds, and asks again; it never takes, and
    dn0 follows no new term."""
    r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
    dn1 = r.devices[1]
    answer = dn1.probe

    def status_only(payload: bytes, now_ns: int) -> bytes | None:
        return answer(payload, now_ns) if payload[3] == STATUS else None

    dn1.probe = status_only  # type: ignore[method-assign]
    _run(r, {1000: [("kill", ("cn",))]}, 1000 + 4 * TAKEOVER)
    outcomes = [(type(a).__name__, getattr(a, "kind", None)) for _, _, a in rounds]
    assert outcomes[:2] == [("Probe", ASK), ("Release", None)], outcomes
    assert ("Take", None) not in outcomes
    releases = [a for _, _, a in rounds if isinstance(a, Release)]
    assert all(None not in a.releases for a in releases)
    assert r.commanders == [(1, "cn", 1)]
    assert r.devices[0].guard is not None and r.devices[0].guard.term == 1
    # Held for want of a majority, then blind: its mirror grew too old.
    held = _texts(r, "cn_takeover_held")
    assert len(held) == 2, held
    assert "a takeover needs more than half" in held[0]
    assert "would turn the vehicle's state back" in held[1]


# -- the invariants over random faults ------------------------------------------------

_FAULT = st.one_of(
    st.tuples(st.just("kill"), st.sampled_from(["cn", "cn_b"])),
    st.tuples(st.just("stop"), st.sampled_from(["cn", "cn_b"]), st.integers(1, 60)),
    st.tuples(
        st.just("partition"),
        st.sampled_from([("cn", "cn_b"), ("cn", "dn0"), ("cn", "dn1"), ("cn_b", "dn0")]),
        st.integers(1, 150),
    ),
    st.tuples(st.just("restart"), st.sampled_from(["cn", "cn_b"])),
)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(50, 700), _FAULT), max_size=4))
def test_never_two_commanders_in_one_term_never_a_term_asked_while_mirrors_are_fresh(
    faults: list[tuple[int, tuple[Any, ...]]],
) -> None:
    """Random kills, stops, partitions and restarts of either control node in
    the first 8 s: at no loop do two control nodes command in one term, no
    loop is driven by two terms, and no standby asks for a term while its
    commander's mirrors are fresh (fewer than ``takeover_loops`` missing,
    and showing the commander with most device nodes' replies)."""
    asked_fresh: list[tuple[str, int]] = []
    original = ControlRole.round_over

    def checked(self: ControlRole, slot: int, now_ns: int) -> Any:
        action = original(self, slot, now_ns)
        sb = self.standby
        asking = isinstance(action, Probe) and action.kind == ASK and sb is not None
        if asking and sb.missing(slot) < TAKEOVER and sb.cut < TAKEOVER:
            asked_fresh.append((self.name, slot))
        return action

    by_loop: dict[int, list[tuple[str, tuple[Any, ...]]]] = {}
    for at, f in faults:
        method, *args = f
        if method == "partition":
            args = [*args[0], args[1]]
        by_loop.setdefault(at, []).append((method, tuple(args)))
    ControlRole.round_over = checked  # type: ignore[method-assign]
    try:
        r = LockstepRunner(FLIGHT, commands=FLIGHT_CMDS)
        for _ in range(900):
            for method, args in by_loop.get(r.loop + 1, ()):
                getattr(r, method)(*args)
            r.step()
            terms = [
                c.logic.term
                for c in r.cns.values()
                if c.role.commanding and not c.dead and c.logic.term
            ]
            assert len(terms) == len(set(terms)), (r.loop, terms)
    finally:
        ControlRole.round_over = original  # type: ignore[method-assign]
    assert asked_fresh == []
    assert _two_term_loops(r) == []
