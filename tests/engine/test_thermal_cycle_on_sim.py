"""The thermal_cycle step through the wire protocols on the simulated cage: a DUT whose offset
on warming is 10 nT above its offset on cooling on x (sim.thermal_hysteresis), warmed and cooled
by the heater on its mount twice, each time held at one temperature on both branches at the same
heater current. The mount's time constant is cut to 8 s (a real one: minutes, so a real
campaign takes hours; tests/test_thermal_hysteresis.py draws 12 h campaigns in simulated time
and finds 0.5 nT there). Four minutes know the hysteresis to about 1 nT here (the residuals
show flicker of about 0.5-1 nT, which the sigma counts). The DUT is
calibrated first, so its offset tempco comes out through the calibration's correction matrix."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from sim.config import SimConfig, load_config
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

HYSTERESIS_NT = (10.0, 0.0, 0.0)

PROCEDURE = """
procedure: thermal cycle
magnetometers: {dut: dut, reference: reference}
loads: [heater]
steps:
  - sphere_sweep: {directions: 36, magnitude_ut: [20, 45], dwell_s: 0.8, seed: 3}
    name: sweep
  - calibrate: {model: vector, steps: [sweep]}
    name: vector calibration
  - thermal_cycle: {thermometer: dut_temp, hold_s: 240, reversal_k: 1.0, bin_s: 5}
    name: thermal cycle
    loads:
      heater: {steps: {levels_a: [1.2, 2.0, 1.2, 0.0, 1.2, 2.0, 1.2, 0.0], dwell_s: 30}}
  - report: {}
"""


def config() -> SimConfig:
    cfg = load_config()
    assert cfg.thermal is not None
    dut = {"noise_ut": 0.005, "offset_hysteresis_nt": HYSTERESIS_NT, "hysteresis_band_k": 0.5}
    mags = tuple(dataclasses.replace(m, **dut) if m.name == "dut" else
                 dataclasses.replace(m, noise_ut=0.002) if m.name == "reference" else m
                 for m in cfg.magnetometers)  # fmt: skip
    # no mains ripple: the DUT and the reference sample it at different instants, and its slow
    # beat with their sample clocks is flicker of about 1 nT in four minutes (a 12 h campaign
    # averages it down; tests/test_thermal_hysteresis.py)
    ambient = dataclasses.replace(cfg.ambient, ripple_amplitude_ut=(0.0, 0.0, 0.0))
    return dataclasses.replace(cfg, magnetometers=mags, ambient=ambient,
                               thermal=dataclasses.replace(cfg.thermal, tau_s=8.0))  # fmt: skip


def test_a_dut_with_thermal_hysteresis_shows_it_within_its_sigma(tmp_path: Path) -> None:
    outcome = run_on_sim(tmp_path, PROCEDURE, sim_config=config())
    assert outcome.status == "complete", outcome.reason
    r = outcome.results["thermal cycle"]
    h, sigma = np.asarray(r["hysteresis_nt"]), np.asarray(r["hysteresis_sigma_nt"])
    assert r["detected"] and r["significance_sigma"] >= 3.0, r
    # the hysteresis is the sensor's (its own axes); the fit sees it through the run's
    # calibration, as it sees the tempco: (10, 0, 0) there is (9.76, -0.66, -0.53) here
    matrix = np.asarray(outcome.results["vector calibration"]["correction"]["matrix"])
    assert np.all(np.abs(h - matrix @ HYSTERESIS_NT) < 3.0 * sigma), (h, sigma)
    raw = 1000.0 * np.asarray(load_config().magnetometer("dut").offset_ut_per_k)  # nT/K
    truth = matrix @ raw
    tempco = np.asarray(r["tempco_nt_per_k"])
    sigma_tc = np.asarray(r["tempco_sigma_nt_per_k"])
    assert np.all(np.abs(tempco - truth) < 3.0 * sigma_tc + 0.01 * np.abs(truth)), (tempco, truth)
    lo, hi = r["temperature_range_c"]
    assert lo < 27.0 and hi > 50.0 and r["calibrated"]
    assert "Thermal cycle &#x27;thermal cycle&#x27;" in (outcome.folder / "report.html").read_text()
