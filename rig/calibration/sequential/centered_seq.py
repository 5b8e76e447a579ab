"""``centered-seq``: Crassidis, Lai and Harman's sequential centered least squares (eqs. 19-22).

Linear: after every sample it is the batch ``centered`` estimate of the samples so far, so it
needs no divergence guard (and no prior: it is ready once the samples make it observable).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rig.calibration.sequential.kind import (
    FilterOptions,
    SequentialFilter,
    SequentialKind,
    numpy_only,
)

if TYPE_CHECKING:
    from rig.calibration.params import Array
    from rig.calibration.sequential.zmodel import ZModel


def _build(opts: FilterOptions, model: ZModel, p0: Array) -> SequentialFilter:
    from rig.calibration.sequential.energy_filter import EnergyFilter

    numpy_only(opts, "centered-seq")
    return EnergyFilter(model, projection=None, forgetting_time_s=opts.forgetting_time_s)


KIND = SequentialKind(
    "centered-seq",
    "sequential centered least squares (Crassidis eqs. 19-22); equals centered after the last"
    " sample",
    _build,
    guarded=False,
    needs="the field magnitude must vary for centered-seq",
)
