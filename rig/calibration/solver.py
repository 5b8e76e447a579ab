"""Levenberg-Marquardt on the normal equations, for residuals with analytic Jacobians.

scipy's ``least_squares`` factors the full N x P Jacobian every iteration; for calibration N is large
(1e5 samples) and P small (9-30), so forming ``J^T J`` (one BLAS call) and solving a P x P system is
an order of magnitude cheaper (see ``bench/bench_scalar_fit.py`` and docs/adr/0004).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rig.calibration.params import Array

ResidualFunction = Callable[[Array], tuple[Array, Array]]


@dataclass(frozen=True)
class LeastSquaresSolution:
    """Solution of a nonlinear least-squares problem (residuals and Jacobian at ``x``)."""

    x: Array
    residuals: Array
    jacobian: Array
    iterations: int
    converged: bool

    @property
    def cost(self) -> float:
        """Sum of squared residuals."""
        return float(self.residuals @ self.residuals)


def levenberg_marquardt(
    fun: ResidualFunction,
    x0: Array,
    *,
    max_iterations: int = 100,
    rel_tol: float = 1e-12,
    stat_tol: float = 1e-2,
) -> LeastSquaresSolution:
    """Minimize ``|r(x)|^2`` from ``x0``; ``fun`` returns ``(r, dr/dx)``.

    Marquardt scaling by ``diag(J^T J)``; the damping shrinks after a successful step and grows after
    a rejected one. Converged when the linear model predicts a cost decrease below ``rel_tol`` of
    the cost, or below what moving the estimate by ``stat_tol`` of its own standard deviation
    would give (``stat_tol^2`` times the residual variance): checked before evaluating, so a
    converged fit costs no extra evaluation. Also converged when
    an accepted step reduces the cost by less than ``rel_tol`` and moves less than
    ``sqrt(rel_tol)`` (scaled).
    """
    x = np.asarray(x0, dtype=float).copy()
    r, jac = fun(x)
    cost = float(r @ r)
    if not np.isfinite(cost):
        raise FloatingPointError("residuals are not finite at the starting point")
    damping = 1e-4
    dof = max(r.size - x.size, 1)
    converged = False
    iteration = 0
    while iteration < max_iterations:
        iteration += 1
        jtj = jac.T @ jac
        grad = jac.T @ r
        scale = np.maximum(np.diag(jtj), 1e-30)
        accepted = False
        while damping < 1e16:
            step = -np.linalg.solve(jtj + damping * np.diag(scale), grad)
            predicted = -(2.0 * grad @ step + step @ jtj @ step)
            if predicted <= max(rel_tol * cost, stat_tol**2 * cost / dof):
                break  # the model predicts no useful decrease: converged without evaluating
            x_new = x + step
            r_new, jac_new = fun(x_new)
            cost_new = float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                accepted = True
                break
            damping *= 8.0
        if not accepted:
            # Either the predicted decrease is negligible or no damping gives descent: at a
            # minimum within precision.
            converged = True
            break
        reduction = (cost - cost_new) / max(cost, 1e-300)
        step_size = float(
            np.sqrt(np.sum(step**2 * scale) / max(float(np.sum(x**2 * scale)), 1e-300))
        )
        x, r, jac, cost = x_new, r_new, jac_new, cost_new
        damping = max(damping / 5.0, 1e-12)
        if reduction < rel_tol and step_size < np.sqrt(rel_tol):
            converged = True
            break
    return LeastSquaresSolution(x, r, jac, iteration, converged)


def covariance_from_jacobian(jac: Array, variance: float) -> Array:
    """``variance * (J^T J)^-1`` via a pseudo-inverse that tolerates near-singular directions."""
    jtj = jac.T @ jac
    scale = np.sqrt(np.maximum(np.diag(jtj), 1e-300))
    normed = jtj / np.outer(scale, scale)
    inv = np.linalg.pinv(normed, rcond=1e-14, hermitian=True)
    return np.asarray(variance * inv / np.outer(scale, scale))
