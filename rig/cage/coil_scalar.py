"""Coil constants and axis angles from a scalar (total-field) magnetometer: the scalar method.

A total-field magnetometer (cesium, Overhauser) at the cage centre measures ``F = |B|`` with an
absolute accuracy no vector sensor has: its scale is a physical constant (the Larmor frequency),
so it needs no certificate. The cage sets the total field to magnitudes ``F_n`` in directions
``u_n``; the reading is modelled as::

    F_n = |K I_n + b0 + b1 (t_n - t_mid) + b2 (t_n - t_mid)^2| + f0

``K`` (uT/A, columns: each coil's field per ampere), ``b0`` the lab field at the sensor, ``b1``
and ``b2`` its drift over the sweep (uT/s, uT/s^2: a lab field swinging by tens of nT over a
quarter of an hour curves by several nT within a minute's sweep; the points go in a random
order, so what the drift terms leave is noise, not a pattern over the directions) and ``f0`` the sensor's own offset (prior 1-sigma
``offset_sigma_nt``, its stated absolute accuracy). A total field does not change when
everything is turned, so only ``K`` up to a rotation is found: ``K`` is parametrized upper
triangular (coil x along the frame's first axis, coil y in its first plane), which leaves the coil
constants ``|K_j|`` and the angles between the coil axes, the quantities sought, untouched. Two
shells of field magnitude separate the sensor's offset from the constants' scale.

Fitted by least squares (``scipy.optimize.least_squares``). A point's error is its readings' own
scatter (a fraction of a nT) and, mostly, the lab field's wander between points (1/f noise: about
a nT), which every point shares alike: each is weighted with its own variance plus that shared
one, estimated from the residuals (their variance over the degrees of freedom beyond the readings'
own); the common scale then comes from the residuals, with the t factor; the covariance from the
Jacobian. (Weighted by the readings' scatter alone, 50 simulated procedures gave rms
error/sigma up to 1.56: the weights were random.)
After Merayo et al. (the DTU scalar calibration) and Olsen et al., applied to the coils instead of
the sensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from rig.cage.coil_axes import ARCSEC_PER_RAD, derived_constants_and_skews, derived_sigmas
from rig.errors import UserInputError

Array = npt.NDArray[np.float64]
WEIGHT_ITERATIONS = 3
"""Rounds of estimating the scatter between points (the lab field's wander) that every reading
shares beside its own."""
MIN_POINTS = 16
"""Fewer readings than this cannot determine 13 unknowns with a residual check."""
_UPPER = np.triu_indices(3)


@dataclass(frozen=True)
class ScalarReading:
    """One field set-point: the coil currents (A), the time (s from the sweep's start) and the
    scalar reading's mean and its 1-sigma (uT)."""

    currents_a: Array
    t_s: float
    total_ut: float
    sigma_ut: float


@dataclass(frozen=True)
class ScalarCoilFit:
    """What the scalar method found, each with its 1-sigma: the coil constants (uT/A), the skews
    (the angle between each pair of coil axes minus 90 deg: xy, xz, yz; arcsec), ``k_ut_per_a``
    (upper triangular: its rotation is not observable), the lab field and drift at the sensor, the
    sensor's offset (nT), the fit's chi-square and degrees of freedom at the readings' own sigmas
    and the scatter between points beyond them (nT: the lab field's wander)."""

    k_ut_per_a: Array
    constants_ut_per_a: Array
    constants_sigma: Array
    skew_arcsec: Array
    skew_sigma_arcsec: Array
    lab_field_ut: Array
    drift_nt_per_min: Array
    offset_nt: float
    offset_sigma_nt: float
    chi2: float
    dof: int
    between_nt: float
    residuals_nt: Array
    notes: tuple[str, ...] = field(default_factory=tuple)


def _k_matrix(p: Array) -> Array:
    k = np.zeros((3, 3))
    k[_UPPER] = p[:6]
    return k


def _model(p: Array, currents: Array, t_s: Array) -> Array:
    drift = np.outer(t_s, p[9:12]) + np.outer(t_s**2, p[13:16])
    field_ut = currents @ _k_matrix(p).T + p[6:9] + drift
    return np.asarray(np.linalg.norm(field_ut, axis=1) + p[12] * 1e-3)


def _residuals(p: Array, currents: Array, t_s: Array, total: Array, sigma: Array,
               offset_sigma_nt: float) -> Array:  # fmt: skip
    data = (total - _model(p, currents, t_s)) / sigma
    return np.append(data, p[12] / offset_sigma_nt)


def fit_scalar_coils(
    readings: list[ScalarReading], k_nominal: Array, offset_sigma_nt: float
) -> ScalarCoilFit:
    """Fit the coils to the scalar readings. ``k_nominal`` (uT/A) starts the fit.

    Raises UserInputError when there are too few readings or the currents do not span the three
    coils (the method would not determine them) or the fit does not converge.
    """
    from scipy.optimize import least_squares

    if len(readings) < MIN_POINTS:
        raise UserInputError(
            f"scalar coil fit: {len(readings)} readings, at least {MIN_POINTS} are needed;"
            " give more directions (points)"
        )
    currents = np.array([r.currents_a for r in readings], float)
    if np.linalg.matrix_rank(currents - currents.mean(axis=0), tol=1e-6) < 3:
        raise UserInputError("scalar coil fit: the currents do not drive all three coils")
    t_s = np.array([r.t_s for r in readings], float)
    t_s = t_s - 0.5 * (t_s.min() + t_s.max())
    total = np.array([r.total_ut for r in readings], float)
    sigma = np.array([max(r.sigma_ut, 1e-6) for r in readings], float)
    _, upper = np.linalg.qr(np.asarray(k_nominal, float))
    upper = upper * np.sign(np.diag(upper))[:, None]  # a positive diagonal
    b0 = _start_lab_field(currents, total, upper)
    p0 = np.concatenate([upper[_UPPER], b0, np.zeros(3), [0.0], np.zeros(3)])
    args = (currents, t_s, total, sigma, offset_sigma_nt)
    fit = least_squares(_residuals, p0, args=args, method="lm", x_scale="jac")
    n = len(readings)
    chi2 = float(np.sum(fit.fun[:n] ** 2))
    dof = max(1, n - 15)  # the offset is the prior's
    between = 0.0
    for _ in range(WEIGHT_ITERATIONS):
        residual = total - _model(fit.x, currents, t_s)
        between = max(0.0, float(np.sum(residual**2)) / dof - float(np.mean(sigma**2)))
        fit = least_squares(_residuals, fit.x, method="lm", x_scale="jac",
                            args=(currents, t_s, total, np.sqrt(sigma**2 + between),
                                  offset_sigma_nt))  # fmt: skip
    weights = np.sqrt(sigma**2 + between)
    scale = math.sqrt(float(np.sum(fit.fun[:n] ** 2)) / dof)
    fit = least_squares(_residuals, fit.x, method="lm", x_scale="jac",
                        args=(currents, t_s, total, scale * weights, offset_sigma_nt))  # fmt: skip
    if not fit.success:
        raise UserInputError(f"scalar coil fit: the fit did not converge ({fit.message})")
    # the t factor dof / (dof - 2) of a noise scale estimated from the data: the data's rows only
    jac = fit.jac.copy()
    jac[:n] /= math.sqrt(dof / (dof - 2.0) if dof > 4 else 3.0)
    cov = np.linalg.pinv(jac.T @ jac)
    return _summarize(fit.x, cov, total - _model(fit.x, currents, t_s), chi2, dof,
                      1e3 * math.sqrt(between))  # fmt: skip


def _start_lab_field(currents: Array, total: Array, k: Array) -> Array:
    """A first lab field: the mean of ``F^2 - |K I|^2 = 2 (K I) . b0 + |b0|^2`` over the readings
    solved linearly for ``b0`` (the constant term left free)."""
    field_ut = currents @ k.T
    design = np.column_stack([2.0 * field_ut, np.ones(len(total))])
    solution, *_ = np.linalg.lstsq(design, total**2 - np.sum(field_ut**2, axis=1), rcond=None)
    return np.asarray(solution[:3])


def _summarize(x: Array, cov: Array, residual_ut: Array, chi2: float, dof: int,
               between_nt: float) -> ScalarCoilFit:  # fmt: skip
    k = _k_matrix(x)
    k_flat = k.T.reshape(-1)  # column-major, as coil_axes
    jac_k = np.zeros((9, len(x)))
    for i, (row, col) in enumerate(zip(*_UPPER, strict=True)):
        jac_k[3 * col + row, i] = 1.0
    value = derived_constants_and_skews(k_flat)
    sigma = derived_sigmas(k_flat, jac_k @ cov @ jac_k.T)
    notes: tuple[str, ...] = ()
    if between_nt > 0.0:
        notes = (f"the points scatter about the fit by {between_nt:.2f} nT beyond their own"
                 " readings' scatter (the lab field between points): every point weighted with it",)  # fmt: skip
    return ScalarCoilFit(
        k_ut_per_a=k,
        constants_ut_per_a=value[:3],
        constants_sigma=sigma[:3],
        skew_arcsec=value[3:] * ARCSEC_PER_RAD,
        skew_sigma_arcsec=sigma[3:] * ARCSEC_PER_RAD,
        lab_field_ut=x[6:9].copy(),
        drift_nt_per_min=x[9:12] * 1e3 * 60.0,
        offset_nt=float(x[12]),
        offset_sigma_nt=float(math.sqrt(max(cov[12, 12], 0.0))),
        chi2=chi2,
        dof=dof,
        between_nt=between_nt,
        residuals_nt=residual_ut * 1e3,
        notes=notes,
    )


def outside_dead_zones(directions: Array, sensor_axis: Array | None, margin_deg: float) -> Array:
    """The directions at least ``margin_deg`` away from a cesium sensor's dead zones (its optical
    ``sensor_axis`` and the plane normal to it, cage frame); all of them when no axis is given
    (an Overhauser sensor has none)."""
    if sensor_axis is None:
        return directions
    axis = np.asarray(sensor_axis, float) / np.linalg.norm(sensor_axis)
    angle = np.degrees(np.arccos(np.clip(np.abs(directions @ axis), 0.0, 1.0)))
    keep = (angle >= margin_deg) & (angle <= 90.0 - margin_deg)
    return np.asarray(directions[keep])
