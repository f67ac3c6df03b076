"""Every relative link of the README and of docs/ points to a file of the repository (the README is a landing page
that links into docs/; a moved or renamed page must not leave a dead link)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s]+)\)")
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def relative_links(page: Path) -> list[str]:
    links = [match.group(1) for match in LINK.finditer(page.read_text(encoding="utf8"))]
    return [link for link in links if "://" not in link and not link.startswith(("#", "mailto:"))]


@pytest.mark.parametrize("page", PAGES, ids=[str(page.relative_to(ROOT)) for page in PAGES])
def test_relative_links_point_to_existing_files(page: Path) -> None:
    missing = [link for link in relative_links(page) if not (page.parent / link.split("#")[0]).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_the_link_pattern_finds_links() -> None:
    page = ROOT / "README.md"
    assert "docs/USAGE.md" in relative_links(page)
