"""The acceptance PDF is a complete filing copy on its own (issue 33): every instrument, the whole
data hash, every calibration's table, the criteria and an approval block, and no word outside its
page - read back from the PDF with poppler's pdftotext, as a reader would see it."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from rig.report.acceptance import build_report
from rig.store import RunReader
from rig.store.seal import data_digest
from tests.tools import require_tool

RUN = Path(__file__).resolve().parents[1] / "data" / "loaded-demo-wrong-fail"
EDGE_PT = 1.0
"""How far (pt) a word's box may reach past its page's edge: font-box rounding, not cut text."""


@pytest.fixture
def built(tmp_path: Path) -> tuple[str, Path]:
    """pdftotext's path, and a copy of the evidence run with its report built afresh."""
    pdftotext = require_tool("pdftotext", what="reading the report's PDF back")
    folder = tmp_path / RUN.name
    shutil.copytree(RUN, folder)
    build_report(folder)
    return pdftotext, folder


def test_the_pdf_holds_everything_a_filing_copy_needs(built: tuple[str, Path]) -> None:
    pdftotext, folder = built
    pdf = folder / "report.pdf"
    raw = subprocess.run([pdftotext, "-layout", str(pdf), "-"], capture_output=True, text=True,
                         check=True).stdout  # fmt: skip
    text = " ".join(raw.split())  # wrapped lines joined: long values wrap, never cut
    reader = RunReader(folder)
    try:
        meta, results = reader.meta(), reader.results()
    finally:
        reader.close()
    table = text[text.index("Instruments device model (as it answered)") :]
    for name, model in meta["instruments"].items():  # each row: the device, what it answered
        assert name in table and all(word in table for word in str(model).split()), name
    assert data_digest(folder / "run.sqlite")[0] in text.replace(" ", "")
    for name in ("vector calibration", "scalar calibration", "live calibration"):
        assert f"Calibration '{name}'" in text, name
        assert name in results
    assert text.count("x0_ut") >= 3  # each calibration's parameter table, in full
    for row in results["verdict"]["criteria"]:
        assert row["name"] in text
    for role in ("Prepared by", "Reviewed by", "Approved by"):
        assert re.search(rf"{role} _{{10,}} _{{10,}} _{{10,}}", text), role
    assert "more in report.html" not in text


def test_no_word_lies_outside_its_page(built: tuple[str, Path], tmp_path: Path) -> None:
    pdftotext, folder = built
    boxes = tmp_path / "boxes.html"
    subprocess.run([pdftotext, "-bbox", str(folder / "report.pdf"), str(boxes)], check=True)
    html = boxes.read_text(encoding="utf-8")
    pages = re.findall(r'<page width="([\d.]+)" height="([\d.]+)">(.*?)</page>', html, re.S)
    assert len(pages) >= 2
    outside = []
    for n, (width, height, body) in enumerate(pages, start=1):
        for x0, y0, x1, y1, word in re.findall(
            r'<word xMin="([-\d.]+)" yMin="([-\d.]+)" xMax="([-\d.]+)" yMax="([-\d.]+)">(.*?)</word>',
            body,
        ):
            # a glyph box may touch the edge by a rounding (0.3 pt seen); 1 pt is beyond that
            left, top = float(x0) + EDGE_PT, float(y0) + EDGE_PT
            right, bottom = float(x1) - EDGE_PT, float(y1) - EDGE_PT
            if left < 0 or top < 0 or right > float(width) or bottom > float(height):
                outside.append((n, word))
    assert not outside, outside[:10]


def test_every_page_is_a4_plots_too(built: tuple[str, Path], tmp_path: Path) -> None:
    """Issue 55: "A4, for filing", yet the plot pages came in 7 sizes, some wider than A4. Every
    page now A4 portrait (595.3 x 841.9 pt), each plot page under its title and numbered."""
    pdftotext, folder = built
    boxes = tmp_path / "boxes.html"
    subprocess.run([pdftotext, "-bbox", str(folder / "report.pdf"), str(boxes)], check=True)
    html = boxes.read_text(encoding="utf-8")
    sizes = re.findall(r'<page width="([\d.]+)" height="([\d.]+)">', html)
    assert len(sizes) >= 6  # the summary pages and the plots
    assert all(abs(float(w) - 595.3) < 0.5 and abs(float(h) - 841.9) < 0.5 for w, h in sizes), (
        sorted(set(sizes))
    )
    text = subprocess.run([pdftotext, str(folder / "report.pdf"), "-"], capture_output=True,
                          text=True, check=True).stdout  # fmt: skip
    assert f"page {len(sizes)}" in text  # the last plot page numbered as the rest
