"""An insider holding one role's keys cannot reach past that role (issue 25),
in process: the plan of tests/faults/insider.py (generated from the key-space
table and the links each role holds), fed to the intakes of
tests/faults/test_keyspace_faults.py.

For every (row, role, frame) the role has no right to send and holds no key
for, the insider tags the frame (a genuine one, one with every header
integer at its largest and at its smallest, one with its freshness fields
at their largest, junk of the longest length taken and of one byte more)
with each channel it does hold,
in the run it knows: the receiving intake refuses each, counts it exactly
once as bad, and still admits the genuine sender's next frame. Every other
case of the plan is a frame only the role's own node or a ground takes, or
a control node's (which commands by design): none reaches past the role.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.faults.insider import REACHES, REFUSED, InsiderCase, plan, shipped
from tests.faults.test_keyspace_faults import (
    MASTER,
    RECIPES,
    T0,
    Harness,
    _harness,
    _junk,
    _kind,
)
from zplatform.core.auth import TAG_LEN, KeySet, Run, host_roles

MISSIONS = shipped()
CASES = [c for n, m in MISSIONS.items() for c in plan(n, m)]


def _variants(h: Harness) -> Iterator[tuple[str, bytes]]:
    """The frames an insider forges from: a genuine one, extremes (every
    header integer at its largest, its smallest; the freshness fields at
    their largest), and junk of the longest length the intake takes and one
    byte more (the tag is then made right for the insider's key)."""
    yield "genuine", h.genuine()
    yield "extreme_max", h.extreme(True)
    yield "extreme_min", h.extreme(False)
    yield "stamp_max", h.stamp_max()
    yield "length_max", _junk(h.max_len)
    yield "length_over", _junk(h.max_len + 1)


def _retag(payload: bytes, keys: KeySet, name: str) -> bytes:
    """``payload``'s frame tagged with channel ``name`` of ``keys`` in the
    run its tag names (the insider learned it as every node does)."""
    run = int.from_bytes(payload[-TAG_LEN : -TAG_LEN + 8], "little")
    ch = keys.channel(name, Run(run))
    return bytes(ch.seal(payload[:-TAG_LEN]))


def test_the_plan_covers_every_role_and_reaches_nowhere() -> None:
    """Every host role of each shipped mission has cases; none reaches a
    vehicle node past its role; each refused case forges with every
    channel the role holds."""
    for name, m in MISSIONS.items():
        roles = {c.role for c in CASES if c.mission == name}
        assert roles == set(host_roles(m)), (name, roles)
    reaches = [c.id for c in CASES if c.verdict == REACHES]
    assert not reaches, f"a role's key reaches past it: {reaches}"
    assert all(c.forge for c in CASES if c.verdict == REFUSED)


def _params() -> Iterator[Any]:
    for c in CASES:
        if c.verdict == REFUSED:
            yield pytest.param(c, id=c.id)


@pytest.mark.parametrize("case", list(_params()))
def test_an_insider_forgery_outside_its_role_is_refused_and_counted_once(
    case: InsiderCase,
) -> None:
    m = MISSIONS[case.mission]
    kind = _kind(case.f)
    assert (case.key.row.name, kind) in RECIPES
    insider = KeySet.from_master(m, MASTER).for_node(case.role)
    refused = 0
    for name in case.forge:
        h = _harness(m, case.key, kind, T0)
        try:
            g = h.genuine()
            assert h.feed(g), "a genuine frame was refused"
            h.advance()
            for what, frame in _variants(h):
                forged = _retag(frame, insider, name)
                before = h.counts()
                assert not h.feed(forged), f"{case.role}'s {name} tag on {what}: admitted"
                after = h.counts()
                delta = {k: after[k] - before[k] for k in after}
                want = "size" if what == "length_over" and "size" in h.kinds else "bad"
                assert sum(delta.values()) == 1 and delta.get(want) == 1, (
                    f"{case.role}'s {name} tag on {what}: counted {delta}, not once as {want}"
                )
                refused += 1
            h.advance()
            assert h.feed(h.genuine()), f"{case.role}: the genuine sender refused after"
        finally:
            h.close()
    assert refused == 6 * len(case.forge)
