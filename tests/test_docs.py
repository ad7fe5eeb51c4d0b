"""The user's documentation stays short, linked and true to the code.

README.md and docs/*.md (and the dataset guide) are read by newcomers: short sentences, working
relative links, no issue numbers. The table of reasons and degradations in docs/algorithm.md is
generated from :mod:`cerpe.reasons`; regenerate it with ``python tests/test_docs.py --write``.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from cerpe.reasons import DEGRADATIONS, REASONS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS, ROOT / "datasets_manifest" / "README.md"]
MAX_README_LINES = 250
MAX_WORDS = 40  # every sentence has fewer words than this
ALGORITHM = ROOT / "docs" / "algorithm.md"
BEGIN, END = "<!-- reasons: generated from cerpe/reasons.py -->", "<!-- reasons: end -->"

_ISSUE = re.compile(r"\bissues?\s*#?\s*\d+", re.IGNORECASE)
_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
_LIST_ITEM = re.compile(r"^\s*(?:[-*+]|\d+\.)\s+")
_SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z`\[(*\"'_0-9])")


def prose_blocks(text: str) -> list[str]:
    """The paragraphs and list items of a Markdown text, each joined into one line.

    Left out: fenced code blocks, tables (lines starting with ``|``), headings and HTML comments.
    """
    blocks: list[list[str]] = []
    current: list[str] = []
    fenced = False

    def close() -> None:
        nonlocal current
        if current:
            blocks.append(current)
        current = []

    for line in text.splitlines():
        s = line.strip()
        if s.startswith("```"):
            fenced = not fenced
            close()
            continue
        if fenced or not s or s.startswith(("|", "#", "<!--")):
            close()
            continue
        if _LIST_ITEM.match(line):
            close()
        current.append(s)
    close()
    return [" ".join(b) for b in blocks]


def sentences(text: str) -> list[str]:
    """The prose sentences of a Markdown text (see :func:`prose_blocks`)."""
    return [s for block in prose_blocks(text) for s in _SENTENCE_END.split(block) if s.strip()]


def long_sentences(text: str) -> list[str]:
    return [s for s in sentences(text) if len(s.split()) >= MAX_WORDS]


def test_the_sentence_splitter_reads_markdown() -> None:
    text = ("# A heading with many words that is not prose at all\n\nOne. Two words `a.b` here.\n"
            "- an item\n  that goes on.\n\n```\ncode. Not. Prose.\n```\n| a | b |\n")
    assert sentences(text) == ["One.", "Two words `a.b` here.", "- an item that goes on."]
    assert long_sentences(" ".join(["word"] * MAX_WORDS) + ".") and not long_sentences("Short.")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_sentence_is_short(page: Path) -> None:
    long = long_sentences(page.read_text())
    assert not long, f"{page.relative_to(ROOT)}: sentences of {MAX_WORDS} words or more:\n" + "\n".join(long)


def test_readme_is_short() -> None:
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines, at most {MAX_README_LINES}"


def _issue_files() -> list[Path]:
    return [README, *DOCS, *sorted((ROOT / "cerpe").rglob("*.py")), *sorted((ROOT / "cerpe").rglob("*.md"))]


def test_no_issue_numbers() -> None:
    assert _ISSUE.search("see issue 20") and _ISSUE.search("Issue #7") and not _ISSUE.search("an issue of 3 parts")
    found = [f"{p.relative_to(ROOT)}: {m.group(0)!r}" for p in _issue_files() for m in _ISSUE.finditer(p.read_text())]
    assert not found, "issue numbers in the code or docs:\n" + "\n".join(found)


def relative_links(page: Path) -> list[str]:
    """The targets of a page's Markdown links that are paths (no scheme, no bare anchor), anchors cut."""
    out = []
    for target in _LINK.findall(page.read_text()):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("#"):
            continue
        out.append(target.split("#")[0])
    return out


@pytest.mark.parametrize("page", [README, *DOCS], ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_at_a_file(page: Path) -> None:
    broken = [t for t in relative_links(page) if not (page.parent / t).exists()]
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files: {broken}"


def reasons_markdown() -> str:
    """The reasons and degradations tables of docs/algorithm.md, between its markers."""
    def table(head: str, items: dict[str, str]) -> list[str]:
        rows = [f"| {head} | meaning |", "|---|---|"]
        return rows + [f"| `{k}` | {v.replace('|', '/')} |" for k, v in items.items()]

    lines = [BEGIN, "", "Reasons (`PairRecord.reason`, the `reason` column of `steps.csv`):", "",
             *table("reason", REASONS), "",
             "Degradations (`RobotRecord.degradations`, the `degradations` column of `robots.csv`):", "",
             *table("degradation", DEGRADATIONS), "", END]
    return "\n".join(lines)


def _with_reasons(text: str) -> str:
    head, sep, rest = text.partition(BEGIN)
    _, sep2, tail = rest.partition(END)
    if not (sep and sep2):
        raise ValueError(f"{ALGORITHM}: the markers {BEGIN!r} and {END!r} are missing")
    return head + reasons_markdown() + tail


def test_algorithm_page_lists_the_vocabulary_of_cerpe_reasons() -> None:
    text = ALGORITHM.read_text()
    assert text == _with_reasons(text), (
        "docs/algorithm.md's reasons and degradations are stale: regenerate them with "
        "`python tests/test_docs.py --write`")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_docs.py --write   (regenerates the tables of docs/algorithm.md)")
    ALGORITHM.write_text(_with_reasons(ALGORITHM.read_text()))
    print(f"written: {ALGORITHM}")
