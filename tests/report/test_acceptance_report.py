"""Acceptance reports: verdict logic, self-contained HTML, a PDF that renders, aborted runs flagged."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from rig.analysis import calibrate_run, evaluate_criteria
from rig.cage_budget import cage_terms
from rig.calibration.synthetic import cage_like
from rig.report.acceptance import build_report
from rig.steps import field_kinds
from rig.store import RunReader, new_run
from tests.tools import require_tool

CRITERIA = [
    {"result": "cal", "value": "residual_rms_nt", "max": 60.0, "name": "fit residual"},
    {"result": "cal", "value": "springmann.a", "min": 0.9, "max": 1.1, "name": "scale x"},
]


def test_verdict_pass_fail_borderline_and_missing() -> None:
    results = {"cal": {"residual_rms_nt": 60.0, "springmann": {"a": 1.02}}}
    v = evaluate_criteria(results, CRITERIA)
    assert v["overall"] == "PASS" and v["criteria"][0]["margin"] == 0.0  # on the limit passes
    v = evaluate_criteria(
        {"cal": {"residual_rms_nt": 60.0001, "springmann": {"a": 1.02}}}, CRITERIA
    )
    assert (
        v["overall"] == "FAIL"
        and v["criteria"][0]["verdict"] == "FAIL"
        and v["criteria"][1]["verdict"] == "PASS"
    )
    v = evaluate_criteria({"cal": {"residual_rms_nt": 1.0, "springmann": {"a": 0.89}}}, CRITERIA)
    assert v["criteria"][1]["verdict"] == "FAIL" and v["criteria"][1]["margin"] == pytest.approx(
        -0.01
    )
    v = evaluate_criteria({}, CRITERIA)
    assert v["overall"] == "FAIL" and "no result 'cal'" in v["criteria"][0]["reason"]
    assert evaluate_criteria({}, [])["overall"] == "FAIL"  # nothing checked is not a pass


def synthetic_run(runs: Path, status: str = "complete") -> Path:
    """A stored run with a cage sweep: reference and DUT samples, two load channels, a calibration."""
    case = cage_like(400, seed=5, noise_ut=0.02, channels=2)
    s = case.samples
    w = new_run(runs, "SN-TEST", procedure="synthetic", dut_serial="SN-TEST", operator="test",
                magnetometers={"dut": "dut", "reference": "reference"}, loads=list(s.channels),
                software_version="test", instruments={"dut": "HMR2300 0001"})  # fmt: skip
    t = 100.0 + np.arange(s.n) * 0.05
    w.set_step(0, "sweep", "sphere_sweep", float(t[0]) - 1.0, float(t[-1]) + 1.0)
    for i in range(s.n):
        w.add_sample(float(t[i]), "dut", tuple(s.measured_ut[i]))
        w.add_sample(float(t[i]), "reference", tuple(case.field_ut[i]))  # same instant as the DUT
        for j, ch in enumerate(s.channels):
            w.add_channel(
                float(t[i]) - 0.001, ch, float(s.telemetry[i, j]), float(s.telemetry[i, j])
            )
    w.add_event(float(t[0]), "operator", "prompt 'mount the DUT': confirmed")
    w.flush()
    reader = RunReader(w.folder)
    params = {"model": "vector", "method": "", "magnetometer": "dut", "telemetry": list(s.channels),
              "steps": [], "noise_nt": 20.0, "settle_s": 0.0}  # fmt: skip
    reference = {"matrix": np.eye(3).tolist(), "position_m": [0.0, 0.0, -0.08]}
    cal = calibrate_run(reader, params, {"dut": "dut", "reference": "reference"}, None,
                        field_kinds(), cage_terms(reference, {}, 15.0))  # fmt: skip
    reader.close()
    w.set_result("cal", cal)
    w.set_result("verdict", evaluate_criteria({"cal": cal}, CRITERIA))
    w.close(status, "synthetic" if status == "complete" else "interrupted by the operator (Ctrl-C)")
    return w.folder


def test_html_is_self_contained_and_has_every_section(tmp_path: Path) -> None:
    folder = synthetic_run(tmp_path)
    html_path, pdf_path = build_report(folder)
    text = html_path.read_text()
    assert "VERDICT: PASS" in text and "SN-TEST" in text and "Data SHA-256" in text
    for needle in (
        "x0_ut",
        "k x",
        "sigma / CRLB",
        "without telemetry",
        "angular uncertainty",
        "Crassidis form",
        "Uncertainty budget (1-sigma)",  # the cage's terms (ADR 0028)
        "reference certificate",
        "limited by",
        "combined 1-sigma",
        "(k=2)",  # the scale criteria judged against the expanded uncertainty
        "Not in the budget: the cage&#x27;s homogeneity",
    ):
        assert needle in text, needle
    assert text.count("<img") >= 4 and "prompt" in text
    refs = re.findall(r"""(?:src|href)\s*=\s*['"]([^'"]+)""", text)
    assert refs and all(r.startswith("data:") for r in refs), [
        r[:40] for r in refs if not r.startswith("data:")
    ]
    assert "http://" not in text and "https://" not in text and "@import" not in text
    assert pdf_path.stat().st_size > 10_000


def test_pdf_renders_with_pdftoppm(tmp_path: Path) -> None:
    require_tool("pdftoppm", what="rendering the report's PDF")
    _, pdf_path = build_report(synthetic_run(tmp_path))
    subprocess.run(
        ["pdftoppm", "-r", "40", "-png", str(pdf_path), str(tmp_path / "page")], check=True
    )
    pages = sorted(tmp_path.glob("page-*.png"))
    assert len(pages) >= 5  # summary page and the plots
    assert all(p.stat().st_size > 2000 for p in pages)


def test_aborted_run_says_so_at_the_top(tmp_path: Path) -> None:
    html_path, _ = build_report(synthetic_run(tmp_path, status="aborted"))
    text = html_path.read_text()
    top = text[: text.index("Acceptance criteria")]
    assert "ABORTED RUN - NOT A VALID ACCEPTANCE" in top


def test_every_user_supplied_string_is_escaped(tmp_path: Path) -> None:
    """Serial, operator, procedure title, step names, log messages, criterion names: all text."""
    hostile = "<script>alert(1)</script>"
    w = new_run(tmp_path, "x", procedure=f"P {hostile}", dut_serial=f"SN{hostile}",
                operator="O'Brien & <b>co</b>", magnetometers={"dut": "dut"},
                instruments={"dut": "<img src=x onerror=alert(2)>"})  # fmt: skip
    w.set_step(0, f"step {hostile}", "hold", 1.0, 2.0)
    w.add_event(1.5, "operator", f"prompt '{hostile}': declined")
    w.set_result("verdict", {"overall": "FAIL", "criteria": [
        {"name": f"crit {hostile}", "verdict": "FAIL", "reason": f"no result '{hostile}'"}]})  # fmt: skip
    w.close("aborted", f"the operator declined: {hostile}")
    text = build_report(w.folder)[0].read_text()
    assert "<script" not in text and "<img src=x" not in text and "<b>co</b>" not in text
    assert text.count("&lt;script&gt;alert(1)&lt;/script&gt;") >= 5


def test_every_instrument_with_its_serial_and_certificate_an_expired_one_flagged(
    tmp_path: Path,
) -> None:
    """Issue 55: the budget is 'limited by reference certificate', so the signed record names
    the reference's serial and certificate; one that had expired when the run started is flagged
    above the table (the lab index kept these, the report did not)."""
    import datetime as dt

    folder = synthetic_run(tmp_path)
    reader = RunReader(folder)
    start = dt.date.fromisoformat(reader.meta()["start_time"][:10])
    reader.close()
    expired, valid = start - dt.timedelta(days=1), start + dt.timedelta(days=365)
    (folder / "rig.toml").write_text(
        f'[devices.reference]\nkind = "ascii-mag"\nserial = "FGM-3-0815"\n'
        f"calibrated_on = 2025-03-01\ncertificate_expires = {expired}\n"
        f'[devices.dut]\nkind = "hmr2300"\nserial = "0001"\ncertificate_expires = {valid}\n'
        '[devices.coil_x]\nkind = "riden-rd6006"\n'
    )
    text = build_report(folder)[0].read_text()
    section = text[text.index("<h2>Instruments") :]
    for needle in ("FGM-3-0815", "2025-03-01", str(expired), str(valid), "HMR2300 0001",
                   "riden-rd6006", "no expiry date given", "valid", "EXPIRED before the run"):  # fmt: skip
        assert needle in section, needle
    assert (f"certificate of &#x27;reference&#x27; (serial FGM-3-0815) expired on {expired}"
            in section)  # fmt: skip
    assert "certificate of &#x27;dut&#x27;" not in text
