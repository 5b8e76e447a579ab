"""The vector method for the coil axes against synthetic truth: a cage with a 0.5 deg skew, a
reference sensor whose certificate is right within its sigma, a fixture whose turns are off by
tens of arcseconds - recovered, and the reported sigmas cover the truth over 60 procedures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.cage.coil_axes import (
    ARCSEC_PER_RAD,
    DEFAULT_POSITIONS,
    CoilResponse,
    SensorPrior,
    fit_coil_axes,
    lower_triangular_part,
    rotation,
)
from rig.errors import UserInputError

pytestmark = pytest.mark.montecarlo

CONSTANTS = np.array([40.2, 39.1, 41.3])
SKEW_XY_DEG = 0.5
NOISE_UT_PER_A = 6e-4  # 5 nT reference noise, 40 readings per level, 1 A


def true_coil_matrix() -> np.ndarray:
    """Columns: x tilted 0.1 deg out of the frame's xy plane; y 0.5 deg from square to x (in the
    xy plane); z tilted 0.2 deg towards x and 0.1 deg towards y."""
    x = rotation(np.radians([0.0, 0.1, 0.0])) @ np.array([1.0, 0.0, 0.0])
    skew = math.radians(90.0 - SKEW_XY_DEG)
    y = np.array([math.cos(skew), math.sin(skew), 0.0])
    z = np.array([math.radians(0.2), math.radians(0.1), 1.0])
    axes = np.column_stack([x, y, z / np.linalg.norm(z)])
    return axes * CONSTANTS


def certificate_l() -> np.ndarray:
    """The reference's certificate: scales and non-orthogonality of a calibrated fluxgate."""
    return np.array([[1.0004, 0.0, 0.0], [2e-4, 0.9997, 0.0], [-1e-4, 3e-4, 1.0002]])


def procedure(seed: int, prior: SensorPrior) -> tuple[list[CoilResponse], np.ndarray]:
    """One simulated procedure: its responses and the true K."""
    rng = np.random.default_rng([seed, 35])
    k = true_coil_matrix()
    l_true = prior.l_matrix.copy()
    diag = np.diag(prior.l_matrix).copy()
    for i in range(3):
        l_true[i, i] += prior.scale_sigma * diag[i] * rng.standard_normal()
        for j in range(i):
            l_true[i, j] += prior.skew_sigma_rad * diag[i] * rng.standard_normal()
    t = l_true @ rotation(np.radians(rng.uniform(-1.0, 1.0, 3)))  # mounted within 1 deg
    data = []
    for pos, (_, nominal) in enumerate(DEFAULT_POSITIONS):
        delta = np.zeros(3) if pos == 0 else prior.fixture_sigma_rad * rng.standard_normal(3)
        a = nominal @ rotation(delta)
        for coil in range(3):
            d = t @ a.T @ k[:, coil] + NOISE_UT_PER_A * rng.standard_normal(3)
            data.append(CoilResponse(pos, coil, d, np.full(3, NOISE_UT_PER_A)))
    return data, k


def skews_arcsec(k: np.ndarray) -> np.ndarray:
    unit = k / np.linalg.norm(k, axis=0)
    return np.array([(math.pi / 2 - math.acos(unit[:, i] @ unit[:, j])) * ARCSEC_PER_RAD
                     for i, j in ((0, 1), (0, 2), (1, 2))])  # fmt: skip


def test_the_certificate_splits_into_sensor_and_mounting() -> None:
    l_matrix = certificate_l()
    m = rotation(np.radians([1.0, -2.0, 3.0]))
    np.testing.assert_allclose(lower_triangular_part(l_matrix @ m), l_matrix, atol=1e-12)


def test_a_skewed_cage_is_recovered_and_its_sigmas_cover_the_truth() -> None:
    prior = SensorPrior(certificate_l())
    z_k, z_const, z_skew, worst_const, skew_sigma = [], [], [], 0.0, []
    for seed in range(60):
        data, k = procedure(seed, prior)
        fit = fit_coil_axes(data, prior)
        sigma_k = np.sqrt(np.diag(fit.k_cov)).reshape(3, 3).T
        z_k.append(((fit.k_ut_per_a - k) / sigma_k).ravel())
        const_err = fit.constants_ut_per_a - CONSTANTS
        z_const.append(const_err / fit.constants_sigma)
        worst_const = max(worst_const, float(np.max(np.abs(const_err) / CONSTANTS)))
        z_skew.append((fit.skew_arcsec - skews_arcsec(k)) / fit.skew_sigma_arcsec)
        skew_sigma.append(fit.skew_sigma_arcsec)
    rms = {name: float(np.sqrt(np.mean(np.square(z))))
           for name, z in (("K", z_k), ("constants", z_const), ("skews", z_skew))}  # fmt: skip
    assert all(0.8 <= v <= 1.25 for v in rms.values()), rms
    assert worst_const < 2e-4, worst_const  # every procedure: constants within 2e-4
    assert np.max(skew_sigma) < 30.0, np.max(skew_sigma)  # the skews known to within 30 arcsec
    assert fit.skew_arcsec[0] == pytest.approx(SKEW_XY_DEG * 3600, abs=4 * fit.skew_sigma_arcsec[0])


def test_a_missing_position_is_named() -> None:
    prior = SensorPrior(certificate_l())
    data, _ = procedure(1, prior)
    with pytest.raises(UserInputError, match=r"coil y in position '\+90 about x'"):
        fit_coil_axes([r for r in data if not (r.position == 2 and r.coil == 1)], prior)


def test_the_sigmas_follow_the_residuals_not_the_readings_scatter() -> None:
    """Responses five times noisier than their sigmas say, or with sigmas five times too large
    (a scatter of mains ripple that averages out): the fit's residuals set the scale, and the
    result says so."""
    prior = SensorPrior(certificate_l())
    data, _ = procedure(2, prior)
    rng = np.random.default_rng(9)
    noisy = [CoilResponse(r.position, r.coil, r.per_amp_ut + 5 * NOISE_UT_PER_A
                          * rng.standard_normal(3), r.sigma_ut) for r in data]  # fmt: skip
    timid = [CoilResponse(r.position, r.coil, r.per_amp_ut, 5 * r.sigma_ut) for r in data]
    plain = fit_coil_axes(data, prior)
    worse, same = fit_coil_axes(noisy, prior), fit_coil_axes(timid, prior)
    assert 0.7 < plain.noise_scale < 1.3 and not plain.notes
    assert worse.noise_scale > 3 and "the sigmas are the fit's" in worse.notes[0]
    assert np.all(worse.skew_sigma_arcsec > 2 * plain.skew_sigma_arcsec)
    assert same.noise_scale == pytest.approx(plain.noise_scale / 5, rel=1e-3) and same.notes
    np.testing.assert_allclose(same.skew_sigma_arcsec, plain.skew_sigma_arcsec, rtol=1e-3)
