"""A sequential filter that diverged is noticed, restarted from a batch estimate, or refused.

A filter on the nonlinear z model can settle in a wrong solution (a local minimum of the energy
projection, or the paper EKF stalling short of the truth from a zero start) while its own
covariance says all is well. Two statistics catch it, both in chi-square units of the raw noise:

* **while running**: the mean normalized innovation squared (NIS) over the last
  :data:`WINDOW` updates. A consistent filter gives 1 (+-0.1 over 200 updates); above
  :data:`NIS_LIMIT` the filter is re-initialized from the batch maximum-likelihood estimate of the
  samples seen so far (at most :data:`MAX_RECOVERIES` times, one window apart);
* **at the end**: the z-domain cost of the filter's estimate over every sample against that of the
  batch estimate of the same samples (scaled by the batch fit's reduced chi-square when above 1,
  so a misstated noise does not count). A converged filter is within a few chi-square units per
  parameter of it; more than :func:`excess_limit` means the answer is wrong, and it is refused
  (:class:`~rig.errors.CalibrationError`, exit 2), never reported.
"""

from __future__ import annotations

import contextlib
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from rig.calibration.batch.nonlinear import ml_fit
from rig.calibration.estimate import delta_method
from rig.calibration.params import Array
from rig.calibration.residuals import Samples, theta_from_p, z_residuals
from rig.errors import CalibrationError

WINDOW = 200
"""Updates per consistency window."""
NIS_LIMIT = 4.0
"""Windowed mean NIS above which a filter counts as diverged (a consistent one: 1 +- 0.1)."""
MAX_RECOVERIES = 3
"""Re-initializations from a batch estimate in one run, at most."""


def z_cost(theta: Array, s: Samples, noise_ut: float) -> float:
    """Chi-square of the z-domain residuals at ``theta`` (each ~ N(0, 1) under raw noise
    ``noise_ut`` uT): about ``s.n`` at a consistent estimate."""
    r, _ = z_residuals(theta, s, 3.0 * noise_ut**2)
    return float(np.sum((r / noise_ut) ** 2))


def excess_limit(n_theta: int) -> float:
    """Cost above the batch estimate's (chi-square units) that a converged filter stays under:
    the 1 - 1e-6 quantile of chi-square with ``n_theta`` degrees of freedom, doubled for the pull
    of the filter's prior."""
    from scipy.stats import chi2  # here: importing scipy.stats costs 0.25 s

    return 2.0 * float(chi2.isf(1e-6, n_theta))


def batch_theta(s: Samples) -> tuple[Array, Array]:
    """Batch maximum likelihood of ``s`` as z-model state and covariance."""
    est = ml_fit(s)
    theta = theta_from_p(est.p)
    _, cov = delta_method(theta_from_p, est.p, est.covariance, "batch")
    return theta, cov


@dataclass
class GuardReport:
    """What the guard saw: the sample indices where it re-initialized the filter, and the final
    cost excess over the batch estimate (chi-square units, NaN when not checked)."""

    recoveries: list[int] = field(default_factory=list)
    final_excess: float = float("nan")
    limit: float = float("nan")


class Resettable(Protocol):
    """A filter that can be restarted from a state and covariance."""

    def reset(self, x: Array, P: Array) -> None: ...


class DivergenceWatch:
    """Windowed NIS of one filter run; says when to re-initialize, and does it."""

    def __init__(self) -> None:
        self._nis: deque[float] = deque(maxlen=WINDOW)
        self._quiet_until = WINDOW
        self.report = GuardReport()

    def diverged(self, k: int, nis: float | None) -> bool:
        """Record the NIS of update ``k`` (None: no innovation yet); True when the window's mean
        says the filter has diverged and a re-initialization is allowed now."""
        if nis is None or not np.isfinite(nis):
            return False
        self._nis.append(nis)
        if k < self._quiet_until or len(self._nis) < WINDOW:
            return False
        if len(self.report.recoveries) >= MAX_RECOVERIES:
            return False
        return float(np.mean(self._nis)) > NIS_LIMIT

    def recovered(self, k: int) -> None:
        """The filter was re-initialized at update ``k``: judge it afresh a window later."""
        self.report.recoveries.append(k)
        self._nis.clear()
        self._quiet_until = k + WINDOW

    def reinitialize(self, f: Resettable, seen: Samples, k: int) -> None:
        """Restart ``f`` at update ``k`` from the batch estimate of the samples ``seen`` so far;
        without one (too few samples yet) it is judged again a window later all the same."""
        with contextlib.suppress(CalibrationError, np.linalg.LinAlgError):
            f.reset(*batch_theta(seen))
        self.recovered(k)


def check_final(
    theta: Array, s: Samples, noise_ut: float, method: str, report: GuardReport
) -> None:
    """Refuse a filter result that is far worse than the batch estimate of the same samples."""
    try:
        best, _ = batch_theta(s)
    except (CalibrationError, np.linalg.LinAlgError):
        return  # no batch reference for these data: the filter's own statistics stand
    n_theta = theta.size
    best_cost = z_cost(best, s, noise_ut)
    # in units of the noise the data show, so that a misstated --noise-nt moves nothing
    excess = (z_cost(theta, s, noise_ut) - best_cost) / max(1.0, best_cost / s.n)
    report.final_excess, report.limit = excess, excess_limit(n_theta)
    if excess > report.limit:
        again = f" after {len(report.recoveries)} re-initialization(s)" if report.recoveries else ""
        raise CalibrationError(
            f"the {method} filter diverged{again}: its estimate fits the data {excess:.0f}"
            f" chi-square units worse than the batch maximum-likelihood fit of the same samples"
            f" (a converged filter: under {report.limit:.0f}); no result is given. The batch fit"
            " (--method ml) converged on these data"
        )
