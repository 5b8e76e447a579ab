"""What every estimator returns, and the delta method that maps covariances between coordinates."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import numeric_jacobian
from rig.errors import CalibrationError


@dataclass(frozen=True)
class FilterHistory:
    """A sequential filter's path: recorded sample indices with the state ``theta`` (R, n) and its
    covariance (R, n, n), the NIS of every update (N,, NaN before the first estimate), and the
    final state and covariance."""

    index: Array
    theta: Array
    covariance: Array
    nis: Array
    final_theta: Array
    final_covariance: Array


@dataclass(frozen=True)
class Estimate:
    """Parameters ``p`` (see :func:`rig.calibration.residuals.parameter_names`) with covariance.

    ``rotation_ref`` is set for a vector estimate (the mounting rotation the ``rot_*`` error angles
    refer to) and ``None`` for a scalar one. ``sample_weights`` are robust weights, if any.
    """

    method: str
    p: Array
    covariance: Array
    rotation_ref: Array | None = None
    sample_weights: Array | None = None
    iterations: int = 0
    notes: tuple[str, ...] = field(default=())
    history: FilterHistory | None = None


def delta_method(
    to_p: Callable[[Array], Array], theta: Array, cov_theta: Array, what: str
) -> tuple[Array, Array]:
    """Map an estimate and its covariance through a closed-form map (Jacobian by differences)."""
    try:
        p = to_p(theta)
        g = numeric_jacobian(to_p, theta)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise CalibrationError(
            f"the {what} estimate is not a valid ellipsoid (its metric is not positive definite):"
            " cover more field directions, or use --method ml"
        ) from exc
    return p, g @ cov_theta @ g.T
