"""Running the README's, the demo's and the docs' commands from the checkout
leaves nothing for git to pick up: every file they write is ignored.

The README is a front page; the commands it had moved to docs/ pages (the
verbs to docs/operations.md), which are read with it. The tutorial is not:
its commands run in a directory of the reader's own, outside the checkout."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: The tutorial's commands run in a directory of the reader's own.
OUTSIDE_THE_CHECKOUT = {"docs/tutorial.md"}


def _docs() -> list[str]:
    """The README, the demo, and every docs page whose commands run from the checkout."""
    pages = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").glob("*.md"))
    return ["README.md", "scripts/demo.sh", *(p for p in pages if p not in OUTSIDE_THE_CHECKOUT)]


_OUTPUT = re.compile(r"--(?:out|record|log|summary)\s+([\w./-]+)")


def _outputs() -> list[str]:
    found: set[str] = set()
    for doc in _docs():
        for m in _OUTPUT.finditer((ROOT / doc).read_text()):
            path = m.group(1).rstrip(".")
            if path.isupper() or path.startswith(("docs/", "-")):
                continue  # a placeholder (CSV, DIR), or a file the repo ships on purpose
            found.add(path)
    return sorted(found)


@pytest.mark.skipif(
    shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs a git checkout"
)
def test_every_file_the_readme_writes_is_ignored() -> None:
    outs = _outputs()
    assert {"rec/", "tm.png", "tm.csv", "sim.csv", "led_test.summary.json"} <= set(outs), outs
    r = subprocess.run(
        ["git", "check-ignore", "--no-index", "-v", *outs],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    ignored = {line.split("\t", 1)[1] for line in r.stdout.splitlines()}
    assert ignored == set(outs), f"not ignored: {sorted(set(outs) - ignored)}"
