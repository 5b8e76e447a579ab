"""The scalar method for the coil constants against synthetic truth: coils 0.5 deg off square, a lab
field that drifts, a total-field sensor with an absolute offset and white noise - recovered, and
the reported sigmas cover the truth over 150 procedures; what cannot be fitted is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.cage.coil_axes import ARCSEC_PER_RAD, derived_constants_and_skews, rotation
from rig.cage.coil_scalar import ScalarReading, fit_scalar_coils, outside_dead_zones
from rig.errors import UserInputError
from rig.steps.coil_scalar import design
from rig.steps.geometry import fibonacci_directions as sphere_directions

pytestmark = pytest.mark.montecarlo

LAB_UT = np.array([19.6, 1.2, -44.8])
NOMINAL = np.diag([40.0, 40.0, 40.0])


def procedure(seed: int, noise_nt: float = 0.05) -> tuple[list[ScalarReading], np.ndarray, float]:
    """One simulated sweep: the readings, the true K and the sensor's true offset (nT)."""
    rng = np.random.default_rng([seed, 36])
    k = np.diag([40.2, 39.1, 41.3]) + math.radians(0.5) * 40 * rng.standard_normal((3, 3))
    k = rotation(0.2 * rng.standard_normal(3)) @ k  # the frame is not the sensor's concern
    drift_ut_per_s = 2e-5 * rng.standard_normal(3)  # tens of nT per hour
    offset_nt = 2.0 * rng.standard_normal()
    readings, t = [], 0.0
    for field in design(30, [22.0, 45.0], np.array([0.0, 0.5, 1.0]), 15.0):
        currents = np.round(np.linalg.solve(NOMINAL, field - LAB_UT), 3)
        total = np.linalg.norm(k @ currents + LAB_UT + drift_ut_per_s * t) + 1e-3 * offset_nt
        readings.append(ScalarReading(currents, t, total + 1e-3 * noise_nt * rng.standard_normal(),
                                      1e-3 * noise_nt))  # fmt: skip
        t += 2.5
    return readings, k, offset_nt


def truth(k: np.ndarray) -> np.ndarray:
    value = derived_constants_and_skews(k.T.reshape(-1))
    return np.concatenate([value[:3], value[3:] * ARCSEC_PER_RAD])


def test_the_sigmas_cover_the_truth_over_150_sweeps() -> None:
    z, offsets = [], []
    for seed in range(150):
        readings, k, offset_nt = procedure(seed)
        fit = fit_scalar_coils(readings, NOMINAL, offset_sigma_nt=3.0)
        estimate = np.concatenate([fit.constants_ut_per_a, fit.skew_arcsec])
        sigma = np.concatenate([fit.constants_sigma, fit.skew_sigma_arcsec])
        z.append((estimate - truth(k)) / sigma)
        offsets.append((fit.offset_nt - offset_nt) / fit.offset_sigma_nt)
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.8) & (rms < 1.25)), rms
    assert 0.7 < math.sqrt(np.mean(np.square(offsets))) < 1.3  # two shells separate the offset
    assert fit.skew_sigma_arcsec.max() < 1.0 and fit.constants_sigma.max() / 40 < 2e-6


def test_a_skew_of_half_a_degree_is_found_to_arcseconds() -> None:
    readings, k, _ = procedure(3, noise_nt=0.5)
    fit = fit_scalar_coils(readings, NOMINAL, offset_sigma_nt=3.0)
    true = truth(k)
    assert np.all(np.abs(fit.skew_arcsec - true[3:]) < 4 * fit.skew_sigma_arcsec)
    assert np.abs(true[3:]).max() > 600  # tens of arcminutes off square, found to a few arcsec
    assert fit.skew_sigma_arcsec.max() < 5.0
    assert fit.between_nt < 0.2  # white noise only: nothing shared between points


def test_the_dead_zones_are_left_out_and_the_points_go_in_a_random_order() -> None:
    axis = np.array([0.0, 0.0, 1.0])
    kept = outside_dead_zones(sphere_directions(200), axis, 15.0)
    angles = np.degrees(np.arccos(np.abs(kept @ axis)))
    assert len(kept) < 200 and angles.min() >= 15.0 and angles.max() <= 75.0
    assert len(outside_dead_zones(sphere_directions(50), None, 15.0)) == 50  # an Overhauser
    fields = np.array(design(40, [22.0, 45.0], None, 15.0))
    magnitude = np.linalg.norm(fields, axis=1)
    # both magnitudes through the whole sweep (a drift cannot pass for the constants' scale)
    first, second = (np.flatnonzero(np.isclose(magnitude, m)) for m in (22.0, 45.0))
    assert len(first) == len(second) == 40 and abs(first.mean() - second.mean()) < 10
    assert np.array_equal(fields, np.array(design(40, [22.0, 45.0], None, 15.0)))  # seeded


def test_a_lab_field_swinging_through_the_sweep_does_not_pass_for_the_coils() -> None:
    """The simulated lab's slow swing (60 nT over 700 s) curves by several nT in a minute's
    sweep: the drift terms and the random order keep the constants within their sigmas."""
    z = []
    for seed in range(40):
        rng = np.random.default_rng([seed, 37])
        readings, k, _ = procedure(seed)
        phase = rng.uniform(0, 2 * math.pi, 3)
        swung = []
        for r in readings:
            swing = 0.06 * np.sin(2 * math.pi * r.t_s / 700.0 + phase)
            field = np.linalg.norm(k @ r.currents_a + LAB_UT + swing)
            swung.append(
                ScalarReading(r.currents_a, r.t_s, field + 1e-3 * rng.normal(0, 0.8), r.sigma_ut)
            )
        fit = fit_scalar_coils(swung, NOMINAL, offset_sigma_nt=3.0)
        z.append((fit.constants_ut_per_a - truth(k)[:3]) / fit.constants_sigma)
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all(rms < 1.3), rms


def test_too_few_readings_or_a_coil_never_driven_is_refused() -> None:
    readings, _, _ = procedure(1)
    with pytest.raises(UserInputError, match="at least 16"):
        fit_scalar_coils(readings[:10], NOMINAL, 3.0)
    flat = [ScalarReading(np.array([r.currents_a[0], r.currents_a[1], 0.0]), r.t_s, r.total_ut,
                          r.sigma_ut) for r in readings]  # fmt: skip
    with pytest.raises(UserInputError, match="do not drive all three coils"):
        fit_scalar_coils(flat, NOMINAL, 3.0)
