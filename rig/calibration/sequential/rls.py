"""``rls``: recursive least squares with a forgetting factor on the linear energy model.

Every observation of the z model is linear in ``psi = [theta, phi]`` (theta the calibration, phi
the bias-energy coefficients, :mod:`.energy_filter`): ``z - mu = a psi + v``. This estimator
carries the estimate of ``psi`` and its covariance and folds in each sample with the classical
covariance-form update (gain, no matrix inverse: O(n^2) per sample), weighted by the observation
variance at the reference ``|h|`` (ADR 0014), started from the options' zero-start prior on theta
(diffuse on phi). Being linear it cannot diverge and is ready from the first sample; with
``forgetting_time_s`` (FilterOptions) each sample fades the past by the forgetting factor
``lambda = exp(-dt / tau)`` (the covariance grows by ``1 / lambda`` before the update), so slowly
varying parameters are tracked. Unlike the energy EKF and UKF it does not impose ``phi =
phi(theta)``: like the centered estimator it treats phi as free, and its covariance is that of the
linear estimate (exact for constant parameters and Gaussian noise).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from rig.calibration.sequential.kind import (
    FilterOptions,
    SequentialFilter,
    SequentialKind,
    numpy_only,
)

if TYPE_CHECKING:
    from rig.calibration.params import Array
    from rig.calibration.sequential.filters import UpdateInfo
    from rig.calibration.sequential.zmodel import ZModel, ZSample

ENERGY_SIGMA_UT2 = 1e4
"""Prior 1-sigma of the bias-energy coefficients (uT^2): diffuse (a 100 uT offset is 1e4 uT^2)."""


class RecursiveLeastSquares:
    """Exponentially weighted recursive least squares on ``psi = [theta, phi]``."""

    def __init__(self, model: ZModel, p0: Array, *, forgetting_time_s: float | None = None) -> None:
        import numpy as np

        from rig.calibration.sequential.energy_filter import energy_pairs

        self.model = model
        self.forgetting_time_s = forgetting_time_s
        m = len(energy_pairs(model.n_channels))
        self.psi = np.zeros(model.n + m)
        self.cov = np.zeros((model.n + m, model.n + m))
        self.cov[: model.n, : model.n] = p0
        self.cov[model.n :, model.n :] = ENERGY_SIGMA_UT2**2 * np.eye(m)
        self.ready = True
        self.updates = 0
        self.nis_sum = 0.0

    @property
    def x(self) -> Array:
        """The calibration estimate ``theta``."""
        return self.psi[: self.model.n]

    @property
    def P(self) -> Array:  # noqa: N802 - the covariance is P in every filter
        """Covariance of ``theta``."""
        return self.cov[: self.model.n, : self.model.n]

    @property
    def mean_nis(self) -> float:
        """Average normalized innovation squared (1 when consistent)."""
        return self.nis_sum / self.updates if self.updates else math.nan

    def final(self) -> tuple[Array, Array, str | None]:
        """The running estimate as it is (linear: the start only adds its diffuse prior)."""
        return self.x, self.P, None

    def reset(self, x: Array, P: Array) -> None:
        """Restart theta at ``x`` with covariance ``P`` (phi kept, uncorrelated with it)."""
        n = self.model.n
        self.psi[:n] = x
        self.cov[:n, :] = 0.0
        self.cov[:, :n] = 0.0
        self.cov[:n, :n] = P

    def update(self, s: ZSample, dt_s: float = 0.0) -> UpdateInfo:
        """Fold in one sample (``dt_s`` after the previous one); its innovation statistics."""
        import numpy as np

        from rig.calibration.sequential.energy_filter import energy_terms
        from rig.calibration.sequential.filters import UpdateInfo

        if self.forgetting_time_s is not None and dt_s > 0:
            self.cov /= math.exp(-dt_s / self.forgetting_time_s)  # the forgetting factor
        a = np.concatenate([s.design, -energy_terms(s.telemetry)])
        pa = self.cov @ a
        var = float(a @ pa) + self.model.reference_variance(s)
        nu = s.z - self.model.mean_noise - float(a @ self.psi)
        gain = pa / var
        self.psi += gain * nu
        self.cov -= np.outer(gain, pa)
        self.cov = 0.5 * (self.cov + self.cov.T)
        info = UpdateInfo(nu, var)
        self.updates += 1
        self.nis_sum += info.nis
        return info


def _build(opts: FilterOptions, model: ZModel, p0: Array) -> SequentialFilter:
    numpy_only(opts, "rls")
    return RecursiveLeastSquares(model, p0, forgetting_time_s=opts.forgetting_time_s)


KIND = SequentialKind(
    "rls",
    "recursive least squares (covariance form, O(n^2) per sample) on the linear energy model from"
    " the zero start's prior; forgets with a forgetting time",
    _build,
    guarded=False,
)
