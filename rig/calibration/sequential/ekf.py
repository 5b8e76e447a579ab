"""``ekf``: the energy-state filter with a Gauss-Newton projection (ADR 0009), or with
``--filter-variant paper`` the paper's EKF (eqs. 25-27), in-house or through filterpy."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rig.calibration.sequential.kind import (
    FilterOptions,
    SequentialFilter,
    SequentialKind,
    energy_form,
    process_noise,
)
from rig.errors import CalibrationError

if TYPE_CHECKING:
    from rig.calibration.params import Array
    from rig.calibration.sequential.zmodel import ZModel


def _build(opts: FilterOptions, model: ZModel, p0: Array) -> SequentialFilter:
    import numpy as np

    from rig.calibration.sequential.filters import ExtendedKalman

    if opts.variant == "energy":
        return energy_form(opts, model, p0, "jacobian")
    if opts.variant == "paper-augmented":
        raise CalibrationError(
            "paper-augmented is a UKF form: use --method ukf or --filter-variant paper"
        )
    x0, q = np.zeros(model.n), process_noise(opts, model)
    if opts.backend == "filterpy":
        from rig.calibration.sequential.filters_filterpy import FilterpyFilter

        return FilterpyFilter(model, x0, p0, "ekf", False, q)
    return ExtendedKalman(model, x0, p0, order=1, process_noise=q)


KIND = SequentialKind(
    "ekf",
    "energy-state filter with a Gauss-Newton projection (--filter-variant paper: the paper's EKF)",
    _build,
)
