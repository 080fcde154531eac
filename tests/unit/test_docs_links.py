"""Every relative link and anchor in the README, CONTRIBUTING.md and docs/*.md resolves.

No network: links with a scheme (https:, mailto:) are not followed. A relative link must name a
file or folder of the repository; an anchor (``#heading`` or ``page.md#heading``) must be the
slug of a heading of that page, as GitHub makes it.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").glob("*.md"))]
#: The target of a Markdown link or image: ``](target)``, the text possibly over several lines.
LINK = re.compile(r"\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def _prose(text: str) -> str:
    """The text without code blocks and inline code (a `](x)` there is not a link)."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`([^`]*)`", r"\1", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading: its text
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every anchor of a page's headings, repeated ones numbered as GitHub does (-1, -2...)."""
    seen: dict[str, int] = {}
    out = set()
    for line in FENCE.sub("", page.read_text()).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(doc: Path) -> list[str]:
    return [t for t in LINK.findall(_prose(doc.read_text())) if not re.match(r"^\w+:", t)]


def test_slugs_are_githubs() -> None:
    assert slug("The `[scenario]` table") == "the-scenario-table"
    assert slug("The paper's evaluation, under its load") == "the-papers-evaluation-under-its-load"
    assert slug("What it is, and why") == "what-it-is-and-why"
    assert slug("The tiers of `make test`") == "the-tiers-of-make-test"


def test_a_broken_link_is_found(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# Top\n\n[ok](#top) [bad](#nowhere) `[code](#not-a-link)`\n")
    assert links(page) == ["#top", "#nowhere"]
    assert anchors(page) == {"top"}


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_and_anchor_resolves(doc: Path) -> None:
    broken = []
    for target in links(doc):
        path, _, anchor = target.partition("#")
        page = (doc.parent / path).resolve() if path else doc
        if not page.exists():
            broken.append(
                f"{target}: no file {page.relative_to(ROOT) if page.is_relative_to(ROOT) else page}"
            )
        elif not page.is_relative_to(ROOT):
            broken.append(f"{target}: outside the repository")
        elif anchor and page.suffix == ".md" and anchor not in anchors(page):
            broken.append(f"{target}: no heading #{anchor} in {page.relative_to(ROOT)}")
    assert not broken, f"{doc.relative_to(ROOT)}: broken links: {broken}"
