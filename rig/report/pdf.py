"""The report's PDF rendering: the sections on as many A4 pages as they need (lines wrapped, never
cut), then one page per figure with its title above the axes."""

from __future__ import annotations

import io
import textwrap
import warnings
from collections.abc import Sequence
from typing import Any

from rig.report.section_model import Section, styled_lines

COLOURS = {"PASS": "#1a7f37", "FAIL": "#b42318", "note": "#444444"}
A4_IN = (8.27, 11.69)
LEFT, TOP, BOTTOM = 0.06, 0.95, 0.05
KEEP_WITH_HEAD = 3
"""Lines a table's header needs below it on its page (itself and two rows), else a new page."""
FIGURE_DPI = 150
"""A figure's resolution (dots per inch), embedded in the PDF as drawn: a 7 inch plot is about
1050 dots across, printed at about 150 dots per inch of A4."""
MONO_CHARS = 112
"""Characters of 7.5 pt monospace across the page between the margins."""
TEXT_CHARS = 120
"""Characters of 8 pt proportional text across the page (typical; wrapped conservatively)."""


class PdfSummary:
    """Writes lines top to bottom, starting a new page when one is full; each page footed with
    ``footer`` and its number."""

    def __init__(self, pdf: Any, plt: Any, footer: str) -> None:
        self.pdf, self.plt, self.footer = pdf, plt, footer
        self.page: Any = None
        self.number = 0
        self.y = TOP

    def _new_page(self) -> None:
        self.finish_page()
        self.page = self.plt.figure(figsize=A4_IN)
        self.number += 1
        self.y = TOP

    def finish_page(self) -> None:
        """Foot and save the current page, if any."""
        if self.page is None:
            return
        self.page.text(LEFT, 0.025, f"{self.footer} - page {self.number}", fontsize=7, color="#666")
        self.pdf.savefig(self.page)
        self.plt.close(self.page)
        self.page = None

    def _room(self, height: float) -> None:
        if self.page is None or self.y - height < BOTTOM:
            self._new_page()

    def title(self, text: str, verdict: str, colour: str) -> None:
        """The report's title and verdict at the top of the first page."""
        self._room(0.09)
        self.page.text(LEFT, self.y, text, fontsize=16, weight="bold")
        self.y -= 0.04
        self.page.text(
            LEFT, self.y, f"VERDICT: {verdict}", fontsize=14, weight="bold", color=colour
        )
        self.y -= 0.04

    def line(self, text: str, style: str) -> None:
        """One line of a section (wrapped onto as many lines as it needs)."""
        if style == "heading":
            self._room(0.06)
            self.y -= 0.012
            self.page.text(LEFT, self.y, text, fontsize=11, weight="bold")
            self.y -= 0.024
            return
        if style == "head":  # a table's header keeps its first rows with it on the page
            self._room(0.017 * KEEP_WITH_HEAD)
        mono = style not in ("text", "note")
        width = MONO_CHARS if mono else TEXT_CHARS
        for part in textwrap.wrap(text, width, subsequent_indent="    ", drop_whitespace=False) or [
            ""
        ]:
            self._room(0.017)
            self.page.text(LEFT, self.y, part, fontsize=7.5 if mono else 8,
                           family="monospace" if mono else "sans-serif",
                           weight="bold" if style == "head" else "normal",
                           style="italic" if style == "note" else "normal",
                           color=COLOURS.get(style, "#111111"))  # fmt: skip
            self.y -= 0.016

    def figure(self, title: str, png: bytes) -> None:
        """One figure (a PNG from :func:`render_figure`) on an A4 page of its own, under its
        title, as wide as the margins allow (or as tall, for a tall one), footed and numbered as
        every page; its pixels embedded as drawn, never resampled (so no page takes the figure's
        own size, issue 55: plot pages came in 7 sizes, some wider than A4)."""
        image = self.plt.imread(io.BytesIO(png))
        self._new_page()
        self.page.text(LEFT, self.y, title, fontsize=10, weight="bold")
        top = self.y - 0.02
        aspect = image.shape[0] / image.shape[1] * A4_IN[0] / A4_IN[1]  # height per width, page
        width = 1.0 - 2 * LEFT
        height = width * aspect
        if height > top - BOTTOM:
            height = top - BOTTOM
            width = height / aspect
        axes = self.page.add_axes((LEFT, top - height, width, height))
        axes.imshow(image, interpolation="none")  # a vector backend embeds it as it is
        axes.set_axis_off()
        self.finish_page()

    def sections(self, sections: Sequence[Section]) -> None:
        """Every section meant for the PDF, in order."""
        for sec in sections:
            if "pdf" in sec.formats and sec.blocks:
                for text, style in styled_lines(sec):
                    self.line(text, style)


def render_figure(fig: Any, plt: Any) -> bytes:
    """``fig`` laid out (tight) and drawn once as a PNG at :data:`FIGURE_DPI`, then closed: the
    PDF page embeds these pixels, the HTML a smaller copy (:func:`scaled_png`)."""
    buf = io.BytesIO()
    with warnings.catch_warnings():  # a projection or twin axes tight_layout cannot fit
        warnings.simplefilter("ignore")
        fig.tight_layout()
    fig.savefig(buf, format="png", dpi=FIGURE_DPI, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def scaled_png(png: bytes, dpi: float) -> bytes:
    """``png`` (drawn at :data:`FIGURE_DPI`) resampled to ``dpi`` (area average), for a page that
    shows it smaller."""
    from PIL import Image

    with Image.open(io.BytesIO(png)) as image:
        size = (max(1, round(image.width * dpi / FIGURE_DPI)),
                max(1, round(image.height * dpi / FIGURE_DPI)))  # fmt: skip
        buf = io.BytesIO()
        image.resize(size, Image.Resampling.BOX).save(buf, format="PNG")
    return buf.getvalue()
