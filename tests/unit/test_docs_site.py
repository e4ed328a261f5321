"""The documentation site (mkdocs.yml) builds, strictly and offline.

`mkdocs build --strict` fails on any broken link or anchor between the
pages (mkdocs.yml's `validation`), so a renamed heading, key or file breaks
this test instead of the reader.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# One worker for both tests (pytest-xdist, --dist loadgroup): the site is
# built once, not once on each worker.
pytestmark = [pytest.mark.timeout(300), pytest.mark.xdist_group("docs_site")]

PAGES = (
    "index.html",  # README.md
    "tutorial/index.html",
    "operations/index.html",
    "missions/index.html",
    "security/index.html",
    "deployment/index.html",
    "faults/index.html",
    "testing/index.html",
    "internals/index.html",
    "mission-reference/index.html",
    "architecture/index.html",
    "keyspace/index.html",
    "requirements/index.html",
    "serial-protocol/index.html",
    "codecs/FORMAT/index.html",
    "bench/REPORT/index.html",
    "bench/ZENOH_API/index.html",
)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("site")
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        env=dict(os.environ, NO_MKDOCS_2_WARNING="1"),
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return out


def test_every_page_is_built(site: Path) -> None:
    for page in PAGES:
        assert (site / page).is_file(), page
    # The pages from outside docs/ come with what they show.
    assert (site / "console.png").is_file()
    assert (site / "bench" / "plots" / "codec.png").is_file()
    index = (site / "index.html").read_text()
    assert "zplatform is open-source flight software" in index
    assert 'src="console.png"' in index


def test_the_site_needs_no_network(site: Path) -> None:
    """No web fonts, scripts or styles from elsewhere: it reads offline."""
    for html in site.rglob("*.html"):
        text = html.read_text()
        assert "fonts.googleapis.com" not in text, html
        remote = re.findall(r'<(?:script|link)\b[^>]*(?:src|href)="(https?://[^"]+)"', text)
        assert remote == [], (html, remote)
