"""The physical range of every number the lab index stores (issue 51).

A run's values reach the index from its folder, which is only as trustworthy as the accounts that
can write it (docs/lab.md): one value of 1e308 moved a lot's control limits to ~1e307 and made
``rig lab audit`` overflow. So a sync refuses a run with a value outside these ranges (one line
naming it; nothing of that run is stored), and the trend and audit leave any value outside them
(stored by an older sync) out of the control limits and count it as an outlier.

The ranges are wide: they hold anything a magnetometer calibration on a cage can produce, and
refuse only what no instrument can. Units as the index stores them (see :mod:`rig.lab.summary`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rig.lab.summary import RunSummary

OFFSET_UT = 1e5
"""|offset| (uT): 0.1 T, ten times the range of any magnetometer a cage calibrates."""
SCALE = (1e-3, 1e3)
"""A scale factor (1): beyond 1000 or below 1/1000 is not a calibration."""
ANGLE_DEG = 180.0
"""|misalignment angle| (deg)."""
RMS_NT = 1e8
"""A residual rms (nT): 0.1 T."""
UNKNOWN = 1e9
"""|value| of a parameter or criterion this table does not name, in its own unit."""

PARAMETERS: dict[str, tuple[float, float]] = {
    "a": SCALE,
    "b": SCALE,
    "c": SCALE,
    "x0_ut": (-OFFSET_UT, OFFSET_UT),
    "y0_ut": (-OFFSET_UT, OFFSET_UT),
    "z0_ut": (-OFFSET_UT, OFFSET_UT),
    "rho_deg": (-ANGLE_DEG, ANGLE_DEG),
    "phi_deg": (-ANGLE_DEG, ANGLE_DEG),
    "lambda_deg": (-ANGLE_DEG, ANGLE_DEG),
    "residual_rms_nt": (0.0, RMS_NT),
}
"""Calibration parameter -> (lowest, highest) value it may have."""

CRITERION_UNITS: dict[str, float] = {
    "uT": OFFSET_UT,
    "nT": OFFSET_UT * 1e3,
    "mT": OFFSET_UT * 1e-3,
    "nT/rtHz": RMS_NT,
    "deg": 360.0,
    "%": 1e6,
    "A": 1e3,
    "mA": 1e6,
    "C": 1e4,
    "s": 1e8,
    "Hz": 1e9,
}
"""Criterion unit -> the largest |value| or |limit| it may have (a margin: twice that)."""


def parameter_range(name: str) -> tuple[float, float]:
    """The (lowest, highest) value of calibration parameter ``name`` (unknown: +-UNKNOWN)."""
    return PARAMETERS.get(name, (-UNKNOWN, UNKNOWN))


def in_range(name: str, value: float) -> bool:
    """Whether ``value`` is finite and within ``name``'s :func:`parameter_range`."""
    lo, hi = parameter_range(name)
    return math.isfinite(value) and lo <= value <= hi


def sigma_limit(name: str) -> float:
    """The largest 1-sigma of parameter ``name`` (the width of its range)."""
    lo, hi = parameter_range(name)
    return hi - lo


def out_of_range(s: RunSummary) -> str | None:
    """The first number of ``s`` outside its physical range, as one line naming it, its value and
    the range; None when every number is within."""
    for r in s.results:
        lo, hi = parameter_range(r.name)
        if not in_range(r.name, r.value):
            return f"{r.source} {r.name} = {r.value!r} is outside {lo:g} .. {hi:g}"
        if r.sigma is not None and not 0.0 <= r.sigma <= sigma_limit(r.name):
            return (
                f"{r.source} {r.name} sigma = {r.sigma!r} is outside 0 .. {sigma_limit(r.name):g}"
            )
    for c in s.criteria:
        bound = CRITERION_UNITS.get(c.unit, UNKNOWN)
        for what, value, limit in (("value", c.value, bound), ("min", c.min, bound),
                                   ("max", c.max, bound), ("margin", c.margin, 2 * bound)):  # fmt: skip
            if value is not None and not (math.isfinite(value) and abs(value) <= limit):
                unit = f" {c.unit}" if c.unit else ""
                return (
                    f"criterion {c.name!r} {what} = {value!r}{unit} is outside"
                    f" -{limit:g} .. {limit:g}{unit}"
                )
    return None
