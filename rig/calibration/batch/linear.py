"""Closed-form estimators: cage linear least squares, algebraic ellipsoid, centered.

Each returns an :class:`~rig.calibration.estimate.Estimate` in the physical parameterization with a covariance of its own:
the linear least-squares covariance of its coefficients, mapped to the physical parameters.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rig.calibration.diagnostics import is_constant_field, require_varying_field
from rig.calibration.estimate import Estimate, delta_method
from rig.calibration.params import Array, Calibration
from rig.calibration.residuals import (
    Samples,
    p_from_calibration,
    p_from_theta,
    quadratic_features,
    row_blocks,
    sym_from_e,
    vector_residuals,
    z_linear_design,
    z_observation,
)
from rig.calibration.solver import per_axis_covariance
from rig.errors import CalibrationError

SHIFT_ROWS = 4096
"""About this many evenly spread rows give the provisional means the Gram matrices are accumulated
about (so that centering afterwards subtracts only a small correction)."""


@dataclass(frozen=True)
class _LinearFit:
    """A weighted linear least-squares fit ``y = intercept + x[:, keep] coef``: ``coef`` (K, Y),
    ``inv = (X_c^T W X_c)^-1`` of the kept (centered) columns, the weighted residual sum of
    squares over all Y columns, and ``keep``, the indices of the columns of ``x`` used."""

    coef: Array
    intercept: Array
    inv: Array
    rss: float
    keep: Array


def _weighted_sums(
    build: Callable[[slice], Array], n: int, w: Array, shift: Array | None
) -> tuple[Array, Array]:
    """The weighted Gram matrix ``A^T W A`` and column sums ``sqrt(w) @ sqrt(w) A`` of the rows
    of ``build`` (less ``shift`` when given), block by block."""
    gram = np.zeros((0, 0))
    total = np.zeros(0)
    for rows in row_blocks(n):
        a = build(rows)  # a fresh array: scaled in place
        if shift is not None:
            a -= shift
        if gram.size == 0:
            gram, total = np.zeros((a.shape[1], a.shape[1])), np.zeros(a.shape[1])
        sw = np.sqrt(w[rows])
        a *= sw[:, None]
        gram += a.T @ a
        total += sw @ a
    return gram, total


def _linear_fit(
    build: Callable[[slice], Array],
    n: int,
    n_x: int,
    weights: Array | None,
    *,
    n_fixed: int | None = None,
    intercept: bool = True,
) -> _LinearFit:
    """Weighted least squares by normal equations accumulated block by block (bounded memory).

    ``build(rows)`` gives the rows of ``[x | y]`` (x first, ``n_x`` columns) as a new array (the
    fit scales it in place); columns from
    ``n_fixed`` on are nuisance candidates kept only when linearly independent of the others
    before them (:func:`independent_from_gram` on their centered Gram). With ``intercept`` the
    problem is solved centered (the weighted means removed, as a free constant would). The
    columns are scaled to unit norm before solving, and a normal matrix with a condition number
    above 1e15 is refused as before. A second pass forms the residuals exactly (not by
    subtracting sums of squares).
    """
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    step = max(n // SHIFT_ROWS, 1)
    sample = slice(0, n, step)
    shift = np.zeros(0)
    if intercept:
        a = build(sample)
        shift = (w[sample] @ a) / max(float(np.sum(w[sample])), 1e-300)
    gram, total = _weighted_sums(build, n, w, shift if intercept else None)
    w_sum = float(np.sum(w))
    d = total / w_sum
    centered = gram - w_sum * np.outer(d, d)
    if intercept:
        gram, mean = centered, shift + d
    n_fixed = n_x if n_fixed is None else n_fixed
    # Candidates are told apart centered (a constant among them is the intercept's business).
    extra = n_fixed + independent_from_gram(centered[n_fixed:n_x, n_fixed:n_x])
    keep = np.concatenate([np.arange(n_fixed), extra]).astype(int)
    xtx = gram[np.ix_(keep, keep)]
    xty = gram[keep, n_x:]
    col = np.sqrt(np.maximum(np.diag(xtx), 0.0))
    col[col == 0] = 1.0
    normal = xtx / np.outer(col, col)
    cond = np.linalg.cond(normal)
    if not np.isfinite(cond) or cond > 1e15:
        raise CalibrationError(
            "the calibration problem is singular for these data (condition number"
            f" {cond:.1e}): cover more field directions and magnitudes, and vary each channel"
        )
    coef = np.linalg.solve(normal, xty / col[:, None]) / col[:, None]
    inv = np.linalg.inv(normal) / np.outer(col, col)
    const = mean[n_x:] - mean[keep] @ coef if intercept else np.zeros(gram.shape[0] - n_x)
    rss = 0.0
    for rows in row_blocks(n):
        a = build(rows)
        resid = a[:, n_x:] - a[:, keep] @ coef - const
        rss += float(np.sum(w[rows] @ resid**2))
    return _LinearFit(coef, const, inv, rss, keep)


def vector_fit(s: Samples, weights: Array | None = None) -> Estimate:
    """Cage calibration: ``m = T h + o + K^T u`` by linear least squares, all three axes at once.

    Exact maximum likelihood for isotropic Gaussian noise on ``m``; ``T`` is then split into the
    mounting rotation and the Springmann-Cutler sensor matrix. The covariance takes each axis's
    residual variance (the estimate is the same whatever the axes' variances: each axis's
    coefficients come from that axis's rows alone).
    """
    if s.field_ut is None:
        raise CalibrationError("vector calibration needs the field vector: give --field X,Y,Z")
    field = s.field_ut

    def build(rows: slice) -> Array:
        return np.hstack([field[rows], s.telemetry[rows], s.measured_ut[rows]])

    fit = _linear_fit(build, s.n, 3 + s.n_channels, weights)
    coef = fit.coef
    cal = Calibration.from_t_matrix(coef[:3].T, fit.intercept, coef[3:], s.channels)
    if np.linalg.det(cal.rotation) < 0:
        raise CalibrationError(
            "the fitted sensor frame is left-handed (an axis is inverted): check the sign and"
            " order of the --measured columns against the --field columns"
        )
    p = p_from_calibration(cal, vector=True)
    r, jac = vector_residuals(p, s, cal.rotation)
    sw = np.ones(3 * s.n) if weights is None else np.sqrt(np.repeat(weights, 3))
    # each axis its own noise variance (the axes of a sensor, or a model's misfit, differ)
    cov = per_axis_covariance(jac * sw[:, None], r * sw)
    return Estimate("vector", p, cov, rotation_ref=cal.rotation, sample_weights=weights)


def _telemetry_products(u: Array, out: Array | None = None) -> Array:
    """Columns ``u_j`` and ``u_i u_j`` (i <= j): the candidate nuisance terms of ``|b(u)|^2``.

    Products that vanish or repeat (two panels never lit at once, a binary channel whose square is
    itself) are dropped by the fits (:func:`_linear_fit`): only the span matters for nuisance
    terms. ``out``: where to write them (N, J (J + 3) / 2), column-major is fastest.
    """
    n_ch = u.shape[1]
    if out is None:
        out = np.empty((u.shape[0], n_ch * (n_ch + 3) // 2), order="F")
    out[:, :n_ch] = u
    col = n_ch
    for i in range(n_ch):  # u_i u_j for j >= i, one broadcast product per i
        np.multiply(u[:, i : i + 1], u[:, i:], out=out[:, col : col + n_ch - i])
        col += n_ch - i
    return out


def independent_from_gram(gram: Array, rel_tol: float = 1e-9) -> Array:
    """Indices of a maximal linearly independent subset of the columns of ``X``, in order, from
    their Gram (information) matrix ``X^T X``: a column is kept when its part orthogonal to the
    kept ones carries more than ``rel_tol`` of its own norm squared.

    Left-looking Cholesky in column order that skips a column whose pivot (the squared norm of
    its part orthogonal to the kept ones, the Schur complement) is below ``rel_tol`` of its own
    squared norm: one matrix-vector product per column, O(n^3) in all.
    """
    n = gram.shape[0]
    factor = np.zeros((n, n))
    keep: list[int] = []
    for i in range(n):
        own = gram[i, i]
        if own <= 1e-300:
            continue
        k = len(keep)
        col = gram[:, i] - factor[:, :k] @ factor[i, :k]
        if col[i] > rel_tol * own:
            factor[:, k] = col / np.sqrt(col[i])
            keep.append(i)
    return np.asarray(keep, dtype=int)


def centered_fit(s: Samples) -> Estimate:
    """Centered estimator (Crassidis eqs. 15-18) extended with telemetry regressors.

    The z model ``2 m^T c(u) - S E - |b(u)|^2`` is linear once the telemetry-dependent parts of
    ``|b(u)|^2`` (terms in ``u_j`` and ``u_i u_j``) get free coefficients; centering removes the
    constant. Weights ``1/sigma_k^2`` with ``sigma_k ~ 2 |h_k|`` (eq. 5b, isotropic noise).
    Singular when |h| is constant: that case raises a :class:`CalibrationError`.

    The regressors hold the noisy readings (errors in variables), so the estimate carries a bias of
    order ``sigma^2 / |h|^2`` that does not shrink with N: about 0.6 sigma on the scale factors at
    100 nT noise and 2000 samples (Monte Carlo, 60 draws). Use it as a start, not as the answer.
    """
    require_varying_field(s, "centered")
    n_lin = 9 + 3 * s.n_channels
    n_x = n_lin + s.n_channels * (s.n_channels + 3) // 2

    def build(rows: slice) -> Array:
        block = s.rows(rows)
        out = np.empty((block.n, n_x + 1), order="F")
        out[:, :n_lin] = z_linear_design(block)
        _telemetry_products(block.telemetry, out[:, n_lin:n_x])
        out[:, n_x] = z_observation(block)
        return out

    w = 1.0 / (4.0 * s.field_magnitude_ut**2)
    fit = _linear_fit(build, s.n, n_x, w, n_fixed=n_lin)
    dof = max(s.n - fit.keep.size - 1, 1)
    variance = fit.rss / dof
    cov_theta = variance * fit.inv[:n_lin, :n_lin]
    p, cov = delta_method(p_from_theta, fit.coef[:n_lin, 0], cov_theta, "centered")
    return Estimate("centered", p, cov)


def ellipsoid_fit(s: Samples) -> Estimate:
    """Algebraic ellipsoid fit (two-step, Foster-Elkaim) extended with telemetry terms.

    The quadric ``(m - c(u))^T M (m - c(u)) = |h|^2`` is linear in ``M``, ``M o``, ``M k_j`` and the
    nuisance telemetry terms. With |h| constant the constant term is the normalization (Foster and
    Elkaim) and the scale comes from |h|; with |h| varying, |h|^2 is the right-hand side, and the
    problem is then the same linear model as :func:`centered_fit` (centering is the intercept),
    so the two agree.
    """
    n_theta = 9 + 3 * s.n_channels
    n_x = n_theta + s.n_channels * (s.n_channels + 3) // 2
    mag2 = s.field_magnitude_ut**2
    constant = is_constant_field(s)
    mean_mag2 = float(np.mean(mag2))

    def build(rows: slice) -> Array:
        m, u = s.measured_ut[rows], s.telemetry[rows]
        mu = [u[:, j : j + 1] * m for j in range(s.n_channels)]
        y = -np.ones((m.shape[0], 1)) if constant else mag2[rows, None]
        return np.hstack([quadratic_features(m), m, *mu, _telemetry_products(u), y])

    # |h| constant: no intercept (the constant term is the normalization, Foster and Elkaim);
    # |h| varying: |h|^2 on the right-hand side with an intercept (solved centered).
    w = np.full(s.n, 1.0 / (4.0 * mean_mag2)) if constant else 1.0 / (4.0 * mag2)
    fit = _linear_fit(build, s.n, n_x, w, n_fixed=n_theta, intercept=not constant)
    dof = max(s.n - fit.keep.size - (0 if constant else 1), 1)
    variance = fit.rss / dof
    cov_coef = variance * fit.inv[:n_theta, :n_theta]
    coef = fit.coef[:, 0]

    def to_p(c: Array) -> Array:
        m_sym = sym_from_e(c[:6])  # S_k . c6 = m^T M m
        lin = -0.5 * c[6:9]
        kj = -0.5 * c[9:n_theta].reshape(-1, 3)
        if constant:
            o = np.linalg.solve(m_sym, lin)
            scale = mean_mag2 / (o @ m_sym @ o - 1.0)
            m_sym, lin, kj = scale * m_sym, scale * lin, scale * kj
        return p_from_theta(_theta_from_metric(m_sym, lin, kj))

    p, cov = delta_method(to_p, coef[:n_theta], cov_coef, "ellipsoid")
    note = ("constant |h|: Foster-Elkaim normalization",) if constant else ()
    return Estimate("ellipsoid", p, cov, notes=note)


def _theta_from_metric(metric: Array, m_o: Array, m_k: Array) -> Array:
    e = metric - np.eye(3)
    e6 = np.array([e[0, 0], e[1, 1], e[2, 2], e[0, 1], e[0, 2], e[1, 2]])
    return np.concatenate([m_o, e6, m_k.reshape(-1)])
