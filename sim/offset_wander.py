"""How a magnetometer's offset wanders: a linear drift, a random walk and flicker (1/f) noise.

The truth behind an Allan deviation: white noise (the reading's own) falls as tau^-1/2, flicker
is a floor, a random walk rises as tau^1/2 and a drift as tau. Flicker is the sum of first-order
Gauss-Markov processes with time constants a decade apart and equal variance (an Allan deviation
flat within 0.98-1.04 of its value from 10 s to 3000 s: :data:`FLICKER_GAIN`). Every term is a function of the
simulated time: the wire protocols sample it in real time, a test drives it over 12 simulated
hours in seconds (:meth:`OffsetWander.values`), and :func:`allan_variance_truth` is its exact
Allan variance for samples at a given rate (the test's truth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

import timebase

Array = npt.NDArray[np.float64]

FLICKER_TAUS_S = (0.3, 3.0, 30.0, 300.0, 3000.0, 30000.0)
"""Time constants of the Gauss-Markov processes whose sum is the flicker noise (s)."""
_TAUS_S = np.array(FLICKER_TAUS_S)
FLICKER_GAIN = 1.2807
"""Per-process standard deviation over the flicker floor: the sum of processes a decade apart,
each with this, has an Allan deviation of 1.00 at 100 s, 0.98-1.04 from 10 s to 3000 s
(:func:`allan_variance_truth` at 1 Hz)."""


@dataclass(frozen=True)
class WanderSpec:
    """The offset's wander per axis: drift (nT/h), random walk (nT/sqrt(h)), flicker floor
    (nT, the Allan deviation's flat part)."""

    drift_nt_per_h: tuple[float, ...] = (0.0, 0.0, 0.0)
    walk_nt_per_sqrt_h: float = 0.0
    flicker_nt: float = 0.0

    @property
    def active(self) -> bool:
        """Any wander at all."""
        return any(self.drift_nt_per_h) or self.walk_nt_per_sqrt_h > 0 or self.flicker_nt > 0


class OffsetWander:
    """The wander (uT, per axis) at simulated times, from ``t0_s`` on; seeded. Times asked for
    out of order get the latest value (two sampler threads)."""

    def __init__(self, spec: WanderSpec, seed: int, t0_s: float = 0.0) -> None:
        self.spec = spec
        self._rng = np.random.default_rng([seed, 37])
        self._t = t0_s
        self._t0 = t0_s
        self._walk = np.zeros(3)  # nT
        self._gm = np.zeros((len(FLICKER_TAUS_S), 3))  # nT, stationary start
        sigma = FLICKER_GAIN * spec.flicker_nt
        if sigma > 0:
            self._gm = sigma * self._rng.standard_normal(self._gm.shape)
        self._lock = timebase.Lock()

    def value(self, t_s: float) -> Array:
        """The wander at ``t_s`` (uT, 3)."""
        with self._lock:
            if t_s > self._t:
                self._advance(t_s - self._t)
                self._t = t_s
            return self._now()

    def values(self, t_s: Array) -> Array:
        """The wander at evenly spaced times ``t_s`` after the last one asked for (uT, (N, 3)):
        the same process, computed as whole arrays (12 h at 20 Hz in about a second)."""
        t = np.asarray(t_s, float)
        dt = float(t[1] - t[0]) if t.size > 1 else float(t[0] - self._t)
        if t.size > 1 and not np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-9):
            raise ValueError("values() needs evenly spaced times; use value() for others")
        if not (t[0] > self._t and dt > 0):
            raise ValueError("values() needs times after the last one asked for")
        from scipy.signal import lfilter

        s = self.spec
        with self._lock:
            steps = np.diff(np.concatenate([[self._t], t]))
            walk = np.zeros((t.size, 3))
            if s.walk_nt_per_sqrt_h > 0:
                q = s.walk_nt_per_sqrt_h**2 / 3600.0
                walk = self._walk + np.cumsum(np.sqrt(q * steps)[:, None]
                                              * self._rng.standard_normal((t.size, 3)), axis=0)  # fmt: skip
                self._walk = walk[-1].copy()
            flicker = np.zeros((t.size, 3))
            if s.flicker_nt > 0:
                sigma = FLICKER_GAIN * s.flicker_nt
                first = steps[0]
                for k, tau in enumerate(FLICKER_TAUS_S):
                    a = math.exp(-dt / tau)
                    n = self._rng.standard_normal((t.size, 3))
                    e = sigma * math.sqrt(1 - a * a) * n
                    a0 = math.exp(-first / tau)  # from the last value: the first step may differ
                    e[0] = a0 * self._gm[k] + sigma * math.sqrt(1 - a0 * a0) * n[0]
                    gm = lfilter([1.0], [1.0, -a], e, axis=0)
                    flicker += gm
                    self._gm[k] = gm[-1]
            drift = np.asarray(s.drift_nt_per_h)[None, :] * (t[:, None] - self._t0) / 3600.0
            self._t = float(t[-1])
            return np.asarray(1e-3 * (drift + walk + flicker))

    def _now(self) -> Array:
        drift = np.asarray(self.spec.drift_nt_per_h) * (self._t - self._t0) / 3600.0
        return np.asarray(1e-3 * (drift + self._walk + self._gm.sum(axis=0)))

    def _advance(self, dt_s: float) -> None:
        """Exact transition over ``dt_s``: the walk's variance grows by q dt, each Gauss-Markov
        process decays by exp(-dt/tau) with the innovation that keeps its variance."""
        s = self.spec
        if s.walk_nt_per_sqrt_h > 0:
            q = s.walk_nt_per_sqrt_h**2 / 3600.0  # nT^2/s
            self._walk += math.sqrt(q * dt_s) * self._rng.standard_normal(3)
        if s.flicker_nt > 0:  # every process at once (the same draws, in the same order)
            a = np.exp(-dt_s / _TAUS_S)[:, None]
            innovation = self._rng.standard_normal(self._gm.shape)
            self._gm = a * self._gm + FLICKER_GAIN * s.flicker_nt * np.sqrt(1 - a * a) * innovation


def allan_variance_truth(spec: WanderSpec, white_nt: float, rate_hz: float, tau_s: float,
                         axis: int = 0) -> float:  # fmt: skip
    """The exact Allan variance (nT^2) at ``tau_s`` of samples at ``rate_hz`` of the wander
    plus white noise ``white_nt`` per sample: from the autocovariance of each stationary term
    through the Allan filter's own autocorrelation, the random walk's and drift's in closed
    form (discrete random walk: v (2m^2 + 1) / 6m)."""
    dt = 1.0 / rate_hz
    m = max(1, round(tau_s * rate_hz))
    lags = np.arange(0, 2 * m)
    c = np.where(lags <= m, 2 * m - 3 * lags, -(2 * m - lags)).astype(float)
    weights = np.concatenate([[c[0]], 2 * c[1:]])  # lags +-j
    cov = np.zeros(lags.size)
    cov[0] += white_nt**2
    sigma = FLICKER_GAIN * spec.flicker_nt
    for tau in FLICKER_TAUS_S:
        cov += sigma**2 * np.exp(-lags * dt / tau)
    avar = float(weights @ cov) / (2.0 * m * m)
    v = spec.walk_nt_per_sqrt_h**2 / 3600.0 * dt
    avar += v * (2 * m * m + 1) / (6 * m)
    drift = spec.drift_nt_per_h[axis] / 3600.0
    return avar + 0.5 * (drift * m * dt) ** 2
