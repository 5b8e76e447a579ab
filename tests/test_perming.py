"""Perming (issue 37): the simulator's truth (a strong field leaves an offset until a set/reset
pulse; an HMR2300 with automatic set/reset shows none) through the HMR2300's own protocol, and
the figures the step reports: a hold's mean with a sigma that covers the truth for white and
correlated noise, a shift whose significance is honest (no shift: detected about as often as 3
sigma allows)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.mag.hmr2300 import Hmr2300 as Hmr2300Driver
from drivers.protocols import SetReset
from rig.characterization.perming import hold_mean, offset_shifts
from sim.hmr2300 import Hmr2300
from sim.perming import Perming
from sim.physics import Faults

pytestmark = pytest.mark.montecarlo


def ar1(rng: np.random.Generator, n: int, rho: float, sigma: float) -> np.ndarray:
    """(n, 3) AR(1) noise with lag-1 correlation ``rho`` and standard deviation ``sigma``."""
    e = rng.standard_normal((n, 3)) * sigma * np.sqrt(1 - rho * rho)
    x = np.empty((n, 3))
    x[0] = rng.standard_normal(3) * sigma
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x


@pytest.mark.parametrize("rho", [0.0, 0.6, -0.8])  # white, wandering, alternating (aliased ripple)
def test_a_holds_sigma_covers_its_true_mean(rho: float) -> None:
    rng = np.random.default_rng(7)
    z = []
    for _ in range(300):
        h = hold_mean(2.5 + ar1(rng, 400, rho, 20.0))
        z += list((np.asarray(h.mean_nt) - 2.5) / np.asarray(h.sigma_nt))
    inside = np.mean(np.abs(z) < 1.0)
    assert 0.62 < inside < 0.75, inside  # 68 % expected (900 values: +-3 %)
    assert 0.85 < float(np.std(z)) < 1.15


def test_no_shift_is_detected_no_more_often_than_3_sigma_allows_and_3_nt_is() -> None:
    rng = np.random.default_rng(11)
    t = np.arange(200) / 10.0
    false = 0
    for _ in range(300):
        (shift,) = offset_shifts([t, t + 60.0], [rng.standard_normal((200, 3)) * 5.0 for _ in "ab"])
        false += shift.detected
    assert false / 300 < 0.02  # 0.27 % expected (at most 0.27 %: the sigma is widened)
    t = np.arange(1000) / 10.0
    before = rng.standard_normal((1000, 3)) * 5.0
    after = rng.standard_normal((1000, 3)) * 5.0 + np.array([3.0, 0.0, 0.0])
    (shift,) = offset_shifts([t, t + 200.0], [before, after])
    # white noise alone: the sigma is 2.5-3.5 times the white-noise one (0.22 nT), for the
    # random walk 100 s holds cannot rule out (ADR 0041): 3 nT is found, 2 nT was at 2.8 sigma
    assert shift.detected and shift.significance_sigma > 3.0
    assert shift.shift_nt[0] == pytest.approx(3.0, abs=4 * shift.sigma_nt[0])


def test_the_simulated_sensor_perms_beyond_its_threshold_until_a_reset() -> None:
    p = Perming(threshold_ut=60.0, nt_per_ut=0.2)
    p.expose(np.array([50.0, 0.0, 0.0]))
    assert not np.any(p.shift_ut)  # below the threshold
    p.expose(np.array([0.0, 80.0, 0.0]))  # 20 uT beyond: 4 nT along y
    assert np.allclose(p.shift_ut, [0.0, 0.004, 0.0])
    p.expose(np.array([-70.0, 0.0, 0.0]))  # weaker: leaves the stronger one's shift
    assert np.allclose(p.shift_ut, [0.0, 0.004, 0.0])
    p.reset()
    assert not np.any(p.shift_ut)
    p.set_auto_reset(True)  # pulsed before every reading: nothing stays
    p.expose(np.array([0.0, 0.0, 100.0]))
    assert not np.any(p.shift_ut) and not p.active


class Field:
    """The sensor's truth: a field (uT) set by the test, with the sensor's perming added."""

    def __init__(self, perming: Perming) -> None:
        self.perming = perming
        self.now = np.zeros(3)

    def __call__(self, t_s: float) -> np.ndarray:
        self.perming.expose(self.now)
        return self.now + self.perming.shift_ut


def test_a_killed_perming_step_leaves_set_reset_off_and_the_next_opening_turns_it_on() -> None:
    """Issue 51: a session turns the simulated sensor's automatic set/reset off (as a perming
    step does) and dies without restoring it; the sensor keeps it off (perming shows); the next
    session's driver turns it on as it opens, and a strong field's perming is cleared again."""
    perming = Perming(threshold_ut=60.0, nt_per_ut=2.5)
    field = Field(perming)
    device = Hmr2300(field, Faults(), baudrate=9600, perming=perming)
    try:
        killed = Hmr2300Driver(device.path, baudrate=9600)
        killed.set_reset_auto(False)
        killed.port.close()  # the process dies here: nothing restores the mode
        assert not device.set_reset
        driver = Hmr2300Driver(device.path, baudrate=9600)
        try:
            assert device.set_reset
            field.now = np.array([80.0, 0.0, 0.0])
            driver.read()
            field.now = np.zeros(3)
            assert abs(1000.0 * driver.read()[0]) < 7.0  # nT: no perming left
        finally:
            driver.close()
    finally:
        device.close()


def test_the_hmr2300s_set_reset_through_its_own_protocol() -> None:
    """S/R on (the default) hides perming; ``TF`` lets it show; ``]S`` clears it (50 nT: above
    the sensor's 6.7 nT count)."""
    perming = Perming(threshold_ut=60.0, nt_per_ut=2.5)
    field = Field(perming)
    device = Hmr2300(field, Faults(), baudrate=9600, perming=perming)
    driver = Hmr2300Driver(device.path, baudrate=9600)
    try:
        assert isinstance(driver, SetReset)

        def shock_then_read() -> float:
            field.now = np.array([80.0, 0.0, 0.0])
            driver.read()
            field.now = np.zeros(3)
            return 1000.0 * driver.read()[0]  # nT

        assert abs(shock_then_read()) < 7.0 and device.set_reset  # auto set/reset: none
        driver.set_reset_auto(False)
        assert not device.set_reset
        assert shock_then_read() == pytest.approx(50.0, abs=7.0)  # 20 uT beyond x 2.5 nT/uT
        driver.set_reset_pulse()
        assert abs(1000.0 * driver.read()[0]) < 7.0
        driver.set_reset_auto(True)
        assert device.set_reset
    finally:
        driver.close()
        device.close()
