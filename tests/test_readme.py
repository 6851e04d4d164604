"""The README is a front page: short, and every link it makes resolves."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def _links(md: Path) -> list[str]:
    return [t for t in LINK.findall(md.read_text(encoding="utf-8"))
            if not t.startswith(("http://", "https://", "mailto:"))]


def test_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250, f"README has {len(lines)} lines; move detail to docs/"
    text = "\n".join(lines)
    for heading in ("## Quick start", "## Commands", "## Methods"):
        assert heading in text


def test_every_relative_link_in_readme_and_docs_resolves():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    missing = [f"{p.relative_to(ROOT)} -> {t}" for p in pages for t in _links(p)
               if not (p.parent / t).exists()]
    assert not missing, missing


def test_readme_links_every_docs_page():
    readme = set(_links(ROOT / "README.md"))
    pages = {f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")}
    assert pages <= readme, f"docs pages not linked from the README: {sorted(pages - readme)}"
