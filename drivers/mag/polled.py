"""Sampling for magnetometers that measure when asked (I2C sensors): the caller paces the reads."""

from __future__ import annotations


class PolledSampling:
    """The Magnetometer protocol's sampling methods for a driver with ``read(timeout_s)``."""

    self_timed = False
    """Polled: the caller paces :meth:`read_samples`."""

    def read(self, timeout_s: float = 0.1) -> tuple[float, float, float]:
        """One fresh measurement (uT); the driver's own."""
        raise NotImplementedError

    def start_sampling(self, rate_hz: float) -> float:
        """Polled measurements: nothing to configure; the caller reads at ``rate_hz``."""
        return rate_hz

    def read_samples(self, max_wait_s: float) -> list[tuple[float, float, float]]:
        """One fresh measurement (uT)."""
        return [self.read(max_wait_s)]

    def stop_sampling(self) -> None:
        """Nothing to stop."""
