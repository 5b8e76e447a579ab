"""The flight software under test, in process: the reference B-dot detumbling law.

B-dot commands a dipole against the change of the measured field, ``m = -k dB/dt``, each rod
clipped to its largest dipole; the torque ``m x B`` then always takes rotational energy out.
``dB/dt`` is the difference of the mean readings of two successive control periods, so the
magnetometer's noise is averaged over a period before it is differenced (a period of samples at
20 Hz and 20 nT of noise: about 20 nT/s of noise on ``dB/dt`` against 520 nT/s of signal at
1 deg/s in 30 uT).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


class FlightSoftware(Protocol):
    """What the loop asks of the flight software: a dipole (A m^2, body frame) from the mean
    reading of the last control period (uT, body frame) dated ``t_s`` (s of the loop)."""

    def dipole(self, field_ut: Array, t_s: float) -> Array: ...


class BDot:
    """``m = -gain dB/dt``, each axis clipped to ``max_dipole_am2``; ``gain`` in A m^2 per
    uT/s. The first period only measures (no rate known yet)."""

    def __init__(self, gain_am2_per_ut_s: float, max_dipole_am2: float) -> None:
        self.gain = gain_am2_per_ut_s
        self.max_dipole = max_dipole_am2
        self._last: tuple[Array, float] | None = None

    def dipole(self, field_ut: Array, t_s: float) -> Array:
        last, self._last = self._last, (np.asarray(field_ut, float), t_s)
        if last is None or t_s <= last[1]:
            return np.zeros(3)
        rate_ut_s = (self._last[0] - last[0]) / (t_s - last[1])
        return np.asarray(np.clip(-self.gain * rate_ut_s, -self.max_dipole, self.max_dipole))


def default_gain(max_dipole_am2: float, field_ut: float = 30.0, rate_deg_s: float = 1.0) -> float:
    """A gain (A m^2 per uT/s) that reaches the rods' largest dipole when the field turns at
    ``rate_deg_s`` (deg/s) relative to the body in a field of ``field_ut`` (uT): full authority
    while tumbling, proportional as the rate falls."""
    return max_dipole_am2 / (math.radians(rate_deg_s) * field_ut)
