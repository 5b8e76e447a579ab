"""Plot axes that stay readable when a few samples are far out: robust limits, outliers marked.

A handful of wild samples (misdated, a glitch) must not scale a residual plot to +-25 000 nT
so that the other thousands are one flat line: the axis covers the bulk of the data and the
samples beyond it are drawn at its edge and counted, so nothing is hidden.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

SPREAD = 8.0
"""The axis reaches this many robust standard deviations beyond the median ..."""
MARGIN = 1.1
"""... or 10 % beyond the 0.5 and 99.5 percentiles, whichever is wider."""
LOG_PAD = 0.25
"""A logarithmic axis reaches this many decades beyond the 1 and 99 percentiles."""


class RobustLimits(NamedTuple):
    """Axis limits and the samples beyond them."""

    lo: float
    hi: float
    outside: int
    """Samples beyond the limits (drawn at the edge)."""
    extreme: float
    """The value furthest from the median (same unit as the data)."""


def robust_limits(values: npt.ArrayLike) -> RobustLimits:
    """Limits covering the bulk of ``values`` (any unit): the median +- SPREAD robust standard
    deviations, widened to the 0.5-99.5 percentile range plus MARGIN; never narrower than the
    data when nothing is far out."""
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return RobustLimits(-1.0, 1.0, 0, 0.0)
    med = float(np.median(v))
    sigma = 1.4826 * float(np.median(np.abs(v - med)))
    p_lo, p_hi = (float(x) for x in np.percentile(v, [0.5, 99.5]))
    half = max(SPREAD * sigma, MARGIN * max(med - p_lo, p_hi - med), 1e-9)
    lo, hi = med - half, med + half
    outside = int(np.count_nonzero((v < lo) | (v > hi)))
    if outside == 0:
        lo, hi = float(v.min()), float(v.max())
        pad = 0.05 * max(hi - lo, 1e-9)
        lo, hi = lo - pad, hi + pad
    extreme = float(v[np.argmax(np.abs(v - med))])
    return RobustLimits(lo, hi, outside, extreme)


def mark_outliers(
    ax: Any, x: npt.ArrayLike, y: npt.ArrayLike, limits: RobustLimits, unit: str
) -> None:
    """Set ``ax``'s y limits and draw the points of (``x``, ``y``) beyond them as red triangles at
    the edge, with a note of how many and the most extreme value (``unit``)."""
    xa, ya = np.asarray(x, float), np.asarray(y, float)
    ax.set_ylim(limits.lo, limits.hi)
    if not limits.outside:
        return
    span = limits.hi - limits.lo
    high, low = ya > limits.hi, ya < limits.lo
    ax.plot(xa[high], np.full(high.sum(), limits.hi - 0.02 * span), "^", color="red", ms=5)
    ax.plot(xa[low], np.full(low.sum(), limits.lo + 0.02 * span), "v", color="red", ms=5)
    ax.text(0.99, 0.02, f"{limits.outside} beyond the axis (red; most extreme"
            f" {limits.extreme:.0f} {unit})", transform=ax.transAxes, ha="right", va="bottom",
            fontsize=8, color="red")  # fmt: skip


def robust_log_limits(values: npt.ArrayLike, also: npt.ArrayLike = ()) -> RobustLimits:
    """:func:`robust_limits` for a logarithmic axis: found on the decades of the positive finite
    ``values`` (a filter's sigma that spiked to 1e13 for one update must not flatten the rest),
    widened to take in ``also`` (a target, a forecast); limits in the values' unit, ``extreme``
    the value furthest out."""
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v) & (v > 0)]
    if v.size == 0:
        return RobustLimits(0.1, 10.0, 0, 0.0)
    decades = np.log10(v)
    p_lo, p_hi = (float(x) for x in np.percentile(decades, [1.0, 99.0]))
    extra = np.asarray(also, float).ravel()
    extra = np.log10(extra[np.isfinite(extra) & (extra > 0)])
    lo = min([p_lo - LOG_PAD, *(extra - 0.05)])
    hi = max([p_hi + LOG_PAD, *(extra + 0.05)])
    outside = int(np.count_nonzero((decades < lo) | (decades > hi)))
    if outside == 0:
        lo, hi = min(lo, float(decades.min()) - 0.05), max(hi, float(decades.max()) + 0.05)
    median = float(np.median(decades))
    extreme = float(v[np.argmax(np.abs(decades - median))])
    return RobustLimits(10.0**lo, 10.0**hi, outside, extreme)
