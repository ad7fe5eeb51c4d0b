"""Plain-text and Markdown tables of already formatted cells (reports print, notebooks write).

``header``: column names; ``rows``: lists of strings, one per column. No pandas here:
callers format their numbers first (so that a table says exactly what was printed).
"""
from __future__ import annotations

from collections.abc import Sequence


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-flavoured Markdown table (no trailing newline)."""
    return "\n".join(["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
                     + ["| " + " | ".join(r) + " |" for r in rows])


def text_table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int = 2) -> str:
    """A fixed-width table: the first ``left`` columns left-aligned, the rest right-aligned."""
    w = [max(len(h), *(len(r[k]) for r in rows)) if rows else len(h) for k, h in enumerate(header)]
    line = lambda cells: "  ".join(c.ljust(w[k]) if k < left else c.rjust(w[k]) for k, c in enumerate(cells)).rstrip()
    return "\n".join([line(header), line(["-" * n for n in w])] + [line(r) for r in rows])
