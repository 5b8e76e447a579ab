"""The acceptance report's sections, built once from a closed run and rendered as HTML, PDF and text
(rig.report.section_model, rig.report.pdf), so the three files cannot say different things. A step kind's
own lines come from the kind (``StepKind.report_lines``); a calibration's from its typed record."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rig.calibration.record import CalibrationRecord, calibrations
from rig.report.section_model import Image, Para, Section, Table
from rig.report.text_report import limit_text, overall_verdict, seal_note
from rig.steps import KINDS
from rig.store.instruments import config_copy, instruments
from rig.verdict import CheckVerdict, check_verdict

SPRINGMANN_UNITS = {"a": "", "b": "", "c": "", "x0_ut": "uT", "y0_ut": "uT", "z0_ut": "uT",
                    "rho_deg": "deg", "phi_deg": "deg", "lambda_deg": "deg"}  # fmt: skip


@dataclass(frozen=True)
class RunFacts:
    """What the report reads of a closed run."""

    folder: Path
    meta: dict[str, Any]
    results: dict[str, Any]
    steps: list[tuple[int, str, str, float, float | None]]
    events: list[tuple[float, str, str]]
    digest: str
    """The data's SHA-256 (rig.store.seal), recomputed."""


def num(v: float, sig: float | None = None) -> str:
    """``v ± sig`` with as many decimals as the 1-sigma supports."""
    if sig is None or not math.isfinite(sig) or sig <= 0:
        return f"{v:.6g}"
    digits = max(0, min(8, 1 - math.floor(math.log10(sig))))
    return f"{v:.{digits}f} ± {sig:.{digits}f}"


CLOCK_ROW = "Time"
SIMULATED_TIME = (
    "SIMULATED: a dry run on the simulated cage in simulated time (ADR 0038); no instrument was"
    " driven, dates are the simulation's"
)
"""The header row of a run recorded on the simulated clock: its verdict is a rehearsal's."""


def header_section(run: RunFacts) -> Section:
    """Who, what, when, on which instruments, and the data's digest."""
    meta = run.meta
    dut = meta.get("magnetometers", {}).get("dut", "dut")
    instruments = meta.get("instruments", {})
    rows = [
        ("Procedure", meta.get("procedure", "")), ("Run", meta.get("run_id", "")),
        ("DUT serial", meta.get("dut_serial", "")), ("DUT model", instruments.get(dut, "")),
        ("Operator", meta.get("operator", "")), ("Date", meta.get("start_time", "")),
        ("Status", f"{meta.get('status', 'incomplete')} ({meta.get('reason', '')})"),
        *(((CLOCK_ROW, SIMULATED_TIME),) if meta.get("clock") == "simulated" else ()),
        ("Software", f"rig {meta.get('software_version', '')}"),
        ("Rig configuration", meta.get("rig_config", "")),
        ("Cage calibration", cage_record_text(meta.get("cage_model") or {})),
        ("Data SHA-256", f"data sha256 {run.digest} ({seal_note(run.folder, run.digest)})"),
    ]  # fmt: skip
    return Section("", (Table(("", ""), tuple((k, str(v)) for k, v in rows), row_heads=True),))


def instruments_section(run: RunFacts) -> Section:
    """Every instrument of the run: what it answered, its serial and its calibration certificate
    (from the run's copy of the rig configuration), an expired one flagged."""
    answered = run.meta.get("instruments", {})
    found = instruments(config_copy(run.folder / "rig.toml"), run.meta.get("start_time"))
    rows = []
    for i in found:
        status = ("EXPIRED before the run" if i.expired else "valid" if i.expired is False
                  else "no expiry date given")  # fmt: skip
        rows.append((i.name, str(answered.get(i.name) or i.kind), i.serial or "-",
                     str(i.calibrated_on or "-"), str(i.certificate_expires or "-"), status))  # fmt: skip
    blocks: list[Para | Table] = []
    for i in found:
        if i.expired:
            blocks.append(Para(f"WARNING: the certificate of '{i.name}' (serial {i.serial or '-'})"
                               f" expired on {i.certificate_expires}, before this run: what it"
                               " measured rests on an expired calibration."))  # fmt: skip
    header = ("device", "model (as it answered)", "serial", "calibrated", "expires", "certificate")
    return Section(
        "Instruments",
        (*blocks, Table(header, tuple(rows)))
        if rows
        else (Para("The run's copy of the rig configuration names no instruments."),),
    )


def cage_record_text(record: dict[str, Any]) -> str:
    """The cage calibration record a run used, cited: its date and file, and each metrology
    result's date and the run it came from."""
    if not record.get("date"):
        return "nominal (not characterized)"
    text = f"{record['date']}"
    if record.get("file"):
        text += f" ({Path(str(record['file'])).name})"
    for kind, entry in sorted((record.get("metrology") or {}).items()):
        if isinstance(entry, dict):
            text += f"; {kind.replace('_', ' ')} of {entry.get('date', '?')} (run {entry.get('run', '?')})"
    return text


def criteria_section(verdict: CheckVerdict | None) -> Section:
    """The acceptance criteria: value, limits, margin and verdict per row."""
    title = "Acceptance criteria"
    if verdict is None:
        return Section(title, (Para("No acceptance criteria were evaluated in this run."),))
    rows = []
    for row in verdict.criteria:
        if row.value is not None:
            rows.append((row.name, *limit_text(row), str(row.verdict)))
        else:
            rows.append((row.name, row.reason, "", "", "FAIL"))
    header = ("criterion", "measured", "limits", "margin", "verdict")
    return Section(title, (Table(header, tuple(rows), verdict_col=4),))


def _result_line(name: str, value: Any) -> str:
    """A result no kind describes: its top-level numbers with their unit-named keys."""
    if not isinstance(value, dict):
        return f"{name}: {value}"
    parts = [f"{k} {v:.4g}" for k, v in value.items()
             if isinstance(v, int | float) and not isinstance(v, bool)]  # fmt: skip
    return f"{name}: " + (", ".join(parts[:8]) or "(see 'rig show RUN --json')")


def step_results_section(run: RunFacts) -> Section:
    """What each step's kind says of its result (noise, spectrum, linearity, cage model...)."""
    cals = calibrations(run.results)
    lines: list[Para] = []
    for _, name, kind, _, _ in run.steps:
        if name not in run.results or name in cals or kind not in KINDS:
            continue
        said = KINDS[kind].report_lines(name, run.results[name])
        lines += [Para(line) for line in (said or [_result_line(name, run.results[name])])]
    return Section("Step results", tuple(lines))


def _parameter_table(res: CalibrationRecord, alt: CalibrationRecord | None) -> Table:
    combined = res.stored.get("combined_sigma", {}).get("springmann")
    header: tuple[str, ...] = ("parameter", "with telemetry", "unit", "sigma / CRLB")
    header += ("combined 1-sigma",) if combined else ()
    header += ("without telemetry",) if alt else ()
    rows: list[tuple[str, ...]] = []
    for key, unit in SPRINGMANN_UNITS.items():
        row: tuple[str, ...] = (
            key,
            num(res.springmann[key], res.sigma_of(key)),
            unit,
            f"{res.ratio_of(key):.2f}",
        )
        row += (f"{float(combined.get(key, math.nan)):.2g}",) if combined else ()
        row += (num(alt.springmann[key], alt.sigma_of(key)),) if alt else ()
        rows.append(row)
    rms: tuple[str, ...] = ("residual rms", f"{res.residual_rms_nt:.1f}", "nT", "")
    rms += ("",) if combined else ()
    rows.append(rms + ((f"{alt.residual_rms_nt:.1f}",) if alt else ()))
    return Table(header, tuple(rows))


def _coefficient_table(res: CalibrationRecord) -> Table:
    sig = res.sigma.get("k_ut_per_unit", {})
    rows = tuple(
        (ch, *(num(v, e) for v, e in zip(k, sig.get(ch, [math.nan] * 3), strict=True)), "uT/A")
        for ch, k in res.k_ut_per_unit.items()
    )
    return Table(("channel", "k x", "k y", "k z", "unit"), rows)


def _selection_line(res: CalibrationRecord) -> Para:
    sel = res.selection
    if sel is None:
        return Para("Samples: every field step settled 0.25 s (recorded before results named"
                    " their selection)", "note")  # fmt: skip
    return Para(f"Samples: steps {', '.join(sel.steps) or '-'} of {sel.dut} against"
                f" {sel.reference}, settled {sel.settle_s:g} s after each change; left out"
                f" {sel.unresolved} unresolved and {sel.misdated} misdated")  # fmt: skip


def _fit_lines(res: CalibrationRecord) -> list[Para]:
    cr = res.stored.get("crassidis", {})
    au = res.angular_uncertainty_deg
    lines = [
        Para("Crassidis form: b = (" + ", ".join(f"{v:.4f}" for v in cr.get("b_ut", [])) + ") uT,"
             f" D = {np.round(np.array(cr.get('D', [])), 6).tolist()}"),
        Para(f"Residual rms {res.residual_rms_nt:.1f} nT, mean {res.residual_mean_nt:.1f} nT,"
             f" max {res.residual_max_nt:.1f} nT; chi-square {res.chi2.get('reduced', math.nan):.2f}"
             f" per dof ({res.chi2.get('verdict', '-')}); angular uncertainty"
             f" {au.get('20_ut', math.nan):.3f} deg at 20 uT, {au.get('50_ut', math.nan):.3f} deg"
             " at 50 uT."),
    ]  # fmt: skip
    if res.mounting_deg is not None:
        lines.append(Para("DUT mounting rotation (rotation vector): "
                          + ", ".join(f"{v:+.3f}" for v in res.mounting_deg) + " deg"))  # fmt: skip
    return lines


def _live_blocks(res: CalibrationRecord) -> list[Para | Table]:
    live = res.live
    if live is None:
        return []
    rows = []
    for key, sigma in live.sigma_at_stop.items():
        limit = live.targets.get(key)
        met = "-" if limit is None else ("PASS" if sigma <= limit else "FAIL")
        rows.append((key, f"{sigma:.3g}", "-" if limit is None else f"{limit:g}", met))
    return [
        Para(
            f"Live calibration: stopped because {live.stopped}; {live.updates} samples used over"
            f" {live.elapsed_s:.1f} s at {live.noise_nt:.1f} nT noise."
        ),
        Table(("target", "1-sigma at stop", "target 1-sigma", "met"), tuple(rows), verdict_col=3),
    ]


def _share(value: float, statistical: float) -> str:
    """A budget entry: two digits, or 0 for one a million times below the statistical term."""
    return "0" if abs(value) < 1e-6 * abs(statistical) else f"{value:.2g}"


def _budget_blocks(res: CalibrationRecord) -> list[Para | Table]:
    """The uncertainty budget: per parameter its statistical 1-sigma, each cage group's
    contribution, the combined 1-sigma and the term that limits it (ADR 0028)."""
    budget = res.stored.get("uncertainty_budget")
    if not isinstance(budget, dict):
        return [Para("No uncertainty budget: the cage's terms are not in these sigmas (a result"
                     " recorded before budgets, or the calibration was refitted without them)",
                     "note")]  # fmt: skip
    groups = budget.get("groups", {})
    combined = res.stored.get("combined_sigma", {}).get("springmann", {})
    stat = budget.get("statistical", {}).get("springmann", {})
    rows = []
    for key, unit in SPRINGMANN_UNITS.items():
        parts = {"statistical": float(stat.get(key, math.nan))}
        parts |= {g: float(c.get("springmann", {}).get(key, math.nan)) for g, c in groups.items()}
        top = max(budget.get("terms", []), default=None,
                  key=lambda t: abs(t["contribution"]["springmann"].get(key, 0.0)))  # fmt: skip
        limiting = max(parts, key=lambda g: parts[g])
        if top is not None and limiting != "statistical":
            limiting = f"{top['group']}: {top['name']}"
        rows.append((key, unit, *(_share(v, parts["statistical"]) for v in parts.values()),
                     f"{float(combined.get(key, math.nan)):.2g}", limiting))  # fmt: skip
    header = ("parameter", "unit", "statistical", *groups, "combined", "limited by")
    blocks: list[Para | Table] = [
        Para("Uncertainty budget (1-sigma): " + str(budget.get("propagation", ""))),
        Table(header, tuple(rows)),
    ]
    blocks += [Para(f"Not in the budget: {why}", "note") for why in budget.get("left_out", [])]
    return blocks


def calibration_section(
    name: str, res: CalibrationRecord, alt: CalibrationRecord | None
) -> Section:
    """A calibration: parameters with sigma and sigma/CRLB (and the fit on the same samples
    without telemetry, ``alt``), current-to-bias coefficients, both forms, residuals, the samples
    it used, a live block, its warnings."""
    title = (f"Calibration '{name}': {res.model} model, method {res.method},"
             f" {res.samples} samples")  # fmt: skip
    blocks: list[Para | Table] = [_selection_line(res), _parameter_table(res, alt)]
    if res.k_ut_per_unit:
        blocks.append(_coefficient_table(res))
    blocks += _fit_lines(res)
    if res.live is None:
        blocks += _budget_blocks(res)
    else:
        blocks.append(Para("The live calibration's sigmas are its filter's (statistical): the"
                           " cage's terms are in the batch calibrations' budgets (ADR 0028)",
                           "note"))  # fmt: skip
    blocks += _live_blocks(res)
    blocks += [Para(w, "note") for w in res.warnings]
    return Section(title, tuple(blocks))


def plots_section(figs: Sequence[Image]) -> Section:
    """Every figure as an embedded PNG (the PDF has them on pages of their own)."""
    return Section("Plots", tuple(figs), frozenset(("html",)))


def step_label(index: int, name: str, kind: str) -> str:
    """A step's name, or for a step the procedure did not name (``check 11``) what its kind
    does."""
    step_kind = KINDS.get(kind)
    if step_kind is None or name != f"{kind} {index + 1}":
        return name
    return step_kind.label(index)


def steps_section(steps: Sequence[tuple[int, str, str, float, float | None]]) -> Section:
    """Each step with its kind and how long it took."""
    rows = tuple((str(i + 1), step_label(i, name, kind), kind,
                  f"{t1 - t0:.1f} s" if t1 is not None else "not finished")
                 for i, name, kind, t0, t1 in steps)  # fmt: skip
    return Section("Steps", (Table(("#", "step", "kind", "duration"), rows),))


def log_section(events: Sequence[tuple[float, str, str]], t_start: float) -> Section:
    """Operator actions, warnings, errors and limit events, in run time (s)."""
    rows = tuple((f"{t - t_start:.1f}", level, message) for t, level, message in events
                 if level in ("operator", "warning", "error") or "limit" in message)  # fmt: skip
    return Section("Log", (Table(("t (s)", "level", "message"), rows),) if rows else ())


def approval_section() -> Section:
    """Lines to sign: who prepared the report, who reviewed and approved it, when."""
    line = "_" * 28
    blank = ("", "", "", "")  # room to sign on paper
    rows = [(role, line, "_" * 14, line) for role in ("Prepared by", "Reviewed by", "Approved by")]
    spaced = tuple(r for row in rows for r in (blank, row))
    return Section("Approval", (Table(("", "name", "date", "signature"), spaced),))


def report_sections(
    run: RunFacts,
    plain: dict[str, CalibrationRecord | None] | None = None,
    figs: Sequence[Image] = (),
) -> list[Section]:
    """The report, top to bottom; ``plain``: each calibration re-fitted without telemetry."""
    plain = plain or {}
    t_start = float(run.meta.get("start_monotonic", run.events[0][0] if run.events else 0.0))
    return [
        header_section(run),
        criteria_section(check_verdict(run.results)),
        instruments_section(run),
        step_results_section(run),
        *(calibration_section(n, r, plain.get(n)) for n, r in calibrations(run.results).items()),
        plots_section(figs),
        steps_section(run.steps),
        log_section(run.events, t_start),
        approval_section(),
    ]


def verdict_of(run: RunFacts) -> str:
    """PASS, FAIL, NO VERDICT or why the run is no acceptance (rig.report.text_report)."""
    return overall_verdict(run.meta, run.results)
