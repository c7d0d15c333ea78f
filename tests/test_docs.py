"""The README and ``docs/*.md``: every relative link resolves, and the README stays a front door.

A link is ``[text](target)`` or ``![alt](target)``, or a reference definition ``[name]: target``.
Its file must exist in the repository and its ``#anchor``, if any, must be a heading of the target
Markdown file as GitHub spells it. ``http(s)://`` and other links with a scheme are not fetched.
No server is needed.
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").glob("*.md"))]
README_MAX_LINES = 200
# The two commands must be visible without scrolling.
README_HEAD_LINES = 6

_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,}).*?^ {0,3}\1[ \t]*$", re.MULTILINE | re.DOTALL)
_CODE_SPAN = re.compile(r"(`+)(?!`).*?(?<!`)\1(?!`)", re.DOTALL)
# Link text may hold one level of brackets and span lines; the target has no spaces, and may be
# followed by a title.
_INLINE_LINK = re.compile(
    r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^\s()<>]+)>?(?:\s+(?:\"[^\"]*\"|'[^']*'))?\s*\)"
)
_REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.MULTILINE)
_HEADING = re.compile(r"^ {0,3}(#{1,6})[ \t]+(.*?)(?:[ \t]+#+)?[ \t]*$", re.MULTILINE)
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def _without_code(text: str) -> str:
    """The text with fenced blocks and code spans blanked out (their newlines kept)."""

    def blank(match: re.Match[str]) -> str:
        return re.sub(r"[^\n]", " ", match.group(0))

    return _CODE_SPAN.sub(blank, _FENCE.sub(blank, text))


def links(text: str) -> list[str]:
    """Every link target of a Markdown text, outside code."""
    prose = _without_code(text)
    return [m.group(1) for m in _INLINE_LINK.finditer(prose)] + [
        m.group(1) for m in _REFERENCE.finditer(prose)
    ]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: the text of its links and code, lowercased, punctuation
    dropped except ``-`` and ``_``, each space a ``-``."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"<[^>]+>", "", text).lower()
    return "".join(c for c in text if c.isalnum() or c in "-_ ").replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every heading anchor of a Markdown text; a repeated heading gets ``-1``, ``-2``, ..."""
    seen: dict[str, int] = {}
    found = set()
    for match in _HEADING.finditer(_FENCE.sub("", text)):
        base = slug(match.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def broken_links(page: Path) -> list[str]:
    """The links of ``page`` that name a missing file or a missing heading, with the reason."""
    problems = []
    for target in links(page.read_text(encoding="utf-8")):
        if _SCHEME.match(target):
            continue
        path, _, anchor = target.partition("#")
        path = unquote(path)
        if not path:
            file = page
        elif path.startswith("/"):
            file = REPO / path.lstrip("/")
        else:
            file = page.parent / path
        file = file.resolve()
        if not file.is_relative_to(REPO):
            problems.append(f"{target}: outside the repository")
        elif not file.exists():
            problems.append(f"{target}: no file {file.relative_to(REPO)}")
        elif anchor and file.suffix == ".md":
            if unquote(anchor) not in anchors(file.read_text(encoding="utf-8")):
                problems.append(f"{target}: no heading #{anchor} in {file.relative_to(REPO)}")
    return problems


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(page: Path) -> None:
    assert broken_links(page) == []


def test_the_pages_have_links() -> None:
    """A parser that finds nothing would pass every page: the README links to every docs page."""
    found = {unquote(t.partition("#")[0]) for t in links(README.read_text(encoding="utf-8"))}
    for page in PAGES[1:]:
        assert str(page.relative_to(REPO)) in found


def test_readme_is_short() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines"


def test_readme_opens_with_the_two_commands() -> None:
    head = "\n".join(README.read_text(encoding="utf-8").splitlines()[:README_HEAD_LINES])
    assert "make serve" in head
    assert "make test" in head


@pytest.mark.parametrize(
    ("heading", "anchor"),
    [
        ("Quick start", "quick-start"),
        ("§4.1 The 57 actions", "41-the-57-actions"),
        ("PPO (`ppo-masked`, `ppo`)", "ppo-ppo-masked-ppo"),
        ("Pipelining: `step_async` and `step_wait`", "pipelining-step_async-and-step_wait"),
        ("The expert, the planner", "the-expert-the-planner"),
        ("See [the rules](rules.md)", "see-the-rules"),
    ],
)
def test_slug_follows_github(heading: str, anchor: str) -> None:
    assert slug(heading) == anchor


def test_links_skip_code_and_find_images() -> None:
    text = (
        "![a picture\nover two lines](img.png) and [a [nested] link](a.md#x 'title')\n"
        "`[not](code.md)`\n\n```\n[not](fenced.md)\n```\n[ref]: b.md\n"
    )
    assert sorted(links(text)) == ["a.md#x", "b.md", "img.png"]


def test_repeated_headings_are_numbered() -> None:
    assert anchors("# Limits\n## Limits\n```\n# not a heading\n```\n") == {"limits", "limits-1"}
