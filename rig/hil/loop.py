"""The loop both runs share, the closed-loop one (the cage and the DUT) and the all-software one
(a model magnetometer): every tick the body-frame field goes out, every control period the flight
software turns the period's readings into a dipole, and Basilisk moves the spacecraft one tick on.

Order within tick ``k`` at loop time ``t_k = k / rate_hz``: the readings dated up to ``t_k``
come in; when one of them is dated at or after the end of the current control period, the period
is closed and the flight software gets the mean of its readings (so a period ends with the
reading that closes it, at the first tick after it, not up to a period later); the dynamics step
to ``t_(k+1)`` with the dipole held; the field in the body frame at ``t_(k+1)`` (the new
attitude, the orbit's inertial field then) goes to the cage at once, so the command a reading
causes follows it by at most a tick. The frames: the body frame is the cage frame (the DUT
mounted as on the spacecraft, its axes along the cage's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from rig.hil.dynamics import BasiliskDynamics, Spacecraft
from rig.hil.flight_software import FlightSoftware

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class OrbitField:
    """The true field along the orbit in the inertial frame: ``field_ut[i]`` (uT) at orbit time
    ``t_orbit_s[i]`` (s), reached at loop time ``t / time_scale`` (an orbit replayed faster than
    the attitude turns, so that the field's direction changes within a test's minutes)."""

    t_orbit_s: Array
    field_ut: Array
    time_scale: float = 1.0

    def at(self, t_s: float) -> Array:
        """The inertial field (uT) at loop time ``t_s`` (s), interpolated."""
        t = t_s * self.time_scale
        return np.array([np.interp(t, self.t_orbit_s, self.field_ut[:, i]) for i in range(3)])

    @property
    def peak_ut(self) -> float:
        """The largest field magnitude along the orbit (uT): any direction in the body."""
        return float(np.max(np.linalg.norm(self.field_ut, axis=1)))


@dataclass(frozen=True)
class LoopPlan:
    """``rate_hz``: ticks per second (the field's updates and the dynamics' steps);
    ``control_hz``: the flight software's periods per second (a period closes with the
    first reading dated at or after its end, at the tick after that reading);
    ``duration_s``: the longest the loop runs (s); ``until_deg_s``: the body rate (deg/s) at
    which the spacecraft counts as detumbled and the loop ends (0: never)."""

    rate_hz: float
    control_hz: float
    duration_s: float
    until_deg_s: float = 0.0

    @property
    def ticks(self) -> int:
        return round(self.duration_s * self.rate_hz)


@dataclass
class Tick:
    """One tick as it went: loop time (s), attitude (MRP), body rate (deg/s), the body field the
    cage was asked for (uT), the flight software's input when a period ended (uT, else None) and
    the dipole held over the tick (A m^2)."""

    t_s: float
    mrp: Array
    rate_deg_s: Array
    field_ut: Array
    reading_ut: Array | None
    dipole_am2: Array


@dataclass
class Loop:
    """The shared loop: :meth:`field_now` (the field to make at this tick), :meth:`reading` for
    each magnetometer reading as it comes, :meth:`advance` to end the tick."""

    craft: Spacecraft
    plan: LoopPlan
    orbit: OrbitField
    software: FlightSoftware
    k: int = 0
    dipole: Array = field(default_factory=lambda: np.zeros(3))
    detumbled_at_s: float | None = None
    _readings: list[Array] = field(default_factory=list)
    _newest_s: float = -math.inf
    _period_end_s: float = 0.0
    _dynamics: BasiliskDynamics | None = None

    def __post_init__(self) -> None:
        self._dynamics = BasiliskDynamics(self.craft, 1.0 / self.plan.rate_hz)

    @property
    def t_s(self) -> float:
        return self.k / self.plan.rate_hz

    def field_now(self) -> Array:
        """The field in the body frame now (uT): the attitude's [BN] times the orbit's field."""
        assert self._dynamics is not None
        return np.asarray(self._dynamics.body_from_inertial() @ self.orbit.at(self.t_s))

    def reading(self, field_ut: Array, t_s: float) -> None:
        """One magnetometer reading (uT, body frame) dated ``t_s`` (s of the loop)."""
        self._readings.append(np.asarray(field_ut, float))
        self._newest_s = max(self._newest_s, t_s)

    def advance(self, field_ut: Array) -> Tick:
        """End tick ``k`` (``field_ut``: the field the cage holds over it): the flight software
        when a reading has closed the control period, then the dynamics one tick on. The tick as
        it went."""
        assert self._dynamics is not None
        sigma, omega = self._dynamics.state()
        rate = np.degrees(omega)
        until = self.plan.until_deg_s
        if self.detumbled_at_s is None and until > 0 and float(np.linalg.norm(rate)) <= until:
            self.detumbled_at_s = self.t_s
        mean = None
        if self._readings and self._newest_s >= self._period_end_s:
            mean = np.mean(self._readings, axis=0)
            self._readings.clear()
            self.dipole = np.asarray(self.software.dipole(mean, self.t_s), float)
            period = 1.0 / self.plan.control_hz
            while self._period_end_s <= self._newest_s:
                self._period_end_s += period
        tick = Tick(self.t_s, sigma, rate, np.asarray(field_ut, float), mean, self.dipole.copy())
        self._dynamics.step(self.dipole, self.orbit.at(self.t_s))
        self.k += 1
        return tick

    @property
    def done(self) -> bool:
        """The loop has run its course: detumbled or out of time."""
        return self.detumbled_at_s is not None or self.k >= self.plan.ticks


def software_only(craft: Spacecraft, plan: LoopPlan, orbit: OrbitField, software: FlightSoftware,
                  noise_ut: float, sample_hz: float,
                  seed: int = 0) -> tuple[list[Tick], float | None]:  # fmt: skip
    """The same scenario with a model magnetometer in place of the cage and the DUT: the field of
    each tick held until the next (as the cage holds a set-point), sampled at ``sample_hz`` with
    white noise of ``noise_ut`` (uT, each axis). (ticks, detumble time s or None)."""
    loop = Loop(craft, plan, orbit, software)
    rng = np.random.default_rng(seed)
    ticks: list[Tick] = []
    period = 1.0 / sample_hz
    next_sample = 0.5 * period
    held = loop.field_now()  # the cage's starting field, made before the loop starts
    while not loop.done:
        while next_sample <= loop.t_s + 1e-12:  # sampled while the last command held
            loop.reading(held + rng.normal(0.0, noise_ut, 3), next_sample)
            next_sample += period
        tick = loop.advance(held)
        held = loop.field_now()  # commanded at once, held until the next tick
        ticks.append(tick)
    return ticks, loop.detumbled_at_s


def percentile_ms(values_s: list[float], q: float) -> float:
    """The ``q``-th percentile (0-100) of ``values_s`` (s) in ms; NaN without values."""
    finite = [v for v in values_s if math.isfinite(v)]
    return float(np.percentile(finite, q) * 1000.0) if finite else math.nan
