"""The field over the DUT's volume from a reference moved over a grid: a harmonic field map.

In the working volume (no currents, no magnetic material) the field is the gradient of a scalar
potential that satisfies Laplace's equation, so it is fitted in the basis of the gradients of the
harmonic polynomials up to degree ``D`` (2 D + 1 of each degree: 3 terms for a uniform field, 5
for a gradient, 7 for the second order, ...; D = 5 is 35 terms and holds the fourth-order error of
a Helmholtz pair, whose second order vanishes by design). The basis is built, not typed in: the
harmonic polynomials of each degree are the null space of the Laplacian on its monomials. Fitted
by linear least squares, weighted by the readings' sigmas and scaled by the fit's residuals (as in
:mod:`rig.cage.coil_axes`); :meth:`FieldMap.error_ut` gives the field at a position less the field
at the centre with its covariance: the cage's homogeneity term for a DUT there.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from rig.errors import UserInputError

Array = npt.NDArray[np.float64]


def _monomials(degree: int) -> list[tuple[int, int, int]]:
    return [
        (a, b, degree - a - b) for a in range(degree, -1, -1) for b in range(degree - a, -1, -1)
    ]


@lru_cache(maxsize=16)
def harmonic_polynomials(degree: int) -> tuple[list[tuple[int, int, int]], Array]:
    """The monomials of ``degree`` and a basis of the harmonic polynomials among them (rows:
    coefficients over the monomials), ``2 degree + 1`` of them."""
    from scipy.linalg import null_space

    mons = _monomials(degree)
    lower = {m: i for i, m in enumerate(_monomials(degree - 2))} if degree >= 2 else {}
    lap = np.zeros((max(len(lower), 1), len(mons)))
    for j, (a, b, c) in enumerate(mons):
        for k, e in enumerate((a, b, c)):
            if e >= 2:
                reduced = [a, b, c]
                reduced[k] -= 2
                lap[lower[(reduced[0], reduced[1], reduced[2])], j] += e * (e - 1)
    basis = null_space(lap).T if lower else np.eye(len(mons))
    return mons, basis


def field_basis(points_m: Array, max_degree: int) -> Array:
    """Gradients of the harmonic polynomials of degrees 1 to ``max_degree`` at ``points`` ((N, 3),
    m): (N, 3, P) with P = (max_degree + 1)^2 - 1. Coordinates are in units of ``SCALE_M`` inside,
    so the columns are of similar size."""
    p = np.asarray(points_m, float) / SCALE_M
    columns = []
    for degree in range(1, max_degree + 1):
        mons, basis = harmonic_polynomials(degree)
        grads = np.zeros((p.shape[0], 3, len(mons)))
        for j, (a, b, c) in enumerate(mons):
            exps = (a, b, c)
            for k in range(3):
                if exps[k] == 0:
                    continue
                e = list(exps)
                e[k] -= 1
                grads[:, k, j] = exps[k] * p[:, 0] ** e[0] * p[:, 1] ** e[1] * p[:, 2] ** e[2]
        columns.append(grads @ basis.T)
    return np.concatenate(columns, axis=2)


SCALE_M = 0.1
"""Length unit of the basis (m): coefficients are field per 10 cm to the power of the order."""


@dataclass(frozen=True)
class FieldMap:
    """A fitted field map: coefficients (P) of :func:`field_basis` and their covariance, the
    degree, the fit's chi-square and degrees of freedom and the scale its residuals put on the
    readings' sigmas."""

    coefficients: Array
    covariance: Array
    max_degree: int
    chi2: float
    dof: int
    noise_scale: float

    def field_ut(self, points_m: Array) -> tuple[Array, Array]:
        """Field (N, 3) at ``points`` and its covariance (3N x 3N)."""
        a = field_basis(np.atleast_2d(points_m), self.max_degree).reshape(
            -1, self.coefficients.size
        )
        return (a @ self.coefficients).reshape(-1, 3), a @ self.covariance @ a.T

    def error_ut(self, points_m: Array) -> tuple[Array, Array]:
        """Field at ``points`` less the field at the centre ((N, 3)) and 1-sigma of each component:
        the cage's homogeneity error for a DUT there."""
        pts = np.atleast_2d(np.asarray(points_m, float))
        a = field_basis(np.vstack([pts, np.zeros((1, 3))]), self.max_degree)
        diff = (a[:-1] - a[-1][None]).reshape(-1, self.coefficients.size)
        value = (diff @ self.coefficients).reshape(-1, 3)
        var = np.einsum("ij,jk,ik->i", diff, self.covariance, diff)
        return value, np.sqrt(np.clip(var, 0.0, None)).reshape(-1, 3)


def fit_field_map(
    points_m: Array, fields_ut: Array, sigma_ut: Array, max_degree: int = 6
) -> FieldMap:
    """Fit the field readings ``fields_ut`` ((N, 3), cage frame) taken at ``points`` ((N, 3), m)
    with 1-sigma ``sigma_ut`` ((N, 3)) by the harmonic basis up to ``max_degree``.

    UserInputError when the grid has too few positions for the degree, or positions that do not
    determine it (repeated ones). (Three components on one plane do determine a source-free field,
    but poorly: a grid spread in all three directions is the one to use.)
    """
    pts = np.asarray(points_m, float)
    a = field_basis(pts, max_degree).reshape(-1, (max_degree + 1) ** 2 - 1)
    y = np.asarray(fields_ut, float).reshape(-1)
    w = 1.0 / np.asarray(sigma_ut, float).reshape(-1)
    n_par = a.shape[1]
    if y.size <= n_par:
        raise UserInputError(
            f"field map: {len(pts)} positions give {y.size} readings for {n_par} terms of degree"
            f" {max_degree}: measure at least {n_par // 3 + 2} positions or lower the degree"
        )
    aw = a * w[:, None]
    u, s, vt = np.linalg.svd(aw, full_matrices=False)
    if s[-1] < 1e-9 * s[0]:
        raise UserInputError(
            f"field map: the positions do not determine a degree-{max_degree} map (too few"
            " distinct positions): add positions spread over the volume in all three directions"
        )
    coef = vt.T @ ((u.T @ (y * w)) / s)
    resid = (y - a @ coef) * w
    dof = y.size - n_par
    chi2 = float(resid @ resid)
    scale2 = chi2 / dof
    cov = (vt.T / s**2) @ vt * scale2 * (dof / (dof - 2.0) if dof > 4 else 3.0)
    return FieldMap(coef, cov, max_degree, chi2, dof, math.sqrt(scale2))


def grid_positions(half_width_m: float, per_axis: int = 3) -> Array:
    """A cubic grid of ``per_axis``^3 positions over +-``half_width_m`` about the centre (m)."""
    ticks = np.linspace(-half_width_m, half_width_m, per_axis)
    return np.array(list(itertools.product(ticks, ticks, ticks)), float)
