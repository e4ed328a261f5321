"""Parameters on real processes: PRM_SAVE killed at every write step, and a
parameter set from the command line changing a controller's output live,
saved, recorded and replayed, and loaded by the next start."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from tests.waits import wait_until
from zplatform import ControlLogic, decode_mission
from zplatform.config.codes import ParamLoad
from zplatform.control.params import (
    SAVE_STEPS,
    ParamTable,
    decode_params,
    encode_params,
    read_params_file,
    write_atomic,
)
from zplatform.sim.lockstep import replay

from .harness import ROOT, Cluster

pytestmark = pytest.mark.timeout(240)

# -- kill -9 at every step of PRM_SAVE's write ------------------------------------

KILL_MISSION = """
mission: prmkill
nodes: {cn: {}}
params:
  - {name: gain, type: f64, default: 1.0, min: 0, max: 1000}
  - {name: steps, type: u32, default: 10, min: 1, max: 100000}
regions: {cn: [{name: x, type: u8}]}
"""
OLD = {"gain": 1.25, "steps": 7}
NEW = {"gain": 987.5, "steps": 99999}

# The child saves NEW with write_atomic's own hook killing it (SIGKILL, no
# clean-up of any kind) when the save reaches the named step.
CHILD = """
import os, signal, sys
from zplatform import decode_mission
from zplatform.control.params import encode_params, write_atomic
mission = decode_mission(sys.argv[1])
path, kill_at = sys.argv[2], sys.argv[3]
def step(name):
    if name == kill_at:
        os.kill(os.getpid(), signal.SIGKILL)
write_atomic(path, encode_params(mission, {"gain": 987.5, "steps": 99999}, seq=2), step=step)
print("saved")
"""


def _save_in_child(path: Path, kill_at: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", CHILD, KILL_MISSION, str(path), kill_at],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )


def _loaded(path: Path) -> tuple[ParamLoad, dict[str, object]]:
    """What a control node's start makes of the file: its status and values."""
    m = decode_mission(KILL_MISSION)
    cn = ControlLogic(m, keys=None)
    table: ParamTable = cn.params
    status = table.load(read_params_file(path), 0, source=str(path))
    return status, table.values()


@pytest.mark.no_mission
@pytest.mark.parametrize("kill_at", SAVE_STEPS)
def test_a_kill_at_any_step_of_a_save_leaves_the_old_file_or_the_new(
    tmp_path: Path, kill_at: str
) -> None:
    m = decode_mission(KILL_MISSION)
    path = tmp_path / "params" / "prmkill.params"
    write_atomic(path, encode_params(m, OLD, seq=1))
    p = _save_in_child(path, kill_at)
    assert p.returncode == -signal.SIGKILL, p.stdout + p.stderr
    status, values = _loaded(path)
    assert status == ParamLoad.LOADED  # never CORRUPT
    renamed = SAVE_STEPS.index(kill_at) >= SAVE_STEPS.index("renamed")
    assert values == (NEW if renamed else OLD)
    # A torn temporary file is left at most; it never stands in for the file,
    # and the next save writes over it (the lock died with the process).
    files = {"prmkill.params", ".prmkill.params.lock"}
    assert {q.name for q in path.parent.iterdir()} <= files | {".prmkill.params.tmp"}
    p = _save_in_child(path, "never")
    assert p.returncode == 0 and p.stdout == "saved\n", p.stderr
    assert _loaded(path) == (ParamLoad.LOADED, NEW)
    assert {q.name for q in path.parent.iterdir()} == files


@pytest.mark.no_mission
def test_two_writers_of_one_file_take_turns(tmp_path: Path) -> None:
    """A writer that holds the file's lock (stopped at "partial", its temporary
    file half written) keeps another from touching the temporary file; the
    other writes once the first is done, and the file is whole."""
    m = decode_mission(KILL_MISSION)
    path = tmp_path / "prmkill.params"
    write_atomic(path, encode_params(m, OLD, seq=1))
    first = subprocess.Popen(
        [sys.executable, "-c", CHILD.replace("SIGKILL", "SIGSTOP"), KILL_MISSION, str(path),
         "partial"],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        tmp = path.with_name(".prmkill.params.tmp")

        def saving() -> bool:  # the first is inside its save (a file it writes)
            assert first.poll() is None, "the first writer exited"
            return tmp.exists() and tmp.stat().st_size > 0

        wait_until(saving, 60, "the first writer inside its save")
        done = threading.Event()
        second = threading.Thread(
            target=lambda: (write_atomic(path, encode_params(m, OLD, seq=3)), done.set())
        )
        second.start()
        assert not done.wait(0.5)  # it waits for the lock, and has not truncated the file
        assert _loaded(path) == (ParamLoad.LOADED, OLD)
        first.send_signal(signal.SIGCONT)
        assert first.wait(timeout=60) == 0
        second.join(timeout=60)
        assert done.is_set()
        assert decode_params(m, path.read_bytes()).seq == 3  # the second wrote last, whole
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()


@pytest.mark.no_mission
def test_a_kill_before_the_first_save_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "prmkill.params"
    for kill_at in SAVE_STEPS[: SAVE_STEPS.index("renamed")]:
        p = _save_in_child(path, kill_at)
        assert p.returncode == -signal.SIGKILL
        status, values = _loaded(path)
        assert status == ParamLoad.MISSING and values == {"gain": 1.0, "steps": 10}


# -- a parameter changes a controller's output, live ---------------------------------

LIVE_MISSION = """
mission: prmlive
loop_hz: 100
nodes:
  cn: {listen: ["tcp/127.0.0.1:7600"]}
  gn: {listen: ["tcp/127.0.0.1:7601"], connect: ["tcp/127.0.0.1:7600"]}
params:
  - {name: gain, type: f32, default: 1.5, min: 0, max: 10, units: 1/s, states: [IDLE],
     doc: "y = gain * u"}
  - {name: limit, type: f32, default: 100, min: 10, max: 200, states: [IDLE], hazardous: true}
regions:
  cn:
    - {name: u, type: f32, initial: 2.0}
    - {name: y, type: f32}
state_machine:
  initial: IDLE
  states:
    IDLE:
      transitions:
        - {element: cn_cmd, op: "==", value: LAUNCH, to: RUN}
    RUN: {}
controllers:
  - {name: amp, class: "prmlive:Gain", node: cn, initial_mode: enabled,
     config: {gain: gain, u: u, y: y}}
commands:
  whitelist:
    IDLE: [NOOP, ARM, LAUNCH, PRM_SET, PRM_SAVE]
    RUN: [NOOP, ARM, PRM_SET, PRM_SAVE]
"""

GAIN = '''
"""y = gain * u, the gain a number or an element (a parameter), read every loop."""
import msgspec
from zplatform.control.controllers import Controller

class Gain(Controller):
    class Config(msgspec.Struct, forbid_unknown_fields=True):
        gain: float | str
        u: str
        y: str

    def bind(self, dv):
        self._gain = self.tunable(self.config.gain, "gain")
        self._u = self.input(self.config.u, "u")
        self._y = self.output(self.config.y, "y")

    def run_enabled(self, t_ns):
        self._y.set(self._gain.get() * self._u.get())

    def run_safed(self, t_ns):
        self._y.set(0.0)
'''


def _zp(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=90,
        env=dict(os.environ, **env),
    )


def _stop(c: Cluster, name: str) -> None:
    """Stop a node cleanly (SIGTERM: its last loop, its files closed)."""
    p = c.procs.pop(name)
    p.terminate()
    assert p.wait(timeout=30) == 0, c.log(name)[-3000:]


def test_prm_set_from_the_command_line_changes_a_controller_live_and_persists(
    tmp_path: Path,
) -> None:
    (tmp_path / "prmlive.py").write_text(GAIN)
    (tmp_path / "src.yaml").write_text(textwrap.dedent(LIVE_MISSION))
    env = {"ZPLATFORM_PARAMS_DIR": str(tmp_path / "params")}
    file = tmp_path / "params" / "prmlive.params"
    rec = tmp_path / "rec"
    with Cluster(tmp_path / "src.yaml", tmp_path) as c:
        path = str(c.path)
        c.spawn("cn", "--record", str(rec), env=env)
        c.wait_for(lambda dv: dv.get("y") == 3.0, 60, "y = 1.5 * 2")
        assert c.tm.get_name("cn_prm_load_status") == "MISSING"

        r = _zp("params", path, env=env)
        assert r.returncode == 0, r.stdout + r.stderr
        lines = r.stdout.splitlines()
        assert lines[0].startswith("prmlive: live telemetry, loop ") and "MISSING" in lines[0]
        assert lines[1].split() == ["NAME", "VALUE", "DEFAULT", "BOUNDS", "STATES"]
        assert lines[2].split() == ["gain", "1.5", "1.5", "[0,", "10]", "1/s", "IDLE"]
        assert lines[3].split() == ["limit", "100", "100", "[10,", "200]", "IDLE", "hazardous"]

        r = _zp("cmd", path, "prm_set", "gain", "2.5", env=env)
        assert r.returncode == 0, r.stdout + r.stderr
        assert r.stdout.splitlines() == ["PRM_SET #1: ACCEPTED (gain = 2.5, was 1.5)"]
        c.wait_for(lambda dv: dv.get("y") == 5.0, 30, "y = 2.5 * 2")
        assert c.tm.get("cn_prm_unsaved") is True

        r = _zp("cmd", path, "prm_set", "gain", "11", env=env)  # refused before sending
        assert r.returncode == 2 and "11 is outside gain's bounds [0, 10] 1/s" in r.stderr
        r = _zp("params", path, "limit", "150", env=env)
        assert r.returncode == 2 and "parameter limit is hazardous" in r.stderr, r.stderr
        r = _zp("params", path, "limit", "150", "--arm", "--save", env=env)
        assert r.returncode == 0, r.stdout + r.stderr
        assert r.stdout.splitlines() == [
            "ARM #2: ACCEPTED",
            "PRM_SET #3: ACCEPTED (limit = 150.0, was 100.0)",
            "PRM_SAVE #4: ACCEPTED (queued: cn_prm_save_status tells when it is written)",
            f"PRM_SAVE #4: SAVED: parameters saved (PRM_SAVE #4) to {file}",
        ]
        saved = decode_params(c.mission, file.read_bytes())
        assert saved.values == {"gain": 2.5, "limit": 150.0} and saved.seq == 4
        c.wait_for(lambda dv: dv.get_name("cn_prm_save_status") == "SAVED", 10, "saved")
        assert c.tm.get("cn_prm_unsaved") is False

        r = _zp("cmd", path, "launch", env=env)
        assert r.returncode == 0, r.stdout + r.stderr
        r = _zp("cmd", path, "prm_set", "gain", "3", env=env)
        assert r.returncode == 1
        assert r.stdout.splitlines() == [
            "PRM_SET #6: REJECTED_PARAM_STATE: parameter gain may not change in state RUN "
            "(only in IDLE)"
        ]
        _stop(c, "cn")

        # The run replays bit for bit, the save's completion included.
        result = replay(rec, c.path)  # the operator names the mission: never the recording
        assert result.identical and result.complete, result.first_difference

        # The next start loads what was saved.
        c.spawn("cn", env=env)
        c.wait_for(lambda dv: dv.get_name("cn_prm_load_status") == "LOADED", 60, "loaded")
        c.wait_for(lambda dv: dv.get("y") == 5.0, 30, "y = 2.5 * 2 from the file")
        assert c.tm.get("limit") == 150.0
        _stop(c, "cn")

        # Not running: the listing reads this host's file.
        r = _zp("params", path, "--json", "--timeout", "5", env=env)
        assert r.returncode == 0, r.stdout + r.stderr
        assert '"live": false' in r.stdout and f"values saved in {file}" in r.stdout

        # A damaged file: every parameter at its default, and the CN says so.
        file.write_bytes(file.read_bytes()[:-1])
        c.spawn("cn", env=env)
        c.wait_for(lambda dv: dv.get_name("cn_prm_load_status") == "CORRUPT", 60, "corrupt")
        c.wait_for(lambda dv: dv.get("y") == 3.0, 30, "y at the default gain")
