"""The pre-flight acceptance report: one self-contained HTML file and a PDF, from a run folder.

Everything comes from the run's store (meta, results, samples, channels, events), so a report can
be rebuilt at any time with ``rig report RUN``. Plots are rendered with matplotlib (Agg) and
embedded as data URIs; the HTML loads nothing from outside.
"""

from __future__ import annotations

import base64
import csv
import datetime as dt
import html
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.analysis import stored_run_data
from rig.calibration import calibrate
from rig.calibration.targets import SIGMA_TARGETS, group_of
from rig.errors import RigError
from rig.report.text_report import (
    criterion_line,
    data_hash,
    limit_text,
    overall_verdict,
    seal_note,
    write_text_report,
)
from rig.steps import KINDS, field_kinds
from rig.store.run_store import RunReader

Array = npt.NDArray[np.float64]
SPRINGMANN_UNITS = {"a": "", "b": "", "c": "", "x0_ut": "uT", "y0_ut": "uT", "z0_ut": "uT",
                    "rho_deg": "deg", "phi_deg": "deg", "lambda_deg": "deg"}  # fmt: skip


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
        s, t = stored_run_data(reader, channels, field_kinds=field_kinds())
    except RigError:
        return None
    w = np.array(res["correction"]["matrix"])
    o = np.array(res["correction"]["offset_ut"])
    k = np.array([res["correction"]["k_ut_per_unit"][c] for c in channels]).reshape(-1, 3)
    bias = o + (s.telemetry @ k if k.size else 0.0)
    corrected = (s.measured_ut - bias) @ w.T
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
        for i, axis in enumerate("xyz"):
            ax.plot(t, series["residual_nt"][:, i], ".", ms=2, label=f"residual {axis}")
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
        ax.hist(r, bins=60, color="tab:blue", alpha=0.8)
        ax.set_xlabel("residual per axis (nT)")
        ax.set_ylabel("samples")
        ax.set_title(f"rms {np.sqrt(np.mean(r**2)):.1f} nT, mean {np.mean(r):.1f} nT", fontsize=9)
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


def read_history(path: Path) -> tuple[list[str], Array] | None:
    """A live calibration's history CSV: header and rows (elapsed s, samples, p..., sigma...)."""

    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        return rows[0], np.array(rows[1:], float).reshape(len(rows) - 1, len(rows[0]))
    except (OSError, ValueError, IndexError):
        return None


def _convergence_figure(folder: Path, live: dict[str, Any], plt: Any) -> Any:
    """One panel per target group: each parameter's 1-sigma against time, the target dashed, the
    stop marked."""

    table = read_history(folder / str(live.get("history_file", "")))
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
        s, _ = stored_run_data(reader, [], field_kinds=field_kinds())
        if res["model"] == "scalar":
            s = s.as_scalar()
        return calibrate(s, res["method"]).to_dict()
    except RigError:
        return None


def _esc(x: Any) -> str:
    return html.escape(str(x))


def _num(v: float, sig: float | None = None) -> str:
    if sig is None or not math.isfinite(sig) or sig <= 0:
        return f"{v:.6g}"
    digits = max(0, min(8, 1 - math.floor(math.log10(sig))))
    return f"{v:.{digits}f} &plusmn; {sig:.{digits}f}"


def build_report(folder: Path) -> tuple[Path, Path]:
    """Write ``report.html`` and ``report.pdf`` (and ``report.txt``) for a run folder."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    digest = data_hash(folder)  # one pass over every row, shared by the three files
    write_text_report(folder, digest)
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

    # ---- HTML ----
    colour = "#1a7f37" if overall == "PASS" else "#b42318"
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>Acceptance report {_esc(meta.get('dut_serial', ''))}</title><style>",
        "body{font-family:Helvetica,Arial,sans-serif;max-width:980px;margin:24px auto;color:#111;font-size:14px}",
        "table{border-collapse:collapse;margin:8px 0 18px}td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}",
        "th{background:#eee}.verdict{font-size:26px;font-weight:bold;padding:10px;color:#fff}",
        ".PASS{color:#1a7f37;font-weight:bold}.FAIL{color:#b42318;font-weight:bold}img{max-width:100%}",
        "h2{border-bottom:2px solid #333;margin-top:28px}@media print{h2{page-break-before:auto}}",
        "</style></head><body>",
        f"<h1>Pre-flight acceptance report: {_esc(meta.get('procedure', ''))}</h1>",
        f"<div class='verdict' style='background:{colour}'>VERDICT: {_esc(overall)}</div>",
        "<table>"
        + "".join(f"<tr><th>{_esc(k)}</th><td>{_esc(v)}</td></tr>" for k, v in header)
        + "</table>",
        "<h2>Acceptance criteria</h2>",
    ]
    if verdict:
        parts.append(
            "<table><tr><th>criterion</th><th>measured</th><th>limits</th><th>margin</th><th>verdict</th></tr>"
        )
        for row in verdict["criteria"]:
            if "value" in row:
                value, limits, margin = limit_text(row)
                parts.append(f"<tr><td>{_esc(row['name'])}</td><td>{_esc(value)}</td><td>{_esc(limits)}</td>"
                             f"<td>{_esc(margin)}</td><td class='{row['verdict']}'>{row['verdict']}</td></tr>")  # fmt: skip
            else:
                parts.append(
                    f"<tr><td>{_esc(row['name'])}</td><td colspan='3'>{_esc(row['reason'])}</td><td class='FAIL'>FAIL</td></tr>"
                )
        parts.append("</table>")
    else:
        parts.append("<p>No acceptance criteria were evaluated in this run.</p>")
    step_parts = [
        KINDS[kind].report_html(name, results[name])
        for _, name, kind, _, _ in steps
        if kind in KINDS and name in results
    ]
    if any(step_parts):
        parts.append("<h2>Step results</h2>" + "".join(step_parts))
    for name, res in cals.items():
        sp, sig = res["springmann"], res["sigma"]["springmann"]
        ratio = res["crlb_ratio"]["springmann"]
        parts.append(
            f"<h2>Calibration '{_esc(name)}': {res['model']} model, method {res['method']}, {res['samples']} samples</h2>"
        )
        alt = plain.get(name)
        parts.append("<table><tr><th>parameter</th><th>with telemetry</th><th>unit</th><th>sigma / CRLB</th>"
                     + ("<th>without telemetry</th>" if alt else "") + "</tr>")  # fmt: skip
        for key, unit in SPRINGMANN_UNITS.items():
            cells = f"<td>{_esc(key)}</td><td>{_num(sp[key], sig[key])}</td><td>{unit}</td><td>{ratio[key]:.2f}</td>"
            if alt:
                cells += f"<td>{_num(alt['springmann'][key], alt['sigma']['springmann'][key])}</td>"
            parts.append(f"<tr>{cells}</tr>")
        rms_row = (
            f"<tr><th>residual rms</th><td>{res['residual_rms_nt']:.1f}</td><td>nT</td><td></td>"
        )
        rms_row += f"<td>{alt['residual_rms_nt']:.1f}</td>" if alt else ""
        parts.append(rms_row + "</tr></table>")
        parts.append(
            "<table><tr><th>channel</th><th>k x</th><th>k y</th><th>k z</th><th>unit</th></tr>"
        )
        for ch, k in res["correction"]["k_ut_per_unit"].items():
            s = res["sigma"]["k_ut_per_unit"][ch]
            parts.append(
                f"<tr><td>{_esc(ch)}</td>"
                + "".join(f"<td>{_num(v, e)}</td>" for v, e in zip(k, s, strict=True))
                + "<td>uT/A</td></tr>"
            )
        parts.append("</table>")
        cr = res["crassidis"]
        parts.append("<p>Crassidis form: b = (" + ", ".join(f"{v:.4f}" for v in cr["b_ut"]) + ") uT, D = "
                     + _esc(np.round(np.array(cr["D"]), 6).tolist()) + "</p>")  # fmt: skip
        au = res["angular_uncertainty_deg"]
        parts.append(f"<p>Residual rms {res['residual_rms_nt']:.1f} nT, mean {res['residual_mean_nt']:.1f} nT, max {res['residual_max_nt']:.1f} nT; "
                     f"chi-square {res['chi2']['reduced']:.2f} per dof ({_esc(res['chi2']['verdict'])}); angular uncertainty "
                     f"{au['20_ut']:.3f} deg at 20 uT, {au['50_ut']:.3f} deg at 50 uT.</p>")  # fmt: skip
        if res.get("mounting", {}).get("observable"):
            parts.append(
                "<p>DUT mounting rotation (rotation vector): "
                + ", ".join(f"{v:+.3f}" for v in res["mounting"]["rotation_vector_deg"])
                + " deg</p>"
            )
        live = res.get("live")
        if isinstance(live, dict):
            parts.append(
                f"<p>Live calibration: stopped because {_esc(live['stopped'])}; {live['updates']} samples"
                f" used over {live['elapsed_s']:.1f} s at {live['noise_nt']:.1f} nT noise.</p>"
                "<table><tr><th>target</th><th>1-sigma at stop</th><th>target 1-sigma</th><th>met</th></tr>"
            )
            for key, sigma in live["sigma_at_stop"].items():
                limit = live["targets"].get(key)
                met = "-" if limit is None else ("PASS" if sigma <= limit else "FAIL")
                parts.append(f"<tr><td>{_esc(key)}</td><td>{sigma:.3g}</td><td>{'-' if limit is None else f'{limit:g}'}</td>"
                             f"<td class='{met}'>{met}</td></tr>")  # fmt: skip
            parts.append("</table>")
        for w in res.get("warnings", []):
            parts.append(f"<p><i>{_esc(w)}</i></p>")
    parts.append("<h2>Plots</h2>")
    for f in figs:
        parts.append(
            f"<h3>{_esc(f.title)}</h3><img alt='{_esc(f.title)}' src='data:image/png;base64,{base64.b64encode(f.png).decode()}'>"
        )
    parts.append(
        "<h2>Steps</h2><table><tr><th>#</th><th>step</th><th>kind</th><th>duration</th></tr>"
    )
    for idx, name, kind, t0, t1 in steps:
        parts.append(
            f"<tr><td>{idx + 1}</td><td>{_esc(name)}</td><td>{_esc(kind)}</td><td>{('%.1f s' % (t1 - t0)) if t1 else 'not finished'}</td></tr>"
        )
    parts.append("</table><h2>Log</h2><table><tr><th>t (s)</th><th>level</th><th>message</th></tr>")
    t_start = float(meta.get("start_monotonic", events[0][0] if events else 0.0))
    for t, level, message in events:
        if level in ("operator", "warning", "error") or "limit" in message:
            parts.append(
                f"<tr><td>{t - t_start:.1f}</td><td>{_esc(level)}</td><td>{_esc(message)}</td></tr>"
            )
    parts.append(
        f"</table><p>Generated {dt.datetime.now(dt.UTC).isoformat(timespec='seconds')} by rig {meta.get('software_version', '')}.</p></body></html>"
    )
    html_path = folder / "report.html"
    html_path.write_text("\n".join(parts), encoding="utf-8")

    # ---- PDF ----
    pdf_path = folder / "report.pdf"
    pdf_info = {"Title": f"Acceptance report {meta.get('run_id', '')}",
                "Subject": f"VERDICT: {overall}; data sha256 {digest}"}  # fmt: skip
    with PdfPages(pdf_path, metadata=pdf_info) as pdf:
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
        y -= 0.015
        if verdict:
            page.text(0.06, y, "Acceptance criteria", fontsize=11, weight="bold")
            y -= 0.025
            for row in verdict["criteria"]:
                line = criterion_line(row)
                page.text(
                    0.06,
                    y,
                    line,
                    fontsize=8,
                    family="monospace",
                    color="#1a7f37" if row["verdict"] == "PASS" else "#b42318",
                )
                y -= 0.018
        for name, res in cals.items():
            y -= 0.015
            page.text(
                0.06,
                y,
                f"Calibration '{name}' ({res['model']}, {res['method']}, {res['samples']} samples)",
                fontsize=11,
                weight="bold",
            )
            y -= 0.022
            for key, unit in SPRINGMANN_UNITS.items():
                page.text(
                    0.08,
                    y,
                    f"{key:<11} {res['springmann'][key]:+.6f} +- {res['sigma']['springmann'][key]:.6f} {unit}",
                    fontsize=8,
                    family="monospace",
                )
                y -= 0.016
            for ch, k in res["correction"]["k_ut_per_unit"].items():
                page.text(
                    0.08,
                    y,
                    f"k[{ch}] " + "  ".join(f"{v:+.4f}" for v in k) + " uT/A",
                    fontsize=8,
                    family="monospace",
                )
                y -= 0.016
            page.text(
                0.08,
                y,
                f"residual rms {res['residual_rms_nt']:.1f} nT; angular uncertainty {res['angular_uncertainty_deg']['50_ut']:.3f} deg at 50 uT",
                fontsize=8,
            )
            y -= 0.02
            if isinstance(res.get("live"), dict):
                page.text(
                    0.08, y, f"live calibration stopped: {res['live']['stopped']}", fontsize=8
                )
                y -= 0.02
            if y < 0.1:
                break
        pdf.savefig(page)
        plt.close(page)
        for f in figs:
            f.fig.suptitle(f.title, fontsize=10)
            pdf.savefig(f.fig, bbox_inches="tight")
            plt.close(f.fig)
    return html_path, pdf_path
