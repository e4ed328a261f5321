"""docs/architecture.md's package layout table names every module of zplatform/."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_layout_table_lists_every_module() -> None:
    arch = (ROOT / "docs" / "architecture.md").read_text()
    table = arch[arch.index("## Package layout") :]
    table = table[: table.index("\n\n", table.index("| path | owns |"))]
    rows = [r for r in table.splitlines() if r.startswith("| `")]
    named: set[str] = set()
    for row in rows:
        cell = row.split("|")[1] + row.split("|")[2]
        folders = re.findall(r"`zplatform/(\w+)/`", row)
        for m in re.findall(r"`(?:zplatform/)?([\w/]+\.py)`", cell):
            named.add(m)
            for f in folders:
                named.add(f"{f}/{m}")
    missing = [
        str(p.relative_to(ROOT / "zplatform"))
        for p in sorted((ROOT / "zplatform").rglob("*.py"))
        if p.name != "__init__.py" and str(p.relative_to(ROOT / "zplatform")) not in named
    ]
    assert missing == [], f"modules missing from the layout table: {missing}"
