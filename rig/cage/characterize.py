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
    cols = [currents_a, np.ones((currents_a.shape[0], 1))]
    if times_s is not None:
        cols.append((times_s - 0.5 * (times_s.min() + times_s.max()))[:, None])
    x = np.hstack(cols)
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


TRANSIENT_S = 0.2
"""Wait after each sweep point's ramp before the reference is read (s): coil L/R settling."""


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
    fields, times = [], []
    for n, p in enumerate(points):
        controller.set_currents(p)
        controller.sleep(transient_s)
        t_start = timebase.monotonic()
        fields.append(controller.measure_ut(samples))
        times.append(0.5 * (t_start + timebase.monotonic()))
        if progress is not None:
            progress(n + 1, len(points))
    controller.set_currents(np.zeros(3))
    k, b0, k_sigma, b0_sigma, rms, drift = fit_cage(points, np.array(fields), np.array(times))
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
        "condition_number": float(np.linalg.cond(k)),
        "drift_nt_per_s": (1000.0 * drift).tolist(),
        "mid_time_monotonic_s": 0.5 * (times[0] + times[-1]),
    }
    return CageModel(k, b0, k_sigma, b0_sigma, meta)
