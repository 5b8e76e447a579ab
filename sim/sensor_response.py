"""A magnetometer's response to a changing field: what it reads is not the field at the instant it
is dated but a filtered one.

Two stages, either of which may be absent: an integration over the conversion window of
``integration_s`` before the reading's date (a magneto-inductive sensor such as the RM3100 counts
oscillator cycles over its measurement time: a boxcar average), then a first-order low-pass of
time constant ``tau_s`` (an AMR bridge's or a fluxgate's analogue filter).

The filter runs on a uniform grid of ``step_s`` (the field evaluated once per grid point: the
window the mean of the last ``n`` points, the low-pass integrated exactly for its input linear
between points), so its cost is one field evaluation per step whatever the reading rate, and its
transfer function is exact (:meth:`SensorResponse.transfer`): the window's
``e^(-i pi f (n-1) h) sin(pi f n h) / (n sin(pi f h))``, the linear interpolation's
``sinc^2(f h)`` and the low-pass's ``1 / (1 + 2 pi i f tau)``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

STEP_S = 0.002
"""The grid the filter runs on (s): 500 Hz, ten points per cycle of 50 Hz mains ripple."""
RESTART_TAUS = 20.0
"""A reading more than this many time constants (plus the window) after the last starts the
grid that long before it (rather than stepping through the whole gap): the start is forgotten by
then (e^-20)."""


class SensorResponse:
    """One sensor's response (not thread-safe: its magnetometer's lock serializes it)."""

    def __init__(self, tau_s: float, integration_s: float, step_s: float = STEP_S) -> None:
        self.tau_s = tau_s
        self.integration_s = integration_s
        self.step_s = step_s
        self._n = max(1, round(integration_s / step_s)) if integration_s > 0 else 1
        self._window: deque[Array] = deque(maxlen=self._n)
        self._k: int | None = None  # the last grid point evaluated
        self._y = np.zeros(3)  # the low-pass output there
        self._x = np.zeros(3)  # its input (the window's mean) there

    @property
    def active(self) -> bool:
        """The sensor reads anything but the instantaneous field."""
        return self.tau_s > 0 or self.integration_s > 0

    def transfer(self, f_hz: float) -> complex:
        """Reading over field at frequency ``f_hz`` (a sine's amplitude ratio and phase lag)."""
        if not self.active:
            return complex(1.0)
        h, n = self.step_s, self._n
        out = complex(float(np.sinc(f_hz * h)) ** 2)
        if n > 1:
            phase = -math.pi * f_hz * (n - 1) * h
            out *= math.sin(math.pi * f_hz * n * h) / (n * math.sin(math.pi * f_hz * h))
            out *= complex(math.cos(phase), math.sin(phase))
        if self.tau_s > 0:
            out /= complex(1.0, 2 * math.pi * f_hz * self.tau_s)
        return out

    def reading(self, t_s: float, field_at: Callable[[float], Array]) -> Array:
        """What the sensor reads at ``t_s`` (s) of the field ``field_at(t)`` (uT)."""
        if not self.active:
            return np.asarray(field_at(t_s), float)
        k_now = math.floor(t_s / self.step_s)
        span = math.ceil((RESTART_TAUS * self.tau_s) / self.step_s) + self._n
        if self._k is None or k_now < self._k or k_now - self._k > span:
            # the grid starts again long enough before to have forgotten its start
            self._restart(k_now - span, field_at)
        while self._k is not None and self._k < k_now:
            self._advance(field_at)
        return self._between(t_s, field_at)

    def _between(self, t_s: float, field_at: Callable[[float], Array]) -> Array:
        """The output at ``t_s``, past the last grid point by a fraction of a step (the next
        point looked at, not kept)."""
        assert self._k is not None
        dt = t_s - self._k * self.step_s
        if dt <= 1e-12:
            return self._y.copy()
        ahead = [*list(self._window)[1:], np.asarray(field_at((self._k + 1) * self.step_s), float)]
        x_t = self._x + (np.mean(ahead, axis=0) - self._x) * (dt / self.step_s)
        return self._follow(self._y, self._x, x_t, dt)

    def _follow(self, y0: Array, x0: Array, x1: Array, dt: float) -> Array:
        """The low-pass ``dt`` on from output ``y0``, its input linear from ``x0`` to ``x1``."""
        if self.tau_s <= 0:
            return x1.copy()
        a = math.exp(-dt / self.tau_s)
        return a * y0 + (1 - a) * x0 + (x1 - x0) * (1 - self.tau_s / dt * (1 - a))

    def _restart(self, k: int, field_at: Callable[[float], Array]) -> None:
        """Settled on the field at grid point ``k`` (its window filled from the points before)."""
        self._window.clear()
        for j in range(k - self._n + 1, k + 1):
            self._window.append(np.asarray(field_at(j * self.step_s), float))
        self._x = np.mean(self._window, axis=0)
        self._y = self._x.copy()
        self._k = k

    def _advance(self, field_at: Callable[[float], Array]) -> None:
        """One grid step: the window slides, the low-pass follows its mean exactly."""
        assert self._k is not None
        self._k += 1
        self._window.append(np.asarray(field_at(self._k * self.step_s), float))
        x1 = np.mean(self._window, axis=0)
        self._y = self._follow(self._y, self._x, x1, self.step_s)
        self._x = x1
