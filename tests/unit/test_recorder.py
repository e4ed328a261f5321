"""The flight recorder's writer, reader and export, without processes (issue 20).

Telemetry frames come from a real :class:`ControlLogic` of the minimal
mission with a ``recorder`` section; the storage is a temporary directory,
or a fake file that stalls or fails on demand.
"""

from __future__ import annotations

import csv
import errno
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

import pytest

from tests.payload import FakeQuery, FakeSession, deliver
from tests.waits import poll_until
from zplatform.config import relocate_mission
from zplatform.control.loop import ControlLogic
from zplatform.core.auth import KeyError_, KeySet
from zplatform.core.datavector import Layout
from zplatform.core.events import EV, EventLog, encode_event
from zplatform.core.health import Liveness, stalled_names
from zplatform.errors import ConfigError, RecordingError
from zplatform.mission.load import decode_mission
from zplatform.recorder import (
    RECORDER_DIR_ENV,
    FlightRecorder,
    RecorderReader,
    export,
    open_recorder,
    reader_role,
    recorded_node,
    recorder_dir,
)
from zplatform.recorder.format import DROPPED, END, EVENT, FRAME, HEADER_LEN
from zplatform.recorder.reader import counts
from zplatform.telemetry.logs import CsvLogger

ROOT = Path(__file__).resolve().parents[2]
MINIMAL = (ROOT / "configs" / "minimal.yaml").read_text()
KEY = bytes.fromhex("85521353c82a2b84575ac3e990e6eebcb7e03704cce11384abb08bf990012529")
"""A master key (every link's key derived from it), as ``ZPLATFORM_KEY`` gives."""
EPOCH = 1_700_000_000_000_000_000
PERIOD = 10_000_000


def mission(extra: str = "recorder: {}", base: Path | None = None) -> Any:
    return decode_mission(MINIMAL + "\n" + extra + "\n", code=False, base_dir=base)


def keys(m: Any, role: str | None = None) -> KeySet:
    """Every link key of ``m`` from :data:`KEY`, or host role ``role``'s."""
    ks = KeySet.from_master(m, KEY)
    return ks.for_node(role) if role is not None else ks


class Telemetry:
    """The CN of the minimal mission, framing telemetry loop by loop."""

    def __init__(self, extra: str = "recorder: {}") -> None:
        self.mission = mission(extra)
        self.cn = ControlLogic(self.mission, keys=keys(self.mission), epoch=EPOCH)

    def frame(self, loop: int) -> bytes:
        t = EPOCH + loop * PERIOD
        self.cn.begin(loop, t)
        tm = self.cn.finish()
        assert tm is not None
        return bytes(tm)

    def frames(self, first: int, last: int) -> Iterator[tuple[int, bytes]]:
        for n in range(first, last + 1):
            yield n, self.frame(n)


def wait_for(ok: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Poll ``ok`` until it holds (True) or ``timeout_s`` passes (False)."""
    return poll_until(ok, timeout_s, poll_s=0.001)


def head(node: str = "cn", run: int = EPOCH) -> dict[str, Any]:
    m = mission()
    layout = Layout.for_node(m, "cn")
    return {
        "mission": m.mission,
        "vehicle": m.vehicle,
        "node": node,
        "run": run,
        "kind": "telemetry",
        "layout_id": layout.layout_id,
        "channel": "telemetry",
        "period_ns": PERIOD,
        "telemetry_divisor": 1,
    }


def recorder(d: Path, tm: Telemetry, **kw: Any) -> FlightRecorder:
    args: dict[str, Any] = {
        "max_bytes": 1 << 20,
        "file_bytes": 64 * 1024,
        "fsync_ms": None,
        "buffer_bytes": 1 << 20,  # no drops unless a test stalls the writer
        "max_record": len(tm.frame(0)),
        "interval_s": 0.001,
    }
    args.update(kw)
    return FlightRecorder(d, head(), **args)


def read(d: Path) -> tuple[RecorderReader, list[tuple[int, int, bytes]]]:
    r = RecorderReader(d)
    return r, [(rec.type, rec.loop, rec.payload) for _, rec in r.records()]


def frame_loops(recs: list[tuple[int, int, bytes]]) -> list[int]:
    return [loop for typ, loop, _ in recs if typ == FRAME]


def test_frames_and_events_come_back_in_order(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path, tm)
    sent = dict(tm.frames(1, 300))
    for n, f in sent.items():
        assert rec.frame(n, f)
        if n % 100 == 0:
            ev = EventLog("cn")
            ev.emit(EV.ERROR, n, text=f"at loop {n}")
            assert rec.event(encode_event(ev.drain()[0]))
    rec.close()
    assert rec.stats()["loops"] == 300 and rec.dropped == 0 and rec.errors == 0
    r, recs = read(tmp_path)
    assert r.problems == [] and r.ended_runs == 1
    assert [(t, loop) for t, loop, _ in recs if t != FRAME] == [
        (EVENT, 100),
        (EVENT, 200),
        (EVENT, 300),
        (END, 300),
    ]
    assert {loop: p for t, loop, p in recs if t == FRAME} == sent
    assert counts(recs[-1][2]) == (300, 0, 3)


def test_export_writes_the_ground_logs_rows_with_the_frame_stamp(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path / "cn", tm)
    ground = CsvLogger(tmp_path / "ground.csv", tm.cn.layout)
    for n, f in tm.frames(1, 50):
        rec.frame(n, f)
        ground.write(tm.cn.t_ns, tm.cn.dv)  # a ground that received it at its stamp
    rec.close()
    ground.close()
    tool = keys(tm.mission, "tool")  # a read-only tool's keys check the CN's record
    s = export(tmp_path / "cn", tm.mission, tool, tmp_path / "rec.csv", tmp_path / "rec.jsonl")
    assert (s.rows, s.first_loop, s.last_loop, s.damaged, s.refused) == (50, 1, 50, 0, 0)
    assert (tmp_path / "rec.csv").read_bytes() == (tmp_path / "ground.csv").read_bytes()
    # Without the key the tags do not check: every frame refused, each said.
    other = KeySet.from_master(tm.mission, bytes(32))
    s = export(tmp_path / "cn", tm.mission, other, tmp_path / "x.csv", None)
    assert s.rows == 0 and s.refused == 50
    assert "bad authentication tag" in s.problems[0]


def test_a_torn_tail_is_skipped_and_said(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path, tm)
    frames = dict(tm.frames(1, 40))
    for n, f in frames.items():
        rec.frame(n, f)
    rec.close()
    seg = sorted(tmp_path.glob("seg-*.zfr"))[-1]
    data = seg.read_bytes()
    last = data.rindex(frames[40]) - HEADER_LEN  # loop 40's record, then END's
    # A power loss in the middle of loop 40's record: the rest zeroed pages.
    seg.write_bytes(data[: last + 100] + bytes(4096))
    r, recs = read(tmp_path)
    assert frame_loops(recs) == list(range(1, 40))  # everything before, nothing misread
    assert r.damaged == 1 and r.ended_runs == 0
    assert r.problems == [
        f"{seg.name}: offset {last}: torn tail (a record whose checksum does not match; the "
        f"last {100 + 4096} bytes hold no complete record): skipped"
    ]
    # Cut inside a record's header: the same, in other words.
    seg.write_bytes(data[: last + 10])
    r, recs = read(tmp_path)
    assert frame_loops(recs) == list(range(1, 40))
    assert r.problems == [
        f"{seg.name}: offset {last}: torn tail (an incomplete record header; the last 10 bytes "
        "hold no complete record): skipped"
    ]


def test_damage_inside_a_file_skips_to_the_next_good_record(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path, tm)
    frames = dict(tm.frames(1, 20))
    for n, f in frames.items():
        rec.frame(n, f)
    rec.close()
    seg = sorted(tmp_path.glob("seg-*.zfr"))[0]
    data = bytearray(seg.read_bytes())
    at = data.index(frames[7]) + 40  # a byte inside loop 7's frame
    data[at] ^= 0xFF
    seg.write_bytes(bytes(data))
    r, recs = read(tmp_path)
    assert frame_loops(recs) == [n for n in range(1, 21) if n != 7]  # never misread
    assert len(r.problems) == 1 and "checksum does not match" in r.problems[0]
    assert "bytes skipped to the next good record" in r.problems[0]


def test_the_ring_wraps_at_its_bound_and_says_so(tmp_path: Path) -> None:
    tm = Telemetry()
    events = EventLog("cn")
    rec = recorder(tmp_path, tm, max_bytes=256 * 1024, file_bytes=64 * 1024)
    rec.attach(tm.cn.dv, events)
    n = 0
    for n, f in tm.frames(1, 2000):
        rec.frame(n, f, n)
        rec.tick(n)
        if n % 50 == 0:  # let the writer keep up (a stall is the next test's)
            assert wait_for(lambda: not rec.backlog)
    rec.close()
    rec.tick(n + 1)
    files = sorted(tmp_path.glob("seg-*.zfr"))
    assert sum(f.stat().st_size for f in files) <= 256 * 1024
    assert rec.evicted > 0 and rec.dropped == 0
    assert tm.cn.dv.get("cn_rec_evicted") == rec.evicted
    removed = [e for e in events.drain() if e.id == "recorder_evicted"]
    assert len(removed) >= 1 and "removed its oldest file seg-00000001.zfr" in removed[0].text
    assert files[0].name == f"seg-{rec.evicted + 1:08d}.zfr"  # the oldest went first
    r, recs = read(tmp_path)
    loops = frame_loops(recs)
    assert r.problems == [] and loops == list(range(loops[0], 2001))  # the newest, whole


class FakeDisk:
    """A segment file on a misbehaving disk: after its header, every write
    blocks while ``gate`` is closed (a stalled disk: ``blocked`` is set once
    one does), or fails (``full``: no space left)."""

    def __init__(
        self,
        path: Path,
        gate: threading.Event | None = None,
        blocked: threading.Event | None = None,
        full: bool = False,
    ) -> None:
        self.f: BinaryIO = open(path, "xb", buffering=0)  # noqa: SIM115
        self.gate, self.blocked, self.full = gate, blocked, full
        self.header_written = False

    def write(self, b: Any) -> int:
        if self.header_written:
            if self.full:
                raise OSError(errno.ENOSPC, "No space left on device")
            if self.gate is not None and not self.gate.is_set():
                assert self.blocked is not None
                self.blocked.set()
                self.gate.wait()
        self.header_written = True
        return self.f.write(b)

    def fileno(self) -> int:
        return self.f.fileno()

    def close(self) -> None:
        self.f.close()


def test_a_stalled_disk_drops_whole_loops_counted_never_blocking(tmp_path: Path) -> None:
    tm = Telemetry()
    frames = dict(tm.frames(1, 31))
    size = HEADER_LEN + len(frames[1])
    gate, blocked = threading.Event(), threading.Event()
    rec = recorder(
        tmp_path,
        tm,
        buffer_bytes=10 * size,  # exactly ten loops
        opener=lambda p: FakeDisk(p, gate, blocked),
    )
    events = EventLog("cn")
    rec.attach(tm.cn.dv, events)
    kept = [rec.frame(n, frames[n], n) for n in range(1, 31)]
    assert blocked.wait(5)
    # Thirty loops went by while the writer stood in a write: none waited.
    assert not gate.is_set()
    assert kept == [True] * 10 + [False] * 20
    rec.tick(30)
    assert rec.dropped == 20 and tm.cn.dv.get("cn_rec_dropped") == 20
    # The writer stuck in its write stops checking in: named stalled
    # (zplatform.core.health), and checks in again once the write returns.
    live = Liveness({"recorder": 50_000_000})
    live.add(rec.heartbeat)
    assert wait_for(lambda: stalled_names(live.stalled(time.monotonic_ns())) == ["recorder"])
    gate.set()
    assert wait_for(lambda: not rec.backlog)
    assert wait_for(lambda: live.stalled(time.monotonic_ns()) == 0)
    assert rec.frame(31, frames[31], 31)  # kept again, after a DROPPED record
    rec.close()
    said = [(e.id, e.text) for e in events.drain()]
    assert said == [
        ("recorder_dropping", said[0][1]),
        (
            "recorder_resumed",
            "cn's recorder keeps loops again from loop 31; 20 loop(s) dropped (11..30)",
        ),
    ]
    assert "drops loops from loop 11" in said[0][1]
    r, recs = read(tmp_path)
    assert r.problems == []
    assert frame_loops(recs) == [*range(1, 11), 31]
    (dropped,) = [counts(p) for t, _, p in recs if t == DROPPED]
    assert dropped == (11, 30, 20)
    s = export(tmp_path, tm.mission, keys(tm.mission), tmp_path / "x.csv", None)
    assert s.not_recorded == 20 and "dropped 20 loop(s) (11..30)" in "\n".join(s.problems)


def test_a_full_disk_is_counted_told_once_and_the_loop_goes_on(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path, tm, opener=lambda p: FakeDisk(p, full=True))
    events = EventLog("cn")
    rec.attach(tm.cn.dv, events)
    for n, f in tm.frames(1, 50):
        assert rec.frame(n, f, n)  # copied: the loop never sees the disk
        rec.tick(n)
        assert wait_for(lambda: not rec.backlog)
    rec.close()
    rec.tick(51)
    assert rec.lost == 50 and rec.dropped == 50 and rec.errors >= 50
    assert tm.cn.dv.get("cn_rec_dropped") == 50
    failed = [e.text for e in events.drain() if e.id == "recorder_failed"]
    assert failed == ["cn's recorder cannot write its file: No space left on device"]


def test_fsync_follows_the_policy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tm = Telemetry()
    synced: list[int] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        synced.append(fd)
        real(fd)

    monkeypatch.setattr("zplatform.recorder.writer.os.fsync", fsync)
    for policy, expect in ((None, False), (0.0, True)):
        synced.clear()
        rec = recorder(tmp_path / str(policy), tm, fsync_ms=policy)
        for n, f in tm.frames(1, 5):
            rec.frame(n, f)
        assert wait_for(lambda r=rec: not r.backlog)
        if expect:
            assert wait_for(lambda: bool(synced))  # a writer wake syncs
        else:
            time.sleep(0.01)  # stimulus: a few writer wakes, none of which may sync
        rec.close()
        assert bool(synced) == expect, policy


def test_one_recorder_per_directory(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path, tm)
    with pytest.raises(RecordingError, match="in use by another recorder"):
        recorder(tmp_path, tm)
    rec.close()
    recorder(tmp_path, tm).close()  # free again; the new run's files follow the old
    assert [p.name for p in sorted(tmp_path.glob("seg-*.zfr"))] == [
        "seg-00000001.zfr",
        "seg-00000002.zfr",
    ]


def test_a_file_too_small_for_the_frames_is_refused(tmp_path: Path) -> None:
    tm = Telemetry()
    with pytest.raises(RecordingError, match="too small"):
        recorder(tmp_path, tm, file_bytes=64 * 1024, max_record=20_000)


def test_the_reader_names_what_it_cannot_read(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no recorder directory"):
        RecorderReader(tmp_path / "nope")
    (tmp_path / "f").write_text("x")
    with pytest.raises(RecordingError, match="is not a directory"):
        RecorderReader(tmp_path / "f")
    with pytest.raises(RecordingError, match="holds no recorder segment"):
        RecorderReader(tmp_path)
    tm = Telemetry()
    rec = recorder(tmp_path / "base" / "cn", tm)
    rec.frame(1, tm.frame(1))
    rec.close()
    with pytest.raises(RecordingError, match="holds the recorder directories of cn; pass one"):
        RecorderReader(tmp_path / "base")
    d = tmp_path / "base" / "cn"
    os.mkfifo(d / "seg-00000007.zfr")  # would block a naive open
    (d / "seg-00000008.zfr").symlink_to("/dev/zero")
    (d / "seg-00000009.zfr").write_bytes(b"not a recorder file at all")
    r, recs = read(d)
    assert frame_loops(recs) == [1]
    assert r.problems[0] == "seg-00000007.zfr: not a regular file: skipped"
    assert r.problems[1].startswith("seg-00000008.zfr: cannot open it")
    assert r.problems[2].startswith("seg-00000009.zfr: offset 0: torn tail (no record marker")


def test_export_refuses_another_missions_layout(tmp_path: Path) -> None:
    tm = Telemetry()
    rec = recorder(tmp_path, tm)
    rec.frame(1, tm.frame(1))
    rec.close()
    other = decode_mission(MINIMAL.replace("name: heartbeat", "name: beat") + "\nrecorder: {}\n")
    with pytest.raises(RecordingError, match="another Data Vector layout"):
        export(tmp_path, other, keys(other), tmp_path / "x.csv", None)


def test_a_device_nodes_directory_reads_as_its_region(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from zplatform.control.loop import DeviceLogic

    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp_path))
    m = mission()
    dn = DeviceLogic(m, "dn0", keys=keys(m, "dn0"))
    cn = Telemetry().cn
    rec = open_recorder(m, "dn0", dn.dv, run=EPOCH, authenticated=True)
    assert rec.directory == tmp_path / "minimal" / "dn0"
    for n in range(1, 11):
        t = EPOCH + n * PERIOD
        reply = dn.step(cn.begin(n, t)[0], t)
        assert reply is not None
        rec.frame(n, reply, t)
    rec.close()
    # Its replies are tagged with the key of its link to the CN: a tool
    # holds none, the DN's own key file does.
    with pytest.raises(KeyError_, match="no key for link cn-dn0"):
        export(rec.directory, m, keys(m, "tool"), tmp_path / "dn0.csv", None)
    assert (recorded_node(rec.directory), reader_role(m, "dn0")) == ("dn0", "dn0")
    s = export(rec.directory, m, keys(m, "dn0"), tmp_path / "dn0.csv", None)
    assert (s.node, s.rows, s.first_loop, s.last_loop) == ("dn0", 10, 1, 10)
    with open(tmp_path / "dn0.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[:3] == ["rx_time_ns", "dn0_loop", "dn0_time_ns"]
    # The region as it stood before each loop's run: loop n carries dn0_loop n - 1.
    assert [int(r["dn0_loop"]) for r in rows] == list(range(0, 10))


# ---------------------------------------------------------------- configuration


def test_the_recorder_is_off_unless_configured() -> None:
    m = mission("")
    assert m.recorder is None and m.recording_nodes == []
    assert not [e for e in Layout.for_node(m, "cn").elements if "_rec_" in e]
    m = mission("recorder: {nodes: [cn]}")
    assert m.recording_nodes == ["cn"]
    names = [e for e in Layout.for_node(m, "cn").elements if "_rec_" in e]
    assert names == ["cn_rec_dropped", "cn_rec_evicted", "cn_rec_errors"]
    m = mission()
    assert m.recording_nodes == ["cn", "dn0"]
    assert "dn0_rec_dropped" in Layout.for_node(m, "dn0").elements


@pytest.mark.parametrize(
    ("extra", "message", "path"),
    [
        ("recorder: {nodes: [gn]}", "the ground node keeps its own log", "$.recorder.nodes[0]"),
        (
            "recorder: {nodes: [dn7]}",
            "not the control node or a device node",
            "$.recorder.nodes[0]",
        ),
        ("recorder: {nodes: [cn, cn]}", "listed twice", "$.recorder.nodes"),
        (
            "recorder: {file_bytes: 1048576, max_bytes: 1048576}",
            "at least two files",
            "$.recorder.max_bytes",
        ),
        ("recorder: {file_bytes: 100}", "Expected `int` >= 65536", "$.recorder.file_bytes"),
        ("recorder: {fsync_ms: -1}", "Expected `float` >= 0", "$.recorder.fsync_ms"),
        ("recorder: {size: 1}", "unknown field `size`", "$.recorder"),
        ("recorder: {dir: ''}", "non-empty path", "$.recorder.dir"),
    ],
)
def test_recorder_config_errors_name_the_yaml_path(extra: str, message: str, path: str) -> None:
    with pytest.raises(ConfigError) as ei:
        mission(extra)
    assert message in ei.value.reason and ei.value.path == path


def test_where_a_node_records(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(RECORDER_DIR_ENV, raising=False)
    m = mission("recorder: {dir: flight-data}", base=tmp_path)
    assert recorder_dir(m, "cn") == tmp_path / "flight-data" / "cn"  # beside the mission file
    raw: dict[str, Any] = {"recorder": {"dir": "flight-data"}}
    relocate_mission(raw, tmp_path / "m.yaml")  # a copy elsewhere records in the same place
    assert raw["recorder"]["dir"] == str(tmp_path / "flight-data")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    if os.geteuid() != 0:
        assert recorder_dir(mission(), "dn0") == (
            tmp_path / "state" / "zplatform" / "recorder" / "minimal" / "dn0"
        )
    monkeypatch.setenv(RECORDER_DIR_ENV, str(tmp_path / "env"))
    assert recorder_dir(m, "cn") == tmp_path / "env" / "minimal" / "cn"


def test_recorded_frames_are_the_telemetry_channels() -> None:
    # What the ground checks them with: the telemetry channel's tag.
    tm = Telemetry()
    keys(tm.mission, "tool").channel("telemetry").open(tm.frame(1))


# ---------------------------------------------------------------- the command


def test_log_from_recorder_mistakes_are_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from zplatform.cli.main import main

    m = tmp_path / "m.yaml"
    m.write_text(MINIMAL + "\nrecorder: {}\n")
    out = str(tmp_path / "x.csv")
    cases = [
        (["--from-recorder", str(tmp_path / "nope")], "no recorder directory"),
        (["--from-recorder", str(m)], "is not a directory"),
        (["--from-recorder", str(tmp_path), "--duration", "3"], "--duration is for a live log"),
    ]
    for extra, message in cases:
        assert main(["log", str(m), "--out", out, *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("zplatform: error: ") and message in err and err.count("\n") == 1


def test_log_from_recorder_writes_the_files_and_names_the_damage(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from zplatform.cli.main import main

    monkeypatch.setenv("ZPLATFORM_KEY", KEY.hex())
    m = tmp_path / "m.yaml"
    m.write_text(MINIMAL + "\nrecorder: {}\n")
    tm = Telemetry()
    rec = recorder(tmp_path / "cn", tm)
    frames = dict(tm.frames(1, 30))
    for n, f in frames.items():
        rec.frame(n, f)
    rec.close()
    seg = sorted((tmp_path / "cn").glob("seg-*.zfr"))[0]
    data = bytearray(seg.read_bytes())
    data[data.index(frames[10]) + 30] ^= 1
    seg.write_bytes(bytes(data))
    assert (
        main(
            [
                "log",
                str(m),
                "--from-recorder",
                str(tmp_path / "cn"),
                "--out",
                str(tmp_path / "t.csv"),
            ]
        )
        == 0
    )
    out, err = capsys.readouterr()
    assert "29 snapshot(s) (loops 1..30)" in out and "1 damaged record(s)" in out
    assert (
        err.startswith(f"zplatform log: {seg.name}: offset ") and "checksum does not match" in err
    )
    assert (tmp_path / "t.events.jsonl").exists()


def test_export_reads_one_run_of_several(tmp_path: Path) -> None:
    """Two runs in one directory: every run by default (named), or one by id or 'last'."""
    tm = Telemetry()
    tool = keys(tm.mission, "tool")
    for run, loops in ((EPOCH, (1, 30)), (EPOCH + 10**12, (1, 20))):
        rec = FlightRecorder(
            tmp_path,
            head(run=run),
            **{
                "max_bytes": 1 << 20,
                "file_bytes": 64 * 1024,
                "fsync_ms": None,
                "buffer_bytes": 1 << 20,
                "max_record": len(tm.frame(0)),
                "interval_s": 0.001,
            },
        )
        for n, f in tm.frames(*loops):
            assert rec.frame(n, f)
        rec.close()
    s = export(tmp_path, tm.mission, tool, tmp_path / "all.csv", None)
    assert (s.rows, s.runs, s.run_ids, s.picked) == (50, 2, (EPOCH, EPOCH + 10**12), None)
    s = export(tmp_path, tm.mission, tool, tmp_path / "one.csv", None, run=EPOCH)
    assert (s.rows, s.first_loop, s.last_loop, s.runs, s.picked) == (30, 1, 30, 1, EPOCH)
    s = export(tmp_path, tm.mission, tool, tmp_path / "last.csv", None, run="last")
    assert (s.rows, s.last_loop, s.picked) == (20, 20, EPOCH + 10**12)
    with pytest.raises(RecordingError, match=r"holds no run 7 \(its runs: "):
        export(tmp_path, tm.mission, tool, tmp_path / "x.csv", None, run=7)


def test_the_recorder_server_refuses_a_replayed_request() -> None:
    """A genuine request is served once: the same request again (a replay
    within its stamp's bound) is refused unserved and counted (in zenoh's
    callback, never in hand: issue 25); a new request for the same loops,
    stamped later, is served."""
    from zplatform.core.auth import channel
    from zplatform.recorder.format import REQUEST, REQUEST_MAGIC
    from zplatform.recorder.server import RecorderServer

    m = mission()
    ch = channel(keys(m), "telemetry")
    assert ch is not None
    rec: Any = type("R", (), {"run": -1})()  # never the run asked: no file is read
    server = RecorderServer(
        FakeSession(),  # type: ignore[arg-type]
        "v/cn/recorder",
        rec,
        channel(keys(m), "telemetry"),
        now_ns=lambda: EPOCH,
        max_age_ns=10**9,
        serve_bps=10**9,
    )
    server.close()

    def serve(t_ns: int) -> FakeQuery:
        (q,) = deliver(server, bytes(ch.seal(REQUEST.pack(REQUEST_MAGIC, 7, 1, 5, t_ns))))
        return q

    first = serve(EPOCH)
    assert first.replies and server.served == 1
    again = FakeQuery(first.payload.to_bytes())
    server.on_query(again)  # type: ignore[arg-type]
    assert again.dropped and not server._pending
    assert again.replies == [] and server.served == 1 and server.refused == 1
    assert "replay" in server.last_refusal
    assert serve(EPOCH + 1).replies and server.served == 2 and server.refused == 1


@pytest.mark.parametrize(("fmt", "channel", "readable"), [(1, None, True), (1, "telemetry", False)])
def test_a_segment_of_the_tag_without_a_header_tag_is_read_only_untagged(
    fmt: int, channel: str | None, readable: bool
) -> None:
    """Format 1's frames carry the 24-byte tag of before the header tag
    (codecs/FORMAT.md §6.1): a segment of untagged frames (an archive's)
    is read as before; a tagged one is refused by name, never misread."""
    import json as _json

    from zplatform.errors import RecordingError as _RecordingError
    from zplatform.recorder.format import FORMAT_VERSION
    from zplatform.recorder.reader import SegmentHead

    meta = {
        "format": fmt,
        "mission": "m",
        "vehicle": "rocket",
        "node": "cn",
        "run": 1,
        "kind": "telemetry",
        "layout_id": 7,
        "channel": channel,
        "period_ns": 10_000_000,
        "telemetry_divisor": 1,
        "created_unix_ns": 1,
    }
    payload = _json.dumps(meta).encode()
    if readable:
        assert SegmentHead.parse(Path("seg"), 1, payload).channel is None
    else:
        with pytest.raises(_RecordingError, match="earlier zplatform's authentication tag"):
            SegmentHead.parse(Path("seg"), 1, payload)
    meta.update(format=FORMAT_VERSION, channel="telemetry")
    assert SegmentHead.parse(Path("seg"), 1, _json.dumps(meta).encode()).channel == "telemetry"
