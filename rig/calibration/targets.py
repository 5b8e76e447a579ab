"""Acceptance sigma targets for a calibration in progress: which 1-sigma, in which unit.

A target names a group of physical parameters and the largest 1-sigma any of them may have:
``bias_nt`` (offsets x0, y0, z0 in nT), ``scale`` (a, b, c), ``nonorthogonality_deg`` (rho, phi,
lambda in degrees) and ``k_ut_per_a`` (every current-to-bias coefficient, uT per A).
"""

from __future__ import annotations

import math

import numpy as np

from rig.calibration.params import Array

SIGMA_TARGETS: dict[str, str] = {
    "bias_nt": "offsets x0, y0, z0 (nT)",
    "scale": "scale factors a, b, c",
    "nonorthogonality_deg": "non-orthogonality rho, phi, lambda (deg)",
    "k_ut_per_a": "current-to-bias coefficients (uT/A)",
}


def group_of(name: str) -> tuple[str, float]:
    """The target group of a scalar-model parameter (see
    :func:`rig.calibration.residuals.parameter_names`) and the factor from its unit in ``p``
    (1, uT, rad, uT per unit) to the target's."""
    if name in ("a", "b", "c"):
        return "scale", 1.0
    if name in ("x0", "y0", "z0"):
        return "bias_nt", 1000.0
    if name in ("rho", "phi", "lambda"):
        return "nonorthogonality_deg", math.degrees(1.0)
    if name.startswith("k["):
        return "k_ut_per_a", 1.0
    raise KeyError(f"no target group for parameter {name!r}")


def group_sigmas(sigma_p: Array, names: tuple[str, ...]) -> dict[str, float]:
    """The largest 1-sigma of each target group, in the target's unit, from the sigmas of the
    parameters ``names``."""
    out: dict[str, float] = {}
    for name, sigma in zip(names, np.asarray(sigma_p, float), strict=True):
        group, factor = group_of(name)
        out[group] = max(out.get(group, 0.0), factor * float(sigma))
    return out


def unmet_targets(sigmas: dict[str, float], targets: dict[str, float]) -> list[str]:
    """The target names not met yet (a group missing from ``sigmas`` is not met)."""
    return [k for k, limit in targets.items() if not sigmas.get(k, math.inf) <= limit]
