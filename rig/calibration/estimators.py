"""The estimator table: every calibration method, once.

``rig calibrate --method`` (choices and help), the procedure language (``calibrate`` and
``live_calibrate`` steps) and :func:`rig.calibration.calibrate` read this table; adding an
batch estimator is one function and one row here, a sequential one a module and a line there.

* **batch** estimators see every sample at once (linear initializers, maximum likelihood, TWOSTEP);
* **sequential** estimators are filters that take the samples one by one, in order (Crassidis, Lai
  and Harman's sequential centered, EKF and UKF; see ADR 0009 for the energy-state forms). Each is
  a module registered in :data:`rig.calibration.sequential.KINDS` (ADR 0022); their rows follow.

Importing this module costs no numpy (the CLI builds its parser from it at start-up): each row's
``run`` imports its implementation when called.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from rig.calibration.sequential import KINDS
from rig.errors import CalibrationError

if TYPE_CHECKING:
    from rig.calibration.estimate import Estimate
    from rig.calibration.params import Array
    from rig.calibration.residuals import Samples
    from rig.calibration.robust import RobustLoss
    from rig.calibration.sequential.kind import FilterOptions

Kind = Literal["batch", "sequential"]
Model = Literal["scalar", "vector"]
BatchMethod = Literal["ml", "twostep", "centered", "ellipsoid", "vector"]
Method = str
"""A row's name: a :data:`BatchMethod` or a key of :data:`rig.calibration.sequential.KINDS`
(checked against the table at run time, :func:`estimator`)."""


@dataclass(frozen=True)
class FitRequest:
    """What an estimator is run with: the method name, the raw noise (uT, 1-sigma per axis; always
    set for a sequential one), the robust loss (only where ``Estimator.robust``), the filter options
    and sample times (sequential ones)."""

    method: Method
    noise_ut: float | None = None
    robust: RobustLoss | None = None
    filter_options: FilterOptions | None = None
    times_s: Array | None = None
    start: Estimate | None = None  # a scalar fit's linear start, when the caller has computed it


@dataclass(frozen=True)
class Estimator:
    """One row of the table.

    ``model`` is what it fits: ``vector`` needs the field vector and estimates the mounting;
    ``scalar`` uses only ``|h|`` (on data with a field vector, its magnitude).
    """

    name: Method
    kind: Kind
    model: Model
    description: str
    run: Callable[[Samples, FitRequest], Estimate]
    robust: bool = False  # takes a robust loss (--robust)


def _vector(s: Samples, r: FitRequest) -> Estimate:
    from rig.calibration.batch.linear import vector_fit
    from rig.calibration.batch.nonlinear import robust_vector_fit

    return vector_fit(s) if r.robust is None else robust_vector_fit(s, r.robust)


def _ml(s: Samples, r: FitRequest) -> Estimate:
    from rig.calibration.batch.nonlinear import ml_fit

    return ml_fit(s, start=None if r.start is None else r.start.p, robust=r.robust)


def _twostep(s: Samples, r: FitRequest) -> Estimate:
    from rig.calibration.batch.nonlinear import twostep_fit

    return twostep_fit(s, r.noise_ut, start=_reused(r, "centered"))


def _centered(s: Samples, r: FitRequest) -> Estimate:
    from rig.calibration.batch.linear import centered_fit

    return _reused(r, "centered") or centered_fit(s)


def _ellipsoid(s: Samples, r: FitRequest) -> Estimate:
    from rig.calibration.batch.linear import ellipsoid_fit

    return _reused(r, "ellipsoid") or ellipsoid_fit(s)


def _reused(r: FitRequest, method: str) -> Estimate | None:
    """The caller's linear start when it is this linear fit of the same samples."""
    return r.start if r.start is not None and r.start.method == method else None


def _filter(s: Samples, r: FitRequest) -> Estimate:
    """Any sequential method: the filter the options describe, run over the samples in order."""
    from dataclasses import replace

    from rig.calibration.sequential.realtime import FilterOptions, run_filter

    opts = r.filter_options or FilterOptions()
    if opts.method != r.method:
        opts = replace(opts, method=r.method)
    if r.noise_ut is None:
        raise CalibrationError(f"{r.method} needs the raw noise: give --noise-nt")
    est, _ = run_filter(s, opts, r.noise_ut, times_s=r.times_s)
    return est


_BATCH: tuple[Estimator, ...] = (
    Estimator("ml", "batch", "scalar", "maximum likelihood on |h| (analytic Jacobian), started"
              " from centered or, when |h| is constant, the ellipsoid", _ml, robust=True),
    Estimator("twostep", "batch", "scalar", "TWOSTEP (Alonso-Shuster): centered start, then"
              " Gauss-Newton on the full |h|^2 loss", _twostep),
    Estimator("centered", "batch", "scalar", "centered least squares (Crassidis eq. 18) with"
              " telemetry regressors; needs a varying |h|", _centered),
    Estimator("ellipsoid", "batch", "scalar", "algebraic ellipsoid fit (linear); works with a"
              " constant |h|", _ellipsoid),
    Estimator("vector", "batch", "vector", "cage linear least squares on the field vector: scale,"
              " misalignment, mounting rotation, offset, current-to-bias", _vector, robust=True),
)  # fmt: skip
"""The batch estimators (each row's name is a :data:`BatchMethod`; a test checks the type)."""

ESTIMATORS: tuple[Estimator, ...] = _BATCH + tuple(
    Estimator(k.name, "sequential", "scalar", k.description, _filter) for k in KINDS.values()
)
"""Every estimator, in the order the CLI lists them: the batch rows, then the registered
sequential ones."""

DEFAULT_METHOD: dict[Model, Method] = {"vector": "vector", "scalar": "ml"}
"""The estimator used when none is named, by what the data allow (field vector or magnitude)."""

_BY_NAME: dict[str, Estimator] = {e.name: e for e in ESTIMATORS}


def method_names(
    model: Model | None = None, kind: Kind | None = None, *, robust: bool | None = None
) -> tuple[Method, ...]:
    """Names of the estimators that fit ``model``, are of ``kind`` and take a robust loss (each
    filter ignored when ``None``), in table order."""
    return tuple(
        e.name
        for e in ESTIMATORS
        if (model is None or e.model == model)
        and (kind is None or e.kind == kind)
        and (robust is None or e.robust == robust)
    )


def estimator(name: str) -> Estimator:
    """The row of ``name``; an unknown name is a one-line error listing the known ones."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise CalibrationError(
            f"unknown method {name!r}: use one of {', '.join(_BY_NAME)}"
        ) from None


def spoken(names: tuple[str, ...], last: str = "or") -> str:
    """``a, b or c`` (for messages and help texts)."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} {last} {names[-1]}"
