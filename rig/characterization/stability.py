"""How a magnetometer's offset wanders: its Allan deviation with confidence intervals, and its
drift per 12 h with a sigma that holds for coloured noise.

The Allan deviation is the overlapping one of ``allantools`` (frequency-type data: each sample
is the offset, nT) on the samples put on a uniform grid; its confidence interval is allantools'
(the noise type identified from the lag-1 autocorrelation where at least 30 averaging times fit
in the record, the last one found beyond; Greenhall's equivalent degrees of freedom; 68 %). The drift is the least-squares slope of each axis. Its sigma cannot come from the
residuals' scatter (a random walk or flicker makes neighbouring residuals alike: a white-noise
sigma would be several times too small), so it comes from the noise itself: the Allan variance
with the drift taken out is fitted as ``a / tau + b + c tau`` (white, flicker, random walk) on the
well-determined averaging times, and the slope's sigma is that of the difference of the record's
two halves, ``2 sqrt(2 AVAR(T/2)) / T`` (for white noise 15 % above the least-squares slope's, for
a random walk 5 %: conservative, never too small).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

TWELVE_HOURS_S = 12 * 3600.0
CI_68 = math.erf(1.0 / math.sqrt(2.0))
"""The confidence of a 1-sigma interval (0.683)."""
MIN_SAMPLES = 32
NOISE_ID_POINTS = 30
"""The noise type is identified (lag-1 autocorrelation) where the record holds at least this
many averaging times; longer ones keep the last type found."""
MODEL_TAU_FRACTION = 0.1
"""The noise model is fitted on averaging times up to this fraction of the record (below it an
Allan deviation has at least a few degrees of freedom)."""


@dataclass(frozen=True)
class AllanDeviation:
    """Per averaging time (s) and axis the overlapping Allan deviation (nT) and its confidence
    interval (nT; 68 % unless asked otherwise), of samples at ``rate_hz``."""

    tau_s: tuple[float, ...]
    adev_nt: tuple[tuple[float, ...], ...]
    low_nt: tuple[tuple[float, ...], ...]
    high_nt: tuple[tuple[float, ...], ...]
    rate_hz: float

    def at(self, tau_s: float) -> tuple[float, ...]:
        """The deviation per axis at the averaging time nearest ``tau_s`` (nT)."""
        i = int(np.argmin(np.abs(np.log(np.asarray(self.tau_s)) - math.log(tau_s))))
        return self.adev_nt[i]


@dataclass(frozen=True)
class Drift:
    """Per axis the offset's drift over 12 h (nT) and its 1-sigma (nT), from a record of
    ``record_s`` seconds."""

    per_12h_nt: tuple[float, ...]
    sigma_nt: tuple[float, ...]
    record_s: float


def on_uniform_grid(t_s: Array, xyz: Array) -> tuple[Array, float]:
    """The samples interpolated onto a uniform grid at their median rate: (N, 3), rate (Hz)."""
    rate_hz = 1.0 / float(np.median(np.diff(t_s)))
    grid = np.arange(t_s[0], t_s[-1], 1.0 / rate_hz)
    return np.column_stack([np.interp(grid, t_s, xyz[:, i]) for i in range(3)]), rate_hz


def default_taus(n: int, rate_hz: float) -> Array:
    """1-2-5 averaging times from two samples up to a quarter of the record (s)."""
    top = n / rate_hz / 4.0
    decades = np.arange(math.floor(math.log10(2.0 / rate_hz)), math.ceil(math.log10(top)) + 1)
    taus = np.array([f * 10.0**d for d in decades for f in (1.0, 2.0, 5.0)])
    return taus[(taus >= 2.0 / rate_hz * (1 - 1e-6)) & (taus <= top)]


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
    for i in range(3):
        taus, dev, _, _ = allantools.oadev(y[:, i], rate=rate, data_type="freq", taus=wanted)
        alpha = 0  # white frequency noise until one is identified
        cis = []
        for tau, d in zip(taus, dev, strict=True):
            af = max(1, round(tau * rate))
            if len(y) // af >= NOISE_ID_POINTS:
                alpha = allantools.autocorr_noise_id(y[:, i], af, data_type="freq", dmin=0,
                                                     dmax=2)[0]  # fmt: skip
            edf = allantools.edf_greenhall(alpha=alpha, d=2, m=af, N=len(y), overlapping=True,
                                           modified=False)  # fmt: skip
            cis.append(allantools.confidence_interval(d, edf, ci))
        per_axis.append((np.asarray(taus), np.asarray(dev), np.asarray(cis, float)))
    taus = per_axis[0][0]
    rows = range(len(taus))
    return AllanDeviation(
        tuple(float(t) for t in taus),
        tuple(tuple(float(a[1][k]) for a in per_axis) for k in rows),
        tuple(tuple(float(a[2][k, 0]) for a in per_axis) for k in rows),
        tuple(tuple(float(a[2][k, 1]) for a in per_axis) for k in rows),
        rate,
    )


def noise_model(y_nt: Array, rate_hz: float, drift_nt_per_s: float) -> Array:
    """``(a, b, c)`` of ``AVAR(tau) = a / tau + b + c tau`` (nT^2; white, flicker, random walk,
    each at least 0) fitted to the Allan variance of one axis's offsets on a uniform grid at
    ``rate_hz`` (:func:`on_uniform_grid`) less the drift's ``(D tau)^2 / 2``
    on 1-2-5 averaging times up to :data:`MODEL_TAU_FRACTION` of the record, each weighted by
    its precision (an Allan variance over m samples of N is good to about sqrt(2 m / N)); a
    flicker or random-walk term its data do not show at 2 sigma is left out."""
    import allantools
    from scipy.optimize import nnls

    y, rate = np.asarray(y_nt, float), rate_hz
    record = len(y) / rate
    wanted = default_taus(len(y), rate)
    wanted = wanted[wanted <= max(MODEL_TAU_FRACTION * record, wanted[min(2, len(wanted) - 1)])]
    tau, dev, _, _ = allantools.oadev(y, rate=rate, data_type="freq", taus=wanted)
    avar = np.asarray(dev) ** 2 - 0.5 * (drift_nt_per_s * np.asarray(tau)) ** 2
    keep = avar > 0
    tau, avar = np.asarray(tau)[keep], avar[keep]
    # relative error of each Allan variance about sqrt(2 m / N): weight by its inverse
    weight = np.sqrt(len(y) / np.maximum(tau * rate, 1.0)) / avar
    design = np.column_stack([1.0 / tau, np.ones_like(tau), tau]) * weight[:, None]
    terms = [0, 1, 2]
    while True:  # a term not shown at 2 sigma is left out (its noise would be extrapolated)
        coef = np.zeros(3)
        coef[terms], _ = nnls(design[:, terms], weight * avar)
        cov = np.linalg.pinv(design[:, terms].T @ design[:, terms])
        weak = [k for j, k in enumerate(terms) if k > 0 and coef[k] < 2.0 * np.sqrt(cov[j, j])]
        if not weak:
            return coef
        terms.remove(max(weak))


def offset_drift(t_s: Array, offsets_nt: Array) -> Drift:
    """The least-squares drift per axis over 12 h (nT) and its sigma from the noise model."""
    t = np.asarray(t_s, float)
    y = np.asarray(offsets_nt, float)
    record = float(t[-1] - t[0])
    design = np.column_stack([np.ones_like(t), t - t.mean()])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    slope = coef[1]  # nT/s per axis
    grid, rate = on_uniform_grid(t, y)  # once for the three axes
    sigmas = []
    for i in range(3):
        a, b, c = noise_model(grid[:, i], rate, float(slope[i]))
        half = record / 2.0
        sigmas.append(2.0 * math.sqrt(2.0 * (a / half + b + c * half)) / record)
    return Drift(tuple(float(s * TWELVE_HOURS_S) for s in slope),
                 tuple(float(s * TWELVE_HOURS_S) for s in sigmas), record)  # fmt: skip
