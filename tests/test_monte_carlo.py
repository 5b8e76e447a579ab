"""Monte Carlo over noise: spread of the estimates against the CRLB and the reported sigma."""

from __future__ import annotations

import numpy as np
import pytest

from rig.calibration import calibrate
from rig.calibration.residuals import p_from_calibration
from rig.calibration.synthetic import SyntheticCase, cage_like, rax_like

pytestmark = pytest.mark.montecarlo

DRAWS = 40


def _monte_carlo(case: SyntheticCase, method: str, noise_nt: float, vector: bool):  # type: ignore[no-untyped-def]
    truth = p_from_calibration(case.truth, vector=vector)
    errors, sigmas, crlbs = [], [], []
    for k in range(DRAWS):
        result = calibrate(case.with_noise(1000 + k).samples, method, noise_nt=noise_nt)  # type: ignore[arg-type]
        err = result.p - truth
        if vector:  # rotation errors are about each fit's own mounting: compare to the truth's
            rel = result.calibration.rotation @ case.truth.rotation.T
            err[9:12] = 0.5 * np.array(
                [rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]
            )
        errors.append(err)
        sigmas.append(result.sigma)
        crlbs.append(result.crlb_sigma)
    errors_a = np.array(errors)
    spread = errors_a.std(axis=0, ddof=1)
    return errors_a, spread, np.mean(sigmas, axis=0), np.mean(crlbs, axis=0)


def test_ml_reaches_the_cramer_rao_bound() -> None:
    case = rax_like(2000, seed=31)
    errors, spread, sigma, crlb = _monte_carlo(case, "ml", 100.0, vector=False)
    to_crlb = spread / crlb
    to_sigma = spread / sigma
    # Averaged over the 24 parameters: within 20 % (a 40-draw spread itself scatters by 11 %).
    assert abs(np.mean(to_crlb) - 1.0) < 0.2, to_crlb
    assert abs(np.mean(to_sigma) - 1.0) < 0.2, to_sigma
    # Each parameter inside the 99.9 % band of a 40-draw standard deviation.
    assert np.all((to_crlb > 0.6) & (to_crlb < 1.45)), to_crlb
    # Unbiased: the mean error is within 4 standard errors for every parameter.
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * crlb / np.sqrt(DRAWS))
    # The reported sigma itself sits on the CRLB (ML is efficient).
    np.testing.assert_allclose(sigma / crlb, 1.0, atol=0.05)


def test_centered_is_consistent_but_above_the_bound() -> None:
    case = rax_like(2000, seed=32)
    _, spread, sigma, crlb = _monte_carlo(case, "centered", 100.0, vector=False)
    assert abs(np.mean(spread / sigma) - 1.0) < 0.2  # its own covariance is honest
    assert np.mean(sigma / crlb) > 1.05  # but the centering approximation costs efficiency


def test_vector_covariance_matches_spread() -> None:
    case = cage_like(600, seed=33, noise_ut=0.05)
    _, spread, sigma, crlb = _monte_carlo(case, "vector", 50.0, vector=True)
    assert abs(np.mean(spread / crlb) - 1.0) < 0.2
    assert abs(np.mean(spread / sigma) - 1.0) < 0.2
