"""The cross_field step through the wire protocols on the simulated cage: a DUT with known
cross-field coefficients, calibrated first (the fit is then in the sensor's own axes)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from rig.steps.cross_field import pairs
from sim.config import load_config
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

TRUTH = ((0.0, 300.0, -150.0), (-200.0, 0.0, 100.0), (120.0, 250.0, 0.0))  # ppm/uT

PROCEDURE = """
procedure: cross-field
magnetometers: {dut: dut, reference: reference}
steps:
  - sphere_sweep: {directions: 36, magnitude_ut: [20, 45], dwell_s: 0.8, seed: 3}
    name: sweep
  - calibrate: {model: vector, steps: [sweep]}
    name: vector calibration
  - cross_field: {transverse_ut: 40, dwell_s: 0.6, settle_s: 0.25}
    name: cross field
  - report: {}
"""


def test_the_coefficients_of_a_calibrated_dut_within_three_sigma_of_the_truth(
    tmp_path: Path,
) -> None:
    cfg = load_config()
    mags = tuple(dataclasses.replace(m, cross_field_ppm_per_ut=TRUTH) if m.name == "dut" else m
                 for m in cfg.magnetometers)  # fmt: skip
    outcome = run_on_sim(
        tmp_path, PROCEDURE, sim_config=dataclasses.replace(cfg, magnetometers=mags)
    )
    assert outcome.status == "complete", outcome.reason
    r = outcome.results["cross field"]
    assert r["frame"] == "sensor" and "calibration 'vector calibration'" in r["frame_note"]
    table, sigma = r["cross_field_ppm_per_ut"], r["sigma_ppm_per_ut"]
    z = [(table[i][j] - TRUTH[i][j]) / sigma[i][j] for i, j in pairs()]
    assert np.all(np.abs(z) < 3.0), (table, sigma)
    assert all(table[i][i] is None for i in range(3))
    assert r["max_abs_ppm_per_ut"] == pytest.approx(max(abs(table[i][j]) for i, j in pairs()))
    assert "Cross-field &#x27;cross field&#x27;" in (outcome.folder / "report.html").read_text()
