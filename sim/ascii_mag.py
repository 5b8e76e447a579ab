"""A configurable ASCII-line magnetometer on a serial line (reference sensor): a pseudo-terminal, or
a line of the simulated clock in simulated time (:mod:`sim.serial_line`).

Streams one line per sample, formatted by ``line_format`` (``{x} {y} {z}`` in uT, ``{t}`` the
device's seconds since start), at ``rate_hz``, paced at the baud rate like a real UART.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

import timebase
from sim.device_kind import CageHost, SimKind
from sim.physics import Faults
from sim.serial_line import open_line, send_paced

if TYPE_CHECKING:
    from sim.config import MagnetometerConfig


class AsciiMagnetometer:
    """Line-oriented magnetometer: ``x y z`` in uT, newline-terminated. ``read_ut(t_s)`` is the
    field (uT) at device time ``t_s`` (monotonic s): each line carries the field of its own sample
    time, also when our thread woke late and sends several lines back to back."""

    def __init__(self, read_ut: Callable[[float], np.ndarray], faults: Faults, *, rate_hz: float = 20.0,
                 baudrate: int = 115200, line_format: str = "{x:.4f} {y:.4f} {z:.4f}",
                 seed: int = 0, name: str = "ascii-mag") -> None:  # fmt: skip
        self.read_ut = read_ut
        self.faults = faults
        self.rate_hz = rate_hz
        self.baudrate = baudrate
        self.line_format = line_format
        self.line = open_line(name, baudrate)
        self._rng = random.Random(seed)
        self._stop = timebase.Event()
        self._t0 = timebase.monotonic()
        self._thread = timebase.Thread(self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """The serial port path a client opens (a pty, or ``simpipe://<name>``)."""
        return self.line.path

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = timebase.monotonic()
        while not self._stop.wait(max(0.0, next_t - timebase.monotonic())):
            sample_t = next_t  # the sensor samples on its own clock, however late we are
            next_t += period
            if self.faults.silent or self.faults.disconnect or not self.line.has_client:
                continue  # (nobody listening: no reading to make; simulated time runs faster)
            x, y, z = (float(v) for v in self.read_ut(sample_t))
            line = self.line_format.format(x=x, y=y, z=z, t=sample_t - self._t0) + "\n"
            send_paced(self.line, line.encode("ascii"), self.faults, self._rng, self.baudrate,
                       self._stop)  # fmt: skip

    def close(self) -> None:
        """Stop streaming and close the line."""
        self._stop.set()
        self._thread.join(timeout=10.0)  # it must not touch the line once it is closed
        self.line.close()


def _start(host: CageHost, m: MagnetometerConfig, index: int) -> dict[str, Any]:
    """An ASCII-line magnetometer on a serial line (uT, ``line_format``)."""
    dev = AsciiMagnetometer(host.field_reader(m.name), host.physics.magnetometers[m.name].faults,
                            rate_hz=m.rate_hz, baudrate=m.endpoint.baudrate,
                            line_format=m.line_format, seed=host.cfg.seed + index,
                            name=m.name)  # fmt: skip
    host.add_serial(m.name, dev)
    endpoint = {"kind": "ascii-mag", "protocol": "serial", "path": dev.path,
                "baudrate": m.endpoint.baudrate, "line_format": m.line_format, "unit": "uT"}  # fmt: skip
    return endpoint | ({"role": m.role} if m.role else {})


KIND = SimKind("ascii-mag", "magnetometers", _start)
