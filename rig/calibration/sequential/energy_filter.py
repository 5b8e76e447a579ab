"""Energy-state filters: the bias energy ``|b(u)|^2`` as states of its own.

The z model ``z = L theta - c(u)^T (I+E)^-1 c(u)`` is nonlinear only through the bias energy, a
quadratic polynomial in the telemetry ``u`` whose coefficients ``phi`` are functions of ``theta``:

    |b(u)|^2 = phi_0 + sum_j u_j phi_j + sum_{i<=j} u_i u_j phi_ij,    phi = phi(theta)

With ``psi = [theta, phi]`` as the state, every observation is *linear*: ``z = a psi + v``, ``a =
[L, -1, -u_j, -u_i u_j]``. Its Kalman (information) update is exact, so nothing can diverge from a
poor start, and the data enter only through the information ``C = sum w a a^T`` and ``r = sum w a
z``, O(n^2) per sample. What the paper's filters linearize every sample is here imposed on the
*output* only: the reported estimate minimizes the exact cost ``psi(theta)^T C psi(theta) - 2 r^T
psi(theta)`` (the TWOSTEP loss plus the prior) over ``theta``, warm-started from the previous one:

* ``projection="jacobian"`` (our EKF): Gauss-Newton with the analytic Jacobian of ``phi``;
* ``projection="unscented"`` (our UKF): the same iteration with ``phi`` linearized statistically
  over sigma points of the current estimate's covariance (iterated posterior linearization).

With no prior the unconstrained solution is the batch centered estimate (centering = the free
``phi_0``): that is the sequential centered filter. See ``docs/adr/0009-energy-state-filters.md``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from rig.calibration.batch.linear import independent_from_gram
from rig.calibration.params import Array
from rig.calibration.sequential.filters import UpdateInfo
from rig.calibration.sequential.zmodel import E_UNITS, ZModel, ZSample, metric

Projection = Literal["jacobian", "unscented"]
MAX_PROJECTION_STEPS = 30
MAX_CONDITION = 1e9
"""Condition number (of the scaled information) below which the centered estimate is reported."""
METRIC_RANGE = (0.25, 4.0)
"""Allowed eigenvalues of ``I + E`` for a projected estimate."""
SMALL_STEP = 1.0
"""Gauss-Newton decrement (chi-square units) below which a step is taken without a line search."""


def energy_pairs(n_channels: int) -> list[tuple[int, int, float]]:
    """``(a, b, factor)`` per energy coefficient: ``phi = factor c_a^T (I+E)^-1 c_b``, c_0 = c0."""
    pairs = [(0, 0, 1.0)] + [(0, j + 1, 2.0) for j in range(n_channels)]
    for i in range(n_channels):
        for j in range(i, n_channels):
            pairs.append((i + 1, j + 1, 1.0 if i == j else 2.0))
    return pairs


def energy_terms(telemetry: Array) -> Array:
    """Multipliers of ``phi`` in ``|b(u)|^2``: ``[1, u_j, u_i u_j (i <= j)]``."""
    u = telemetry
    n_ch = u.size
    prods = [u[i] * u[j] for i in range(n_ch) for j in range(i, n_ch)]
    return np.concatenate([[1.0], u, np.asarray(prods, dtype=float)])


class EnergyModel:
    """``phi(theta)`` and its Jacobian for ``n_channels`` telemetry channels."""

    def __init__(self, n_channels: int) -> None:
        self.n_channels = n_channels
        self.pairs = energy_pairs(n_channels)
        self.m = len(self.pairs)
        self._ia = np.array([a for a, _, _ in self.pairs])
        self._ib = np.array([b for _, b, _ in self.pairs])
        self._factor = np.array([f for _, _, f in self.pairs])
        self.n = 9 + 3 * n_channels

    def c_columns(self, theta: Array) -> Array:
        """``[c0, c_1, ..., c_J]`` as columns (3, J+1)."""
        return np.column_stack([theta[0:3], theta[9:].reshape(-1, 3).T])

    def phi(self, theta: Array) -> Array:
        """Energy coefficients (uT^2 per telemetry unit power) for one state or a stack (P, n)."""
        cols = np.concatenate(
            [theta[..., None, 0:3], theta[..., 9:].reshape(*theta.shape[:-1], -1, 3)], axis=-2
        )  # (..., J+1, 3)
        y = np.linalg.solve(metric(theta), np.swapaxes(cols, -1, -2))  # (..., 3, J+1)
        gram = np.einsum("...ak,...kb->...ab", cols, y)
        return np.asarray(self._factor * gram[..., self._ia, self._ib])

    def phi_jacobian(self, theta: Array) -> tuple[Array, Array]:
        """``phi`` and ``d phi / d theta`` (m, n)."""
        cols = self.c_columns(theta)
        minv = np.linalg.inv(metric(theta))
        y = minv @ cols
        phi = np.empty(self.m)
        jac = np.zeros((self.m, self.n))
        for row, (a, b, f) in enumerate(self.pairs):
            phi[row] = f * cols[:, a] @ y[:, b]
            sl_a = slice(0, 3) if a == 0 else slice(9 + 3 * (a - 1), 12 + 3 * (a - 1))
            sl_b = slice(0, 3) if b == 0 else slice(9 + 3 * (b - 1), 12 + 3 * (b - 1))
            jac[row, sl_a] += f * y[:, b]
            jac[row, sl_b] += f * y[:, a]
            jac[row, 3:9] = -f * np.einsum("k,ikl,l->i", y[:, a], E_UNITS, y[:, b])
        return phi, jac


class EnergyFilter:
    """Information filter on ``psi = [theta, phi]`` with the estimate projected onto ``phi(theta)``.

    Args:
        model: the z model (telemetry channel count and raw noise).
        x0, P0: prior of ``theta`` (the paper's zero start and eq. 48, or :func:`initial_covariance`);
            ``None`` for no prior (the sequential centered estimator).
        projection: ``"jacobian"`` (EKF), ``"unscented"`` (UKF) or ``None`` (centered: no projection).
        forgetting_time_s: time constant (s) of exponential forgetting, for slowly varying
            parameters; ``None`` keeps everything (constant parameters).
        energy_sigma_ut2: prior 1-sigma of the energy coefficients (uT^2), effectively diffuse.
    """

    def __init__(
        self,
        model: ZModel,
        x0: Array | None = None,
        P0: Array | None = None,
        *,
        projection: Projection | None = "jacobian",
        forgetting_time_s: float | None = None,
        energy_sigma_ut2: float = 1e5,
        alpha: float = 0.1,
        beta: float = 2.0,
    ) -> None:
        self.model = model
        self.energy = EnergyModel(model.n_channels)
        n, m = model.n, self.energy.m
        self.size = n + m
        self.projection = projection
        self.forgetting_time_s = forgetting_time_s
        self.info = np.zeros((self.size, self.size))
        self.info_vec = np.zeros(self.size)
        self.has_prior = P0 is not None
        # the start's information on theta, faded with the data's: taken out by final()
        self.start_info: Array = np.zeros((n, n))
        self.start_vec: Array = np.zeros(n)
        if P0 is not None:
            x0 = np.zeros(n) if x0 is None else np.asarray(x0, float)
            self.start_info = np.asarray(np.linalg.inv(P0), float)
            self.start_vec = self.start_info @ x0
            self.info[:n, :n] = self.start_info
            self.info_vec[:n] = self.start_vec
            self.info[n:, n:] += np.eye(m) / energy_sigma_ut2**2
        self.x = np.zeros(n) if x0 is None else np.asarray(x0, float).copy()
        self.P = np.full((n, n), np.nan) if P0 is None else np.asarray(P0, float).copy()
        self.ready = P0 is not None
        self.updates = 0
        self.seen = 0
        self.nis_sum = 0.0
        self.last_iterations = 0
        big_l = n
        lam = alpha**2 * 3.0 - big_l  # kappa = 3 - L
        self._gamma = math.sqrt(big_l + lam)
        self._wm0 = lam / (big_l + lam)
        self._wc0 = self._wm0 + 1.0 - alpha**2 + beta
        self._wi = 1.0 / (2.0 * (big_l + lam))

    @property
    def mean_nis(self) -> float:
        """Average NIS over the updates made with an estimate in hand."""
        return self.nis_sum / self.updates if self.updates else math.nan

    def reset(self, x: Array, P: Array) -> None:
        """Restart the projection from ``x`` with covariance ``P`` (the information is kept: it
        is exact). The centered form has no projection and nothing to restart."""
        if self.projection is not None:
            self.x, self.P = np.array(x, float), np.array(P, float)
            self._project()

    def regressor(self, s: ZSample) -> Array:
        """``a`` with ``z - mu = a psi``."""
        return np.concatenate([s.design, -energy_terms(s.telemetry)])

    def update(self, s: ZSample, dt_s: float = 0.0) -> UpdateInfo | None:
        """Fold in one sample and refresh the estimate; innovation statistics once ready."""
        info: UpdateInfo | None = None
        if self.ready:
            h = self.model.gradient(self.x, s)
            nu = s.z - self.model.predict(self.x, s)
            pvv = float(h @ self.P @ h) + self.model.variance(self.x, s)
            info = UpdateInfo(nu, pvv)
            self.updates += 1
            self.nis_sum += info.nis
        if self.forgetting_time_s is not None and dt_s > 0:
            fade = math.exp(-dt_s / self.forgetting_time_s)
            self.info *= fade
            self.info_vec *= fade
            self.start_info = self.start_info * fade
            self.start_vec = self.start_vec * fade
        a = self.regressor(s)
        # eq. 5b with the reference |h| for the size of M (m - o): a weight from the noisy
        # reading would correlate with the noise and bias the estimate (ADR 0014)
        if self.ready and self.projection is not None:
            w = 1.0 / self.model.weight_variance(self.x, s)
        else:
            w = 1.0 / self.model.reference_variance(s)
        self.info += w * np.outer(a, a)
        self.info_vec += (w * (s.z - self.model.mean_noise)) * a
        if self.projection is not None:
            # bias-compensated: the design row holds the noisy reading, which correlates with
            # the observation's noise (ADR 0014); evaluated at the current estimate
            self.info_vec[: self.model.n] -= w * self.model.eiv_correlation(self.x, s)
        self.seen += 1
        if self.projection is None:
            self._solve_centered()
        elif self.ready:
            self._project()
        return info

    def final(self) -> tuple[Array, Array, str | None]:
        """The estimate from the data alone: the start's information on theta taken out and the
        projection repeated from the running estimate.

        The start (zero, :func:`~.filters.initial_covariance`) keeps the first samples' projection
        in a plausible region; once the data determine every parameter it only pulls the answer
        toward zero, by a bias its covariance does not cover (TRMM orbit, 200 draws: the scale
        factors 0.42 sigma, y0 0.30 sigma). Where the data alone do not determine theta (or
        the projection fails) the running estimate stands, and the note says so.
        """
        n = self.model.n
        if not self.has_prior or self.projection is None or not self.ready:
            return self.x, self.P, None
        kept = (self.info, self.info_vec, self.x, self.P, self.last_iterations)
        self.info = self.info.copy()
        self.info[:n, :n] -= self.start_info
        self.info_vec = self.info_vec.copy()
        self.info_vec[:n] -= self.start_vec
        try:
            running_p = self.P = self.P.copy()
            self.x = self.x.copy()
            self._project()
            if self.P is running_p:  # no projection step solved: no data-only covariance
                raise np.linalg.LinAlgError("singular")
            x, cov = self.x, 0.5 * (self.P + self.P.T)
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            x, cov = kept[2], np.full((n, n), np.nan)
        finally:
            self.info, self.info_vec, self.x, self.P, self.last_iterations = kept
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(cov))):
            return (
                self.x,
                self.P,
                (
                    "the data alone do not determine every parameter: the estimate keeps the"
                    " filter's zero start"
                ),
            )
        pull = float(np.max(np.abs(self.x - x) / np.sqrt(np.diag(cov))))
        return (
            x,
            cov,
            f"reported from the data alone (the zero start's pull, {pull:.2f} sigma at most, taken out)",
        )

    # --- sequential centered (no prior, no projection) ------------------------------------------

    def _solve_centered(self) -> None:
        """The unconstrained solution over the identifiable columns: energy terms that never vary
        (channels never on together) or repeat (a two-level channel's square) are left out."""
        n = self.model.n
        if not self.ready and (self.seen < 2 * self.size or self.seen % 8):
            return
        scale = np.sqrt(np.diag(self.info))
        if np.any(scale[:n] <= 0):
            return
        scale[scale <= 0] = 1.0
        normed = self.info / np.outer(scale, scale)
        keep = independent_from_gram(normed)
        if keep.size < n or np.any(keep[:n] != np.arange(n)):
            return
        sub = normed[np.ix_(keep, keep)]
        if not self.ready and np.linalg.cond(sub) > MAX_CONDITION:
            return
        try:
            chol = np.linalg.cholesky(sub)
        except np.linalg.LinAlgError:
            return
        cov = _chol_inverse(chol) / np.outer(scale[keep], scale[keep])
        psi = cov @ self.info_vec[keep]
        self.x, self.P = psi[:n], cov[:n, :n]
        self.ready = True

    # --- projection onto phi = phi(theta) ---------------------------------------------------------

    def _cost(self, theta: Array) -> float:
        psi = np.concatenate([theta, self.energy.phi(theta)])
        return float(psi @ self.info @ psi - 2.0 * self.info_vec @ psi)

    def _linearize(self, theta: Array) -> tuple[Array, Array, Array | None]:
        """``phi`` at ``theta`` (or its sigma-point mean), the slope used for the step and, for the
        statistical linearization, a root ``R`` of its error covariance (``R R^T = Omega``)."""
        if self.projection == "jacobian":
            phi, jac = self.energy.phi_jacobian(theta)
            return phi, jac, None
        n = self.model.n
        root = np.linalg.cholesky(self.P) * self._gamma
        pts = np.vstack([theta, theta + root.T, theta - root.T])
        phis = self.energy.phi(pts)
        w_m = np.full(2 * n + 1, self._wi)
        w_m[0] = self._wm0
        w_c = w_m.copy()
        w_c[0] = self._wc0  # the centre point has dx = 0: w_c0 only matters through phi_bar
        phi_bar = w_m @ phis
        dx = pts - theta
        cross = (w_c[:, None] * (phis - phi_bar)).T @ dx  # P_phi_theta
        slope = np.linalg.solve(self.P, cross.T).T  # the sigma points' own covariance is P
        dphi = phis - phi_bar
        omega = (w_c[:, None] * dphi).T @ dphi - slope @ cross.T
        vals, vecs = np.linalg.eigh(0.5 * (omega + omega.T))
        return phi_bar, slope, vecs * np.sqrt(np.clip(vals, 0.0, None))

    def _project(self) -> None:
        n = self.model.n
        theta = self.x.copy()
        cost = self._cost(theta)
        c_tt, c_tp, c_pp = self.info[:n, :n], self.info[:n, n:], self.info[n:, n:]
        r_t, r_p = self.info_vec[:n], self.info_vec[n:]
        iterations = 0
        for iterations in range(1, MAX_PROJECTION_STEPS + 1):  # noqa: B007 - reported below
            phi, slope, root = self._linearize(theta)
            # psi(theta + d) ~ [theta + d, phi + S d + R eps], eps ~ N(0, I) the linearization
            # error (none for the Jacobian); minimize the quadratic in (d, eps)
            resid_t = c_tt @ theta + c_tp @ phi - r_t
            resid_p = c_tp.T @ theta + c_pp @ phi - r_p
            grad = resid_t + slope.T @ resid_p
            hess = c_tt + c_tp @ slope + slope.T @ c_tp.T + slope.T @ c_pp @ slope
            try:
                if root is None:
                    step = -np.linalg.solve(hess, grad)
                    cov = _sym_inverse(hess)
                    decrement = float(-grad @ step)
                else:
                    side = (c_tp + slope.T @ c_pp) @ root
                    full = np.block(
                        [[hess, side], [side.T, root.T @ c_pp @ root + np.eye(len(phi))]]
                    )
                    full_grad = np.concatenate([grad, root.T @ resid_p])
                    full_step = -np.linalg.solve(full, full_grad)
                    step = full_step[:n]
                    cov = _sym_inverse(full)[:n, :n]
                    decrement = float(-full_grad @ full_step)
            except np.linalg.LinAlgError:
                break
            # decrement: twice the predicted cost reduction (chi-square units)
            if decrement < SMALL_STEP and _positive(theta + step):
                # well inside the quadratic region: take the Gauss-Newton step as it is
                theta = theta + step
                self.P = cov
                break
            accepted = False
            for _ in range(12):
                trial = theta + step
                try:
                    trial_cost = self._cost(trial) if _positive(trial) else math.inf
                except np.linalg.LinAlgError:
                    trial_cost = math.inf
                if trial_cost <= cost:
                    theta, cost, accepted = trial, trial_cost, True
                    break
                step *= 0.5
            self.P = cov
            if not accepted:
                break
        self.x = theta
        self.last_iterations = iterations


def _positive(theta: Array) -> bool:
    """``I + E`` a plausible sensor metric: eigenvalues within ``METRIC_RANGE`` (scale factors
    between 0.5 and 2). Keeps the projection out of the degenerate region (``I + E`` near
    singular) where a poorly informed early cost can drag it and from which it cannot return."""
    vals = np.linalg.eigvalsh(metric(theta))
    return bool(METRIC_RANGE[0] <= vals[0] and vals[-1] <= METRIC_RANGE[1])


def _chol_inverse(chol: Array) -> Array:
    inv_l = np.linalg.inv(chol)
    return np.asarray(inv_l.T @ inv_l)


def _sym_inverse(a: Array) -> Array:
    out = np.linalg.inv(a)
    return np.asarray(0.5 * (out + out.T))
