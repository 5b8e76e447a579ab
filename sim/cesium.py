"""A cesium total-field magnetometer behind a Geometrics CM-201 counter, on a serial line (a
pseudo-terminal, or a line of the simulated clock in simulated time: :mod:`sim.serial_line`).

As the maker's counter defines it (G-882/G-858 manuals, the counter's ASCII output): at the cycle
rate (default 10 Hz) one line per reading, ``$`` then ``1`` or a blank (above or below
99999.999 nT), the field in nT as five digits, a point and three digits, a comma, the Larmor
signal level as four digits (0-9999) and CR LF: ``$ 49895.131,1249``. Commands end with a CR:
``Cnnnn`` (or ``Cnnnnx``, ``x`` 0 or 5) sets the cycle time in 0.01 s units (``C0010``: 10 Hz);
anything else is answered ``ERR00:`` and the command echoed.

The physics: the total field where the sensor sits (coils and lab field, from the cage's physics)
plus the sensor's absolute offset and its heading error (``heading_error_nt`` times the cosine of
the angle between the field and the optical axis), plus white noise (``noise_ut``). A cesium cell
has no Larmor signal (signal level near 0) when the field lies within ``dead_zone_deg`` of its
optical axis or of the plane normal to it, or is outside 17-100 uT; the counter then sends
zeros for the field.
"""

from __future__ import annotations

import math
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

RANGE_UT = (17.0, 100.0)
"""The cesium sensor's operating range (G-882: 17,000 to 100,000 nT)."""
LOCKED_SIGNAL = 1250
"""The signal level with the Larmor resonance locked (the manual's example lines: 1214-1298)."""
NO_SIGNAL = 40
SUBSAMPLES = 20
"""The counter counts Larmor cycles over its whole cycle time: the field is averaged over that many
instants spread through it (so 50 Hz mains ripple averages out of a 0.1 s cycle, as it does)."""


def counter_line(total_nt: float, signal: int) -> bytes:
    """One reading as the counter sends it: ``$ 49895.131,1249`` and CR LF."""
    total_nt = min(max(total_nt, 0.0), 199999.999)
    high = "1" if total_nt > 99999.999 else " "
    digits = f"{total_nt % 100000.0:09.3f}"
    return f"${high}{digits},{min(max(signal, 0), 9999):04d}\r\n".encode("ascii")


class CesiumCounter:
    """The simulated sensor and counter: ``field_ut(t)`` is the true field vector (uT, cage frame)
    where the sensor sits at device time ``t`` (monotonic s)."""

    def __init__(self, field_ut: Callable[[float], np.ndarray], faults: Faults, *,
                 optical_axis: np.ndarray, offset_nt: float, heading_error_nt: float,
                 dead_zone_deg: float, noise_nt: float, baudrate: int, seed: int,
                 name: str = "cesium") -> None:  # fmt: skip
        self.field_ut = field_ut
        self.faults = faults
        self.axis = np.asarray(optical_axis, float) / np.linalg.norm(optical_axis)
        self.offset_nt, self.heading_error_nt = offset_nt, heading_error_nt
        self.dead_zone_deg, self.noise_nt = dead_zone_deg, noise_nt
        self.baudrate = baudrate
        self.cycle_s = 0.1
        self.line = open_line(name, baudrate)
        self._rng = random.Random(seed)
        self._noise = np.random.default_rng(seed)
        self._stop = timebase.Event()
        self._thread = timebase.Thread(self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """The serial port path a client opens (a pty, or ``simpipe://<name>``)."""
        return self.line.path

    def reading(self, t_s: float) -> tuple[float, int]:
        """The counter's field (nT) and signal level for the cycle ending at ``t_s``."""
        instants = t_s - self.cycle_s * (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES
        fields = np.array([self.field_ut(float(t)) for t in instants])
        b = fields.mean(axis=0)
        magnitude = float(np.mean(np.linalg.norm(fields, axis=1)))
        cos_axis = abs(float(b @ self.axis)) / max(magnitude, 1e-12)
        from_axis = math.degrees(math.acos(min(cos_axis, 1.0)))
        dead = from_axis < self.dead_zone_deg or from_axis > 90.0 - self.dead_zone_deg
        if dead or not RANGE_UT[0] <= magnitude <= RANGE_UT[1]:
            return 0.0, NO_SIGNAL + int(self._noise.integers(0, 20))
        heading = self.heading_error_nt * float(b @ self.axis) / magnitude
        total = 1e3 * magnitude + self.offset_nt + heading
        total += self.noise_nt * float(self._noise.standard_normal())
        return total, LOCKED_SIGNAL + int(self._noise.integers(-40, 40))

    def _run(self) -> None:
        next_t = timebase.monotonic()
        pending = b""
        while not self._stop.is_set():
            try:
                ready = self.line.wait_readable(max(0.0, next_t - timebase.monotonic()))
            except (OSError, ValueError):
                return
            if ready:
                pending = self._command(pending + self._read())
                continue
            sample_t = next_t
            next_t += self.cycle_s
            if self.faults.silent or self.faults.disconnect or not self.line.has_client:
                continue  # (nobody listening: no reading to make; simulated time runs faster)
            self._send(counter_line(*self.reading(sample_t)))

    def _read(self) -> bytes:
        data = self.line.read_available()
        if not data:
            self._stop.wait(0.01)
        return data

    def _command(self, data: bytes) -> bytes:
        """Act on every complete command in ``data``; return the incomplete rest."""
        while b"\r" in data:
            line, data = data.split(b"\r", 1)
            text = line.decode("ascii", errors="replace").strip()
            digits = text[1:]
            if text[:1] == "C" and digits.isdigit() and len(digits) in (4, 5) and int(digits[:4]):
                extra = 0.005 if len(digits) == 5 and digits[4] == "5" else 0.0
                self.cycle_s = int(digits[:4]) * 0.01 + extra
            elif text:
                self._send(f"ERR00:{text}\r\n".encode("ascii", errors="replace"))
        return data[-64:]

    def _send(self, line: bytes) -> None:
        send_paced(self.line, line, self.faults, self._rng, self.baudrate, self._stop)

    def close(self) -> None:
        """Stop sending and close the line."""
        self._stop.set()
        self._thread.join(timeout=10.0)  # it must not touch the line once it is closed
        self.line.close()


def _start(host: CageHost, m: MagnetometerConfig, index: int) -> dict[str, Any]:
    """A cesium sensor and CM-201 counter on a serial line (nT lines)."""
    physics = host.physics

    def field_ut(t_s: float) -> np.ndarray:
        return physics.field_at_ut(m.name, t_s)

    dev = CesiumCounter(field_ut, physics.magnetometers[m.name].faults,
                        optical_axis=np.array(m.optical_axis), offset_nt=m.scalar_offset_nt,
                        heading_error_nt=m.heading_error_nt, dead_zone_deg=m.dead_zone_deg,
                        noise_nt=1e3 * m.noise_ut, baudrate=m.endpoint.baudrate,
                        seed=host.cfg.seed + index, name=m.name)  # fmt: skip
    host.add_serial(m.name, dev)
    endpoint = {"kind": "geometrics-cm201", "protocol": "serial", "path": dev.path,
                "baudrate": m.endpoint.baudrate, "optical_axis": [float(v) for v in dev.axis]}  # fmt: skip
    return endpoint | ({"role": m.role} if m.role else {})


KIND = SimKind("geometrics-cm201", "magnetometers", _start)
