"""docs/tutorial.md, followed as a new user would: every file it shows is
written and every command it shows is run, and what it says they print is
checked.

The tutorial is the script. Its fenced blocks are the steps, in order:

* a block with ``title="PATH"`` (any language but ``console``) is a file
  the reader writes: it is written to PATH;
* a ``console`` block holds commands: a ``$ `` line is a command (run by
  bash; it must exit 0, so a command expected to fail is written
  ``cmd; echo "exit $?"``), the lines under it are what it prints (each
  must begin a line of the output, in order; ``...`` matches anything, a
  line of only ``...`` marks left-out lines), ``> `` lines are typed at
  its prompt (its stdin);
* a console block titled ``terminal 1`` runs its command in the background,
  as in a second terminal: the steps go on once the lines shown under it
  have appeared; a later ``terminal 1`` block starting with ``^C`` presses
  Ctrl-C (SIGINT), waits for the command to end (exit 0) and checks the
  lines under ``^C``.

Everything runs in a temporary directory outside the checkout, with the
installed ``zplatform`` on PATH, without PYTHONPATH, with a fresh HOME (no
mission key yet) and runtime directory (no other mission's registry), and
with no ZPLATFORM_* variable: as a new user on a fresh machine.
PYTHONUNBUFFERED stands in for the terminal's line buffering, so that
output interleaves as a terminal shows it.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TUTORIAL = ROOT / "docs" / "tutorial.md"
BACKGROUND = "terminal 1"
COMMAND_TIMEOUT_S = 180.0

pytestmark = pytest.mark.timeout(600)

_FENCE = re.compile(r"^```(?P<lang>[\w-]*)(?P<info>[^\n]*)\n(?P<body>.*?)^```[ \t]*$", re.M | re.S)
_TITLE = re.compile(r'title="([^"]+)"')


@dataclass
class Step:
    """One thing the reader does: write a file, run a command, press Ctrl-C."""

    kind: str  # "file", "run", "start" (in the background), "interrupt"
    text: str  # the file's path, or the command
    line: int  # where it is in the tutorial
    content: str = ""  # a file's content
    stdin: list[str] = field(default_factory=list)
    expected: list[str] = field(default_factory=list)


def parse(markdown: str) -> list[Step]:
    """The tutorial's steps, in order (see the module docstring)."""
    steps: list[Step] = []
    for m in _FENCE.finditer(markdown):
        lang, body = m.group("lang"), m.group("body")
        title_m = _TITLE.search(m.group("info"))
        title = title_m.group(1) if title_m else None
        first = markdown.count("\n", 0, m.start()) + 2
        if lang != "console":
            if title is not None:
                steps.append(Step("file", title, first, content=body))
            continue
        current: Step | None = None
        for i, line in enumerate(body.splitlines()):
            if line.startswith("$ "):
                kind = "start" if title == BACKGROUND else "run"
                current = Step(kind, line[2:], first + i)
                steps.append(current)
            elif line.strip() == "^C":
                assert title == BACKGROUND, f"line {first + i}: ^C outside {BACKGROUND!r}"
                current = Step("interrupt", "^C", first + i)
                steps.append(current)
            elif current is None:
                raise AssertionError(f"line {first + i}: output before any command: {line!r}")
            elif line.startswith("> "):
                current.stdin.append(line[2:])
            elif line.strip():
                current.expected.append(line)
    return steps


def _pattern(line: str) -> re.Pattern[str]:
    parts = " ".join(line.split()).split("...")
    return re.compile(".*?".join(re.escape(p) for p in parts))


def unmatched(expected: list[str], output: str) -> str | None:
    """The first expected line that does not begin a line of ``output`` after
    the previous one's (whitespace runs count as one space); None if all do."""
    lines = [" ".join(x.split()) for x in output.splitlines()]
    at = 0
    for want in expected:
        if want.strip() == "...":
            continue
        pattern = _pattern(want)
        while at < len(lines) and not pattern.match(lines[at]):
            at += 1
        if at == len(lines):
            return want
        at += 1
    return None


class Background:
    """The command of ``terminal 1``: its output collected as it comes."""

    def __init__(self, command: str, cwd: Path, env: dict[str, str]) -> None:
        # exec: Ctrl-C (SIGINT) reaches the command itself, as in a terminal.
        self.proc = subprocess.Popen(
            ["bash", "-c", "exec " + command],
            cwd=cwd,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.output = ""
        self.done = False
        self.changed = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self.changed:
                self.output += line
                self.changed.notify_all()
        with self.changed:
            self.done = True
            self.changed.notify_all()

    def wait_for(self, expected: list[str], timeout_s: float) -> None:
        """Until every expected line has been printed (or the command ended)."""
        with self.changed:
            self.changed.wait_for(
                lambda: self.done or unmatched(expected, self.output) is None, timeout_s
            )

    def interrupt(self, timeout_s: float) -> int:
        """Ctrl-C; the exit code once the command ended and its output is read."""
        self.proc.send_signal(signal.SIGINT)
        code = self.proc.wait(timeout=timeout_s)
        with self.changed:
            self.changed.wait_for(lambda: self.done, timeout_s)
        return code

    def stop(self) -> None:
        """Whatever happened: the command ends (SIGINT first, so it stops its nodes)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _new_user_env(home: Path, runtime: Path) -> dict[str, str]:
    zplatform = shutil.which("zplatform", path=str(Path(sys.executable).parent))
    assert zplatform is not None, "the zplatform command is not installed next to this python"
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("ZPLATFORM_") and k not in ("PYTHONPATH", "XDG_CONFIG_HOME")
    }
    env.update(
        HOME=str(home),
        XDG_RUNTIME_DIR=str(runtime),
        PATH=f"{Path(zplatform).parent}{os.pathsep}/usr/bin{os.pathsep}/bin",
        PYTHONUNBUFFERED="1",
    )
    return env


def test_the_tutorial_parses_into_its_steps() -> None:
    steps = parse(TUTORIAL.read_text(encoding="utf-8"))
    files = {s.text for s in steps if s.kind == "file"}
    assert {"first-mission/oven.yaml", "first-mission/oven/__init__.py"} <= files
    commands = " ".join(s.text for s in steps if s.kind in ("run", "start"))
    for verb in ("check", "schema", "sim", "up", "tap", "cmd", "ground", "ps"):
        assert f"zplatform {verb} " in commands, verb
    assert [s.kind for s in steps].count("start") == 1
    assert steps[-1].kind == "interrupt"
    # Every zplatform command, and Ctrl-C, shows what it prints: something to check.
    shown = [s for s in steps if "zplatform" in s.text or s.kind == "interrupt"]
    assert all(s.expected for s in shown), [s.text for s in shown if not s.expected]


# The tutorial runs a mission from its own directory with no PYTHONPATH, as
# a new user would: the mission file's directory is on the import path of
# the verbs that run its code, and ground verbs need only the mission file.
def test_the_tutorial_runs_as_written(tmp_path: Path) -> None:
    work, home, runtime = tmp_path / "work", tmp_path / "home", tmp_path / "run"
    for d in (work, home, runtime):
        d.mkdir(mode=0o700)
    env = _new_user_env(home, runtime)
    background: Background | None = None
    try:
        for step in parse(TUTORIAL.read_text(encoding="utf-8")):
            where = f"docs/tutorial.md line {step.line}: {step.text}"
            if step.kind == "file":
                path = work / step.text
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(step.content, encoding="utf-8")
            elif step.kind == "run":
                r = subprocess.run(
                    ["bash", "-c", step.text],
                    cwd=work,
                    env=env,
                    input="".join(line + "\n" for line in step.stdin),
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    text=True,
                    timeout=COMMAND_TIMEOUT_S,
                )
                assert r.returncode == 0, f"{where}\nexit {r.returncode}:\n{r.stdout}"
                missing = unmatched(step.expected, r.stdout)
                assert missing is None, f"{where}\nmissing {missing!r} in:\n{r.stdout}"
            elif step.kind == "start":
                assert background is None, f"{where}: {BACKGROUND} is already running"
                background = Background(step.text, work, env)
                background.wait_for(step.expected, COMMAND_TIMEOUT_S)
                missing = unmatched(step.expected, background.output)
                assert missing is None, f"{where}\nmissing {missing!r} in:\n{background.output}"
            else:  # interrupt
                assert background is not None, f"{where}: nothing runs in {BACKGROUND}"
                code = background.interrupt(COMMAND_TIMEOUT_S)
                assert code == 0, f"{where}\nexit {code}:\n{background.output}"
                missing = unmatched(step.expected, background.output)
                assert missing is None, f"{where}\nmissing {missing!r} in:\n{background.output}"
                background = None
    finally:
        if background is not None:
            background.stop()
