"""Robust reweighting (iteratively reweighted least squares) against outliers."""

from __future__ import annotations

from typing import Literal

import numpy as np

from rig.calibration.params import Array

RobustLoss = Literal["huber", "bisquare"]

HUBER_C = 1.345
"""Huber tuning constant: 95 % efficiency under Gaussian noise."""
BISQUARE_C = 4.685
"""Tukey bisquare tuning constant: 95 % efficiency under Gaussian noise."""


def robust_scale(residuals: Array) -> float:
    """Normalized median absolute deviation (a consistent estimate of sigma for Gaussian noise)."""
    med = float(np.median(residuals))
    return max(1.4826 * float(np.median(np.abs(residuals - med))), 1e-12)


def robust_weights(residuals: Array, loss: RobustLoss, scale: float | None = None) -> Array:
    """IRLS weights in [0, 1] for residuals; ``scale`` defaults to :func:`robust_scale`."""
    s = robust_scale(residuals) if scale is None else scale
    z = np.abs(residuals) / s
    if loss == "huber":
        return np.asarray(np.where(z <= HUBER_C, 1.0, HUBER_C / np.maximum(z, 1e-300)))
    if loss == "bisquare":
        return np.asarray(np.where(z < BISQUARE_C, (1.0 - (z / BISQUARE_C) ** 2) ** 2, 0.0))
    raise ValueError(f"unknown robust loss {loss!r}: use 'huber' or 'bisquare'")
