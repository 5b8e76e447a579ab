"""The cage's bandwidth and the DUT's frequency response through the wire protocols on the
simulated cage. The cage: coils of L/R 24-26 ms behind 50 Hz set-points (a zero-order hold), its
half-power frequency measured by ``cage_response`` within 5 % of that truth and kept in the cage
record (on a computer too busy to send the set-points on time, points known worse than 2 % are
named and left out, and the limit kept is never above the truth). The DUT: readings through a first-order low-pass of 8 ms (a 20 Hz corner), the reference
of 1 ms (its certificate's, in the rig configuration), both at 100 Hz; sines on each axis at
0.5-5.5 Hz (up to the cage's measured bandwidth, 5.8-6.1 Hz): the DUT's amplitude within 1 % and
phase within 1 degree of the truth at each. A later run asking for a sine above the measured
bandwidth is refused before it starts."""

from __future__ import annotations

import cmath
import dataclasses
import math
from pathlib import Path

import pytest
from scipy.optimize import brentq

from rig.errors import UserInputError
from sim.config import SimConfig, load_config
from sim.sensor_response import SensorResponse
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

DUT_TAU_S, REF_TAU_S = 0.008, 0.001

PROCEDURE = """
procedure: frequency response
magnetometers: {dut: dut, reference: reference}
steps:
  - sphere_sweep: {directions: 36, magnitude_ut: [20, 45], dwell_s: 0.8, seed: 3}
    name: sweep
  - calibrate: {model: vector, steps: [sweep]}
    name: vector calibration
  - cage_response: {frequencies_hz: [1, 2, 4, 6, 8], amplitude_ut: 5, bias_ut: 20, rate_hz: 50}
    name: cage
  - frequency_response: {frequencies_hz: [0.5, 1, 2, 4, 5.5], cycles: 3, min_s: 4, rate_hz: 40,
                         amplitude_ut: 7, bias_ut: 30}
    name: bode
  - report: {}
"""
TOO_FAST = """
procedure: too fast
magnetometers: {dut: dut, reference: reference}
steps:
  - frequency_response: {frequencies_hz: [2, 7], amplitude_ut: 5, bias_ut: 20, rate_hz: 50}
"""


def config() -> SimConfig:
    # both at 100 Hz: the set-points' staircase resolved, not aliased onto the sine
    cfg = load_config()
    mags = tuple(dataclasses.replace(m, response_tau_s=DUT_TAU_S, rate_hz=100) if m.name == "dut" else
                 dataclasses.replace(m, response_tau_s=REF_TAU_S, rate_hz=100) if m.name == "reference" else m
                 for m in cfg.magnetometers)  # fmt: skip
    return dataclasses.replace(cfg, magnetometers=mags)


def cage_truth(cfg: SimConfig, axis: int, rate_hz: float, f_hz: float) -> float:
    """The field made over the field asked (amplitude): the coil's L/R behind a zero-order hold."""
    tau = cfg.cage.inductance_h[axis] / cfg.cage.resistance_ohm[axis]
    x = math.pi * f_hz / rate_hz
    return abs(math.sin(x) / x / complex(1.0, 2.0 * math.pi * f_hz * tau))


def test_cage_bandwidth_then_the_dut_within_1_percent_and_1_degree_up_to_it(
    tmp_path: Path,
) -> None:
    cfg = config()
    outcome = run_on_sim(tmp_path, PROCEDURE, sim_config=cfg)
    assert outcome.status == "complete", outcome.reason
    cage = outcome.results["cage"]
    for axis, points in cage["axes"].items():
        i = "xyz".index(axis)
        half = brentq(lambda f, i=i: cage_truth(cfg, i, 50.0, f) - 2**-0.5, 1.0, 20.0)
        limit = cage["limit_hz"][axis]
        # never generous: a limit is at most the truth's half power (5 %: the points' own 0.5-1.5 %
        # above the hold-and-coil model move it 1.3-4 % where the amplitude falls slowly)
        assert limit is None or limit < 1.05 * half, (axis, limit, half)
        if not cage["poorly_measured_hz"][axis]:  # every point measured well (an idle computer)
            assert cage["bandwidth_hz"][axis] == pytest.approx(half, rel=0.05), (axis, half)
            for p in points:
                want = cage_truth(cfg, i, 50.0, p["f_hz"])
                assert p["amplitude"] == pytest.approx(want, abs=0.01), (axis, p)
    r = outcome.results["bode"]
    assert r["frame"] == "sensor" and "tau 0.001 s" in r["reference_response"]
    truth = SensorResponse(DUT_TAU_S, 0.0)
    for axis, points in r["axes"].items():
        assert [p["f_hz"] for p in points] == [0.5, 1, 2, 4, 5.5]  # all below 5.8-6.1 Hz
        for p in points:  # each within the must-show (on a loaded computer too: 0.35 %, 0.2 deg)
            want = truth.transfer(p["f_hz"])
            assert p["amplitude"] == pytest.approx(abs(want), abs=0.01), (axis, p)
            assert p["phase_deg"] == pytest.approx(math.degrees(cmath.phase(want)), abs=1.0), (
                axis,
                p,
            )
    report = (outcome.folder / "report.html").read_text()
    assert "Frequency response &#x27;bode&#x27;" in report and "Cage response" in report
    # the record keeps the bandwidth: a sine above it is refused before a run starts (where an
    # axis was measured well enough to have a limit: each one on an idle computer)
    if any(limit is not None for limit in cage["limit_hz"].values()):
        with pytest.raises(UserInputError, match=r"7 Hz on [xyz] beyond the cage's measured"):
            run_on_sim(tmp_path, TOO_FAST, sim_config=cfg)  # the same folder: the same record
