"""The cross-field effect: how a field across a magnetometer's axis changes that axis's scale.

An axis ``i`` reads ``m_i = o + s h_i + k h_j + ... + s c h_i h_j``: besides its offset, its
scale and its misalignment towards ``j`` (linear in ``h_j``), a field ``h_j`` across it changes
its scale by ``c`` per uT (the cross-field coefficient, ppm/uT; AMR sensors show percents at
100 uT). With each axis swept at several levels while a field across it is held at -B, 0 and
+B, every sample is fitted at once by least squares per measured axis, on ``1``, the three
components, their squares and their products, and ``c`` is a product term over the linear one,
its sigma from the fit's covariance by the delta method. The axes are the sensor's when the field
and readings are given in them (a calibration's mounting rotation and correction); in the cage's
axes a mounting rotation of a few degrees mixes about that fraction of the other transverse
coefficient in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
MIN_SAMPLES = 12


@dataclass(frozen=True)
class CrossField:
    """Axis ``axis`` with a field along ``transverse``: the coefficient and its 1-sigma (ppm of
    scale per uT), from ``samples`` samples with a residual rms of ``residual_nt``."""

    axis: int
    transverse: int
    ppm_per_ut: float
    sigma_ppm_per_ut: float
    samples: int
    residual_nt: float


def fit_cross_field(field_ut: Array, reading_ut: Array, axis: int) -> tuple[CrossField, ...]:
    """Fit axis ``axis`` of the readings (uT) against the field (uT) in the same axes, every
    sample at once: ``1``, the three components, their squares and their three products; the
    coefficient towards each other axis ``j`` is the ``h_i h_j`` term over the ``h_i`` one."""
    h = np.asarray(field_ut, float)
    m = np.asarray(reading_ut, float)[:, axis]
    if len(m) < MIN_SAMPLES:
        raise ValueError(f"{len(m)} samples: a cross-field fit needs at least {MIN_SAMPLES}")
    others = [j for j in range(3) if j != axis]
    products = [(axis, others[0]), (axis, others[1]), (others[0], others[1])]
    design = np.column_stack([np.ones(len(m)), h, h**2, *(h[:, a] * h[:, b] for a, b in products)])
    coef, *_ = np.linalg.lstsq(design, m, rcond=None)
    resid = m - design @ coef
    dof = max(len(m) - design.shape[1], 1)
    cov = float(resid @ resid) / dof * np.linalg.pinv(design.T @ design)
    rms = 1000.0 * float(np.sqrt(np.mean(resid**2)))
    out = []
    for n, j in enumerate(others):
        lin, prod = 1 + axis, 7 + n
        s, p = coef[lin], coef[prod]
        grad = np.array([-p / s**2, 1.0 / s])  # d c / d (s, p)
        sigma = float(np.sqrt(grad @ cov[np.ix_([lin, prod], [lin, prod])] @ grad))
        out.append(CrossField(axis, j, 1e6 * float(p / s), 1e6 * sigma, len(m), rms))
    return tuple(out)
