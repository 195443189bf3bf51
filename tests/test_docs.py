"""The README and docs/ describe the system as it is: no issue numbers, commit hashes or
work periods (git log keeps those), pages short enough to read, and links that resolve."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MAX_LINES = {"README.md": 150, "docs/performance.md": 250}

ISSUE = re.compile(r"\bissues?\s+#?\d+", re.IGNORECASE)
# A commit hash as git prints one: 7 to 40 lowercase hex digits holding both a digit and
# a letter (so neither a number like 1800000 nor a word like "defaced"). Inside backticks
# or a fenced block it counts too: no page needs one. Not a hash: the last part of a
# hyphenated name, as in a sweep's run key, whose settings digest ends it
# (`left_turn-v20-c30-d0-autocast-s0-t40-mpaper-a4efd27e`).
HEX_WORD = re.compile(r"(?<![\w-])[0-9a-f]{7,40}\b")
# Dates of work periods: 2026-12-01 and the like. (A run id's compact 20261201-155734 is
# not one.)
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
# A work period named as one: "the third session", "this session's code", "this stop".
PERIOD = re.compile(
    r"\b(?:first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|this|that|"
    r"last|previous|next|same|earlier|later)\s+(?:session|stop)\b",
    re.IGNORECASE,
)
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _rel(page: Path) -> str:
    return page.relative_to(ROOT).as_posix()


def _is_hash(word: str) -> bool:
    return any(c.isdigit() for c in word) and any(c.isalpha() for c in word)


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_no_history_in_page(page):
    found = []
    for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        found += [f"{n}: issue reference {m.group()!r}" for m in ISSUE.finditer(line)]
        found += [f"{n}: commit hash {w!r}" for w in HEX_WORD.findall(line) if _is_hash(w)]
        found += [f"{n}: date {m.group()!r}" for m in DATE.finditer(line)]
        found += [f"{n}: work period {m.group()!r}" for m in PERIOD.finditer(line)]
    assert not found, f"{_rel(page)} names history (git log keeps it):\n" + "\n".join(found)


@pytest.mark.parametrize("name,limit", sorted(MAX_LINES.items()))
def test_page_length(name, limit):
    lines = len((ROOT / name).read_text(encoding="utf-8").splitlines())
    assert lines <= limit, f"{name} has {lines} lines, more than {limit}"


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors for a page's headings: lower case, punctuation dropped, spaces
    to hyphens."""
    out = set()
    for line in page.read_text(encoding="utf-8").splitlines():
        if m := re.match(r"#{1,6}\s+(.*)", line):
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            out.add(slug)
    return out


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_relative_links_resolve(page):
    text = page.read_text(encoding="utf-8")
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)  # code is not links
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading with that anchor")
    for path in re.findall(r"(?<![\w/.])(docs/[\w-]+\.md)", text):  # "see docs/running.md"
        if not (ROOT / path).exists():
            broken.append(f"{path}: no such page")
    assert not broken, f"{_rel(page)} has broken links:\n" + "\n".join(broken)
