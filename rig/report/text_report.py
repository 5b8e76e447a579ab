"""A plain-text run report (``report.txt``): what ran, on what, the results and the verdict."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from rig.store.run_store import RunReader


def data_hash(folder: Path) -> str:
    """SHA-256 of the run database (identifies the recorded data)."""
    h = hashlib.sha256()
    with (folder / "run.sqlite").open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


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


def write_text_report(folder: Path) -> Path:
    """Write ``report.txt`` for a run folder; returns its path."""
    reader = RunReader(folder)
    try:
        meta, results = reader.meta(), reader.results()
        steps = reader.steps()
    finally:
        reader.close()
    lines = [
        f"ACCEPTANCE REPORT - {meta.get('procedure', '')}",
        f"run {meta.get('run_id')}  status {meta.get('status')}",
        f"DUT serial {meta.get('dut_serial', '')}  operator {meta.get('operator', '')}",
        f"started {meta.get('start_time')}  software rig {meta.get('software_version')}",
        f"instruments: {meta.get('instruments', {})}",
        f"data sha256 {data_hash(folder)}",
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
        for row in verdict["criteria"]:
            if "value" in row:
                lines.append(
                    f"  {row['verdict']}  {row['name']}: {row['value']:.4g} (min {row['min']}, max {row['max']}, margin {row['margin']:.3g})"
                )
            else:
                lines.append(f"  {row['verdict']}  {row['name']}: {row['reason']}")
        lines.append(f"VERDICT: {verdict['overall']}")
    path = folder / "report.txt"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
