"""The docs and the code cite only documents the repository ships.

Readers of a published repository cannot open a working file that was
never shipped ("seed 003", "thesis 000", a design note's DESIGN.md): a
requirement is said in the project's own words, a source by its title (the
thesis: *A Distributed Avionics Software Platform for a Liquid-Fueled
Rocket*), and anything else by a file of this repository.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCANNED = ["README.md", "zplatform", "nodes", "docs", "configs", "bench", "codecs"]
SUFFIXES = {".py", ".md", ".yaml", ".yml", ".commands", ".toml", ".txt", ".html", ".js"}

#: A working document named by number ("seed 003", "thesis 000", "note #4").
NUMBERED = re.compile(r"\b(?:seed|thesis|note|brief|design)s?[ _-]?#?0\d{2}\b", re.I)
#: A Markdown file named in the text (a link, a path in backquotes, a bare name).
MARKDOWN = re.compile(r"(?<![\w/.-])([\w./-]*[A-Za-z]\w*\.md)\b")


def _files() -> list[Path]:
    out: list[Path] = []
    for name in SCANNED:
        p = ROOT / name
        out += [p] if p.is_file() else sorted(f for f in p.rglob("*") if f.suffix in SUFFIXES)
    return out


def _shipped_markdown() -> set[str]:
    skip = {".venv", "site", ".git", "node_modules"}
    return {f.name for f in ROOT.rglob("*.md") if not skip & set(f.relative_to(ROOT).parts)}


def test_no_working_document_is_cited_by_number() -> None:
    found = [
        f"{f.relative_to(ROOT)}:{n}: {m.group(0)!r}"
        for f in _files()
        for n, line in enumerate(f.read_text(encoding="utf-8", errors="replace").splitlines(), 1)
        for m in NUMBERED.finditer(line)
    ]
    assert found == [], "cites documents the repository does not ship:\n" + "\n".join(found)


def test_every_markdown_file_named_is_shipped() -> None:
    shipped = _shipped_markdown()
    assert {"README.md", "requirements.md", "architecture.md"} <= shipped
    named = [
        (f"{f.relative_to(ROOT)}:{n}", m.group(1))
        for f in _files()
        for n, line in enumerate(f.read_text(encoding="utf-8", errors="replace").splitlines(), 1)
        for m in MARKDOWN.finditer(line)
    ]
    assert len(named) > 100, "too few Markdown names found: is the pattern still right?"
    found = [f"{where}: {md!r}" for where, md in named if Path(md).name not in shipped]
    assert found == [], "names Markdown files the repository does not ship:\n" + "\n".join(found)
