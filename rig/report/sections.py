"""The acceptance report's sections. Each renders one part of a closed run as HTML and as lines for
the PDF's summary page; the report is the list of them (rig.report.acceptance), so the HTML and the
PDF cannot say different things. A step kind's own paragraph comes from the kind
(``StepKind.report_html``)."""

from __future__ import annotations

import base64
import html
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np

from rig.report.text_report import criterion_line, limit_text
from rig.steps import KINDS
from rig.store.run_states import Verdict

SPRINGMANN_UNITS = {"a": "", "b": "", "c": "", "x0_ut": "uT", "y0_ut": "uT", "z0_ut": "uT",
                    "rho_deg": "deg", "phi_deg": "deg", "lambda_deg": "deg"}  # fmt: skip

Style = Literal["heading", "text", "mono", "PASS", "FAIL"]


@dataclass(frozen=True)
class PdfLine:
    """One line of the PDF summary page: ``heading``, ``text``, ``mono`` or a verdict colour."""

    text: str
    style: Style = "text"


@dataclass(frozen=True)
class Section:
    """A part of the report: its HTML (headed by its own ``<h2>``) and its PDF summary lines."""

    html: str
    pdf: tuple[PdfLine, ...] = ()


class Plot(Protocol):
    """A rendered figure (rig.report.acceptance.Figure)."""

    title: str
    png: bytes


def esc(x: Any) -> str:
    """Text for HTML."""
    return html.escape(str(x))


def num(v: float, sig: float | None = None) -> str:
    """``v +- sig`` with as many decimals as the 1-sigma supports (HTML)."""
    if sig is None or not math.isfinite(sig) or sig <= 0:
        return f"{v:.6g}"
    digits = max(0, min(8, 1 - math.floor(math.log10(sig))))
    return f"{v:.{digits}f} &plusmn; {sig:.{digits}f}"


def criteria_section(verdict: dict[str, Any] | None) -> Section:
    """The acceptance criteria: value, limits, margin and verdict per row."""
    if not verdict:
        return Section(
            "<h2>Acceptance criteria</h2><p>No acceptance criteria were evaluated in this run.</p>"
        )
    rows = ["<h2>Acceptance criteria</h2><table><tr><th>criterion</th><th>measured</th>"
            "<th>limits</th><th>margin</th><th>verdict</th></tr>"]  # fmt: skip
    lines = [PdfLine("Acceptance criteria", "heading")]
    for row in verdict["criteria"]:
        if "value" in row:
            value, limits, margin = limit_text(row)
            rows.append(f"<tr><td>{esc(row['name'])}</td><td>{esc(value)}</td><td>{esc(limits)}</td>"
                        f"<td>{esc(margin)}</td><td class='{row['verdict']}'>{row['verdict']}</td></tr>")  # fmt: skip
        else:
            rows.append(f"<tr><td>{esc(row['name'])}</td><td colspan='3'>{esc(row['reason'])}</td>"
                        "<td class='FAIL'>FAIL</td></tr>")  # fmt: skip
        lines.append(
            PdfLine(criterion_line(row), "PASS" if row["verdict"] == Verdict.PASS else "FAIL")
        )
    return Section("".join(rows) + "</table>", tuple(lines))


def step_results_section(steps: Sequence[tuple[Any, ...]], results: dict[str, Any]) -> Section:
    """What each step's kind says of its result (noise spectrum, linearity, ...)."""
    parts = [
        KINDS[kind].report_html(name, results[name])
        for _, name, kind, _, _ in steps
        if kind in KINDS and name in results
    ]
    parts = [p for p in parts if p]
    if not parts:
        return Section("")
    lines = [PdfLine(html.unescape(re.sub(r"<[^>]+>", "", p))) for p in parts]
    return Section(
        "<h2>Step results</h2>" + "".join(parts), (PdfLine("Step results", "heading"), *lines)
    )


def calibration_section(name: str, res: dict[str, Any], alt: dict[str, Any] | None) -> Section:
    """A calibration result: parameters with sigma and sigma/CRLB (and the fit without telemetry
    beside it, ``alt``), current-to-bias coefficients, both forms, residuals, a live block."""
    sp, sig = res["springmann"], res["sigma"]["springmann"]
    ratio = res["crlb_ratio"]["springmann"]
    parts = [
        f"<h2>Calibration '{esc(name)}': {res['model']} model, method {res['method']}, {res['samples']} samples</h2>",
        "<table><tr><th>parameter</th><th>with telemetry</th><th>unit</th><th>sigma / CRLB</th>"
        + ("<th>without telemetry</th>" if alt else "") + "</tr>",
    ]  # fmt: skip
    lines = [
        PdfLine(
            f"Calibration '{name}' ({res['model']}, {res['method']}, {res['samples']} samples)",
            "heading",
        )
    ]
    for key, unit in SPRINGMANN_UNITS.items():
        cells = f"<td>{esc(key)}</td><td>{num(sp[key], sig[key])}</td><td>{unit}</td><td>{ratio[key]:.2f}</td>"
        if alt:
            cells += f"<td>{num(alt['springmann'][key], alt['sigma']['springmann'][key])}</td>"
        parts.append(f"<tr>{cells}</tr>")
        lines.append(PdfLine(f"{key:<11} {sp[key]:+.6f} +- {sig[key]:.6f} {unit}", "mono"))
    rms_row = f"<tr><th>residual rms</th><td>{res['residual_rms_nt']:.1f}</td><td>nT</td><td></td>"
    rms_row += f"<td>{alt['residual_rms_nt']:.1f}</td>" if alt else ""
    parts.append(rms_row + "</tr></table>")
    parts.append(
        "<table><tr><th>channel</th><th>k x</th><th>k y</th><th>k z</th><th>unit</th></tr>"
    )
    for ch, k in res["correction"]["k_ut_per_unit"].items():
        s = res["sigma"]["k_ut_per_unit"][ch]
        parts.append(f"<tr><td>{esc(ch)}</td>" + "".join(f"<td>{num(v, e)}</td>" for v, e in zip(k, s, strict=True))
                     + "<td>uT/A</td></tr>")  # fmt: skip
        lines.append(PdfLine(f"k[{ch}] " + "  ".join(f"{v:+.4f}" for v in k) + " uT/A", "mono"))
    parts.append("</table>")
    cr = res["crassidis"]
    parts.append("<p>Crassidis form: b = (" + ", ".join(f"{v:.4f}" for v in cr["b_ut"]) + ") uT, D = "
                 + esc(np.round(np.array(cr["D"]), 6).tolist()) + "</p>")  # fmt: skip
    au = res["angular_uncertainty_deg"]
    parts.append(f"<p>Residual rms {res['residual_rms_nt']:.1f} nT, mean {res['residual_mean_nt']:.1f} nT, max {res['residual_max_nt']:.1f} nT; "
                 f"chi-square {res['chi2']['reduced']:.2f} per dof ({esc(res['chi2']['verdict'])}); angular uncertainty "
                 f"{au['20_ut']:.3f} deg at 20 uT, {au['50_ut']:.3f} deg at 50 uT.</p>")  # fmt: skip
    lines.append(
        PdfLine(
            f"residual rms {res['residual_rms_nt']:.1f} nT; angular uncertainty {au['50_ut']:.3f} deg at 50 uT"
        )
    )
    if res.get("mounting", {}).get("observable"):
        parts.append("<p>DUT mounting rotation (rotation vector): "
                     + ", ".join(f"{v:+.3f}" for v in res["mounting"]["rotation_vector_deg"]) + " deg</p>")  # fmt: skip
    live = res.get("live")
    if isinstance(live, dict):
        parts.append(f"<p>Live calibration: stopped because {esc(live['stopped'])}; {live['updates']} samples"
                     f" used over {live['elapsed_s']:.1f} s at {live['noise_nt']:.1f} nT noise.</p>"
                     "<table><tr><th>target</th><th>1-sigma at stop</th><th>target 1-sigma</th><th>met</th></tr>")  # fmt: skip
        for key, sigma in live["sigma_at_stop"].items():
            limit = live["targets"].get(key)
            met = "-" if limit is None else ("PASS" if sigma <= limit else "FAIL")
            parts.append(f"<tr><td>{esc(key)}</td><td>{sigma:.3g}</td><td>{'-' if limit is None else f'{limit:g}'}</td>"
                         f"<td class='{met}'>{met}</td></tr>")  # fmt: skip
        parts.append("</table>")
        lines.append(PdfLine(f"live calibration stopped: {live['stopped']}"))
    parts += [f"<p><i>{esc(w)}</i></p>" for w in res.get("warnings", [])]
    return Section("".join(parts), tuple(lines))


def plots_section(figs: Sequence[Plot]) -> Section:
    """Every figure as an embedded PNG (the PDF has them on pages of their own)."""
    parts = ["<h2>Plots</h2>"]
    for f in figs:
        parts.append(f"<h3>{esc(f.title)}</h3><img alt='{esc(f.title)}' "
                     f"src='data:image/png;base64,{base64.b64encode(f.png).decode()}'>")  # fmt: skip
    return Section("".join(parts))


def steps_section(steps: Sequence[tuple[Any, ...]]) -> Section:
    """Each step with its kind and how long it took."""
    parts = ["<h2>Steps</h2><table><tr><th>#</th><th>step</th><th>kind</th><th>duration</th></tr>"]
    for idx, name, kind, t0, t1 in steps:
        took = f"{t1 - t0:.1f} s" if t1 else "not finished"
        parts.append(
            f"<tr><td>{idx + 1}</td><td>{esc(name)}</td><td>{esc(kind)}</td><td>{took}</td></tr>"
        )
    return Section("".join(parts) + "</table>")


def log_section(events: Sequence[tuple[float, str, str]], t_start: float) -> Section:
    """Operator actions, warnings, errors and limit events, in run time (s)."""
    parts = ["<h2>Log</h2><table><tr><th>t (s)</th><th>level</th><th>message</th></tr>"]
    for t, level, message in events:
        if level in ("operator", "warning", "error") or "limit" in message:
            parts.append(
                f"<tr><td>{t - t_start:.1f}</td><td>{esc(level)}</td><td>{esc(message)}</td></tr>"
            )
    return Section("".join(parts) + "</table>")
