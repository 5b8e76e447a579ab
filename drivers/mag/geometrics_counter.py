"""Geometrics CM-201 / CM-221 counter: a cesium total-field magnetometer's serial output.

The counter (behind the G-858, G-882 and similar cesium sensors) streams one ASCII line per
cycle: ``$``, ``1`` or a blank (above or below 99999.999 nT), five digits, a point, three digits
(nT), a comma, the Larmor signal level (four digits, 0-9999 for 0-5 V) and CR LF, e.g.
``$ 49895.131,1249``. Default 9600 Bd, 8N1, 10 Hz. ``Cnnnn`` + CR sets the cycle time in 0.01 s
units (``C00125`` adds 5 ms: 8 Hz). A reading whose signal level is below ``min_signal`` is not a
measurement: the cell has lost its resonance (the field in a dead zone of the sensor or outside
its range) and the counter's number means nothing.
"""

from __future__ import annotations

import re

from drivers.errors import DeviceProtocolError, DeviceRefusedError
from drivers.identity import Identity
from drivers.transport.serial_port import SerialPort

CYCLES_WAITED = 10
"""A reading is awaited for this many cycles (at least the port's timeout) before the counter
counts as silent."""
LINE = re.compile(rb"^\$([ 1])(\d{5}\.\d{3}),(\d{4})$")


def parse_line(line: bytes) -> tuple[float, int]:
    """One counter line to (field nT, signal level); DeviceProtocolError naming the line."""
    found = LINE.match(line.strip(b"\r\n"))
    if found is None:
        text = line.decode("ascii", errors="replace").strip()
        raise DeviceProtocolError(f"unreadable counter line {text[:40]!r}")
    high = 100000.0 if found[1] == b"1" else 0.0
    return high + float(found[2]), int(found[3])


class GeometricsCounter:
    """Total-field readings (nT) from a CM-201 counter on a serial line."""

    def __init__(self, url: str, *, baudrate: int = 9600, min_signal: int = 500,
                 timeout_s: float = 1.0, max_bad_lines: int = 3,
                 name: str = "geometrics-cm201") -> None:  # fmt: skip
        self.name = name
        self.port = SerialPort(url, baudrate, timeout_s=timeout_s, name=name)
        self.min_signal = min_signal
        self.max_bad_lines = max_bad_lines
        self.bad_lines = 0

    def identify(self) -> Identity:
        """The counter has no identity reply in its stream; one line proves the link."""
        self.read_line()
        return Identity("Geometrics CM-201 counter (cesium)", "", "")

    def set_cycle(self, rate_hz: float) -> float:
        """Set the cycle time nearest ``rate_hz`` (0.005 s steps, 0.01-99.99 s); the rate set."""
        hundredths = min(max(round(200.0 / rate_hz) / 2.0, 1.0), 9999.0)
        whole, half = int(hundredths), hundredths % 1.0 >= 0.5
        self.port.write(f"C{whole:04d}{'5' if half else ''}\r".encode("ascii"))
        cycle_s = (whole + (0.5 if half else 0.0)) / 100.0
        self.port.timeout_s = max(self.port.timeout_s, CYCLES_WAITED * cycle_s)
        return 1.0 / cycle_s

    def flush(self) -> None:
        """Drop buffered lines and the partial line in flight."""
        self.port.drain_input(quiet_s=0.0)
        self.port.read_until(b"\n")

    def read_line(self) -> tuple[float, int]:
        """The next readable line: (field nT, signal level), garbled lines skipped up to
        ``max_bad_lines`` in a row."""
        for _ in range(self.max_bad_lines + 1):
            line = self.port.read_until(b"\n")
            if line.startswith(b"ERR"):
                raise DeviceRefusedError(
                    f"{self.name} on {self.port.url}: the counter refused a command"
                    f" ({line.decode('ascii', errors='replace').strip()})"
                )
            try:
                return parse_line(line)
            except DeviceProtocolError:
                self.bad_lines += 1
        raise DeviceProtocolError(
            f"{self.name} on {self.port.url}: {self.max_bad_lines + 1} unreadable lines in a row;"
            " check the baud rate (the counter's default is 9600) and that it sends ASCII"
        )

    def read_total_nt(self) -> float | None:
        """The next reading (nT), or None when the sensor had no resonance (signal level below
        ``min_signal``: the field in its dead zone or outside its range)."""
        total, signal = self.read_line()
        return total if signal >= self.min_signal else None

    def close(self) -> None:
        """Close the port."""
        self.port.close()
