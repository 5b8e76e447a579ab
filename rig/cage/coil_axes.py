"""Coil constants and axis directions from a reference sensor turned on a fixture (vector method).

A reference magnetometer sits on a rotation fixture at the cage centre. In each fixture position
``k`` (nominally the rotation ``R_k`` of the sensor from its base position) every coil is driven
at ``+I`` and ``-I``; the half difference per ampere cancels the ambient field and the sensor's
offset::

    d_jk = (m(+I) - m(-I)) / (2 I) = T A_k^T K_j,    A_k = R_k exp([delta_k]x)

``K_j`` (uT/A) is coil j's field per ampere in the fixture's base frame (the cage frame), ``T =
L M`` the sensor (``L`` lower triangular: its scales and non-orthogonality, known from its
certificate within ``sigma``; ``M`` its rotation on the fixture, free) and ``delta_k`` each
position's small rotation error (prior 1-sigma ``fixture_sigma_rad``; the base position defines
the frame). With positions about two different fixture axes (the default: base, +90 deg about z,
about x and about y: 12 vectors, after McPherron and Snare's UCLA procedure) everything but the
common scale of ``T`` and ``K`` is determined by the turns; the certificate's scale fixes that,
so its uncertainty is part of the coil constants' sigma. Fitted by weighted least squares
(``scipy.optimize.least_squares``) with the priors as pseudo-observations; covariance from the
Jacobian at the solution. A reading's scatter misstates its mean's error both ways - mains
ripple aliased by the sampling averages out of the mean (scatter too large), a lab field that moves
between the +I and -I readings does not (too small) - and by a different factor per axis (the
ripple is largest on the vertical axis). So the responses are weighted per sensor axis by how well
their two +I readings repeat (pooled over every response), and their common scale comes from the
fit's residuals (the data's chi-square over their degrees of freedom: their count less the trace
of their hat matrix, about 10 with four positions), while the priors keep theirs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from rig.errors import UserInputError

Array = npt.NDArray[np.float64]
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0
MAX_SCALE_ITERATIONS = 8
NOISE_NOTE = (0.8, 1.25)
"""Scale of the responses' sigmas outside which the result says how far they were off."""


def rotation(rotvec_rad: Array) -> Array:
    """Rotation matrix of a rotation vector (rad)."""
    angle = float(np.linalg.norm(rotvec_rad))
    if angle < 1e-15:
        return np.eye(3)
    k = np.asarray(rotvec_rad, float) / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.asarray(np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx)


DEFAULT_POSITIONS: tuple[tuple[str, Array], ...] = (
    ("base", np.eye(3)),
    ("+90 about z", rotation(np.array([0.0, 0.0, math.pi / 2]))),
    ("+90 about x", rotation(np.array([math.pi / 2, 0.0, 0.0]))),
    ("+90 about y", rotation(np.array([0.0, math.pi / 2, 0.0]))),
)
"""The fixture positions: name and nominal rotation of the sensor from its base position."""


@dataclass(frozen=True)
class SensorPrior:
    """What the reference's certificate says of it: ``l_matrix`` (lower triangular, the sensor
    matrix without its mounting; ``lower_triangular_part`` of the certificate's inverse correction)
    with 1-sigma ``scale_sigma`` (relative, diagonal) and ``skew_sigma_rad`` (off-diagonal), and
    the fixture's rotation error per position and axis, ``fixture_sigma_rad``."""

    l_matrix: Array
    scale_sigma: float = 5e-5
    skew_sigma_rad: float = 20.0 / ARCSEC_PER_RAD
    fixture_sigma_rad: float = 30.0 / ARCSEC_PER_RAD


@dataclass(frozen=True)
class CoilResponse:
    """One fixture position and coil: the sensor's reading change per ampere (uT/A, sensor frame)
    and its 1-sigma per axis from the readings' scatter; ``repeat_ut``, when measured, the
    difference of the two ``+I`` readings per ampere (what the mean readings really repeat to)."""

    position: int
    coil: int
    per_amp_ut: Array
    sigma_ut: Array
    repeat_ut: Array | None = None


@dataclass(frozen=True)
class CoilAxes:
    """The fitted coil matrix and what follows from it, each with its 1-sigma.

    ``k_ut_per_a`` (3x3, columns: each coil's field per ampere in the cage frame), ``k_cov``
    (9x9, column-major: K_x, K_y, K_z), ``constants_ut_per_a`` = |K_j|, ``skew_arcsec`` = the
    angle between each pair of coil axes minus 90 deg (xy, xz, yz), ``fixture_error_arcsec`` per
    non-base position, ``chi2`` and ``dof`` of the data (at the stated sigmas) and
    ``noise_scale``, the factor the fit's residuals put on the stated sigmas.
    """

    k_ut_per_a: Array
    k_cov: Array
    constants_ut_per_a: Array
    constants_sigma: Array
    skew_arcsec: Array
    skew_sigma_arcsec: Array
    fixture_error_arcsec: Array
    chi2: float
    dof: int
    noise_scale: float
    notes: tuple[str, ...] = field(default_factory=tuple)


def lower_triangular_part(t_matrix: Array) -> Array:
    """``L`` of ``T = L M`` (``M`` a rotation, ``L`` lower triangular with a positive diagonal)."""
    _, r = np.linalg.qr(np.asarray(t_matrix, float).T)  # T^T = M^T L^T: QR
    signs = np.sign(np.diag(r))
    return np.asarray((signs[:, None] * r).T)


_TRIL = np.tril_indices(3)


def _unpack(p: Array, n_pos: int) -> tuple[Array, Array, Array, Array]:
    k = p[:9].reshape(3, 3).T  # columns K_x, K_y, K_z
    l_matrix = np.zeros((3, 3))
    l_matrix[_TRIL] = p[9:15]
    m = rotation(p[15:18])
    deltas = np.vstack([np.zeros(3), p[18:].reshape(n_pos - 1, 3)])
    return k, l_matrix, m, deltas


def _residuals(
    p: Array, data: list[CoilResponse], nominal: list[Array], prior: SensorPrior
) -> Array:
    k, l_matrix, m, deltas = _unpack(p, len(nominal))
    t = l_matrix @ m
    out = []
    for r in data:
        a = nominal[r.position] @ rotation(deltas[r.position])
        out.append((r.per_amp_ut - t @ a.T @ k[:, r.coil]) / r.sigma_ut)
    diag = np.diag(prior.l_matrix)
    l_sigma = np.where(_TRIL[0] == _TRIL[1], prior.scale_sigma * diag[_TRIL[0]],
                       prior.skew_sigma_rad * diag[_TRIL[0]])  # fmt: skip
    out.append((p[9:15] - prior.l_matrix[_TRIL]) / l_sigma)
    out.append(p[18:] / prior.fixture_sigma_rad)
    return np.concatenate(out)


def fit_coil_axes(
    data: list[CoilResponse],
    prior: SensorPrior,
    positions: tuple[tuple[str, Array], ...] = DEFAULT_POSITIONS,
) -> CoilAxes:
    """Fit the coil matrix to the responses of every coil in every fixture position.

    Raises UserInputError when a coil or position is missing (the turns would not determine the
    axes) or the fit does not converge.
    """
    from scipy.optimize import least_squares

    n_pos = len(positions)
    _require_every_response(data, positions)
    data = repeatability_weights(data)
    nominal = [rot for _, rot in positions]
    base = [r for r in data if r.position == 0]
    k0 = np.zeros((3, 3))
    for r in base:
        k0[:, r.coil] = np.linalg.solve(prior.l_matrix, r.per_amp_ut)
    p0 = np.concatenate(
        [k0.T.reshape(-1), prior.l_matrix[_TRIL], np.zeros(3), np.zeros(3 * (n_pos - 1))]
    )
    fit = least_squares(_residuals, p0, args=(data, nominal, prior), method="lm", x_scale="jac")
    n_data = 3 * len(data)
    chi2 = float(np.sum(fit.fun[:n_data] ** 2))
    scale, dof = 1.0, n_data
    for _ in range(MAX_SCALE_ITERATIONS):
        # the data's degrees of freedom: their count less what they determine (the trace of their
        # hat matrix), the rest being the priors'
        jac = fit.jac
        hat = jac[:n_data] @ np.linalg.pinv(jac.T @ jac) @ jac[:n_data].T
        dof = max(1, round(n_data - float(np.trace(hat))))
        factor = math.sqrt(float(np.sum(fit.fun[:n_data] ** 2)) / dof)
        scale *= factor
        scaled = [CoilResponse(r.position, r.coil, r.per_amp_ut, scale * r.sigma_ut) for r in data]
        fit = least_squares(_residuals, fit.x, args=(scaled, nominal, prior), method="lm",
                            x_scale="jac")  # fmt: skip
        if abs(factor - 1.0) < 0.01:
            break
    if not fit.success:
        raise UserInputError(f"coil axes: the fit did not converge ({fit.message})")
    # a scale estimated from dof degrees of freedom leaves t-distributed errors: their variance is
    # dof / (dof - 2) times the estimate's (the sigma is a promise about the rms error); the
    # data's, not the priors' (the certificate states its own)
    jac = fit.jac.copy()
    jac[:n_data] /= math.sqrt(dof / (dof - 2.0) if dof > 4 else 3.0)
    cov = np.linalg.pinv(jac.T @ jac)
    notes: tuple[str, ...] = ()
    if not NOISE_NOTE[0] <= scale <= NOISE_NOTE[1]:
        notes = (f"the responses scatter about the fit {scale:.2f} times their readings' sigmas"
                 f" (chi-square {chi2:.1f} for {dof} dof): the sigmas are the fit's",)  # fmt: skip
    return _summarize(fit.x, cov, n_pos, chi2, dof, scale, notes)


def _require_every_response(data: list[CoilResponse], positions: tuple[tuple[str, Array], ...]
                            ) -> None:  # fmt: skip
    """UserInputError naming every coil and position without a response."""
    seen = {(r.position, r.coil) for r in data}
    missing = [(positions[k][0], "xyz"[j]) for k in range(len(positions)) for j in range(3)
               if (k, j) not in seen]  # fmt: skip
    if missing:
        raise UserInputError(
            "coil axes: no response for "
            + ", ".join(f"coil {c} in position '{p}'" for p, c in missing)
            + "; every coil must be driven in every fixture position"
        )


def repeatability_weights(data: list[CoilResponse]) -> list[CoilResponse]:
    """The responses with the sigma each sensor axis's mean readings really repeat to: from the
    two ``+I`` readings of every response, pooled per axis (``var(d) = 3/4 var(repeat)`` for
    independent means). A reading's scatter misstates its mean's error by axis (mains ripple that
    the sampling aliases inflates the scatter and averages out of the mean), which would weight
    the axes wrongly; the common scale still comes from the fit's residuals. Unchanged when a
    response has no repeat."""
    if not data or any(r.repeat_ut is None for r in data):
        return data
    repeats = np.array([r.repeat_ut for r in data], float)
    sigma = np.sqrt(0.75 * np.mean(repeats**2, axis=0))
    floor = 1e-3 * float(np.max(sigma)) + 1e-12
    sigma = np.maximum(sigma, floor)
    return [CoilResponse(r.position, r.coil, r.per_amp_ut, sigma, r.repeat_ut) for r in data]


def derived_constants_and_skews(k_flat: Array) -> Array:
    """Coil constants (3, uT/A) and skews (rad: xy, xz, yz) from K (column-major)."""
    k = k_flat.reshape(3, 3).T
    norms = np.linalg.norm(k, axis=0)
    skews = []
    for i, j in ((0, 1), (0, 2), (1, 2)):
        cos = float(k[:, i] @ k[:, j] / (norms[i] * norms[j]))
        skews.append(math.pi / 2 - math.acos(max(-1.0, min(1.0, cos))))
    return np.concatenate([norms, skews])


def derived_sigmas(k_flat: Array, k_cov: Array) -> Array:
    """1-sigma of :func:`derived_constants_and_skews` from K's covariance (9x9, column-major),
    by linear propagation (central differences)."""
    jac = np.empty((6, 9))
    for i in range(9):
        step = 1e-7 * max(1.0, abs(k_flat[i]))
        up, down = k_flat.copy(), k_flat.copy()
        up[i] += step
        down[i] -= step
        jac[:, i] = (derived_constants_and_skews(up) - derived_constants_and_skews(down)) / (
            2 * step
        )
    return np.sqrt(np.clip(np.diag(jac @ k_cov @ jac.T), 0.0, None))


def _summarize(x: Array, cov: Array, n_pos: int, chi2: float, dof: int, noise_scale: float,
               notes: tuple[str, ...]) -> CoilAxes:  # fmt: skip
    k_cov = cov[:9, :9]
    value = derived_constants_and_skews(x[:9])
    sigma = derived_sigmas(x[:9], k_cov)
    fixture = x[18:].reshape(n_pos - 1, 3) * ARCSEC_PER_RAD
    return CoilAxes(
        k_ut_per_a=x[:9].reshape(3, 3).T.copy(),
        k_cov=k_cov,
        constants_ut_per_a=value[:3],
        constants_sigma=sigma[:3],
        skew_arcsec=value[3:] * ARCSEC_PER_RAD,
        skew_sigma_arcsec=sigma[3:] * ARCSEC_PER_RAD,
        fixture_error_arcsec=fixture,
        chi2=chi2,
        dof=dof,
        noise_scale=noise_scale,
        notes=notes,
    )


class Controller(Protocol):
    """What the measurement needs of the cage controller."""

    def set_currents(self, target_a: npt.ArrayLike) -> Array: ...

    def sleep(self, seconds: float) -> None: ...

    def reference_readings(self, samples: int, *, fresh: bool = True) -> Array: ...


def measure_position(
    controller: Controller, position: int, amplitude_a: float, samples: int, transient_s: float
) -> list[CoilResponse]:
    """Drive each coil at ``+I, -I, +I`` (``amplitude_a``), reading the reference ``samples``
    times at each after ``transient_s``; the half difference per ampere of the mean of the two
    ``+I`` readings and the ``-I`` one (a linear drift of the lab field cancels) with its 1-sigma
    from the readings' scatter. Leaves the coils at zero."""
    out = []
    for coil in range(3):
        means, variances = [], []
        for sign in (1.0, -1.0, 1.0):
            target = np.zeros(3)
            target[coil] = sign * amplitude_a
            controller.set_currents(target)
            controller.sleep(transient_s)
            readings = controller.reference_readings(samples)
            means.append(readings.mean(axis=0))
            variances.append(readings.var(axis=0, ddof=1) / samples)
        d = (0.5 * (means[0] + means[2]) - means[1]) / (2.0 * amplitude_a)
        var = (0.25 * (variances[0] + variances[2]) + variances[1]) / (2.0 * amplitude_a) ** 2
        repeat = (means[0] - means[2]) / (2.0 * amplitude_a)
        out.append(CoilResponse(position, coil, d, np.sqrt(var), repeat))
    controller.set_currents(np.zeros(3))
    return out
