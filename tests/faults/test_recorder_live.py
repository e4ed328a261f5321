"""The flight recorder on real node processes (issue 20).

* A ground link cut of 5 s (the GN behind a fault relay, partitioned; the
  vehicle flies on): the ground fills the gap from the CN's recorder, and
  its CSV has every loop the CN ran, each row equal to the CN recorder's
  own row for that loop (every element column; ``rx_time_ns`` too for the
  filled rows, which carry the frame's stamp as the recorder's do).
* kill -9 of the CN mid-run: ``zplatform log --from-recorder`` reads its
  directory to the last record written (loops 1..N, without a hole but the
  periods the CN's scheduler skipped, which its overrun count shows), says
  the run has no END record, and skips a torn record appended to the tail,
  saying so.
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from tests.faults.missions import relay_links
from tests.faults.relay import FaultRelay
from tests.integration.harness import CONFIGS, ROOT, Cluster
from tests.waits import wait_until
from zplatform.mission.load import load_mission
from zplatform.recorder import RECORDER_DIR_ENV, RecorderReader, recorder_dir
from zplatform.recorder.format import FRAME

pytestmark = pytest.mark.timeout(180)


def recorder_mission(tmp: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The minimal mission with a small flight recorder (ring of 256 KiB
    files), recording into this test's directory (the nodes inherit it)."""
    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp / "rec"))
    raw = yaml.safe_load((CONFIGS / "minimal.yaml").read_text())
    raw["recorder"] = {"file_bytes": 262144, "max_bytes": 8388608}
    path = tmp / "minimal_rec.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def recorded_loops(directory: Path) -> list[int]:
    """The loops of every frame in a recorder directory (read while it runs)."""
    r = RecorderReader(directory)
    return [rec.loop for _, rec in r.records() if rec.type == FRAME]


@contextlib.contextmanager
def logging_behind_a_relay(
    tmp_path: Path,
    fault_relay: Callable[..., FaultRelay],
    monkeypatch: pytest.MonkeyPatch,
    seed: int,
) -> Iterator[tuple[Cluster, FaultRelay, Path]]:
    """dn0, the ground node (logging to ``gn.csv``, its link behind a fault
    relay) and the CN of :func:`recorder_mission`, running: the CN past
    loop 100 and the ground's log 50 rows long. Yields the cluster, the
    relay and the log's path; every process is stopped after."""
    c = Cluster(recorder_mission(tmp_path, monkeypatch), tmp_path)
    relay = relay_links(c.path, fault_relay, ["gn"], seed=seed)["gn"]
    c.mission = load_mission(c.path)
    gn_csv = tmp_path / "gn.csv"
    with c:
        c.spawn("dn0")
        c.spawn("gn", "--log", str(gn_csv))
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_loop")) >= 100, 60, "the CN looping")
        wait_until(
            lambda: gn_csv.exists() and len(rows(gn_csv)) >= 50, 30, "the GN logging", poll_s=0.1
        )
        yield c, relay, gn_csv


def zplatform(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )


# A 5 s cut: with the soaks (-m slow). A cut filled from the CN's recorder
# stays in the default suite (tests/faults/test_event_gaps_live.py), and the
# gap fill's rules in tests/unit/test_ground_gapfill.py.
@pytest.mark.slow
def test_ground_fills_a_5s_link_cut_from_the_cn_recorder(
    tmp_path: Path, fault_relay: Callable[..., FaultRelay], monkeypatch: pytest.MonkeyPatch
) -> None:
    with logging_behind_a_relay(tmp_path, fault_relay, monkeypatch, 20) as (c, relay, gn_csv):
        relay.partition()
        c.advance(500)  # 5 s of loops, on the test's own link to the CN
        healed_at = int(c.tm.get("cn_loop"))
        relay.heal()

        def filled_past_the_cut() -> bool:
            loops = [int(r["cn_loop"]) for r in rows(gn_csv)]
            return bool(loops) and loops[-1] >= healed_at + 100

        wait_until(filled_past_the_cut, 60, "the GN logging again after the cut", poll_s=0.1)
        c.advance(50)
        c.procs["gn"].terminate()
        assert c.procs["gn"].wait(30) == 0, c.log("gn")
    ground = rows(gn_csv)
    loops = [int(r["cn_loop"]) for r in ground]
    cn_dir = recorder_dir(c.mission, "cn")
    # Zero rows missing, none twice, in loop order, across the cut: every loop
    # the CN ran (on a loaded host its scheduler may skip a period: that loop
    # number never ran, and is in neither file) between the first and the last.
    on_board = [n for n in recorded_loops(cn_dir) if loops[0] <= n <= loops[-1]]
    holes = sorted(set(on_board) - set(loops))
    assert loops == on_board, (
        f"the ground log differs from the CN's loops: missing {holes[:20]}\n{c.log('gn')[-3000:]}"
    )
    assert loops[-1] > healed_at + 100
    gn_log = c.log("gn")
    assert "gap_filled" in gn_log, gn_log[-3000:]
    # The CN recorder's own rows (zplatform log --from-recorder).
    out = tmp_path / "cn_rec.csv"
    r = zplatform("log", str(c.path), "--from-recorder", str(cn_dir), "--out", str(out))
    assert r.returncode == 0, r.stderr
    recorded = {r["cn_loop"]: r for r in rows(out)}
    filled = 0
    for row in ground:
        rec = recorded[row["cn_loop"]]
        # A filled row carries the frame's stamp, as the recorder's rows do;
        # a live one its arrival time (never exactly the stamp).
        live = row["rx_time_ns"] != rec["rx_time_ns"]
        filled += not live
        # Every element column equal; rx_time_ns equal too for the filled rows.
        assert {k: v for k, v in row.items() if k != "rx_time_ns" or not live} == {
            k: v for k, v in rec.items() if k != "rx_time_ns" or not live
        }, f"loop {row['cn_loop']} differs from the CN recorder's row"
    # The CN ran 500 loops while the GN was cut off; the GN missed them all
    # (and those of its reconnection), but for a few in flight at the cut.
    assert filled >= 450, filled
    events = (tmp_path / "gn.events.jsonl").read_text()
    assert '"gap_filled"' in events and '"gap_unfilled"' not in events


def test_kill9_of_the_cn_leaves_a_recorder_read_to_its_last_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    c = Cluster(recorder_mission(tmp_path, monkeypatch), tmp_path)
    with c:
        c.spawn("dn0")
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_loop")) >= 200, 60, "the CN looping")
        seen = int(c.tm.get("cn_loop"))
        cn_dir = recorder_dir(c.mission, "cn")
        # What the CN published is on its disk soon after (written, not fsynced).
        wait_until(
            lambda: recorded_loops(cn_dir)[-1] >= seen, 10, f"loop {seen} recorded", poll_s=0.1
        )
        c.kill("cn")
    loops = recorded_loops(cn_dir)
    assert loops[0] == 1 and loops[-1] >= seen
    out = tmp_path / "cn.csv"
    r = zplatform("log", str(c.path), "--from-recorder", str(cn_dir), "--out", str(out))
    assert r.returncode == 0, r.stderr
    # No hole but the periods the CN's scheduler skipped (counted as overruns).
    got = rows(out)
    for a, b in itertools.pairwise(got):
        skipped = int(b["cn_loop_overruns"]) - int(a["cn_loop_overruns"])
        assert int(b["cn_loop"]) - int(a["cn_loop"]) == 1 + skipped, (a["cn_loop"], b["cn_loop"])
    assert f"{len(loops)} snapshot(s) (loops 1..{loops[-1]})" in r.stdout
    assert "has no END record" in r.stderr
    # A torn write at the tail (a power loss mid-record): skipped and said so.
    last = sorted(cn_dir.glob("seg-*.zfr"))[-1]
    whole = last.read_bytes()
    with open(last, "ab") as f:
        f.write(whole[-700:-300])  # a piece of a record: its header, not its end
    r = zplatform("log", str(c.path), "--from-recorder", str(cn_dir), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"{len(loops)} snapshot(s) (loops 1..{loops[-1]})" in r.stdout
    assert f"{last.name}: offset {len(whole)}: torn tail" in r.stderr, r.stderr
    assert "1 damaged record(s)" in r.stdout
    assert [int(x["cn_loop"]) for x in rows(out)] == loops
