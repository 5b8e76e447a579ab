"""Delays in a moving field when the DUT's and the reference's dates differ (issue 30): the offset
is fitted with the delays and its uncertainty carried into theirs; under correlated noise the
profiled sigmas come from the same HAC sandwich as every other parameter's (ADR 0025) and cover
the truth."""

from __future__ import annotations

import numpy as np
import pytest

from rig.calibration.estimators import FitRequest, estimator
from rig.calibration.profiled import (
    clock_offset_parameter,
    delay_parameter,
    profile_fit,
    shifted,
)
from rig.calibration.residuals import Samples

pytestmark = pytest.mark.montecarlo

RATE_HZ = 20.0
NOISE_UT = 0.03
TRUE_DELAYS_S = (0.0, 0.05)
K_TRUE = np.array([[0.9, -0.3, 0.4], [-0.3, 0.7, 0.2]])  # uT per A
LOWER = np.array([[1.02, 0, 0], [0.01, 0.98, 0], [-0.02, 0.015, 1.01]])
OFFSET_UT = np.array([2.4, -1.2, 0.9])


def tumbling_field(t: np.ndarray) -> np.ndarray:
    """A 40 uT field seen from a body tumbling at 4.5 deg/s about a tilted axis (uT, (N, 3))."""
    a = np.deg2rad(4.5) * t
    b = 0.37 * np.sin(2 * np.pi * t / 47.0)
    return 40.0 * np.column_stack([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)])


def tumbling_run(seed: int, ref_offset_s: float, n: int = 2400, ar: float = 0.0):
    """DUT samples dated truly; the reference's dates ``ref_offset_s`` late. The panel current
    follows the sun on the tumbling body (so it correlates with the field's motion), the bus
    current steps. Noise AR(1) with coefficient ``ar`` (0: white)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE_HZ
    h = tumbling_field(t)
    # the sun lies near the field's direction in the orbit plane: the panel's light moves with
    # the field, and an eclipse cuts it off for a sixth of the run
    sun = np.maximum(-np.cos(np.deg2rad(4.5) * t - 0.3), 0.0) * (
        np.abs(t - 0.6 * t[-1]) > t[-1] / 12
    )
    bus = 0.8 + 0.8 * (np.floor(t / 3.1) % 2)
    u = np.column_stack([bus, 1.5 * sun])
    late = np.column_stack([shifted(t, u[:, j], TRUE_DELAYS_S[j]) for j in range(2)])
    e = rng.standard_normal((n, 3))
    for i in range(1, n):
        e[i] = ar * e[i - 1] + np.sqrt(1 - ar**2) * e[i]
    m = h @ LOWER.T + OFFSET_UT + late @ K_TRUE + NOISE_UT * e
    s = Samples.build(m, field_ut=h, telemetry=u, channels=("bus", "panel"))
    t_ref = t + ref_offset_s

    def field_at(times: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(times, t_ref, h[:, i]) for i in range(3)])

    return s.__class__(s.measured_ut, s.field_magnitude_ut, s.telemetry, s.channels,
                       field_at(t)), t, field_at  # fmt: skip


def _refit(data: Samples):
    return estimator("vector").run(data, FitRequest("vector", None, None, None, None, None))


def _fit(s, t, field_at=None):
    params = tuple(delay_parameter(s, t, c, 0.5) for c in ("bus", "panel"))
    if field_at is not None:
        params += (clock_offset_parameter(s, t, field_at, 0.05),)
    return profile_fit(s, params, _refit)


def test_the_offset_between_the_streams_dates_is_found_and_carried_into_the_delays() -> None:
    s, t, field_at = tumbling_run(1, ref_offset_s=0.004, n=1200)
    joint = _fit(s, t, field_at)
    truth = np.array([*TRUE_DELAYS_S, 0.004])
    z = (joint.values - truth) / joint.sigma
    assert np.all(np.abs(z) < 3), (joint.values, joint.sigma)
    assert abs(joint.values[2] - 0.004) < 0.001  # the offset itself to a fraction of a ms
    labels = [p.table_label for p in joint.params]
    assert labels == ["delay[bus]", "delay[panel]", "DUT vs reference dates"]


def test_no_offset_is_found_where_there_is_none() -> None:
    s, t, field_at = tumbling_run(2, ref_offset_s=0.0, n=1200)
    joint = _fit(s, t, field_at)
    z = (joint.values - np.array([*TRUE_DELAYS_S, 0.0])) / joint.sigma
    assert np.all(np.abs(z) < 3), (joint.values, joint.sigma)


def test_delay_sigmas_cover_the_truth_under_correlated_noise_and_an_offset() -> None:
    zs = []
    for seed in range(8):
        s, t, field_at = tumbling_run(100 + seed, 0.003, n=1200, ar=0.7)
        fit = _fit(s, t, field_at)
        zs.append((fit.values - np.array([*TRUE_DELAYS_S, 0.003])) / fit.sigma)
    z = np.abs(np.array(zs))
    assert np.max(z) < 4.0, z
    assert np.mean(z < 2.0) > 0.8, z  # about 95 % for an honest sigma (24 values)
