"""The ground archive under faults, on real node processes (issue 28).

* kill -9 of the ground node mid-run (led_test), then a ground node started again on
  the same archive: it opens clean (what the kill left recovered from the
  raw segment, no ``*.tmp`` left, nothing damaged); every loop the ground
  had archived before the kill is there exactly once, each row equal to the
  CN flight recorder's for that loop; ``archive runs`` lists the run once.
* A real full disk (the archive on a 2 MiB tmpfs the test mounts, filled):
  the ground's CSV keeps its rows (the receive path never waits on the
  archive), the failure is evented once, what was archived before stays,
  and once space is freed the archive resumes: every loop received after
  that is archived.
"""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from tests.integration.harness import CONFIGS, ROOT, Cluster
from tests.tmpfs import fill, mounted_tmpfs
from tests.waits import wait_until
from zplatform.archive import ARCHIVE_DIR_ENV
from zplatform.recorder import RECORDER_DIR_ENV, recorder_dir
from zplatform.recorder.format import FRAME
from zplatform.recorder.reader import scan_segment

pytestmark = pytest.mark.timeout(240)


def archive_mission(
    tmp: Path, monkeypatch: pytest.MonkeyPatch, archive: Path, base: str = "minimal.yaml"
) -> Path:
    """Mission ``base`` (in configs/) with a flight recorder on the CN and an
    archive closing a file every 2 s (1 s row groups), both in this test's
    directories (the nodes inherit the environment)."""
    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp / "rec"))
    monkeypatch.setenv(ARCHIVE_DIR_ENV, str(archive))
    raw = yaml.safe_load((CONFIGS / base).read_text())
    raw["recorder"] = {"file_bytes": 262144, "max_bytes": 8388608}
    raw["archive"] = {"row_group_s": 1.0, "file_s": 2.0}
    path = tmp / "minimal_arch.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def zp(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )


def csv_rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def file_rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def raw_loops(root: Path) -> list[int]:
    """The loops of every frame in the archive's open raw segments (read while written)."""
    out: list[int] = []
    for seg in sorted(root.glob("raw/run-*/seg-*.zfr")):
        out.extend(r.loop for r in scan_segment(seg, lambda _: None) if r.type == FRAME)
    return out


def closed_parts(root: Path) -> list[Path]:
    return sorted(root.glob("tm/run-*/*/part-*.parquet"))


def archived(mission: Path, root: Path) -> tuple[dict[str, object], list[dict[str, str]]]:
    """The archive's one run (``archive runs --json``) and its rows (``query``)."""
    runs = zp("archive", str(mission), "--dir", str(root), "runs", "--json")
    assert runs.returncode == 0, runs.stderr
    (run,) = json.loads(runs.stdout)  # the run listed once
    q = zp(
        "archive",
        str(mission),
        "--dir",
        str(root),
        "query",
        "--run",
        str(run["run"]),
        "--elements",
        "*",
    )
    assert q.returncode == 0, q.stderr
    assert q.stderr == ""  # nothing damaged skipped
    return run, csv_rows(q.stdout)


def recorder_rows(mission: Path, cn_dir: Path, out: Path) -> dict[str, dict[str, str]]:
    """The CN flight recorder's rows by loop (``zplatform log --from-recorder``)."""
    r = zp("log", str(mission), "--from-recorder", str(cn_dir), "--out", str(out))
    assert r.returncode == 0, r.stderr
    return {row["cn_loop"]: row for row in file_rows(out)}


def same_row(row: dict[str, str], rec: dict[str, str]) -> bool:
    """Every element column equal (``rx_time_ns``: a live row's arrival
    time, never the recorder's stamp, so left out)."""
    return {k: v for k, v in row.items() if k != "rx_time_ns"} == {
        k: v for k, v in rec.items() if k != "rx_time_ns"
    }


# With the soaks (-m slow): the ground killed in flight stays in the default
# suite (tests/faults/test_worst_day_live.py, gn_kill9), the archive's
# recovery in tests/unit/test_archive*.py.
@pytest.mark.slow
def test_kill9_of_the_ground_node_then_the_archive_opens_clean(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The LED platform (three device nodes; arrays, enums, flags), as the
    # live archive test flies it, on node processes the test can kill.
    root = tmp_path / "archive" / "led_test"
    mission = archive_mission(tmp_path, monkeypatch, tmp_path / "archive", "led_test.yaml")
    c = Cluster(mission, tmp_path)
    with c:
        for dn in ("dn0", "dn1", "dn2"):
            c.spawn(dn)
        c.spawn("gn", "--log", str(tmp_path / "gn1.csv"))
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_loop")) >= 300, 60, "the CN looping")
        # Files closed, and the open raw segment past a loop the test saw.
        wait_until(lambda: len(closed_parts(root)) >= 1, 60, "a closed Parquet file", poll_s=0.1)
        seen = int(c.tm.get("cn_loop"))
        wait_until(
            lambda: (raw_loops(root) or [0])[-1] >= seen, 30, f"loop {seen} archived", poll_s=0.1
        )
        c.kill("gn")
        before = raw_loops(root)  # what the kill left: the archive's source of truth
        killed_at = before[-1]
        assert killed_at >= seen
        c.advance(200)
        # A ground node again, on the same archive: it recovers what the kill left.
        c.spawn("gn", "--log", str(tmp_path / "gn2.csv"))
        wait_until(lambda: len(file_rows(tmp_path / "gn2.csv")) >= 300, 60, "the GN logging again")
        c.procs["gn"].terminate()
        assert c.procs["gn"].wait(30) == 0, c.log("gn")
    assert "no archive" not in c.log("gn")
    run, rows = archived(c.path, root)
    assert run["outcome"] == "ended"
    loops = [int(r["cn_loop"]) for r in rows]
    assert loops == sorted(set(loops))  # each loop once, in order
    recorded = recorder_rows(c.path, recorder_dir(c.mission, "cn"), tmp_path / "cn.csv")
    # Every loop archived before the kill is there (none lost with the open
    # row group: the raw segment had it), exactly once.
    upto = [n for n in loops if n <= killed_at]
    assert upto == sorted(set(before)), "the loops archived before the kill differ"
    # No hole among them but the periods the CN's scheduler skipped (in neither).
    on_board = [int(n) for n in recorded if upto[0] <= int(n) <= killed_at]
    assert upto == sorted(on_board)
    # Every row, before and after the kill, equal to the CN recorder's.
    for row in rows:
        assert same_row(row, recorded[row["cn_loop"]]), f"loop {row['cn_loop']} differs"
    assert loops[-1] > killed_at + 200  # the second ground node archived on
    assert run["loops"] == len(loops)
    assert not list(root.glob("**/*.tmp"))


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 2 MiB tmpfs at ``tmp_path/disk``, unmounted at the end."""
    with mounted_tmpfs(tmp_path / "disk", "2m") as d:
        yield d


def events_of(path: Path) -> list[dict[str, object]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


# With the soaks (-m slow): a full disk's rules are tests/unit/test_archive_full_disk.py's
# (in process, every write failing where the test says).
@pytest.mark.slow
def test_a_full_disk_never_stops_the_grounds_log_and_the_archive_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, small_disk: Path
) -> None:
    root = small_disk / "minimal"
    gn_csv = tmp_path / "gn.csv"
    gn_events = tmp_path / "gn.events.jsonl"
    c = Cluster(archive_mission(tmp_path, monkeypatch, small_disk), tmp_path)
    with c:
        c.spawn("dn0")
        c.spawn("gn", "--log", str(gn_csv))
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_loop")) >= 200, 60, "the CN looping")
        wait_until(lambda: len(closed_parts(root)) >= 1, 60, "a closed Parquet file", poll_s=0.1)
        seen = int(c.tm.get("cn_loop"))
        wait_until(
            lambda: (raw_loops(root) or [0])[-1] >= seen, 30, f"loop {seen} archived", poll_s=0.1
        )
        fill(small_disk / "filler", leave=48 * 1024)
        full_at = int(c.tm.get("cn_loop"))

        def failed() -> bool:
            return any(e["id"] == "archive_failed" for e in events_of(gn_events))

        wait_until(failed, 60, "the archive telling its failure", poll_s=0.1)
        # The ground's log keeps its rows while the archive cannot write.
        c.advance(300)
        target = full_at + 300
        wait_until(
            lambda: int((file_rows(gn_csv) or [{"cn_loop": "0"}])[-1]["cn_loop"]) >= target,
            60,
            f"the GN logging loop {target} with the disk full",
            poll_s=0.1,
        )
        (small_disk / "filler").unlink()  # space freed
        c.advance(1)
        later = int(c.tm.get("cn_loop")) + 100
        # The running archive writes again (its raw segment takes new loops).
        wait_until(
            lambda: (raw_loops(root) or [0])[-1] >= later, 60, f"loop {later} archived", poll_s=0.1
        )
        c.advance(100)
        c.procs["gn"].terminate()
        assert c.procs["gn"].wait(30) == 0, c.log("gn")
    logged = [int(r["cn_loop"]) for r in file_rows(gn_csv)]
    told = [e for e in events_of(gn_events) if str(e["id"]).startswith("archive_")]
    assert [e["id"] for e in told] == ["archive_failed"], told  # once
    assert "No space left on device" in str(told[0]["text"])
    run, rows = archived(c.path, root)
    assert run["outcome"] == "ended"
    loops = [int(r["cn_loop"]) for r in rows]
    assert loops == sorted(set(loops))  # each loop once
    assert set(loops) <= set(logged)
    # What was archived before the disk filled stays; all the GN logged
    # once space was freed is archived.
    assert [n for n in logged if n <= seen] == [n for n in loops if n <= seen]
    # Loops were lost while the disk was full (the raw segment could not
    # take them); every loop the GN logged after space was freed (from
    # `later`, a loop it received after the unlink) is archived: it resumed.
    assert len(loops) < len(logged)
    assert [n for n in loops if n >= later] == [n for n in logged if n >= later]
    assert loops[-1] >= later
    assert not list(root.glob("**/*.tmp"))
