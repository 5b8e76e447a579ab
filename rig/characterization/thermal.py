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
hysteresis ``h``. The samples are averaged into bins per branch, temperature, current and
``bin_s`` of time, and the bins fitted by generalized least squares with the covariance the
residuals' own noise gives them (white, flicker and random walk from their Allan variance, as
the stability step's drift sigma): the offset's slow wander between a warming and a cooling
plateau an hour apart is most of a hysteresis's sigma, which a white-noise fit put at half the
spread of its estimates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import stats

from rig.characterization.stability import noise_model, on_uniform_grid

Array = npt.NDArray[np.float64]

DETECTED_SIGMA = 3.0
MIN_BINS = 6


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
    bins = _bins(temp[keep], s[keep], np.asarray(offsets_nt, float)[keep], cur[keep],
                 hours[keep], bin_k, bin_s / 3600.0)  # fmt: skip
    t_bin, s_bin, y_bin, i_bin, h_bin, n_bin = bins
    t0 = float(np.mean(t_bin)) if reference_c is None else float(reference_c)
    dt = t_bin - t0
    x = _design(dt, i_bin, h_bin, s_bin)
    if len(t_bin) < max(MIN_BINS, x.shape[1] + 3) or np.linalg.matrix_rank(x) < x.shape[1]:
        raise ValueError(f"{len(t_bin)} temperature bins cannot separate the hysteresis from the"
                         " temperature and current dependence: hold a temperature on both"
                         " branches at the same heater current")  # fmt: skip
    xs = _design(temp[keep] - t0, cur[keep], hours[keep], s[keep])
    h, hs, c, cs, d, ds = [], [], [], [], [], []
    for axis in range(3):
        y = np.asarray(offsets_nt, float)[keep, axis]
        first = np.linalg.lstsq(x * np.sqrt(n_bin)[:, None], y_bin[:, axis] * np.sqrt(n_bin),
                                rcond=None)[0]  # fmt: skip
        cov_bins = _bin_covariance(np.asarray(time_s, float)[keep], y - xs @ first,
                                   3600.0 * h_bin + float(np.mean(time_s)), n_bin)  # fmt: skip
        beta, cov = _gls(x, y_bin[:, axis], cov_bins)
        sig = np.sqrt(np.diag(cov))
        h.append(float(beta[-1]))
        hs.append(float(sig[-1]))
        c.append(float(beta[1]))
        cs.append(float(sig[1]))
        d.append(float(beta[-2]))
        ds.append(float(sig[-2]))
    chi2 = float(np.sum((np.asarray(h) / np.asarray(hs)) ** 2))
    p = float(stats.chi2.sf(chi2, 3))
    z = float(stats.norm.isf(p / 2.0)) if p > 0 else math.inf
    return ThermalFit(tuple(h), tuple(hs), tuple(c), tuple(cs), tuple(d), tuple(ds), z, t0,
                      tuple(float(v) for v in t_bin), tuple(int(v) for v in s_bin),
                      tuple(tuple(float(v) for v in r) for r in y_bin),
                      tuple(int(v) for v in n_bin))  # fmt: skip


def _design(dt: Array, currents: Array, hours: Array, branch: Array) -> Array:
    """The regressors: 1, dT, dT^2, each current, time (h), half the branch."""
    return np.column_stack([np.ones_like(dt), dt, dt * dt, *currents.T, hours, 0.5 * branch])


def _bin_covariance(t_s: Array, resid_nt: Array, t_bin_s: Array, n_bin: Array) -> Array:
    """The covariance of the bins' mean offsets (nT^2) from the residuals' own noise (white,
    flicker and random walk fitted to their Allan variance, :func:`noise_model`): white over each
    bin's samples, the random walk's ``q min(t_i, t_j)``, and flicker as Gauss-Markov processes a
    decade apart whose Allan variance is the flicker's flat one (:func:`_flicker_kernel`)."""
    grid, rate = on_uniform_grid(t_s, np.column_stack([resid_nt] * 3))
    a, b, c = noise_model(grid[:, 0], rate, 0.0)
    a = max(a, 1e-6 * float(np.var(resid_nt)) / rate)  # a white part, however small: invertible
    since = t_bin_s - float(t_s[0])
    lag = np.abs(np.subtract.outer(since, since))
    record = float(t_s[-1] - t_s[0])
    cov = (np.diag(a * rate / n_bin) + 3.0 * c * np.minimum.outer(since, since)
           + b * _flicker_kernel(lag, record))  # fmt: skip
    return np.asarray(cov, float)


def _flicker_kernel(lag_s: Array, record_s: float) -> Array:
    """The autocovariance (per nT^2 of flat Allan variance) of flicker noise over ``lag_s``: the
    sum of Gauss-Markov processes with time constants a decade apart from 1 s to ten records,
    scaled so that their Allan variance at a hundredth of the record is 1."""
    taus = 10.0 ** np.arange(0.0, np.log10(10.0 * record_s) + 1.0)
    probe = max(record_s / 100.0, 1.0)
    x = probe / taus
    # an OU process of unit variance: AVAR(tau) = (T/tau)^2 (4 e^-x - e^-2x + 2x - 3), x = tau/T
    avar = float(np.sum((4.0 * np.exp(-x) - np.exp(-2.0 * x) + 2.0 * x - 3.0) / x**2))
    return np.asarray(sum(np.exp(-lag_s / t) for t in taus) / avar, float)


def _gls(x: Array, y: Array, cov: Array) -> tuple[Array, Array]:
    """Generalized least squares: the coefficients and their covariance."""
    chol = np.linalg.cholesky(cov)
    xw = np.linalg.solve(chol, x)
    yw = np.linalg.solve(chol, y)
    beta = np.linalg.lstsq(xw, yw, rcond=None)[0]
    return np.asarray(beta, float), np.asarray(np.linalg.inv(xw.T @ xw), float)


def _bins(temp: Array, s: Array, y: Array, cur: Array, hours: Array, bin_k: float,
          bin_h: float) -> tuple[Array, Array, Array, Array, Array, Array]:  # fmt: skip
    """Means per (branch, temperature bin, currents, time bin): temperature, branch, offsets,
    currents, time (h), samples."""
    keys = np.column_stack([s, np.floor(temp / bin_k), np.round(cur, 3), np.floor(hours / bin_h)])
    _, index = np.unique(keys, axis=0, return_inverse=True)
    index = index.ravel()
    count = np.bincount(index).astype(float)

    def mean(v: Array) -> Array:
        return np.asarray(np.bincount(index, weights=v) / count, float)

    y_mean = np.column_stack([mean(y[:, k]) for k in range(y.shape[1])])
    i_mean = np.column_stack([mean(cur[:, k]) for k in range(cur.shape[1])]) if cur.shape[1] else (
        np.zeros((len(count), 0)))  # fmt: skip
    return mean(temp), np.sign(mean(s)), y_mean, i_mean, mean(hours), count
