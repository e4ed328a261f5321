"""mkdocs hooks for the documentation site (mkdocs.yml).

The site is built from docs/ plus pages that live elsewhere in the
repository, where they belong: README.md (the home page), codecs/FORMAT.md,
bench/REPORT.md and the plots it shows, bench/ZENOH_API.md. :func:`on_files` adds them, read
from the repository at build time (never copied, so never stale), and
:func:`on_page_markdown` rewrites every relative link of a page from the
page's place in the repository to its place in the site, so the same
markdown works on GitHub and in the site. A link to a repository file the
site does not hold is left alone; `mkdocs build --strict` then fails on it.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
DOCS = "docs/"

# Repository path -> site path of the pages and assets outside docs/.
PAGES = {
    "README.md": "index.md",
    "codecs/FORMAT.md": "codecs/FORMAT.md",
    "bench/REPORT.md": "bench/REPORT.md",
    "bench/ZENOH_API.md": "bench/ZENOH_API.md",
}
ASSETS = ("bench/plots/*.png",)

# An inline link or image target: ](target) or ](target "title").
_LINK = re.compile(r"(\]\()([^)\s]+)((?:\s+\"[^\"]*\")?\))")


def _external() -> dict[str, str]:
    out = dict(PAGES)
    for pattern in ASSETS:
        for path in sorted(ROOT.glob(pattern)):
            rel = path.relative_to(ROOT).as_posix()
            out[rel] = rel
    return out


def _site_path(repo_path: str, external: dict[str, str]) -> str | None:
    if repo_path in external:
        return external[repo_path]
    if repo_path.startswith(DOCS):
        return repo_path[len(DOCS) :]
    return None


def on_files(files: Files, config: Any) -> Files:
    for repo_path, site_path in _external().items():
        files.append(File.generated(config, site_path, abs_src_path=str(ROOT / repo_path)))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    external = _external()
    site_src = page.file.src_uri
    repo_src = next((r for r, s in external.items() if s == site_src), DOCS + site_src)

    def rewrite(m: re.Match[str]) -> str:
        target = m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:|^#|^/", target):  # a URL, an anchor, absolute
            return m.group(0)
        path, hash_, anchor = target.partition("#")
        repo_target = posixpath.normpath(posixpath.join(posixpath.dirname(repo_src), path))
        site_target = _site_path(repo_target, external)
        if site_target is None:
            return m.group(0)
        rel = posixpath.relpath(site_target, posixpath.dirname(site_src) or ".")
        return f"{m.group(1)}{rel}{hash_}{anchor}{m.group(3)}"

    return _LINK.sub(rewrite, markdown)
