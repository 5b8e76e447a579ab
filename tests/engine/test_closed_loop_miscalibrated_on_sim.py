"""A miscalibrated DUT in the closed loop on the simulated cage (issue 56), in simulated time: the
DUT mounted turned 60 degrees about z with 2 uT more offset on z than the default cage's (and its
scale and axis errors). Read raw, the loop's detumble differs from the all-software run with a
perfect sensor by what that error predicts (the software run with the DUT's own truth in its
model magnetometer); read through the run's calibration, the difference goes away."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from sim.config import SimConfig, load_config
from sim.physics import Magnetometer
from tests.engine.closed_loop_scenario import LOOP, calibration_steps, loop_step
from tests.simrun import run_on_sim
from tests.steps.test_closed_loop_step import software_detumble_s

pytestmark = pytest.mark.simcage

PROCEDURE = (
    """
procedure: closed loop with a miscalibrated DUT
magnetometers: {dut: dut, reference: reference}
steps:
  - characterize_cage: {amplitude_a: 1.0, samples: 5, repeats: 1}
    name: cage model
  - null_field: {hold_s: 2}
    name: noise floor
"""
    + calibration_steps(loads=False)
    + loop_step("raw", duration_s=240, readings="raw")
    + loop_step("calibrated", readings="calibrated")
)


def turned_dut() -> SimConfig:
    cfg = load_config()
    mags = tuple(
        dataclasses.replace(m, mounting_deg=(0.0, 0.0, 60.0),
                            offset_ut=(m.offset_ut[0], m.offset_ut[1], m.offset_ut[2] + 2.0))
        if m.name == "dut" else m
        for m in cfg.magnetometers
    )  # fmt: skip
    return dataclasses.replace(cfg, magnetometers=mags)


def test_a_miscalibrated_dut_changes_the_loop_as_predicted_and_its_calibration_takes_it_out(
    tmp_path: Path,
) -> None:
    cfg = turned_dut()
    outcome = run_on_sim(tmp_path, PROCEDURE, sim_config=cfg)
    assert outcome.status == "complete", outcome.reason
    raw, cal = outcome.results["raw"], outcome.results["calibrated"]
    # the prediction: the software run whose model magnetometer reads as this DUT does (its
    # truth without noise: scale, axes, the turn and the offset), with the noise the run measured
    truth = Magnetometer(next(m for m in cfg.magnetometers if m.name == "dut"),
                         np.random.default_rng(0))  # fmt: skip
    noise = {**LOOP, "duration_s": 240, "noise_nt": float(raw["noise_nt"])}
    predicted = software_detumble_s(lambda b: truth.truth_reading(b, {}), noise)
    print(f"turned DUT, raw: {raw['summary']} (predicted with its error {predicted:.1f} s);"
          f" calibrated: {cal['summary']}")  # fmt: skip
    assert raw["detumble_s"] is not None and predicted is not None
    assert raw["detumble_s"] == pytest.approx(predicted, rel=0.10)
    assert float(raw["difference_pct"]) > 15.0  # slower than with a perfect sensor
    assert cal["readings"] == "calibrated" and cal["detumble_s"] is not None
    assert abs(float(cal["difference_pct"])) <= 10.0, cal["summary"]
