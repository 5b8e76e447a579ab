"""Every analytic Jacobian equals central finite differences of its residual."""

from __future__ import annotations

import numpy as np
import pytest

from rig.calibration.residuals import (
    Samples,
    numeric_jacobian,
    p_from_calibration,
    scalar_residuals,
    theta_from_p,
    vector_residuals,
    z_residuals,
)
from rig.calibration.synthetic import SyntheticCase


def _perturbed(p: np.ndarray, seed: int) -> np.ndarray:
    """Away from the truth, so that no term of the Jacobian vanishes by accident."""
    rng = np.random.default_rng(seed)
    return p + 0.02 * rng.standard_normal(p.size) * np.maximum(np.abs(p), 0.1)


def _compare(analytic: np.ndarray, numeric: np.ndarray) -> None:
    scale = np.maximum(np.abs(numeric).max(axis=0), 1e-6)
    err = np.abs(analytic - numeric).max(axis=0) / scale
    assert err.max() < 1e-6, f"worst column {int(err.argmax())}: relative error {err.max():.2e}"


def test_scalar_jacobian(rax_case: SyntheticCase) -> None:
    s = Samples(
        *(
            a[:200]
            for a in (
                rax_case.samples.measured_ut,
                rax_case.samples.field_magnitude_ut,
                rax_case.samples.telemetry,
            )
        ),
        rax_case.samples.channels,
    )
    p = _perturbed(p_from_calibration(rax_case.truth, vector=False), 1)
    _, jac = scalar_residuals(p, s)
    assert jac.shape == (200, 9 + 3 * s.n_channels)
    _compare(jac, numeric_jacobian(lambda x: scalar_residuals(x, s)[0], p))


def test_vector_jacobian(cage_case: SyntheticCase) -> None:
    s0 = cage_case.samples
    s = Samples(
        s0.measured_ut[:150],
        s0.field_magnitude_ut[:150],
        s0.telemetry[:150],
        s0.channels,
        s0.field_ut[:150],
    )
    p = _perturbed(p_from_calibration(cage_case.truth, vector=True), 2)
    p[9:12] = 0.0  # the rotation error is defined about the reference rotation
    rot = cage_case.truth.rotation
    _, jac = vector_residuals(p, s, rot)
    assert jac.shape == (450, 12 + 3 * s.n_channels)
    _compare(jac, numeric_jacobian(lambda x: vector_residuals(x, s, rot)[0], p))


@pytest.mark.parametrize("mu", [0.0, -0.03])
def test_z_domain_jacobian(rax_case: SyntheticCase, mu: float) -> None:
    s0 = rax_case.samples
    s = Samples(s0.measured_ut[:200], s0.field_magnitude_ut[:200], s0.telemetry[:200], s0.channels)
    theta = _perturbed(theta_from_p(p_from_calibration(rax_case.truth, vector=False)), 3)
    _, jac = z_residuals(theta, s, mu)
    _compare(jac, numeric_jacobian(lambda x: z_residuals(x, s, mu)[0], theta))


def test_z_model_is_exact_at_truth(rax_case: SyntheticCase) -> None:
    """Noise-free data satisfy the z-domain model exactly (the algebra of Crassidis eqs. 2-4)."""
    s0 = rax_case.samples
    clean = rax_case.truth.predict(rax_case.field_ut, s0.telemetry)
    s = Samples(clean, s0.field_magnitude_ut, s0.telemetry, s0.channels)
    r, _ = z_residuals(theta_from_p(p_from_calibration(rax_case.truth, vector=False)), s)
    assert np.abs(r).max() < 1e-9
    r_scalar, _ = scalar_residuals(p_from_calibration(rax_case.truth, vector=False), s)
    assert np.abs(r_scalar).max() < 1e-9


def test_weighted_scalar_residuals_equal_weighting_afterwards(rax_case: SyntheticCase) -> None:
    s = rax_case.samples
    p = p_from_calibration(rax_case.truth, vector=False)
    sw = np.random.default_rng(4).uniform(0.5, 2.0, s.n)
    r, jac = scalar_residuals(p, s)
    rw, jw = scalar_residuals(p, s, sw)
    np.testing.assert_allclose(rw, r * sw, rtol=1e-13)
    np.testing.assert_allclose(jw, jac * sw[:, None], rtol=1e-12, atol=1e-15)
