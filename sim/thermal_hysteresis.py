"""Thermal hysteresis: a magnetometer's offset on warming differs from its offset on cooling.

The offset follows the temperature through a play (backlash) operator of half-width ``band_k``:
its internal temperature ``p`` stays put while the sensor's temperature ``T`` is within
``band_k`` of it and is dragged along beyond, so ``s = (T - p) / band_k`` is +1 on a warming
branch, -1 on a cooling one and moves between them over ``2 band_k`` after each reversal. The
offset adds ``hysteresis_nt / 2 * s``: warming minus cooling at the same temperature is
``hysteresis_nt`` (per axis). A sensor at rest since switch-on is half-way (``s = 0``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


class ThermalHysteresis:
    """One sensor's thermal history (not thread-safe: its magnetometer's lock serializes it)."""

    def __init__(self, hysteresis_nt: tuple[float, ...], band_k: float) -> None:
        self.hysteresis_ut = 1e-3 * np.asarray(hysteresis_nt, float)
        self.band_k = band_k
        self._p: float | None = None  # the play operator's state (C)

    @property
    def active(self) -> bool:
        """The sensor has any hysteresis."""
        return bool(np.any(self.hysteresis_ut))

    def branch(self, temperature_c: float) -> float:
        """The sensor at ``temperature_c`` (C, in time order): -1 (cooling) to +1 (warming)."""
        if self._p is None:
            self._p = temperature_c
        if temperature_c > self._p + self.band_k:
            self._p = temperature_c - self.band_k
        elif temperature_c < self._p - self.band_k:
            self._p = temperature_c + self.band_k
        return (temperature_c - self._p) / self.band_k

    def offset_ut(self, temperature_c: float) -> Array:
        """The offset it adds at ``temperature_c`` (uT per axis), the history updated."""
        if not self.active:
            return np.zeros(3)
        return np.asarray(0.5 * self.hysteresis_ut * self.branch(temperature_c))
