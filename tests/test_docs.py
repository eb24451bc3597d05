"""The front door and the docs site hold together: a README of at most about 200 lines
whose links all lead somewhere, and docs pages whose links to each other's sections
land on a heading (Sphinx's strict build finds a missing page; a missing section of an
existing page it lets through, so it is checked here with MyST's own slugs)."""

from __future__ import annotations

import re
from pathlib import Path

from myst_parser.slugs import github_slugify

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _prose(text: str) -> str:
    """The text outside fenced code blocks."""
    out, fence = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fence = not fence
            continue
        if not fence:
            out.append(line)
    return "\n".join(out)


def _anchors(page: Path) -> set[str]:
    return {
        github_slugify(m.group(1).strip())
        for m in re.finditer(r"^#{1,6} (.+)$", _prose(page.read_text(encoding="utf-8")), re.M)
    }


def _pages() -> list[Path]:
    return [
        p for p in sorted(DOCS.rglob("*.md")) if not {"_build", "commands"} & set(p.relative_to(DOCS).parts)
    ]


def test_the_readme_is_a_front_door() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 200
    for target in LINK.findall(_prose(text)):
        if target.startswith(("http://", "https://")):
            continue
        path = target.split("#", 1)[0]
        assert (ROOT / path).exists(), f"README links to {target}, which does not exist"


def test_every_link_between_docs_pages_lands_on_a_page_and_a_section() -> None:
    checked = 0
    for page in _pages():
        for target in LINK.findall(_prose(page.read_text(encoding="utf-8"))):
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)} links to {target}"
            assert dest.exists(), f"{where}: no such file"
            if anchor and dest.suffix == ".md":
                assert anchor in _anchors(dest), f"{where}: no such section in {dest.name}"
            checked += 1
    assert checked >= 10  # the pages do link to each other


def test_the_anchor_check_finds_a_missing_section(tmp_path: Path) -> None:
    page = tmp_path / "a.md"
    page.write_text("# Title\n\n## The ground station's API\n\n```sh\n# not a heading\n```\n")
    assert _anchors(page) == {"title", "the-ground-stations-api"}
