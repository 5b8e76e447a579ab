"""The frequency_response step through the wire protocols on the simulated cage: a DUT whose
readings pass a first-order low-pass of 8 ms (a 20 Hz corner: 2.9 degrees of lag at 1 Hz), a
reference of 1 ms (its certificate's, in the rig configuration), sines on each axis at 0.2, 0.5
and 1 Hz; the DUT's amplitude within 1 % and phase within 1 degree of the truth at each, and the
cage's own response measured. At 2 Hz (within the cage's bandwidth too) three runs gave 0.3-1.4 %
and up to 0.5 degree, its sigma 0.3-19 % as the computer was idle or loaded: not yet the 1 %
issue 37 asks for there, so not asserted here."""

from __future__ import annotations

import cmath
import dataclasses
import math
from pathlib import Path

import pytest

from sim.config import SimConfig, load_config
from sim.sensor_response import SensorResponse
from tests.simrun import run_on_sim

DUT_TAU_S, REF_TAU_S = 0.008, 0.001

PROCEDURE = """
procedure: frequency response
magnetometers: {dut: dut, reference: reference}
steps:
  - sphere_sweep: {directions: 36, magnitude_ut: [20, 45], dwell_s: 0.8, seed: 3}
    name: sweep
  - calibrate: {model: vector, steps: [sweep]}
    name: vector calibration
  - frequency_response: {frequencies_hz: [0.2, 0.5, 1.0], cycles: 3, amplitude_ut: 10, bias_ut: 30}
    name: bode
  - report: {}
"""


def config() -> SimConfig:
    cfg = load_config()
    # both at 100 Hz: the set-points' 25 Hz staircase resolved, not aliased onto the sine
    mags = tuple(dataclasses.replace(m, response_tau_s=DUT_TAU_S, rate_hz=100) if m.name == "dut" else
                 dataclasses.replace(m, response_tau_s=REF_TAU_S, rate_hz=100) if m.name == "reference" else m
                 for m in cfg.magnetometers)  # fmt: skip
    return dataclasses.replace(cfg, magnetometers=mags)


@pytest.mark.slow
def test_the_dut_response_within_1_percent_and_1_degree_of_the_truth(tmp_path: Path) -> None:
    outcome = run_on_sim(tmp_path, PROCEDURE, sim_config=config())
    assert outcome.status == "complete", outcome.reason
    r = outcome.results["bode"]
    assert r["frame"] == "sensor" and "tau 0.001 s" in r["reference_response"]
    truth = SensorResponse(DUT_TAU_S, 0.0)
    judged = 0
    for axis, points in r["axes"].items():
        for p in points:
            want = truth.transfer(p["f_hz"])
            assert p["cage_amplitude"] > 0.5, p  # the cage's own response, measured
            if not p["within_bandwidth"]:
                continue
            judged += 1
            assert p["amplitude"] == pytest.approx(abs(want), abs=0.01), (axis, p)
            assert p["phase_deg"] == pytest.approx(math.degrees(cmath.phase(want)), abs=1.0), (
                axis,
                p,
            )
    assert judged == 9 and r["cage_bandwidth_hz"] == 1.0
    assert r["amplitude_error_max"] < 0.02 and r["phase_abs_max_deg"] < 4.0
    assert "Frequency response &#x27;bode&#x27;" in (outcome.folder / "report.html").read_text()
