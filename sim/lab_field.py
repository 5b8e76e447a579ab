"""The lab's own field around the cage: what a city lab adds to the coils' field, by position.

``B(r, t) = B0 + G r + diurnal(t) + flicker(t) + sum of traffic dipoles(r, t)`` (uT), every term a
deterministic function of the time since the simulator started (seeded), so any thread may
evaluate any time in any order:

* ``G`` (uT/m): a static gradient (steel in the building), checked curl- and divergence-free;
* diurnal: one sinusoid per axis over ``diurnal_period_s`` (the ionosphere's daily variation);
* flicker: 1/f noise of rms ``flicker_ut`` per axis between :data:`FLICKER_BAND_HZ`, as equal
  power in each of :data:`FLICKER_BINS` log-spaced bins (a 1/f spectrum has equal power per
  decade), one sinusoid per bin at a random frequency within it and a random phase;
* traffic: vehicles parking or passing on a street ``traffic_distance_m`` from the cage, each a
  magnetic dipole that appears (2 s ramp), stays an exponential time of mean
  ``traffic_duration_s`` and leaves; arrivals Poisson at ``traffic_rate_per_h``, moments sized to
  give about ``traffic_field_ut`` at the cage centre. Being near, they differ between the cage and
  a reference outside it, which is why a reference's offset to the cage is fitted, not assumed.

The distant terms (diurnal, flicker) are the same everywhere; the gradient and the traffic are not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from sim.config import AmbientConfig, SimConfigError

Array = npt.NDArray[np.float64]

FLICKER_BAND_HZ = (1e-5, 1.0)
FLICKER_BINS = 300
TRAFFIC_RAMP_S = 2.0
"""A vehicle's field rises and falls linearly over this time."""
DAY_S = 86400.0
MU0_OVER_4PI_UT_M_PER_A = 0.1
"""mu0 / 4 pi in uT m / A: a dipole of m A m^2 gives 0.1 m / r^3 uT on its axis (times 2)."""


def check_gradient(g_ut_per_m: Array) -> None:
    """A static field outside its sources is curl- and divergence-free: ``G`` symmetric and
    traceless (to 1e-9 uT/m); SimConfigError naming the fix otherwise."""
    if abs(float(np.trace(g_ut_per_m))) > 1e-9 or np.abs(g_ut_per_m - g_ut_per_m.T).max() > 1e-9:
        raise SimConfigError(
            "ambient.gradient_ut_per_m must be symmetric with zero trace (a field with no sources"
            " in the room: curl and divergence zero)"
        )


def dipole_field_ut(moment_a_m2: Array, source_m: Array, points_m: Array) -> Array:
    """Field (uT, (N, 3)) of a point dipole ``moment`` at ``source`` seen at ``points`` ((N, 3))."""
    r = points_m - source_m
    dist = np.linalg.norm(r, axis=1)[:, None]
    unit = r / dist
    m_r = (unit @ moment_a_m2)[:, None]
    return np.asarray(MU0_OVER_4PI_UT_M_PER_A * (3.0 * m_r * unit - moment_a_m2) / dist**3)


@dataclass(frozen=True)
class Vehicle:
    """One traffic event: it arrives at ``start_s``, stays ``stay_s`` (after its ramp), a dipole
    of ``moment_a_m2`` at ``source_m``."""

    start_s: float
    stay_s: float
    source_m: Array
    moment_a_m2: Array

    def weight(self, t_s: float) -> float:
        """0 before and after, 1 while parked, linear over the ramps."""
        rise = (t_s - self.start_s) / TRAFFIC_RAMP_S
        fall = (self.start_s + TRAFFIC_RAMP_S + self.stay_s + TRAFFIC_RAMP_S - t_s) / TRAFFIC_RAMP_S
        return float(min(1.0, max(0.0, rise), max(0.0, fall)))


class LabField:
    """The lab field of an ``[ambient]`` table (seeded) at positions and times since start."""

    def __init__(self, cfg: AmbientConfig, seed: int) -> None:
        self.cfg = cfg
        self.seed = seed
        self.gradient = np.array(cfg.gradient_ut_per_m, float)
        check_gradient(self.gradient)
        rng = np.random.default_rng([seed, 101])
        self._diurnal_phase = rng.uniform(0, 2 * np.pi, 3)
        edges = np.geomspace(*FLICKER_BAND_HZ, FLICKER_BINS + 1)
        self._flicker_hz = np.exp(
            rng.uniform(np.log(edges[:-1]), np.log(edges[1:]), (3, FLICKER_BINS))
        )
        self._flicker_phase = rng.uniform(0, 2 * np.pi, (3, FLICKER_BINS))
        self._flicker_amp = cfg.flicker_ut * math.sqrt(2.0 / FLICKER_BINS)
        self.temperature_phase = float(rng.uniform(0, 2 * np.pi))
        self._diurnal_ut = np.array(cfg.diurnal_amplitude_ut)
        self._present: tuple[float, float, list[Vehicle]] = (0.0, 0.0, [])  # (from, to, who)

    def uniform_ut(self, t_s: float) -> Array:
        """The terms that are the same everywhere (diurnal, flicker) at ``t_s`` since start."""
        a = self.cfg
        b = self._diurnal_ut * np.sin(2 * np.pi * t_s / a.diurnal_period_s + self._diurnal_phase)
        if self._flicker_amp > 0:
            arg = 2 * np.pi * self._flicker_hz * t_s + self._flicker_phase
            b = b + self._flicker_amp * np.sin(arg).sum(axis=1)
        return np.asarray(b)

    def local_ut(self, t_s: float, positions_m: Array) -> Array:
        """The terms that depend on position (gradient, traffic), (N, 3) uT at ``positions``."""
        b = positions_m @ self.gradient.T
        for car in self.vehicles_at(t_s):
            b = b + car.weight(t_s) * dipole_field_ut(car.moment_a_m2, car.source_m, positions_m)
        return np.asarray(b)

    def vehicles_at(self, t_s: float) -> list[Vehicle]:
        """The vehicles present at ``t_s`` (arrived on that day or the day before)."""
        lo, hi, present = self._present
        if lo < t_s < hi:  # no vehicle came or went since the last time asked
            return present
        day = math.floor(t_s / DAY_S)
        present, lo, hi = [], day * DAY_S, (day + 1) * DAY_S
        for d in (day - 1, day):
            starts, ends, cars = _vehicles(self.cfg, self.seed, d)
            present += [cars[i] for i in np.flatnonzero((starts < t_s) & (t_s < ends))]
            edges = np.concatenate([starts, ends])
            lo = max(lo, float(edges[edges <= t_s].max(initial=lo)))
            hi = min(hi, float(edges[edges >= t_s].min(initial=hi)))
        self._present = (lo, hi, present)
        return present

    def lab_temperature_c(self, t_s: float) -> float:
        """The lab's temperature offset from its mean (K): the daily swing."""
        a = self.cfg
        return a.lab_temperature_swing_c * math.sin(
            2 * math.pi * t_s / a.diurnal_period_s + self.temperature_phase
        )


@lru_cache(maxsize=64)
def _vehicles(cfg: AmbientConfig, seed: int, day: int) -> tuple[Array, Array, list[Vehicle]]:
    """The vehicles arriving on one day (seeded by the day: the same whichever is asked first),
    with their arrival and departure times (s since start)."""
    if cfg.traffic_rate_per_h <= 0 or day < -1:
        return np.zeros(0), np.zeros(0), []
    rng = np.random.default_rng([seed, 102, day + 1])
    count = int(rng.poisson(cfg.traffic_rate_per_h * DAY_S / 3600.0))
    starts = np.sort(rng.uniform(0.0, DAY_S, count)) + day * DAY_S
    cars = []
    for start in starts:
        along = rng.uniform(-3.0, 3.0) * cfg.traffic_distance_m
        source = np.array([along, cfg.traffic_distance_m, 0.0])
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
        # sized for about traffic_field_ut at the centre were it abeam (log-normal spread)
        size = cfg.traffic_field_ut * cfg.traffic_distance_m**3 / MU0_OVER_4PI_UT_M_PER_A
        moment = size * float(np.exp(rng.normal(0.0, 0.5))) * direction
        stay = float(rng.exponential(cfg.traffic_duration_s))
        cars.append(Vehicle(float(start), stay, source, moment))
    starts = np.array([c.start_s for c in cars])
    ends = starts + 2.0 * TRAFFIC_RAMP_S + np.array([c.stay_s for c in cars])
    return starts, ends, cars
