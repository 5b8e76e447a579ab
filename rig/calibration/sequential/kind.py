"""The contract of a sequential estimator: how :func:`~.realtime.make_filter` builds its filter.

A sequential estimator is one module in this package with ``KIND = SequentialKind(...)`` and one
line in :data:`rig.calibration.sequential.KINDS`. The estimator table, ``rig calibrate --method``
and the ``live_calibrate`` step read that registry. This module, like every estimator module,
imports no numpy until a filter is built (the CLI builds its parser from the names).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol

from rig.errors import CalibrationError

if TYPE_CHECKING:
    from rig.calibration.params import Array
    from rig.calibration.sequential.filters import UpdateInfo
    from rig.calibration.sequential.zmodel import ZModel, ZSample

Variant = Literal["energy", "paper", "paper-augmented"]
Backend = Literal["numpy", "filterpy"]


class SequentialFilter(Protocol):
    """What the run loop and the live view need from a filter."""

    ready: bool

    @property
    def x(self) -> Array: ...

    @property
    def P(self) -> Array: ...  # noqa: N802 - the covariance is P in every filter

    @property
    def mean_nis(self) -> float: ...

    def update(self, s: ZSample, dt_s: float = 0.0) -> UpdateInfo | None: ...

    def reset(self, x: Array, P: Array) -> None: ...

    def final(self) -> tuple[Array, Array, str | None]:
        """The state and covariance to report once every sample is in, and a note saying how
        they differ from ``x`` and ``P`` (None: they are ``x`` and ``P``)."""
        ...


@dataclass(frozen=True)
class FilterOptions:
    """How to build a filter. Sigmas are the 1-sigma of the zero start (uT, 1, uT per unit).

    ``method`` is a name in :data:`rig.calibration.sequential.KINDS`. ``forgetting_time_s``
    (energy, centered and RLS forms) and ``process_noise`` (paper variants, variance per second for
    every state) let slowly varying parameters be tracked; both off by default.
    """

    method: str = "ukf"
    variant: Variant = "energy"
    backend: Backend = "numpy"
    bias_sigma_ut: float = 20.0
    e_sigma: float = 0.0316
    k_sigma_ut_per_unit: float = 2.0
    forgetting_time_s: float | None = None
    process_noise: float | None = None


Build = Callable[[FilterOptions, "ZModel", "Array"], SequentialFilter]
"""``build(options, model, P0)``: the filter for the z ``model`` started at zero with covariance
``P0`` (:func:`~.filters.initial_covariance` of the options' sigmas)."""


@dataclass(frozen=True)
class SequentialKind:
    """One sequential estimator.

    ``guarded``: its filter can diverge, so the run watches its innovations and checks its final
    answer against the batch fit (:mod:`.guard`); a linear estimator that is the batch answer at
    every step is not. ``needs`` says what the data must give for the calibration to be observable
    (shown when they did not).
    """

    name: str
    description: str
    build: Build
    guarded: bool = True
    needs: str = "cover more directions and magnitudes"


def numpy_only(opts: FilterOptions, name: str) -> None:
    """Refuse a variant or backend for an estimator that has one form on the numpy backend."""
    if opts.variant != "energy" or opts.backend != "numpy":
        raise CalibrationError(
            f"{name} has one form and runs on the numpy backend: drop --filter-variant and"
            " --backend"
        )


def energy_form(
    opts: FilterOptions, model: ZModel, p0: Array, projection: Literal["jacobian", "unscented"]
) -> SequentialFilter:
    """The energy-state filter (ADR 0009) with the given projection, on the numpy backend."""
    import numpy as np

    from rig.calibration.sequential.energy_filter import EnergyFilter

    if opts.backend != "numpy":
        raise CalibrationError(
            "the filterpy backend runs the paper's filters: add --filter-variant paper"
        )
    return EnergyFilter(
        model, np.zeros(model.n), p0, projection=projection,
        forgetting_time_s=opts.forgetting_time_s,
    )  # fmt: skip


def process_noise(opts: FilterOptions, model: ZModel) -> Array | None:
    """The paper variants' process noise: ``opts.process_noise`` (per second) on every state."""
    import numpy as np

    return None if opts.process_noise is None else np.full(model.n, opts.process_noise)
