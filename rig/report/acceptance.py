"""The pre-flight acceptance report of a closed run: ``report.html`` (self-contained),
``report.pdf`` (the filing copy) and ``report.txt``, all three from the same sections.

Everything comes from the run's store (meta, results, samples, channels, events), so a report can
be rebuilt at any time with ``rig report RUN``. Plots are rendered with matplotlib (Agg) and
embedded as data URIs; the HTML loads nothing from outside.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

from rig.analysis import selected_data
from rig.calibration import calibrate
from rig.calibration.record import CalibrationRecord, calibrations, latest_calibration
from rig.errors import RigError
from rig.report.calibration_figures import (
    calibration_figures,
    calibration_series,
    convergence_figure,
)
from rig.report.pdf import PdfSummary, render_figure, scaled_png
from rig.report.section_model import Image, Section, esc, render_html, render_text
from rig.report.sections import RunFacts, report_sections, verdict_of
from rig.report.text_report import data_hash
from rig.steps import KINDS, field_kinds
from rig.store import safe_files
from rig.store.run_store import RunReader
from rig.store.seal import record_written

__all__ = ["build_report", "calibration_series", "make_figures", "without_telemetry"]

COLOURS = {"PASS": "#1a7f37"}
"""The verdict banner's colour; anything else is red."""
STYLE = (
    "body{font-family:Helvetica,Arial,sans-serif;max-width:980px;margin:24px auto;color:#111;font-size:14px}"
    "table{border-collapse:collapse;margin:8px 0 18px}td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}"
    "th{background:#eee}.verdict{font-size:26px;font-weight:bold;padding:10px;color:#fff}"
    ".PASS{color:#1a7f37;font-weight:bold}.FAIL{color:#b42318;font-weight:bold}img{max-width:100%}"
    "h2{border-bottom:2px solid #333;margin-top:28px}@media print{h2{page-break-before:auto}}"
)  # fmt: skip


HTML_DPI = 110
"""The HTML page's plots (dots per inch of the figure): a 7 inch plot about 770 dots across."""


def make_figures(
    reader: RunReader, meta: dict[str, Any], results: dict[str, Any], plt: Any
) -> list[tuple[str, Any]]:
    """Every plot the report shows, labelled with units: the latest (vector, when there is one)
    calibration's, each live calibration's convergence, and what each step's kind draws."""
    figs: list[tuple[str, Any]] = []
    latest = latest_calibration(results, "vector") or latest_calibration(results)
    if latest is not None:
        figs += calibration_figures(reader, meta, latest[0], latest[1], plt)
    for name, cal in calibrations(results).items():
        fig = convergence_figure(reader.folder, cal.live, plt) if cal.live else None
        if fig is not None:
            figs.append((f"Live calibration '{name}': 1-sigma converging", fig))
    for _, name, kind, _, t1 in reader.steps():
        step_kind = KINDS.get(kind)
        if step_kind is not None and t1 is not None and name in results:
            figs += step_kind.figures(reader, name, results[name], plt)
    return figs


def without_telemetry(reader: RunReader, res: CalibrationRecord) -> CalibrationRecord | None:
    """The same calibration re-fitted on the same samples (its stored selection) without the
    current channels (the Springmann comparison)."""
    if not res.channels or (res.live is not None and res.selection is None):
        return None  # a live fit recorded without its selection: its samples are not known
    try:
        s, *_ = selected_data(reader, res, field_kinds=field_kinds(), telemetry=[])
        if res.model == "scalar":
            s = s.as_scalar()
        return CalibrationRecord.from_dict(calibrate(s, res.method).to_dict())
    except RigError:
        return None


def _html(run: RunFacts, sections: list[Section], verdict: str) -> str:
    meta = run.meta
    colour = COLOURS.get(verdict, "#b42318")
    generated = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    return "\n".join([
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>Acceptance report {esc(meta.get('dut_serial', ''))}</title><style>{STYLE}</style></head><body>",
        f"<h1>Pre-flight acceptance report: {esc(meta.get('procedure', ''))}</h1>",
        f"<div class='verdict' style='background:{colour}'>VERDICT: {esc(verdict)}</div>",
        render_html(sections),
        f"<p>Generated {generated} by rig {esc(meta.get('software_version', ''))}.</p></body></html>",
    ])  # fmt: skip


def _text(run: RunFacts, sections: list[Section], verdict: str) -> str:
    lines = [f"ACCEPTANCE REPORT - {run.meta.get('procedure', '')}", f"VERDICT: {verdict}"]
    lines += render_text(sections)
    return "\n".join([*lines, "", f"VERDICT: {verdict}"]) + "\n"


def _pdf(
    path: Path, run: RunFacts, sections: list[Section], verdict: str, drawn: list[tuple[str, bytes]]
) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    info = {"Title": f"Acceptance report {run.meta.get('run_id', '')}",
            "Subject": f"VERDICT: {verdict}; data sha256 {run.digest}"}  # fmt: skip
    # the file is ours to open and close: matplotlib's own handle was left open (a
    # ResourceWarning in the tests) when it opened the file itself
    with (safe_files.replacing(path) as tmp, open(tmp, "wb") as fh,
          PdfPages(fh, metadata=info) as pdf):  # fmt: skip
        summary = PdfSummary(pdf, plt, f"Acceptance report {run.meta.get('run_id', '')}")
        summary.title("Pre-flight acceptance report", verdict, COLOURS.get(verdict, "#b42318"))
        summary.sections(sections)
        summary.finish_page()
        for title, png in drawn:
            summary.figure(title, png)


def read_run(folder: Path, digest: str) -> RunFacts:
    """What the report reads of a run folder."""
    reader = RunReader(folder)
    try:
        return RunFacts(
            folder, reader.meta(), reader.results(), reader.steps(), reader.events(), digest
        )
    finally:
        reader.close()


def build_report(folder: Path) -> tuple[Path, Path]:
    """Write ``report.html``, ``report.pdf`` and ``report.txt`` for a run folder, each replacing
    its name (never written through a link), and enter them in the run's manifest."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = read_run(folder, data_hash(folder))  # one pass over every row, shared by the three
    reader = RunReader(folder)
    try:
        figs = make_figures(reader, run.meta, run.results, plt)
        plain = {n: without_telemetry(reader, r) for n, r in calibrations(run.results).items()}
    finally:
        reader.close()
    drawn = [(title, render_figure(fig, plt)) for title, fig in figs]  # each drawn once
    images = [Image(title, scaled_png(png, HTML_DPI)) for title, png in drawn]
    sections = report_sections(run, plain, images)
    verdict = verdict_of(run)
    paths = (folder / "report.txt", folder / "report.html", folder / "report.pdf")
    safe_files.write_text(paths[0], _text(run, sections, verdict))
    safe_files.write_text(paths[1], _html(run, sections, verdict))
    _pdf(paths[2], run, sections, verdict, drawn)
    # the closed run's manifest learns the reports' digests: 'rig verify' tells an edit from these
    record_written(folder, list(paths), "the rig wrote the reports")
    return paths[1], paths[2]
