"""The PDF's pages: a table's header never alone at a page's foot (issue 55), read back with
poppler's pdftotext page by page."""

from __future__ import annotations

import subprocess
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
from matplotlib.backends.backend_pdf import PdfPages

from rig.report.pdf import PdfSummary
from rig.report.section_model import Para, Section, Table
from tests.tools import require_tool


def test_a_tables_header_moves_to_the_next_page_with_its_rows(tmp_path: Path) -> None:
    pdftotext = require_tool("pdftotext", what="reading the PDF back")
    filler = tuple(Para(f"line {k}") for k in range(54))  # the page full but for two lines
    table = Table(("criterion", "measured", "verdict"),
                  tuple((f"row {k}", "1.0", "PASS") for k in range(5)), verdict_col=2)  # fmt: skip
    path = tmp_path / "t.pdf"
    with PdfPages(path) as pdf:
        summary = PdfSummary(pdf, plt, "test")
        summary.sections([Section("", (*filler, table))])
        summary.finish_page()
    pages = [subprocess.run([pdftotext, "-f", str(n), "-l", str(n), str(path), "-"],
                            capture_output=True, text=True, check=True).stdout
             for n in (1, 2)]  # fmt: skip
    assert "line 53" in pages[0] and "criterion" not in pages[0]
    assert "criterion" in pages[1] and "row 0" in pages[1]
