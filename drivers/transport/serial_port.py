"""A serial port opened by pyserial URL (device path, ``socket://``, ``rfc2217://``, ``loop://``)."""

from __future__ import annotations

import time

import serial

from drivers.errors import DeviceNotFoundError, DeviceTimeoutError


class SerialPort:
    """Byte-level access with timeouts that raise :class:`DeviceTimeoutError` naming the port."""

    def __init__(
        self, url: str, baudrate: int, *, timeout_s: float = 0.5, name: str = "serial"
    ) -> None:
        self.url = url
        self.name = name
        self.timeout_s = timeout_s
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceNotFoundError(
                f"{name}: cannot open {url}: {exc}; check the cable and the port name"
            ) from None

    @property
    def baudrate(self) -> int:
        """Current line speed."""
        return int(self._port.baudrate)

    @baudrate.setter
    def baudrate(self, value: int) -> None:
        self._port.baudrate = value

    def write(self, data: bytes) -> None:
        """Send bytes."""
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFoundError(
                f"{self.name} on {self.url}: write failed ({exc}); is it still connected?"
            ) from None

    def read_exact(self, n: int, timeout_s: float | None = None) -> bytes:
        """Exactly ``n`` bytes or :class:`DeviceTimeoutError`."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        buf = bytearray()
        while len(buf) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self._port.timeout = remaining
            try:
                chunk = self._port.read(n - len(buf))
            except (serial.SerialException, OSError) as exc:
                raise DeviceNotFoundError(
                    f"{self.name} on {self.url}: read failed ({exc}); is it still connected?"
                ) from None
            buf += chunk
        if len(buf) < n:
            raise DeviceTimeoutError(
                f"{self.name} on {self.url}: got {len(buf)} of {n} bytes within"
                f" {self.timeout_s if timeout_s is None else timeout_s:g} s; check power, cable and baud rate"
            )
        return bytes(buf)

    def read_until(
        self, terminator: bytes = b"\r", max_bytes: int = 256, timeout_s: float | None = None
    ) -> bytes:
        """Bytes up to and including ``terminator`` or :class:`DeviceTimeoutError`."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        buf = bytearray()
        while not buf.endswith(terminator) and len(buf) < max_bytes:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeoutError(
                    f"{self.name} on {self.url}: no complete reply (got {bytes(buf)!r});"
                    " check power, cable and baud rate"
                )
            self._port.timeout = remaining
            try:
                buf += self._port.read(1)
            except (serial.SerialException, OSError) as exc:
                raise DeviceNotFoundError(
                    f"{self.name} on {self.url}: read failed ({exc})"
                ) from None
        return bytes(buf)

    def in_waiting(self) -> int:
        """Bytes already received."""
        return int(self._port.in_waiting)

    def read_available(self) -> bytes:
        """Whatever has arrived, without waiting."""
        n = self._port.in_waiting
        return bytes(self._port.read(n)) if n else b""

    def drain_input(self, quiet_s: float = 0.05) -> None:
        """Discard input until the line has been quiet for ``quiet_s``."""
        self._port.timeout = quiet_s
        while self._port.read(4096):
            pass

    def close(self) -> None:
        """Close the port."""
        self._port.close()
