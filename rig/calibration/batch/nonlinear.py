"""Iterative estimators: scalar maximum likelihood, TWOSTEP (Alonso-Shuster), robust vector fit."""

from __future__ import annotations

from dataclasses import replace
from typing import Literal

import numpy as np

from rig.calibration.batch.linear import centered_fit, ellipsoid_fit, vector_fit
from rig.calibration.diagnostics import is_constant_field, require_varying_field
from rig.calibration.estimate import Estimate, delta_method
from rig.calibration.params import Array
from rig.calibration.residuals import (
    Samples,
    p_from_theta,
    scalar_noise_gain,
    scalar_normal_equations,
    scalar_residuals_only,
    theta_from_p,
    vector_residuals,
    z_eiv_correlation,
    z_noise_mean,
    z_residuals,
)
from rig.calibration.robust import RobustLoss, robust_scale, robust_weights
from rig.calibration.solver import (
    NormalEquations,
    covariance_from_jacobian,
    covariance_from_normal,
    levenberg_marquardt,
)
from rig.errors import CalibrationError

MAX_IRLS_PASSES = 12
MAX_GN_STEPS = 50
GN_TOLERANCE = 1e-9
"""TWOSTEP's Gauss-Newton stops when no parameter moves by more than this (relative)."""
GAIN_TOLERANCE = 1e-3
"""Noise-gain change (relative) below which the ML weights are not refreshed: the efficiency lost
to a weight error e is of order e^2."""


START_ROWS = 20_000
"""A start for the maximum-likelihood fit (``scalar_start(quick=True)``) is fitted on at most
about this many evenly spread samples (more with many telemetry channels: 50 per column of the
linear design). The linear fit's cost grows with samples x columns^2 and its columns with the
square of the channels (the nuisance products), the ML fit's only with samples x parameters^2."""


def scalar_start(s: Samples, *, quick: bool = False) -> Estimate:
    """The linear initializer suited to the data: centered if |h| varies, else the ellipsoid.

    ``quick``: only a start is wanted (for :func:`ml_fit`), so on more than :data:`START_ROWS`
    samples it is fitted on evenly spread rows; the estimate's method then reads
    ``centered-start`` or ``ellipsoid-start`` (it is not the linear estimator's answer).
    """
    fit = ellipsoid_fit if is_constant_field(s) else centered_fit
    n_x = 9 + 3 * s.n_channels + s.n_channels * (s.n_channels + 3) // 2
    rows = max(START_ROWS, 50 * n_x)
    if not quick or s.n <= 2 * rows:
        return fit(s)
    est = fit(s.rows(slice(0, s.n, s.n // rows)))
    return replace(est, method=f"{est.method}-start")


def ml_fit(
    s: Samples,
    start: Array | None = None,
    robust: RobustLoss | None = None,
) -> Estimate:
    """Attitude-independent maximum likelihood: minimize ``sum w_k (|W v_k| - |h_k|)^2``.

    ``w_k = 1/|W^T n_k|^2`` is the inverse variance of the magnitude residual under isotropic raw
    noise (first order), refreshed between passes. With ``robust`` the weights are multiplied by
    Huber or bisquare IRLS weights on the standardized residuals.
    """
    p = scalar_start(s, quick=True).p if start is None else np.asarray(start, float)
    robust_w = np.ones(s.n)
    iterations = 0
    # Pass 1 fits with the noise gains of the start; pass 2 refreshes them if they moved (from a
    # cold start). Robust fits iterate until the IRLS weights settle. Every evaluation returns the
    # noise gains at its point, so the refresh costs no extra pass over the data.
    gain = scalar_noise_gain(p, s)
    for pass_index in range(MAX_IRLS_PASSES if robust else 2):
        w = robust_w / gain**2

        def fun(x: Array, w: Array = w) -> NormalEquations:
            return scalar_normal_equations(x, s, w)

        sol = levenberg_marquardt(fun, p)
        iterations += sol.iterations
        p = sol.x
        assert sol.normal.gain is not None
        new_gain = sol.normal.gain
        gain_change = float(np.max(np.abs(new_gain / gain - 1.0)))
        gain = new_gain
        if robust:
            new_w = robust_weights(scalar_residuals_only(p, s) / gain, robust)
            change = float(np.max(np.abs(new_w - robust_w)))
            robust_w = new_w
            if change < 1e-3 and pass_index > 0:
                break
        elif gain_change < GAIN_TOLERANCE:
            break  # refreshing the weights would move the estimate by a negligible amount
    if not sol.converged:
        raise CalibrationError(
            "the maximum-likelihood fit did not converge: check the column order and units, and"
            " that the field directions cover the sphere (turn the sensor through every attitude)"
        )
    dof = max(float(np.sum(robust_w > 0)) - p.size, 1.0)
    cov = covariance_from_normal(sol.normal.jtj, sol.cost / dof)
    return Estimate(
        "ml", p, cov, sample_weights=None if robust is None else robust_w, iterations=iterations
    )


def twostep_fit(
    s: Samples,
    noise_ut: float | None = None,
    start: Estimate | None = None,
    noise_frame: Literal["raw", "corrected"] = "raw",
) -> Estimate:
    """TWOSTEP: the centered estimate, then Gauss-Newton on the full (uncentered) z-domain loss,
    bias-compensated.

    The z residual keeps the ``|b|^2`` term that centering discards, with its mean ``tr(M
    Sigma)`` (:func:`z_noise_mean`); ``sigma`` is the given noise (raw, or on the corrected side
    as in Crassidis eq. 1) or the centered estimate's residual scale. The regressors hold the noisy
    readings, so plain Gauss-Newton converges to a point biased by a fixed amount of order
    ``sigma^2`` (1.2 and 1.3 sigma on scale b and offset y0 at 11 520 samples of the Crassidis
    Table 1 orbit); each step here subtracts the expected regressor-residual correlation
    (:func:`z_eiv_correlation`) from the gradient. ``start``: the centered estimate, when already
    computed.
    """
    require_varying_field(s, "TWOSTEP")
    start = centered_fit(s) if start is None else start
    theta = theta_from_p(start.p)
    given = noise_ut is not None
    if noise_ut is None:
        r0, _ = z_residuals(theta, s)
        noise_ut = float(np.sqrt(np.mean(r0**2)))
    theta, iterations = _twostep_gauss_newton(theta, s, noise_ut, noise_frame)
    if not given and noise_frame == "raw":
        # The centered fit's residuals overstate the noise (its model error counts as noise) and
        # the compensation scales as its square: over-compensated by 1.6-1.8 sigma on b and y0 of
        # the TRMM orbit (issue 34 audit). Take the noise from this fit's residuals and go again.
        r, _ = z_residuals(theta, s, z_noise_mean(theta, noise_ut, noise_frame))
        gain = scalar_noise_gain(p_from_theta(theta), s)
        noise_ut = float(np.sqrt(np.sum(r**2) / max(s.n - theta.size, 1) / np.mean(gain**2)))
        theta, more = _twostep_gauss_newton(theta, s, noise_ut, noise_frame)
        iterations += more
    r, jac = z_residuals(theta, s, z_noise_mean(theta, noise_ut, noise_frame))
    dof = max(s.n - theta.size, 1)
    cov_theta = covariance_from_jacobian(jac, float(r @ r) / dof)
    p, cov = delta_method(p_from_theta, theta, cov_theta, "TWOSTEP")
    return Estimate("twostep", p, cov, iterations=iterations)


def _twostep_gauss_newton(
    theta: Array, s: Samples, noise_ut: float, noise_frame: Literal["raw", "corrected"]
) -> tuple[Array, int]:
    """TWOSTEP's bias-compensated Gauss-Newton from ``theta`` for raw noise ``noise_ut`` (uT):
    the converged ``theta`` and the steps taken; CalibrationError when it does not converge."""
    inv_scale2 = 1.0 / (2.0 * s.field_magnitude_ut) ** 2
    for iterations in range(1, MAX_GN_STEPS + 1):
        r, jac = z_residuals(theta, s, z_noise_mean(theta, noise_ut, noise_frame))
        correlation = z_eiv_correlation(theta, s, noise_ut, noise_frame)
        # r = (z - model) / 2|h|, jac = -dmodel / 2|h|: the compensated gradient is
        # sum (dmodel (z - model) - E[dmodel (z - model)]) / (2|h|)^2
        gradient = -(jac.T @ r) - (correlation.T @ inv_scale2)
        step = np.linalg.solve(jac.T @ jac, gradient)
        theta = theta + step
        if not np.all(np.isfinite(theta)):
            break
        if np.all(np.abs(step) <= GN_TOLERANCE * (np.abs(theta) + 1e-6)):
            return theta, iterations
    raise CalibrationError("TWOSTEP's Gauss-Newton step did not converge: try --method ml")


def robust_vector_fit(s: Samples, loss: RobustLoss) -> Estimate:
    """IRLS around the cage linear least squares, one weight per sample from its residual norm."""
    est = vector_fit(s)
    weights = np.ones(s.n)
    for _ in range(MAX_IRLS_PASSES):
        assert est.rotation_ref is not None
        r, _ = vector_residuals(est.p, s, est.rotation_ref)
        per_axis = r.reshape(-1, 3)
        size = np.linalg.norm(per_axis, axis=1) / np.sqrt(3.0)
        new_w = robust_weights(size, loss, scale=robust_scale(per_axis.reshape(-1)))
        change = float(np.max(np.abs(new_w - weights)))
        weights = new_w
        est = vector_fit(s, weights)
        if change < 1e-3:
            break
    return est
