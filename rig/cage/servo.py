"""The ambient servo: hold a field at the DUT against the lab field's changes.

Two paths, each period (``period_s``):

* **feed-forward from the outside reference** (``[cage] ambient``, outside the coils): its change
  since the start is the lab field's change, applied with the opposite sign at once (a distant
  source changes the field alike there and here);
* **integral feedback from the inner reference** (beside the DUT): what the feed-forward misses
  (a near source, a vehicle in the street, changes the field differently 8 m away) is integrated
  out with a time constant of ``period_s / feedback_gain``.

The correction goes to the trim windings (``[cage] trim``, a few turns per axis on the coils'
frames with their own supplies, ``trim_ut_per_a``): at 2 uT/A a supply's 0.1 mA step is 0.2 nT,
where the main coils' is 4 nT. The trims run about a bias (``bias_a``, half their range either
way); the main coils take the bias out at the start. The coils' own far field at the outside
reference does not enter: the main currents hold still while the servo runs, and the trims' far
field is 20 times smaller still.

What the inner reference would have read without the servo is measured in the same run: its
reading less the field the trims applied (``trim_ut_per_a`` times their change). Both are
reported as the rms of ``report_s`` means against the target (a reference's white noise averages
out over them; the servo's quantity is the slow field).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

import timebase
from rig.errors import RigError

Array = npt.NDArray[np.float64]


class Trim(Protocol):
    """A trim winding's supply (a load channel's interface)."""

    @property
    def max_current_a(self) -> float: ...
    def set_current(self, amps: float) -> float: ...


class Sensor(Protocol):
    """A streaming magnetometer: whatever arrived since the last call (raw uT, its own frame)."""

    def read_samples(self, max_wait_s: float) -> list[tuple[float, float, float]]: ...


@dataclass
class ServoRecord:
    """Per period: time (s since the start), the inner reference's mean (uT, cage frame), the
    outside reference's change (uT) and the field the trims applied (uT)."""

    t_s: list[float] = field(default_factory=list)
    inner_ut: list[Array] = field(default_factory=list)
    outside_change_ut: list[Array] = field(default_factory=list)
    applied_ut: list[Array] = field(default_factory=list)
    saturated: int = 0

    def rms_nt(self, target_ut: Array, report_s: float, servoed: bool = True) -> Array:
        """Per axis, the rms of ``report_s`` means of the inner field (servoed) or of the field
        without the servo (inner less applied) about ``target_ut`` (nT)."""
        t = np.asarray(self.t_s)
        inner = np.asarray(self.inner_ut)
        field_ut = inner if servoed else inner - np.asarray(self.applied_ut)
        blocks = np.floor((t - t[0]) / report_s).astype(int)
        means = np.array([field_ut[blocks == b].mean(axis=0) for b in np.unique(blocks)
                          if np.sum(blocks == b) >= 2])  # fmt: skip
        if means.size == 0:
            raise RigError(f"the hold was shorter than one {report_s:g} s block: hold longer")
        return np.asarray(1000.0 * np.sqrt(np.mean((means - target_ut) ** 2, axis=0)))


@dataclass(frozen=True)
class ServoSettings:
    """Period of the loop (s), feedback gain per period (0-1), the trims' bias (A) and field per
    ampere (uT/A per axis)."""

    trim_ut_per_a: tuple[float, float, float]
    period_s: float = 0.5
    feedback_gain: float = 0.25
    bias_a: float = 0.5


def _mean(sensor: Sensor, period_s: float) -> Array | None:
    rows = sensor.read_samples(period_s)
    return None if not rows else np.asarray(np.mean(np.asarray(rows, float), axis=0))


@dataclass
class AmbientServo:
    """The loop over an inner reference (``inner``, with ``to_cage``: raw uT -> cage frame), an
    outside one and the three trims; ``sleep`` is the session's (a fault ends the hold)."""

    inner: Sensor
    to_cage: Callable[[Array], Array]
    outside: Sensor
    trims: Sequence[Trim]
    settings: ServoSettings
    sleep: Callable[[float], None] = timebase.sleep
    clock: Callable[[], float] = timebase.monotonic
    record: ServoRecord = field(default_factory=ServoRecord)

    def hold(self, target_ut: Array, duration_s: float | None, stop: threading.Event,
             progress: Callable[[float], None] | None = None) -> ServoRecord:  # fmt: skip
        """Servo the field at the inner reference to ``target_ut`` for ``duration_s`` (None:
        until ``stop``); the trims are left at their bias (the caller's session takes them and
        the coils to the safe state)."""
        s = self.settings
        per_a = np.asarray(s.trim_ut_per_a, float)
        clock = self.clock
        baseline = self._first(self.outside, s.period_s)
        start = clock()
        integral = np.zeros(3)
        applied = np.zeros(3)
        periods = 0
        _mean(self.inner, 0.0)  # what piled up before the start
        while not stop.is_set() and (duration_s is None or clock() - start < duration_s):
            periods += 1
            self.sleep(max(0.0, start + periods * s.period_s - clock()))
            outside, inner = _mean(self.outside, s.period_s), _mean(self.inner, 0.0)
            if outside is None or inner is None:
                raise RigError("a reference stopped sending during the servo: check its cable")
            inner_ut = self.to_cage(inner)
            change = outside - baseline
            self.record.t_s.append(clock() - start)
            self.record.inner_ut.append(inner_ut)
            self.record.outside_change_ut.append(change)
            self.record.applied_ut.append(applied.copy())
            integral += s.feedback_gain * (np.asarray(target_ut) - inner_ut)
            applied = self._apply(integral - change, per_a)
            if progress is not None:
                progress(clock() - start)
        return self.record

    def _first(self, sensor: Sensor, period_s: float) -> Array:
        for _ in range(math.ceil(5.0 / period_s)):  # 5 s for its first readings
            self.sleep(period_s)
            mean = _mean(sensor, period_s)
            if mean is not None:
                return mean
        raise RigError("the outside reference sends nothing: check [cage] ambient and its cable")

    def _apply(self, correction_ut: Array, per_a: Array) -> Array:
        """Set the trims for ``correction_ut`` (uT about their bias); the field they apply."""
        s = self.settings
        if not self.trims:  # measuring only
            return np.zeros(3)
        amps = s.bias_a + correction_ut / per_a
        top = np.array([t.max_current_a for t in self.trims])
        clipped = np.clip(amps, 0.0, np.minimum(top, 2.0 * s.bias_a))
        if np.any(clipped != amps):
            self.record.saturated += 1
        set_a = np.array(
            [t.set_current(float(a)) for t, a in zip(self.trims, clipped, strict=True)]
        )
        return np.asarray((set_a - s.bias_a) * per_a)
