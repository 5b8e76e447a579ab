"""A magnetometer's offset against its temperature on warming and on cooling: the temperature
coefficient and the thermal hysteresis (the offset warming less the offset cooling at the same
temperature), each with a sigma.

Each sample is put on a branch by the thermometer's own history: a play operator of half-width
``reversal_k`` on the measured temperature gives +1 once the temperature has risen ``1.5
reversal_k`` from its last turning point (and while it stays within ``reversal_k / 2`` of the
highest since: a plateau's thermometer noise is not a reversal), -1 likewise on the way down,
and the samples between (just after a reversal, where a sensor moves from one branch to the
other) are left out. The
offset is then fitted per axis as ``c0 + c1 dT + c2 dT^2 + sum_j k_j I_j + d t + h/2 s``: a
smooth temperature dependence, a bias per load current (a heater's current can bias the sensor,
and it is on while warming: a plateau held at the same current on both branches is what tells
``k`` from ``h``), the offset's drift over the campaign (hours: a drift would otherwise pass for
hysteresis, the branches coming at different times; cycling twice separates them) and the
hysteresis ``h``. The samples are averaged into bins, runs of consecutive samples on one branch
at one current spanning at most ``bin_k`` and ``bin_s``, and the bins fitted by generalized
least squares with the offset's noise (white, flicker and random walk) estimated alongside, as
for the stability step's drift (:func:`rig.characterization.offset_noise.fit_bins`): the
offset's slow wander between a warming and a cooling plateau an hour apart is most of a
hysteresis's sigma, which a white-noise fit put at half the spread of its estimates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rig.characterization.offset_noise import Bins, fit_bins, joint_z

Array = npt.NDArray[np.float64]

DETECTED_SIGMA = 3.0
MIN_BINS = 6
MAX_BINS = 300
"""Bins are widened until at most this many remain (the noise fit's work grows with the cube
of their number; each bin's mean regressors keep the fit exact however wide they are)."""


@dataclass(frozen=True)
class ThermalFit:
    """Per axis the hysteresis (nT, warming less cooling), the temperature coefficient at the
    reference temperature (nT/K) and the drift (nT/h), each with 1-sigma; the hysteresis's significance (the three
    axes' chi-square as an equivalent Gaussian sigma); the bins fitted (for the plot: mean
    temperature C, branch +-1, mean offset nT per axis, samples)."""

    hysteresis_nt: tuple[float, ...]
    hysteresis_sigma_nt: tuple[float, ...]
    tempco_nt_per_k: tuple[float, ...]
    tempco_sigma_nt_per_k: tuple[float, ...]
    drift_nt_per_h: tuple[float, ...]
    drift_sigma_nt_per_h: tuple[float, ...]
    significance_sigma: float
    reference_c: float
    bin_temperature_c: tuple[float, ...]
    bin_branch: tuple[int, ...]
    bin_offset_nt: tuple[tuple[float, ...], ...]
    bin_samples: tuple[int, ...]

    @property
    def detected(self) -> bool:
        """A hysteresis at :data:`DETECTED_SIGMA` or more."""
        return self.significance_sigma >= DETECTED_SIGMA


def branches(temperature_c: Array, reversal_k: float) -> Array:
    """+1 (warming), -1 (cooling) or 0 (within ``1.5 reversal_k`` of a turning point) per sample
    of ``temperature_c`` (C, in time order)."""
    out = np.zeros(len(temperature_c))
    p = float(temperature_c[0]) if len(temperature_c) else 0.0
    for i, t in enumerate(temperature_c):
        if t > p + reversal_k:
            p = float(t) - reversal_k
        elif t < p - reversal_k:
            p = float(t) + reversal_k
        s = (t - p) / reversal_k  # +1 while being dragged up, -1 down
        out[i] = 1.0 if s > 0.5 else -1.0 if s < -0.5 else 0.0
    return out


def fit_thermal(time_s: Array, temperature_c: Array, offsets_nt: Array,
                currents_a: Array | None = None, reversal_k: float = 1.0, bin_k: float = 0.5,
                bin_s: float = 60.0, reference_c: float | None = None) -> ThermalFit:  # fmt: skip
    """Fit the offsets (N x 3, nT) against the temperatures (N, C) and the load currents (N x J,
    A) at times ``time_s`` (N, s, increasing); ``reference_c`` (default the mean bin temperature)
    is where the temperature coefficient is given. ValueError when a branch is missing or the
    terms cannot be told apart."""
    temp = np.asarray(temperature_c, float)
    s = branches(temp, reversal_k)
    cur = np.zeros((len(temp), 0)) if currents_a is None else np.asarray(currents_a, float)
    hours = (np.asarray(time_s, float) - float(np.mean(time_s))) / 3600.0
    keep = s != 0
    if not (np.any(s > 0) and np.any(s < 0)):
        raise ValueError("the temperature must rise and fall by more than twice reversal_k each:"
                         " no warming or no cooling branch")  # fmt: skip
    t_keep = np.asarray(time_s, float)[keep]
    bins = _bins(temp[keep], s[keep], np.asarray(offsets_nt, float)[keep], cur[keep], t_keep,
                 bin_k, bin_s)  # fmt: skip
    t_bin, s_bin, y_bin, n_bin, start_s, end_s, index = bins
    t0 = float(np.mean(t_bin)) if reference_c is None else float(reference_c)
    # each bin's mean regressors (exact for a model linear in them, however wide the bin)
    xs = _design(temp[keep] - t0, cur[keep], hours[keep], s[keep])
    x = np.column_stack([np.bincount(index, weights=col) / n_bin for col in xs.T])
    if len(t_bin) < max(MIN_BINS, x.shape[1] + 3) or np.linalg.matrix_rank(x) < x.shape[1]:
        raise ValueError(f"{len(t_bin)} temperature bins cannot separate the hysteresis from the"
                         " temperature and current dependence: hold a temperature on both"
                         " branches at the same heater current")  # fmt: skip
    spans = Bins(start_s, end_s, n_bin, 1.0 / float(np.median(np.diff(t_keep))))
    h, hs, c, cs, d, ds = [], [], [], [], [], []
    for axis in range(3):
        fit = fit_bins(x, y_bin[:, axis], spans)
        h.append(float(fit.coef[-1]))
        hs.append(float(fit.sigma[-1]))
        c.append(float(fit.coef[1]))
        cs.append(float(fit.sigma[1]))
        d.append(float(fit.coef[-2]))
        ds.append(float(fit.sigma[-2]))
    chi2 = float(np.sum((np.asarray(h) / np.asarray(hs)) ** 2))
    z = joint_z(chi2, 3)
    return ThermalFit(tuple(h), tuple(hs), tuple(c), tuple(cs), tuple(d), tuple(ds), z, t0,
                      tuple(float(v) for v in t_bin), tuple(int(v) for v in s_bin),
                      tuple(tuple(float(v) for v in r) for r in y_bin),
                      tuple(int(v) for v in n_bin))  # fmt: skip


def _design(dt: Array, currents: Array, hours: Array, branch: Array) -> Array:
    """The regressors: 1, dT, dT^2, each current, time (h), half the branch."""
    return np.column_stack([np.ones_like(dt), dt, dt * dt, *currents.T, hours, 0.5 * branch])


def _bins(
    temp: Array, s: Array, y: Array, cur: Array, t_s: Array, bin_k: float, bin_s: float
) -> tuple[Array, Array, Array, Array, Array, Array, npt.NDArray[np.intp]]:
    """Means over runs of consecutive samples on one branch at one set of currents, each ending
    when the temperature has moved ``bin_k`` (K) from its first sample's, after ``bin_s`` (s) or
    at a gap in the samples (so each bin is one stretch of the record, as the noise model's
    covariance wants); both doubled until at most :data:`MAX_BINS` bins remain. Returns the mean
    temperature, branch and offsets, the samples, each bin's first and last sample's time (s)
    and each sample's bin."""
    index = _run_index(temp, s, cur, t_s, bin_k, bin_s)
    while index[-1] + 1 > MAX_BINS:
        bin_k, bin_s = 2.0 * bin_k, 2.0 * bin_s
        index = _run_index(temp, s, cur, t_s, bin_k, bin_s)
    count = np.bincount(index).astype(float)

    def mean(v: Array) -> Array:
        return np.asarray(np.bincount(index, weights=v) / count, float)

    y_mean = np.column_stack([mean(y[:, k]) for k in range(y.shape[1])])
    first = np.full(len(count), np.inf)
    last = np.full(len(count), -np.inf)
    np.minimum.at(first, index, t_s)
    np.maximum.at(last, index, t_s)
    return mean(temp), np.sign(mean(s)), y_mean, count, first, last, index


def _run_index(temp: Array, s: Array, cur: Array, t_s: Array, bin_k: float,
               bin_s: float) -> npt.NDArray[np.intp]:  # fmt: skip
    """The bin of each sample (see :func:`_bins`): 0, 1, ... in time order."""
    step = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
    index = np.zeros(len(temp), dtype=np.intp)
    k, first = 0, 0
    for i in range(1, len(temp)):
        if (s[i] != s[first] or abs(temp[i] - temp[first]) >= bin_k
                or t_s[i] - t_s[first] >= bin_s or t_s[i] - t_s[i - 1] > 2.5 * step
                or (cur.shape[1] and np.any(np.abs(cur[i] - cur[first]) > 1e-3))):  # fmt: skip
            k, first = k + 1, i
        index[i] = k
    return index
