"""Offset stability against the simulator's truth (issue 37): the Allan deviation at 1, 100 and
1000 s within its 68 % interval of the exact one, the drift per 12 h within 20 % and its sigma
covering the truth, on 12 h of the simulated DUT's offset process.

Simulated time: the simulator's offset wander (drift, random walk, flicker) is a function of the
simulated time, which the wire protocols sample in real time; these tests draw 12 simulated hours
of the same process in about a second (``OffsetWander.values``) and add the white noise the
DUT less the reference has."""

from __future__ import annotations

import numpy as np
import pytest

from rig.characterization.stability import allan_deviation, offset_drift
from sim.offset_wander import OffsetWander, WanderSpec, allan_variance_truth

pytestmark = pytest.mark.montecarlo

SPEC = WanderSpec(drift_nt_per_h=(2.0, -1.5, 2.5), walk_nt_per_sqrt_h=0.1, flicker_nt=0.3)
WHITE_NT = 10.0
RATE_HZ = 2.0


def twelve_hours(seed: int, spec: WanderSpec = SPEC) -> tuple[np.ndarray, np.ndarray]:
    """12 h of offsets (nT) at RATE_HZ: the simulator's wander plus white noise."""
    t = np.arange(1, int(12 * 3600 * RATE_HZ) + 1) / RATE_HZ
    wander = 1000.0 * OffsetWander(spec, seed).values(t)
    return t, wander + WHITE_NT * np.random.default_rng([seed, 5]).standard_normal(wander.shape)


def test_the_simulated_wander_has_the_allan_deviation_it_is_built_for() -> None:
    """The flicker floor is flat (0.98-1.04 of its value from 10 to 3000 s), and a 12 h draw
    has the exact Allan deviation within its interval."""
    flicker = WanderSpec(flicker_nt=1.0)
    floor = [np.sqrt(allan_variance_truth(flicker, 0.0, 1.0, tau)) for tau in (10, 100, 1000, 3000)]
    assert floor == pytest.approx([1.0, 1.0, 1.0, 1.0], abs=0.04)
    white = allan_variance_truth(WanderSpec(), 10.0, 2.0, 5.0)
    assert white == pytest.approx(100.0 / 10)  # sigma^2 / m
    walk = WanderSpec(walk_nt_per_sqrt_h=1.0)
    assert allan_variance_truth(walk, 0.0, 1.0, 3600.0) == pytest.approx(1.0 / 3, rel=1e-3)


def test_allan_deviation_at_1_100_1000_s_within_its_interval_of_the_truth() -> None:
    """Over 12 holds of 12 h, the exact Allan deviation at 1, 100 and 1000 s (each axis) lies
    within the 68 % interval 60-77 % of the time and within the 95 % interval at least 90 % of
    the time: the intervals say what they promise."""
    taus = np.array([1.0, 100.0, 1000.0])
    truth = np.array([[np.sqrt(allan_variance_truth(SPEC, WHITE_NT, RATE_HZ, tau, axis=i))
                       for i in range(3)] for tau in taus])  # fmt: skip
    inside_68, inside_95 = [], []
    for seed in range(1, 13):
        t, y = twelve_hours(seed)
        for ci, inside in ((0.683, inside_68), (0.95, inside_95)):
            adev = allan_deviation(t, y, taus, ci=ci)
            assert adev.tau_s == pytest.approx(tuple(taus))
            inside += list((np.asarray(adev.low_nt) <= truth).ravel()
                           & (truth <= np.asarray(adev.high_nt)).ravel())  # fmt: skip
    assert 0.60 <= np.mean(inside_68) <= 0.77, np.mean(inside_68)
    assert np.mean(inside_95) >= 0.90, np.mean(inside_95)


def test_the_drift_over_12_h_within_20_percent_and_its_sigma_covers_the_truth() -> None:
    """Every one of 21 holds of 12 h: each axis within 20 % of its drift (at most 6.7, 8.7 and
    4.7 % when written); the error over the sigma has an rms of 0.3-1.3 (0.59, 0.36, 0.48: a
    sigma from the noise itself, with the random walk and flicker one record cannot tell apart
    or rule out counted (ADR 0041): pessimistic, never optimistic; a white-noise sigma from the
    residuals is several times too small here)."""
    truth = 12.0 * np.asarray(SPEC.drift_nt_per_h)
    t, y = twelve_hours(seed=1)
    one = offset_drift(t, y)
    assert np.all(np.abs(np.asarray(one.per_12h_nt) / truth - 1) < 0.2), one
    z = []
    for seed in range(2, 22):
        t, y = twelve_hours(seed)
        d = offset_drift(t, y)
        assert np.all(np.abs(np.asarray(d.per_12h_nt) / truth - 1) < 0.2), (seed, d)
        z.append((np.asarray(d.per_12h_nt) - truth) / np.asarray(d.sigma_nt))
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.3) & (rms < 1.3)), rms
    # the white-noise sigma of the slope, from the residuals, for comparison
    resid = y - np.polyval(np.polyfit(t, y[:, 0], 1), t)[:, None]
    naive = 12 * 3600 * np.std(resid[:, 0]) / np.sqrt(np.sum((t - t.mean()) ** 2))
    assert naive < 0.5 * d.sigma_nt[0]
