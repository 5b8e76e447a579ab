"""A plain-text run report (``report.txt``): what ran, on what, the results and the verdict."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rig.analysis import value_unit
from rig.store import safe_files
from rig.store.run_states import ACCEPTANCE, RunStatus
from rig.store.run_store import RunReader
from rig.store.seal import data_digest, read_seal, record_written


def data_hash(folder: Path) -> str:
    """The run's data digest (SHA-256 of its rows, see :mod:`rig.store.seal`), recomputed."""
    return data_digest(folder / "run.sqlite")[0]


def seal_note(folder: Path, digest: str) -> str:
    """How ``digest`` compares with the run's seal, for the report header."""
    seal = read_seal(folder)
    if seal is None:
        return "not sealed (the run was still running, or recorded before runs were sealed)"
    if seal.get("data_sha256") != digest:
        return f"DATA CHANGED SINCE THE RUN WAS SEALED (sealed {seal.get('data_sha256')})"
    return f"matches the seal of {seal.get('sealed_at')}"


def overall_verdict(meta: dict[str, Any], results: dict[str, Any]) -> str:
    """PASS, FAIL or NO VERDICT for a closed run; a run that did not finish is never an acceptance."""
    status = meta.get("status", RunStatus.INCOMPLETE)
    if status not in ACCEPTANCE:
        return f"{str(status).upper()} RUN - NOT A VALID ACCEPTANCE"
    verdict = results.get("verdict")
    return str(verdict["overall"]) if verdict else "NO VERDICT"


def limit_text(row: dict[str, Any]) -> tuple[str, str, str]:
    """(value, limits, margin) of one criterion row, with its unit."""
    unit = row.get("unit")
    if unit is None:  # recorded before rows carried their unit
        unit = value_unit(str(row.get("name", "")))
    u = f" {unit}" if unit else ""
    lo, hi = row.get("min"), row.get("max")
    bounds = [f"{what} {v:g}{u}" for what, v in (("min", lo), ("max", hi)) if v is not None]
    limits = ", ".join(bounds) or "no limit"
    return f"{row['value']:.4g}{u}", limits, f"{row['margin']:.3g}{u}"


def criterion_line(row: dict[str, Any]) -> str:
    """One criterion as a line: verdict, name, value with unit, limits, margin."""
    if "value" not in row:
        return f"{row['verdict']:<4}  {row['name']}: {row['reason']}"
    value, limits, margin = limit_text(row)
    return f"{row['verdict']:<4}  {row['name']}: {value} ({limits}; margin {margin})"


def _calibration_lines(name: str, res: dict[str, Any]) -> list[str]:
    sp, sig = res["springmann"], res["sigma"]["springmann"]
    lines = [
        f"Calibration '{name}': {res['model']} model, method {res['method']}, {res['samples']} samples"
    ]
    for key, value in sp.items():
        lines.append(f"  {key:<12} {value:+12.6f}  +- {sig[key]:.6f}")
    for ch, k in res["correction"]["k_ut_per_unit"].items():
        s = res["sigma"]["k_ut_per_unit"][ch]
        lines.append(
            f"  k[{ch}]".ljust(15)
            + "  ".join(f"{v:+.4f}+-{e:.4f}" for v, e in zip(k, s, strict=True))
            + "  uT/A"
        )
    if res.get("mounting", {}).get("observable"):
        lines.append(
            "  mounting rotation vector (deg): "
            + " ".join(f"{v:+.3f}" for v in res["mounting"]["rotation_vector_deg"])
        )
    lines.append(
        f"  residual rms {res['residual_rms_nt']:.1f} nT, chi2 verdict: {res['chi2']['verdict']}"
    )
    return lines


def write_text_report(folder: Path, digest: str | None = None, *, record: bool = True) -> Path:
    """Write ``report.txt`` for a run folder (``digest``: its data digest when the caller has
    already computed it), never through a link; returns its path. ``record``: enter it in the
    closed run's manifest (the caller does, when it writes more reports)."""
    reader = RunReader(folder)
    try:
        meta, results = reader.meta(), reader.results()
        steps = reader.steps()
    finally:
        reader.close()
    digest = digest or data_hash(folder)
    lines = [
        f"ACCEPTANCE REPORT - {meta.get('procedure', '')}",
        f"VERDICT: {overall_verdict(meta, results)}",
        f"run {meta.get('run_id')}  status {meta.get('status')} ({meta.get('reason', '')})",
        f"DUT serial {meta.get('dut_serial', '')}  operator {meta.get('operator', '')}",
        f"started {meta.get('start_time')}  software rig {meta.get('software_version')}",
        f"instruments: {meta.get('instruments', {})}",
        f"data sha256 {digest} ({seal_note(folder, digest)})",
        "",
        "Steps:",
        *(
            f"  {i + 1:2d} {name} ({kind}) {('%.1f s' % (t1 - t0)) if t1 else 'not finished'}"
            for i, name, kind, t0, t1 in steps
        ),
        "",
    ]
    for name, res in results.items():
        if isinstance(res, dict) and "springmann" in res:
            lines += [*_calibration_lines(name, res), ""]
        elif name != "verdict":
            lines.append(f"{name}: {res}")
    verdict = results.get("verdict")
    if verdict:
        lines += ["", "Acceptance criteria:"]
        lines += [f"  {criterion_line(row)}" for row in verdict["criteria"]]
    lines.append(f"VERDICT: {overall_verdict(meta, results)}")
    path = folder / "report.txt"
    safe_files.write_text(path, "\n".join(lines) + "\n")
    if record:
        record_written(folder, [path], "the rig wrote the text report")
    return path
