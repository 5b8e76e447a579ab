"""Nonlinear least squares for tall, thin problems: Levenberg-Marquardt on the normal equations.

scipy's ``least_squares`` factors the full N x P Jacobian every iteration; for calibration N is large
(1e5-1e7 samples) and P small (9-70), so forming ``J^T J`` (one BLAS call per block of rows) and
solving a P x P system is an order of magnitude cheaper (see ``bench/bench_scalar_fit.py`` and
docs/adr/0004). The residual function hands back the normal equations themselves, accumulated
block by block, so no N x P array need exist at all (docs/adr/0017).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rig.calibration.params import Array


@dataclass(frozen=True)
class NormalEquations:
    """A weighted least-squares problem at one point, summed over the samples: ``J^T J`` (P, P),
    ``J^T r`` (P,), the cost ``r^T r`` and the number of residuals. ``gain``: per-sample values the
    residual function computed along the way (the scalar fit's noise gains ``|W^T n_hat_k|``),
    else None."""

    jtj: Array
    jtr: Array
    cost: float
    n_residuals: int
    gain: Array | None = None

    @staticmethod
    def of(residuals: Array, jacobian: Array) -> NormalEquations:
        """From a residual vector and its Jacobian held in memory."""
        return NormalEquations(
            jacobian.T @ jacobian, jacobian.T @ residuals, float(residuals @ residuals),
            int(residuals.size),
        )  # fmt: skip


NormalFunction = Callable[[Array], NormalEquations]


@dataclass(frozen=True)
class LeastSquaresSolution:
    """Solution of a nonlinear least-squares problem, with its normal equations at ``x``."""

    x: Array
    normal: NormalEquations
    iterations: int
    converged: bool

    @property
    def cost(self) -> float:
        """Sum of squared residuals."""
        return self.normal.cost


def levenberg_marquardt(
    fun: NormalFunction,
    x0: Array,
    *,
    max_iterations: int = 100,
    rel_tol: float = 1e-12,
    stat_tol: float = 1e-2,
) -> LeastSquaresSolution:
    """Minimize ``|r(x)|^2`` from ``x0``; ``fun`` returns the normal equations at ``x``.

    Marquardt scaling by ``diag(J^T J)``; the damping shrinks after a successful step and grows after
    a rejected one. Converged when the linear model predicts a cost decrease below ``rel_tol`` of
    the cost, or below what moving the estimate by ``stat_tol`` of its own standard deviation
    would give (``stat_tol^2`` times the residual variance): checked before evaluating, so a
    converged fit costs no extra evaluation. Also converged when
    an accepted step reduces the cost by less than ``rel_tol`` and moves less than
    ``sqrt(rel_tol)`` (scaled).
    """
    x = np.asarray(x0, dtype=float).copy()
    ne = fun(x)
    cost = ne.cost
    if not np.isfinite(cost):
        raise FloatingPointError("residuals are not finite at the starting point")
    damping = 1e-4
    dof = max(ne.n_residuals - x.size, 1)
    converged = False
    iteration = 0
    while iteration < max_iterations:
        iteration += 1
        jtj, grad = ne.jtj, ne.jtr
        scale = np.maximum(np.diag(jtj), 1e-30)
        accepted = False
        while damping < 1e16:
            step = -np.linalg.solve(jtj + damping * np.diag(scale), grad)
            predicted = -(2.0 * grad @ step + step @ jtj @ step)
            if predicted <= max(rel_tol * cost, stat_tol**2 * cost / dof):
                break  # the model predicts no useful decrease: converged without evaluating
            x_new = x + step
            ne_new = fun(x_new)
            cost_new = ne_new.cost
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
        x, ne, cost = x_new, ne_new, cost_new
        damping = max(damping / 5.0, 1e-12)
        if reduction < rel_tol and step_size < np.sqrt(rel_tol):
            converged = True
            break
    return LeastSquaresSolution(x, ne, iteration, converged)


def covariance_from_jacobian(jac: Array, variance: float) -> Array:
    """``variance * (J^T J)^-1`` via a pseudo-inverse that tolerates near-singular directions."""
    return covariance_from_normal(jac.T @ jac, variance)


def covariance_from_normal(jtj: Array, variance: float) -> Array:
    """``variance * (J^T J)^-1`` given ``J^T J`` (scaled pseudo-inverse, as
    :func:`covariance_from_jacobian`)."""
    scale = np.sqrt(np.maximum(np.diag(jtj), 1e-300))
    normed = jtj / np.outer(scale, scale)
    inv = np.linalg.pinv(normed, rcond=1e-14, hermitian=True)
    return np.asarray(variance * inv / np.outer(scale, scale))


def axis_variances(residuals: Array, n_params: int) -> Array:
    """Residual variance per axis (3,) of a vector fit's residuals (3N,; x, y, z per sample), each
    axis charged a third of the ``n_params`` fitted."""
    per_axis = residuals.reshape(-1, 3)
    dof = max(per_axis.shape[0] - n_params / 3.0, 1.0)
    return np.asarray(np.sum(per_axis**2, axis=0) / dof)


def per_axis_covariance(jac: Array, residuals: Array) -> Array:
    """Least-squares covariance ``H^-1 (sum_a v_a J_a^T J_a) H^-1`` of a vector fit whose axes
    have their own noise variance ``v_a`` (:func:`axis_variances`), from its Jacobian (3N, P) and
    residuals (3N,), both already weighted; ``v (J^T J)^-1`` when the axes agree."""
    v = axis_variances(residuals, jac.shape[1])
    h_inv = covariance_from_normal(jac.T @ jac, 1.0)
    rows = jac.reshape(-1, 3, jac.shape[1])
    middle = sum(v[a] * (rows[:, a, :].T @ rows[:, a, :]) for a in range(3))
    return np.asarray(h_inv @ middle @ h_inv)
