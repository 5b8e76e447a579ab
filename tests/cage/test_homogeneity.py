"""The harmonic field map against the simulated cage's Biot-Savart coils (the physics, no wire):
fitted over a 27-position grid it predicts the field error at random positions in the volume
within its stated uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from rig.cage.homogeneity import field_basis, fit_field_map, grid_positions
from rig.errors import UserInputError
from sim.config import load_config
from sim.physics import CagePhysics

NOISE_UT_PER_A = 5e-4  # 5 nT reference noise averaged and halved by a +-1 A difference


def test_the_basis_is_a_field_without_sources() -> None:
    pts = np.random.default_rng(1).uniform(-0.2, 0.2, (6, 3))
    h = 1e-5
    # d field_i / d x_k for every basis column: (N, 3 components, 3 derivatives, P)
    jac = np.stack([(field_basis(pts + h * e, 6) - field_basis(pts - h * e, 6)) / (2 * h)
                    for e in np.eye(3)], axis=2)  # fmt: skip
    assert jac.shape == (6, 3, 3, 48)
    div = jac[:, 0, 0] + jac[:, 1, 1] + jac[:, 2, 2]
    curl = [jac[:, 1, 0] - jac[:, 0, 1], jac[:, 2, 0] - jac[:, 0, 2], jac[:, 2, 1] - jac[:, 1, 2]]
    scale = np.abs(jac).max()
    assert np.abs(div).max() < 1e-6 * scale and max(np.abs(c).max() for c in curl) < 1e-6 * scale


@pytest.mark.parametrize(("half_width_m", "degree"), [(0.10, 5), (0.15, 6)])
def test_the_map_predicts_the_coils_field_error_within_its_sigma(
    half_width_m: float, degree: int
) -> None:
    physics = CagePhysics(load_config(), start_s=0.0)
    grid = grid_positions(half_width_m)
    rng = np.random.default_rng(7)
    z, largest = [], 0.0
    for coil in range(3):
        truth = np.array([physics.coil_matrix_at_m(p)[:, coil] for p in grid])
        centre = physics.coil_matrix[:, coil]
        for _ in range(8):
            noisy = truth + NOISE_UT_PER_A * rng.standard_normal(truth.shape)
            fitted = fit_field_map(grid, noisy, np.full(truth.shape, NOISE_UT_PER_A), degree)
            test = rng.uniform(-half_width_m, half_width_m, (10, 3))
            true_error = np.array([physics.coil_matrix_at_m(p)[:, coil] for p in test]) - centre
            value, sigma = fitted.error_ut(test)
            z.append(((value - true_error) / sigma).ravel())
            largest = max(largest, float(np.abs(true_error).max()))
    z_all = np.concatenate(z)
    rms = float(np.sqrt(np.mean(z_all**2)))
    assert 0.8 <= rms <= 1.25 and np.abs(z_all).max() < 5.0, rms
    assert largest > 10 * NOISE_UT_PER_A  # a real error to find: 5-33 nT/A at the corners


def test_a_grid_that_cannot_determine_the_map_is_refused() -> None:
    flat = grid_positions(0.1)
    flat = flat[flat[:, 2] == 0.0]  # one plane: 9 positions
    with pytest.raises(UserInputError, match="at least"):
        fit_field_map(flat, np.zeros((9, 3)), np.ones((9, 3)), 6)
    with pytest.raises(UserInputError, match="all three directions"):
        fit_field_map(np.vstack([flat] * 4), np.zeros((36, 3)), np.ones((36, 3)), 6)
