"""The pre-flight acceptance report: one self-contained HTML file and a PDF, from a run folder.

Everything comes from the run's store (meta, results, samples, channels, events), so a report can
be rebuilt at any time with ``rig report RUN``. Plots are rendered with matplotlib (Agg) and
embedded as data URIs; the HTML loads nothing from outside.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.analysis import apply_correction, stored_run_data
from rig.calibration import calibrate
from rig.calibration.targets import SIGMA_TARGETS, group_of
from rig.errors import RigError
from rig.report.scaling import mark_outliers, robust_limits
from rig.report.sections import (
    PdfLine,
    calibration_section,
    criteria_section,
    esc,
    log_section,
    plots_section,
    step_results_section,
    steps_section,
)
from rig.report.text_report import data_hash, overall_verdict, seal_note, write_text_report
from rig.steps import KINDS, field_kinds
from rig.store import safe_files
from rig.store.run_states import Verdict
from rig.store.run_store import RunReader
from rig.store.seal import record_written

Array = npt.NDArray[np.float64]


@dataclass
class Figure:
    """A rendered plot: title, PNG bytes, and the matplotlib figure for the PDF."""

    title: str
    png: bytes
    fig: Any


def _figure(title: str, fig: Any) -> Figure:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return Figure(title, buf.getvalue(), fig)


def _calibration_series(
    reader: RunReader, meta: dict[str, Any], res: dict[str, Any]
) -> dict[str, Array] | None:
    """Time series for the plots: DUT raw and corrected magnitude, reference magnitude, residual."""

    channels = list(res["channels"])
    try:
        s, t, *_ = stored_run_data(reader, channels, field_kinds=field_kinds())
    except RigError:
        return None
    corrected = apply_correction(res["correction"], s.measured_ut, s.telemetry, channels)
    return {
        "t": t - float(meta.get("start_monotonic", t[0])),
        "raw": np.linalg.norm(s.measured_ut, axis=1),
        "corrected": np.linalg.norm(corrected, axis=1),
        "reference": s.field_magnitude_ut,
        "residual_nt": 1000.0 * (corrected - (s.field_ut if s.field_ut is not None else 0.0)),
        "field": s.field_ut if s.field_ut is not None else np.zeros((s.n, 3)),
        "telemetry": s.telemetry,
        "channels": np.array(channels, dtype=object),
    }


def make_figures(reader: RunReader, meta: dict[str, Any], results: dict[str, Any]) -> list[Figure]:
    """Every plot the report shows, labelled with units."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs: list[Figure] = []
    cal_name = next(
        (n for n, r in results.items() if isinstance(r, dict) and r.get("model") == "vector"), None
    )
    cal_name = cal_name or next(
        (n for n, r in results.items() if isinstance(r, dict) and "springmann" in r), None
    )
    series = _calibration_series(reader, meta, results[cal_name]) if cal_name else None
    if series is not None:
        t = series["t"]
        fig, ax = plt.subplots(figsize=(9, 3.6))
        ax.plot(t, series["raw"], ".", ms=2, label="DUT raw |m|")
        ax.plot(t, series["corrected"], ".", ms=2, label="DUT calibrated |h|")
        ax.plot(t, series["reference"], "-", lw=0.8, label="reference |h|")
        ax.set_xlabel("time since start (s)")
        ax.set_ylabel("field magnitude (uT)")
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
        figs.append(_figure(f"Field magnitude: raw, calibrated ('{cal_name}') and reference", fig))

        fig, ax = plt.subplots(figsize=(9, 3.6))
        limits = robust_limits(series["residual_nt"])
        for i, axis in enumerate("xyz"):
            ax.plot(t, series["residual_nt"][:, i], ".", ms=2, label=f"residual {axis}")
        mark_outliers(ax, np.repeat(t, 3), series["residual_nt"].ravel(), limits, "nT")
        ax.set_xlabel("time since start (s)")
        ax.set_ylabel("calibrated minus reference (nT)")
        ax.grid(alpha=0.3)
        if series["telemetry"].size:
            ax2 = ax.twinx()
            for j, ch in enumerate(series["channels"]):
                ax2.plot(t, series["telemetry"][:, j], "-", lw=0.8, alpha=0.6, label=f"{ch} (A)")
            ax2.set_ylabel("load current (A)")
            ax2.legend(loc="upper right", fontsize=8)
        ax.legend(loc="upper left", fontsize=8)
        figs.append(_figure("Residual over time with the load currents", fig))

        fig, ax = plt.subplots(figsize=(6, 3.4))
        r = series["residual_nt"].ravel()
        limits = robust_limits(r)
        ax.hist(np.clip(r, limits.lo, limits.hi), bins=60, range=(limits.lo, limits.hi),
                color="tab:blue", alpha=0.8)  # fmt: skip
        ax.set_xlabel("residual per axis (nT)")
        ax.set_ylabel("samples")
        beyond = (f"; {limits.outside} beyond the axis, counted in its end bins (most extreme"
                  f" {limits.extreme:.0f} nT)" if limits.outside else "")  # fmt: skip
        ax.set_title(f"rms {np.sqrt(np.mean(r**2)):.1f} nT, mean {np.mean(r):.1f} nT{beyond}",
                     fontsize=9)  # fmt: skip
        figs.append(_figure("Residual histogram", fig))

        f = series["field"]
        f = f[np.linalg.norm(f, axis=1) > 2.0]  # a null field has no direction
        d = f / np.maximum(np.linalg.norm(f, axis=1), 1e-12)[:, None]
        fig = plt.figure(figsize=(7, 3.6))
        ax = fig.add_subplot(111, projection="mollweide")
        lon = np.arctan2(d[:, 1], d[:, 0])
        lat = np.arcsin(np.clip(d[:, 2], -1, 1))
        sc = ax.scatter(lon, lat, c=np.linalg.norm(f, axis=1), s=4, cmap="viridis")
        ax.grid(alpha=0.4)
        ax.tick_params(labelsize=7)
        fig.colorbar(sc, ax=ax, label="|B| (uT)", shrink=0.8)
        ax.set_title("applied field directions (cage frame, longitude = atan2(By, Bx))", fontsize=9)
        figs.append(_figure("Coverage of applied field directions", fig))
    for name, res in results.items():
        if isinstance(res, dict) and isinstance(res.get("live"), dict):
            fig = _convergence_figure(reader.folder, res["live"], plt)
            if fig is not None:
                figs.append(_figure(f"Live calibration '{name}': 1-sigma converging", fig))
    for _, name, kind, _, t1 in reader.steps():  # what each step's kind draws (rig.steps)
        step_kind = KINDS.get(kind)
        if step_kind is not None and t1 is not None and name in results:
            for title, fig in step_kind.figures(reader, name, results[name], plt):
                figs.append(_figure(title, fig))
    noise_step = next(
        (st for st in reader.steps() if st[2] == "null_field" and st[4] is not None), None
    )
    dut = meta.get("magnetometers", {}).get("dut", "dut")
    if noise_step is not None and noise_step[4] is not None:
        t_a, t_b = noise_step[3] + 0.3, noise_step[4]
        rows = np.array([r for r in reader.samples(dut) if t_a <= r[0] <= t_b], dtype=np.float64)
        if rows.size:
            fig, ax = plt.subplots(figsize=(9, 3.0))
            for i, axis in enumerate("xyz"):
                ax.plot(
                    rows[:, 0] - rows[0, 0],
                    1000 * (rows[:, 1 + i] - rows[:, 1 + i].mean()),
                    "-",
                    lw=0.8,
                    label=axis,
                )
            ax.set_xlabel("time in the null-field hold (s)")
            ax.set_ylabel("DUT reading minus mean (nT)")
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
            figs.append(_figure(f"Noise floor at null field ('{noise_step[1]}')", fig))
    return figs


MAX_HISTORY_BYTES = 64 << 20
"""A live calibration's history file larger than this is not plotted."""


def read_history(path: Path) -> tuple[list[str], Array] | None:
    """A live calibration's history CSV: header and rows (elapsed s, samples, p..., sigma...);
    None when missing, unreadable, a link or not a regular file."""

    try:
        text = safe_files.read_text(path, MAX_HISTORY_BYTES)
        rows = list(csv.reader(io.StringIO(text, newline="")))
        return rows[0], np.array(rows[1:], float).reshape(len(rows) - 1, len(rows[0]))
    except (OSError, ValueError, IndexError, safe_files.UnsafeFileError):
        return None


def _convergence_figure(folder: Path, live: dict[str, Any], plt: Any) -> Any:
    """One panel per target group: each parameter's 1-sigma against time, the target dashed, the
    stop marked."""

    name = str(live.get("history_file", ""))
    if not name or "/" in name or "\\" in name or name.startswith("."):
        return None  # a file of the run folder itself, never a path elsewhere
    table = read_history(folder / name)
    if table is None or table[1].shape[0] == 0:
        return None
    header, rows = table
    sigma_cols = [(i, h[len("sigma_") :]) for i, h in enumerate(header) if h.startswith("sigma_")]
    groups = [g for g in SIGMA_TARGETS if any(group_of(n)[0] == g for _, n in sigma_cols)]
    fig, axes = plt.subplots(1, len(groups), figsize=(3.0 * len(groups), 3.2), squeeze=False)
    t = rows[:, 0]
    for ax, group in zip(axes[0], groups, strict=True):
        for i, name in sigma_cols:
            g, factor = group_of(name)
            if g == group:
                ax.semilogy(t, factor * rows[:, i], lw=1.0, label=name)
        target = live.get("targets", {}).get(group)
        if target:
            ax.axhline(target, color="k", ls="--", lw=1.0, label="target")
        ax.axvline(float(live.get("elapsed_s", t[-1])), color="tab:red", lw=0.8, alpha=0.7)
        ax.set_title(SIGMA_TARGETS[group], fontsize=8)
        ax.set_xlabel("time in step (s)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6, loc="upper right")
    axes[0][0].set_ylabel("1-sigma")
    fig.suptitle(str(live.get("stopped", "")), fontsize=9)
    fig.tight_layout()
    return fig


def without_telemetry(reader: RunReader, res: dict[str, Any]) -> dict[str, Any] | None:
    """The same calibration re-fitted without the current channels (the Springmann comparison)."""

    if not res["channels"]:
        return None
    try:
        s, *_ = stored_run_data(reader, [], field_kinds=field_kinds())
        if res["model"] == "scalar":
            s = s.as_scalar()
        return calibrate(s, res["method"]).to_dict()
    except RigError:
        return None


def build_report(folder: Path) -> tuple[Path, Path]:
    """Write ``report.html`` and ``report.pdf`` (and ``report.txt``) for a run folder, each
    replacing its name (never written through a link), and enter them in the run's manifest."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    digest = data_hash(folder)  # one pass over every row, shared by the three files
    text_path = write_text_report(folder, digest, record=False)
    reader = RunReader(folder)
    try:
        meta, results, events = reader.meta(), reader.results(), reader.events()
        steps = reader.steps()
        figs = make_figures(reader, meta, results)
        cals = {n: r for n, r in results.items() if isinstance(r, dict) and "springmann" in r}
        plain = {n: without_telemetry(reader, r) for n, r in cals.items()}
    finally:
        reader.close()
    status = meta.get("status", "incomplete")
    verdict = results.get("verdict")
    overall = overall_verdict(meta, results)
    header = [
        ("Procedure", meta.get("procedure", "")), ("Run", meta.get("run_id", "")),
        ("DUT serial", meta.get("dut_serial", "")), ("DUT model", meta.get("instruments", {}).get(meta.get("magnetometers", {}).get("dut", "dut"), "")),
        ("Operator", meta.get("operator", "")), ("Date", meta.get("start_time", "")),
        ("Status", f"{status} ({meta.get('reason', '')})"), ("Software", f"rig {meta.get('software_version', '')}"),
        ("Rig configuration", meta.get("rig_config", "")),
        ("Cage calibration", meta.get("cage_model", {}).get("date", "nominal (not characterized)")),
        ("Instruments", "; ".join(f"{k}: {v}" for k, v in meta.get("instruments", {}).items())),
        ("Data SHA-256", f"data sha256 {digest} ({seal_note(folder, digest)})"),
    ]  # fmt: skip

    colour = "#1a7f37" if overall == Verdict.PASS else "#b42318"
    t_start = float(meta.get("start_monotonic", events[0][0] if events else 0.0))
    sections = [
        criteria_section(verdict),
        step_results_section(steps, results),
        *(calibration_section(name, res, plain.get(name)) for name, res in cals.items()),
        plots_section(figs),
        steps_section(steps),
        log_section(events, t_start),
    ]

    # ---- HTML ----
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>Acceptance report {esc(meta.get('dut_serial', ''))}</title><style>",
        "body{font-family:Helvetica,Arial,sans-serif;max-width:980px;margin:24px auto;color:#111;font-size:14px}",
        "table{border-collapse:collapse;margin:8px 0 18px}td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}",
        "th{background:#eee}.verdict{font-size:26px;font-weight:bold;padding:10px;color:#fff}",
        ".PASS{color:#1a7f37;font-weight:bold}.FAIL{color:#b42318;font-weight:bold}img{max-width:100%}",
        "h2{border-bottom:2px solid #333;margin-top:28px}@media print{h2{page-break-before:auto}}",
        "</style></head><body>",
        f"<h1>Pre-flight acceptance report: {esc(meta.get('procedure', ''))}</h1>",
        f"<div class='verdict' style='background:{colour}'>VERDICT: {esc(overall)}</div>",
        "<table>"
        + "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in header)
        + "</table>",
        *(sec.html for sec in sections if sec.html),
        f"<p>Generated {dt.datetime.now(dt.UTC).isoformat(timespec='seconds')} by rig {meta.get('software_version', '')}.</p></body></html>",
    ]  # fmt: skip
    html_path = folder / "report.html"
    safe_files.write_text(html_path, "\n".join(parts))

    # ---- PDF: a summary page from the same sections, then one page per figure ----
    pdf_path = folder / "report.pdf"
    pdf_info = {"Title": f"Acceptance report {meta.get('run_id', '')}",
                "Subject": f"VERDICT: {overall}; data sha256 {digest}"}  # fmt: skip
    with safe_files.replacing(pdf_path) as pdf_tmp, PdfPages(pdf_tmp, metadata=pdf_info) as pdf:
        page = plt.figure(figsize=(8.27, 11.69))  # A4 portrait
        y = 0.95
        page.text(0.06, y, "Pre-flight acceptance report", fontsize=16, weight="bold")
        y -= 0.04
        page.text(0.06, y, f"VERDICT: {overall}", fontsize=14, weight="bold", color=colour)
        y -= 0.04
        for k, v in header:
            text = str(v)
            page.text(0.06, y, f"{k}:", fontsize=8, weight="bold")
            page.text(0.28, y, text if len(text) < 95 else text[:92] + "...", fontsize=8)
            y -= 0.02
        for line in (line for sec in sections for line in sec.pdf):
            if y < 0.06:
                page.text(0.06, y, "(more in report.html)", fontsize=8, style="italic")
                break
            y = _pdf_line(page, line, y)
        pdf.savefig(page)
        plt.close(page)
        for f in figs:
            f.fig.suptitle(f.title, fontsize=10)
            pdf.savefig(f.fig, bbox_inches="tight")
            plt.close(f.fig)
    # the closed run's manifest learns the reports' digests: 'rig verify' tells an edit from these
    record_written(folder, [text_path, html_path, pdf_path], "the rig wrote the reports")
    return html_path, pdf_path


PDF_COLOURS = {"PASS": "#1a7f37", "FAIL": "#b42318"}


def _pdf_line(page: Any, line: PdfLine, y: float) -> float:
    """Draw one summary line at height ``y`` (figure fraction); returns the next line's height."""
    if line.style == "heading":
        y -= 0.015
        page.text(0.06, y, line.text, fontsize=11, weight="bold")
        return y - 0.025
    mono = line.style != "text"
    page.text(0.08 if line.style == "mono" or not mono else 0.06, y, line.text, fontsize=8,
              family="monospace" if mono else None, color=PDF_COLOURS.get(line.style, "#111111"))  # fmt: skip
    return y - 0.018
