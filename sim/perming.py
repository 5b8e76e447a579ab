"""Perming: what a strong field leaves in a magnetometer's offset, and the set/reset that clears it.

A field at the sensor beyond ``threshold_ut`` (its magnitude, sensor axes) re-magnetizes it: the
offset moves by ``nt_per_ut`` per uT beyond the threshold, along that field, and stays after the
field is gone. A stronger exposure replaces a weaker one's shift; a weaker one leaves it. A
set/reset pulse (an AMR sensor's: the HMR2300's ``]S``/``]R``, and before every reading when its
automatic set/reset is on) restores the sensor's own offset. So a 2 nT shift needs a field
``2 / nt_per_ut`` uT beyond the threshold.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

import timebase

Array = npt.NDArray[np.float64]


class Perming:
    """One sensor's perming state (thread-safe: the device's thread reads, its commands reset)."""

    def __init__(self, threshold_ut: float, nt_per_ut: float) -> None:
        self.threshold_ut = threshold_ut
        self.nt_per_ut = nt_per_ut
        self._excess_ut = 0.0  # the strongest exposure since the last reset, beyond the threshold
        self._shift_ut = np.zeros(3)
        self._lock = timebase.Lock()
        self.auto_reset = False
        """Set/reset pulses before every reading (the HMR2300's S/R mode): no shift stays."""

    @property
    def active(self) -> bool:
        """The sensor perms at all (and its automatic set/reset is off)."""
        return self.nt_per_ut > 0.0 and not self.auto_reset

    def expose(self, u_ut: Array) -> None:
        """The sensor sees field ``u_ut`` (uT, sensor axes)."""
        if not self.active:
            return
        size = float(np.linalg.norm(u_ut))
        excess = size - self.threshold_ut
        with self._lock:
            if excess > self._excess_ut:
                self._excess_ut = excess
                self._shift_ut = 1e-3 * self.nt_per_ut * excess * np.asarray(u_ut, float) / size

    @property
    def shift_ut(self) -> Array:
        """The offset the exposures left (uT, sensor axes)."""
        if self.auto_reset:
            return np.zeros(3)
        with self._lock:
            return self._shift_ut.copy()

    def set_auto_reset(self, on: bool) -> None:
        """Automatic set/reset on or off; turning it on is a pulse as well."""
        self.auto_reset = on
        if on:
            self.reset()

    def reset(self) -> None:
        """A set/reset pulse: the shift is gone."""
        with self._lock:
            self._excess_ut = 0.0
            self._shift_ut = np.zeros(3)
