"""Every module of zplatform/ states its contract in a short module docstring.

A module docstring says what the module holds and its contract (blocks? copies?
raises? which thread?) in at most 20 lines and points to docs/architecture.md
(or codecs/FORMAT.md) for the detail; the detail lives in docs/, once.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MAX_LINES = 20

# Modules whose docstrings are being shortened by another change (none now).
EXEMPT: dict[str, str] = {}


def _docstrings() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for p in sorted((ROOT / "zplatform").rglob("*.py")):
        tree = ast.parse(p.read_text())
        out[str(p.relative_to(ROOT))] = ast.get_docstring(tree, clean=False)
    return out


def test_every_module_has_a_short_docstring() -> None:
    missing, long = [], []
    for path, doc in _docstrings().items():
        if path in EXEMPT:
            continue
        if not doc:
            missing.append(path)
        elif doc.count("\n") + 1 > MAX_LINES:
            long.append(f"{path} ({doc.count(chr(10)) + 1} lines)")
    assert missing == [], f"modules without a docstring: {missing}"
    assert long == [], f"module docstrings over {MAX_LINES} lines: {long}"


def test_the_exempt_modules_exist() -> None:
    assert [p for p in EXEMPT if not (ROOT / p).is_file()] == []


def _anchors(page: Path) -> set[str]:
    """The ids a link into ``page`` may name: explicit ``<a id>`` tags and the
    headings' slugs as the docs site makes them."""
    text = page.read_text()
    ids = set(re.findall(r'<a id="([^"]+)"', text))
    for heading in re.findall(r"^#+ (.+)$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.replace("`", "")).strip().lower()
        ids.add(re.sub(r"[\s-]+", "-", slug))
    return ids


def test_docstrings_name_files_that_exist() -> None:
    bad = []
    for path, doc in _docstrings().items():
        for ref, anchor in re.findall(r"\b((?:docs|codecs)/[\w./-]*\w)(?:#([\w-]+))?", doc or ""):
            target = ROOT / ref
            if not target.exists():
                bad.append(f"{path}: {ref}")
            elif anchor and target.suffix == ".md" and anchor not in _anchors(target):
                bad.append(f"{path}: {ref}#{anchor}")
    assert bad == [], f"module docstrings name files or sections that do not exist: {bad}"
