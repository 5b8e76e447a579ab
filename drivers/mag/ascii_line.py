"""A configurable line-oriented magnetometer: one sample per text line.

Covers space-separated Arduino bridges (``x y z`` in uT at 115200) and CSV loggers
(``Timestamp_ms,B1x_nT,B1y_nT,B1z_nT,...``): a delimiter (None = whitespace), the three column
indices, a scale to uT, an optional poll command and lines to skip (headers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.errors import DeviceProtocolError, DeviceTimeoutError
from drivers.identity import Identity
from drivers.transport.serial_port import SerialPort


@dataclass(frozen=True)
class LineFormat:
    """How to read a line: ``columns`` are the x, y, z indices; ``scale_to_ut`` multiplies them."""

    delimiter: str | None = None
    columns: tuple[int, int, int] = (0, 1, 2)
    scale_to_ut: float = 1.0
    terminator: bytes = b"\n"
    poll_command: bytes = b""

    def parse(self, line: bytes) -> tuple[float, float, float]:
        """One line to (x, y, z) uT, or DeviceProtocolError naming the line."""
        text = line.decode("ascii", errors="replace").strip()
        cells = text.split(self.delimiter) if self.delimiter else text.split()
        try:
            x, y, z = (float(cells[i]) * self.scale_to_ut for i in self.columns)
        except (IndexError, ValueError):
            raise DeviceProtocolError(f"unreadable magnetometer line {text[:60]!r}") from None
        if not all(math.isfinite(v) for v in (x, y, z)):
            raise DeviceProtocolError(f"non-finite value in magnetometer line {text[:60]!r}")
        return x, y, z


class AsciiLineMagnetometer:
    """Reads samples from a serial line; skips garbled lines up to ``max_bad_lines`` in a row."""

    def __init__(self, url: str, *, baudrate: int = 115200, fmt: LineFormat | None = None,
                 timeout_s: float = 0.5, max_bad_lines: int = 3, name: str = "ascii-mag") -> None:  # fmt: skip
        self.name = name
        self.fmt = fmt or LineFormat()
        self.port = SerialPort(url, baudrate, timeout_s=timeout_s, name=name)
        self.max_bad_lines = max_bad_lines
        self.bad_lines = 0
        self.lost_before: tuple[int, ...] = ()
        """Per line of the last :meth:`read_burst`: unreadable lines just before it (empty: none)."""

    def identify(self) -> Identity:
        """Line sensors have no identity query; reads one sample to prove the link."""
        self.read()
        return Identity("ASCII line magnetometer", "", "")

    def flush(self) -> None:
        """Drop buffered (stale) lines and the partial line in flight, so the next read is a
        complete line measured after this call."""
        self.port.drain_input(quiet_s=0.0)
        self.port.read_until(self.fmt.terminator)

    def read(self) -> tuple[float, float, float]:
        """The next complete line as uT."""
        return self._next()[1]

    def _next(self) -> tuple[int, tuple[float, float, float]]:
        """(lines lost before it, the next readable line as uT)."""
        if self.fmt.poll_command:
            self.port.write(self.fmt.poll_command)
        lost, self._carry = self._carry, 0
        for _ in range(self.max_bad_lines + 1):
            line = self.port.read_until(self.fmt.terminator)
            try:
                value = self.fmt.parse(line)
            except DeviceProtocolError:
                self.bad_lines += 1
                lost += self._lines_in(line)
                continue
            self._line_bytes = len(line)
            return lost, value
        raise DeviceProtocolError(
            f"{self.name} on {self.port.url}: {self.max_bad_lines + 1} unreadable lines in a row;"
            " check the baud rate and the line format"
        )

    def _lines_in(self, garbled: bytes) -> int:
        """How many of the sensor's lines an unreadable one stands for: one, or as many as its
        length holds (a line whose terminator was lost runs into the next)."""
        if not self._line_bytes:
            return 1
        return max(1, round(len(garbled) / self._line_bytes))

    def read_burst(self) -> list[tuple[float, float, float]]:
        """The next line and every further complete line already received, oldest first (uT);
        :attr:`lost_before` says how many lines were unreadable before each.

        A streaming sensor keeps sending while the reader is busy; the lines that piled up are
        older than the moment they are read, and the caller can date them by the sensor's rate.
        """
        out = [self._next()]
        if not self.fmt.poll_command:
            lost = 0
            while self.port.has_complete(self.fmt.terminator):
                line = self.port.read_until(self.fmt.terminator)
                try:
                    out.append((lost, self.fmt.parse(line)))
                    lost = 0
                except DeviceProtocolError:
                    self.bad_lines += 1
                    lost += self._lines_in(line)
            self._carry = lost  # unreadable lines at the burst's end precede the next burst
        gaps = tuple(k for k, _ in out)
        self.lost_before = gaps if any(gaps) else ()
        return [xyz for _, xyz in out]

    _line_bytes = 0
    _carry = 0

    @property
    def frame_line_s(self) -> float:
        """How long the last line took on the wire (s): 10 bits a byte at the port's speed. A
        streamed line arrives this long after the sensor sent it (the sampler dates it so)."""
        return self._line_bytes * 10.0 / self.port.baudrate

    @property
    def self_timed(self) -> bool:
        """A streaming sensor sends at its own rate; one with a poll command answers each poll."""
        return not self.fmt.poll_command

    def start_sampling(self, rate_hz: float) -> float:
        """Nothing to configure: the sensor's rate is set on the sensor (``rate_hz`` in the rig
        configuration says what it is)."""
        return rate_hz

    def read_samples(self, max_wait_s: float) -> list[tuple[float, float, float]]:
        """The lines received so far (:meth:`read_burst`; the port's timeout bounds the wait)."""
        return self.read_burst()

    def stop_sampling(self) -> None:
        """Nothing to stop."""

    def close(self) -> None:
        """Close the port."""
        self.port.close()


__all__ = ["AsciiLineMagnetometer", "DeviceTimeoutError", "LineFormat"]
