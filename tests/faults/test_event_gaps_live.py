"""Events a ground missed are filled from the CN's flight recorder, on real
node processes: the ground node behind a fault relay, partitioned while an
operator's commands make the CN emit events; after the cut the ground sees
the gap in the CN's event numbers at its next event, asks the recorder, and
its events log holds every CN event of the span once, the missed ones
marked filled, in number order after the gap's own event."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.faults.relay import FaultRelay
from tests.faults.test_recorder_live import logging_behind_a_relay, rows
from tests.waits import wait_until
from zplatform.ground.link import GroundLink

pytestmark = pytest.mark.timeout(180)


def last_loop(csv_path: Path) -> int:
    """The loop of the GN log's last whole row (0: none yet)."""
    for row in reversed(rows(csv_path)):
        if (loop := row.get("cn_loop") or "").isdigit():
            return int(loop)
    return 0


def events(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:  # a line being written
            continue
    return out


def test_events_missed_in_a_link_cut_are_filled_from_the_cn_recorder(
    tmp_path: Path, fault_relay: Callable[..., FaultRelay], monkeypatch: pytest.MonkeyPatch
) -> None:
    gn_events = tmp_path / "gn.events.jsonl"

    def cmd_events() -> list[dict[str, Any]]:
        return [e for e in events(gn_events) if e["id"] in ("cmd_accepted", "cmd_rejected")]

    with logging_behind_a_relay(tmp_path, fault_relay, monkeypatch, 21) as (c, relay, gn_csv):
        op = GroundLink(c.mission, commands=True)
        try:
            op.command("noop", timeout_s=20)  # #1: the GN sees its event
            wait_until(lambda: len(cmd_events()) == 1, 30, "the GN's first command event")
            relay.partition()
            for _ in range(3):  # #2..#4: their events do not reach the GN
                op.command("noop", timeout_s=20)
            healed_at = int(op.dv.get("cn_loop"))
            relay.heal()
            wait_until(
                lambda: last_loop(gn_csv) > healed_at + 50,
                60,
                "the GN logging again after the cut",
                poll_s=0.1,
            )
            op.command("noop", timeout_s=20)  # #5: the GN sees the gap before it
            wait_until(
                lambda: any(e["id"] == "events_filled" for e in events(gn_events)),
                60,
                "the GN filling the CN's events",
                poll_s=0.1,
            )
        finally:
            op.close()
        c.procs["gn"].terminate()
        assert c.procs["gn"].wait(30) == 0, c.log("gn")
    got = events(gn_events)
    cn = [e for e in got if e["node"] == "cn"]
    seqs = [e["seq"] for e in cn]
    # Every CN event from the first the GN saw to the last, exactly once.
    assert sorted(seqs) == list(range(min(seqs), max(seqs) + 1)), seqs
    cmds = dict(sorted((e["text"].split(" ")[2], e["filled"]) for e in cmd_events()))
    assert len(cmd_events()) == 5 and sorted(cmds) == ["#1", "#2", "#3", "#4", "#5"], cmds
    # #4's event may leave the CN after its verdict reached the operator and
    # the cut healed (beside a CPU hog it came live): filled or live, once.
    assert (cmds["#1"], cmds["#2"], cmds["#3"], cmds["#5"]) == (False, True, True, False), cmds
    missed = [e for e in got if e["id"] == "events_missed"]
    assert missed and all("asked of the control node's recorder" in e["text"] for e in missed)
    assert not [e for e in got if e["id"] == "events_unfilled"], c.log("gn")[-3000:]
    # Filled ones come after the gap's event, in number order.
    filled = [e["seq"] for e in cn if e["filled"]]
    assert filled == sorted(filled) and len(filled) >= 2
