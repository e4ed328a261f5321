"""docs/requirements.md cites only evidence that exists, so the table cannot rot silently.

Every ``tests/<path>.py::<name>`` in the document must name a file that
exists and defines ``def <name>(``; every ``python -m bench.<name>`` a module
``bench/<name>.py``. Every requirement row has a valid status, and the
totals line agrees with the rows. A renamed or deleted test fails here:
update the table in the same change.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "requirements.md"

TEST_CITE = re.compile(r"\b(tests/[\w/]+\.py)::(\w+)")
BENCH_CITE = re.compile(r"\bpython -m bench\.(\w+)")
ROW = re.compile(r"^\|\s*((?:TH|FS|SR|PL)-\d+)\s*\|.*\|\s*([^|]*?)\s*\|\s*$", re.M)
TOTALS = re.compile(
    r"\*\*Totals:\*\*\s*(\d+) requirements; (\d+) verified, (\d+) partly, (\d+) not yet\."
)
STATUSES = ("verified", "partly", "not yet")


def _doc() -> str:
    return DOC.read_text(encoding="utf-8")


def test_every_cited_test_exists() -> None:
    cites = sorted(set(TEST_CITE.findall(_doc())))
    assert len(cites) >= 30, f"only {len(cites)} test citations found: is the pattern still right?"
    sources: dict[str, str | None] = {}
    missing = []
    for path, name in cites:
        if path not in sources:
            f = ROOT / path
            sources[path] = f.read_text(encoding="utf-8") if f.is_file() else None
        src = sources[path]
        if src is None:
            missing.append(f"{path}::{name} (no such file)")
        elif not re.search(rf"^\s*(?:async\s+)?def {re.escape(name)}\(", src, re.M):
            missing.append(f"{path}::{name} (no such function)")
    assert not missing, "docs/requirements.md cites tests that do not exist:\n" + "\n".join(missing)


def test_every_cited_benchmark_exists() -> None:
    names = sorted(set(BENCH_CITE.findall(_doc())))
    assert names, "no benchmark citations found"
    missing = [n for n in names if not (ROOT / "bench" / f"{n}.py").is_file()]
    assert not missing, f"docs/requirements.md cites missing benchmarks: {missing}"


def test_every_requirement_has_one_row_and_a_valid_status() -> None:
    rows = ROW.findall(_doc())
    assert rows, "no requirement rows found"
    ids = Counter(i for i, _ in rows)
    assert [i for i, n in ids.items() if n > 1] == []
    bad = [(i, s) for i, s in rows if s not in STATUSES]
    assert bad == [], f"status must be one of {STATUSES}"


def test_totals_line_matches_the_table() -> None:
    text = _doc()
    m = TOTALS.search(text)
    assert m, "no '**Totals:** N requirements; a verified, b partly, c not yet.' line"
    counts = Counter(s for _, s in ROW.findall(text))
    want = (sum(counts.values()), counts["verified"], counts["partly"], counts["not yet"])
    assert tuple(int(g) for g in m.groups()) == want
