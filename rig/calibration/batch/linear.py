"""Closed-form estimators: cage linear least squares, algebraic ellipsoid, centered.

Each returns an :class:`~rig.calibration.estimate.Estimate` in the physical parameterization with a covariance of its own:
the linear least-squares covariance of its coefficients, mapped to the physical parameters.
"""

from __future__ import annotations

import numpy as np

from rig.calibration.diagnostics import is_constant_field, require_varying_field
from rig.calibration.estimate import Estimate, delta_method
from rig.calibration.params import Array, Calibration
from rig.calibration.residuals import (
    Samples,
    p_from_calibration,
    p_from_theta,
    quadratic_features,
    sym_from_e,
    vector_residuals,
    z_linear_design,
    z_observation,
)
from rig.calibration.solver import covariance_from_jacobian
from rig.errors import CalibrationError


def _weighted_lstsq(x: Array, y: Array, w: Array | None) -> tuple[Array, Array, Array]:
    """Solve ``x b = y`` in least squares with row weights; returns (b, residuals, (X^T W X)^-1)."""
    sw = np.ones(x.shape[0]) if w is None else np.sqrt(w)
    xs = x * sw[:, None]
    ys = y * (sw[:, None] if y.ndim == 2 else sw)
    col = np.linalg.norm(xs, axis=0)
    col[col == 0] = 1.0
    b, *_ = np.linalg.lstsq(xs / col, ys, rcond=None)
    b = (b.T / col).T if b.ndim == 2 else b / col
    normal = (xs / col).T @ (xs / col)
    cond = np.linalg.cond(normal)
    if not np.isfinite(cond) or cond > 1e15:
        raise CalibrationError(
            "the calibration problem is singular for these data (condition number"
            f" {cond:.1e}): cover more field directions and magnitudes, and vary each channel"
        )
    inv = np.linalg.inv(normal) / np.outer(col, col)
    return b, y - x @ b, inv


def vector_fit(s: Samples, weights: Array | None = None) -> Estimate:
    """Cage calibration: ``m = T h + o + K^T u`` by linear least squares, all three axes at once.

    Exact maximum likelihood for isotropic Gaussian noise on ``m``; ``T`` is then split into the
    mounting rotation and the Springmann-Cutler sensor matrix.
    """
    if s.field_ut is None:
        raise CalibrationError("vector calibration needs the field vector: give --field X,Y,Z")
    x = np.hstack([s.field_ut, np.ones((s.n, 1)), s.telemetry])
    coef, resid, _ = _weighted_lstsq(x, s.measured_ut, weights)
    cal = Calibration.from_t_matrix(coef[:3].T, coef[3], coef[4:], s.channels)
    if np.linalg.det(cal.rotation) < 0:
        raise CalibrationError(
            "the fitted sensor frame is left-handed (an axis is inverted): check the sign and"
            " order of the --measured columns against the --field columns"
        )
    p = p_from_calibration(cal, vector=True)
    _, jac = vector_residuals(p, s, cal.rotation)
    wr = np.ones(3 * s.n) if weights is None else np.repeat(weights, 3)
    dof = max(3 * s.n - p.size, 1)
    variance = float(np.sum(wr * resid.reshape(-1) ** 2) / dof)
    cov = covariance_from_jacobian(jac * np.sqrt(wr)[:, None], variance)
    return Estimate("vector", p, cov, rotation_ref=cal.rotation, sample_weights=weights)


def _telemetry_products(u: Array) -> Array:
    """Columns ``u_j`` and ``u_i u_j`` (i <= j): the nuisance terms of ``|b(u)|^2``.

    Products that vanish or repeat (two panels never lit at once, a binary channel whose square is
    itself) are dropped: only the span matters for nuisance terms.
    """
    n_ch = u.shape[1]
    if n_ch == 0:
        return np.zeros((u.shape[0], 0))
    cols = [u] + [(u[:, i] * u[:, j])[:, None] for i in range(n_ch) for j in range(i, n_ch)]
    x = np.hstack(cols)
    return x[:, independent_columns(x - x.mean(axis=0))]


def independent_columns(x: Array, rel_tol: float = 1e-9) -> Array:
    """Indices of a maximal linearly independent subset of the columns of ``x``, in order.

    Greedy Gram-Schmidt on the (small) Gram matrix: a column is kept when its part orthogonal to
    the kept ones carries more than ``rel_tol`` of its own norm squared.
    """
    return independent_from_gram(x.T @ x, rel_tol)


def independent_from_gram(gram: Array, rel_tol: float = 1e-9) -> Array:
    """:func:`independent_columns` given the Gram (information) matrix ``X^T X`` itself."""
    keep: list[int] = []
    for i in range(gram.shape[0]):
        own = gram[i, i]
        if own <= 1e-300:
            continue
        if keep:
            g_kk = gram[np.ix_(keep, keep)]
            g_ki = gram[keep, i]
            own = own - g_ki @ np.linalg.solve(g_kk, g_ki)
        if own > rel_tol * gram[i, i]:
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
    lin = z_linear_design(s)
    x = np.hstack([lin, _telemetry_products(s.telemetry)])
    z = z_observation(s)
    w = 1.0 / (4.0 * s.field_magnitude_ut**2)
    wn = w / w.sum()
    xc = x - wn @ x
    zc = z - wn @ z
    coef, resid, inv = _weighted_lstsq(xc, zc, w)
    n_theta = lin.shape[1]
    dof = max(s.n - x.shape[1] - 1, 1)
    variance = float(np.sum(w * resid**2) / dof)
    cov_theta = variance * inv[:n_theta, :n_theta]
    p, cov = delta_method(p_from_theta, coef[:n_theta], cov_theta, "centered")
    return Estimate("centered", p, cov)


def ellipsoid_fit(s: Samples) -> Estimate:
    """Algebraic ellipsoid fit (two-step, Foster-Elkaim) extended with telemetry terms.

    The quadric ``(m - c(u))^T M (m - c(u)) = |h|^2`` is linear in ``M``, ``M o``, ``M k_j`` and the
    nuisance telemetry terms. With |h| constant the constant term is the normalization (Foster and
    Elkaim) and the scale comes from |h|; with |h| varying, |h|^2 is the right-hand side, and the
    problem is then the same linear model as :func:`centered_fit` (centering is the intercept),
    so the two agree.
    """
    quad = quadratic_features(s.measured_ut)
    mu = [s.telemetry[:, j : j + 1] * s.measured_ut for j in range(s.n_channels)]
    base = np.hstack([quad, s.measured_ut, *mu, _telemetry_products(s.telemetry)])
    n_theta = 9 + 3 * s.n_channels
    mag2 = s.field_magnitude_ut**2
    w = 1.0 / (4.0 * mag2)
    constant = is_constant_field(s)
    if constant:
        x, y = base, -np.ones(s.n)
        mean_mag2 = float(np.mean(mag2))
        w = np.full(s.n, 1.0 / (4.0 * mean_mag2))
    else:
        x, y = np.hstack([base, np.ones((s.n, 1))]), mag2
    coef, resid, inv = _weighted_lstsq(x, y, w)
    dof = max(s.n - x.shape[1], 1)
    variance = float(np.sum(w * resid**2) / dof)
    cov_coef = variance * inv[:n_theta, :n_theta]

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
