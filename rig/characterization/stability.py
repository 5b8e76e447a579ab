"""How a magnetometer's offset wanders: its Allan deviation with confidence intervals, and its
drift per 12 h with a sigma that holds for coloured noise.

The Allan deviation is the overlapping one of ``allantools`` (frequency-type data: each sample
is the offset, nT) on the samples put on a uniform grid; its confidence interval is allantools'
(the noise type identified from the lag-1 autocorrelation where at least 30 averaging times fit
in the record, the last one found beyond, held within the power laws Greenhall's equivalent
degrees of freedom are defined for; 68 %). Where that interval cannot be had (a record too
short for the noise it holds), the interval of a chi-square with the plain overlapping estimate's
degrees of freedom is given instead, and said. The drift is a line fitted to the record's
stretch averages with the offset's noise (white, flicker and random walk) estimated alongside
(:mod:`rig.characterization.offset_noise`): no term is dropped, and the sigma is widened for
the little a single record says of its slowest noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rig.characterization.offset_noise import (
    OffsetNoise,
    contiguous_bins,
    fit_bins,
    hadamard_noise,
    taus_125,
)

Array = npt.NDArray[np.float64]

TWELVE_HOURS_S = 12 * 3600.0
CI_68 = math.erf(1.0 / math.sqrt(2.0))
"""The confidence of a 1-sigma interval (0.683)."""
MIN_SAMPLES = 32
NOISE_ID_POINTS = 30
"""The noise type is identified (lag-1 autocorrelation) where the record holds at least this
many averaging times; longer ones keep the last type found."""
ALPHA_RANGE = (-2, 2)
"""The power laws of frequency-type noise (random walk to white phase) Greenhall's equivalent
degrees of freedom hold for; an identification beyond is held at the nearest."""


@dataclass(frozen=True)
class AllanDeviation:
    """Per averaging time (s) and axis the overlapping Allan deviation (nT) and its confidence
    interval (nT; 68 % unless asked otherwise), of samples at ``rate_hz``."""

    tau_s: tuple[float, ...]
    adev_nt: tuple[tuple[float, ...], ...]
    low_nt: tuple[tuple[float, ...], ...]
    high_nt: tuple[tuple[float, ...], ...]
    rate_hz: float
    notes: tuple[str, ...] = ()

    def at(self, tau_s: float) -> tuple[float, ...]:
        """The deviation per axis at the averaging time nearest ``tau_s`` (nT)."""
        i = int(np.argmin(np.abs(np.log(np.asarray(self.tau_s)) - math.log(tau_s))))
        return self.adev_nt[i]


@dataclass(frozen=True)
class Drift:
    """Per axis the offset's drift over 12 h (nT) and its 1-sigma (nT), from a record of
    ``record_s`` seconds, and the offset's noise fitted alongside."""

    per_12h_nt: tuple[float, ...]
    sigma_nt: tuple[float, ...]
    record_s: float
    noise: tuple[OffsetNoise, ...] = ()


def on_uniform_grid(t_s: Array, xyz: Array) -> tuple[Array, float]:
    """The samples interpolated onto a uniform grid at their median rate: (N, 3), rate (Hz)."""
    rate_hz = 1.0 / float(np.median(np.diff(t_s)))
    grid = np.arange(t_s[0], t_s[-1], 1.0 / rate_hz)
    return np.column_stack([np.interp(grid, t_s, xyz[:, i]) for i in range(3)]), rate_hz


def default_taus(n: int, rate_hz: float) -> Array:
    """1-2-5 averaging times from two samples up to a quarter of the record (s)."""
    return taus_125(2.0 / rate_hz, n / rate_hz / 4.0)


def allan_deviation(t_s: Array, offsets_nt: Array, taus_s: Array | None = None,
                    ci: float = CI_68) -> AllanDeviation:  # fmt: skip
    """The overlapping Allan deviation per axis of offsets (nT) sampled at ``t_s`` (s), with
    its ``ci`` confidence interval (default 68 %)."""
    import allantools

    if len(t_s) < MIN_SAMPLES:
        raise ValueError(f"{len(t_s)} samples: an Allan deviation needs at least {MIN_SAMPLES}")
    y, rate = on_uniform_grid(np.asarray(t_s, float), np.asarray(offsets_nt, float))
    wanted = default_taus(len(y), rate) if taus_s is None else np.asarray(taus_s, float)
    per_axis = []
    fallbacks: list[str] = []
    for i in range(3):
        taus, dev, _, _ = allantools.oadev(y[:, i], rate=rate, data_type="freq", taus=wanted)
        alpha = 0  # white frequency noise until one is identified
        cis = []
        for tau, d in zip(taus, dev, strict=True):
            af = max(1, round(tau * rate))
            if len(y) // af >= NOISE_ID_POINTS:
                found = allantools.autocorr_noise_id(y[:, i], af, data_type="freq", dmin=0,
                                                     dmax=2)[0]  # fmt: skip
                alpha = int(min(max(round(found), ALPHA_RANGE[0]), ALPHA_RANGE[1]))
            try:
                edf = allantools.edf_greenhall(alpha=alpha, d=2, m=af, N=len(y),
                                               overlapping=True, modified=False)  # fmt: skip
                cis.append(allantools.confidence_interval(d, edf, ci))
            except (AssertionError, ValueError, ZeroDivisionError, FloatingPointError):
                edf = max(1.0, (len(y) - 2 * af + 1) / (2.0 * af))  # white-noise estimate
                cis.append(allantools.confidence_interval(d, edf, ci))
                fallbacks.append(f"axis {'xyz'[i]} at {tau:g} s")
        per_axis.append((np.asarray(taus), np.asarray(dev), np.asarray(cis, float)))
    notes = (f"Allan deviation intervals from the white-noise degrees of freedom (the noise type"
             f" could not be used) at {', '.join(fallbacks)}",) if fallbacks else ()  # fmt: skip
    taus = per_axis[0][0]
    rows = range(len(taus))
    return AllanDeviation(
        tuple(float(t) for t in taus),
        tuple(tuple(float(a[1][k]) for a in per_axis) for k in rows),
        tuple(tuple(float(a[2][k, 0]) for a in per_axis) for k in rows),
        tuple(tuple(float(a[2][k, 1]) for a in per_axis) for k in rows),
        rate,
        notes,
    )


DRIFT_BINS = 100
"""The record is averaged over this many stretches for the drift's fit."""


def offset_drift(t_s: Array, offsets_nt: Array) -> Drift:
    """The drift per axis over 12 h (nT) and its sigma: a line fitted to the record's
    :data:`DRIFT_BINS` stretch averages with the offset's noise (white, flicker and random walk,
    :func:`~rig.characterization.offset_noise.fit_bins`) estimated alongside."""
    t = np.asarray(t_s, float)
    y = np.asarray(offsets_nt, float)
    grid, rate = on_uniform_grid(t, y)  # once for the three axes
    bins, idx = contiguous_bins(t, DRIFT_BINS)
    design = np.column_stack([np.ones(len(idx)), bins.centre_s - float(np.mean(t))])
    slopes, sigmas, noise = [], [], []
    for i in range(3):
        means = np.array([float(np.mean(y[j, i])) for j in idx])
        fit = fit_bins(design, means, bins, hadamard_noise(grid[:, i], rate))
        slopes.append(float(fit.coef[1]) * TWELVE_HOURS_S)
        sigmas.append(float(fit.sigma[1]) * TWELVE_HOURS_S)
        noise.append(fit.noise)
    return Drift(tuple(slopes), tuple(sigmas), float(t[-1] - t[0]), tuple(noise))
