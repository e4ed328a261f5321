"""The README is a front page that tells the truth, and the docs list what ships.

The README says what zplatform is, gives the two commands (the demo; the
tests, exactly as CI runs them), how to reach the installed command, and a
short tour whose commands the CLI takes as written; the rest lives in
docs/. The docs' list of shipped missions names every file in configs/,
and the tutorial and the docs say what `tap` really does with a mission
that is not running yet.
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import pytest

from zplatform.cli import main as cli

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
MAX_README_LINES = 250
ACTIVATE = "source .venv/bin/activate"


def _readme() -> str:
    return README.read_text(encoding="utf-8")


def _section(markdown: str, heading: str) -> str:
    """The text under ``## heading``, up to the next heading of that level."""
    m = re.search(rf"^## {re.escape(heading)}\n(.*?)(?=^## |\Z)", markdown, re.M | re.S)
    assert m is not None, f"no section {heading!r}"
    return m.group(1)


def test_the_readme_is_a_front_page() -> None:
    lines = _readme().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines"


def test_the_readme_names_both_commands_and_how_to_reach_the_cli() -> None:
    text = _readme()
    quick = _section(text, "Quick start")
    for command in ("./scripts/demo.sh", "./scripts/test.sh", ACTIVATE):
        assert command in quick, command
    # The test command is exactly what CI runs, and CI really runs it.
    assert "exactly as CI does" in quick
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert re.search(r"^exec bash scripts/test\.sh\b", ci, re.M), ci


def test_the_demo_says_how_to_reach_the_cli() -> None:
    """After demo.sh the command is in .venv, not on PATH: its last words say so."""
    demo = (ROOT / "scripts" / "demo.sh").read_text(encoding="utf-8")
    tail = demo[demo.index("zplatform up configs/led_test.yaml") :]
    assert ACTIVATE in tail
    assert ".venv/bin/zplatform" in tail


def _commands(markdown: str) -> list[list[str]]:
    """The `zplatform` command lines of the indented code blocks, without
    `zplatform` and comments. In a transcript (a block with `$ ` prompts)
    only the prompted lines are commands; the rest is what they print."""
    out = []
    for block in re.findall(r"(?:^    .*\n?)+", markdown, re.M):
        lines = [line[4:] for line in block.splitlines()]
        if any(line.startswith("$ ") for line in lines):
            lines = [line[2:] for line in lines if line.startswith("$ ")]
        for line in lines:
            if line.startswith("zplatform "):
                out.append(shlex.split(line, comments=True)[1:])
    return out


def _check_parses(cmds: list[list[str]]) -> None:
    cli._load_extras()
    parser = cli.build_parser()
    for argv in cmds:
        try:
            parser.parse_args(argv)
        except SystemExit as exc:  # 0: --version, --help; else a usage error
            if exc.code:
                pytest.fail(f"the CLI refuses: zplatform {shlex.join(argv)}")
        for arg in argv:
            if arg.startswith("configs/"):
                assert (ROOT / arg).is_file(), arg


def test_the_tour_s_commands_are_taken_by_the_cli_as_written() -> None:
    cmds = _commands(_section(_readme(), "A 5-minute tour"))
    verbs = [c[0] for c in cmds]
    for verb in ("check", "sim", "up", "ps", "tap", "cmd", "log", "ground", "plot"):
        assert verb in verbs, verb
    _check_parses(cmds)


@pytest.mark.parametrize("page", ["operations.md", "missions.md", "security.md", "deployment.md"])
def test_the_docs_commands_are_taken_by_the_cli_as_written(page: str) -> None:
    cmds = _commands((ROOT / "docs" / page).read_text(encoding="utf-8"))
    assert cmds, page
    _check_parses(cmds)


def _shipped_missions_table() -> str:
    return _section(
        (ROOT / "docs" / "missions.md").read_text(encoding="utf-8"), "The shipped missions"
    )


def test_every_shipped_mission_is_in_the_docs_configs_list() -> None:
    table = _shipped_missions_table()
    listed = set(re.findall(r"^\| `(configs/[^`]+)` \|", table, re.M))
    shipped = {p.relative_to(ROOT).as_posix() for p in (ROOT / "configs").iterdir() if p.is_file()}
    yamls = {p for p in shipped if p.endswith(".yaml")}
    assert "configs/led_test.yaml" in yamls, yamls
    assert yamls <= listed, f"not in docs/missions.md: {sorted(yamls - listed)}"
    # The command scripts too, and nothing that does not ship.
    assert listed == shipped, (sorted(shipped - listed), sorted(listed - shipped))


def test_the_tutorial_asks_for_no_extra_for_the_console() -> None:
    """The console is a base dependency: `pip install -e .` is the whole install."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert any(d.startswith("textual") for d in project["dependencies"])
    tutorial = (ROOT / "docs" / "tutorial.md").read_text(encoding="utf-8")
    assert "[ground]" not in tutorial


def test_tap_before_up_has_registered_the_name_fails_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """What the tutorial and docs/operations.md say: `tap NAME` started before
    `up` registered NAME does not wait out its --timeout for a sample (that
    would be exit 1, "nothing arrived"); it refuses the name, exit 2."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # no mission runs here
    monkeypatch.chdir(tmp_path)
    rc = cli.main(["tap", "oven", "oven/dn0/to_cn", "--count", "1", "--timeout", "60"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "no such file or running mission: 'oven'" in err
    for doc in ("docs/tutorial.md", "docs/operations.md"):
        text = " ".join((ROOT / doc).read_text(encoding="utf-8").split())
        assert "no such file or running mission" in text, doc


def test_the_reference_names_the_key_set_auth_reads() -> None:
    """Keys are one file per host role in the mission's key set directory
    (zplatform/core/auth.py), not one key file per mission."""
    from zplatform.core.auth import default_key_dir, key_file_name

    reference = (ROOT / "docs" / "mission-reference.md").read_text(encoding="utf-8")
    row = next(line for line in reference.splitlines() if line.startswith("| `$.mission` |"))
    assert default_key_dir("m").parts[-3:] == ("zplatform", "keys", "m")
    assert "~/.config/zplatform/keys/<mission>/" in row
    for role in ("cn", "dn0", "gn", "tool"):
        assert f"`{key_file_name(role)}`" in row, role
    assert "<mission>.key`" not in reference
