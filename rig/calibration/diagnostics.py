"""Checks that say, before fitting, whether the data can support a calibration."""

from __future__ import annotations

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import Samples
from rig.errors import CalibrationError

CONSTANT_FIELD_SPREAD = 0.01
"""Relative spread of |h| (std/mean) below which the field magnitude counts as constant."""


def field_magnitude_spread(s: Samples) -> float:
    """Relative spread std(|h|)/mean(|h|) of the reference field magnitude."""
    mag = s.field_magnitude_ut
    return float(np.std(mag) / np.mean(mag))


def is_constant_field(s: Samples) -> bool:
    """True when |h| is (nearly) constant: the centered and TWOSTEP problems are then singular."""
    return field_magnitude_spread(s) < CONSTANT_FIELD_SPREAD


def require_varying_field(s: Samples, method: str) -> None:
    """Raise a one-line error when ``method`` cannot work because |h| is nearly constant."""
    if is_constant_field(s):
        raise CalibrationError(
            f"the field magnitude is nearly constant (spread {100 * field_magnitude_spread(s):.2f} %"
            f" < {100 * CONSTANT_FIELD_SPREAD:.0f} %), so the {method} estimator is singular: use"
            " --method ml or --method ellipsoid, or record data at several field magnitudes"
        )


def check_samples(s: Samples, n_parameters: int) -> None:
    """Minimum sample count, positive field magnitude, independent telemetry channels."""
    needed = max(2 * n_parameters, n_parameters + 10)
    if s.n < needed:
        raise CalibrationError(
            f"only {s.n} samples for {n_parameters} parameters: record at least {needed} samples"
            " (more directions and field levels)"
        )
    bad = np.flatnonzero(~(s.field_magnitude_ut > 0.0))
    if bad.size:
        raise CalibrationError(
            f"the reference field magnitude is zero or negative in {bad.size} samples (first at"
            f" sample {bad[0] + 1}): the fit needs |h| > 0; remove those rows or fix the field column"
        )
    check_telemetry_rank(s.telemetry, s.channels)


def check_telemetry_rank(u: Array, channels: tuple[str, ...]) -> None:
    """Each channel must vary and be linearly independent of the others and of the offset."""
    if u.shape[1] == 0:
        return
    for j, name in enumerate(channels):
        col = u[:, j]
        if np.ptp(col) <= 1e-9 * max(1.0, float(np.max(np.abs(col)))):
            raise CalibrationError(
                f"telemetry channel '{name}' is constant ({col[0]:g}), so its coefficient cannot be"
                " told from the offset: drop it from --telemetry or record it varying"
            )
    # The singular values of the centered, unit-norm columns, from their (J, J) Gram matrix
    # accumulated in blocks of rows about a provisional mean: no N x J copy.
    shift = u[:: max(u.shape[0] // 4096, 1)].mean(axis=0)
    gram = np.zeros((u.shape[1], u.shape[1]))
    total = np.zeros(u.shape[1])
    for start in range(0, u.shape[0], 65_536):
        block = u[start : start + 65_536] - shift
        gram += block.T @ block
        total += block.sum(axis=0)
    gram -= np.outer(total, total) / u.shape[0]
    norm = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    eig, vec = np.linalg.eigh(gram / np.outer(norm, norm))
    sv = np.sqrt(np.maximum(eig[::-1], 0.0))
    if sv[-1] < 1e-6 * sv[0]:
        null = vec[:, 0]
        involved = [channels[j] for j in np.argsort(-np.abs(null)) if abs(null[j]) > 0.1]
        names = ", ".join(f"'{c}'" for c in involved)
        raise CalibrationError(
            f"telemetry channels {names} are linearly dependent (identical, scaled or summing to"
            " another), so their coefficients are not separable: drop one of them from --telemetry"
        )


COVERAGE_CONE_DEG = 60.0
"""A field direction covers an axis direction (+x, -x, ...) when within this angle of it (deg)."""
COVERAGE_MIN_FRACTION = 0.01
"""An axis direction with fewer of the samples than this (fraction) counts as not covered: the
words of the identifiability warning and refusal (rig.calibration.identifiability), not a rule."""
CAPS = ("+x", "-x", "+y", "-y", "+z", "-z")


def direction_coverage(field: Array, centre: Array | None = None) -> dict[str, float]:
    """Fraction of the rows of ``field - centre`` (N, 3; any unit; ``centre`` (3,) default 0)
    within :data:`COVERAGE_CONE_DEG` of each axis direction +x, -x, +y, -y, +z, -z."""
    cos_min = float(np.cos(np.radians(COVERAGE_CONE_DEG)))
    counts = np.zeros((3, 2))
    for start in range(0, field.shape[0], 65_536):  # blocks of rows: no N x 3 temporaries
        block = field[start : start + 65_536]
        block = block if centre is None else block - centre
        unit = block / np.maximum(np.linalg.norm(block, axis=1, keepdims=True), 1e-300)
        counts[:, 0] += np.count_nonzero(unit > cos_min, axis=0)
        counts[:, 1] += np.count_nonzero(unit < -cos_min, axis=0)
    share = counts / max(field.shape[0], 1)
    out = {}
    for i, axis in enumerate("xyz"):
        out[f"+{axis}"] = float(share[i, 0])
        out[f"-{axis}"] = float(share[i, 1])
    return out


def coverage_text(coverage: dict[str, float]) -> str:
    """'+z not covered (0.0 % of samples within 60 deg); -z 52.3 %, ...' in one line."""
    missing = [c for c in CAPS if coverage[c] < COVERAGE_MIN_FRACTION]
    shares = ", ".join(f"{c} {100 * coverage[c]:.1f} %" for c in CAPS)
    head = f"{', '.join(missing)} not covered" if missing else "every axis direction covered"
    return f"{head} (samples within {COVERAGE_CONE_DEG:.0f} deg: {shares})"
