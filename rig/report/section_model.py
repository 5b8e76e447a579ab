"""The report's section model and its HTML and text renderings (the PDF's: rig.report.pdf).

A section is a title and blocks (paragraphs, tables, images); the report is a list of them, built
once (rig.report.sections) and rendered three ways, so report.html, report.pdf and report.txt
cannot say different things.
"""

from __future__ import annotations

import base64
import html
import textwrap
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

Style = Literal["text", "mono", "note", "PASS", "FAIL"]
Format = Literal["html", "pdf", "text"]
EVERYWHERE: frozenset[Format] = frozenset(("html", "pdf", "text"))


@dataclass(frozen=True)
class Para:
    """A paragraph: plain ``text`` (escaped by each renderer), or a verdict-coloured line."""

    text: str
    style: Style = "text"


@dataclass(frozen=True)
class Table:
    """A table of text cells; ``verdict_col``: the column whose PASS/FAIL colours its cell;
    ``row_heads``: the first column heads each row (a key/value table, no header row)."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    verdict_col: int | None = None
    row_heads: bool = False


@dataclass(frozen=True)
class Image:
    """A rendered figure (PNG), in the HTML only: the PDF gives each figure a page of its own."""

    title: str
    png: bytes


Block = Para | Table | Image


@dataclass(frozen=True)
class Section:
    """A part of the report: a title (none: no heading) and its blocks, in ``formats``."""

    title: str
    blocks: tuple[Block, ...]
    formats: frozenset[Format] = EVERYWHERE


def esc(x: object) -> str:
    """Text for HTML."""
    return html.escape(str(x))


def _html_table(t: Table) -> str:
    rows = (
        [] if t.row_heads else ["<tr>" + "".join(f"<th>{esc(h)}</th>" for h in t.header) + "</tr>"]
    )
    for row in t.rows:
        cells = []
        for i, cell in enumerate(row):
            if t.row_heads and i == 0:
                cells.append(f"<th>{esc(cell)}</th>")
            elif i == t.verdict_col:
                cells.append(f"<td class='{esc(cell)}'>{esc(cell)}</td>")
            else:
                cells.append(f"<td>{esc(cell)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return "<table>" + "".join(rows) + "</table>"


def _html_block(b: Block) -> str:
    if isinstance(b, Table):
        return _html_table(b)
    if isinstance(b, Image):
        data = base64.b64encode(b.png).decode()
        return (
            f"<h3>{esc(b.title)}</h3><img alt='{esc(b.title)}' src='data:image/png;base64,{data}'>"
        )
    if b.style == "note":
        return f"<p><i>{esc(b.text)}</i></p>"
    if b.style in ("PASS", "FAIL"):
        return f"<p class='{b.style}'>{esc(b.text)}</p>"
    return f"<p>{esc(b.text)}</p>"


def render_html(sections: Iterable[Section]) -> str:
    """The sections as HTML, each headed by its ``<h2>``."""
    parts = []
    for sec in sections:
        if "html" not in sec.formats or not sec.blocks:
            continue
        if sec.title:
            parts.append(f"<h2>{esc(sec.title)}</h2>")
        parts += [_html_block(b) for b in sec.blocks]
    return "\n".join(parts)


def table_lines(t: Table) -> list[str]:
    """A table as aligned text columns (header, rule, rows)."""
    rows = ([] if t.row_heads else [t.header]) + list(t.rows)
    widths = [max(len(r[i]) for r in rows if i < len(r)) for i in range(max(map(len, rows)))]
    if t.row_heads:
        return [f"{r[0] + ':':<{widths[0] + 1}} " + "  ".join(r[1:]) for r in rows]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=False)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return lines


LineStyle = Style | Literal["heading", "head"]


def styled_lines(sec: Section) -> list[tuple[str, LineStyle]]:
    """A section as (line, style) pairs: its heading, paragraphs, table lines (header ``head``)."""
    out: list[tuple[str, LineStyle]] = []
    if sec.title:
        out.append((sec.title, "heading"))
    for b in sec.blocks:
        if isinstance(b, Para):
            out.append((b.text, b.style))
        elif isinstance(b, Table):
            lines = table_lines(b)
            head = 0 if b.row_heads else 2
            for i, line in enumerate(lines):
                verdict = (
                    b.rows[i - head][b.verdict_col]
                    if b.verdict_col is not None and i >= head
                    else ""
                )
                style: LineStyle = "mono"
                if i < head:
                    style = "head"
                elif verdict:
                    style = "PASS" if verdict == "PASS" else "FAIL"
                out.append((line, style))
    return out


def render_text(sections: Sequence[Section], width: int = 100) -> list[str]:
    """The sections as plain text lines (paragraphs wrapped at ``width``, tables as columns)."""
    lines: list[str] = []
    for sec in sections:
        if "text" not in sec.formats or not sec.blocks:
            continue
        for text, style in styled_lines(sec):
            if style == "heading":
                lines += ["", text, "=" * len(text)]
            elif style in ("text", "note"):
                lines += textwrap.wrap(text, width, subsequent_indent="  ") or [""]
            else:
                lines.append(text)
    return lines
