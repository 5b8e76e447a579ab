"""Recorded data checked against the record's own timing: a DUT that moves while nothing moved it.

During a hold (the settled samples between two field or load changes) the field is still and
every load current is steady, so the DUT reads a constant plus noise. A jump in the DUT's
readings close to the *next* change, lasting until it, while the reference holds still, means the
DUT's samples there are dated before the change that caused them: they were misdated (a stream
clock that lost count, a simulator or a sensor buffer that was late), not settled at the old
state. The mirror image - a jump just after a hold began - is a response dated late. Either way
those samples contradict the record, and a fit that took them as settled would be wrecked by a
few samples (the evidence in issue 30: 2 samples of 22 uT each, a 990 nT residual).

:func:`misdated_samples` finds them in each hold and returns them with what was found (when,
how big, how early or late), so that the caller leaves them out and says so. A jump in the
middle of a hold, or one the reference shares, is left alone: that is the DUT's or the field's
own behaviour and the fit must see it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

JUMP_SIGMA = 12.0
"""A jump between the levels on either side of a sample, this many robust standard deviations of
the hold's sample-to-sample differences, is a change of state, not noise."""
EDGE_S = 0.6
"""Only a jump this close (s) to a hold's end (before the next change was issued) or start (after
the last one settled) is taken as misdated: timing errors of a busy computer are up to a few
sample periods; a jump further inside a hold is the DUT's own behaviour."""
MIN_HOLD = 6
"""Holds with fewer settled samples are not judged (too few for a noise estimate)."""
LEVEL = 3
"""Samples on each side of a candidate jump whose median is its level."""
FLOOR_UT = 0.02
"""Smallest sample-to-sample noise believed (uT): a quantized stream (HMR2300: 6.7 nT per count)
has mostly zero differences and a tiny robust spread, which would make a few counts of drift a
"jump"; with this floor a jump must exceed 0.24 uT, far beyond what settles wrongly by chance and
far below the microtesla effects of a misdated load or field change."""


class MisdatedHold(NamedTuple):
    """Samples of one hold that moved while the reference and every command held still."""

    t_s: float
    """When the DUT's readings jumped (s, the first sample at the new level)."""
    early_s: float
    """How far before the next change was issued (> 0), or after the hold began (< 0) the jump
    is dated (s): the size of the timing error."""
    jump_ut: float
    """Size of the jump (uT, largest axis)."""
    samples: int
    """Samples left out."""


def _robust_sigma(d: Array) -> Array:
    """Per-axis standard deviation of the samples from their first differences ``d``."""
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return np.asarray(np.maximum(1.4826 * mad / np.sqrt(2.0), FLOOR_UT), float)


def _largest_jump(x: Array, sigma: Array) -> tuple[int, float, float]:
    """(index of the first sample after the most likely single level jump, its size in sigma,
    in uT). The split is the one that best separates two constant levels (the two-sample
    statistic of the means, largest axis); its size is judged on the medians of the LEVEL samples
    on either side, so one noise spike does not make a jump."""
    n = x.shape[0]
    z = x / sigma
    csum = np.cumsum(z, axis=0)
    total = csum[-1]
    k = np.arange(1, n)[:, None].astype(float)
    mean_before = csum[:-1] / k
    mean_after = (total - csum[:-1]) / (n - k)
    separation = np.max((mean_after - mean_before) ** 2 * k * (n - k) / n, axis=1)
    split = int(np.argmax(separation)) + 1
    near_before, near_after = x[max(0, split - LEVEL) : split], x[split : split + LEVEL]
    before, after = np.median(near_before, axis=0), np.median(near_after, axis=0)
    # every sample on each side must sit at its own level: one spike is not a jump
    step = np.minimum(np.min(np.abs(near_after - before), axis=0),
                      np.min(np.abs(near_before - after), axis=0))  # fmt: skip
    return split, float(np.max(step / sigma)), float(np.max(np.abs(after - before)))


def _holds(keep: Mask) -> list[tuple[int, int]]:
    """(first, end) index ranges of consecutive kept samples."""
    edges = np.diff(np.r_[0, keep.astype(np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _reference_moved(ref_t: Array, ref_ut: Array, t0: float, t1: float) -> bool:
    """Whether the reference's readings jumped between ``t0`` and ``t1`` (s, the hold) by more
    than JUMP_SIGMA of their own noise: then the field itself moved and the DUT's jump is no
    timing error."""
    inside = (ref_t >= t0) & (ref_t <= t1)
    if np.count_nonzero(inside) < MIN_HOLD:
        return False
    x = ref_ut[inside]
    _, score, _ = _largest_jump(x, _robust_sigma(np.diff(x, axis=0)))
    return score > JUMP_SIGMA


def misdated_samples(t_s: Array, dut_ut: Array, keep: Mask, ref_t: Array, ref_ut: Array,
                     change_starts_s: Array) -> tuple[Mask, list[MisdatedHold]]:  # fmt: skip
    """The DUT samples (True) among ``keep`` that contradict the record, and what was found.

    ``t_s`` (N,) and ``dut_ut`` (N, 3) are the DUT's samples, ``keep`` (N,) those taken as
    settled (holds are its runs of consecutive True); ``ref_t``, ``ref_ut`` the reference's;
    ``change_starts_s`` when every field or load change was issued (s)."""
    out = np.zeros(t_s.shape, bool)
    found: list[MisdatedHold] = []
    starts = np.sort(np.asarray(change_starts_s, float))
    for first, end in _holds(keep):
        first, end = int(first), int(end)
        if end - first < MIN_HOLD:
            continue
        t, x = t_s[first:end], dut_ut[first:end]
        sigma = _robust_sigma(np.diff(x, axis=0))
        k, score, jump_ut = _largest_jump(x, sigma)
        if score <= JUMP_SIGMA:
            continue
        if _reference_moved(ref_t, ref_ut, float(t[0]), float(t[-1])):
            continue  # the field itself moved: not the DUT's timing
        later = starts[starts > t[-1]]
        issued_next = float(later[0]) if later.size else np.inf
        if issued_next - t[k] <= EDGE_S:  # moved before the next change was issued
            out[first + k : end] = True
            found.append(
                MisdatedHold(
                    float(t[k]), float(issued_next - t[k]), float(jump_ut), int(end - first - k)
                )
            )
        elif t[k] - t[0] <= EDGE_S:  # still moving after the hold was taken as settled
            out[first : first + k] = True
            found.append(MisdatedHold(float(t[k]), -float(t[k] - t[0]), float(jump_ut), int(k)))
    return out, found


def misdated_note(found: Sequence[MisdatedHold], total: int) -> str:
    """One warning line for :func:`misdated_samples`' findings (``total``: samples judged)."""
    left = sum(f.samples for f in found)
    worst = max(found, key=lambda f: abs(f.early_s))
    when = (f"{1000.0 * worst.early_s:.0f} ms before the next change was issued"
            if worst.early_s > 0 else f"{-1000.0 * worst.early_s:.0f} ms into a settled hold")  # fmt: skip
    return (f"{left} of {total} DUT samples left out: in {len(found)} hold(s) the DUT moved while"
            f" the reference and every command held still (worst {worst.jump_ut:.2f} uT at"
            f" t = {worst.t_s:.3f} s, {when}): those samples are misdated by a timing error;"
            " re-run the step if many are")  # fmt: skip


MAX_MISDATED_FRACTION = 0.01
"""More misdated samples than this fraction of those judged, and the record's timing is not
trusted for the step: leaving them out may not have found them all (ADR 0020)."""
MAX_MISDATED_HOLDS = 5
"""Nor when more holds than this had misdated samples."""


def timing_fault(found: Sequence[MisdatedHold], total: int) -> str | None:
    """Why a calibration's data cannot be trusted for a verdict (a re-run is needed), or None:
    too many misdated samples (:data:`MAX_MISDATED_FRACTION` of ``total`` judged) or holds
    (:data:`MAX_MISDATED_HOLDS`). A few, left out, leave the rest trusted."""
    left = sum(f.samples for f in found)
    if left <= MAX_MISDATED_FRACTION * max(total, 1) and len(found) <= MAX_MISDATED_HOLDS:
        return None
    worst = max(found, key=lambda f: abs(f.early_s))
    return (f"timing fault: {left} of {total} samples in {len(found)} hold(s) contradict their"
            f" dates (worst {1000.0 * abs(worst.early_s):.0f} ms); the data cannot be trusted"
            " for a verdict: re-run the step on a less busy computer")  # fmt: skip
