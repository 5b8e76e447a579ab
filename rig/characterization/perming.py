"""What a strong field leaves in a magnetometer's offset (perming), and whether a reset clears it.

The offset is measured in null-field holds before and after the field shock (the DUT less the
reference, nT): each hold's mean per axis with a sigma from batch means (right for noise whose
neighbouring samples are alike or opposite). The shifts between holds are fitted to the holds'
stretch averages together, with the offset's noise (white, flicker and a random walk, which
keeps wandering between the holds while the shock is on) estimated alongside
(:func:`rig.characterization.offset_noise.fit_bins`): a wandering offset widens a shift's sigma
by what it can have wandered in the time between, where two holds' batch means alone left it
three to six times too small. Whether a shift is there at all is a chi-square test of the three
axes together, reported as the equivalent Gaussian significance (3 sigma: one chance in 370
that noise alone made it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rig.characterization.offset_noise import Bins, contiguous_bins, fit_bins, joint_z

Array = npt.NDArray[np.float64]

MIN_HOLD_SAMPLES = 10
BATCHES = 20
"""A hold's mean has its sigma from this many batches (its own precision about 16 %); the
shifts are fitted to this many stretch averages per hold."""
DETECTED_SIGMA = 3.0
"""A shift at least this significant (equivalent Gaussian sigma) is reported as detected."""


@dataclass(frozen=True)
class HoldMean:
    """A null-field hold's offset: per axis the mean (nT) and its 1-sigma (nT), of ``samples``."""

    mean_nt: tuple[float, ...]
    sigma_nt: tuple[float, ...]
    samples: int


@dataclass(frozen=True)
class OffsetShift:
    """The offset after less before (nT per axis) with its 1-sigma, its size (nT) and how
    significant it is (equivalent Gaussian sigma of the three axes' chi-square)."""

    shift_nt: tuple[float, ...]
    sigma_nt: tuple[float, ...]
    significance_sigma: float

    @property
    def size_nt(self) -> float:
        """The shift's magnitude (nT)."""
        return float(np.linalg.norm(self.shift_nt))

    @property
    def detected(self) -> bool:
        """Significant at :data:`DETECTED_SIGMA` or more."""
        return self.significance_sigma >= DETECTED_SIGMA


def hold_mean(offsets_nt: Array) -> HoldMean:
    """The mean offset of one hold (``offsets_nt``: samples x 3, nT) and its sigma: the scatter of
    :data:`BATCHES` consecutive batches' means over the square root of their number, which holds
    for correlated noise of either sign (a lab's mains ripple aliased by two sensors sampling at
    different instants alternates sample to sample and averages out faster than white noise;
    slowly wandering noise averages out slower) as long as it forgets within a batch."""
    x = np.asarray(offsets_nt, float)
    n = len(x)
    if n < MIN_HOLD_SAMPLES:
        raise ValueError(f"{n} samples in a hold: at least {MIN_HOLD_SAMPLES} are needed")
    batches = min(BATCHES, n // 2)
    size = n // batches
    means = x[: batches * size].reshape(batches, size, -1).mean(axis=1)
    sigma = means.std(axis=0, ddof=1) / np.sqrt(batches)
    return HoldMean(tuple(float(v) for v in x.mean(axis=0)), tuple(float(v) for v in sigma), n)


def offset_shifts(t_s: list[Array], offsets_nt: list[Array]) -> list[OffsetShift]:
    """Each hold after the first less the first: ``t_s`` the holds' sample times (s, one
    clock), ``offsets_nt`` their offsets (samples x 3, nT). Fitted together (module docstring);
    ValueError when a hold has fewer than :data:`MIN_HOLD_SAMPLES` samples."""
    starts, ends, counts, members, rates = [], [], [], [], []
    for k, (t, x) in enumerate(zip(t_s, offsets_nt, strict=True)):
        if len(t) < MIN_HOLD_SAMPLES:
            raise ValueError(f"{len(t)} samples in a hold: at least {MIN_HOLD_SAMPLES} are needed")
        bins, idx = contiguous_bins(np.asarray(t, float), min(BATCHES, len(t) // 2))
        starts.append(bins.start_s)
        ends.append(bins.end_s)
        counts.append(bins.samples)
        rates.append(bins.rate_hz)
        members += [(k, np.asarray(x, float)[i].mean(axis=0)) for i in idx]
    spans = Bins(np.concatenate(starts), np.concatenate(ends), np.concatenate(counts),
                 float(np.median(rates)))  # fmt: skip
    holds = len(t_s)
    design = np.array([[1.0] + [float(k == j) for j in range(1, holds)] for k, _ in members])
    means = np.array([m for _, m in members])
    fits = [fit_bins(design, means[:, axis], spans) for axis in range(3)]
    out = []
    for j in range(1, holds):
        d = np.array([float(f.coef[j]) for f in fits])
        sig = np.array([float(f.sigma[j]) for f in fits])
        chi2 = float(np.sum((d / sig) ** 2))
        z = joint_z(chi2, 3)
        out.append(OffsetShift(tuple(float(v) for v in d), tuple(float(v) for v in sig), z))
    return out
