"""One entry point: pick and run an estimator, return a :class:`CalibrationResult`."""

from __future__ import annotations

from typing import Literal

import numpy as np

from rig.calibration.diagnostics import check_samples
from rig.calibration.estimate import Estimate
from rig.calibration.linear import centered_fit, ellipsoid_fit, vector_fit
from rig.calibration.nonlinear import MAX_IRLS_PASSES, ml_fit, twostep_fit
from rig.calibration.params import Array
from rig.calibration.realtime import (
    FILTER_METHODS,
    FilterOptions,
    run_filter,
)
from rig.calibration.residuals import (
    Samples,
    scalar_noise_gain,
    scalar_residuals_only,
    vector_residuals,
)
from rig.calibration.result import CalibrationResult, summarize
from rig.calibration.robust import RobustLoss, robust_scale, robust_weights
from rig.errors import CalibrationError

Method = Literal["ml", "twostep", "centered", "ellipsoid", "vector", "centered-seq", "ekf", "ukf"]
METHODS: tuple[Method, ...] = (
    "ml", "twostep", "centered", "ellipsoid", "vector", *FILTER_METHODS
)  # fmt: skip
SCALAR_METHODS = frozenset({"ml", "twostep", "centered", "ellipsoid", *FILTER_METHODS})
ROBUST_METHODS = frozenset({"ml", "vector"})


def default_method(s: Samples) -> Method:
    """The best estimator for the input: ``vector`` with a field vector, else ``ml``."""
    return "vector" if s.field_ut is not None else "ml"


def calibrate(
    s: Samples,
    method: Method | None = None,
    *,
    noise_nt: float | None = None,
    robust: RobustLoss | None = None,
    filter_options: FilterOptions | None = None,
    times_s: Array | None = None,
) -> CalibrationResult:
    """Fit the measurement model to ``s`` and summarize.

    Args:
        s: the samples (field vector for a vector fit, magnitude for a scalar fit).
        method: estimator; ``None`` picks :func:`default_method`. Scalar methods on data with a field
            vector use only its magnitude (the DUT mounting is then not estimated).
        noise_nt: raw noise 1-sigma per axis (nT) for the chi-square test and the Cramer-Rao bound;
            ``None`` uses the residual estimate.
        robust: ``"huber"`` or ``"bisquare"`` IRLS (``ml`` and ``vector`` only).
        filter_options: variant, backend and start of the sequential filters (``centered-seq``,
            ``ekf``, ``ukf``); they need the raw noise, estimated from the data when not given.
        times_s: sample times (s), for the filters' process noise or forgetting.
    """
    method = method or default_method(s)
    if method not in METHODS:
        raise CalibrationError(f"unknown method {method!r}: use one of {', '.join(METHODS)}")
    if robust is not None and method not in ROBUST_METHODS:
        raise CalibrationError(
            f"--robust works with --method ml or vector, not {method}: drop --robust or change method"
        )
    if noise_nt is not None and not noise_nt > 0:
        raise CalibrationError(f"--noise-nt must be positive, got {noise_nt:g}")
    vector = method == "vector"
    if vector and s.field_ut is None:
        raise CalibrationError(
            "--method vector needs the field vector: give --field X,Y,Z instead of --field-magnitude"
        )
    n_params = (12 if vector else 9) + 3 * s.n_channels
    check_samples(s, n_params)
    data = s if vector else s.as_scalar()
    notes: tuple[str, ...] = ()
    if method in FILTER_METHODS:
        opts = FilterOptions(method=method) if filter_options is None else filter_options
        if opts.method != method:
            from dataclasses import replace

            opts = replace(opts, method=method)
        noise_ut = noise_nt / 1000.0 if noise_nt is not None else None
        if noise_ut is None:
            noise_ut = _batch_noise_ut(data)
            notes += (
                f"raw noise {1000 * noise_ut:.3g} nT estimated from a batch maximum-likelihood fit"
                " (give --noise-nt to set it)",
            )
        est, _ = run_filter(data, opts, noise_ut, times_s=times_s)
        return summarize(est, data, noise_nt, notes)
    est = _run(method, data, noise_nt, robust)
    if not vector and s.field_ut is not None:
        notes = ("field vector given but a scalar method chosen: only |h| was used",)
    return summarize(est, data, noise_nt, notes)


def _batch_noise_ut(s: Samples) -> float:
    """Raw noise 1-sigma (uT) from the residuals of a scalar ML fit (any sample order)."""
    est = ml_fit(s)
    r = scalar_residuals_only(est.p, s) / scalar_noise_gain(est.p, s)
    return float(np.sqrt(np.sum(r**2) / max(s.n - est.p.size, 1)))


def _run(method: Method, s: Samples, noise_nt: float | None, robust: RobustLoss | None) -> Estimate:
    if method == "vector":
        return _robust_vector(s, robust) if robust else vector_fit(s)
    if method == "ml":
        return ml_fit(s, robust=robust)
    if method == "twostep":
        return twostep_fit(s, None if noise_nt is None else noise_nt / 1000.0)
    if method == "centered":
        return centered_fit(s)
    return ellipsoid_fit(s)


def _robust_vector(s: Samples, loss: RobustLoss) -> Estimate:
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
