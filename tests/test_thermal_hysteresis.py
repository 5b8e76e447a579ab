"""Thermal hysteresis (issue 37) against the simulator's truth, in simulated time: the sensor's
play operator (sim.thermal_hysteresis) and the default DUT's offset wander, noise and temperature
coefficient, through a 12 h heater campaign of twelve cycles, each holding one temperature on both
branches at the same heater current (12 hours of samples drawn in seconds: a real campaign takes
that long). A 0.5 nT hysteresis is found at 3 sigma or more; a DUT without one passes; the sigma
covers the truth (over 24 campaigns, 72 values: error over sigma rms 1.03, largest 2.9; a fit
with white noise only put the sigma at half the estimates' spread, the offset's random walk
between a warming and a cooling plateau being most of it)."""

from __future__ import annotations

import numpy as np
import pytest

from rig.characterization.thermal import branches, fit_thermal
from sim.offset_wander import OffsetWander, WanderSpec
from sim.thermal_hysteresis import ThermalHysteresis

pytestmark = pytest.mark.montecarlo

RATE_HZ = 2.0  # a campaign's offsets averaged to 2 Hz (the noise per sample scaled to match)
NOISE_NT = 21.0 / np.sqrt(20.0 / RATE_HZ)  # the DUT less the reference at 20 Hz: about 21 nT
TEMPCO_NT_PER_K = np.array([30.0, -20.0, 15.0])  # the default DUT's offset_ut_per_k
K_PER_A2 = 8.0  # steady warming per A^2 of heater current (2 K/W on a 4 ohm pad)
TAU_S = 120.0
# (heater A, seconds): up to a plateau, hotter, back to the same plateau from above, cooler: 12 h
PROFILE = [(1.2, 1200.0), (2.0, 600.0), (1.2, 1200.0), (0.0, 600.0)] * 12


def campaign(hysteresis_nt: tuple[float, float, float], seed: int) -> tuple[np.ndarray, ...]:
    """(time s, temperature C, offsets nT, heater A) of one simulated campaign."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, sum(d for _, d in PROFILE), 1.0 / RATE_HZ)
    amps = np.zeros_like(t)
    start = 0.0
    for a, d in PROFILE:
        amps[(t >= start) & (t < start + d)] = a
        start += d
    target = 25.0 + K_PER_A2 * amps**2
    temp = np.empty_like(t)
    temp[0] = 25.0
    alpha = 1.0 - np.exp(-1.0 / RATE_HZ / TAU_S)
    for k in range(1, len(t)):  # the mount's first-order response
        temp[k] = temp[k - 1] + alpha * (target[k - 1] - temp[k - 1])
    play = ThermalHysteresis(hysteresis_nt, band_k=1.0)
    hyst = np.array([play.offset_ut(v) for v in temp]) * 1000.0
    wander = OffsetWander(WanderSpec((0.5, -0.3, 0.4), 0.2, 0.1), seed, -1.0).values(t)
    offsets = (np.outer(temp - 25.0, TEMPCO_NT_PER_K) + hyst + 1000.0 * wander
               + NOISE_NT * rng.standard_normal((len(t), 3)))  # fmt: skip
    thermometer = temp + 0.01 * rng.standard_normal(len(t))
    return t, thermometer, offsets, amps[:, None]


def test_the_branches_follow_the_thermometers_history() -> None:
    temp = np.array([25.0, 25.5, 27.0, 30.0, 29.5, 28.5, 27.9, 26.0, 26.5])
    assert list(branches(temp, 1.0)) == [0, 0, 1, 1, 0, 0, -1, -1, 0]


def test_a_half_nt_hysteresis_is_found_at_3_sigma_and_within_its_sigma() -> None:
    t, temp, offsets, amps = campaign((0.5, 0.0, 0.0), seed=1)
    fit = fit_thermal(t, temp, offsets, amps, reversal_k=1.5)
    assert fit.detected and fit.significance_sigma >= 3.0, fit.hysteresis_nt
    err = (np.asarray(fit.hysteresis_nt) - [0.5, 0.0, 0.0]) / np.asarray(fit.hysteresis_sigma_nt)
    assert np.all(np.abs(err) < 3.0), (fit.hysteresis_nt, fit.hysteresis_sigma_nt)
    z = (np.asarray(fit.tempco_nt_per_k) - TEMPCO_NT_PER_K) / np.asarray(fit.tempco_sigma_nt_per_k)
    assert np.all(np.abs(z) < 4.0), (fit.tempco_nt_per_k, fit.tempco_sigma_nt_per_k)


def test_a_dut_without_hysteresis_passes_and_the_sigma_is_honest() -> None:
    zs = []
    for seed in range(6):
        t, temp, offsets, amps = campaign((0.0, 0.0, 0.0), seed=100 + seed)
        fit = fit_thermal(t, temp, offsets, amps, reversal_k=1.5)
        zs += list(np.asarray(fit.hysteresis_nt) / np.asarray(fit.hysteresis_sigma_nt))
        if seed < 3:
            assert not fit.detected, fit.hysteresis_nt
    rms = float(np.sqrt(np.mean(np.square(zs))))
    assert 0.65 < rms < 1.4, (rms, np.round(zs, 2))  # 18 values: +-0.33 at 2 sigma


def test_without_a_cooling_branch_it_says_what_to_do() -> None:
    t = np.arange(0.0, 600.0, 1.0)
    temp = 25.0 + t / 60.0
    with pytest.raises(ValueError, match="no warming or no cooling branch"):
        fit_thermal(t, temp, np.zeros((len(t), 3)))
