"""One sample of the attitude-independent z model, for the sequential filters.

Crassidis, Lai and Harman (eqs. 3-5, 26-27) extended with current-to-bias terms: the state is
``theta = [c0, E11, E22, E33, E12, E13, E23, c_1, ..., c_J]`` (uT, 1, uT per telemetry unit) and one
sample ``(m, |h|, u)`` gives the scalar observation

    z = |m|^2 - |h|^2 = L theta - c(u)^T (I + E)^-1 c(u) + v,   c(u) = c0 + sum_j u_j c_j

with ``L = [2 m^T, -S(m), 2 u_1 m^T, ...]`` and noise ``v`` of mean ``+tr(Sigma)`` and variance
``4 g^T Sigma g + 2 tr(Sigma^2)``, ``g = (I + D)(m - o(u))`` (eq. 5). The same model as the batch
z residuals in :mod:`rig.calibration.residuals`; this module adds the per-sample gradient, Hessian
and the measurement variance at an estimate, for isotropic raw noise ``Sigma = s^2 I``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import E_INDEX, eiv_correlation_rows, quadratic_features

M_FROM_E = np.array([0, 3, 4, 3, 1, 5, 4, 5, 2])
"""Flat 3x3 index -> position in ``[E11, E22, E33, E12, E13, E23]``."""
E_MULTIPLICITY = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
"""How often each E entry appears in the symmetric matrix (d/dE of a quadratic form)."""
E_UNITS = np.zeros((6, 3, 3))
"""``dM/dE_i`` for the six entries of E (unit symmetric matrices), shape (6, 3, 3)."""
for _i, (_a, _b) in enumerate(E_INDEX):
    E_UNITS[_i, _a, _b] = E_UNITS[_i, _b, _a] = 1.0


@dataclass(frozen=True)
class ZSample:
    """One observation: ``z`` (uT^2), its linear design row ``L``, the reading and telemetry."""

    z: float
    design: Array
    measured_ut: Array
    telemetry: Array
    field_magnitude_ut: float

    @property
    def measured_sq(self) -> float:
        """``|m|^2`` (uT^2)."""
        return float(self.measured_ut @ self.measured_ut)


def z_sample(measured_ut: Array, field_magnitude_ut: float, telemetry: Array) -> ZSample:
    """Build the observation for one reading ``m`` (uT), ``|h|`` (uT) and telemetry ``u``."""
    m = np.asarray(measured_ut, dtype=float).reshape(3)
    u = np.asarray(telemetry, dtype=float).reshape(-1)
    quad = quadratic_features(m[None, :])[0]
    parts = [2.0 * m, -quad] + [2.0 * uj * m for uj in u]
    z = float(m @ m - field_magnitude_ut**2)
    return ZSample(z, np.concatenate(parts), m, u, float(field_magnitude_ut))


def n_states(n_channels: int) -> int:
    """Length of ``theta`` for ``n_channels`` telemetry channels."""
    return 9 + 3 * n_channels


def bias_vector(theta: Array, telemetry: Array) -> Array:
    """``c(u) = c0 + sum_j u_j c_j`` (uT), for one state (n,) or a stack of states (P, n)."""
    c = theta[..., 0:3]
    n_ch = telemetry.size
    if n_ch:
        cj = theta[..., 9:].reshape(*theta.shape[:-1], n_ch, 3)
        c = c + np.einsum("...jk,j->...k", cj, telemetry)
    return np.asarray(c)


def metric(theta: Array) -> Array:
    """``I + E`` for one state (3, 3) or a stack (P, 3, 3)."""
    e = theta[..., 3:9][..., M_FROM_E].reshape(*theta.shape[:-1], 3, 3)
    return np.asarray(e + np.eye(3))


def bias_energy(theta: Array, telemetry: Array) -> tuple[Array, Array]:
    """``q = c^T (I + E)^-1 c`` (= ``|b(u)|^2``, uT^2) and ``y = (I + E)^-1 c``, stacked or not."""
    c = bias_vector(theta, telemetry)
    y = np.linalg.solve(metric(theta), c[..., None])[..., 0]
    return np.asarray(np.einsum("...k,...k->...", c, y)), np.asarray(y)


class ZModel:
    """The z model for ``n_channels`` telemetry channels and isotropic raw noise ``noise_ut``."""

    def __init__(
        self, n_channels: int, noise_ut: float, noise_frame: Literal["raw", "corrected"] = "raw"
    ) -> None:
        if not noise_ut > 0:
            raise ValueError(f"noise must be positive, got {noise_ut!r} uT")
        self.n_channels = n_channels
        self.n = n_states(n_channels)
        self.noise_ut = float(noise_ut)
        self.noise_var = self.noise_ut**2
        # +tr(Sigma): the paper's eq. 5a says -tr(Sigma), but the reading in L holds the noise
        # too (rig.calibration.residuals.z_noise_mean); first order in E for raw noise
        self.mean_noise = 3.0 * self.noise_var
        self.noise_floor_var = 6.0 * self.noise_var**2  # 2 tr(Sigma^2)
        self.noise_frame = noise_frame

    def predict(self, theta: Array, s: ZSample) -> float:
        """Expected ``z`` at ``theta`` (uT^2), noise mean included."""
        q, _ = bias_energy(theta, s.telemetry)
        return float(s.design @ theta - q + self.mean_noise)

    def gradient(self, theta: Array, s: ZSample) -> Array:
        """``dh/dtheta`` (eqs. 26-27 extended to the telemetry states)."""
        _, y = bias_energy(theta, s.telemetry)
        grad = s.design.copy()
        grad[0:3] -= 2.0 * y
        grad[3:9] += E_MULTIPLICITY * np.array([y[i] * y[j] for i, j in E_INDEX])
        for j, uj in enumerate(s.telemetry):
            grad[9 + 3 * j : 12 + 3 * j] -= 2.0 * uj * y
        return grad

    def hessian(self, theta: Array, s: ZSample) -> Array:
        """``d2h/dtheta2`` = ``-d2q/dtheta2`` (for the second-order filter), shape (n, n)."""
        n_ch = s.telemetry.size
        minv = np.linalg.inv(metric(theta))
        c = bias_vector(theta, s.telemetry)
        y = minv @ c
        # c = G theta_c with G = [I, u_1 I, ...]; the c-rows of the state are 0:3 and 9:.
        c_idx = np.r_[0:3, 9 : 9 + 3 * n_ch]
        g = np.hstack([np.eye(3)] + [uj * np.eye(3) for uj in s.telemetry])
        ay = E_UNITS @ y  # (6, 3): A_i y
        hq = np.zeros((self.n, self.n))
        hq[np.ix_(c_idx, c_idx)] = g.T @ (2.0 * minv) @ g
        hq[3:9, 3:9] = 2.0 * ay @ minv @ ay.T
        cross = -2.0 * (minv @ ay.T)  # (3, 6): d2q/dc dE_i
        hq[np.ix_(c_idx, np.arange(3, 9))] = g.T @ cross
        hq[np.ix_(np.arange(3, 9), c_idx)] = (g.T @ cross).T
        return -hq

    def variance(self, theta: Array, s: ZSample) -> float:
        """Measurement variance at ``theta`` (eq. 5b, uT^4).

        Noise on the corrected side (the paper's ``Sigma = s^2 I``): ``4 s^2 |g|^2 + 6 s^4`` with
        ``|g|^2 = |m|^2 - (L theta - q)``, clipped at zero. Raw noise on the reading (the rig's
        ``--noise-nt``), ``Sigma = s^2 M``: ``4 s^2 |M (m - o)|^2 + 2 s^4 tr(M^2)``.
        """
        q, y = bias_energy(theta, s.telemetry)
        if self.noise_frame == "corrected":
            g2 = max(s.measured_sq - float(s.design @ theta - q), 0.0)
            return 4.0 * self.noise_var * g2 + self.noise_floor_var
        met = metric(theta)
        v = met @ (s.measured_ut - y)
        return float(4.0 * self.noise_var * (v @ v) + 2.0 * self.noise_var**2 * np.sum(met * met))

    def noise_terms(self, theta: Array, s: ZSample, e: Array) -> float:
        """What a noise vector ``e`` (raw or corrected, per ``noise_frame``) adds to ``z``."""
        _, y = bias_energy(theta, s.telemetry)
        if self.noise_frame == "corrected":
            g = symmetric_root(theta) @ (s.measured_ut - y)
            return float(2.0 * g @ e - e @ e)
        met = metric(theta)
        return float(2.0 * (met @ (s.measured_ut - y)) @ e + e @ met @ e)

    def eiv_correlation(self, theta: Array, s: ZSample) -> Array:
        """``E[L^T (z - L theta + q - mu)]`` of one sample at ``theta`` (n,): what the noisy
        reading in the design row adds to the information vector on average (errors in
        variables, :func:`rig.calibration.residuals.z_eiv_correlation`); a filter subtracts it."""
        rows = eiv_correlation_rows(
            theta, s.measured_ut[None, :], s.telemetry[None, :], self.noise_ut, self.noise_frame
        )
        return np.asarray(rows[0], float)

    def weight_variance(self, theta: Array, s: ZSample) -> float:
        """Measurement variance (uT^4) for an information weight, with the reference ``|h|``
        where :meth:`variance` has the noisy reading: a weight that moves with the reading's
        noise correlates with the residual and biases the estimate (errors in variables).

        Raw noise: ``4 s^2 |h|^2 (v^T M^2 v) / (v^T M v) + 2 s^4 tr(M^2)``, ``v = m - o``: the
        size of ``M (m0 - o) = W^T h`` from ``|h|``, only its direction from the reading (its
        noise then enters through the sensor's anisotropy alone). Corrected-side noise: ``4 s^2
        |h|^2 + 6 s^4``, exact."""
        if self.noise_frame == "corrected":
            return self.reference_variance(s)
        _, y = bias_energy(theta, s.telemetry)
        met = metric(theta)
        v = s.measured_ut - y
        mv = met @ v
        ratio = float(mv @ mv) / max(float(v @ mv), 1e-12)
        return float(
            4.0 * self.noise_var * s.field_magnitude_ut**2 * ratio
            + 2.0 * self.noise_var**2 * np.sum(met * met)
        )

    def reference_variance(self, s: ZSample) -> float:
        """Measurement variance with ``|g|`` replaced by the reference ``|h|`` (state independent)."""
        return 4.0 * self.noise_var * s.field_magnitude_ut**2 + self.noise_floor_var


def symmetric_root(theta: Array) -> Array:
    """``I + D`` = the symmetric positive square root of ``I + E`` (eqs. 6-8)."""
    vals, vecs = np.linalg.eigh(metric(theta))
    return np.asarray((vecs * np.sqrt(np.clip(vals, 0.0, None))) @ vecs.T)
