"""The recorder's worst day: a disk that stalls. Loops that do not fit are
dropped and counted, the record says so, and a replay stops at the gap."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest

from zplatform import ControlLogic, Recorder, load_mission
from zplatform.errors import RecordingError
from zplatform.sim import replay_recording as recording
from zplatform.sim.replay_recording import RecordReader

ROOT = Path(__file__).resolve().parents[2]
MISSION = ROOT / "configs" / "minimal.yaml"


class _StallingFile:
    """A file whose writes block while ``stalled`` (a disk that stops)."""

    def __init__(self, real: Any) -> None:
        self.real = real
        self.go = threading.Event()
        self.go.set()

    def write(self, b: Any) -> int:
        self.go.wait()
        return int(self.real.write(b))

    def close(self) -> None:
        self.real.close()


def test_a_stalled_disk_drops_whole_loops_counted_and_marked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    files: list[_StallingFile] = []

    def stalling_open(path: Any, mode: str) -> _StallingFile:
        files.append(_StallingFile(open(path, mode)))  # noqa: SIM115 - closed by close()
        return files[-1]

    monkeypatch.setattr(recording, "open", stalling_open, raising=False)
    m = load_mission(MISSION)
    cn = ControlLogic(m, keys=None, epoch=1)
    rec = Recorder(tmp_path / "rec", m, MISSION, cn.dv, seconds=0.0)
    stalled = files[0]
    stalled.go.clear()  # the disk stops
    cn.recorder = rec
    loops = 3 * len(rec._chunks) * (rec.chunk_size // 64)  # far more than the ring holds
    for n in range(1, loops + 1):
        cn.begin(n, n * m.period_ns)
        cn.finish()  # the DN never answers: a miss, recorded like any input
    assert rec.dropped_loops > 0 and rec.loops + rec.dropped_loops == loops
    stalled.go.set()
    rec.close()
    reader = RecordReader(tmp_path / "rec")
    kept = list(reader.loops())
    assert kept and [r.loop for r in kept] == list(range(1, len(kept) + 1))  # no hole inside
    assert not reader.complete and reader.dropped_loops > 0  # the gap is in the record


def test_the_final_loop_flag_is_recorded_and_replayed(tmp_path: Path) -> None:
    """A run's last loop (dnX_final in its frames and telemetry) is an input
    of the loop like the others: the replay repeats it, bit for bit."""
    from zplatform import replay
    from zplatform.core.auth import load_keys

    m = load_mission(MISSION)
    cn = ControlLogic(m, keys=load_keys(m, "cn"), epoch=1)
    rec = Recorder(tmp_path / "rec", m, MISSION, cn.dv)
    cn.recorder = rec
    for n in (1, 2, 3):
        cn.begin(n, n * m.period_ns, final=n == 3)
        cn.finish()
    rec.close()
    assert [r.final for r in RecordReader(tmp_path / "rec").loops()] == [False, False, True]
    res = replay(tmp_path / "rec", MISSION)
    assert res.identical and res.loops == 3, res


@pytest.mark.parametrize("version", [2, 3, 4, 5, 7, 8, 9])
def test_a_recording_of_an_earlier_format_is_refused_by_name(tmp_path: Path, version: int) -> None:
    """Versions 2 to 4 end a loop without the intake's refusals, 2 to 5
    have no mission digest, 7's frames carry the tag without a header tag
    (codecs/FORMAT.md §6.1), 8's loops end without the frames dropped
    unchecked, 9's without the mirrors refused: refused with one error
    that says to record again, never misread."""
    m = load_mission(MISSION)
    cn = ControlLogic(m, keys=None, epoch=1)
    rec = Recorder(tmp_path / "rec", m, MISSION, cn.dv)
    cn.recorder = rec
    cn.begin(1, m.period_ns)
    cn.finish()
    rec.close()
    path = tmp_path / "rec" / recording.RECORD_FILE
    data = bytearray(path.read_bytes())
    data[6:8] = version.to_bytes(2, "little")  # the header's u16 version
    path.write_bytes(bytes(data))
    with pytest.raises(
        RecordingError, match=f"version {version}, made by an earlier zplatform.*record again"
    ):
        RecordReader(tmp_path / "rec")


def test_the_mirrors_refused_are_recorded_and_replayed(tmp_path: Path) -> None:
    """A redundant mission's ``cn_mirror_refused`` comes from an input of
    the loop (the refusals' ``mirror_refused``, in FINISH since version
    10): recorded, read back and replayed bit for bit."""
    from zplatform import replay
    from zplatform.control.intake import CnRefusals
    from zplatform.core.auth import load_keys

    flight = ROOT / "configs" / "flight.yaml"
    m = load_mission(flight)
    cn = ControlLogic(m, keys=load_keys(m, "cn"), epoch=1)
    rec = Recorder(tmp_path / "rec", m, flight, cn.dv)
    cn.recorder = rec
    for n, refused in ((1, 0), (2, 5), (3, 2)):
        r = CnRefusals()
        r.mirror_refused = refused
        cn.begin(n, n * m.period_ns)
        cn.finish(refused=r)
    rec.close()
    assert cn.dv.get("cn_mirror_refused") == 7
    assert [r.refused[-1] for r in RecordReader(tmp_path / "rec").loops()] == [0, 5, 2]
    res = replay(tmp_path / "rec", flight)
    assert res.identical and res.loops == 3, res
