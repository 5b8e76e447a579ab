"""Cage characterization: fit ``B = K I + B0`` from a current sweep measured by the reference."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

import timebase
from rig.cage.controller import CageController
from rig.cage.model import CageModel

Array = npt.NDArray[np.float64]


def sweep_points(amplitude_a: float) -> Array:
    """Zero, +-a on each axis, the four (+-a, +-a, +-a) diagonals; zero between groups to expose
    ambient drift. 14 points for 5 unknowns per output axis (K row, B0, drift)."""
    a = amplitude_a
    pts: list[list[float]] = [[0.0, 0.0, 0.0]]
    for axis in range(3):
        for s in (1, -1):
            p = [0.0, 0.0, 0.0]
            p[axis] = s * a
            pts.append(p)
        pts.append([0.0, 0.0, 0.0])
    pts += [[a, a, a], [-a, a, -a], [a, -a, -a], [-a, -a, a]]
    return np.array(pts, float)


def fit_cage(
    currents_a: Array, fields_ut: Array, times_s: Array | None = None
) -> tuple[Array, Array, Array, Array, float, Array]:
    """Least squares ``B = K I + B0 + D (t - t_mid)``.

    The linear drift term ``D`` (uT/s) keeps a slowly drifting lab field out of ``K`` and ``B0``;
    ``B0`` is the ambient field at the middle of the sweep. Returns K, B0, their 1-sigma, the
    residual RMS (uT) and D.
    """
    x = _design(currents_a, times_s)
    coef, *_ = np.linalg.lstsq(x, fields_ut, rcond=None)
    resid = fields_ut - x @ coef
    dof = max(x.shape[0] - x.shape[1], 1)
    var = np.sum(resid**2, axis=0) / dof  # per output axis
    inv = np.linalg.inv(x.T @ x)
    sigma = np.sqrt(np.outer(np.diag(inv), var))  # parameter row, output axis column
    drift = np.asarray(coef[4] if times_s is not None else np.zeros(3), dtype=np.float64)
    k = np.asarray(coef[:3].T, dtype=np.float64)
    b0 = np.asarray(coef[3], dtype=np.float64)
    k_sigma = np.asarray(sigma[:3].T, dtype=np.float64)
    b0_sigma = np.asarray(sigma[3], dtype=np.float64)
    return k, b0, k_sigma, b0_sigma, float(np.sqrt(np.mean(resid**2))), drift


def _design(currents_a: Array, times_s: Array | None) -> Array:
    """The regressors of :func:`fit_cage`: the currents (A), 1, and the time from the middle of
    the sweep (s) when ``times_s`` is given."""
    cols = [currents_a, np.ones((currents_a.shape[0], 1))]
    if times_s is not None:
        cols.append((times_s - 0.5 * (times_s.min() + times_s.max()))[:, None])
    return np.hstack(cols)


TRANSIENT_S = 0.2
"""Wait after each sweep point's ramp before the reference is read (s): coil L/R settling."""
OUTLIER_T = 6.0
"""A sweep point whose externally studentized residual exceeds this on any axis is measured once
more (a door, a passing vehicle or a late reading during that point): Student's t with 8 degrees
of freedom passes 6 about once in 3000 point-axes."""


def outlying_points(currents_a: Array, fields_ut: Array, times_s: Array) -> list[int]:
    """Indices of the sweep points whose externally studentized residual (leave-one-out, per
    output axis, the :func:`fit_cage` model) exceeds :data:`OUTLIER_T` in magnitude on any axis,
    worst first; none when the fit has under 4 degrees of freedom to judge by."""
    x = _design(currents_a, times_s)
    dof = x.shape[0] - x.shape[1]
    if dof < 4:
        return []
    coef, *_ = np.linalg.lstsq(x, fields_ut, rcond=None)
    resid = fields_ut - x @ coef
    lever = np.einsum("ij,jk,ik->i", x, np.linalg.pinv(x.T @ x), x).clip(max=1 - 1e-9)
    sse = np.sum(resid**2, axis=0)
    deleted_var = (sse[None, :] - resid**2 / (1 - lever[:, None])) / (dof - 1)
    scale = np.sqrt(np.maximum(deleted_var, 1e-30) * (1 - lever[:, None]))
    worst = np.max(np.abs(resid) / scale, axis=1)
    return [int(i) for i in np.argsort(-worst) if worst[i] > OUTLIER_T]


def characterize(
    controller: CageController,
    amplitude_a: float,
    *,
    samples: int = 20,
    repeats: int = 1,
    transient_s: float = TRANSIENT_S,
    instruments: dict[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> CageModel:
    """Sweep the coil currents, measure the reference at each point, fit the cage model.

    ``repeats`` runs the sweep pattern several times (more degrees of freedom for the residual
    variance, hence a better-determined uncertainty). The controller's own limits apply to every
    point; the currents are ramped back to zero at the end.
    """
    points = np.tile(sweep_points(amplitude_a), (repeats, 1))
    fields, times = np.zeros((len(points), 3)), np.zeros(len(points))
    for n, p in enumerate(points):
        fields[n], times[n] = _measure_point(controller, p, samples, transient_s)
        if progress is not None:
            progress(n + 1, len(points))
    remeasured = outlying_points(points, fields, times)
    for n in remeasured:  # measured once more: kept as measured then, however it turns out
        fields[n], times[n] = _measure_point(controller, points[n], samples, transient_s)
    controller.set_currents(np.zeros(3))
    k, b0, k_sigma, b0_sigma, rms, drift = fit_cage(points, fields, times)
    meta = {
        "date": dt.datetime.fromtimestamp(timebase.wall_time(), dt.UTC).isoformat(
            timespec="seconds"
        ),
        "instruments": instruments if instruments is not None else controller.instruments(),
        "amplitude_a": amplitude_a,
        "points": len(points),
        "repeats": repeats,
        "samples_per_point": samples,
        "residual_rms_nt": 1000.0 * rms,
        "remeasured_points": remeasured,
        "condition_number": float(np.linalg.cond(k)),
        "drift_nt_per_s": (1000.0 * drift).tolist(),
        "mid_time_monotonic_s": 0.5 * float(times.min() + times.max()),
    }
    return CageModel(k, b0, k_sigma, b0_sigma, meta)


def _measure_point(
    controller: CageController, currents_a: Array, samples: int, transient_s: float
) -> tuple[Array, float]:
    """Set one sweep point's currents, wait out the transient, and return the reference's mean
    field (uT, cage frame) with the middle of its reading (monotonic s)."""
    controller.set_currents(currents_a)
    controller.sleep(transient_s)
    t_start = timebase.monotonic()
    field = controller.measure_ut(samples)
    return field, 0.5 * (t_start + timebase.monotonic())
