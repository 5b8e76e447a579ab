"""``ukf``: the energy-state filter with a sigma-point projection (ADR 0009), or the paper's UKF
(``--filter-variant paper``: 9 states; ``paper-augmented``: 12 states, eq. 47), in-house or
through filterpy."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rig.calibration.sequential.kind import (
    FilterOptions,
    SequentialFilter,
    SequentialKind,
    energy_form,
    process_noise,
)

if TYPE_CHECKING:
    from rig.calibration.params import Array
    from rig.calibration.sequential.zmodel import ZModel


def _build(opts: FilterOptions, model: ZModel, p0: Array) -> SequentialFilter:
    import numpy as np

    from rig.calibration.sequential.filters import UnscentedKalman

    if opts.variant == "energy":
        return energy_form(opts, model, p0, "unscented")
    x0, q = np.zeros(model.n), process_noise(opts, model)
    augmented = opts.variant == "paper-augmented"
    if opts.backend == "filterpy":
        from rig.calibration.sequential.filters_filterpy import FilterpyFilter

        return FilterpyFilter(model, x0, p0, "ukf", augmented, q)
    return UnscentedKalman(model, x0, p0, augmented=augmented, process_noise=q)


KIND = SequentialKind(
    "ukf",
    "energy-state filter with a sigma-point projection (--filter-variant paper: the paper's"
    " 9-state UKF)",
    _build,
)
