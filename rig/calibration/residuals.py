"""Residuals and analytic Jacobians shared by every estimator.

Three residual families, each with its Jacobian (checked against finite differences in the tests):

* **scalar** (attitude independent): ``r_k = |W (m_k - o - K^T u_k)| - |h_k|`` in uT, parameters
  ``p = [a, b, c, x0, y0, z0, rho, phi, lambda, k_1, ..., k_J]`` (Springmann-Cutler, rad);
* **vector** (field vector known): ``r_k = m_k - L R h_k - o - K^T u_k`` (3 per sample, uT),
  parameters as scalar plus a small mounting-rotation error ``delta`` (rad, about the DUT axes)
  after the angles: ``R = exp([delta]x) R_ref``;
* **z-domain** (Alonso-Shuster / Crassidis): ``z_k = |m_k|^2 - |h_k|^2`` against
  ``2 m_k^T c(u_k) - S_k E - c(u_k)^T (I + E)^-1 c(u_k)``, parameters
  ``theta = [c0, E11, E22, E33, E12, E13, E23, c_1, ..., c_J]`` with ``c(u) = c0 + sum_j c_j u_j``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from rig.calibration.params import (
    SPRINGMANN_KEYS,
    Array,
    Calibration,
    lower_from_metric,
    rotation_from_vector,
    skew,
    springmann_matrix,
    springmann_matrix_derivatives,
    springmann_shape_from_matrix,
)
from rig.calibration.solver import NormalEquations

Holds = npt.NDArray[np.int64]
"""Per sample the number of the hold it was taken in."""
AXES = ("x", "y", "z")
ROTATION_KEYS = ("rot_x", "rot_y", "rot_z")


@dataclass(frozen=True)
class Samples:
    """Calibration input: raw readings (N, 3) uT, reference field, telemetry (N, J).

    ``field_ut`` is (N, 3) for a vector calibration; ``field_magnitude_ut`` (N,) is always set.
    ``holds`` (N,) numbers the hold each sample was taken in (one field and one set of load
    currents, settled), None when the field was not held (a tracked field) or not known.
    """

    measured_ut: Array
    field_magnitude_ut: Array
    telemetry: Array
    channels: tuple[str, ...] = ()
    field_ut: Array | None = None
    holds: Holds | None = None

    @cached_property
    def telemetry_by_channel(self) -> Array:
        """Telemetry as (J, N), each channel contiguous (for the Jacobian's column passes)."""
        return np.ascontiguousarray(self.telemetry.T)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.measured_ut.shape[0])

    @property
    def n_channels(self) -> int:
        """Number of telemetry channels."""
        return int(self.telemetry.shape[1])

    @staticmethod
    def build(
        measured_ut: Array,
        *,
        field_ut: Array | None = None,
        field_magnitude_ut: Array | None = None,
        telemetry: Array | None = None,
        channels: tuple[str, ...] = (),
        holds: npt.ArrayLike | None = None,
    ) -> Samples:
        """Assemble from arrays; exactly one of ``field_ut`` and ``field_magnitude_ut``."""
        m = np.asarray(measured_ut, dtype=float).reshape(-1, 3)
        if field_ut is not None:
            h = np.asarray(field_ut, dtype=float).reshape(-1, 3)
            mag = np.linalg.norm(h, axis=1)
        elif field_magnitude_ut is not None:
            h = None
            mag = np.asarray(field_magnitude_ut, dtype=float).reshape(-1)
        else:
            raise ValueError("give field_ut or field_magnitude_ut")
        u = np.zeros((m.shape[0], 0)) if telemetry is None else np.asarray(telemetry, float)
        u = u.reshape(m.shape[0], -1)
        if not channels:
            channels = tuple(f"u{j + 1}" for j in range(u.shape[1]))
        held = None if holds is None else np.asarray(holds, dtype=np.int64).reshape(-1)
        return Samples(m, mag, u, tuple(channels), h, held)

    def head(self, n: int) -> Samples:
        """The first ``n`` samples (scalar: the field vector is dropped)."""
        return Samples(self.measured_ut[:n], self.field_magnitude_ut[:n], self.telemetry[:n],
                       self.channels, None, None if self.holds is None else self.holds[:n])  # fmt: skip

    def take(self, keep: Array) -> Samples:
        """The samples where boolean mask ``keep`` (N,) is true (field vector kept if present)."""
        h = None if self.field_ut is None else self.field_ut[keep]
        held = None if self.holds is None else self.holds[keep]
        return Samples(self.measured_ut[keep], self.field_magnitude_ut[keep],
                       self.telemetry[keep], self.channels, h, held)  # fmt: skip

    def rows(self, rows: slice) -> Samples:
        """A range of consecutive samples, as views (field vector kept if present)."""
        h = None if self.field_ut is None else self.field_ut[rows]
        held = None if self.holds is None else self.holds[rows]
        return Samples(self.measured_ut[rows], self.field_magnitude_ut[rows],
                       self.telemetry[rows], self.channels, h, held)  # fmt: skip

    def as_scalar(self) -> Samples:
        """The same samples with the field vector dropped (only ``|h|`` kept)."""
        return Samples(self.measured_ut, self.field_magnitude_ut, self.telemetry, self.channels,
                       None, self.holds)  # fmt: skip


def parameter_names(channels: tuple[str, ...], *, vector: bool) -> tuple[str, ...]:
    """Names of the entries of the physical parameter vector ``p``."""
    names = list(SPRINGMANN_KEYS)
    if vector:
        names += list(ROTATION_KEYS)
    for ch in channels:
        names += [f"k[{ch}].{ax}" for ax in AXES]
    return tuple(names)


def k_start(vector: bool) -> int:
    """Index of the first current-to-bias coefficient in ``p``."""
    return 12 if vector else 9


def p_from_calibration(cal: Calibration, *, vector: bool) -> Array:
    """Physical parameter vector of a calibration (rotation error zero for vector)."""
    shape = springmann_shape_from_matrix(cal.sensor)
    parts = [shape[:3], cal.offset_ut, shape[3:]]
    if vector:
        parts.append(np.zeros(3))
    parts.append(cal.k_ut_per_unit.reshape(-1))
    return np.concatenate(parts)


def calibration_from_p(
    p: Array, channels: tuple[str, ...], *, rotation_ref: Array | None = None
) -> Calibration:
    """Inverse of :func:`p_from_calibration`; with ``rotation_ref`` the model is vector."""
    shape = np.concatenate([p[:3], p[6:9]])
    vector = rotation_ref is not None
    rot = np.eye(3)
    if rotation_ref is not None:
        rot = rotation_from_vector(p[9:12]) @ rotation_ref
    k = p[k_start(vector) :].reshape(-1, 3)
    return Calibration(springmann_matrix(shape), p[3:6].copy(), k, channels, rot)


def _shape(p: Array) -> Array:
    return np.concatenate([p[:3], p[6:9]])


CHUNK_ROWS = 32_768
"""Rows per block of the accumulating passes (normal equations, noise gains, linear starts): the
per-block work arrays are then a few MB whatever the number of samples, so memory grows with the
samples only through the data and a few per-sample vectors (docs/adr/0017)."""


def row_blocks(n: int, rows: int = CHUNK_ROWS) -> Iterator[slice]:
    """Consecutive row ranges of at most ``rows`` rows covering ``0..n``."""
    for start in range(0, n, rows):
        yield slice(start, min(start + rows, n))


def scalar_residuals(
    p: Array, s: Samples, sqrt_weights: Array | None = None
) -> tuple[Array, Array]:
    """Scalar residuals ``|W v_k| - |h_k|`` (uT) and their Jacobian (N, 9 + 3J) in ``p``.

    With ``sqrt_weights`` both come multiplied row by row (cheaper than weighting afterwards).
    The whole Jacobian is N x P: the fits use :func:`scalar_normal_equations` instead.
    """
    r, jac, _ = _scalar_block(p, s, _ScalarModel.at(p), sqrt_weights)
    return (r if sqrt_weights is None else r * sqrt_weights), jac


@dataclass(frozen=True)
class _ScalarModel:
    """What every block needs of ``p``: ``W``, ``dL/dshape``, offsets and ``K`` (J, 3)."""

    w: Array
    d_lower: Array
    offset: Array
    k: Array

    @staticmethod
    def at(p: Array) -> _ScalarModel:
        shape = _shape(p)
        w = np.asarray(np.linalg.inv(springmann_matrix(shape)), dtype=np.float64)
        return _ScalarModel(w, springmann_matrix_derivatives(shape), p[3:6], p[9:].reshape(-1, 3))

    def corrected(self, s: Samples) -> Array:
        """``g_k = W (m_k - o - K^T u_k)``, shape (N, 3)."""
        v = s.measured_ut - self.offset
        if self.k.size:
            v = v - s.telemetry @ self.k
        return np.asarray(v @ self.w.T)

    def magnitude_and_gain(self, s: Samples) -> tuple[Array, Array, Array, Array]:
        """``g``, ``|g|``, ``q = W^T n_hat`` (N, 3) and its norm, the noise gain."""
        g = self.corrected(s)
        ng = np.sqrt(np.einsum("ij,ij->i", g, g))
        q = (g / ng[:, None]) @ self.w
        return g, ng, q, np.sqrt(np.einsum("ij,ij->i", q, q))


def _scalar_block(
    p: Array, s: Samples, model: _ScalarModel, sqrt_weights: Array | None
) -> tuple[Array, Array, Array]:
    """Residuals (unweighted), Jacobian (column-major, rows times ``sqrt_weights``) and noise
    gains of the samples ``s`` (one block)."""
    g, ng, q, gain = model.magnitude_and_gain(s)
    r = ng - s.field_magnitude_ut
    # rows of q are W^T n_hat: every Jacobian column is linear in q
    if sqrt_weights is not None:
        q = q * sqrt_weights[:, None]
    # Column-major output and axis-major inputs: every column is one contiguous pass.
    jac = np.empty((s.n, p.size), order="F")
    qt, gt = np.ascontiguousarray(q.T), np.ascontiguousarray(g.T)
    ut = s.telemetry_by_channel
    d_lower = model.d_lower
    for i, col in enumerate((0, 1, 2, 6, 7, 8)):  # d|g|/dtheta = -(W^T n)^T (dL/dtheta) g
        nz = list(zip(*np.nonzero(d_lower[i]), strict=True))
        out = jac[:, col]
        np.multiply(qt[nz[0][0]], gt[nz[0][1]], out=out)
        out *= -d_lower[i, nz[0][0], nz[0][1]]
        for a_, b_ in nz[1:]:
            out -= d_lower[i, a_, b_] * qt[a_] * gt[b_]
    for ax in range(3):
        np.negative(qt[ax], out=jac[:, 3 + ax])
        for j in range(model.k.shape[0]):
            np.multiply(ut[j], jac[:, 3 + ax], out=jac[:, 9 + 3 * j + ax])
    return r, jac, gain


def scalar_normal_equations(
    p: Array,
    s: Samples,
    weights: Array | None = None,
    *,
    noise_weighted: bool = False,
    residuals_out: Array | None = None,
) -> NormalEquations:
    """The scalar problem's normal equations at ``p``, block by block (bounded memory).

    ``weights`` (N,) multiply the squared residuals; ``noise_weighted`` further divides each by
    the square of its own noise gain at ``p`` (the Fisher information at ``p``). The noise gains
    at ``p`` come back in ``gain``; ``residuals_out`` (N,), if given, receives the unweighted
    residuals (uT).
    """
    model = _ScalarModel.at(p)
    jtj = np.zeros((p.size, p.size))
    jtr = np.zeros(p.size)
    cost = 0.0
    gain = np.empty(s.n)
    for rows in row_blocks(s.n):
        block = s.rows(rows)
        sw = None if weights is None else np.sqrt(weights[rows])
        r, jac, gain[rows] = _scalar_block(p, block, model, sw)
        if residuals_out is not None:
            residuals_out[rows] = r
        if sw is not None:
            r = r * sw
        if noise_weighted:
            r = r / gain[rows]
            jac /= gain[rows][:, None]
        jtj += jac.T @ jac
        jtr += jac.T @ r
        cost += float(r @ r)
    return NormalEquations(jtj, jtr, cost, s.n, gain)


def scalar_jacobian_rows(p: Array, s: Samples) -> tuple[Array, Array, Array]:
    """Residuals (uT), Jacobian (N, P) and noise gains of the samples ``s`` at ``p``, unweighted,
    in memory: call it on a block of rows (:meth:`Samples.rows`)."""
    return _scalar_block(p, s, _ScalarModel.at(p), None)


def scalar_residuals_only(p: Array, s: Samples) -> Array:
    """The residuals of :func:`scalar_residuals` without the Jacobian (uT)."""
    return scalar_residuals_and_gain(p, s)[0]


def scalar_noise_gain(p: Array, s: Samples) -> Array:
    """``|W^T n_hat_k|``: how raw isotropic noise maps into the magnitude residual (per sample)."""
    return scalar_residuals_and_gain(p, s)[1]


def scalar_residuals_and_gain(p: Array, s: Samples) -> tuple[Array, Array]:
    """Scalar residuals (uT) and noise gains at ``p`` in one blockwise pass, (N,) each."""
    model = _ScalarModel.at(p)
    r, gain = np.empty(s.n), np.empty(s.n)
    for rows in row_blocks(s.n):
        block = s.rows(rows)
        _, ng, _, gain[rows] = model.magnitude_and_gain(block)
        r[rows] = ng - block.field_magnitude_ut
    return r, gain


def _vector_model(p: Array, s: Samples, rotation_ref: Array) -> tuple[Array, Array, Array]:
    """Residuals ``m - L R h - o - K^T u`` (N, 3) uT, the field in the DUT frame ``R h`` (N, 3)
    and the sensor matrix ``L``."""
    if s.field_ut is None:
        raise ValueError("vector residuals need the field vector")
    lower = springmann_matrix(_shape(p))
    rot = rotation_from_vector(p[9:12]) @ rotation_ref
    k = p[12:].reshape(-1, 3)
    hr = s.field_ut @ rot.T  # R h, field in the DUT frame
    pred = hr @ lower.T + p[3:6]
    if k.size:
        pred = pred + s.telemetry @ k
    return s.measured_ut - pred, hr, lower


def vector_residual_values(p: Array, s: Samples, rotation_ref: Array) -> Array:
    """Vector residuals ``m - L R h - o - K^T u`` flattened (3N,) uT, without the Jacobian."""
    return _vector_model(p, s, rotation_ref)[0].reshape(-1)


def vector_residuals(p: Array, s: Samples, rotation_ref: Array) -> tuple[Array, Array]:
    """Vector residuals ``m - L R h - o - K^T u`` flattened (3N,) uT and Jacobian (3N, 12 + 3J)."""
    r, hr, lower = _vector_model(p, s, rotation_ref)
    shape = _shape(p)
    k = p[12:].reshape(-1, 3)
    n = s.n
    jac = np.zeros((n, 3, p.size))
    d_lower = springmann_matrix_derivatives(shape)  # (6, 3, 3)
    d_shape = -np.tensordot(hr, d_lower, axes=([1], [2])).transpose(0, 2, 1)  # (N, 3, 6)
    jac[:, :, 0:3] = d_shape[:, :, 0:3]
    jac[:, :, 6:9] = d_shape[:, :, 3:6]
    jac[:, :, 3:6] = -np.eye(3)
    # d(exp([d]x) R h)/dd = -[R h]x at d = 0 (first order about the reference); residual sign flips.
    jac[:, :, 9:12] = lower @ _skew_rows(hr)
    for j in range(k.shape[0]):
        jac[:, :, 12 + 3 * j : 15 + 3 * j] = -s.telemetry[:, j, None, None] * np.eye(3)
    return r.reshape(-1), jac.reshape(3 * n, p.size)


def _skew_rows(v: Array) -> Array:
    """Stack of cross-product matrices, shape (N, 3, 3)."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


# --- z-domain (Crassidis / Alonso-Shuster) --------------------------------------------------------

E_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def sym_from_e(e6: Array) -> Array:
    """Symmetric 3x3 from ``[E11, E22, E33, E12, E13, E23]``."""
    e = np.zeros((3, 3))
    for value, (i, j) in zip(e6, E_INDEX, strict=True):
        e[i, j] = e[j, i] = value
    return e


def quadratic_features(m: Array) -> Array:
    """``S_k = [m1^2, m2^2, m3^2, 2 m1 m2, 2 m1 m3, 2 m2 m3]`` (Crassidis eq. 2c), shape (N, 6)."""
    return np.column_stack(
        [m[:, 0] ** 2, m[:, 1] ** 2, m[:, 2] ** 2,
         2 * m[:, 0] * m[:, 1], 2 * m[:, 0] * m[:, 2], 2 * m[:, 1] * m[:, 2]]
    )  # fmt: skip


def z_observation(s: Samples) -> Array:
    """Attitude-independent observation ``z_k = |m_k|^2 - |h_k|^2`` (uT^2, eq. 3a)."""
    return np.asarray(np.einsum("ij,ij->i", s.measured_ut, s.measured_ut) - s.field_magnitude_ut**2)


def z_linear_design(s: Samples) -> Array:
    """The linear part ``L_k`` of the z model: ``[2 m^T, -S_k, 2 u_j m^T ...]``, shape (N, 9 + 3J)."""
    cols = [2.0 * s.measured_ut, -quadratic_features(s.measured_ut)]
    for j in range(s.n_channels):
        cols.append(2.0 * s.telemetry[:, j : j + 1] * s.measured_ut)
    return np.hstack(cols)


def z_residuals(theta: Array, s: Samples, mu_ut2: float = 0.0) -> tuple[Array, Array]:
    """z-domain residuals divided by ``2 |h_k|`` (so roughly uT) and their Jacobian in ``theta``."""
    lin = z_linear_design(s)
    c0, e6 = theta[:3], theta[3:9]
    cj = theta[9:].reshape(-1, 3)
    c_u = np.broadcast_to(c0, (s.n, 3)) + (s.telemetry @ cj if cj.size else 0.0)
    y = np.linalg.solve(np.eye(3) + sym_from_e(e6), c_u.T).T  # (I + E)^-1 c(u_k)
    model = lin @ theta - np.einsum("ij,ij->i", c_u, y) + mu_ut2
    scale = 2.0 * s.field_magnitude_ut
    r = (z_observation(s) - model) / scale
    dmodel = lin.copy()
    dmodel[:, 0:3] -= 2.0 * y
    for idx, (i, j) in enumerate(E_INDEX):
        dmodel[:, 3 + idx] += (1.0 if i == j else 2.0) * y[:, i] * y[:, j]
    for j in range(cj.shape[0]):
        dmodel[:, 9 + 3 * j : 12 + 3 * j] -= 2.0 * s.telemetry[:, j : j + 1] * y
    return r, -dmodel / scale[:, None]


def p_from_theta(theta: Array) -> Array:
    """Scalar physical parameters ``p`` from z-domain ``theta`` (Crassidis eqs. 6-9 generalized).

    ``I + E = W^T W`` is the metric, ``o = (I + E)^-1 c0`` and ``k_j = (I + E)^-1 c_j``.
    Raises ``np.linalg.LinAlgError`` when ``I + E`` is not positive definite.
    """
    metric = np.eye(3) + sym_from_e(theta[3:9])
    lower = lower_from_metric(metric)
    shape = springmann_shape_from_matrix(lower)
    o = np.linalg.solve(metric, theta[:3])
    k = np.linalg.solve(metric, theta[9:].reshape(-1, 3).T).T
    return np.concatenate([shape[:3], o, shape[3:], k.reshape(-1)])


def theta_from_p(p: Array) -> Array:
    """Inverse of :func:`p_from_theta` (used to start TWOSTEP from any scalar estimate)."""
    lower = springmann_matrix(_shape(p))
    w = np.linalg.inv(lower)
    metric = w.T @ w
    e = metric - np.eye(3)
    e6 = np.array([e[i, j] for i, j in E_INDEX])
    c0 = metric @ p[3:6]
    cj = (metric @ p[9:].reshape(-1, 3).T).T
    return np.concatenate([c0, e6, cj.reshape(-1)])


def numeric_jacobian(fun: Callable[[Array], Array], x: Array, rel_step: float = 1e-6) -> Array:
    """Central-difference Jacobian of a smooth closed-form map (for covariance propagation only)."""
    f0 = np.asarray(fun(x))
    jac = np.empty((f0.size, x.size))
    for i in range(x.size):
        h = rel_step * max(1.0, abs(float(x[i])))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        jac[:, i] = (np.asarray(fun(xp)) - np.asarray(fun(xm))) / (2 * h)
    return jac


__all__ = [
    "Samples",
    "calibration_from_p",
    "numeric_jacobian",
    "p_from_calibration",
    "p_from_theta",
    "parameter_names",
    "scalar_residuals",
    "skew",
    "theta_from_p",
    "vector_residual_values",
    "vector_residuals",
    "z_residuals",
]


def z_noise_covariance(theta: Array, noise_ut: float, frame: str = "raw") -> Array:
    """Covariance (uT^2, 3x3) of the noise on the raw reading: ``s^2 I`` for raw noise, ``s^2 (I +
    E)^-1`` for isotropic noise on the corrected side (Crassidis eq. 1, ``n = (I + D)^-1 eps``)."""
    var = float(noise_ut) ** 2
    if frame == "corrected":
        return np.asarray(var * np.linalg.inv(np.eye(3) + sym_from_e(theta[3:9])), float)
    return var * np.eye(3)


def z_noise_mean(theta: Array, noise_ut: float, frame: str = "raw") -> float:
    """Mean (uT^2) of ``z - model`` at the truth: ``tr(M Sigma)`` with ``M = I + E`` and ``Sigma``
    the raw-noise covariance (3 s^2 for noise on the corrected side). The noise sits in the
    reading itself, so ``2 n^T M (m - o)`` has mean ``2 tr(M Sigma)``, not 0: the paper's eq. 5a,
    ``-tr(Sigma)``, treats the noisy reading as exact and has the sign wrong."""
    metric = np.eye(3) + sym_from_e(theta[3:9])
    return float(np.sum(metric * z_noise_covariance(theta, noise_ut, frame)))


def z_eiv_correlation(theta: Array, s: Samples, noise_ut: float, frame: str = "raw") -> Array:
    """``E[d model_k/d theta * (z_k - model_k)]`` at the truth, per sample (N, n), estimated from
    the noisy readings without bias (uT^2 per parameter unit times uT^2).

    The regressors of the z model hold the noisy reading (errors in variables), so they correlate
    with the residual: with ``m = m0 + n``, ``a = M (m0 - o(u))`` and ``r = 2 n^T a + n^T M n -
    tr(M Sigma)``, ``E[2 (m - o) r] = 4 Sigma a`` for ``c``, ``E[m_i m_j r] = 2 (m0_i (Sigma a)_j +
    m0_j (Sigma a)_i) + 2 (Sigma M Sigma)_ij`` for ``E`` (times the sign and multiplicity of its
    column) and ``u_j`` times the ``c`` term for ``c_j``. Gauss-Newton on the z residuals with
    these subtracted from its gradient (bias-compensated least squares) has no bias of order
    ``sigma^2`` that stays as N grows."""
    return eiv_correlation_rows(theta, s.measured_ut, s.telemetry, noise_ut, frame)


def eiv_correlation_rows(
    theta: Array, measured_ut: Array, telemetry: Array, noise_ut: float, frame: str = "raw"
) -> Array:
    """:func:`z_eiv_correlation` for readings (N, 3) uT and telemetry (N, J) as arrays (the
    sequential filters pass one row)."""
    metric = np.eye(3) + sym_from_e(theta[3:9])
    sigma = z_noise_covariance(theta, noise_ut, frame)
    c0, cj = theta[:3], theta[9:].reshape(-1, 3)
    n = measured_ut.shape[0]
    c_u = np.broadcast_to(c0, (n, 3)) + (telemetry @ cj if cj.size else 0.0)
    o_u = np.linalg.solve(metric, c_u.T).T
    m = measured_ut
    sa = (m - o_u) @ metric @ sigma  # rows: Sigma a_k (Sigma, M symmetric)
    sms = sigma @ metric @ sigma
    out = np.empty((n, 9 + cj.size))
    out[:, 0:3] = 4.0 * sa
    for idx, (i, j) in enumerate(E_INDEX):
        # E[m_i (Sigma a(m))_j] = m0_i (Sigma a)_j + (Sigma M Sigma)_ij: the plug-in's excess
        mm = 2.0 * (m[:, i] * sa[:, j] + m[:, j] * sa[:, i]) - 2.0 * sms[i, j]
        out[:, 3 + idx] = -(1.0 if i == j else 2.0) * mm
    for j in range(cj.shape[0]):
        out[:, 9 + 3 * j : 12 + 3 * j] = 4.0 * telemetry[:, j : j + 1] * sa
    return out
