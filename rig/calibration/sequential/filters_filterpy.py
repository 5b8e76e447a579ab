"""The paper's EKF and UKF through filterpy (the project's reference backend).

Same model, start and tuning as :mod:`rig.calibration.sequential.filters`; the tests hold the two
backends to the same answer to numerical precision. filterpy predicts with ``fx = identity``
(constant parameters), which with ``Q = 0`` returns the state and covariance unchanged, as the
paper's eqs. 40-41 note. The augmented (12-state) UKF keeps the raw noise in the last three
states and resets them to zero mean and covariance ``Sigma`` before every update (eq. 47).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from rig.calibration.params import Array
from rig.calibration.sequential.filters import UpdateInfo
from rig.calibration.sequential.zmodel import ZModel, ZSample, bias_energy


class FilterpyFilter:
    """Adapter giving filterpy's filters the in-house interface (``update``, ``x``, ``P``)."""

    def __init__(
        self,
        model: ZModel,
        x0: Array,
        P0: Array,
        method: Literal["ekf", "ukf"],
        augmented: bool,
        process_noise: Array | None,
    ) -> None:
        from filterpy.kalman import (
            ExtendedKalmanFilter,
            MerweScaledSigmaPoints,
            UnscentedKalmanFilter,
        )

        self.model = model
        self.method = method
        self.augmented = augmented
        self.ready = True
        self.updates = 0
        self.nis_sum = 0.0
        self._q = process_noise
        n = model.n
        self._n = n
        self._kf: Any
        if method == "ekf":
            self._kf = ExtendedKalmanFilter(dim_x=n, dim_z=1)
            self._kf.x = np.array(x0, float).reshape(n, 1)
            self._kf.P = np.array(P0, float)
        else:
            dim = n + (3 if augmented else 0)
            points = MerweScaledSigmaPoints(dim, alpha=0.1, beta=2.0, kappa=3.0 - dim)
            self._kf = UnscentedKalmanFilter(
                dim_x=dim, dim_z=1, dt=1.0, hx=self._hx, fx=lambda x, dt: x, points=points
            )
            self._kf.x = np.zeros(dim)
            self._kf.x[:n] = x0
            self._kf.P = np.zeros((dim, dim))
            self._kf.P[:n, :n] = P0
            self._kf.Q = np.zeros((dim, dim))

    @property
    def x(self) -> Array:
        """State ``theta``."""
        return np.asarray(self._kf.x, float).reshape(-1)[: self._n]

    @property
    def P(self) -> Array:  # noqa: N802 - the covariance is P in every filter
        """Covariance of ``theta``."""
        return np.asarray(self._kf.P, float)[: self._n, : self._n]

    def final(self) -> tuple[Array, Array, str | None]:
        """The running estimate as it is: the paper's filters report their own state."""
        return self.x, self.P, None

    def reset(self, x: Array, P: Array) -> None:
        """Restart from state ``x`` and covariance ``P`` (a re-initialization)."""
        n = self._n
        if self.method == "ekf":
            self._kf.x = np.array(x, float).reshape(n, 1)
            self._kf.P = np.array(P, float)
            return
        self._kf.x[:n] = x
        self._kf.P[:n, :n] = P
        self._kf.P[:n, n:] = 0.0
        self._kf.P[n:, :n] = 0.0

    @property
    def mean_nis(self) -> float:
        """Average NIS over all updates."""
        return self.nis_sum / self.updates if self.updates else float("nan")

    def _hx(self, x: Array, s: ZSample) -> Array:
        theta = x[: self._n]
        q, _ = bias_energy(theta, s.telemetry)
        z = float(s.design @ theta - q)
        if self.augmented:
            z += self.model.noise_terms(theta, s, x[self._n :])
        return np.array([z])

    def update(self, s: ZSample, dt_s: float = 0.0) -> UpdateInfo:
        """Fold in one sample (filterpy predict + update)."""
        m, kf, n = self.model, self._kf, self._n
        if self._q is not None and dt_s > 0:
            kf.P[np.arange(n), np.arange(n)] += self._q * dt_s
        if self.method == "ekf":
            theta = kf.x.reshape(-1)
            r = m.variance(theta, s)
            zhat = m.predict(theta, s)
            kf.update(
                np.array([[s.z]]),
                HJacobian=lambda x: m.gradient(x.reshape(-1), s)[None, :],
                Hx=lambda x: np.array([[zhat]]),
                R=np.array([[r]]),
            )
            nu, pvv = float(kf.y.reshape(-1)[0]), float(kf.S.reshape(-1)[0])
        elif self.augmented:
            kf.x[n:] = 0.0
            kf.P[n:, :] = 0.0
            kf.P[:, n:] = 0.0
            kf.P[n:, n:] = m.noise_var * np.eye(3)
            kf.predict()
            kf.update(np.array([s.z]), R=np.zeros((1, 1)), s=s)
            nu, pvv = float(kf.y[0]), float(kf.S[0, 0])
        else:
            theta = kf.x.copy()
            kf.predict()
            kf.update(np.array([s.z - m.mean_noise]), R=m.variance(theta, s), s=s)
            nu, pvv = float(kf.y[0]), float(kf.S[0, 0])
        info = UpdateInfo(nu, pvv)
        self.updates += 1
        self.nis_sum += info.nis
        return info
