"""The simulated sensors' response to a changing field (issue 37's frequency response truth): a
sine read at a sensor's sample times has the amplitude ratio and phase lag its transfer function
says, to 1e-4 and 0.01 degree, for a first-order low-pass, a conversion window, and both."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.sensor_response import SensorResponse


def sine_fit(t: np.ndarray, y: np.ndarray, f_hz: float) -> complex:
    """The complex amplitude of ``y`` at ``f_hz`` (least squares with a constant)."""
    w = 2 * math.pi * f_hz * t
    design = np.column_stack([np.ones_like(t), np.sin(w), np.cos(w)])
    c = np.linalg.lstsq(design, y, rcond=None)[0]
    return complex(c[1], c[2])  # y = a sin + b cos = Im((a + ib) e^{iw})


@pytest.mark.parametrize(("tau_s", "integration_s"), [(0.008, 0.0), (0.0, 0.0132), (0.008, 0.0132)])
@pytest.mark.parametrize("f_hz", [0.1, 1.0, 5.0])
def test_a_sine_is_read_as_the_transfer_function_says(
    tau_s: float, integration_s: float, f_hz: float
) -> None:
    response = SensorResponse(tau_s, integration_s)
    rng = np.random.default_rng(1)
    t = np.sort(100.0 + rng.uniform(0.0, 20.0 / f_hz, 4000))  # irregular dates, many cycles
    t = t[t > 100.0 + 0.2]  # after the start-up

    def field(s: float) -> np.ndarray:
        return np.array([30.0 + 10.0 * math.sin(2 * math.pi * f_hz * s), 0.0, 0.0])

    read = np.array([response.reading(s, field)[0] for s in t])
    got = sine_fit(t, read, f_hz) / 10.0
    want = response.transfer(f_hz)
    assert abs(got) == pytest.approx(abs(want), abs=1e-4)
    assert math.degrees(np.angle(got) - np.angle(want)) == pytest.approx(0.0, abs=0.01)
    if tau_s == 0.008 and integration_s == 0.0:  # a 20 Hz corner: the textbook values, but for
        # the 2 ms grid's linear interpolation (sinc^2(f h): 3e-4 at 5 Hz)
        textbook = 1 / complex(1, 2 * math.pi * f_hz * tau_s)
        assert abs(want) == pytest.approx(abs(textbook), rel=4e-4)
        assert np.angle(want) == pytest.approx(np.angle(textbook), abs=1e-9)


def test_an_ideal_sensor_reads_the_field_and_a_long_gap_restarts_the_filter() -> None:
    ideal = SensorResponse(0.0, 0.0)
    assert not ideal.active and ideal.transfer(3.0) == 1.0
    r = SensorResponse(0.008, 0.0)
    assert np.allclose(r.reading(10.0, lambda s: np.array([1.0, 2.0, 3.0])), [1, 2, 3])
    # an hour later the field is another: the filter starts shortly before, not an hour of steps
    assert np.allclose(r.reading(3610.0, lambda s: np.array([4.0, 5.0, 6.0])), [4, 5, 6])
