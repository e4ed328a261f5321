"""The telemetry's two paths to a ground on the CN's host, without iceoryx2
(zplatform.runtime.tmiox, zplatform.control.intake.Dedupe): each frame
taken once, the other path's copy a duplicate (never a refusal), a
replay still refused; the path and its fallbacks; ``up``'s status line."""

from __future__ import annotations

import os
import time
from pathlib import Path

import msgspec

from zplatform.cli import supervisor
from zplatform.control.intake import DEDUPE_WINDOW, IOX, ZENOH, Dedupe, TelemetryIntake
from zplatform.control.loop import ControlLogic
from zplatform.core.auth import KEY_ENV, KeySet, Run, channel, new_run_epoch
from zplatform.core.events import EV
from zplatform.mission.load import load_mission
from zplatform.runtime.tmiox import STALE_FRAMES, TelemetryPaths, telemetry_path_wanted
from zplatform.telemetry.records import EventRecord

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
MAX_AGE_NS = 5 * 10**9


class _Payload:
    def __init__(self, b: bytes) -> None:
        self._b = b

    def __len__(self) -> int:
        return len(self._b)

    def to_bytes(self) -> bytes:
        return self._b


def _frames(n: int, *, keyed: bool = True) -> tuple[TelemetryIntake, list[bytes]]:
    m = load_mission(CONFIGS / "minimal.yaml")
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV])) if keyed else None
    run = new_run_epoch(time.time_ns())
    logic = ControlLogic(m, keys=keys, epoch=run)
    frames = []
    for loop in range(1, n + 1):
        logic.begin(loop, time.time_ns())
        tm = logic.finish()
        assert tm is not None
        frames.append(bytes(tm))
    intake = TelemetryIntake(m, channel(keys, "telemetry", Run(run)), 64, MAX_AGE_NS, dedupe=True)
    return intake, frames


def test_the_other_paths_copy_is_a_duplicate_and_a_further_copy_is_refused() -> None:
    for keyed in (True, False):
        intake, (f1, f2) = _frames(2, keyed=keyed)
        now = time.time_ns()
        assert intake.admit_view(memoryview(f1), now, IOX)
        assert not intake.admit(_Payload(f1), now, ZENOH)  # zenoh's copy
        assert intake.duplicates == 1 and intake.take_counts() == (0, 0, 0)
        # A third copy on either path goes through the intake: with keys it
        # is refused there as not fresh (without, the ground's logic refuses
        # it as not newer, as any replay).
        third = [
            intake.admit(_Payload(f1), now, ZENOH),
            intake.admit_view(memoryview(f1), now, IOX),
        ]
        assert intake.duplicates == 1
        if keyed:
            assert third == [False, False] and intake.take_counts() == (0, 0, 2)
        else:
            assert third == [True, True]
        # zenoh first, then iceoryx2: the same, the other way round.
        assert intake.admit(_Payload(f2), now, ZENOH)
        assert not intake.admit_view(memoryview(f2), now, IOX)
        assert intake.duplicates == 2
        assert intake.box is not None and len(intake.box) == (2 if keyed else 4)


def test_a_copy_with_another_tag_is_no_duplicate_and_is_refused_as_bad() -> None:
    intake, (f1,) = _frames(1)
    now = time.time_ns()
    assert intake.admit_view(memoryview(f1), now, IOX)
    forged = bytearray(f1)
    forged[-1] ^= 1  # the same loop and stamp, another tag
    assert not intake.admit(_Payload(bytes(forged)), now, ZENOH)
    assert intake.duplicates == 0 and intake.take_counts() == (0, 1, 0)
    # The genuine copy is still the other path's duplicate.
    assert not intake.admit(_Payload(f1), now, ZENOH) and intake.duplicates == 1


def test_a_late_copy_within_the_window_is_a_duplicate_not_a_stale_refusal() -> None:
    intake, frames = _frames(DEDUPE_WINDOW + 1)
    now = time.time_ns()
    for f in frames:  # iceoryx2 brought them all before zenoh's first came
        assert intake.admit_view(memoryview(f), now, IOX)
    # The first frame's slot was taken by the last one: that copy is no
    # longer told from a replay; every other one is a duplicate.
    for f in frames[1:]:
        assert not intake.admit(_Payload(f), now, ZENOH)
    assert intake.duplicates == DEDUPE_WINDOW and intake.take_counts() == (0, 0, 0)
    # Each path's admissions are counted (the ground's path and counters).
    assert (intake.taken_iox, intake.taken_zenoh) == (DEDUPE_WINDOW + 1, 0)
    assert not intake.admit(_Payload(frames[0]), now, ZENOH)  # slot reused: a replay
    assert intake.taken_zenoh == 0 and intake.take_counts() == (0, 0, 1)


def test_dedupe_never_takes_a_frame_without_the_fixed_header() -> None:
    d = Dedupe()
    assert not d.repeat(b"\x00" * 100, ZENOH)
    d.note(b"\x00" * 100, IOX)  # nothing noted
    assert not d.repeat(b"\x00" * 100, ZENOH)


def test_the_path_follows_the_frames_and_falls_back_once() -> None:
    p = TelemetryPaths()
    assert p.update(0, 1, 1, "") is None and p.path == "zenoh"
    assert p.update(1, 1, 1, "") == ("iox", "a frame over it passed the intake")
    assert p.update(1, 2, 1, "") is None  # zenoh won one race: not a stall
    assert p.update(2, 2, 1, "") is None and p.path == "iox"
    for i in range(STALE_FRAMES - 1):
        assert p.update(2, 3 + i, 1, "") is None
    change = p.update(2, 2 + STALE_FRAMES, 1, "")
    assert change is not None and change[0] == "zenoh" and p.fallbacks == 1
    assert p.update(2, 3 + STALE_FRAMES, 1, "") is None  # on zenoh: no more events
    assert p.update(3, 3 + STALE_FRAMES, 1, "") == ("iox", "a frame over it passed the intake")
    # The publisher gone: the first frame zenoh brings says so.
    change = p.update(3, 4 + STALE_FRAMES, 0, "")
    assert change == ("zenoh", "the control node's iceoryx2 publisher is gone")
    assert p.fallbacks == 2


def test_the_publisher_gone_at_the_runs_end_is_no_fallback() -> None:
    p = TelemetryPaths()
    assert p.update(5, 5, 1, "") is not None
    assert p.update(5, 5, 0, "") is None and p.path == "iox"  # nothing more came


def test_a_failed_receiver_falls_back_once_and_stays_on_zenoh() -> None:
    p = TelemetryPaths()
    p.update(1, 0, 1, "")
    change = p.update(1, 0, 1, "broken")
    assert change is not None and change[0] == "zenoh" and "broken" in change[1]
    assert p.update(2, 1, 1, "broken") is None and p.path == "zenoh"


def test_up_shows_the_grounds_telemetry_path_from_its_events() -> None:
    m = load_mission(CONFIGS / "minimal.yaml")
    assert telemetry_path_wanted(m)
    w = supervisor.Watch()
    assert supervisor.telemetry_path(m, w) == "  tm=zenoh"
    w.on_event(EventRecord(0, "gn", 0, 0, "INFO", EV.TM_ON_SHM.name, "x"))
    assert supervisor.telemetry_path(m, w) == "  tm=iox"
    w.on_event(EventRecord(0, "cn", 1, 0, "INFO", EV.TM_FALLBACK.name, "x"))  # not the ground's
    assert supervisor.telemetry_path(m, w) == "  tm=iox"
    w.on_event(EventRecord(0, "gn", 2, 0, "INFO", EV.TM_FALLBACK.name, "x"))
    assert supervisor.telemetry_path(m, w) == "  tm=zenoh"
    pinned = msgspec.structs.replace(
        m, transport=msgspec.structs.replace(m.transport, intra_host="zenoh")
    )
    assert supervisor.telemetry_path(pinned, w) == ""
