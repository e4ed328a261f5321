"""The command line as a new user meets it: clear errors, no tracebacks, `ps`.

One test per rough edge: each checks the message a user sees, the exit
code, and that no traceback reaches stderr. The two tests that run a
mission (`up` registered in `ps`, found by name, events logged) wait on
files and telemetry, never on sleeps, and kill what they start.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.waits import wait_until
from zplatform import CommandError
from zplatform.cli import registry
from zplatform.cli import runtime as cli_runtime
from zplatform.cli.main import build_parser, main
from zplatform.core.events import Event, Severity, encode_event
from zplatform.runtime.transport import rewrite_endpoints

from .harness import CONFIGS, ROOT

pytestmark = pytest.mark.timeout(120)


def _zp(
    *args: str, env: dict[str, str] | None = None, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=dict(os.environ, **(env or {})),
    )


def _clear_error(r: subprocess.CompletedProcess[str], code: int, *phrases: str) -> None:
    assert r.returncode == code, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    assert ".rs:" not in r.stderr, r.stderr  # no Rust source paths
    for p in phrases:
        assert p in r.stderr, (p, r.stderr)


def _up_minimal(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """`up configs/minimal.yaml --free-ports --no-realtime --quiet ARGS`, its
    output piped (the caller ends it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "zplatform", "up", "configs/minimal.yaml", "--free-ports",
         "--no-realtime", "--quiet", *args],
        cwd=ROOT,
        env=env if env is not None else dict(os.environ, PYTHONUNBUFFERED="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip


@pytest.fixture
def runtime(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private registry directory (this process and its children)."""
    d = tmp_path / "run"
    monkeypatch.setenv(registry.ENV_DIR, str(d))
    return d


# ---------------------------------------------------------------- paths


def test_up_log_to_a_missing_directory_is_refused_before_spawning() -> None:
    r = _zp("up", "configs/minimal.yaml", "--log", "/nonexistent/x.csv", "--duration", "1")
    _clear_error(r, 2, "cannot write telemetry log '/nonexistent/x.csv'", "no directory")
    assert "not alive" not in r.stderr and "loops" not in r.stdout


@pytest.mark.no_mission
def test_sim_log_to_a_bad_path(tmp_path: Path) -> None:
    r = _zp("sim", "configs/minimal.yaml", "--log", str(tmp_path / "no" / "x.csv"))
    _clear_error(r, 2, "cannot write telemetry log", "no directory")
    r = _zp("sim", "configs/minimal.yaml", "--log", str(tmp_path))
    _clear_error(r, 2, "it is a directory")


@pytest.mark.no_mission
def test_plot_of_a_missing_csv(tmp_path: Path) -> None:
    r = _zp("plot", str(tmp_path / "missing.csv"), "cn_state", "--out", str(tmp_path / "p.png"))
    _clear_error(r, 2, "no such telemetry CSV")


@pytest.mark.no_mission
def test_unknown_mission_names_what_is_running(runtime: Path) -> None:
    r = _zp("ground", "no_such_mission")
    _clear_error(
        r, 2, "no such file or running mission: 'no_such_mission'", "no mission is running"
    )
    r = _zp("check", "configs/nope.yaml")
    _clear_error(r, 2, "no such mission file")
    # A bare name that is a mission file nearby (the README's verbs run from
    # the repository): the error names the file to give.
    r = _zp("keygen", "led_test")
    _clear_error(r, 2, "'led_test'; did you mean the file configs/led_test.yaml?")


# ---------------------------------------------------------------- tap


def test_tap_rejects_a_bad_key_expression() -> None:
    r = _zp("tap", "configs/minimal.yaml", "rocket/**/")
    _clear_error(r, 2, "'rocket/**/' is not a zenoh key expression")


@pytest.mark.no_mission
def test_tap_with_no_publisher_says_so(tmp_path: Path) -> None:
    mission = tmp_path / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", mission)  # nobody runs there
    r = _zp("tap", str(mission), "rocket/nothing/here", "--timeout", "1")
    _clear_error(r, 1, "no sample on rocket/nothing/here within 1 s", "zplatform ps")
    assert r.stdout == ""


@pytest.mark.no_mission
def test_tap_without_bounds_gives_up_on_silence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    mission = tmp_path / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", mission)
    monkeypatch.setattr(cli_runtime, "TAP_SILENCE_S", 0.5)
    assert main(["tap", str(mission)]) == 1
    assert "no sample on rocket/** within 0.5 s" in capsys.readouterr().err


def test_tap_shows_f32_values_at_their_own_precision() -> None:
    """0.7 in an f32 element taps as 0.7, not the widened double 0.699999988079071."""
    from zplatform.control.loop import ControlLogic
    from zplatform.core.auth import load_keys
    from zplatform.ground.tap import TapDecoder, format_tap
    from zplatform.mission.load import load_mission

    mission = load_mission(CONFIGS / "flight.yaml")
    cn = ControlLogic(mission, keys=load_keys(mission, "cn"), epoch=10**18)
    cn.begin(1, 10**18 + 10**7)
    cn.dv.set("airbrake_rate_ps", 0.7)  # an f32 parameter
    tm = cn.finish()
    assert tm is not None
    d = TapDecoder(mission).decode("rocket/cn/telemetry", bytes(tm))
    assert "airbrake_rate_ps=0.7 " in format_tap(d, as_json=False)
    assert json.loads(format_tap(d, as_json=True))["values"]["airbrake_rate_ps"] == 0.7


def test_tap_prints_events_decoded() -> None:
    from zplatform.core.auth import load_keys
    from zplatform.ground.tap import TapDecoder, format_tap
    from zplatform.mission.load import load_mission

    mission = load_mission(CONFIGS / "minimal.yaml")
    dec = TapDecoder(mission)
    sev = max(Severity)  # whatever the most severe is called
    ev = Event("cn", 3, 1_000, int(sev), "cmd_rejected", "command LAUNCH #4 rejected")
    cn = load_keys(mission, "cn")
    assert cn is not None  # events carry the CN's own event tag
    tagged = bytes(cn.channel("events_cn").seal(encode_event(ev)))
    d = dec.decode("rocket/cn/events", tagged, rx_ns=2_000)
    out = format_tap(d, as_json=False)
    assert f"rocket/cn/events EVENT {sev.name:<8} cmd_rejected: command LAUNCH #4" in out
    assert "unverified" not in out
    # --json: the event as the events file has it.
    assert json.loads(format_tap(d, as_json=True))["event"] == {
        "rx_time_ns": 2_000,
        "node": "cn",
        "seq": 3,
        "t_ns": 1_000,
        "severity": sev.name,
        "id": "cmd_rejected",
        "text": "command LAUNCH #4 rejected",
        "verified": True,
        "filled": False,  # live, not filled from the CN's recorder
    }
    # Forged (untagged), it is refused, not shown as the CN's.
    d = dec.decode("rocket/cn/events", encode_event(ev))
    assert "tag" in d["error"]


@pytest.mark.parametrize(
    ("argv", "blocked", "phrase"),
    [
        (["xtce", "configs/minimal.yaml"], ("yamcs", "zplatform.cli.xtce"), "zplatform[ground]"),
        (
            ["ccsds", "configs/minimal.yaml", "--decode", "x.bin", "--out", "x.csv"],
            ("spacepackets", "zplatform.telemetry.ccsds", "zplatform.cli.xtce"),
            "zplatform[ground]",
        ),
        (["plot", "x.csv", "cn_loop", "--out", "x.png"], ("matplotlib",), "zplatform[plot]"),
    ],
)
def test_verbs_that_need_an_extra_name_it(
    argv: list[str],
    blocked: tuple[str, ...],
    phrase: str,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Without its extra a verb says which, in one line, exit 2 (no traceback)."""
    for name in blocked:  # None in sys.modules: `import name` raises ImportError
        monkeypatch.setitem(sys.modules, name, None)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("zplatform: error: ") and phrase in err and err.count("\n") == 1, err


# ---------------------------------------------------------------- output


@pytest.mark.no_mission
def test_check_json_into_a_closed_pipe_is_quiet() -> None:
    # A pipe whose reader is gone before the first byte: the very first
    # write breaks it, every time (one process, not rounds of them hoping
    # that one of them writes after `head` went).
    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run(
            [sys.executable, "-m", "zplatform", "check", "configs/led_test.yaml", "--json"],
            cwd=ROOT, stdout=w, stderr=subprocess.PIPE, text=True, timeout=60,
        )  # fmt: skip
    finally:
        os.close(w)
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr
    assert p.returncode == 141, (p.returncode, p.stderr)  # as killed by SIGPIPE, quietly
    # A reader that takes the first line and goes: that line is the JSON's.
    script = f"{sys.executable} -m zplatform check configs/led_test.yaml --json | head -n 1"
    q = subprocess.run(["bash", "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert "Traceback" not in q.stderr and "BrokenPipe" not in q.stderr, q.stderr
    assert q.stdout.strip() == "{"


def test_broken_pipe_in_process(monkeypatch: pytest.MonkeyPatch) -> None:
    class Closed:
        def write(self, s: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self) -> int:
            raise OSError("no fileno")

    monkeypatch.setattr(sys, "stdout", Closed())
    assert main(["check", str(CONFIGS / "minimal.yaml"), "--json"]) == 141


# ---------------------------------------------------------------- options


@pytest.mark.parametrize(
    ("argv", "phrase"),
    [
        (["up", "configs/minimal.yaml", "--duration", "-1"], "--duration: must be > 0, got -1"),
        (["up", "configs/minimal.yaml", "--duration", "0"], "--duration: must be > 0"),
        (["up", "configs/minimal.yaml", "--ready-timeout", "0"], "--ready-timeout: must be > 0"),
        (["sim", "configs/minimal.yaml", "--log", "x.csv", "--duration", "nan"], "must be > 0"),
        (["tap", "configs/minimal.yaml", "--count", "0"], "--count: must be >= 1"),
        (["up", "configs/minimal.yaml", "--settle", "0"], "--settle: must be > 0"),
        (["cmd", "configs/minimal.yaml", "noop", "--timeout", "abc"], "expected a number"),
    ],
)
def test_numeric_options_are_validated(
    argv: list[str], phrase: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert phrase in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra", [[], ["--commands", "configs/led_test.commands", "--duration", "5"]]
)
def test_settle_is_for_a_script_without_a_duration(
    extra: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["up", "configs/led_test.yaml", "--settle", "1", *extra]) == 2
    err = capsys.readouterr().err
    assert "--settle is how long a run goes on after its script (--commands) without " \
        "--duration" in err and err.count("\n") == 1, err  # fmt: skip


def test_version_and_help(capsys: pytest.CaptureFixture[str]) -> None:
    from zplatform import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"zplatform {__version__}"
    parser = build_parser()
    texts = [parser.format_help()]
    missing = []
    sub = next(a for a in parser._actions if a.dest == "command")
    for verb, p in sub.choices.items():  # type: ignore[union-attr]
        texts.append(p.format_help())
        for a in p._actions:
            if a.help is None and a.dest != "help":
                missing.append(f"{verb} {'/'.join(a.option_strings) or a.dest}")
    assert not missing, f"options without help: {missing}"
    assert not any("DESIGN" in t for t in texts)
    # Help is prose for a user, never a raw docstring's markup.
    raw = [v for v, p in sub.choices.items() if "``" in p.format_help()]  # type: ignore[union-attr]
    assert not raw, f"help with raw docstring markup: {raw}"
    node = sub.choices["node"].format_help()  # type: ignore[index]
    assert "cn_b" in node


def test_sim_needs_no_log_and_prints_no_reprs(capsys: pytest.CaptureFixture[str]) -> None:
    """`sim MISSION` alone runs and reports (the CSV is opt-in), in words."""
    code = main(["sim", str(CONFIGS / "led_test.yaml"), "--duration", "1"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "errors 0 (cn 0, dn0 0, dn1 0, dn2 0)" in out and "(no --log)" in out, out
    assert "{" not in out and "'" not in out, out


# ---------------------------------------------------------------- up


def test_second_up_on_the_same_ports_is_refused(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        raw = yaml.safe_load((CONFIGS / "minimal.yaml").read_text())
        raw["nodes"]["cn"]["listen"] = [f"tcp/127.0.0.1:{port}"]
        mission = tmp_path / "m.yaml"
        mission.write_text(yaml.safe_dump(raw, sort_keys=False))
        r = _zp("up", str(mission), "--duration", "1")
    _clear_error(
        r,
        2,
        f"port {port} (cn's listen endpoint tcp/127.0.0.1:{port}) is in use",
        "zplatform ps",
        "--free-ports",
    )
    assert "loops" not in r.stdout


def test_sim_default_duration_covers_the_script(tmp_path: Path) -> None:
    from zplatform.telemetry.logs import read_csv

    out = tmp_path / "sim.csv"
    rc = main(
        [
            "sim",
            str(CONFIGS / "recovery_igniter.yaml"),
            "--commands",
            str(CONFIGS / "recovery_igniter.commands"),
            "--log",
            str(out),
        ]
    )
    assert rc == 0
    assert read_csv(out)[-1]["cn_state"] == "DEPLOYED"
    events = [json.loads(x) for x in (tmp_path / "sim.events.jsonl").read_text().splitlines()]
    assert any(e["id"] == "state_change" and "DEPLOYED" in e["text"] for e in events)


def test_up_registers_is_found_by_name_logs_events_and_cleans_up(
    tmp_path: Path, runtime: Path
) -> None:
    """`up --free-ports` registers; `ps`, `tap NAME` find it; SIGTERM removes it all."""
    script = tmp_path / "s.commands"
    script.write_text("at 0.3 launch\n")
    scratch = tmp_path / "scratch"  # TMPDIR of `up`: its scratch folder must not stay
    scratch.mkdir()
    log = tmp_path / "tm.csv"
    events = tmp_path / "tm.events.jsonl"
    env = dict(os.environ, TMPDIR=str(scratch), PYTHONUNBUFFERED="1")
    up = _up_minimal("--log", str(log), "--commands", str(script), env=env)
    try:
        entry = runtime / "minimal.json"
        wait_until(lambda: entry.exists() and b'"nodes":{"' in entry.read_bytes(), 30, "entry")
        r = _zp("ps", "--json")
        assert r.returncode == 0, r.stderr
        (e,) = json.loads(r.stdout)
        assert e["name"] == "minimal" and e["pid"] == up.pid
        assert Path(e["mission_file"]).is_file() and Path(e["mission_file"]).parent == runtime
        assert e["logs"] == {"telemetry": str(log), "events": str(events)}
        assert set(e["nodes"]) == {"cn", "dn0", "gn"}
        # Any verb takes the running mission's name.
        r = _zp("tap", "minimal", "rocket/cn/telemetry", "--count", "2", "--json")
        assert r.returncode == 0, r.stderr
        assert all(json.loads(x)["key"] == "rocket/cn/telemetry" for x in r.stdout.splitlines())
        # The ground node logs the events of the scripted LAUNCH beside the CSV.
        wait_until(lambda: events.exists() and "state_change" in events.read_text(), 60, "events")
        up.send_signal(signal.SIGTERM)
        _out, err = up.communicate(timeout=30)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
    assert "Traceback" not in err, err
    recs = [json.loads(x) for x in events.read_text().splitlines()]
    ids = {(r["node"], r["id"]) for r in recs}
    assert ("cn", "cmd_accepted") in ids and ("cn", "state_change") in ids, recs
    assert {"rx_time_ns", "seq", "t_ns", "severity", "text"} <= set(recs[0])
    assert list(runtime.iterdir()) == []  # entry and remapped mission gone
    assert list(scratch.iterdir()) == []  # no zplatform-up-* left behind
    r = _zp("ps")
    assert r.stdout.strip() == "no mission is running"


def test_up_says_so_when_the_ground_node_playing_its_script_dies(
    tmp_path: Path, runtime: Path
) -> None:
    """`up --commands` without --duration ends after the script; if the
    ground node that plays it dies first, `up` says the script will not end
    and the vehicle flies on (a dead ground changes nothing on board; it used
    to fly on without a word), until the operator stops it."""
    script = tmp_path / "late.commands"
    script.write_text("at 600 launch\n")  # never reached: the GN dies first
    err_path = tmp_path / "up.err"
    with err_path.open("w") as err_file:
        up = subprocess.Popen(
            [sys.executable, "-m", "zplatform", "up", "configs/minimal.yaml", "--free-ports",
             "--no-realtime", "--quiet", "--commands", str(script)],
            cwd=ROOT,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
            stdout=subprocess.DEVNULL,
            stderr=err_file,
            text=True,
        )  # fmt: skip
    try:
        entry = runtime / "minimal.json"

        def pid(node: str) -> int | None:
            try:
                return json.loads(entry.read_text()).get("nodes", {}).get(node)
            except (OSError, ValueError):
                return None  # not written yet

        wait_until(lambda: pid("gn") is not None and pid("cn") is not None, 30, "the entry")
        gn, cn = pid("gn"), pid("cn")
        assert gn is not None and cn is not None
        os.kill(gn, signal.SIGKILL)
        wait_until(lambda: "Ctrl-C ends the run" in err_path.read_text(), 60, "up's word")
        err = err_path.read_text()
        assert "node gn died" in err and "the vehicle flies on" in err, err
        assert up.poll() is None  # up goes on, and so does the control node
        os.kill(cn, 0)
        up.send_signal(signal.SIGTERM)
        up.wait(timeout=60)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert "Traceback" not in err_path.read_text()


def test_registry_names_stale_entries_and_resolution(runtime: Path, tmp_path: Path) -> None:
    a = registry.register("led_test", str(CONFIGS / "led_test.yaml"))
    b = registry.register("led_test", str(CONFIGS / "led_test.yaml"))
    try:
        assert (a.name, b.name) == ("led_test", "led_test-2")
        assert [e.name for e in registry.running()] == ["led_test", "led_test-2"]
        assert registry.resolve_mission("led_test-2") == str((CONFIGS / "led_test.yaml").resolve())
        # An existing file wins over a running name.
        f = tmp_path / "led_test"
        f.write_text("x")
        assert registry.resolve_mission(str(f)) == str(f)
        # A dead `up` leaves a stale entry: reading the registry drops it.
        stale = runtime / "ghost.json"
        dead = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.wait()
        stale.write_bytes(
            json.dumps(
                {
                    "name": "ghost",
                    "mission": "ghost",
                    "pid": dead.pid,
                    "mission_file": "/x",
                    "source_file": "/x",
                    "started": 0.0,
                }
            ).encode()
        )
        assert "ghost" not in [e.name for e in registry.running()]
        assert not stale.exists()
        with pytest.raises(Exception, match="running: led_test, led_test-2"):
            registry.resolve_mission("ghost")
    finally:
        a.remove()
        b.remove()
    assert registry.running() == []


def test_ps_shows_the_file_the_user_started(
    runtime: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`up --free-ports` runs a remapped copy; `ps` names the user's file."""
    a = registry.register("led_test", str(CONFIGS / "led_test.yaml"))
    try:
        copy = runtime / "led_test.mission.yaml"
        copy.write_text((CONFIGS / "led_test.yaml").read_text())
        a.update(mission_file=str(copy))
        assert main(["ps"]) == 0
        out = capsys.readouterr().out
        assert str((CONFIGS / "led_test.yaml").resolve()) in out and str(copy) not in out, out
    finally:
        a.remove()


def test_a_device_given_as_the_mission_is_named_for_what_it_is(runtime: Path) -> None:
    """`check /dev/null` (or a pipe) is not called a directory."""
    with pytest.raises(CommandError) as exc:
        registry.resolve_mission("/dev/null")
    assert "/dev/null is a device, pipe or socket, not a mission file" in str(exc.value)


def test_a_directory_named_like_a_running_mission_does_not_hide_it(
    runtime: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`cmd led_test` from a checkout holding a `led_test/` folder reaches the
    running mission; with none running, the message names both readings."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "led_test").mkdir()
    with pytest.raises(CommandError) as exc:
        registry.resolve_mission("led_test")
    assert "led_test is a directory, not a mission file, and no running mission is named" in str(
        exc.value
    )
    assert "no mission is running" in str(exc.value)
    a = registry.register("led_test", str(CONFIGS / "led_test.yaml"))
    try:
        assert registry.resolve_mission("led_test") == a.entry.mission_file
    finally:
        a.remove()


@pytest.mark.no_mission
@pytest.mark.parametrize(
    ("line", "phrase"),
    [
        ("at 1.0 write no_such_elem 1", "no element named 'no_such_elem'"),
        ("at 1.0 frobnicate", "unknown command 'frobnicate'"),
    ],
)
def test_up_checks_the_command_script_against_the_mission_before_spawning(
    tmp_path: Path, line: str, phrase: str
) -> None:
    """A script `sim` refuses is refused by `up` too, naming its line, before
    any node starts (it used to start every node, lose the ground node on the
    bad line and wait 60 s for it)."""
    script = tmp_path / "bad.commands"
    script.write_text(f"# a comment\n{line}\n")
    r = _zp("up", "configs/led_test.yaml", "--commands", str(script), "--free-ports")
    _clear_error(r, 2, f"{script}:2", phrase)
    assert "loops" not in r.stdout and "alive" not in r.stderr


def test_up_quiet_prints_no_info(tmp_path: Path, runtime: Path) -> None:
    """`up --quiet` of a clean run prints nothing: the nodes log warnings and
    errors only (they used to log every INFO line to the terminal)."""
    r = _zp(
        "up",
        "configs/minimal.yaml",
        "--duration",
        "1",
        "--quiet",
        "--free-ports",
        "--no-realtime",
        timeout=90,
    )
    assert r.returncode == 0, r.stderr
    assert " INFO " not in r.stderr and r.stdout == "", (r.stdout, r.stderr)


def test_up_s_status_line_never_runs_into_a_node_s_log_line(runtime: Path) -> None:
    """On a terminal `up` redraws its status line in place (\\r); each node's
    log line starts by clearing it, so the two never share a line."""
    import pty
    import re

    main_fd, sub_fd = pty.openpty()
    up = subprocess.Popen(
        [sys.executable, "-m", "zplatform", "up", "configs/minimal.yaml", "--duration", "3",
         "--free-ports", "--no-realtime"],
        cwd=ROOT, stdin=subprocess.DEVNULL, stdout=sub_fd, stderr=sub_fd,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )  # fmt: skip
    os.close(sub_fd)
    out = bytearray()
    try:
        while True:
            try:
                chunk = os.read(main_fd, 65536)
            except OSError:  # EIO: every writer of the terminal has gone
                break
            if not chunk:
                break
            out += chunk
        assert up.wait(timeout=60) == 0, out.decode(errors="replace")
    finally:
        os.close(main_fd)
        if up.poll() is None:
            up.kill()
            up.wait()
    text = out.decode(errors="replace")
    assert re.search(r"\rloop +\d+ ", text), text  # the status line, drawn in place
    stamps = [m.start() for m in re.finditer(r"20\d\d-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} ", text)]
    assert stamps, text
    for at in stamps:
        assert text[max(0, at - 4) : at] == "\r\x1b[K", repr(text[max(0, at - 120) : at + 40])
