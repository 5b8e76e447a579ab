"""A calibration's report plots and comparisons use the samples it was fitted on (its stored
selection), never every field step at another settling."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rig.analysis import calibrate_run, stored_run_data
from rig.calibration.record import CalibrationRecord, latest_calibration
from rig.calibration.synthetic import cage_like
from rig.report.acceptance import calibration_series, without_telemetry
from rig.steps import field_kinds
from rig.store import RunReader, new_run


def _two_sweep_run(runs: Path) -> Path:
    """Two field steps; the calibration is fitted on the first only, settled 0.3 s after the load
    changes (every field step at 0.25 s would be another data set)."""
    case = cage_like(400, seed=7, noise_ut=0.02, channels=1)
    s = case.samples
    w = new_run(runs, "SN-SEL", procedure="selection", dut_serial="SN-SEL", operator="test",
                magnetometers={"dut": "dut", "reference": "reference"}, loads=list(s.channels),
                software_version="test")  # fmt: skip
    t = 100.0 + np.arange(s.n) * 0.05
    w.set_step(0, "sweep A", "sphere_sweep", float(t[0]) - 0.5, float(t[199]) + 0.01)
    w.set_step(1, "sweep B", "sphere_sweep", float(t[200]) - 0.01, float(t[-1]) + 0.5)
    for i in range(s.n):
        w.add_sample(float(t[i]), "dut", tuple(s.measured_ut[i]))
        w.add_sample(float(t[i]), "reference", tuple(case.field_ut[i]))
        w.add_channel(float(t[i]) - 0.001, s.channels[0], float(s.telemetry[i, 0]),
                      float(s.telemetry[i, 0]))  # fmt: skip
    for k in range(0, 200, 40):  # load changes in the first sweep: settling removes samples
        w.add_command(float(t[k]), 0, "load", {"channel": s.channels[0], "current_a": 1.0})
    w.flush()
    reader = RunReader(w.folder)
    params = {"model": "vector", "method": "", "magnetometer": "dut",
              "telemetry": list(s.channels), "steps": ["sweep A"], "noise_nt": 20.0,
              "settle_s": 0.3}  # fmt: skip
    cal = calibrate_run(reader, params, {"dut": "dut", "reference": "reference"}, None,
                        field_kinds())  # fmt: skip
    reader.close()
    w.set_result("cal", cal)
    w.close("complete", "synthetic")
    return w.folder


def test_report_residuals_are_the_calibrate_steps_own_samples(tmp_path: Path) -> None:
    folder = _two_sweep_run(tmp_path)
    reader = RunReader(folder)
    try:
        found = latest_calibration(reader.results())
        assert found is not None
        name, record = found
        sel = record.selection
        assert name == "cal" and sel is not None
        assert sel.steps == ("sweep A",) and sel.settle_s == 0.3 and sel.dut == "dut"
        everything = stored_run_data(reader, list(record.channels), field_kinds=field_kinds())
        series = calibration_series(reader, reader.meta(), record)
        plain = without_telemetry(reader, record)
    finally:
        reader.close()
    assert series is not None and plain is not None
    assert everything.samples.n != record.samples  # the selections differ
    assert series["residual_nt"].shape == (record.samples, 3)
    rms = float(np.sqrt(np.mean(series["residual_nt"] ** 2)))
    assert abs(rms - record.residual_rms_nt) < 1e-6 * max(1.0, rms)
    assert plain.samples == record.samples


def test_the_stored_value_reads_back_unchanged(tmp_path: Path) -> None:
    folder = _two_sweep_run(tmp_path)
    reader = RunReader(folder)
    try:
        stored = reader.results()["cal"]
    finally:
        reader.close()
    assert CalibrationRecord.from_dict(stored).to_dict() == stored


def test_an_old_run_without_a_selection_still_reads() -> None:
    folder = Path(__file__).parents[1] / "data" / "loaded-demo-wrong-fail"
    reader = RunReader(folder)
    try:
        results = reader.results()
    finally:
        reader.close()
    found = latest_calibration(results, "vector")
    assert found is not None and found[0] == "vector calibration"
    assert found[1].selection is None
    assert (
        CalibrationRecord.from_dict(results["vector calibration"]).to_dict()
        == results["vector calibration"]
    )
