"""`up`'s one-line account of a run: words, not Python reprs, and a takeover said."""

from __future__ import annotations

from pathlib import Path

from zplatform.cli.supervisor import format_run_summary, merge_summaries
from zplatform.mission.load import load_mission
from zplatform.telemetry.summary import CnSummary, write_summary

FLIGHT = Path(__file__).resolve().parents[2] / "configs" / "flight.yaml"


def _cn(node: str, loops: int, last: int, term: int, *, commanding: bool, took: int) -> CnSummary:
    return CnSummary(
        loops=loops,
        duration_s=loops / 100,
        rate_hz=100.0,
        loop_overruns=0,
        sync_overruns=0,
        missed={"dn0": 1, "dn1": 0},
        late={"dn0": 0, "dn1": 0},
        rx={},
        bad_frames=0,
        errors=0,
        final_state="LANDED",
        node=node,
        last_loop=last,
        term=term,
        commanding=commanding,
        takeovers=took,
    )


def test_a_takeover_is_said_and_the_run_counts_the_vehicle_s_loops(tmp_path: Path) -> None:
    mission = load_mission(FLIGHT, code=False)
    paths = {"cn": tmp_path / "cn.json", "cn_b": tmp_path / "cn_b.json"}
    write_summary(paths["cn"], _cn("cn", 500, 500, 1, commanding=False, took=0))
    write_summary(paths["cn_b"], _cn("cn_b", 495, 1000, 2, commanding=True, took=1))
    s = merge_summaries(mission, paths, {"cn": -9, "cn_b": 0})
    assert s.loops == 1000
    line = format_run_summary(s)
    assert "missed dn0 1, dn1 0; late dn0 0, dn1 0" in line and "{" not in line, line
    assert line.endswith(
        "command changed hands: cn (term 1, 500 loops), then cn_b (term 2, 495 loops)"
    ), line


def test_one_commander_says_nothing_of_command(tmp_path: Path) -> None:
    mission = load_mission(FLIGHT, code=False)
    paths = {"cn": tmp_path / "cn.json"}
    write_summary(paths["cn"], _cn("cn", 800, 800, 1, commanding=True, took=0))
    s = merge_summaries(mission, paths, {"cn": 0})
    assert s.loops == 800 and s.takeover is None
    assert "command changed hands" not in format_run_summary(s)


def test_the_grounds_missed_events_are_said(tmp_path: Path) -> None:
    """The ground node's events_missed reaches `up`'s line and the log's."""
    from zplatform.ground.logger import log_summary_line
    from zplatform.telemetry.summary import GnSummary

    mission = load_mission(FLIGHT, code=False)
    paths = {"cn": tmp_path / "cn.json", "gn": tmp_path / "gn.json"}
    write_summary(paths["cn"], _cn("cn", 800, 800, 1, commanding=True, took=0))
    gn = GnSummary(
        telemetry_received=800,
        telemetry_gaps=0,
        telemetry_bad=0,
        first_seq=1,
        last_seq=800,
        final_state="LANDED",
        events_missed=3,
        events_filled=2,
        events_unfilled=1,
    )
    write_summary(paths["gn"], gn)
    s = merge_summaries(mission, paths, {"cn": 0, "gn": 0})
    assert s.events_missed == 3
    assert format_run_summary(s).endswith("; events missed 3 (the ground's events_missed)")
    assert log_summary_line(gn, None, "ev.jsonl").endswith(
        "; 3 event(s) did not arrive, 2 of them filled from the CN's recorder"
    )
