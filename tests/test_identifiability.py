"""Identifiability by information (issue 34, docs/adr/0026): a scalar fit on one-sided field
directions is refused only when the Fisher information leaves a combination undetermined; else
it is fitted, with a warning saying what the missing directions would buy."""

from __future__ import annotations

import datetime as dt
import re

import numpy as np
import pytest

from rig.calibration import Samples, calibrate
from rig.calibration.batch.nonlinear import ml_fit, scalar_start
from rig.calibration.diagnostics import direction_coverage
from rig.calibration.identifiability import (
    combination_words,
    hypothetical_samples,
    information,
    noise_bias,
    worst_combination,
)
from rig.calibration.params import Calibration
from rig.calibration.residuals import parameter_names
from rig.calibration.synthetic import CAP_TRUTH, constant_field_cap
from rig.errors import CalibrationError

TRUTH = CAP_TRUTH
FIELD_UT = 47.0


def cap_of_constant_field(cap_deg: float, n: int = 5000, noise_ut: float = 0.2) -> Samples:
    """Field directions uniform within ``cap_deg`` of -z (90: a hemisphere), |h| constant."""
    return constant_field_cap(cap_deg, n, noise_ut=noise_ut, field_ut=FIELD_UT).samples


def _coverage_warning(warnings: tuple[str, ...]) -> str:
    found = [w for w in warnings if w.startswith("field directions:")]
    assert len(found) == 1, warnings
    return found[0]


def test_a_uniform_hemisphere_calibrates_with_the_warning() -> None:
    result = calibrate(cap_of_constant_field(90.0), "ml")
    truth = TRUTH.as_vector()[3:6]
    error = (result.p[3:6] - truth) / result.sigma[3:6]
    assert np.all(np.abs(error) < 3.0), (result.p[3:6], result.sigma[3:6])
    warning = _coverage_warning(result.warnings)
    assert "+z not covered" in warning and "with +z recorded" in warning, warning
    z0 = re.search(r"z0 sigma ([\d.e-]+) uT, ([\d.e-]+) uT with \+z recorded", warning)
    assert z0 is not None, warning
    # The warning's sigma is the fit's, and +z would shrink it several times (offset and z scale
    # no longer trade off).
    assert float(z0[1]) == pytest.approx(result.sigma[5], rel=0.1)
    assert float(z0[2]) < float(z0[1]) / 3.0


def test_the_trmm_orbit_calibrates_with_ml() -> None:
    """Crassidis, Lai and Harman's orbit (402 km, 35 deg, Earth pointing, |B| 20-43 uT): body +y
    is never near the field, yet the varying magnitude determines every parameter."""
    from bench.bench_realtime_filters import B_TRUE_UT, D_TRUE, readings
    from rig.steps.orbit import circular_orbit_track

    t = np.arange(0.0, 8 * 3600.0, 10.0)
    field = circular_orbit_track(402.0, 35.0, dt.datetime(2003, 6, 1), t, "nadir").field_body_ut
    s = Samples.build(readings(field, 1000), field_magnitude_ut=np.linalg.norm(field, axis=1))
    assert direction_coverage(s.measured_ut)["+y"] < 0.01
    result = calibrate(s, "ml")
    offset = np.linalg.solve(np.eye(3) + D_TRUE, B_TRUE_UT)  # B = (I + D)^-1 (H + b)
    error = (result.p[3:6] - offset) / result.sigma[3:6]
    assert np.all(np.abs(error) < 3.0), (result.p[3:6], offset, result.sigma[3:6])
    assert "+y not covered" in _coverage_warning(result.warnings)


@pytest.mark.parametrize("method", ["ml", "ellipsoid"])
def test_a_small_cap_of_a_constant_field_is_refused_naming_the_combination(method: str) -> None:
    """Within 50 deg of -z only: the likelihood keeps rising as the z scale and the z0 offset
    grow together, so no fit has an answer."""
    with pytest.raises(CalibrationError) as err:
        calibrate(cap_of_constant_field(50.0), method)
    text = str(err.value)
    assert len(text.splitlines()) == 1
    assert text.startswith("z scale and z0 offset trade off:"), text
    assert "record directions with +z " in text and "-z 100.0 %" in text, text


def test_a_sphere_has_no_coverage_warning() -> None:
    rng = np.random.default_rng(3)
    u = rng.standard_normal((3000, 3))
    field = FIELD_UT * u / np.linalg.norm(u, axis=1, keepdims=True)
    m = Calibration.from_springmann(TRUTH).predict(field) + 0.2 * rng.standard_normal((3000, 3))
    result = calibrate(Samples.build(m, field_magnitude_ut=np.full(3000, FIELD_UT)), "ml")
    assert not [w for w in result.warnings if w.startswith("field directions:")], result.warnings


def test_hypothetical_samples_fill_the_named_caps_at_the_field_magnitude() -> None:
    s = cap_of_constant_field(90.0)
    p = TRUTH.as_vector()
    extra = hypothetical_samples(s, p, ["+z", "-x"], 400)
    assert extra.n == 800
    cal = Calibration.from_springmann(TRUTH)
    corrected = (extra.measured_ut - cal.offset_ut) @ np.linalg.inv(cal.t_matrix).T
    assert np.allclose(np.linalg.norm(corrected, axis=1), FIELD_UT)
    first, second = extra.rows(slice(0, 400)), extra.rows(slice(400, 800))
    assert direction_coverage(first.measured_ut, cal.offset_ut)["+z"] == 1.0
    assert direction_coverage(second.measured_ut, cal.offset_ut)["-x"] == 1.0


def test_the_worst_combination_is_the_least_informed_scaled_direction() -> None:
    names = parameter_names((), vector=False)
    scales = np.array([1.0, 1.0, 1.0, 50.0, 50.0, 50.0, 1.0, 1.0, 1.0])
    direction = np.zeros(9)
    direction[[2, 5]] = [1.0, 1.0] / np.sqrt(2.0)  # z scale and z0 (scaled) together
    weak = np.eye(9) * 1e4 - (1e4 - 0.25) * np.outer(direction, direction)  # scaled sigma 2 there
    fisher = weak / np.outer(scales, scales)
    sigma, found = worst_combination(fisher, scales)
    assert sigma == pytest.approx(2.0)
    assert abs(found @ direction) == pytest.approx(1.0)
    assert combination_words(found, names) == "z scale and z0 offset trade off"
    singular = fisher.copy()
    singular[:, 0] = singular[0, :] = 0.0
    assert worst_combination(singular, scales)[0] == float("inf")


def test_a_noise_bias_beyond_three_sigma_is_refused_and_it_is_the_one_predicted() -> None:
    """Within 75 deg of -z at 0.2 uT: the scalar ML estimate of z0 sits several sigma off the
    truth, by the amount :func:`noise_bias` predicts (ADR 0026); no sigma covers that, so the
    fit is refused, naming the bias and what to record."""
    s = cap_of_constant_field(75.0)
    with pytest.raises(CalibrationError, match=r"the raw noise biases a scalar \(ml\) fit") as exc:
        calibrate(s, "ml")
    z0 = re.search(r"z0 ([+-][\d.]+) uT \(([+-][\d.]+) sigma\)", str(exc.value))
    assert z0 is not None and float(z0[2]) > 3.0, str(exc.value)
    assert "record +z" in str(exc.value)
    start = scalar_start(s.as_scalar(), quick=True).p
    info = information(s.as_scalar(), start)
    fit = ml_fit(s.as_scalar(), start=start)  # the estimator itself, unchecked
    off = fit.p[5] - TRUTH.z0
    sigma = float(np.sqrt(fit.covariance[5, 5]))
    assert off > 3.0 * sigma  # the bias the sigmas do not hold
    assert abs(off - noise_bias(s.as_scalar(), info)[5]) < sigma, (off, str(exc.value))
