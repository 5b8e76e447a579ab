"""Each step result a kind stores is a typed record (ADR 0024): the real step's stored mapping reads
back as its record and writes back as the very same mapping (stored run folders do not change), an
old stored result still reads, and a malformed one is a one-line StoredResultError naming the key,
or is skipped by the report as before (its numbers listed instead of the kind's lines)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from rig.calibration.record import latest_calibration
from rig.engine.page_feed import corrected_dut
from rig.errors import StoredResultError
from rig.lab.summary import criteria, stored_verdict
from rig.report.sections import RunFacts, criteria_section, step_results_section
from rig.report.text_report import limit_text, overall_verdict
from rig.steps import KINDS
from rig.steps.characterize_cage import CageCharacterizationResult
from rig.steps.linearity import LinearityResult
from rig.steps.noise_spectrum import NoiseSpectrumResult
from rig.store.run_states import Verdict
from rig.verdict import CheckVerdict, CriterionResult, check_verdict
from tests.steps.fake_context import FakeContext, carry_out, held_fields, make_procedure, make_step
from tests.steps.test_step_results import LinearCage

DEMO_RUN = Path(__file__).parent / "data" / "loaded-demo-wrong-fail" / "run.sqlite"
"""A run folder recorded by the rig (the loaded demo, failing): its results as stored."""


def stored_texts() -> dict[str, str]:
    """The demo run's results as the JSON text stored, read without touching the file."""
    con = sqlite3.connect(f"file:{DEMO_RUN}?immutable=1", uri=True)
    try:
        return dict(con.execute("SELECT name, value FROM results").fetchall())
    finally:
        con.close()


def round_trips(record_type: Any, stored: dict[str, Any]) -> None:
    """``stored`` -> record -> the same mapping, and the same JSON text the store writes."""
    back = record_type.from_dict(stored).to_dict()
    assert back == stored
    assert json.dumps(back) == json.dumps(stored)


# --- results of the real steps read back unchanged ----------------------------------------------


def linearity_result(tmp_path: Path) -> dict[str, Any]:
    step = make_step("linearity", {"points": 7, "dwell_s": 1}, name="lin")
    ctx = FakeContext(make_procedure(step), tmp_path)
    fields = np.concatenate([np.eye(3)[a] * np.linspace(-80, 80, 7)[:, None] for a in range(3)])
    window = held_fields(ctx.recording, fields, 1.0, lambda b: 1.0 + 1.01 * b + 3e-4 * b**2,
                         t0=0.0, step=(0, "lin", "linearity"))  # fmt: skip
    result: dict[str, Any] = carry_out(ctx, step, window)
    return result


def spectrum_result(tmp_path: Path) -> dict[str, Any]:
    step = make_step("noise_spectrum", {"hold_s": 60, "band_hz": [0.1, 5]}, name="spectrum")
    ctx = FakeContext(make_procedure(step), tmp_path)
    t = 100.0 + np.arange(0.0, 60.0, 0.05)
    ctx.recording.add_field(100.0, [0, 0, 0])
    noise = 0.05 * np.random.default_rng(4).standard_normal((t.size, 3))
    ctx.recording.add_samples("dut", t, noise)
    result: dict[str, Any] = carry_out(ctx, step, (100.0, 160.0))
    return result


def characterization_result(tmp_path: Path) -> dict[str, Any]:
    k = np.diag([41.0, 39.0, 43.0]) + 0.3
    cage = LinearCage(k, np.array([18.0, -2.5, 41.0]), noise_ut=0.05)
    step = make_step("characterize_cage", {"amplitude_a": 1.0, "samples": 5, "repeats": 1})
    ctx = FakeContext(make_procedure(step), tmp_path, controller=cage,
                      cfg=SimpleNamespace(cage=None))  # fmt: skip
    result: dict[str, Any] = carry_out(ctx, step)
    return result


def check_result(tmp_path: Path) -> dict[str, Any]:
    criteria_ = [
        {"result": "floor", "value": "dut_noise_nt", "max": 50, "name": "DUT noise"},
        {"result": "lin", "value": "nonlinearity_ppm", "min": 0.0, "max": 2000.0},
        {"result": "missing", "value": "rms_nt", "max": 1},
    ]
    step = make_step("check", {"criteria": criteria_})
    results = {"floor": {"dut_noise_nt": 20.0}, "lin": {"nonlinearity_ppm": 2500.0}}
    ctx = FakeContext(make_procedure(step), tmp_path, results=results)
    carry_out(ctx, step)
    verdict: dict[str, Any] = ctx.results["verdict"]
    return verdict


def test_a_linearity_result_reads_back_as_stored(tmp_path: Path) -> None:
    stored = linearity_result(tmp_path)
    round_trips(LinearityResult, stored)
    record = LinearityResult.from_dict(stored)
    assert record.full_scale_ut == 80.0 and set(record.points) == {"x", "y", "z"}
    assert record.points["y"].gain == pytest.approx(1.01, abs=1e-9)
    assert record.nonlinearity_ppm == max(record.axis_nonlinearity_ppm.values())


def test_a_noise_spectrum_result_reads_back_as_stored(tmp_path: Path) -> None:
    stored = spectrum_result(tmp_path)
    round_trips(NoiseSpectrumResult, stored)
    record = NoiseSpectrumResult.from_dict(stored)
    assert record.device == "dut" and record.band_hz == (0.1, 5.0)
    assert record.rate_hz == pytest.approx(20.0)
    assert record.band_density_nt_per_rthz == max(record.axis_band_density_nt_per_rthz)


def test_a_cage_characterization_result_reads_back_as_stored(tmp_path: Path) -> None:
    stored = characterization_result(tmp_path)
    round_trips(CageCharacterizationResult, stored)
    record = CageCharacterizationResult.from_dict(stored)
    assert np.allclose(record.k_ut_per_a, np.diag([41.0, 39.0, 43.0]) + 0.3, atol=0.05)
    assert len(record.b0_sigma_ut) == 3 and record.condition_number > 1.0


def test_a_check_verdict_reads_back_as_stored(tmp_path: Path) -> None:
    stored = check_result(tmp_path)
    round_trips(CheckVerdict, stored)
    verdict = CheckVerdict.from_dict(stored)
    assert verdict.overall == Verdict.FAIL and verdict.rerun == ()
    assert [c.verdict for c in verdict.criteria] == [Verdict.PASS, Verdict.FAIL, Verdict.FAIL]
    assert verdict.failed == ["lin.nonlinearity_ppm", "missing.rms_nt"]
    noise, lin, missing = verdict.criteria
    assert (noise.unit, noise.max, noise.margin) == ("nT", 50, 30.0)
    assert isinstance(noise.max, int)  # a limit written as an int is stored as one
    assert lin.unit == "ppm" and lin.margin == pytest.approx(-500.0)
    assert missing.value is None and "no result 'missing'" in missing.reason


def test_the_results_of_a_recorded_run_read_back_to_the_same_stored_text() -> None:
    """The demo run folder's stored JSON, byte for byte, from each record's to_dict."""
    texts = stored_texts()
    records = {"linearity": LinearityResult, "noise spectrum": NoiseSpectrumResult,
               "cage model": CageCharacterizationResult, "verdict": CheckVerdict}  # fmt: skip
    for name, record_type in records.items():
        assert json.dumps(record_type.from_dict(json.loads(texts[name])).to_dict()) == texts[name]


def test_a_verdict_recorded_before_criteria_carried_units_still_reads() -> None:
    """Rows as the first check step wrote them (no ``unit``; a failed row only its reason)."""
    old = {
        "criteria": [
            {"name": "noise.dut_noise_nt", "value": 12.5, "min": None, "max": 50, "margin": 37.5,
             "verdict": "PASS"},
            {"name": "fit.residual_rms_nt", "verdict": "FAIL", "reason": "no result 'fit'"},
        ],
        "overall": "FAIL",
    }  # fmt: skip
    round_trips(CheckVerdict, old)
    row = CheckVerdict.from_dict(old).criteria[0]
    assert row.unit is None
    assert limit_text(row) == ("12.5 nT", "max 50 nT", "37.5 nT")  # the unit from its name


def test_a_rerun_verdict_keeps_its_steps_and_reasons() -> None:
    stored = {"criteria": [{"name": "fit", "value": 30.0, "unit": "nT", "min": None, "max": 60,
                            "margin": 30.0, "verdict": "PASS"}],
              "overall": "RE-RUN", "rerun": [{"result": "fit", "why": "timing fault: 40 of 900"}]}  # fmt: skip
    round_trips(CheckVerdict, stored)
    assert CheckVerdict.from_dict(stored).rerun == (("fit", "timing fault: 40 of 900"),)
    line = overall_verdict({"status": "re-run"}, {"verdict": stored})
    assert line == "RE-RUN - NOT JUDGED, RUN AGAIN (fit: timing fault: 40 of 900)"


# --- malformed stored results --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("record_type", "make", "key", "bad", "message"),
    [
        (LinearityResult, linearity_result, "full_scale_ut", None,
         r"stored linearity result has no 'full_scale_ut'"),
        (LinearityResult, linearity_result, "nonlinearity_ppm", "386",
         r"linearity result: 'nonlinearity_ppm' must be a number, got '386'"),
        (NoiseSpectrumResult, spectrum_result, "device", None,
         r"stored noise spectrum result has no 'device'"),
        (NoiseSpectrumResult, spectrum_result, "band_hz", [0.1],
         r"noise spectrum result: 'band_hz' must hold 2 numbers, got 1"),
        (NoiseSpectrumResult, spectrum_result, "samples", 230.5,
         r"noise spectrum result: 'samples' must be a whole number"),
        (CageCharacterizationResult, characterization_result, "b0_sigma_ut", None,
         r"stored cage characterization result has no 'b0_sigma_ut'"),
        (CageCharacterizationResult, characterization_result, "k_ut_per_a", [[1, 0, 0]],
         r"cage characterization result: 'k_ut_per_a' must be a 3x3 matrix"),
        (CheckVerdict, check_result, "overall", None, r"stored check verdict has no 'overall'"),
        (CheckVerdict, check_result, "overall", "MAYBE",
         r"check verdict: 'overall' must be one of PASS, FAIL, RE-RUN, got 'MAYBE'"),
        (CheckVerdict, check_result, "criteria", {"name": "x"},
         r"check verdict: 'criteria' must be a list"),
    ],
    ids=["linearity-missing", "linearity-type", "spectrum-missing", "spectrum-band",
         "spectrum-samples", "cage-missing", "cage-matrix", "verdict-missing", "verdict-value",
         "verdict-criteria"],
)  # fmt: skip
def test_a_malformed_result_is_an_error_naming_the_key(
    tmp_path: Path, record_type: Any, make: Any, key: str, bad: Any, message: str
) -> None:
    stored = make(tmp_path)
    broken = {k: v for k, v in stored.items() if k != key}
    if bad is not None:
        broken[key] = bad
    with pytest.raises(StoredResultError, match=message):
        record_type.from_dict(broken)


def test_a_malformed_criterion_row_names_the_criterion(tmp_path: Path) -> None:
    stored = check_result(tmp_path)
    stored["criteria"][0]["value"] = "20 nT"
    with pytest.raises(StoredResultError, match=r"check criterion 'DUT noise': 'value' must be a"):
        check_verdict({"verdict": stored})
    del stored["criteria"][0]["name"]
    with pytest.raises(StoredResultError, match=r"stored check criterion has no 'name'"):
        CriterionResult.from_dict(stored["criteria"][0])


def test_the_report_skips_a_malformed_result_of_a_kind_and_lists_its_numbers(
    tmp_path: Path,
) -> None:
    """As before: the kind says nothing of a result it cannot read (no lines, no figure) and the
    report shows the result's top-level numbers instead of failing."""
    lin, spectrum = linearity_result(tmp_path), spectrum_result(tmp_path)
    del lin["axis_nonlinearity_ppm"]
    spectrum["samples"] = "many"
    assert KINDS["linearity"].report_lines("lin", lin) == []
    assert KINDS["linearity"].figures(None, "lin", lin, None) == []
    assert KINDS["noise_spectrum"].report_lines("spectrum", spectrum) == []
    steps = [(0, "lin", "linearity", 0.0, 21.0), (1, "spectrum", "noise_spectrum", 21.0, 81.0)]
    run = RunFacts(tmp_path, {}, {"lin": lin, "spectrum": spectrum}, steps, [], "0" * 64)
    lines = [p.text for p in step_results_section(run).blocks]
    assert lines[0].startswith("lin: nonlinearity_ppm ") and "full_scale_ut 80" in lines[0]
    assert lines[1].startswith("spectrum: density_1hz_nt_per_rthz ")
    intact = {"lin": linearity_result(tmp_path)}
    said = step_results_section(RunFacts(tmp_path, {}, intact, steps[:1], [], "0" * 64)).blocks
    assert said[0].text.startswith("Linearity lin: ")


def test_the_verdict_is_read_through_its_record_by_the_report_and_the_lab(tmp_path: Path) -> None:
    stored = check_result(tmp_path)
    verdict = check_verdict({"verdict": stored, "other": {"x": 1.0}})
    assert verdict is not None and check_verdict({"other": {}}) is None
    table = criteria_section(verdict).blocks[0]
    assert [r[0] for r in table.rows] == ["DUT noise", "lin.nonlinearity_ppm", "missing.rms_nt"]
    assert table.rows[0][1:] == ("20 nT", "max 50 nT", "30 nT", "PASS")
    lab = criteria(stored_verdict({"verdict": stored}))
    assert [(c.name, c.unit, c.margin, c.verdict) for c in lab[:2]] == [
        ("DUT noise", "nT", 30.0, "PASS"), ("lin.nonlinearity_ppm", "ppm", -500.0, "FAIL")]  # fmt: skip
    # the lab index takes a run from elsewhere without a verdict it cannot read, not refusing it
    assert stored_verdict({"verdict": {"overall": "PASS"}}) is None
    assert criteria(None) == []


# --- the engine's corrected DUT reading: the run's latest calibration -------------------------


def test_corrected_dut_applies_the_latest_calibration_of_the_run() -> None:
    def calibration(scale: float) -> dict[str, Any]:
        return {"model": "vector", "method": "vector", "samples": 10, "residual_rms_nt": 1.0,
                "springmann": {"a": scale},
                "correction": {"matrix": (scale * np.eye(3)).tolist(), "offset_ut": [1.0, 0, 0],
                               "k_ut_per_unit": {"bus": [0.5, 0.0, 0.0]}}}  # fmt: skip

    runner = SimpleNamespace(results={}, commanded_loads={"bus": 2.0})
    raw = np.array([11.0, 2.0, 3.0])
    assert corrected_dut(runner, raw) is None
    runner.results = {"first": calibration(2.0), "floor": {"dut_noise_nt": 20.0},
                      "second": calibration(3.0)}  # fmt: skip
    assert latest_calibration(runner.results) is not None
    corrected = corrected_dut(runner, raw)
    assert np.allclose(corrected, 3.0 * (raw - [1.0, 0, 0] - [1.0, 0, 0]))  # offset, 0.5 uT/A x 2 A
    assert corrected_dut(runner, None) is None
