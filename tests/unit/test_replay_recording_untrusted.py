"""A recording is a file someone handed over (issue 18, item 7): reading or
replaying one never imports code it names, never hangs on a FIFO or reads a
device, allocates only what the mission allows, and ends every malformed
recording in one RecordingError (``zplatform: error: ...``, exit 2).

The crafted recordings are built here, byte for byte, around a real one (the
minimal mission, recorded through :class:`zplatform.Recorder` with a DN
answering). The "evil" mission names a controller and a device in a module,
next to the recording, that leaves a mark when imported. The fuzz test
(hypothesis, bounded) throws truncations, flipped bytes, huge lengths, wrong
types and short items at the reader and the replay.
"""

from __future__ import annotations

import os
import shutil
import stat
import struct
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zplatform import ControlLogic, Recorder, load_mission, replay
from zplatform.cli.main import main
from zplatform.config.codes import CommandStatus
from zplatform.control.loop import DeviceLogic
from zplatform.core.auth import load_keys
from zplatform.core.datavector import Layout
from zplatform.errors import RecordingError
from zplatform.mission.load import decode_mission
from zplatform.sim.replay_recording import (
    MAX_META_BYTES,
    MAX_MISSION_BYTES,
    MISSION_FILE,
    RECORD_FILE,
    VERSION,
    RecordMeta,
    RecordReader,
    mission_digest,
    read_recording,
)

_N_STATUS = len(CommandStatus)  # the first status that is none (codes.py appends new ones)

ROOT = Path(__file__).resolve().parents[2]
MINIMAL = ROOT / "configs" / "minimal.yaml"
LOOPS = 12

EVIL_CODE = """
import os
open(os.environ["ZP_EVIL_MARK"], "a").write("imported\\n")
raise SystemExit("evil code ran")
"""
EVIL_SECTIONS = """
controllers:
  - {name: evil, class: "evil_mod:Ctl", node: cn}
devices:
  - {name: evil_dev, class: "evil_mod:Dev", node: dn0}
"""

_HEAD = struct.Struct("<6sHI")
_ITEM = struct.Struct("<BBI")
# FINISH: sync_overrun, loop_overruns, inbox_dropped, the intake's refusals, the
# querier recoveries
_FINISH = struct.Struct("<BII7IBQIIII")


@pytest.fixture(autouse=True)
def evil_mark(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Where the evil module writes if anything ever imports it."""
    mark = tmp_path / "evil-was-imported"
    monkeypatch.setenv("ZP_EVIL_MARK", str(mark))
    yield mark
    assert not mark.exists(), "a module a recording named was imported"
    assert "evil_mod" not in sys.modules


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real recording of the minimal mission: LOOPS loops, dn0 answering."""
    d = tmp_path_factory.mktemp("real") / "rec"
    m = load_mission(MINIMAL)
    cn = ControlLogic(m, keys=load_keys(m, "cn"), epoch=1)
    dn = DeviceLogic(m, "dn0", keys=load_keys(m, "dn0"))
    rec = Recorder(d, m, MINIMAL, cn.dv)
    cn.recorder = rec
    for n in range(1, LOOPS + 1):
        t = n * m.period_ns
        (frame,) = cn.begin(n, t, final=n == LOOPS)
        cn.reply(0, dn.step(frame, t))
        cn.finish()
    rec.close()
    assert replay(d, MINIMAL).identical
    return d


@pytest.mark.parametrize(("state", "tis"), [(99, 0), (255, 0), (0, -5)])
def test_a_first_vector_no_control_node_could_write_is_refused(
    tmp_path: Path, state: int, tis: int
) -> None:
    """A recording that starts mid-run (cn_loop above 0) names a state the
    mission does not have, or a negative time in it: the replay refuses it
    with RecordingError (found by the fuzz below beside a CPU hog: the
    replay's adopt raised IndexError)."""
    d = tmp_path / "rec"
    m = load_mission(MINIMAL)
    cn = ControlLogic(m, keys=load_keys(m, "cn"), epoch=1)
    cn.dv.set("cn_loop", 5)
    # Raw bytes, as a damaged file holds them (set() refuses an unknown state).
    cn.dv.buf[cn.dv.layout.elements["cn_state"].offset] = state
    cn.dv.set("cn_time_in_state_ns", tis)
    rec = Recorder(d, m, MINIMAL, cn.dv)
    rec.close()
    with pytest.raises(RecordingError, match="cannot be taken up"):
        replay(d, MINIMAL)


def _header(mission_text: str, pythonpath: Path | None = None) -> tuple[bytes, str]:
    """A consistent header for ``mission_text`` (loaded without its code),
    and the text as it is written beside it."""
    if pythonpath is not None:
        mission_text += f"pythonpath: [{str(pythonpath)!r}]\n"
    m = decode_mission(mission_text, code=False)
    layout = Layout.for_node(m, "cn")
    meta = msgspec.json.encode(
        RecordMeta(
            mission=m.mission,
            layout_id=layout.layout_id,
            size=layout.size,
            period_ns=m.period_ns,
            device_nodes=m.device_nodes,
            telemetry_divisor=m.telemetry_divisor,
            mission_digest=mission_digest(m),
            created_unix_s=0.0,
        )
    )
    head = _HEAD.pack(b"ZPREC\x00", VERSION, len(meta)) + meta
    return head + struct.pack("<I", layout.size) + bytes(layout.size), mission_text


def _evil(d: Path, items: bytes = b"") -> Path:
    """A recording whose mission names evil_mod, which sits beside it."""
    d.mkdir(parents=True, exist_ok=True)
    (d / "evil_mod.py").write_text(EVIL_CODE)
    head, text = _header(MINIMAL.read_text() + EVIL_SECTIONS, pythonpath=d)
    (d / MISSION_FILE).write_text(text)
    (d / RECORD_FILE).write_bytes(head + items)
    return d


def _copy(real: Path, dst: Path) -> Path:
    shutil.copytree(real, dst)
    return dst


def _zp(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )


def _refused(r: subprocess.CompletedProcess[str], words: str) -> None:
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.startswith("zplatform: error: ") and r.stderr.count("\n") == 1, r.stderr
    assert "Traceback" not in r.stderr and words in r.stderr, r.stderr


# ---------------------------------------------------------------------------
# no code from a recording


def test_a_recording_s_own_code_is_never_imported(tmp_path: Path, evil_mark: Path) -> None:
    d = _evil(tmp_path / "rec")
    # Bare: a replay needs the mission file.
    _refused(_zp("replay", str(d)), "pass the mission file that was recorded (--mission FILE)")
    # What needs no code works, and imports nothing.
    r = _zp("replay", str(d), "--list")
    assert r.returncode == 0 and "recording of minimal: loops 0..0 (0 loops" in r.stdout, r
    # Another mission file: refused, naming the first difference.
    r = _zp("replay", str(d), "--mission", str(MINIMAL))
    _refused(r, "a recording of another mission than the one given (first at `$.controllers`")
    with pytest.raises(RecordingError, match="another mission"):
        replay(d, MINIMAL)
    s = read_recording(d)
    assert (s.mission, s.loops) == ("minimal", 0)
    assert not evil_mark.exists()


def test_the_recorded_mission_must_be_the_operator_s(real: Path, tmp_path: Path) -> None:
    """Where it runs does not matter (ports, pythonpath: a copy on free
    ports replays with the shipped file); what its loop does does."""
    moved = _copy(real, tmp_path / "moved")
    text = (moved / MISSION_FILE).read_text().replace("127.0.0.1:746", "127.0.0.1:956")
    (moved / MISSION_FILE).write_text(text)
    assert replay(moved, MINIMAL).identical
    other = tmp_path / "other.yaml"
    other.write_text(MINIMAL.read_text().replace("loop_hz: 100", "loop_hz: 50"))
    with pytest.raises(RecordingError, match=r"first at `\$.loop_hz`: recorded 100.0, the "):
        replay(real, other)
    # A header that is not of the mission.yaml beside it.
    forged = _copy(real, tmp_path / "forged")
    (forged / MISSION_FILE).write_text(MINIMAL.read_text().replace("loop_hz: 100", "loop_hz: 50"))
    with pytest.raises(RecordingError, match=r"the header is not of the mission\.yaml beside it"):
        RecordReader(forged)


def test_list_and_log_read_a_recording_without_its_code(real: Path, tmp_path: Path) -> None:
    r = _zp("replay", str(real), "--list", "--log", str(tmp_path / "tm.csv"))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("loop        1  t 10000000  replies [dn0=")
    assert lines[LOOPS - 1].endswith("final") and lines[LOOPS].startswith(
        f"recording of minimal: loops 1..{LOOPS} ({LOOPS} loops, {LOOPS} telemetry frames ->"
    )
    assert "pass the recorded mission's file (--mission FILE)" in lines[-1]
    rows = (tmp_path / "tm.csv").read_text().splitlines()
    assert len(rows) == LOOPS + 1 and "cn_loop" in rows[0]
    r = _zp("replay", str(real), "--mission", str(MINIMAL))
    assert r.returncode == 0 and "bit-identical" in r.stdout, r.stdout + r.stderr


# ---------------------------------------------------------------------------
# files that are not what they say


@pytest.mark.timeout(30)
@pytest.mark.parametrize("name", [RECORD_FILE, MISSION_FILE])
def test_fifos_devices_and_symlinks_are_refused_at_once(
    real: Path, tmp_path: Path, name: str
) -> None:
    d = _copy(real, tmp_path / "rec")
    (d / name).unlink()
    os.mkfifo(d / name)  # nobody ever writes it: a blocking open would hang
    with pytest.raises(RecordingError, match=f"{name} is not a regular file"):
        RecordReader(d)
    (d / name).unlink()
    (d / name).symlink_to("/dev/zero")
    with pytest.raises(RecordingError, match=f"{name} is a symbolic link"):
        RecordReader(d)
    (d / name).unlink()
    (d / name).symlink_to(real / name)  # the same bytes, outside the directory
    with pytest.raises(RecordingError, match="symbolic link"):
        RecordReader(d)
    (d / name).unlink()
    try:
        os.mknod(d / name, stat.S_IFCHR | 0o600, os.makedev(1, 5))  # /dev/zero itself
    except PermissionError:
        pytest.skip("mknod needs root")
    with pytest.raises(RecordingError, match=f"{name} is not a regular file"):
        RecordReader(d)
    _refused(_zp("replay", str(d), "--mission", str(MINIMAL)), "is not a regular file")


def test_sizes_are_checked_before_anything_is_read(real: Path, tmp_path: Path) -> None:
    d = _copy(real, tmp_path / "rec")
    with open(d / MISSION_FILE, "r+b") as f:  # sparse: huge, and no disk used
        f.truncate(MAX_MISSION_BYTES + 1)
    with pytest.raises(RecordingError, match=f"is {MAX_MISSION_BYTES + 1} bytes; at most"):
        RecordReader(d)
    d = _copy(real, tmp_path / "meta")
    data = bytearray((d / RECORD_FILE).read_bytes())
    struct.pack_into("<I", data, 8, 0xFFFF_FFFF)  # the metadata's length
    (d / RECORD_FILE).write_bytes(data)
    with pytest.raises(RecordingError, match=f"at most {MAX_META_BYTES}"):
        RecordReader(d)


def test_a_yaml_alias_bomb_is_refused_unexpanded(tmp_path: Path) -> None:
    d = tmp_path / "rec"
    head, text = _header(MINIMAL.read_text())
    # A billion laughs: ten lists of ten aliases of the one before.
    bomb = "doc_parts:\n  l0: &l0 [x, x, x, x, x, x, x, x, x, x]\n"
    for i in range(1, 9):
        bomb += f"  l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]\n"
    d.mkdir()
    (d / MISSION_FILE).write_text(text + bomb)
    (d / RECORD_FILE).write_bytes(head)
    with pytest.raises(RecordingError, match="YAML aliases"):
        RecordReader(d)


# ---------------------------------------------------------------------------
# malformed content: one clear error, whatever it is


def _items(*items: tuple[int, int, bytes]) -> bytes:
    return b"".join(_ITEM.pack(t, dn, len(b)) + b for t, dn, b in items)


BEGIN = (1, 0, struct.pack("<QqB", 1, 10_000_000, 0))
FINISH = (8, 0, bytes(_FINISH.size))


def test_a_health_block_in_a_mission_without_health_is_a_recording_error(
    tmp_path: Path,
) -> None:
    d = tmp_path / "rec"
    d.mkdir()
    head, text = _header(MINIMAL.read_text() + "health: null\n")
    (d / MISSION_FILE).write_text(text)
    (d / RECORD_FILE).write_bytes(head + _items(BEGIN, (12, 0, b"h")))
    with pytest.raises(RecordingError, match="a health block; the mission has no health"):
        list(RecordReader(d).loops())


@pytest.mark.parametrize(
    ("items", "words"),
    [
        (_items((1, 0, b"\x01\x02\x03")), "BEGIN of 3 bytes (exactly 17"),
        (_items(BEGIN, (8, 0, b"\x00")), f"FINISH of 1 bytes (exactly {_FINISH.size}"),
        (_items(BEGIN, (2, 7, b"x")), "a reply of DN 7; the mission has 1"),
        (_items(BEGIN, (2, 0, b"x" * 100_000)), "REPLY of 100000 bytes (at most"),
        (_ITEM.pack(7, 0, 0xFFFF_FFFF), "TELEMETRY of 4294967295 bytes (at most"),
        (_items(BEGIN, (42, 0, b"")), "unknown type 42"),
        (_items((2, 0, b"x")), "REPLY outside a loop"),
        (_items(BEGIN, BEGIN), "loop 1 never ends"),
        (_items(BEGIN, (7, 0, b"t"), (7, 0, b"t")), "loop 1: two telemetry frames"),
        (_items(BEGIN, *[(2, 0, b"r")] * 65), "loop 1: over 64 DN replies"),
        (_items(BEGIN, (10, 255, b"k")), "unknown type 10"),  # FOREIGN, before version 5
        (_items(BEGIN, (12, 0, b"h")), "HEALTH of 1 bytes (exactly "),
        (_items(BEGIN, (11, 0, b"\x01\x02\x03")), "PRM_SAVED of 3 bytes (at least 9)"),
        (_items(BEGIN, (11, 0, b"s" * 600)), "PRM_SAVED of 600 bytes (at most 521 "),
        # A refusal's status the loop would have to name (hypothesis found it:
        # a ValueError out of the control loop's refusal event, not this error).
        (
            _items(BEGIN, (8, 0, bytes(_FINISH.size - 25) + bytes([_N_STATUS]) + bytes(24))),
            f"loop 1: FINISH with command status {_N_STATUS} (at most {_N_STATUS - 1})",
        ),
    ],
)
def test_malformed_items_end_in_one_recording_error(
    tmp_path: Path, items: bytes, words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    d = tmp_path / "rec"
    d.mkdir()
    head, text = _header(MINIMAL.read_text())
    (d / MISSION_FILE).write_text(text)
    (d / RECORD_FILE).write_bytes(head + items)
    with pytest.raises(RecordingError, match=r"cn\.zrec: ") as ei:
        list(RecordReader(d).loops())
    assert words in str(ei.value)
    # `zplatform replay` says it in one line, exit 2: the command line's own
    # code, in this process (a process per case is test_a_recording_s_own_code_
    # is_never_imported's; the error path is the same for every case).
    code = main(["replay", str(d), "--mission", str(MINIMAL)])
    err = capsys.readouterr().err
    _refused(subprocess.CompletedProcess([], code, "", err), words)


def test_a_tail_cut_off_mid_item_is_an_incomplete_recording(real: Path, tmp_path: Path) -> None:
    """What a killed recorder leaves: replayed up to the cut, said so."""
    d = _copy(real, tmp_path / "rec")
    data = (d / RECORD_FILE).read_bytes()
    (d / RECORD_FILE).write_bytes(data[:-5])
    res = replay(d, MINIMAL)
    assert res.identical and not res.complete and res.loops == LOOPS - 1


# ---------------------------------------------------------------------------
# the fuzz


def _mutations() -> st.SearchStrategy[tuple[str, int, bytes]]:
    return st.tuples(
        st.sampled_from(["truncate", "flip", "overwrite", "insert"]),
        st.integers(min_value=0),
        st.binary(min_size=1, max_size=24),
    )


def _mutate(data: bytes, how: str, at: int, junk: bytes) -> bytes:
    at %= len(data) + 1
    if how == "truncate":
        return data[:at]
    if how == "flip":
        if not data:  # truncated to nothing already: no byte to flip
            return data
        b = bytearray(data)
        i = at % len(b)
        b[i] ^= junk[0] or 0xFF
        return bytes(b)
    if how == "overwrite":
        return data[:at] + junk + data[at + len(junk) :]
    return data[:at] + junk + data[at:]


ITEM_TYPES = st.integers(min_value=0, max_value=12)
LENGTHS = st.one_of(
    st.integers(min_value=0, max_value=40), st.sampled_from([0xFFFF_FFFF, 1 << 31, 65_537])
)


@st.composite
def _crafted_items(draw: st.DrawFn) -> bytes:
    """Items with any type, DN and declared length, bodies of any length."""
    out = b""
    for _ in range(draw(st.integers(min_value=1, max_value=8))):
        typ = draw(ITEM_TYPES)
        dn = draw(st.sampled_from([0, 1, 255]))
        n = draw(LENGTHS)
        body = draw(st.binary(max_size=min(n, 40)))
        out += _ITEM.pack(typ, dn, n) + body
    return out


@pytest.mark.timeout(300)
@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    evil=st.booleans(),
    mutations=st.lists(_mutations(), max_size=3),
    crafted=st.one_of(st.none(), _crafted_items()),
)
def test_any_damage_is_read_or_refused_never_crashes_nor_runs_its_code(
    real: Path,
    tmp_path_factory: pytest.TempPathFactory,
    evil: bool,
    mutations: list[tuple[str, int, bytes]],
    crafted: bytes | None,
) -> None:
    """Property: a damaged recording (the real one mutated, or crafted items
    after a valid header, with the evil mission or the real one) is replayed,
    read, or refused with RecordingError, and its code never runs."""
    d = tmp_path_factory.mktemp("fuzz") / "rec"
    if evil:
        _evil(d)
        data = (d / RECORD_FILE).read_bytes()
    else:
        _copy(real, d)
        data = (d / RECORD_FILE).read_bytes()
    if crafted is not None:
        data += crafted
    for how, at, junk in mutations:
        data = _mutate(data, how, at, junk)
    (d / RECORD_FILE).write_bytes(data)
    for read in (lambda: replay(d, MINIMAL), lambda: read_recording(d)):
        try:
            read()
        except RecordingError:
            pass
