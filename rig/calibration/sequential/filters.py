"""Sequential (real-time) calibration filters on the z model: the in-house numpy backend.

Crassidis, Lai and Harman: sequential centered least squares (eqs. 19-22), the extended Kalman
filter (eqs. 23-27) and the Unscented filter (eqs. 28-47, the 9-state form with the state-dependent
measurement variance and the augmented form with the raw noise in the state), every one extended
with current-to-bias states (:mod:`rig.calibration.sequential.zmodel`). The parameters are
constant, so there is no propagation step; optional process noise (a random walk per state) lets
slowly varying parameters be tracked.

The EKF has two modes. ``order=1`` is the paper's filter, which from a zero start with large bias
errors drops the ``E[c^T (I+E)^-1 c] = c^T (I+E)^-1 c + tr(...P...)`` part of the predicted
measurement, becomes overconfident and stalls short of the truth. ``order=2`` (default) is the
Gaussian second-order filter (Gelb 1974, the paper's ref. 12): it adds ``1/2 tr(H2 P)`` to the
prediction and ``1/2 tr(H2 P H2 P)`` to the innovation variance, with the analytic Hessian ``H2``
of the model. For this model that is what the Unscented transform captures, and the EKF then
converges from the zero start too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import sym_from_e
from rig.calibration.sequential.zmodel import M_FROM_E, ZModel, ZSample, bias_energy, symmetric_root


@dataclass(frozen=True)
class UpdateInfo:
    """One update: innovation (uT^2), its predicted variance (uT^4) and ``NIS = nu^2 / var``."""

    innovation: float
    innovation_var: float

    @property
    def nis(self) -> float:
        """Normalized innovation squared (chi-square with 1 dof when the filter is consistent)."""
        return self.innovation**2 / self.innovation_var


def initial_covariance(
    n_channels: int,
    bias_sigma_ut: float = 20.0,
    e_sigma: float = 0.0316,
    k_sigma_ut_per_unit: float = 2.0,
) -> Array:
    """Diagonal start covariance in the state ``[c0, E, c_j]``.

    The defaults span a bench DUT (offsets to 60 uT and scale errors to 10 % at 3 sigma); the
    paper's eq. 48 is ``bias_sigma_ut = sqrt(5)`` (500 mG^2), ``e_sigma = sqrt(0.001)``.
    """
    diag = [bias_sigma_ut**2] * 3 + [e_sigma**2] * 6 + [k_sigma_ut_per_unit**2] * (3 * n_channels)
    return np.diag(np.asarray(diag, dtype=float))


@dataclass
class FilterBase:
    """State ``x`` and covariance ``P`` of ``theta``, process noise per second (variance rate)."""

    model: ZModel
    x: Array
    P: Array
    process_noise: Array | None = None
    updates: int = 0
    nis_sum: float = 0.0
    ready: bool = field(default=True)

    def _propagate(self, dt_s: float) -> None:
        if self.process_noise is not None and dt_s > 0:
            self.P[np.diag_indices_from(self.P)] += self.process_noise * dt_s

    def _finish(self, nu: float, pvv: float) -> UpdateInfo:
        info = UpdateInfo(nu, pvv)
        self.updates += 1
        self.nis_sum += info.nis
        return info

    @property
    def mean_nis(self) -> float:
        """Average NIS over all updates (1 for a consistent filter)."""
        return self.nis_sum / self.updates if self.updates else math.nan

    def reset(self, x: Array, P: Array) -> None:
        """Restart from state ``x`` and covariance ``P`` (a re-initialization)."""
        self.x, self.P = np.array(x, float), np.array(P, float)

    def final(self) -> tuple[Array, Array, str | None]:
        """The running estimate as it is: the paper's filters report their own state."""
        return self.x, self.P, None


class ExtendedKalman(FilterBase):
    """EKF on the z model (eqs. 25-27); ``order=2`` adds the Gaussian second-order terms."""

    def __init__(
        self,
        model: ZModel,
        x0: Array,
        P0: Array,
        *,
        order: Literal[1, 2] = 2,
        process_noise: Array | None = None,
    ) -> None:
        super().__init__(model, np.array(x0, float), np.array(P0, float), process_noise)
        self.order = order

    def update(self, s: ZSample, dt_s: float = 0.0) -> UpdateInfo:
        """Fold in one sample; returns the innovation statistics."""
        self._propagate(dt_s)
        m, x, P = self.model, self.x, self.P
        zhat = m.predict(x, s)
        h = m.gradient(x, s)
        ph = P @ h
        pvv = float(h @ ph) + m.variance(x, s)
        if self.order == 2:
            h2p = m.hessian(x, s) @ P
            zhat += 0.5 * float(np.trace(h2p))
            pvv += 0.5 * float(np.sum(h2p * h2p.T))
        nu = s.z - zhat
        k = ph / pvv
        self.x = x + k * nu
        self.P = P - pvv * np.outer(k, k)
        return self._finish(nu, pvv)


class UnscentedKalman(FilterBase):
    """Unscented filter (eqs. 33-47). ``augmented`` appends the raw noise (12-state form, eq. 47).

    ``alpha``, ``beta`` and ``kappa = 3 - L`` as in the paper. The update costs one Cholesky
    factorization and one stacked 3x3 solve over the ``2L + 1`` sigma points.
    """

    def __init__(
        self,
        model: ZModel,
        x0: Array,
        P0: Array,
        *,
        augmented: bool = False,
        alpha: float = 0.1,
        beta: float = 2.0,
        kappa: float | None = None,
        process_noise: Array | None = None,
    ) -> None:
        super().__init__(model, np.array(x0, float), np.array(P0, float), process_noise)
        n = model.n
        self.augmented = augmented
        big_l = n + (3 if augmented else 0)
        kappa = 3.0 - big_l if kappa is None else kappa
        lam = alpha**2 * (big_l + kappa) - big_l
        self.gamma = math.sqrt(big_l + lam)
        self.w_mean0 = lam / (big_l + lam)
        self.w_cov0 = self.w_mean0 + 1.0 - alpha**2 + beta
        self.w_i = 1.0 / (2.0 * (big_l + lam))
        self._points = np.empty((2 * n + 1, n))
        self._eye = np.eye(3)

    def update(self, s: ZSample, dt_s: float = 0.0) -> UpdateInfo:
        """Fold in one sample; returns the innovation statistics."""
        self._propagate(dt_s)
        m, x = self.model, self.x
        n = m.n
        root = np.linalg.cholesky(self.P)
        root *= self.gamma
        pts = self._points
        pts[0] = x
        np.add(x, root.T, out=pts[1 : n + 1])
        np.subtract(x, root.T, out=pts[n + 1 :])
        # z model on every sigma point: L theta - c^T (I + E)^-1 c (+ noise mean)
        c = pts[:, 0:3]
        if m.n_channels:
            c = c + np.einsum("pjk,j->pk", pts[:, 9:].reshape(-1, m.n_channels, 3), s.telemetry)
        met = pts[:, 3:9][:, M_FROM_E].reshape(-1, 3, 3)
        met += self._eye
        y = np.linalg.solve(met, c[:, :, None])
        q = np.einsum("pk,pk->p", c, y[:, :, 0])
        zeta = pts @ s.design
        zeta -= q
        w_i = self.w_i
        if self.augmented:
            zeta = np.concatenate([zeta, self._noise_points(x, s, float(zeta[0]))])
        zhat = self.w_mean0 * zeta[0] + w_i * float(zeta[1:].sum())
        dz = zeta - zhat
        pzz = self.w_cov0 * float(dz[0]) ** 2 + w_i * float(dz[1:] @ dz[1:])
        pxz = root @ (w_i * (dz[1 : n + 1] - dz[n + 1 : 2 * n + 1]))
        if self.augmented:
            pvv = pzz  # eq. 45: the noise is inside the sigma points
        else:
            pvv = pzz + self._variance(s, float(zeta[0]), met[0], c[0])
            zhat += m.mean_noise
        nu = s.z - zhat
        k = pxz / pvv
        self.x = x + k * nu
        self.P -= pvv * np.outer(k, k)
        return self._finish(nu, pvv)

    def _variance(self, s: ZSample, zeta0: float, met: Array, c: Array) -> float:
        """Eq. 5b at the estimate (see :meth:`ZModel.variance`), from the centre sigma point."""
        m = self.model
        if m.noise_frame == "corrected":
            g2 = max(s.measured_sq - zeta0, 0.0)
            return 4.0 * m.noise_var * g2 + m.noise_floor_var
        v = met @ s.measured_ut - c
        return float(4.0 * m.noise_var * (v @ v) + 2.0 * m.noise_var**2 * np.sum(met * met))

    def _noise_points(self, x: Array, s: ZSample, zeta0: float) -> Array:
        """The six noise sigma points of the augmented filter (eq. 47), state at its mean.

        With the raw noise ``e`` in the state, ``z = L theta - q + 2 g^T e - |e|^2`` with ``g = (I +
        D)(m - o(u))``; the state points carry ``e = 0``, the noise points ``theta = x`` and ``e =
        +-gamma s e_k``.
        """
        _, y = bias_energy(x, s.telemetry)
        sd = self.gamma * self.model.noise_ut
        if self.model.noise_frame == "corrected":
            g = symmetric_root(x) @ (s.measured_ut - y)
            quad = np.ones(3)
        else:  # raw noise n: z gains 2 (M (m - o))^T n + n^T M n
            met = np.eye(3) + sym_from_e(x[3:9])
            g = met @ (s.measured_ut - y)
            quad = -np.diag(met)
        return np.concatenate(
            [zeta0 + 2.0 * sd * g - sd**2 * quad, zeta0 - 2.0 * sd * g - sd**2 * quad]
        )
